"""One writer per output folder: an exclusive `flock` on a lock file, naming its holder.

The lock file (`OUT/.morphgs.lock`, or `.OUT.morphgs.lock` beside OUT for commands that replace
OUT by a rename) holds the holder's pid, host, start time and command line while it is held and
is emptied on a clean release. The kernel drops an `flock` when its process dies, however it
dies (SIGKILL included), so a lock left by a dead process is simply taken over; the stale holder
it names is reported.

A second process either gets a `FolderBusyError` at once, naming the holder, or (`wait=True`,
the commands' `--wait`) waits for the folder to be free.

Shards of one logical run (`curate --shard-index/--num-shards`) share the folder: each holds the
folder lock *shared* and its own shard lock exclusively, so shards run side by side while two
processes of one shard, or an unsharded run beside shards, are refused.

Forked children (DataLoader workers) close their copies of the lock's descriptors at once, so
the lock dies with the process that took it, not with its last child.

Filesystems without `flock` (some network mounts) get a warning and no protection.
"""

from __future__ import annotations

import errno
import fcntl
import functools
import inspect
import json
import os
import socket
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from morphgs._core import MorphgsError, MorphgsWarning

_F = TypeVar("_F", bound=Callable[..., Any])

__all__ = ["LOCK_PREFIX", "FolderBusyError", "FolderLock", "Holder", "add_wait_argument", "folder_lock",
           "is_lock_file", "locks_folder"]

LOCK_PREFIX = ".morphgs"
_MAIN = f"{LOCK_PREFIX}.lock"


# descriptors of the locks this process holds; a forked child closes its copies (see below)
_HELD: set[int] = set()
# unsharded locks this process holds, by lock file: taking one again nests (no second flock)
_OWNED: dict[str, int] = {}


def _close_in_child() -> None:
    for fd in list(_HELD):
        try:
            os.close(fd)
        except OSError:
            pass
    _HELD.clear()
    _OWNED.clear()


os.register_at_fork(after_in_child=_close_in_child)


class FolderBusyError(MorphgsError):
    """Another process is writing the folder (the message names it: pid, host, start time)."""


def is_lock_file(name: str) -> bool:
    """Whether a file name is one of the lock files (emptiness checks of output folders skip them)."""
    return name.startswith(LOCK_PREFIX) and name.endswith(".lock")


@dataclass(frozen=True)
class Holder:
    """Who holds (or last held) a lock."""

    pid: int
    host: str
    started: str
    command: str

    def describe(self) -> str:
        return f"pid {self.pid} on {self.host}, started {self.started}: {self.command}"


def _read_holder(fd: int) -> Holder | None:
    try:
        raw = os.pread(fd, 65536, 0)
        d = json.loads(raw.decode("utf-8")) if raw.strip() else None
        if not isinstance(d, dict):
            return None
        return Holder(int(d["pid"]), str(d["host"]), str(d["started"]), str(d.get("command", "")))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _holder_of(path: Path) -> Holder | None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        return _read_holder(fd)
    finally:
        os.close(fd)


