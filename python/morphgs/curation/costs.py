"""What a pair's corrupted side costs, from its manifest record (docs/curation.md, "Cost per pair").

Every record's `timings` holds `corrupted`, the seconds of making this pair's corrupted side
apart from any fit (perturbing the scene, or loading its cached fit, plus half the render pass,
which renders the clean and the corrupted scene at once), and `fit`, the wall seconds of the
whole fit its corrupted scene comes from (null for perturbation configs, or for a fit made
before costs were kept). A fit is shared by several pairs, and how many is known only once they
are all made, so the share is computed here, when reporting:

    cost(pair) = corrupted + fit / (pairs among `records` whose corrupted scene is that fit)

(the fit is told apart by its PLY, so an underfit run's stops are separate fits, each costing
the shared run's seconds up to its step).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from typing import Any

__all__ = ["pair_costs", "summarise"]


def _own(rec: Mapping[str, Any]) -> float | None:
    t = rec.get("timings") or {}
    if t.get("corrupted") is not None:
        return float(t["corrupted"])
    if rec.get("fit") is None and "perturb" in t and "render" in t:  # a record from before the field
        return float(t["perturb"]) + float(t["render"]) / 2
    return None


def pair_costs(records: Iterable[Mapping[str, Any]]) -> dict[str, float | None]:
    """pair id -> seconds of its corrupted side with its share of the fit (None when a record
    lacks what it takes: made before these fields were kept)."""
    recs = list(records)
    sharing = Counter(r["fit"]["ply"] for r in recs if r.get("fit"))
    out: dict[str, float | None] = {}
    for r in recs:
        own = _own(r)
        fit = r.get("fit")
        if fit:
            secs = (r.get("timings") or {}).get("fit", fit.get("seconds"))
            out[r["pair_id"]] = None if own is None or secs is None else own + float(secs) / sharing[fit["ply"]]
        else:
            out[r["pair_id"]] = own
    return out


def summarise(records: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """The cost of a set of pairs (one config's, say): `pairs`, `fits` (distinct), `fit_seconds`
    (their wall seconds, summed; None when one is unknown), `corrupted_seconds` (the mean of the
    pairs' own corrupted-side seconds), `seconds_per_pair` (the mean of `pair_costs`; None when
    one is unknown)."""
    recs = list(records)
    fits: dict[str, Any] = {}
    for r in recs:
        if r.get("fit"):
            fits[r["fit"]["ply"]] = (r.get("timings") or {}).get("fit", r["fit"].get("seconds"))
    costs = list(pair_costs(recs).values())
    own = [_own(r) for r in recs]

    def mean(v: list[float | None]) -> float | None:
        if not v or any(x is None for x in v):
            return None
        return round(sum(float(x) for x in v if x is not None) / len(v), 4)

    fit_total = None if any(v is None for v in fits.values()) else round(sum(float(v) for v in fits.values()), 3)
    return {"pairs": len(recs), "fits": len(fits), "fit_seconds": fit_total, "corrupted_seconds": mean(own),
            "seconds_per_pair": mean(costs)}
