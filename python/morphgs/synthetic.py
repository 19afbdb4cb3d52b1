"""A deterministic procedural scene that renders like a small real capture, so that everything in
morphgs runs with no download and benchmarks can build scenes of any size.

The world is z-up with the ground plane at z = 0. The scene is a room corner about 8 m across:

* a textured floor (wooden checker tiles with grain and a rug) over x, y in [-4, 4],
* three walls: the back wall y = 4 (with a framed picture), the left wall x = -4 and a short
  right wall x = 4 (y in [1, 4]), each 3 m high, with a darker skirting band,
* objects near the origin resting on the floor: a large striped sphere, a rotated box with a small
  glossy sphere on top, a cylinder and a cone,
* half a percent of "floaters": loose, large, faint Gaussians in the air, as real captures have.

Everything lies inside [-4, 4] x [-4, 4] x [0, 3] (``EXTENT_MIN``, ``EXTENT_MAX``); the objects fill
roughly [-1.6, 1.6] x [-1.6, 1.4] x [0, 1.5]. Surfaces are covered by flat anisotropic Gaussians
whose thin axis (scale_2) is aligned with the surface normal, sized from the local sample spacing
(so renders look filled at any Gaussian count) with a log-normal spread; opacities are mostly high
with a tail of faint ones; colours carry view-dependent higher SH bands.

``suggested_orbit()`` gives a camera orbit (look-at centre, radius, height) that frames the objects
with the walls behind them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from morphgs._core import GaussianScene

__all__ = ["EXTENT_MAX", "EXTENT_MIN", "Orbit", "scene", "suggested_orbit"]

#: Corners of the box that holds every Gaussian centre (metres, z-up).
EXTENT_MIN = (-4.0, -4.0, 0.0)
EXTENT_MAX = (4.0, 4.0, 3.0)

SH_C0 = 0.28209479177387814

# Share of the Gaussian budget per part (objects get more than their area: they are what a camera
# looks at). Parts whose share rounds to zero at tiny budgets are simply absent.
_SHARES = {
    "floor": 0.30,
    "back_wall": 0.10,
    "left_wall": 0.08,
    "right_wall": 0.04,
    "sphere": 0.14,
    "box": 0.12,
    "small_sphere": 0.04,
    "cylinder": 0.08,
    "cone": 0.095,
    "floaters": 0.005,
}


@dataclass(frozen=True)
class Orbit:
    """A circular camera path around the synthetic scene's objects (z-up world).

    Attributes:
        center: the look-at point (x, y, z).
        radius: horizontal distance of the cameras from the centre.
        height: camera height above the floor (z).
    """

    center: tuple[float, float, float]
    radius: float
    height: float

    def eye(self, angle: float) -> np.ndarray:
        """Camera position at `angle` radians (0 looks along +y, from the open side of the room)."""
        cx, cy, _ = self.center
        return np.array([cx + self.radius * math.sin(angle), cy - self.radius * math.cos(angle),
                         self.height])


def suggested_orbit() -> Orbit:
    """The orbit that frames the synthetic scene: every camera on it stays inside the room and
    sees the objects against the floor and walls."""
    return Orbit(center=(0.0, 0.0, 0.5), radius=3.0, height=1.6)


def _split(n: int) -> dict[str, int]:
    """Largest-remainder split of `n` over the parts; the counts sum to exactly `n`."""
    names = list(_SHARES)
    raw = np.array([_SHARES[k] * n for k in names])
    counts = np.floor(raw).astype(np.int64)
    order = np.argsort(-(raw - counts), kind="stable")
    counts[order[: n - int(counts.sum())]] += 1
    return dict(zip(names, (int(c) for c in counts)))


class _Part:
    """Centres, unit normals, colours and surface area of one sampled surface."""

    def __init__(self, p: np.ndarray, nrm: np.ndarray, rgb: np.ndarray, area: float,
                 gloss: float) -> None:
        self.p, self.nrm, self.rgb, self.area, self.gloss = p, nrm, rgb, area, gloss


def _noise(rng: np.random.Generator, xy: np.ndarray, octaves: int = 4, base: float = 1.5) -> np.ndarray:
    """Smooth value in about [-1, 1]: a sum of random plane waves (vectorised, seeded)."""
    out = np.zeros(len(xy), dtype=np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        k = rng.normal(size=(3, xy.shape[1])).astype(np.float32) * np.float32(base * 2.0**o)
        ph = rng.uniform(0, 2 * np.pi, size=3).astype(np.float32)
        for j in range(3):
            arg = xy[:, 0] * k[j, 0] + ph[j]
            for d in range(1, xy.shape[1]):
                arg += xy[:, d] * k[j, d]
            out += np.float32(amp / 3) * np.sin(arg)
        total += amp
        amp *= 0.5
    return out / np.float32(total / 1.5)


def _rect(rng: np.random.Generator, m: int, origin: tuple[float, ...], u: tuple[float, ...],
          v: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`m` uniform points on the rectangle origin + a*u + b*v; returns points, (a, b) and normal."""
    ab = rng.random((m, 2), dtype=np.float32)
    o, uu, vv = (np.asarray(x, dtype=np.float32) for x in (origin, u, v))
    p = o + ab[:, :1] * uu + ab[:, 1:] * vv
    nrm = np.cross(uu, vv)
    nrm = np.broadcast_to(nrm / np.linalg.norm(nrm), (m, 3)).astype(np.float32)
    return p, ab * np.array([np.linalg.norm(uu), np.linalg.norm(vv)], dtype=np.float32), nrm


