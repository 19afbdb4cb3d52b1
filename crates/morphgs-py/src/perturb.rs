//! `_perturb` and `_artifacts`: the native halves of `morphgs.perturb` and of the strength
//! families' sparse-view ops (the Python side resolves configs).
use numpy::{
    IntoPyArray, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray3, PyReadonlyArray4,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use splat_core::perturb::artifacts::{self, ArtifactParams, TrainImages};
use splat_core::perturb::haze;
use splat_core::perturb::popping;
use splat_core::perturb::shatter::{self, ShatterParams, Views};
use splat_core::perturb::veil;
use splat_core::perturb::PerturbParams;

use crate::errors::detach;
use crate::render::{cameras_from, slice_of};
use crate::scene::PyGaussianScene;

fn extras_refs<'a>(
    extras: &'a [(String, PyReadonlyArray1<'_, f32>)],
) -> PyResult<Vec<(&'a str, &'a [f32])>> {
    extras
        .iter()
        .map(|(n, a)| Ok((n.as_str(), a.as_slice()?)))
        .collect::<Result<_, numpy::AsSliceError>>()
        .map_err(|e| PyValueError::new_err(e.to_string()))
}

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
///     keep: an (N,) boolean mask of rows to remove besides pruning (false: removed), as
///         `_artifacts` returns for its holes; every other row's noise is unchanged by it.
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
                    rotation_angle = None, keep = None))]
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
    keep: Option<PyReadonlyArray1<'py, bool>>,
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
    let mask = match &keep {
        Some(k) => Some(slice_of(k, "keep")?),
        None => None,
    };
    if let Some(m) = mask {
        if m.len() != n {
            return Err(PyValueError::new_err(format!(
                "keep must hold one value per Gaussian ({n}), got {}",
                m.len()
            )));
        }
    }
    // Without pruning, only the arrays an enabled op writes are new; the output shares the
    // others (sh_rest, extras, ...) with the input, which is safe as scene arrays are read-only.
    let changed = if mask.is_some_and(|m| m.iter().any(|&k| !k)) {
        None
    } else {
        detach(py, || {
            crate::pool::install(|| splat_core::perturb::perturb_changed(&view, &params, seed))
        })?
    };
    let (out, keep) = match changed {
        Some(c) => (
            scene.with_arrays(py, c.means, c.quats, c.log_scales, c.opacity_logits, c.sh0)?,
            vec![true; n],
        ),
        None => {
            let extras = scene.extras_readonly(py)?;
            let extras_ref = extras_refs(&extras)?;
            let (out, keep) = detach(py, || {
                crate::pool::install(|| match mask {
                    Some(m) => {
                        splat_core::perturb::perturb_masked(&view, &extras_ref, &params, seed, m)
                    }
                    None => splat_core::perturb::perturb(&view, &extras_ref, &params, seed),
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

/// Apply the sparse-view ops (depth slide, view-dependent colour, needles, holes, dilation,
/// floaters; `splat_core::perturb::artifacts`) from a set of virtual training cameras.
///
/// Prefer `morphgs.strength.Strength.apply`, which resolves strengths and renders the images.
///
/// Args:
///     scene: the input scene (never modified).
///     depth, view_color, needles, holes, dilate, floaters: the ops' parameters (None or 0
///         disables one); hole_size: the hole grid's cell edge in units of the scene extent.
///     world_to_camera, K, width, height: the training cameras, (T,4,4) and (T,3,3).
///     images, depth: None, or their clean renders, (T,H,W,3) and (T,H,W) float32 (the
///         floaters' colours; which Gaussians each view sees, not behind its surface).
///     seed: the seed of the counter-based generator.
///
/// Returns:
///     (scene, keep): the scene (the input rows, then the floaters) and its (M,) keep mask
///     (false: in a hole), for `_perturb(..., keep=)`.
///
/// Raises:
///     ValueError: a parameter is invalid, cameras are needed but none are given, the images
///         do not match the cameras (the message names it).
#[pyfunction]
#[pyo3(signature = (scene, *, depth, view_color, needles, holes, hole_size, dilate, floaters,
                    world_to_camera, K, width, height, images, depth_maps, seed))]
#[allow(non_snake_case)]
fn _artifacts<'py>(
    py: Python<'py>,
    scene: &PyGaussianScene,
    depth: Option<f32>,
    view_color: Option<f32>,
    needles: Option<f32>,
    holes: Option<f32>,
    hole_size: f32,
    dilate: Option<f32>,
    floaters: Option<f32>,
    world_to_camera: PyReadonlyArray3<'py, f64>,
    K: PyReadonlyArray3<'py, f64>,
    width: u32,
    height: u32,
    images: Option<PyReadonlyArray4<'py, f32>>,
    depth_maps: Option<PyReadonlyArray3<'py, f32>>,
    seed: u64,
) -> PyResult<Bound<'py, PyTuple>> {
    let params = ArtifactParams {
        depth,
        view_color,
        needles,
        holes,
        hole_size,
        dilate,
        floaters,
    };
    let cams = cameras_from(&world_to_camera, &K, width, height, 0.01, 1e10)?;
    let maps = match (&images, &depth_maps) {
        (Some(a), Some(d)) => {
            let (sh, dh) = (a.shape(), d.shape());
            let t = cams.len();
            if sh != [t, height as usize, width as usize, 3]
                || dh != [t, height as usize, width as usize]
            {
                return Err(PyValueError::new_err(format!(
                    "images must be ({t}, {height}, {width}, 3) and depth_maps ({t}, {height}, {width}), one \
                     render per training camera, got {sh:?} and {dh:?}"
                )));
            }
            Some((slice_of(a, "images")?, slice_of(d, "depth_maps")?))
        }
        (None, None) => None,
        _ => {
            return Err(PyValueError::new_err(
                "give both images and depth_maps, or neither",
            ))
        }
    };
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    let extras = scene.extras_readonly(py)?;
    let extras_ref = extras_refs(&extras)?;
    let (out, keep) = detach(py, || {
        crate::pool::install(|| {
            let im = maps.map(|(rgb, depth)| TrainImages {
                rgb,
                depth,
                width,
                height,
            });
            artifacts::apply(&view, &extras_ref, &params, &cams, im, seed)
        })
    })?;
    let out = Bound::new(py, PyGaussianScene::from_core(py, out)?)?.into_any();
    PyTuple::new(py, [out, keep.into_pyarray(py).into_any()])
}

/// Draw the popping caps (`splat_core::perturb::popping`) of every Gaussian of a scene.
///
/// Prefer `morphgs.strength.Strength.apply` (op "popping"), which resolves the strength.
///
/// Args:
///     scene: the scene whose rows get caps (never modified).
///     popping: the fraction p: a Gaussian of weight w (opacity x size, 1 for a median-sized
///         opaque one) pops with probability 1 - (1 - p)^w.
///     world_to_camera, K, width, height: the training cameras in path order, (T,4,4), (T,3,3).
///     seed: the seed of the counter-based generator.
///
/// Returns:
///     The scene (its arrays shared) with the extras popping_x, popping_y, popping_z (the cap
///     axes) and popping_h (cap heights, 0: never hidden), which `_render` honours.
///
/// Raises:
///     ValueError: a fraction outside [0, 1] or no cameras (named).
#[pyfunction]
#[pyo3(signature = (scene, *, popping, world_to_camera, K, width, height, seed))]
#[allow(non_snake_case)]
fn _popping(
    py: Python<'_>,
    scene: &PyGaussianScene,
    popping: f32,
    world_to_camera: PyReadonlyArray3<'_, f64>,
    K: PyReadonlyArray3<'_, f64>,
    width: u32,
    height: u32,
    seed: u64,
) -> PyResult<PyGaussianScene> {
    let cams = cameras_from(&world_to_camera, &K, width, height, 0.01, 1e10)?;
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    let caps = detach(py, || popping::caps(&view, &cams, popping, seed))?;
    let names = splat_core::raster::caps::EXTRAS.map(str::to_owned);
    scene.with_extras(py, names.into_iter().zip(caps).collect())
}

/// Rows of three floats as one flat vector (for an (N, 3) array).
fn flat3(v: &[[f32; 3]]) -> Vec<f32> {
    v.iter().flatten().copied().collect()
}

/// The training cameras of images of shape `(V, H, W, 3)`: one per image, at the images' size.
#[allow(non_snake_case)]
fn view_cameras(
    world_to_camera: &PyReadonlyArray3<'_, f64>,
    K: &PyReadonlyArray3<'_, f64>,
    shape: &[usize],
) -> PyResult<Vec<splat_core::camera::Camera>> {
    let cams = cameras_from(
        world_to_camera,
        K,
        shape[2] as u32,
        shape[1] as u32,
        0.01,
        1e10,
    )?;
    if cams.len() != shape[0] {
        return Err(PyValueError::new_err(format!(
            "one camera per training view: {} cameras for {} images",
            cams.len(),
            shape[0]
        )));
    }
    Ok(cams)
}

/// Which of `n` Gaussians the shatter op removes at `value` (`splat_core::perturb::shatter`).
///
/// Prefer `morphgs.strength.Strength.apply` (op "shatter").
///
/// Returns:
///     (n,) bool, true: removed (each with probability 1 - exp(-value); a larger value removes a
///     superset).
///
/// Raises:
///     ValueError: a value that is not a finite number >= 0.
#[pyfunction]
#[pyo3(signature = (n, *, value, seed))]
fn _shatter_removal(py: Python<'_>, n: usize, value: f32, seed: u64) -> PyResult<Bound<'_, PyAny>> {
    if !(value.is_finite() && value >= 0.0) {
        return Err(PyValueError::new_err(format!(
            "shatter value must be a finite number >= 0, got {value}"
        )));
    }
    let gone = detach(py, || Ok(shatter::removal(n, value, seed)))?;
    Ok(gone.into_pyarray(py).into_any())
}

/// The shatter op's fragments (`splat_core::perturb::shatter::fragments`): small Gaussians on the
/// rays of the training views' pixels at wrong depths, coloured to agree with every training
/// view that sees them.
///
/// Prefer `morphgs.strength.Strength.apply` (op "shatter"), which renders the training views.
///
/// Args:
///     value: the op's value v >= 0.
///     images, depth, alpha: the training views' clean renders, (T,H,W,3), (T,H,W), (T,H,W)
///         float32.
///     world_to_camera, K: the training cameras, (T,4,4) and (T,3,3) float64.
///     removed: how many Gaussians the op removed (the fragment budget is 4 per removal).
///     seed: the seed of the counter-based generator.
///     ridge, max_error, drop: the colour fit's band-1 ridge, the largest RMS colour error a kept
///         fragment may have in a view, and whether a fragment that fails is dropped (else put
///         back on the surface).
///
/// Returns:
///     A dict of float32 arrays means (N,3), log_scales (N,3), opacity_logits (N,), sh0 (N,3),
///     sh1 (N,3,3) (band-1 coefficients by channel), quats (N,4) (identity), and view (N,) int32.
///
/// Raises:
///     ValueError: a bad parameter or maps that do not match the cameras (named).
#[pyfunction]
#[pyo3(signature = (value, images, depth, alpha, world_to_camera, K, removed, *, seed, ridge = 1.0,
                    max_error = 0.08, drop = true))]
