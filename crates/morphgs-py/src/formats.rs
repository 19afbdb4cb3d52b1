//! save_splat / save_spz: writers for the web-viewer formats.
use std::path::PathBuf;

use pyo3::prelude::*;

use crate::errors::detach;
use crate::io::parse_spz_axes;
use crate::scene::PyGaussianScene;

/// Write a scene as an antimatter15 .splat (32 bytes per Gaussian; no SH beyond the DC colour).
///
/// Positions and scales stay float32; colour and opacity are rounded to 8 bits and the rotation
/// to 8 bits per component. The file is written to a temporary beside `path` and renamed.
///
/// Args:
///     scene: the scene (its higher SH bands are dropped).
///     path: the output file.
///
/// Raises:
///     ValueError: the scene holds NaN or Inf values.
///     OSError: the file cannot be written.
#[pyfunction]
fn save_splat(py: Python<'_>, scene: &PyGaussianScene, path: PathBuf) -> PyResult<()> {
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    detach(py, || splat_core::formats::splat::write(&path, &view))
}

/// Write a scene as a Niantic .spz version 3 (gzip), readable by nianticlabs/spz and web viewers.
///
/// Positions become 24-bit fixed point (12 fractional bits, fewer when a coordinate exceeds
/// 2048), colour, opacity, log-scale and SH 8 bits each, rotations smallest-three (4 bytes).
/// The file is written to a temporary beside `path` and renamed.
///
/// Args:
///     scene: the scene.
///     path: the output file.
///     spz_axes: "rdf" (default): the scene is in PLY/OpenCV axes and is converted to the RUB
///         axes .spz stores; "stored": the scene is already in RUB (e.g. loaded with
///         spz_axes="stored") and is written as is.
///
/// Raises:
///     ValueError: the scene holds NaN or Inf values, or a position too large for 24 bits.
///     OSError: the file cannot be written.
#[pyfunction]
#[pyo3(signature = (scene, path, *, spz_axes = "rdf"))]
fn save_spz(
    py: Python<'_>,
    scene: &PyGaussianScene,
    path: PathBuf,
    spz_axes: &str,
) -> PyResult<()> {
    let axes = parse_spz_axes(spz_axes)?;
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    detach(py, || splat_core::formats::spz::write(&path, &view, axes))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(save_splat, m)?)?;
    m.add_function(wrap_pyfunction!(save_spz, m)?)?;
    Ok(())
}