def _floor(rng: np.random.Generator, m: int) -> _Part:
    p, ab, nrm = _rect(rng, m, (-4, -4, 0), (8, 0, 0), (0, 8, 0))
    tile = ((np.floor(p[:, 0] / 0.5) + np.floor(p[:, 1] / 0.5)) % 2).astype(np.float32)[:, None]
    light = np.array([0.62, 0.48, 0.34], dtype=np.float32)
    dark = np.array([0.42, 0.31, 0.22], dtype=np.float32)
    rgb = light * (1 - tile) + dark * tile
    # wood grain along x inside each tile, plus large-scale dirt
    grain = np.sin(p[:, 1] * 60.0 + 3.0 * _noise(rng, p[:, :2], 3, 2.0)).astype(np.float32)
    rgb = rgb * (1 + 0.06 * grain[:, None]) * (1 + 0.12 * _noise(rng, p[:, :2], 3, 0.4)[:, None])
    # an oval rug under the objects
    rug = ((p[:, 0] / 2.4) ** 2 + ((p[:, 1] + 0.1) / 1.9) ** 2) < 1.0
    stripes = (np.floor((p[rug, 0] * 0.8 + p[rug, 1] * 0.6) / 0.18) % 3).astype(np.int64)
    palette = np.array([[0.55, 0.12, 0.10], [0.80, 0.68, 0.42], [0.12, 0.22, 0.40]], dtype=np.float32)
    rgb[rug] = palette[stripes] * (1 + 0.08 * _noise(rng, p[rug, :2], 2, 6.0)[:, None])
    return _Part(p, nrm, rgb, 64.0, 0.3)


