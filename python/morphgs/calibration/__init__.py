"""Calibration: perturbation strength matched to real (e.g. sparse-view) artifacts
(`morphgs calibrate`, docs/calibration.md).

- `stats`: per-pair statistics (PSNR, SSIM, LPIPS, error spectrum, colour shift, coverage,
  temporal error);
- `search`: the per-family strength search (log-grid scan with common random numbers,
  monotonicity check, bisection, quantile matching, reachability, op shares);
- `fit`: goodness of fit (per-statistic distances, two-sample classifier AUC, real-vs-real floor);
- `run`: the command's pipeline (real pairs, synthetic pairs, outputs).
"""