def _is_held(path: Path) -> bool:
    """Whether some process holds `path` exclusively (probed with a shared non-blocking lock)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class FolderLock:
    """The lock of one output folder (use `folder_lock`, or `acquire`/`release`).

    Args:
        folder: the output folder (created when missing, unless `beside`).
        command: the command name, recorded for the message a second process shows.
        shard: (index, count) of a sharded writer, or None (one writer).
        wait: wait for the folder instead of raising `FolderBusyError`.
        beside: keep the lock file beside the folder (`.NAME.morphgs.lock`), for commands that
            replace the folder itself by a rename (export).
        poll: seconds between attempts while waiting. say: where notes go (stderr).
    """

    def __init__(self, folder: str | os.PathLike[str], *, command: str, shard: tuple[int, int] | None = None,
                 wait: bool = False, beside: bool = False, poll: float = 0.2,
                 say: Callable[[str], None] | None = None) -> None:
        self.folder = Path(folder)
        self.command = command
        self.shard = shard if shard is not None and shard[1] > 1 else None
        self.wait, self.beside, self.poll = bool(wait), bool(beside), float(poll)
        self.say = say or _stderr
        self._fds: list[int] = []
        self._info_fd: int | None = None
        self._pid = os.getpid()
        self._nested: str | None = None

    # -- paths --
    def _dir(self) -> Path:
        return self.folder.parent if self.beside else self.folder

    def main_path(self) -> Path:
        return self.folder.parent / f".{self.folder.name}{_MAIN}" if self.beside else self.folder / _MAIN

    def shard_path(self, index: int, count: int) -> Path:
        return self._dir() / f"{LOCK_PREFIX}-shard{index:03d}-of{count:03d}.lock"

    # -- taking and releasing --
    def acquire(self) -> FolderLock:
        self._pid = os.getpid()
        self._dir().mkdir(parents=True, exist_ok=True)
        main = self.main_path()
        key = str(main.resolve())
        if self.shard is None and key in _OWNED:  # this process holds it already: nest
            _OWNED[key] += 1
            self._nested = key
            return self
        try:
            if self.shard is None:
                self._info_fd = self._take(main, exclusive=True)
            else:
                self._take(main, exclusive=False)
                self._info_fd = self._take(self.shard_path(*self.shard), exclusive=True)
        except BaseException:
            self.release()
            raise
        if self._info_fd is not None:
            self._claim(self._info_fd)
        if self.shard is None:
            _OWNED[key] = 1
        return self

    def release(self) -> None:
        """Empty the holder record (a clean exit leaves no stale note) and drop the locks."""
        if os.getpid() != self._pid:  # a forked child: its copies are closed already
            self._fds.clear()
            self._info_fd = None
            return
        if self._nested is not None:
            _OWNED[self._nested] -= 1
            self._nested = None
            return
        if self.shard is None and self._fds:
            _OWNED.pop(str(self.main_path().resolve()), None)
        if self._info_fd is not None:
            try:
                os.ftruncate(self._info_fd, 0)
                if self.beside:  # leave nothing beside OUT (a waiting process re-opens: see _take)
                    os.unlink(self.main_path())
            except OSError:
                pass
            self._info_fd = None
        while self._fds:
            fd = self._fds.pop()
            _HELD.discard(fd)
            os.close(fd)

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def _take(self, path: Path, *, exclusive: bool) -> int | None:
        announced = False
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            self._fds.append(fd)
            _HELD.add(fd)
            try:
                if exclusive:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                else:
                    self._take_shared(fd)
                if self._same_file(fd, path):
                    return fd
                self._drop(fd)  # its holder removed the file on release: lock the new one
                continue
            except BlockingIOError:
                self._drop(fd)
            except OSError as e:
                if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                    warnings.warn(f"{path}: the filesystem does not support locks ({e.strerror}); nothing stops a "
                                  "second process writing the same folder", MorphgsWarning, stacklevel=3)
                    self._drop(fd)
                    return None
                raise
            busy = self.busy_message()
            if not self.wait:
                raise FolderBusyError(f"{busy}; wait for it to end, rerun with --wait, or choose another folder")
            if not announced:
                self.say(f"morphgs {self.command}: {busy}; waiting for it to end")
                announced = True
            time.sleep(self.poll)

    def _drop(self, fd: int) -> None:
        self._fds.remove(fd)
        _HELD.discard(fd)
        os.close(fd)

    @staticmethod
    def _same_file(fd: int, path: Path) -> bool:
        try:
            st = os.stat(path)
        except FileNotFoundError:
            return False
        return (st.st_ino, st.st_dev) == (os.fstat(fd).st_ino, os.fstat(fd).st_dev)

    def _take_shared(self, fd: int) -> None:
        """Shared lock of a shard on the folder; a stale unsharded holder's record is cleared first."""
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # other shards hold it shared: join them
            return
        self._note_stale(fd)
        os.ftruncate(fd, 0)
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)

    def _note_stale(self, fd: int) -> None:
        old = _read_holder(fd)
        if old is not None and (old.pid, old.host) != (os.getpid(), socket.gethostname()):
            self.say(f"morphgs {self.command}: took over the lock of {self.folder} left by a process that is "
                     f"gone ({old.describe()})")

    def _claim(self, fd: int) -> None:
        self._note_stale(fd)
        argv = " ".join(sys.argv) if sys.argv and sys.argv[0] else self.command
        info = {"pid": os.getpid(), "host": socket.gethostname(),
                "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "command": argv[:300],
                "folder": str(self.folder)}
        data = (json.dumps(info) + "\n").encode("utf-8")
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)

    def busy_message(self) -> str:
        """'FOLDER is being written by ...' naming every holder that can be found."""
        holders = []
        main = self.main_path()
        if _is_held(main):
            h = _holder_of(main)
            if h is not None:
                holders.append(h.describe())
        for p in sorted(self._dir().glob(f"{LOCK_PREFIX}-shard*.lock")):
            if _is_held(p):
                h = _holder_of(p)
                holders.append(f"{p.name[len(LOCK_PREFIX) + 1:-5]}: " + (h.describe() if h else "a process"))
        who = "; ".join(holders) if holders else "another process"
        return f"{self.folder} is being written by another morphgs process ({who})"


@contextmanager
def folder_lock(folder: str | os.PathLike[str], *, command: str, shard: tuple[int, int] | None = None,
                wait: bool = False, beside: bool = False, say: Callable[[str], None] | None = None
                ) -> Iterator[FolderLock]:
    """Hold the lock of an output folder for the `with` block (see `FolderLock`).

    Raises:
        FolderBusyError: another process writes the folder (and not `wait`).
    """
    lock = FolderLock(folder, command=command, shard=shard, wait=wait, beside=beside, say=say)
    with lock:
        yield lock


def add_wait_argument(parser: Any) -> None:
    """The `--wait` flag of a command that writes a folder."""
    parser.add_argument("--wait", action="store_true",
                        help="if another process is writing the output folder, wait for it instead of stopping")


def locks_folder(command: str, *, folder_arg: str = "out", beside: bool = False) -> Callable[[_F], _F]:
    """Decorate a function that writes the folder given as its `folder_arg` argument: it runs with
    the folder locked, and takes one more keyword, `wait` (see `FolderLock`)."""

    def deco(func: _F) -> _F:
        sig = inspect.signature(func)

        @functools.wraps(func)
        def wrapper(*args: Any, wait: bool = False, **kwargs: Any) -> Any:
            folder = sig.bind_partial(*args, **kwargs).arguments[folder_arg]
            with folder_lock(folder, command=command, wait=wait, beside=beside):
                return func(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return deco
