//! Spherical-harmonic colour (SPEC §4 step 5): Sloan's real SH basis as gsplat and INRIA
//! evaluate it, degrees 0-3, along the unit view direction.

/// Evaluate the first `(degree+1)^2` SH basis functions at the unit direction (x, y, z); the
/// other entries of `out` are left as they are.
#[inline]
pub fn basis(degree: u8, dir: [f32; 3], out: &mut [f32; 16]) {
    let mut b = [[0.0f32; 1]; 16];
    basis_lanes(degree, &[[dir[0]], [dir[1]], [dir[2]]], &mut b);
    let n = (degree as usize + 1) * (degree as usize + 1);
    for (o, v) in out.iter_mut().zip(&b).take(n) {
        *o = v[0];
    }
}

/// [`basis`] for `L` directions at once, lane l of `dir` giving lane l of every basis function
/// (short loops over lanes that vectorise; the same operations per lane, so the same bits).
/// Entries past the degree's `(degree+1)^2` are left as they are.
#[inline(always)]
pub(crate) fn basis_lanes<const L: usize>(
    degree: u8,
    dir: &[[f32; L]; 3],
    out: &mut [[f32; L]; 16],
) {
    let [xs, ys, zs] = dir;
    out[0] = [0.282_094_8; L];
    if degree == 0 {
        return;
    }
    let a1 = -0.488_602_52_f32;
    for l in 0..L {
        let (x, y, z) = (xs[l], ys[l], zs[l]);
        out[1][l] = a1 * y;
        out[2][l] = -a1 * z;
        out[3][l] = a1 * x;
    }
    if degree == 1 {
        return;
    }
    for l in 0..L {
        let (x, y, z) = (xs[l], ys[l], zs[l]);
        let z2 = z * z;
        let tmp_b = -1.092_548_4 * z;
        let tmp_a = 0.546_274_24_f32;
        let c1 = x * x - y * y;
        let s1 = 2.0 * x * y;
        out[4][l] = tmp_a * s1;
        out[5][l] = tmp_b * y;
        out[6][l] = 0.946_174_7 * z2 - 0.315_391_57;
        out[7][l] = tmp_b * x;
        out[8][l] = tmp_a * c1;
    }
    if degree == 2 {
        return;
    }
    for l in 0..L {
        let (x, y, z) = (xs[l], ys[l], zs[l]);
        let z2 = z * z;
        let c1 = x * x - y * y;
        let s1 = 2.0 * x * y;
        let tmp_c = -2.285_229 * z2 + 0.457_045_8;
        let tmp_b = 1.445_305_7 * z;
        let tmp_a = -0.590_043_6_f32;
        let c2 = x * c1 - y * s1;
        let s2 = x * s1 + y * c1;
        out[9][l] = tmp_a * s2;
        out[10][l] = tmp_b * s1;
        out[11][l] = tmp_c * y;
        out[12][l] = z * (1.865_881_7 * z2 - 1.119_529);
        out[13][l] = tmp_c * x;
        out[14][l] = tmp_b * c1;
        out[15][l] = tmp_a * c2;
    }
}

/// RGB colour of one Gaussian: sum over bases of basis * coefficient, + 0.5, clamped at 0.
///
/// `rest` holds the Gaussian's higher bands, `(K,3)` basis-major; only the first
/// `(degree+1)^2 - 1` of them are used.
#[inline]
pub fn color(degree: u8, dir: [f32; 3], sh0: &[f32], rest: &[f32]) -> [f32; 3] {
    let mut b = [0.0f32; 16];
    basis(degree, dir, &mut b);
    color_from_basis(degree, &b, [sh0[0], sh0[1], sh0[2]], rest)
}

/// [`color`] from the basis values `b` (as [`basis`] gives them).
#[inline(always)]
pub(crate) fn color_from_basis(degree: u8, b: &[f32; 16], sh0: [f32; 3], rest: &[f32]) -> [f32; 3] {
    let n = (degree as usize + 1) * (degree as usize + 1);
    let mut rgb = [b[0] * sh0[0], b[0] * sh0[1], b[0] * sh0[2]];
    for k in 1..n {
        let c = &rest[(k - 1) * 3..k * 3];
        for ch in 0..3 {
            rgb[ch] += b[k] * c[ch];
        }
    }
    rgb.map(|v| (v + 0.5).max(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn degree_zero_is_the_dc_colour() {
        let rgb = color(0, [0.0, 0.0, 1.0], &[1.0, 0.0, -5.0], &[]);
        assert!((rgb[0] - (0.5 + 0.282_094_8)).abs() < 1e-7);
        assert_eq!(rgb[1], 0.5);
        assert_eq!(rgb[2], 0.0, "clamped at zero");
    }

    #[test]
    fn band_one_flips_with_the_view_direction() {
        // coefficient on basis 3 (x): colour differs between +x and -x views, symmetric about 0.5
        let mut rest = [0.0f32; 9];
        rest[6] = 0.5;
        let a = color(1, [1.0, 0.0, 0.0], &[0.0; 3], &rest);
        let b = color(1, [-1.0, 0.0, 0.0], &[0.0; 3], &rest);
        assert!(((a[0] - 0.5) + (b[0] - 0.5)).abs() < 1e-7);
        assert!(a[0] < 0.5);
    }
}
