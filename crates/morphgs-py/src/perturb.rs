//! `_perturb`: the native half of `morphgs.perturb` (the Python side resolves configs).
use numpy::IntoPyArray;
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use splat_core::perturb::PerturbParams;

use crate::errors::detach;
use crate::scene::PyGaussianScene;

/// Perturb a scene with explicit per-operation parameters (None disables an operation).
///
/// Prefer `morphgs.perturb`, which accepts presets and `PerturbConfig`s.
///
/// Args:
///     scene: the input scene (never modified).
///     position_jitter, color_noise, opacity_noise, prune, scale_noise, rotation_noise: the
///         operation parameters of SPEC §2.
///     log_scale_noise, rotation_angle: the strength parameterisation's relative scale noise
///         (op 7, sigma in log space) and isotropic rotation (op 8, RMS angle in radians).
///     seed: the seed of the counter-based generator (0 <= seed < 2**64).
///     return_mask: also return the (N,) boolean keep-mask of the pruning.
///
/// Returns:
///     The perturbed GaussianScene, or (scene, mask) with return_mask. Without pruning, the
///     arrays no enabled operation writes are shared with the input scene (read-only, no copy).
///
/// Raises:
///     ValueError: a parameter is invalid (the message names it).
#[pyfunction]
#[pyo3(signature = (scene, *, position_jitter, color_noise, opacity_noise, prune, scale_noise,
                    rotation_noise, seed, return_mask = false, log_scale_noise = None,
                    rotation_angle = None))]
fn _perturb<'py>(
    py: Python<'py>,
    scene: &PyGaussianScene,
    position_jitter: Option<f32>,
    color_noise: Option<f32>,
    opacity_noise: Option<f32>,
    prune: Option<f32>,
    scale_noise: Option<f32>,
    rotation_noise: Option<f32>,
    seed: u64,
    return_mask: bool,
    log_scale_noise: Option<f32>,
    rotation_angle: Option<f32>,
) -> PyResult<Bound<'py, PyAny>> {
    let params = PerturbParams {
        position_jitter,
        color_noise,
        opacity_noise,
        prune,
        scale_noise,
        rotation_noise,
        log_scale_noise,
        rotation_angle,
    };
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    let n = view.len();
    // Without pruning, only the arrays an enabled op writes are new; the output shares the
    // others (sh_rest, extras, ...) with the input, which is safe as scene arrays are read-only.
    let changed = detach(py, || {
        crate::pool::install(|| splat_core::perturb::perturb_changed(&view, &params, seed))
    })?;
    let (out, keep) = match changed {
        Some(c) => (
            scene.with_arrays(py, c.means, c.quats, c.log_scales, c.opacity_logits, c.sh0)?,
            vec![true; n],
        ),
        None => {
            let extras = scene.extras_readonly(py)?;
            let extras_ref: Vec<(&str, &[f32])> = extras
                .iter()
                .map(|(n, a)| Ok((n.as_str(), a.as_slice()?)))
                .collect::<Result<_, numpy::AsSliceError>>()
                .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?;
            let (out, keep) = detach(py, || {
                crate::pool::install(|| {
                    splat_core::perturb::perturb(&view, &extras_ref, &params, seed)
                })
            })?;
            (PyGaussianScene::from_core(py, out)?, keep)
        }
    };
    let out = Bound::new(py, out)?.into_any();
    if return_mask {
        Ok(PyTuple::new(py, [out, keep.into_pyarray(py).into_any()])?.into_any())
    } else {
        Ok(out)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_perturb, m)?)?;
    Ok(())
}
