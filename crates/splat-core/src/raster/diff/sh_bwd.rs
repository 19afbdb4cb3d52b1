//! Vector-Jacobian product of the SH colour (SPEC §4 step 5; gsplat's
//! `sh_coeffs_to_color_fast_vjp`): gradients of the coefficients and of the unnormalised view
//! direction mean - camera centre (which flows into the mean).
#[cfg(test)]
use crate::raster::sh;

/// Gradient of the first `(degree+1)^2` basis functions at the unit direction (x, y, z),
/// as functions of (x, y, z) in R^3 (the projection onto the sphere's tangent plane is applied
/// by the caller): `out[k] = dY_k/d(x, y, z)`.
#[inline]
pub(crate) fn basis_grad(degree: u8, dir: [f32; 3], out: &mut [[f32; 3]; 16]) {
    let [x, y, z] = dir;
    out[0] = [0.0; 3];
    if degree == 0 {
        return;
    }
    let a1 = -0.488_602_52_f32;
    out[1] = [0.0, a1, 0.0];
    out[2] = [0.0, 0.0, -a1];
    out[3] = [a1, 0.0, 0.0];
    if degree == 1 {
        return;
    }
    let ta = 0.546_274_24_f32;
    let tb = -1.092_548_4_f32;
    out[4] = [2.0 * ta * y, 2.0 * ta * x, 0.0]; // ta 2xy
    out[5] = [0.0, tb * z, tb * y]; // tb z y
    out[6] = [0.0, 0.0, 2.0 * 0.946_174_7 * z]; // 0.946 z^2 - 0.315
    out[7] = [tb * z, 0.0, tb * x]; // tb z x
    out[8] = [2.0 * ta * x, -2.0 * ta * y, 0.0]; // ta (x^2 - y^2)
    if degree == 2 {
        return;
    }
    let z2 = z * z;
    let tmp_c = -2.285_229 * z2 + 0.457_045_8;
    let tmp_c_z = -2.0 * 2.285_229 * z;
    let kb = 1.445_305_7_f32;
    let tmp_b = kb * z;
    let a3 = -0.590_043_6_f32;
    let c1 = x * x - y * y;
    let s1 = 2.0 * x * y;
    // s2 = 3x^2 y - y^3, c2 = x^3 - 3 x y^2
    let s2_x = 6.0 * x * y;
    let s2_y = 3.0 * (x * x - y * y);
    let c2_x = 3.0 * (x * x - y * y);
    let c2_y = -6.0 * x * y;
    out[9] = [a3 * s2_x, a3 * s2_y, 0.0];
    out[10] = [tmp_b * 2.0 * y, tmp_b * 2.0 * x, kb * s1];
    out[11] = [0.0, tmp_c, tmp_c_z * y];
    out[12] = [0.0, 0.0, 3.0 * 1.865_881_7 * z2 - 1.119_529];
    out[13] = [tmp_c, 0.0, tmp_c_z * x];
    out[14] = [tmp_b * 2.0 * x, -tmp_b * 2.0 * y, kb * c1];
    out[15] = [a3 * c2_x, a3 * c2_y, 0.0];
}

/// Gradients of one Gaussian's SH colour. `g` is dL/d(colour) already gated by the clamp at
/// zero; `coef(k)` returns basis k's (r, g, b) coefficients (k = 0 is sh0).
///
/// Returns the coefficient gradients in `v_coef[k]` for k < (degree+1)^2 and the gradient of
/// the unnormalised direction d (= mean - camera centre), given |d| = `dn` and d / |d| = `dir`.
/// (The scalar reference's form; the backward runs the same operations on lane arrays in
/// `gauss_block`.)
#[cfg(test)]
#[inline]
pub(crate) fn sh_vjp(
    degree: u8,
    dir: [f32; 3],
    dn: f32,
    coef: impl Fn(usize) -> [f32; 3],
    g: [f32; 3],
    v_coef: &mut [[f32; 3]; 16],
) -> [f32; 3] {
    let mut b = [0.0f32; 16];
    sh::basis(degree, dir, &mut b);
    let nb = (degree as usize + 1) * (degree as usize + 1);
    for k in 0..nb {
        v_coef[k] = [b[k] * g[0], b[k] * g[1], b[k] * g[2]];
    }
    if degree == 0 || dn <= 0.0 {
        return [0.0; 3];
    }
    let mut db = [[0.0f32; 3]; 16];
    basis_grad(degree, dir, &mut db);
    let mut v_hat = [0.0f32; 3];
    for (k, dbk) in db.iter().enumerate().take(nb).skip(1) {
        let c = coef(k);
        let w = c[0] * g[0] + c[1] * g[1] + c[2] * g[2];
        for a in 0..3 {
            v_hat[a] += w * dbk[a];
        }
    }
    // d/dd of d / |d|: (I - dir dir^T) / |d|
    let dot = v_hat[0] * dir[0] + v_hat[1] * dir[1] + v_hat[2] * dir[2];
    [
        (v_hat[0] - dot * dir[0]) / dn,
        (v_hat[1] - dot * dir[1]) / dn,
        (v_hat[2] - dot * dir[2]) / dn,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The basis gradient against central differences of the basis in float64 terms.
    #[test]
    fn basis_grad_matches_finite_differences() {
        let dirs = [[0.3f32, -0.5, 0.8], [-0.9, 0.1, 0.2], [0.05, 0.7, -0.6]];
        for d in dirs {
            let mut g = [[0.0f32; 3]; 16];
            basis_grad(3, d, &mut g);
            for a in 0..3 {
                let h = 1e-3f32;
                let (mut p, mut m) = (d, d);
                p[a] += h;
                m[a] -= h;
                let (mut bp, mut bm) = ([0.0f32; 16], [0.0f32; 16]);
                sh::basis(3, p, &mut bp);
                sh::basis(3, m, &mut bm);
                for k in 0..16 {
                    let fd = (bp[k] as f64 - bm[k] as f64) / (2.0 * h as f64);
                    assert!(
                        (fd - g[k][a] as f64).abs() < 2e-3,
                        "basis {k} axis {a}: {fd} vs {}",
                        g[k][a]
                    );
                }
            }
        }
    }
}
