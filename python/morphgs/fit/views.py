"""Which views train and which are held out (docs/fit.md, "View selection").

The held-out rule comes first: `holdout="every:8"` (the default, the Mip-NeRF 360 / DL3DV
benchmark split: view i is held out when i % 8 == 0), `"none"`, or an explicit list. The other
views, in order, are the *training trajectory*; the selection picks from it:

- `"all"`: every view of the trajectory;
- `"every:K"`: the paper's S_K, every K-th view of the trajectory starting with its first
  (trajectory[0::K], ceil(len / K) views);
- `"n:N"`: N views spread evenly over the trajectory, both ends included (round(linspace(0,
  len - 1, N)), 3DGS-Enhancer's 3/6/9-view protocol);
- an explicit list of view indices (of all views), e.g. `"0,12,24"` or `[0, 12, 24]`; those
  are then removed from the held-out set.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from morphgs._core import MorphgsError

__all__ = ["ViewSelection", "ViewSelectionError", "select_views"]


class ViewSelectionError(MorphgsError):
    """A view selection that is malformed or leaves no training view."""


@dataclass(frozen=True)
class ViewSelection:
    """Indices (into the dataset's views) of the training and the held-out views."""

    train: list[int]
    heldout: list[int]
    spec: str
    holdout: str


def _index_list(spec: str | Sequence[int], n: int, what: str) -> list[int]:
    if isinstance(spec, str):
        try:
            idx = [int(v) for v in spec.replace(" ", "").split(",") if v != ""]
        except ValueError:
            raise ViewSelectionError(f"{what} {spec!r}: expected all, every:K, n:N or a list like 0,8,16") from None
    else:
        idx = [int(v) for v in spec]
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        raise ViewSelectionError(f"{what}: view indices {bad} are out of range (the dataset has {n} views)")
    return sorted(set(idx))


def _count(spec: str, prefix: str, what: str) -> int:
    try:
        k = int(spec[len(prefix):])
    except ValueError:
        raise ViewSelectionError(f"{what} {spec!r}: {prefix}K needs an integer K") from None
    if k < 1:
        raise ViewSelectionError(f"{what} {spec!r}: {prefix}K needs K >= 1")
    return k


def select_views(n: int, views: str | Sequence[int] = "all", *, holdout: str | Sequence[int] = "every:8") -> ViewSelection:
    """Split `n` views into training and held-out views.

    Raises:
        ViewSelectionError: a malformed spec, or a selection that leaves no training view.
    """
    if isinstance(holdout, str) and holdout.startswith("every:"):
        k = _count(holdout, "every:", "holdout")
        held = [i for i in range(n) if i % k == 0] if k > 1 else []
        if k == 1:
            raise ViewSelectionError("holdout every:1 would hold out every view")
    elif isinstance(holdout, str) and holdout in ("none", ""):
        held = []
    else:
        held = _index_list(holdout, n, "holdout")
    traj = [i for i in range(n) if i not in set(held)]
    spec_text = views if isinstance(views, str) else ",".join(str(int(v)) for v in views)
    if isinstance(views, str) and views == "all":
        train = traj
    elif isinstance(views, str) and views.startswith("every:"):
        train = traj[::_count(views, "every:", "views")]
    elif isinstance(views, str) and views.startswith("n:"):
        k = _count(views, "n:", "views")
        if not traj:
            train = []
        else:
            train = sorted({traj[int(i)] for i in np.round(np.linspace(0, len(traj) - 1, k))})
    else:
        train = _index_list(views, n, "views")
        held = [i for i in held if i not in set(train)]
    if not train:
        raise ViewSelectionError(
            f"view selection {spec_text!r} leaves no training view ({n} views, {len(held)} held out "
            f"by holdout {holdout!r})")
    hold_text = holdout if isinstance(holdout, str) else ",".join(str(int(v)) for v in holdout)
    return ViewSelection(train, held, spec_text, hold_text)