#[allow(non_snake_case, clippy::too_many_arguments)]
fn _shatter<'py>(
    py: Python<'py>,
    value: f32,
    images: PyReadonlyArray4<'py, f32>,
    depth: PyReadonlyArray3<'py, f32>,
    alpha: PyReadonlyArray3<'py, f32>,
    world_to_camera: PyReadonlyArray3<'py, f64>,
    K: PyReadonlyArray3<'py, f64>,
    removed: usize,
    seed: u64,
    ridge: f64,
    max_error: f64,
    drop: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let (ish, dsh, ash) = (images.shape(), depth.shape(), alpha.shape());
    if ish.len() != 4 || ish[3] != 3 || dsh != &ish[..3] || ash != &ish[..3] {
        return Err(PyValueError::new_err(format!(
            "images must be (T,H,W,3) and depth and alpha (T,H,W), got {ish:?}, {dsh:?} and {ash:?}"
        )));
    }
    let cams = view_cameras(&world_to_camera, &K, ish)?;
    let views = Views {
        rgb: slice_of(&images, "images")?,
        depth: slice_of(&depth, "depth")?,
        alpha: slice_of(&alpha, "alpha")?,
    };
    let params = ShatterParams {
        value,
        ridge,
        max_error,
        drop,
    };
    let f = detach(py, || {
        shatter::fragments(&params, &cams, views, removed, seed)
    })?;
    let n = f.len();
    let d = PyDict::new(py);
    d.set_item("means", flat3(&f.means).into_pyarray(py).reshape([n, 3])?)?;
    let scales: Vec<f32> = f.log_scales.iter().flat_map(|&s| [s; 3]).collect();
    d.set_item("log_scales", scales.into_pyarray(py).reshape([n, 3])?)?;
    d.set_item("opacity_logits", f.opacity_logits.into_pyarray(py))?;
    d.set_item("sh0", flat3(&f.sh0).into_pyarray(py).reshape([n, 3])?)?;
    let sh1: Vec<f32> = f.sh1.iter().flatten().flatten().copied().collect();
    d.set_item("sh1", sh1.into_pyarray(py).reshape([n, 3, 3])?)?;
    let quats: Vec<f32> = (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
    d.set_item("quats", quats.into_pyarray(py).reshape([n, 4])?)?;
    let view: Vec<i32> = f.view.iter().map(|&v| v as i32).collect();
    d.set_item("view", view.into_pyarray(py))?;
    Ok(d)
}

