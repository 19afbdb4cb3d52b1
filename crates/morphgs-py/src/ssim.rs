//! `_ssim_batch`: the fit's streaming SSIM kernel (`splat_core::fit::ssim`, INRIA 3DGS's
//! variant) over a batch of images, value and gradient, for training losses in torch
//! (`morphgs.metrics.ssim_3dgs`).
use numpy::ndarray::{Array1, Array4};
use numpy::{IntoPyArray, PyArray1, PyArray4, PyReadonlyArray4, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rayon::prelude::*;
use splat_core::fit::ssim::SsimWorkspace;

/// The most values one call takes (2^31: 8 GB of float32 per array).
const MAX_VALUES: usize = 1 << 31;

/// Mean SSIM of each of N images against its target, INRIA 3DGS's variant (11x11 Gaussian
/// window of sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, zero 'same' padding, each channel on its own,
/// the mean over H x W x 3), and with `grad` the gradient of each image's mean SSIM with respect
/// to its prediction. The images run in parallel, each with its own kernel call: the same bits
/// for any thread count and kernel (`MORPHGS_SIMD` picks a lower one, as for rendering).
///
/// Args:
///     pred, target: float32 (N, H, W, 3), C-contiguous, the same shape.
///     grad: also return d ssim_i / d pred_i.
///
/// Returns:
///     (ssim (N,) float64, gradient (N, H, W, 3) float32 or None).
///
/// Raises:
///     ValueError: shapes that differ or are not (N, H, W, 3), an empty image, a layout that
///         is not C-contiguous.
#[pyfunction]
#[pyo3(signature = (pred, target, *, grad = true))]
#[allow(clippy::type_complexity)]
fn _ssim_batch<'py>(
    py: Python<'py>,
    pred: PyReadonlyArray4<'py, f32>,
    target: PyReadonlyArray4<'py, f32>,
    grad: bool,
) -> PyResult<(Bound<'py, PyArray1<f64>>, Option<Bound<'py, PyArray4<f32>>>)> {
    let sh = pred.shape().to_vec();
    if sh[3] != 3 || target.shape() != sh.as_slice() {
        return Err(PyValueError::new_err(format!(
            "pred and target must both be (N, H, W, 3), got {sh:?} and {:?}",
            target.shape()
        )));
    }
    let (n, h, w) = (sh[0], sh[1], sh[2]);
    if h == 0 || w == 0 {
        return Err(PyValueError::new_err(format!(
            "images must be at least 1x1 pixels, got {w}x{h}"
        )));
    }
    let per = h * w * 3;
    if n.saturating_mul(per) > MAX_VALUES {
        return Err(PyValueError::new_err(format!(
            "{n} images of {w}x{h} is more than one call takes ({MAX_VALUES} values); split the batch"
        )));
    }
    let layout = |name: &str| PyValueError::new_err(format!("{name} must be C-contiguous"));
    // as_slice also takes Fortran order, which is not row-major: refuse it
    if !pred.is_c_contiguous() {
        return Err(layout("pred"));
    }
    if !target.is_c_contiguous() {
        return Err(layout("target"));
    }
    let p = pred.as_slice().map_err(|_| layout("pred"))?;
    let t = target.as_slice().map_err(|_| layout("target"))?;
    let simd = crate::render::simd_from_env()?;
    let mut g = if grad {
        vec![0.0f32; n * per]
    } else {
        Vec::new()
    };
    let values: Vec<f64> = py.detach(|| {
        crate::pool::install(|| {
            let one = |i: usize, out: Option<&mut [f32]>| {
                // one band an image: the images are the parallel unit
                let mut ws = SsimWorkspace::default();
                ws.band_rows = h;
                ws.simd = simd;
                let (pi, ti) = (&p[i * per..(i + 1) * per], &t[i * per..(i + 1) * per]);
                ws.ssim(pi, ti, w, h, false, out.map(|o| (o, 1.0)))
            };
            if grad {
                g.par_chunks_mut(per)
                    .enumerate()
                    .map(|(i, o)| one(i, Some(o)))
                    .collect()
            } else {
                (0..n).into_par_iter().map(|i| one(i, None)).collect()
            }
        })
    });
    let vals = Array1::from_vec(values).into_pyarray(py);
    let grads = if grad {
        let a = Array4::from_shape_vec((n, h, w, 3), g)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Some(a.into_pyarray(py))
    } else {
        None
    };
    Ok((vals, grads))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_ssim_batch, m)?)?;
    Ok(())
}
