//! The projection's formulas that other passes share: the 2D covariance and the quaternion's
//! rotation (the forward, the backward and densification compute them with the same operations,
//! so they round alike), and the bound on a camera rotation's gain behind the off-screen early
//! out.

/// A = J T (J the EWA Jacobian [j00, j02, j11, j12] of its two non-zero rows, T = W R S) and
/// the 2D covariance A A^T without eps2d: (A's rows, [c00, c01, c11]). The forward and the
/// backward (which recomputes it) share it, so they round alike.
#[inline(always)]
pub(crate) fn cov2d(
    [j00, j02, j11, j12]: [f32; 4],
    t: &[[f32; 3]; 3],
) -> ([f32; 3], [f32; 3], [f32; 3]) {
    let mut a0 = [0.0f32; 3];
    let mut a1 = [0.0f32; 3];
    for c in 0..3 {
        a0[c] = j00 * t[0][c] + j02 * t[2][c];
        a1[c] = j11 * t[1][c] + j12 * t[2][c];
    }
    let c00 = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2];
    let c01 = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2];
    let c11 = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2];
    (a0, a1, [c00, c01, c11])
}

/// Rotation matrix of a unit quaternion (w, x, y, z), row-major: the one formula the forward,
/// the backward and densification share (same operations, so the same bits everywhere).
#[inline(always)]
pub(crate) fn quat_rotation(qw: f32, qx: f32, qy: f32, qz: f32) -> [[f32; 3]; 3] {
    [
        [
            1.0 - 2.0 * (qy * qy + qz * qz),
            2.0 * (qx * qy - qw * qz),
            2.0 * (qx * qz + qw * qy),
        ],
        [
            2.0 * (qx * qy + qw * qz),
            1.0 - 2.0 * (qx * qx + qz * qz),
            2.0 * (qy * qz - qw * qx),
        ],
        [
            2.0 * (qx * qz - qw * qy),
            2.0 * (qy * qz + qw * qx),
            1.0 - 2.0 * (qx * qx + qy * qy),
        ],
    ]
}

/// An upper bound of the largest singular value of `m`: 1 (plus rounding slack) for a rotation,
/// else the Frobenius norm, so the off-screen early out stays conservative for any matrix.
pub(super) fn spectral_norm_bound(m: &[[f64; 3]; 3]) -> f32 {
    let mut frob2 = 0.0;
    let mut off = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let mtm: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
            off = off.max((mtm - if i == j { 1.0 } else { 0.0 }).abs());
            if i == j {
                frob2 += mtm;
            }
        }
    }
    if off < 1e-5 {
        1.0001
    } else {
        (frob2.sqrt() * 1.0001) as f32
    }
}