/// The haze op's Gaussians (`splat_core::perturb::haze`): faint, large Gaussians beside the
/// training cameras, as a sparse fit leaves them (docs/artifacts.md, "Haze").
///
/// Prefer `morphgs.strength.Strength.apply` (op "haze").
///
/// Args:
///     world_to_camera, K: the training cameras, (V,4,4) and (V,3,3) float64, V >= 2.
///     width, height: their image size.
///     value: the op's value v >= 0 (round(250 v V) Gaussians).
///     seed: the seed of the counter-based generator.
///
/// Returns:
///     A dict of float32 arrays means (N,3), quats (N,4) (w, x, y, z), log_scales (N,3) (largest
///     first), opacity_logits (N,), sh0 (N,3); a larger value gives the same first rows and more.
///
/// Raises:
///     ValueError: a bad value, fewer than two cameras or bad camera matrices (named).
#[pyfunction]
#[pyo3(signature = (world_to_camera, K, width, height, *, value, seed))]
#[allow(non_snake_case)]
fn _haze<'py>(
    py: Python<'py>,
    world_to_camera: PyReadonlyArray3<'py, f64>,
    K: PyReadonlyArray3<'py, f64>,
    width: u32,
    height: u32,
    value: f32,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let cams = cameras_from(&world_to_camera, &K, width, height, 0.01, 1e10)?;
    let h = detach(py, || haze::haze(&cams, value, seed))?;
    appended(py, &h)
}