def _wall(rng: np.random.Generator, m: int, origin: tuple[float, ...], u: tuple[float, ...],
          v: tuple[float, ...], tint: tuple[float, float, float], picture: bool) -> _Part:
    p, ab, nrm = _rect(rng, m, origin, u, v)
    rgb = np.broadcast_to(np.asarray(tint, dtype=np.float32), (m, 3)).copy()
    rgb *= (1 + 0.05 * _noise(rng, ab, 4, 1.2))[:, None]
    rgb[p[:, 2] < 0.15] = (0.30, 0.26, 0.22)  # skirting board
    if picture:
        a, b = ab[:, 0], ab[:, 1]  # along the wall, up
        frame = (np.abs(a - 4.6) < 1.3) & (np.abs(b - 1.75) < 0.8)
        inner = (np.abs(a - 4.6) < 1.18) & (np.abs(b - 1.75) < 0.68)
        rgb[frame] = (0.18, 0.12, 0.07)
        t = (b[inner] - 1.07) / 1.36
        sky = np.stack([0.35 + 0.4 * t, 0.55 + 0.3 * t, 0.85 - 0.1 * t], axis=1)
        hills = (b[inner] - 1.07) < 0.45 + 0.15 * np.sin(3.0 * a[inner])
        sky[hills] = (0.25, 0.45, 0.18)
        sun = (a[inner] - 5.2) ** 2 + (b[inner] - 2.1) ** 2 < 0.03
        sky[sun] = (0.98, 0.85, 0.35)
        rgb[inner] = sky.astype(np.float32)
    return _Part(p, nrm, rgb, float(np.linalg.norm(u) * np.linalg.norm(v)), 0.1)


def _sphere(rng: np.random.Generator, m: int, c: tuple[float, float, float], r: float,
            stripe: tuple[tuple[float, ...], tuple[float, ...]], gloss: float) -> _Part:
    z = rng.uniform(-1, 1, m).astype(np.float32)
    phi = rng.uniform(0, 2 * np.pi, m).astype(np.float32)
    s = np.sqrt(1 - z * z)
    nrm = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
    p = np.asarray(c, dtype=np.float32) + np.float32(r) * nrm
    band = ((np.floor((z + 0.05 * np.sin(4 * phi)) * 5) % 2) == 0)[:, None]
    rgb = np.where(band, np.asarray(stripe[0], np.float32), np.asarray(stripe[1], np.float32))
    rgb = rgb * (1 + 0.05 * _noise(rng, nrm, 2, 2.0))[:, None]
    return _Part(p, nrm.astype(np.float32), rgb.astype(np.float32), 4 * math.pi * r * r, gloss)


def _box(rng: np.random.Generator, m: int, c: tuple[float, float], size: tuple[float, float, float],
         yaw: float) -> _Part:
    sx, sy, sz = size
    faces = [  # (local normal, u axis, v axis, centre offset) ; no bottom face
        ((0, 0, 1), (sx, 0, 0), (0, sy, 0), (0, 0, sz / 2)),
        ((1, 0, 0), (0, sy, 0), (0, 0, sz), (sx / 2, 0, 0)),
        ((-1, 0, 0), (0, sy, 0), (0, 0, sz), (-sx / 2, 0, 0)),
        ((0, 1, 0), (sx, 0, 0), (0, 0, sz), (0, sy / 2, 0)),
        ((0, -1, 0), (sx, 0, 0), (0, 0, sz), (0, -sy / 2, 0)),
    ]
    areas = np.array([np.linalg.norm(np.cross(f[1], f[2])) for f in faces])
    face = rng.choice(len(faces), size=m, p=areas / areas.sum())
    ab = rng.random((m, 2), dtype=np.float32) - 0.5
    n_l = np.array([f[0] for f in faces], dtype=np.float32)[face]
    u = np.array([f[1] for f in faces], dtype=np.float32)[face]
    v = np.array([f[2] for f in faces], dtype=np.float32)[face]
    off = np.array([f[3] for f in faces], dtype=np.float32)[face]
    p_l = off + ab[:, :1] * u + ab[:, 1:] * v
    cy_, sy_ = math.cos(yaw), math.sin(yaw)
    rot = np.array([[cy_, -sy_, 0], [sy_, cy_, 0], [0, 0, 1]], dtype=np.float32)
    p = p_l @ rot.T + np.array([c[0], c[1], sz / 2], dtype=np.float32)
    nrm = n_l @ rot.T
    shade = np.array([1.0, 0.85, 0.8, 0.92, 0.75], dtype=np.float32)[face][:, None]
    rgb = np.array([0.20, 0.35, 0.70], dtype=np.float32) * shade
    edge = (np.abs(ab) > 0.46).any(axis=1)  # lighter trim along the edges
    rgb[edge] = (0.85, 0.85, 0.80)
    return _Part(p, nrm, rgb, float(areas.sum()), 0.5)


