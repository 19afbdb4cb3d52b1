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

/// Write a scene as a Niantic .spz, readable by nianticlabs/spz and web viewers.
///
/// Positions become 24-bit fixed point (12 fractional bits, fewer when a coordinate exceeds
/// 2048), colour, opacity, log-scale and SH 8 bits each, rotations smallest-three (4 bytes).
/// Version 3 (default) is one gzip stream, the widest-read variant; version 4 compresses each
/// attribute as its own zstd frame (nianticlabs/spz's current default). The file is written to
/// a temporary beside `path` and renamed.
///
/// Args:
///     scene: the scene.
///     path: the output file.
///     spz_axes: "rdf" (default): the scene is in PLY/OpenCV axes and is converted to the RUB
///         axes .spz stores; "stored": the scene is already in RUB (e.g. loaded with
///         spz_axes="stored") and is written as is.
///     version: 3 (gzip) or 4 (zstd streams).
///
/// Raises:
///     ValueError: the scene holds NaN or Inf values, a position too large for 24 bits, or the
///         version is not 3 or 4.
///     OSError: the file cannot be written.
#[pyfunction]
#[pyo3(signature = (scene, path, *, spz_axes = "rdf", version = 3))]
fn save_spz(
    py: Python<'_>,
    scene: &PyGaussianScene,
    path: PathBuf,
    spz_axes: &str,
    version: u32,
) -> PyResult<()> {
    let axes = parse_spz_axes(spz_axes)?;
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    detach(py, || {
        splat_core::formats::spz::write_version(&path, &view, axes, version)
    })
}

/// Write a scene as a SuperSplat/PlayCanvas compressed PLY (about 16 bytes per Gaussian plus 1
/// byte per SH coefficient), the layout playcanvas/splat-transform writes.
///
/// Gaussians are reordered along a Morton curve and quantised per 256-Gaussian chunk: position
/// and log-scale 11/10/11 bits inside the chunk's bounds, rotation 2+3x10 bits, colour and
/// opacity 8 bits, SH 8 bits in [-4, 4]. SH bands above degree 3 are dropped (viewers stop at 3).
///
/// Args:
///     scene: the scene (PLY/OpenCV axes, stored as is).
///     path: the output file (conventionally `*.compressed.ply`).
///
/// Raises:
///     ValueError: the scene holds NaN or Inf values.
///     OSError: the file cannot be written.
#[pyfunction]
fn save_compressed_ply(py: Python<'_>, scene: &PyGaussianScene, path: PathBuf) -> PyResult<()> {
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    detach(py, || {
        splat_core::formats::compressed_ply::write(&path, &view)
    })
}

/// Write a scene as a binary glTF (.glb) with the KHR_gaussian_splatting extension.
///
/// Values are stored activated, as the extension requires: float32 positions, unit (x,y,z,w)
/// rotations, linear scales, opacity in [0,1], SH coefficients (degrees 0-3; a degree-4 band is
/// dropped), plus a COLOR_0 point-cloud fallback. Axes are converted from PLY/OpenCV (RDF) to
/// glTF's +Y up, +Z front (a 180-degree rotation about Z, as splat-transform does).
///
/// Args:
///     scene: the scene.
///     path: the output file.
///
/// Raises:
///     ValueError: the scene holds NaN or Inf values or exceeds 4 GiB as GLB.
///     OSError: the file cannot be written.
#[pyfunction]
fn save_glb(py: Python<'_>, scene: &PyGaussianScene, path: PathBuf) -> PyResult<()> {
    let borrow = scene.borrow(py)?;
    let view = borrow.view()?;
    detach(py, || splat_core::formats::gltf::write(&path, &view))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(save_splat, m)?)?;
    m.add_function(wrap_pyfunction!(save_spz, m)?)?;
    m.add_function(wrap_pyfunction!(save_compressed_ply, m)?)?;
    m.add_function(wrap_pyfunction!(save_glb, m)?)?;
    Ok(())
}