/// The rows an appending op (haze, veil) made, as a dict of float32 arrays.
fn appended<'py>(py: Python<'py>, h: &haze::Haze) -> PyResult<Bound<'py, PyDict>> {
    let n = h.len();
    let d = PyDict::new(py);
    d.set_item("means", flat3(&h.means).into_pyarray(py).reshape([n, 3])?)?;
    let quats: Vec<f32> = h.quats.iter().flatten().copied().collect();
    d.set_item("quats", quats.into_pyarray(py).reshape([n, 4])?)?;
    d.set_item(
        "log_scales",
        flat3(&h.log_scales).into_pyarray(py).reshape([n, 3])?,
    )?;
    d.set_item("opacity_logits", h.opacity_logits.clone().into_pyarray(py))?;
    d.set_item("sh0", flat3(&h.sh0).into_pyarray(py).reshape([n, 3])?)?;
    Ok(d)
}

/// The veil op's Gaussians (`splat_core::perturb::veil`): faint, wide Gaussians placed where every
/// training view that sees them shows their own colour (docs/artifacts.md, "Veil").
///
/// Prefer `morphgs.strength.Strength.apply` (op "veil").
///
/// Args:
///     world_to_camera, K: the training cameras, (V,4,4) and (V,3,3) float64, V >= 2.
///     images, depth: their clean renders, (V,H,W,3) and (V,H,W) float32 (the expected camera z,
///         0 where nothing is hit).
///     value: the op's value v >= 0 (round(100 v V) Gaussians at most).
///     seed: the seed of the counter-based generator.
///
/// Returns:
///     A dict of float32 arrays means (N,3), quats (N,4) (w, x, y, z), log_scales (N,3),
///     opacity_logits (N,), sh0 (N,3); a larger value gives the same first rows and more.
///
/// Raises:
///     ValueError: a bad value, fewer than two cameras, bad camera matrices or maps that do not
///         match them.
#[pyfunction]
#[pyo3(signature = (world_to_camera, K, images, depth, *, value, seed))]
#[allow(non_snake_case)]
fn _veil<'py>(
    py: Python<'py>,
    world_to_camera: PyReadonlyArray3<'py, f64>,
    K: PyReadonlyArray3<'py, f64>,
    images: PyReadonlyArray4<'py, f32>,
    depth: PyReadonlyArray3<'py, f32>,
    value: f32,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let (ish, dsh) = (images.shape(), depth.shape());
    if ish.len() != 4 || ish[3] != 3 || dsh != &ish[..3] {
        return Err(PyValueError::new_err(format!(
            "images must be (V,H,W,3) and depth (V,H,W), got {ish:?} and {dsh:?}"
        )));
    }
    let cams = view_cameras(&world_to_camera, &K, ish)?;
    let views = veil::Views {
        rgb: slice_of(&images, "images")?,
        depth: slice_of(&depth, "depth")?,
    };
    let h = detach(py, || veil::veil(&cams, views, value, seed))?;
    appended(py, &h)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_perturb, m)?)?;
    m.add_function(wrap_pyfunction!(_artifacts, m)?)?;
    m.add_function(wrap_pyfunction!(_popping, m)?)?;
    m.add_function(wrap_pyfunction!(_shatter_removal, m)?)?;
    m.add_function(wrap_pyfunction!(_shatter, m)?)?;
    m.add_function(wrap_pyfunction!(_haze, m)?)?;
    m.add_function(wrap_pyfunction!(_veil, m)?)?;
    Ok(())
}