def _cylinder(rng: np.random.Generator, m: int, c: tuple[float, float], r: float, h: float) -> _Part:
    side, top = 2 * math.pi * r * h, math.pi * r * r
    on_top = rng.random(m) < top / (side + top)
    phi = rng.uniform(0, 2 * np.pi, m).astype(np.float32)
    z = rng.uniform(0, h, m).astype(np.float32)
    rr = np.where(on_top, r * np.sqrt(rng.random(m, dtype=np.float32)), r).astype(np.float32)
    p = np.stack([c[0] + rr * np.cos(phi), c[1] + rr * np.sin(phi), np.where(on_top, h, z)], axis=1)
    nrm = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    nrm[on_top] = (0, 0, 1)
    stripe = (np.floor(phi / (2 * np.pi) * 16) % 2)[:, None]
    rgb = np.where(stripe == 0, np.array([0.20, 0.55, 0.25], dtype=np.float32), np.array([0.85, 0.80, 0.30], dtype=np.float32))
    rgb[on_top] = (0.30, 0.60, 0.32)
    return _Part(p.astype(np.float32), nrm.astype(np.float32), rgb.astype(np.float32), side + top, 0.4)


def _cone(rng: np.random.Generator, m: int, c: tuple[float, float], r: float, h: float) -> _Part:
    # area-uniform on the lateral surface: radius fraction ~ sqrt(uniform)
    t = np.sqrt(rng.random(m, dtype=np.float32))
    phi = rng.uniform(0, 2 * np.pi, m).astype(np.float32)
    p = np.stack([c[0] + r * t * np.cos(phi), c[1] + r * t * np.sin(phi), h * (1 - t)], axis=1)
    sl = math.hypot(r, h)
    nrm = np.stack([h / sl * np.cos(phi), h / sl * np.sin(phi), np.full_like(phi, r / sl)], axis=1)
    rgb = np.where((np.floor(p[:, 2] / 0.12) % 2 == 0)[:, None], np.array([0.90, 0.45, 0.10], dtype=np.float32),
                   np.array([0.95, 0.92, 0.88], dtype=np.float32))
    return _Part(p.astype(np.float32), nrm.astype(np.float32), rgb.astype(np.float32),
                 math.pi * r * sl, 0.2)


