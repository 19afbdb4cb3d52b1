"""Shared reliability mechanisms of the commands that write a folder (docs/reliability.md):

- `folder_lock`: one writer per output folder (pid, host and start time of the holder; a lock
  left by a dead process is taken over; `wait=True` waits instead of refusing).
- `write_checksums` / `verify_checksums`: a checksum file written when a checkpoint or cache
  entry is saved, checked before it is used.
- `sigterm_raises` / `StopRequest`: SIGTERM (what clusters and Ray send before a kill) handled
  like Ctrl-C, either raised as `Preempted` or turned into a flag the loop checks between steps.
- `one_line`: the single line a CLI user sees for an exception (a DataLoader worker's wrapped
  traceback unwrapped to the message behind it).

A new command gets all of it with a few lines::

    from morphgs.reliability import folder_lock, sigterm_raises

    def register(sub):
        p = sub.add_parser("ablate", ...)
        add_wait_argument(p)                        # --wait

    def run(args):
        with folder_lock(args.out, command="ablate", wait=args.wait):
            ...   # SIGTERM arrives as Preempted (cli.main installs sigterm_raises), printed with
                  # the resume line of cli._RESUME

or, on the API function that writes the folder, `@locks_folder("ablate")` (adds `wait=`).
"""

from __future__ import annotations

from morphgs.reliability.checksums import ChecksumError, verify_checksums, write_checksums
from morphgs.reliability.errors import one_line, unwrap_worker_message
from morphgs.reliability.lock import LOCK_PREFIX, FolderBusyError, FolderLock, add_wait_argument, folder_lock, is_lock_file, \
    locks_folder
from morphgs.reliability.signals import Preempted, StopRequest, sigterm_raises, signals_held

__all__ = [
    "LOCK_PREFIX",
    "ChecksumError",
    "FolderBusyError",
    "FolderLock",
    "Preempted",
    "StopRequest",
    "add_wait_argument",
    "folder_lock",
    "is_lock_file",
    "locks_folder",
    "one_line",
    "sigterm_raises",
    "unwrap_worker_message",
    "verify_checksums",
    "write_checksums",
]
