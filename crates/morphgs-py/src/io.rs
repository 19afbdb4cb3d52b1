//! load / save_ply.
use std::path::PathBuf;

use pyo3::prelude::*;
use splat_core::formats::SpzAxes;
use splat_core::io::LoadOptions;
use splat_core::ply::OnInvalid;

use crate::errors::{detach, MorphgsWarning};
use crate::scene::PyGaussianScene;

fn parse_on_invalid(s: &str) -> PyResult<OnInvalid> {
    match s {
        "error" => Ok(OnInvalid::Error),
        "drop" => Ok(OnInvalid::Drop),
        other => Err(pyo3::exceptions::PyValueError::new_err(format!(
            "on_invalid must be 'error' or 'drop', got '{other}'"
        ))),
    }
}

pub(crate) fn parse_spz_axes(s: &str) -> PyResult<SpzAxes> {
    match s {
        "rdf" => Ok(SpzAxes::Rdf),
        "stored" => Ok(SpzAxes::Stored),
        other => Err(pyo3::exceptions::PyValueError::new_err(format!(
            "spz_axes must be 'rdf' or 'stored', got '{other}'"
        ))),
    }
}

/// Load a Gaussian-splat scene, detecting the format from the content (not the name): INRIA
/// 3DGS PLY, SuperSplat compressed PLY, Niantic .spz (v1-v4), PlayCanvas SOG (.sog bundle,
/// meta.json or its folder), glTF/GLB with KHR_gaussian_splatting, a SceneSplat .npy folder or
/// antimatter15 .splat.
///
/// Lossy sources (SceneSplat folders: 8-bit DC colour only) and .spz extension records that were
/// skipped or are informational are reported with a MorphgsWarning.
///
/// Args:
///     path: the scene file or folder.
///     on_invalid: "error" (default) raises SceneFormatError on NaN/Inf values; "drop" removes
///         those Gaussians and warns with MorphgsWarning saying how many.
///     spz_axes: "rdf" (default) converts .spz scenes from their stored RUB axes to the PLY/OpenCV
///         RDF convention (positions, rotations and SH); "stored" keeps them as stored.
///
/// Returns:
///     GaussianScene
///
/// Raises:
///     FileNotFoundError: the file does not exist.
///     SceneFormatError: the file is malformed or unsupported (names the file, element, property).
#[pyfunction]
#[pyo3(signature = (path, *, on_invalid = "error", spz_axes = "rdf"))]
fn load(
    py: Python<'_>,
    path: PathBuf,
    on_invalid: &str,
    spz_axes: &str,
) -> PyResult<PyGaussianScene> {
    let opts = LoadOptions {
        on_invalid: parse_on_invalid(on_invalid)?,
        spz_axes: parse_spz_axes(spz_axes)?,
    };
    let p = path.clone();
    let (scene, report) = detach(py, move || splat_core::io::load(&p, opts))?;
    let cat = py.get_type::<MorphgsWarning>();
    for note in &report.notes {
        PyErr::warn(py, &cat, &std::ffi::CString::new(note.as_str())?, 1)?;
    }
    if report.dropped > 0 {
        let msg = format!(
            "{}: dropped {} of {} Gaussians holding NaN or Inf values",
            path.display(),
            report.dropped,
            report.dropped + scene.len()
        );
        let cat = py.get_type::<MorphgsWarning>();
        PyErr::warn(py, &cat, &std::ffi::CString::new(msg)?, 1)?;
    }
    PyGaussianScene::from_core(py, scene)
}

/// Write a scene as an INRIA 3DGS PLY (binary little-endian float32, zero normals, extras kept).
///
/// The file is written to a temporary beside `path` and renamed, so a failure never leaves a
/// partial file behind.
#[pyfunction]
fn save_ply(py: Python<'_>, scene: &PyGaussianScene, path: PathBuf) -> PyResult<()> {
    let borrow = scene.borrow(py)?;
    let extras = scene.extras_readonly(py)?;
    let view = borrow.view()?;
    let extras_ref: Vec<(&str, &[f32])> = extras
        .iter()
        .map(|(n, a)| Ok((n.as_str(), a.as_slice()?)))
        .collect::<Result<_, numpy::AsSliceError>>()
        .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?;
    detach(py, || splat_core::ply::write_ply(&path, &view, &extras_ref))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(load, m)?)?;
    m.add_function(wrap_pyfunction!(save_ply, m)?)?;
    Ok(())
}