def _align_quats(rng: np.random.Generator, nrm: np.ndarray) -> np.ndarray:
    """(w,x,y,z) rotations taking the local z axis to `nrm`, with a random twist about it."""
    m = len(nrm)
    nz = nrm[:, 2]
    # shortest arc from z to n: (1 + n_z, z x n) normalised; n = -z needs a half turn about x
    q = np.stack([1 + nz, -nrm[:, 1], nrm[:, 0], np.zeros(m, np.float32)], axis=1)
    flip = nz < -0.999999
    q[flip] = (0, 1, 0, 0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    half = rng.uniform(0, np.pi, m).astype(np.float32)
    tw, tz = np.cos(half), np.sin(half)  # twist (cos, 0, 0, sin) applied in the local frame
    w, x, y, z = q.T
    return np.stack([w * tw - z * tz, x * tw + y * tz, y * tw - x * tz, w * tz + z * tw], axis=1)


def scene(n_gaussians: int = 100_000, sh_degree: int = 3, seed: int = 0) -> GaussianScene:
    """Build the synthetic room-corner scene (see the module docstring).

    Args:
        n_gaussians: exact number of Gaussians (>= 0).
        sh_degree: SH degree 0..4 of the colours; degrees >= 1 get view-dependent bands.
        seed: seed of the numpy Generator; the same arguments always give the same scene.

    Returns:
        GaussianScene with `n_gaussians` Gaussians.

    Raises:
        ValueError: `n_gaussians` is negative or `sh_degree` is not in 0..4.
    """
    n = int(n_gaussians)
    if n != n_gaussians or n < 0:
        raise ValueError(f"n_gaussians must be a non-negative integer, got {n_gaussians!r}")
    if sh_degree not in (0, 1, 2, 3, 4):
        raise ValueError(f"sh_degree must be 0..4, got {sh_degree!r}")
    rng = np.random.default_rng(seed)
    counts = _split(n)
    parts: list[_Part] = []
    # The seed also varies the layout, so sample scenes of different seeds are different rooms:
    # objects shift by up to 0.3 m, spheres change colours and size, walls change tint.
    lay = np.random.default_rng([int(seed), 0x5EED])

    def shift() -> tuple[float, float]:
        dx, dy = lay.uniform(-0.3, 0.3, 2)
        return float(dx), float(dy)

    def tint(base: tuple[float, float, float]) -> tuple[float, float, float]:
        t = np.clip(np.asarray(base) + lay.uniform(-0.08, 0.08, 3), 0.0, 1.0)
        return (float(t[0]), float(t[1]), float(t[2]))

    stripes = [(0.80, 0.15, 0.12), (0.15, 0.35, 0.80), (0.15, 0.60, 0.25), (0.55, 0.20, 0.65),
               (0.90, 0.55, 0.10)]
    stripe = stripes[int(lay.integers(len(stripes)))]
    (sx, sy), (bx, by), (cx, cy), (kx, ky) = shift(), shift(), shift(), shift()
    r_big = 0.6 * float(lay.uniform(0.85, 1.15))
    yaw = 0.5 + float(lay.uniform(-0.4, 0.4))
    walls = [tint(c) for c in ((0.80, 0.78, 0.72), (0.70, 0.76, 0.78), (0.78, 0.74, 0.70))]
    builders = {
        "floor": lambda m: _floor(rng, m),
        "back_wall": lambda m: _wall(rng, m, (-4, 4, 0), (8, 0, 0), (0, 0, 3), walls[0], True),
        "left_wall": lambda m: _wall(rng, m, (-4, -4, 0), (0, 0, 3), (0, 8, 0), walls[1], False),
        "right_wall": lambda m: _wall(rng, m, (4, 1, 0), (0, 3, 0), (0, 0, 3), walls[2], False),
        "sphere": lambda m: _sphere(rng, m, (0.9 + sx, 0.4 + sy, r_big), r_big,
                                    (stripe, (0.95, 0.90, 0.85)), 0.8),
        "box": lambda m: _box(rng, m, (-0.9 + bx, 0.2 + by), (0.9, 0.7, 0.8), yaw),
        "small_sphere": lambda m: _sphere(rng, m, (-0.9 + bx, 0.2 + by, 1.05), 0.25,
                                          ((0.95, 0.78, 0.25), (0.85, 0.65, 0.15)), 1.0),
        "cylinder": lambda m: _cylinder(rng, m, (0.3 + cx, -1.1 + cy), 0.3, 1.1),
        "cone": lambda m: _cone(rng, m, (-1.1 + kx, -1.2 + ky), 0.4, 0.9),
    }
    for name, build in builders.items():
        parts.append(build(counts[name]))

    means, normals, rgb, spacing, gloss = [], [], [], [], []
    for part in parts:
        m = len(part.p)
        means.append(part.p)
        normals.append(part.nrm)
        rgb.append(part.rgb)
        spacing.append(np.full(m, math.sqrt(part.area / max(m, 1)), dtype=np.float32))
        gloss.append(np.full(m, part.gloss, dtype=np.float32))
    surf_means = np.concatenate(means).astype(np.float32)
    surf_n = np.concatenate(normals).astype(np.float32)
    ms = len(surf_means)
    f32 = np.float32

    def normal(shape: tuple[int, ...], mu: float = 0.0, sigma: float = 1.0) -> np.ndarray:
        out = rng.standard_normal(shape, dtype=f32)
        out *= f32(sigma)
        out += f32(mu)
        return out

    # captured surfaces are a little noisy along the normal
    surf_means += surf_n * normal((ms, 1), 0.0, 0.004)

    # surface Gaussians: flat discs, thin axis = scale_2 along the normal, log-normal sizes around
    # the local sample spacing
    sp = np.log(np.concatenate(spacing) * f32(0.9))[:, None]
    tang = normal((ms, 2), 0.0, 0.35) + sp
    thin = tang.min(axis=1, keepdims=True) + normal((ms, 1), -2.3, 0.4)
    surf_log_scales = np.concatenate([tang, thin], axis=1)
    surf_quats = _align_quats(rng, surf_n)
    # mostly opaque (alpha near 1, exponential tail), 12% faint
    faint = rng.random(ms, dtype=f32) < 0.12
    alpha = 1 - np.minimum(f32(0.5), rng.standard_exponential(ms, dtype=f32) * f32(0.06))
    alpha[faint] = rng.uniform(0.02, 0.4, int(faint.sum())).astype(f32)
    surf_rgb = np.concatenate(rgb).astype(f32)
    surf_rgb *= 1 + normal((ms, 1), 0.0, 0.04)
    surf_rgb += normal((ms, 3), 0.0, 0.015)
    surf_gloss = np.concatenate(gloss)

    # floaters: loose, roughly isotropic, faint, greyish
    mf = counts["floaters"]
    f_means = (rng.uniform(EXTENT_MIN, EXTENT_MAX, (mf, 3)) * (0.9, 0.9, 0.8) + (0, 0, 0.3))
    f_log_scales = rng.normal(math.log(0.06), 0.5, (mf, 1)) + rng.normal(0, 0.3, (mf, 3))
    f_quats = rng.normal(size=(mf, 4))
    f_alpha = rng.uniform(0.02, 0.12, mf)
    f_rgb = rng.uniform(0.3, 0.8, (mf, 1)) + rng.normal(0, 0.05, (mf, 3))

    means_all = np.concatenate([surf_means, f_means.astype(f32)])
    np.clip(means_all, np.array(EXTENT_MIN, dtype=f32), np.array(EXTENT_MAX, dtype=f32), out=means_all)
    alpha_all = np.clip(np.concatenate([alpha, f_alpha.astype(f32)]), f32(1e-4), f32(1 - 1e-4))
    rgb_all = np.concatenate([surf_rgb, f_rgb.astype(f32)])
    np.clip(rgb_all, f32(0), f32(1), out=rgb_all)
    gloss_all = np.concatenate([surf_gloss, np.full(mf, 0.05, f32)])

    k = (sh_degree + 1) ** 2 - 1
    sh_rest: np.ndarray | None = None
    if k:
        # band l decays like 0.5^l; glossy parts carry more view dependence; a shared,
        # colour-neutral component makes highlights white-ish rather than random hues
        band = np.concatenate([np.full(2 * l + 1, 0.5**l, f32) for l in range(1, sh_degree + 1)])
        sh_rest = rng.random((n, k, 3), dtype=f32)  # uniform, zero mean, unit variance
        sh_rest -= f32(0.5)
        sh_rest *= f32(math.sqrt(12.0))
        shared = rng.random((n, k, 1), dtype=f32)
        shared -= f32(0.5)
        shared *= f32(math.sqrt(12.0) * 1.2)
        sh_rest += shared  # broadcast over the channels, in place
        del shared
        sh_rest *= band[None, :, None]
        sh_rest *= (f32(0.03) + f32(0.12) * gloss_all)[:, None, None]

    return GaussianScene.from_arrays(
        means=means_all,
        quats=np.concatenate([surf_quats, f_quats.astype(np.float32)]),
        log_scales=np.concatenate([surf_log_scales, f_log_scales.astype(np.float32)]),
        opacity_logits=np.log(alpha_all / (1 - alpha_all)),
        sh0=(rgb_all - 0.5) / SH_C0,
        sh_rest=sh_rest,
    )
