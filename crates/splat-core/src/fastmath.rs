//! Branch-free float32 `ln`, `exp` and quarter-turn `sin`/`cos` from `+ - * /` and bit
//! manipulation only.
//!
//! They vectorise (libm's do not), and they are deterministic everywhere: IEEE basic operations
//! are exactly rounded and no fused multiply-add is used, so a SIMD lane and the scalar path give
//! the same bits on every platform. Accuracy is about one ulp over the ranges documented below.

/// ln 2 split for Cody-Waite reduction: `n * LN2_HI` is exact for |n| < 2^9.
const LN2_HI: f32 = f32::from_bits(0x3f31_7180);
const LN2_LO: f32 = f32::from_bits(0x3717_f7d1);

/// Natural log, within 3 ulp (about 1 typically) for positive normal floats; `+inf` gives `+inf`, NaN gives
/// NaN, zero, negative and subnormal inputs give NaN (callers never pass them).
#[inline(always)]
pub fn ln(x: f32) -> f32 {
    let bits = x.to_bits();
    let mut e = ((bits >> 23) & 0xff) as i32 - 127;
    let mut m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000); // [1, 2)
    let big = m > core::f32::consts::SQRT_2;
    m = if big { m * 0.5 } else { m };
    e += big as i32;
    // ln m = 2 atanh(s), s = (m - 1) / (m + 1), |s| <= 0.1716
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let p = 1.0 + s2 * (1.0 / 3.0 + s2 * (0.2 + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0))));
    let ef = e as f32;
    let v = ef * LN2_HI + (ef * LN2_LO + 2.0 * s * p);
    let normal = (f32::MIN_POSITIVE..f32::INFINITY).contains(&x);
    if normal {
        v
    } else if x == f32::INFINITY {
        x
    } else {
        f32::NAN
    }
}

/// e^x to about 1 ulp; overflows to `+inf` above 88.72, underflows gradually to 0; NaN stays NaN.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    const LOG2E: f32 = core::f32::consts::LOG2_E;
    const SHIFTER: f32 = 12_582_912.0; // 1.5 * 2^23: adding it rounds to an integer
    let xc = x.clamp(-104.0, 89.0);
    let t = xc * LOG2E + SHIFTER;
    let n = t - SHIFTER;
    let ni = t.to_bits() as i32 - SHIFTER.to_bits() as i32;
    let r = (xc - n * LN2_HI) - n * LN2_LO; // |r| <= 0.35
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    // 2^n as two factors so that n in [-150, 129] never leaves the normal exponent range
    let n1 = ni >> 1;
    let n2 = ni - n1;
    let f1 = f32::from_bits(((n1 + 127) as u32) << 23);
    let f2 = f32::from_bits(((n2 + 127) as u32) << 23);
    let v = p * f1 * f2;
    if x.is_nan() {
        x
    } else {
        v
    }
}

/// (sin x, cos x) for x in [0, pi/2], Taylor polynomials to degree 11 / 12 (error < 1e-7).
#[inline(always)]
pub fn sin_cos_quarter(x: f32) -> (f32, f32) {
    let x2 = x * x;
    let s = x
        * (1.0
            + x2 * (-1.0 / 6.0
                + x2 * (1.0 / 120.0
                    + x2 * (-1.0 / 5040.0 + x2 * (1.0 / 362_880.0 + x2 * (-1.0 / 39_916_800.0))))));
    let c = 1.0
        + x2 * (-0.5
            + x2 * (1.0 / 24.0
                + x2 * (-1.0 / 720.0
                    + x2 * (1.0 / 40_320.0
                        + x2 * (-1.0 / 3_628_800.0 + x2 * (1.0 / 479_001_600.0))))));
    (s, c)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f32, b: f64) -> f64 {
        let b32 = b as f32;
        let ulp = (f32::from_bits(b32.abs().to_bits() + 1) - b32.abs()) as f64;
        (a as f64 - b).abs() / ulp
    }

    #[test]
    fn ln_is_within_three_ulps_over_the_normal_range() {
        let mut worst = 0.0f64;
        let mut bits = f32::MIN_POSITIVE.to_bits();
        while bits < f32::MAX.to_bits() {
            let x = f32::from_bits(bits);
            let want = (x as f64).ln();
            if want.abs() > 1e-3 {
                worst = worst.max(ulps(ln(x), want));
            } else {
                assert!((ln(x) as f64 - want).abs() < 1e-9, "{x}");
            }
            bits += 9_973;
        }
        assert!(worst <= 3.0, "worst {worst} ulp");
        assert_eq!(ln(1.0), 0.0);
        assert_eq!(ln(f32::INFINITY), f32::INFINITY);
        assert!(ln(f32::NAN).is_nan() && ln(0.0).is_nan() && ln(-1.0).is_nan());
    }

    #[test]
    fn exp_is_within_two_ulps_and_saturates() {
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x < 88.7 {
            worst = worst.max(ulps(exp(x), (x as f64).exp()));
            x += 0.001_37;
        }
        assert!(worst <= 2.0, "worst {worst} ulp");
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(89.0), f32::INFINITY);
        assert_eq!(exp(1000.0), f32::INFINITY);
        assert_eq!(exp(-1000.0), 0.0);
        assert!(exp(-100.0) > 0.0 && exp(-100.0) < 1e-43);
        assert!(exp(f32::NAN).is_nan());
    }

    #[test]
    fn sin_cos_match_std() {
        let mut worst = 0.0f64;
        for k in 0..=100_000u32 {
            let x = k as f32 / 100_000.0 * core::f32::consts::FRAC_PI_2;
            let (s, c) = sin_cos_quarter(x);
            worst = worst
                .max((s as f64 - (x as f64).sin()).abs())
                .max((c as f64 - (x as f64).cos()).abs());
        }
        assert!(worst < 2e-7, "sin/cos error {worst}");
    }
}
