"""Training objectives and sampling loops of the two refiners.

- DDPM epsilon prediction (the sandbox): SD 1.5's scaled-linear betas (0.00085 -> 0.012 over 1000
  steps), built from explicit keyword arguments rather than a hub scheduler config.
- Flow matching (the Wan ControlNet): ``x_t = (1 - sigma) x_0 + sigma * noise``, target
  ``noise - x_0``, timestep ``1000 * sigma``; sigma drawn by `compute_density_for_timestep_sampling`
  ("uniform", "logit_normal" or "mode") and shifted as `FlowMatchEulerDiscreteScheduler` does:
  ``sigma = shift * s / (1 + (shift - 1) * s)``. A sigma range restricts training to one Wan2.2
  A14B expert.

Noise comes from the given `torch.Generator`, or the global torch RNG (which the training loop
checkpoints) when none is given.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = [
    "FLOW_SAMPLING",
    "SD15_DDPM",
    "FlowSettings",
    "ddim_scheduler",
    "ddpm_inputs",
    "ddpm_scheduler",
    "flow_inputs",
    "flow_loss_weights",
    "flow_sigmas",
    "sample_epsilon",
    "sample_flow",
    "shift_sigmas",
    "unshift_sigmas",
]

#: SD 1.5's training noise schedule (its scheduler_config.json), as explicit kwargs
SD15_DDPM: dict[str, Any] = {
    "num_train_timesteps": 1000,
    "beta_start": 0.00085,
    "beta_end": 0.012,
    "beta_schedule": "scaled_linear",
    "prediction_type": "epsilon",
    "clip_sample": False,
    "steps_offset": 1,
    "timestep_spacing": "leading",
}
FLOW_SAMPLING = ("uniform", "logit_normal", "mode")


def ddpm_scheduler(**overrides: Any) -> Any:
    """A `DDPMScheduler` with SD 1.5's schedule (keyword arguments override single entries)."""
    from diffusers import DDPMScheduler

    return DDPMScheduler(**{**SD15_DDPM, **overrides})


def ddim_scheduler(train_scheduler: Any) -> Any:
    """A `DDIMScheduler` over the same betas as a training scheduler (for N-step sampling)."""
    from diffusers import DDIMScheduler

    return DDIMScheduler.from_config(train_scheduler.config, set_alpha_to_one=False)


