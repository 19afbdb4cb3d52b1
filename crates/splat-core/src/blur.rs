//! Separable Gaussian blur of image stacks: the paper's "2D Render Blur" baseline (SPEC §5).
//!
//! Images are `(frames, height, width, channels)` float32, row-major. The kernel is the sampled
//! Gaussian exp(-x^2 / (2 sigma^2)) for |x| <= ceil(3 sigma), normalised to sum 1; borders
//! replicate the edge pixel. Every output value is a fixed-order sum, so results are identical
//! for any thread count.
use rayon::prelude::*;

use crate::{Error, Result};

/// Largest accepted sigma in pixels (kernel radius 768).
pub const MAX_SIGMA: f64 = 256.0;

/// The normalised kernel for `sigma` (radius ceil(3 sigma)); `[1.0]` for sigma == 0.
pub fn gaussian_kernel(sigma: f64) -> Result<Vec<f32>> {
    if !sigma.is_finite() || !(0.0..=MAX_SIGMA).contains(&sigma) {
        return Err(Error::InvalidArgument(format!(
            "blur sigma must be in [0, {MAX_SIGMA}] pixels, got {sigma}"
        )));
    }
    if sigma == 0.0 {
        return Ok(vec![1.0]);
    }
    let r = (3.0 * sigma).ceil() as i64;
    let w: Vec<f64> = (-r..=r)
        .map(|x| (-((x * x) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = w.iter().sum();
    Ok(w.iter().map(|v| (v / sum) as f32).collect())
}

/// Blur `data` (frames x height x width x channels) with a Gaussian of `sigma` pixels.
pub fn gaussian_blur(
    data: &[f32],
    frames: usize,
    height: usize,
    width: usize,
    channels: usize,
    sigma: f64,
) -> Result<Vec<f32>> {
    let row = width
        .checked_mul(channels)
        .ok_or_else(|| Error::InvalidArgument("image too large".into()))?;
    let total = frames
        .checked_mul(height)
        .and_then(|n| n.checked_mul(row))
        .ok_or_else(|| Error::InvalidArgument("image stack too large".into()))?;
    if data.len() != total {
        return Err(Error::InvalidArgument(format!(
            "blur: {} values for {frames}x{height}x{width}x{channels}",
            data.len()
        )));
    }
    let kernel = gaussian_kernel(sigma)?;
    if kernel.len() == 1 || total == 0 {
        return Ok(data.to_vec());
    }
    let r = kernel.len() / 2;
    // Horizontal pass: each row padded by replicating its edge pixels, then a contiguous axpy
    // per tap.
    let mut tmp = vec![0.0f32; total];
    tmp.par_chunks_mut(row)
        .zip(data.par_chunks(row))
        .for_each_init(
            || vec![0.0f32; (width + 2 * r) * channels],
            |padded, (out, src)| {
                let (first, last) = (&src[..channels], &src[row - channels..]);
                for i in 0..r {
                    padded[i * channels..(i + 1) * channels].copy_from_slice(first);
                    let j = r + width + i;
                    padded[j * channels..(j + 1) * channels].copy_from_slice(last);
                }
                padded[r * channels..(r + width) * channels].copy_from_slice(src);
                out.fill(0.0);
                for (k, &wk) in kernel.iter().enumerate() {
                    let s = &padded[k * channels..k * channels + row];
                    for (o, v) in out.iter_mut().zip(s) {
                        *o += wk * v;
                    }
                }
            },
        );
    // Vertical pass: output row y of frame f sums rows clamp(y + k - r) of the same frame.
    let mut out = vec![0.0f32; total];
    let frame_len = height * row;
    out.par_chunks_mut(row).enumerate().for_each(|(idx, dst)| {
        let (f, y) = (idx / height, idx % height);
        let base = f * frame_len;
        dst.fill(0.0);
        for (k, &wk) in kernel.iter().enumerate() {
            let yy = (y + k).saturating_sub(r).min(height - 1);
            let s = &tmp[base + yy * row..base + (yy + 1) * row];
            for (o, v) in dst.iter_mut().zip(s) {
                *o += wk * v;
            }
        }
    });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernel_is_normalised_and_symmetric() {
        let k = gaussian_kernel(2.0).unwrap_or_default();
        assert_eq!(k.len(), 13);
        let s: f32 = k.iter().sum();
        assert!((s - 1.0).abs() < 1e-6);
        assert_eq!(k[0], k[12]);
    }

    #[test]
    fn constant_image_stays_constant_and_impulse_spreads_to_kernel() {
        let (h, w) = (9, 11);
        let flat = vec![0.25f32; h * w];
        let out = gaussian_blur(&flat, 1, h, w, 1, 1.5).unwrap_or_default();
        assert!(out.iter().all(|v| (v - 0.25).abs() < 1e-6));
        let mut imp = vec![0.0f32; h * w];
        imp[4 * w + 5] = 1.0;
        let out = gaussian_blur(&imp, 1, h, w, 1, 1.0).unwrap_or_default();
        let k = gaussian_kernel(1.0).unwrap_or_default();
        // separable: out[4+dy][5+dx] = k[r+dy] * k[r+dx]
        for dy in -3i64..=3 {
            for dx in -3i64..=3 {
                let v = out[((4 + dy) as usize) * w + (5 + dx) as usize];
                let e = k[(3 + dy) as usize] * k[(3 + dx) as usize];
                assert!((v - e).abs() < 1e-7, "{dy} {dx} {v} {e}");
            }
        }
    }

    #[test]
    fn bad_sigma_and_size_are_errors() {
        assert!(gaussian_kernel(f64::NAN).is_err());
        assert!(gaussian_kernel(-1.0).is_err());
        assert!(gaussian_blur(&[0.0; 5], 1, 2, 2, 1, 1.0).is_err());
    }
}
