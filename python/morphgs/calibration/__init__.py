"""Calibration: perturbation strength matched to real (e.g. sparse-view) artifacts
(`morphgs calibrate`, docs/calibration.md).

- `stats`: per-pair statistics (PSNR, SSIM, LPIPS, error spectrum, colour shift, coverage,
  temporal error);
- `pairs`: real pairs read from a curated folder, and their synthetic counterparts (`Bench`);
- `search`: the per-family strength search (log-grid scan with common random numbers,
  monotonicity check, bisection, quantile matching, reachability);
- `mix`: the op-mix search's candidates and distances;
- `goodness`: goodness of fit (per-statistic distances, two-sample classifier AUC, real-vs-real floor);
- `pipeline`: `calibrate_pairs`, the calibration of loaded pairs and scenes (plain data, writes nothing);
- `outputs`, `report`: calibration.json, the configs, report.md and its plots;
- `run`: the command (`calibrate`: real pairs made or read, scenes found, outputs and timings written).
"""
