"""Torch side of morphgs. Importing it imports torch (``import morphgs`` never does).

- :func:`rasterization`: a differentiable CPU 3DGS rasterizer with gsplat's argument names and
  shape conventions (``gsplat.rasterization``), backed by morphgs's deterministic multithreaded
  Rust forward and backward passes.
"""

from __future__ import annotations

from morphgs.torch._raster import rasterization

__all__ = ["rasterization"]
