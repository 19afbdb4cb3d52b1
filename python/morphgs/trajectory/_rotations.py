"""Rotation helpers: matrices <-> unit quaternions (w, x, y, z), slerp and squad."""

from __future__ import annotations

import numpy as np


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(...,3,3) rotation matrices -> (...,4) unit quaternions (w,x,y,z), w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for n, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        qa = np.asarray(q)
        qa /= np.linalg.norm(qa)
        out[n] = -qa if qa[0] < 0 else qa
    return out.reshape(r.shape[:-2] + (4,))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(...,4) quaternions (w,x,y,z), normalised here -> (...,3,3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], -1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_log(q: np.ndarray) -> np.ndarray:
    """Log of unit quaternions -> (...,4) pure quaternions (0, v * angle/2)."""
    v = q[..., 1:]
    vn = np.linalg.norm(v, axis=-1, keepdims=True)
    half = np.arctan2(vn, q[..., :1])
    scale = np.where(vn > 1e-12, half / np.maximum(vn, 1e-300), 1.0)
    return np.concatenate([np.zeros_like(q[..., :1]), v * scale], -1)


def quat_exp(p: np.ndarray) -> np.ndarray:
    """Exp of pure quaternions (0, v) -> unit quaternions."""
    v = p[..., 1:]
    a = np.linalg.norm(v, axis=-1, keepdims=True)
    s = np.where(a > 1e-12, np.sin(a) / np.maximum(a, 1e-300), 1.0)
    return np.concatenate([np.cos(a), v * s], -1)


def make_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs so consecutive quaternions lie in the same hemisphere (shortest arcs)."""
    q = np.array(q, dtype=np.float64)
    for i in range(1, len(q)):
        if np.dot(q[i - 1], q[i]) < 0:
            q[i] = -q[i]
    return q


def slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation, shortest arc; `t` broadcasts against the leading axes."""
    t = np.asarray(t, dtype=np.float64)[..., None]
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0, -b, b)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    st = np.sin(theta)
    small = st < 1e-9
    wa = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / np.where(small, 1.0, st))
    wb = np.where(small, t, np.sin(t * theta) / np.where(small, 1.0, st))
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def squad_controls(q: np.ndarray) -> np.ndarray:
    """Inner control quaternions s_i of Shoemake's squad for a continuous key sequence q (N,4)."""
    n = len(q)
    s = np.empty_like(q)
    for i in range(n):
        qp = q[max(i - 1, 0)]
        qn = q[min(i + 1, n - 1)]
        inv = quat_conj(q[i])
        t = -(quat_log(quat_mul(inv, qn)) + quat_log(quat_mul(inv, qp))) / 4.0
        s[i] = quat_mul(q[i], quat_exp(t))
    return s


def squad(q0: np.ndarray, q1: np.ndarray, s0: np.ndarray, s1: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """squad(q0, q1, s0, s1; t) = slerp(slerp(q0,q1,t), slerp(s0,s1,t), 2t(1-t)): C1 across keys."""
    t = np.asarray(t, dtype=np.float64)
    return slerp(slerp(q0, q1, t), slerp(s0, s1, t), 2.0 * t * (1.0 - t))


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (radians) of the rotation between unit quaternions a and b."""
    d = np.abs(np.sum(a * b, axis=-1))
    return 2.0 * np.arccos(np.clip(d, -1.0, 1.0))
