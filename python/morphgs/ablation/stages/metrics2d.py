"""Stage 6, 2D metrics: per refined clip against its clean clip, PSNR, SSIM, LPIPS and E_flow
(morphgs.metrics, the same functions as `morphgs eval`). LPIPS is None (n/a in the table) when
its weights are absent or the study turns it off; the reason is kept in `metrics2d.json`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["lpips_status", "make"]


def lpips_status(setting: str, net: str) -> str | None:
    """None when LPIPS can run, else why not (the report prints it)."""
    if setting == "off":
        return "LPIPS turned off in the study ([metrics] lpips = \"off\")"
    try:
        from morphgs.metrics import lpips_model

        lpips_model(net)
    except Exception as e:  # noqa: BLE001 - any failure to load the weights means n/a, with its reason
        return f"LPIPS weights not available ({type(e).__name__}: {e})"
    return None


def make(work: Path, *, testset_dir: str, refined_dir: str, lpips: str, lpips_net: str, eflow: bool,
         threads: int) -> None:
    import torch

    from morphgs import media
    from morphgs import metrics as M

    if threads:
        torch.set_num_threads(threads)
    ts, rd = Path(testset_dir), Path(refined_dir)
    meta = json.loads((ts / "testset.json").read_text(encoding="utf-8"))
    why = lpips_status(lpips, lpips_net)
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
