//! gaussian_blur: the 2D blur baseline on image stacks.
use numpy::{IntoPyArray, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::errors::detach;

/// Separable Gaussian blur of an image or image stack (the paper's "2D Render Blur" baseline).
///
/// Kernel: the sampled Gaussian of `sigma` pixels over radius ceil(3 sigma), normalised; borders
/// replicate the edge pixel; runs in parallel with identical results for any thread count.
///
/// Args:
///     images: float32 array (H,W), (H,W,C) or (F,H,W,C) (any memory layout).
///     sigma: standard deviation in pixels, in [0, 256]; 0 returns a copy.
///
/// Returns:
///     A new float32 array of the same shape.
///
/// Raises:
///     ValueError: bad shape or sigma out of range.
#[pyfunction]
#[pyo3(signature = (images, sigma))]
fn gaussian_blur<'py>(
    py: Python<'py>,
    images: PyReadonlyArrayDyn<'py, f32>,
    sigma: f64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let shape = images.shape().to_vec();
    let (f, h, w, c) = match shape.as_slice() {
        [h, w] => (1, *h, *w, 1),
        [h, w, c] => (1, *h, *w, *c),
        [f, h, w, c] => (*f, *h, *w, *c),
        _ => {
            return Err(PyValueError::new_err(format!(
                "images must have shape (H,W), (H,W,C) or (F,H,W,C), got {shape:?}"
            )))
        }
    };
    // as_slice also accepts Fortran order, whose memory is not row-major: copy other layouts
    // into logical (row-major) order instead of reading them wrongly
    let copied: Vec<f32>;
    let data = if images.is_c_contiguous() {
        images
            .as_slice()
            .map_err(|_| PyValueError::new_err("images must be C-contiguous"))?
    } else {
        copied = images.as_array().iter().copied().collect();
        &copied
    };
    let out = detach(py, || {
        splat_core::blur::gaussian_blur(data, f, h, w, c, sigma)
    })?;
    let arr = out.into_pyarray(py);
    arr.reshape(shape)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(gaussian_blur, m)?)?;
    Ok(())
}
