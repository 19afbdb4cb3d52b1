"""Stage 6, 2D metrics: per refined clip against its clean clip, PSNR, SSIM, LPIPS and E_flow
(morphgs.metrics, the same functions as `morphgs eval`). LPIPS is None (n/a in the table) when
its weights are absent or the study turns it off; the reason is kept in `metrics2d.json`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["IGNORE", "RESUMABLE", "VERSION", "lpips_status", "make"]

VERSION = 1
IGNORE = ("threads",)
RESUMABLE = False


def lpips_status(setting: str, net: str) -> str | None:
    """None when LPIPS can run, else why not (the report prints it). Cheap: it looks for torch and
    the weight files without loading them (a plan, a dry run, reads it too)."""
    import importlib.util

    if setting == "off":
        return "LPIPS turned off in the study ([metrics] lpips = \"off\")"
    if importlib.util.find_spec("torch") is None:
        return "LPIPS needs torch (pip install 'morphgs[metrics]')"
    from morphgs.metrics.perceptual import lpips_weights_file

    try:
        lpips_weights_file(net)
    except Exception as e:  # noqa: BLE001 - any failure to find the weights means n/a, with its reason
        return f"LPIPS weights not available ({type(e).__name__}: {e})"
    return None


def make(work: Path, *, testset_dir: str, refined_dir: str, lpips_note: str | None, lpips_net: str, eflow: bool,
         threads: int) -> None:
    """Score every refined clip against its clean clip into `work/metrics2d.json` (LPIPS n/a
    with `lpips_note` as the reason when that is set)."""
    from morphgs import media
    from morphgs import metrics as M
    from morphgs.ablation.stages.common import read_testset, torch_threads

    torch_threads(threads)
    ts, rd = Path(testset_dir), Path(refined_dir)
    meta = read_testset(ts)
    why = lpips_note
    rows: dict[str, dict[str, Any]] = {}
    for j in meta["clips"]:
        gt = media.read_clip(ts / "clips" / j / "clean")
        pred = media.read_clip(rd / "clips" / j / "frames")
        rows[j] = {
            "psnr2d": float(M.psnr(pred, gt)),
            "ssim2d": float(M.ssim(pred, gt)),
            "lpips2d": None if why else float(M.lpips(pred, gt, net=lpips_net)),
            "eflow": float(M.flow_epe(pred, gt)) if eflow else None,
        }
    (work / "metrics2d.json").write_text(json.dumps({"clips": rows, "lpips_note": why}, indent=1, sort_keys=True)
                                         + "\n", encoding="utf-8")