def _randn(like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    if generator is None:
        return torch.randn(like.shape, dtype=torch.float32, device=like.device)
    return torch.randn(like.shape, dtype=torch.float32, generator=generator, device=generator.device).to(like.device)


def ddpm_inputs(scheduler: Any, latents: torch.Tensor, *,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Noise clean latents at uniformly drawn timesteps (one per sample).

    Args:
        scheduler: a `DDPMScheduler`.
        latents: clean (scaled) latents, any shape (B, ...), float32.
        generator: random source, or None for the global torch RNG.

    Returns:
        ``(noisy, target, timesteps)``: the target is the noise for epsilon prediction and the
        velocity for ``v_prediction``; timesteps are int64 (B,).
    """
    noise = _randn(latents, generator)
    n = int(scheduler.config.num_train_timesteps)
    if generator is None:
        t = torch.randint(0, n, (latents.shape[0],), device=latents.device)
    else:
        t = torch.randint(0, n, (latents.shape[0],), generator=generator, device=generator.device).to(latents.device)
    noisy = scheduler.add_noise(latents, noise, t)
    kind = scheduler.config.prediction_type
    if kind == "epsilon":
        target = noise
    elif kind == "v_prediction":
        target = scheduler.get_velocity(latents, noise, t)
    else:
        raise ValueError(f"DDPM objective: prediction_type {kind!r} is not supported (epsilon, v_prediction)")
    return noisy, target, t


@dataclass(frozen=True)
class FlowSettings:
    """How flow-matching training draws noise levels.

    Attributes:
        shift: sigma shift (Wan: 3.0 for 480p Wan2.1, 5.0 for TI2V-5B, 12.0 for T2V-A14B sampling).
        sampling: "uniform", "logit_normal" (SD3) or "mode".
        logit_mean, logit_std: the logit-normal's parameters.
        mode_scale: the "mode" density's scale.
        weighting: loss weighting: "none", "sigma_sqrt" or "cosmap" (SD3's options).
        num_train_timesteps: timestep = sigma * this.
    """

    shift: float = 5.0
    sampling: str = "uniform"
    logit_mean: float = 0.0
    logit_std: float = 1.0
    mode_scale: float = 1.29
    weighting: str = "none"
    num_train_timesteps: int = 1000

    def __post_init__(self) -> None:
        if self.sampling not in FLOW_SAMPLING:
            raise ValueError(f"flow matching: sampling {self.sampling!r} is not one of {', '.join(FLOW_SAMPLING)}")
        if self.weighting not in ("none", "sigma_sqrt", "cosmap"):
            raise ValueError(f"flow matching: weighting {self.weighting!r} is not one of none, sigma_sqrt, cosmap")
        if not self.shift > 0:
            raise ValueError(f"flow matching: shift must be > 0, got {self.shift}")


def shift_sigmas(s: torch.Tensor, shift: float) -> torch.Tensor:
    """``shift * s / (1 + (shift - 1) * s)``, FlowMatchEulerDiscreteScheduler's static shift."""
    return shift * s / (1 + (shift - 1) * s)


def unshift_sigmas(sigma: torch.Tensor, shift: float) -> torch.Tensor:
    """The inverse of `shift_sigmas`."""
    return sigma / (shift - (shift - 1) * sigma)


def flow_sigmas(batch: int, settings: FlowSettings, *, sigma_range: tuple[float, float] = (0.0, 1.0),
                generator: torch.Generator | None = None, device: torch.device | str = "cpu") -> torch.Tensor:
    """Draw shifted noise levels sigma in ``sigma_range`` for a batch.

    ``s`` is drawn from the chosen density on (0, 1), mapped linearly onto the unshifted image
    of ``sigma_range`` and then shifted, so a range restricts training to one expert without
    changing the shape of the density inside it.

    Returns:
        float32 sigmas (batch,).
    """
    from diffusers.training_utils import compute_density_for_timestep_sampling

    lo, hi = sigma_range
    if not 0.0 <= lo < hi <= 1.0:
        raise ValueError(f"flow matching: sigma range {sigma_range} must satisfy 0 <= lo < hi <= 1")
    gen_device = generator.device if generator is not None else device
    u = compute_density_for_timestep_sampling(
        "none" if settings.sampling == "uniform" else settings.sampling, batch,
        logit_mean=settings.logit_mean, logit_std=settings.logit_std, mode_scale=settings.mode_scale,
        device=gen_device, generator=generator).float()
    bounds = unshift_sigmas(torch.tensor([lo, hi], dtype=torch.float64), settings.shift).float()
    s = bounds[0] + (bounds[1] - bounds[0]) * u.cpu()
    return shift_sigmas(s, settings.shift).clamp(1e-4, 1.0).to(device)


def flow_inputs(latents: torch.Tensor, sigmas: torch.Tensor, *, num_train_timesteps: int = 1000,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flow-matching inputs for clean latents (B, ...).

    Returns:
        ``(noisy, target, timesteps)``: ``(1 - sigma) x_0 + sigma * noise``, ``noise - x_0`` and
        ``sigma * num_train_timesteps`` (float32, (B,)).
    """
    noise = _randn(latents, generator).to(latents.dtype)
    s = sigmas.to(latents.device, latents.dtype).view(-1, *([1] * (latents.ndim - 1)))
    noisy = (1 - s) * latents + s * noise
    return noisy, noise - latents, sigmas.float() * num_train_timesteps


def flow_loss_weights(sigmas: torch.Tensor, settings: FlowSettings) -> torch.Tensor:
    """Per-sample loss weights (B,) for the configured weighting scheme."""
    from diffusers.training_utils import compute_loss_weighting_for_sd3

    return compute_loss_weighting_for_sd3(settings.weighting, sigmas.float())


def sample_epsilon(model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], scheduler: Any,
                   shape: tuple[int, ...], *, steps: int, generator: torch.Generator | None = None,
                   device: torch.device | str = "cpu") -> torch.Tensor:
    """Denoise from Gaussian noise with an epsilon (or v) model in ``steps`` scheduler steps.

    Args:
        model: ``model(x_t, t) -> prediction`` (conditioning is the caller's closure).
        scheduler: a diffusers scheduler (DDIM, DDPM, ...) over the training betas.
        shape: latent shape (B, C, F, H, W).
        steps: denoising steps.
        generator: random source for the initial noise (and stochastic schedulers).

    Returns:
        The clean latent estimate, float32.
    """
    scheduler.set_timesteps(steps, device=device)
    x = torch.randn(shape, generator=generator, device=generator.device if generator else device,
                    dtype=torch.float32).to(device) * scheduler.init_noise_sigma
    for t in scheduler.timesteps:
        pred = model(scheduler.scale_model_input(x, t), t)
        x = scheduler.step(pred.float(), t, x, generator=generator, return_dict=False)[0]
    return x


def sample_flow(model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], shape: tuple[int, ...], *,
                steps: int = 50, shift: float = 5.0, generator: torch.Generator | None = None,
                device: torch.device | str = "cpu") -> torch.Tensor:
    """Integrate a flow (velocity) model from noise (sigma 1) to data (sigma 0) with
    `FlowMatchEulerDiscreteScheduler` (``shift`` as in training).

    Args:
        model: ``model(x_t, timestep) -> velocity``; the timestep is ``1000 * sigma`` and tells the
            caller which expert to run.
        shape: latent shape (B, C, F, H, W).
        steps: Euler steps (50 in the paper's setting).
        shift: sigma shift.
        generator: random source for the initial noise.

    Returns:
        The clean latent estimate, float32.
    """
    from diffusers import FlowMatchEulerDiscreteScheduler

    sched: Any = FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=shift)
    sched.set_timesteps(steps, device=device)
    x = torch.randn(shape, generator=generator, device=generator.device if generator else device,
                    dtype=torch.float32).to(device)
    for t in sched.timesteps:
        v = model(x, t.expand(shape[0]))
        x = sched.step(v.float(), t, x, return_dict=False)[0]
    return x
