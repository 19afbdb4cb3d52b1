"""Record a model's intermediate features with forward hooks, and their CKA over training.

The paper's Figure 4 tracks how the temporal-attention features of a video model drift while it
is fine-tuned: record the outputs of every temporal-attention module on a fixed probe input at
a few training steps, then compare each snapshot with the first by linear CKA.

    history = FeatureHistory(unet, probe=lambda: unet(sample, t, encoder_hidden_states=text))
    history.snapshot(step=0)
    ...train...
    history.snapshot(step=500)
    history.cka()          # {module name: [CKA(step 0, step s) for each snapshot s]}

In diffusers' `UNetMotionModel` the temporal attention is the `attn1` of each motion module's
transformer blocks (`down_blocks.{i}.motion_modules.{j}.transformer_blocks.{k}.attn1`, also
under `up_blocks` and `mid_block`); its output is (B*H*W, F, C), read as rows of C features.
Nothing here imports torch at module level; the hooks are plain `register_forward_hook`s.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

import numpy as np

from morphgs.metrics._arrays import MetricError
from morphgs.metrics.cka import linear_cka

__all__ = ["TEMPORAL_ATTENTION", "FeatureHistory", "FeatureRecorder"]

# diffusers' AnimateDiff motion modules: temporal self-attention (attn1; attn2 is also temporal
# there, but attn1 is the first and the one the paper's analysis hooks)
TEMPORAL_ATTENTION = r"motion_modules\.\d+\.transformer_blocks\.\d+\.attn1$"


class FeatureRecorder:
    """Forward hooks on every submodule whose qualified name matches `pattern` (re.search).

    Args:
        model: a torch `nn.Module`.
        pattern: regular expression over `model.named_modules()` names.
        max_rows: keep at most this many rows (examples) per module; when a module yields more,
            the same rows (a seeded choice that depends only on the row count) are kept at every
            recording, so recordings of the same probe stay row-aligned for CKA.
        seed: seed of that row choice.

    Raises:
        MetricError: no module matches `pattern`.
    """

    def __init__(self, model: Any, *, pattern: str = TEMPORAL_ATTENTION, max_rows: int = 4096, seed: int = 0) -> None:
        self.model = model
        self.pattern = pattern
        self.max_rows = int(max_rows)
        self.seed = int(seed)
        rx = re.compile(pattern)
        self.modules = {name: m for name, m in model.named_modules() if name and rx.search(name)}
        if not self.modules:
            raise MetricError(f"no submodule of {type(model).__name__} matches {pattern!r}")

    @property
    def names(self) -> list[str]:
        return list(self.modules)

    def _rows(self, n: int) -> np.ndarray | None:
        if n <= self.max_rows:
            return None
        return np.sort(np.random.default_rng([self.seed, n]).choice(n, self.max_rows, replace=False))

    def record(self, run: Callable[[], Any]) -> dict[str, np.ndarray]:
        """Call `run()` (a forward pass of the model) without gradients, in eval mode, with the
        hooks attached; return {module name: (rows, C) float64 features}. The model's training
        mode is restored and the hooks are removed afterwards, even if `run` raises.

        Raises:
            MetricError: a matched module did not run during `run()`.
        """
        import torch

        store: dict[str, list[np.ndarray]] = {name: [] for name in self.modules}

        def hook(name: str) -> Callable[..., None]:
            def fn(_module: Any, _inputs: Any, output: Any) -> None:
                out = output[0] if isinstance(output, (tuple, list)) else output
                store[name].append(out.detach().to(torch.float64).reshape(-1, out.shape[-1]).cpu().numpy())
            return fn

        handles = [m.register_forward_hook(hook(name)) for name, m in self.modules.items()]
        was_training = self.model.training
        self.model.eval()
        try:
            with torch.no_grad():
                run()
        finally:
            for h in handles:
                h.remove()
            self.model.train(was_training)
        out: dict[str, np.ndarray] = {}
        for name, chunks in store.items():
            if not chunks:
                raise MetricError(f"{name} matched {self.pattern!r} but did not run during the probe")
            feats = np.concatenate(chunks)
            rows = self._rows(len(feats))
            out[name] = feats if rows is None else feats[rows]
        return out


class FeatureHistory:
    """Snapshots of a model's hooked features on a fixed probe, over training steps.

    Args:
        model: a torch `nn.Module`.
        probe: a callable running the model on fixed inputs (the same inputs at every snapshot).
        pattern, max_rows, seed: as `FeatureRecorder`.
    """

    def __init__(self, model: Any, probe: Callable[[], Any], *, pattern: str = TEMPORAL_ATTENTION,
                 max_rows: int = 4096, seed: int = 0) -> None:
        self.recorder = FeatureRecorder(model, pattern=pattern, max_rows=max_rows, seed=seed)
        self.probe = probe
        self.steps: list[int] = []
        self.snapshots: list[dict[str, np.ndarray]] = []

    def snapshot(self, step: int) -> dict[str, np.ndarray]:
        """Record the features at training step `step` and keep them."""
        feats = self.recorder.record(self.probe)
        self.steps.append(int(step))
        self.snapshots.append(feats)
        return feats

    def cka(self, *, reference: int = 0, debiased: bool = False) -> dict[str, list[float]]:
        """{module name: [linear CKA(snapshot `reference`, snapshot s) for every snapshot s]}.

        Raises:
            MetricError: no snapshot yet, or a reference index out of range.
        """
        if not self.snapshots:
            raise MetricError("FeatureHistory.cka: take a snapshot first")
        if not -len(self.snapshots) <= reference < len(self.snapshots):
            raise MetricError(f"reference snapshot {reference} out of range ({len(self.snapshots)} taken)")
        ref = self.snapshots[reference]
        return {name: [linear_cka(ref[name], snap[name], debiased=debiased) for snap in self.snapshots]
                for name in self.recorder.names}
