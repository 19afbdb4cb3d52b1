//! The extension module `morphgs._core`: thin wrappers over `splat-core`.
//! Each domain registers its names from its own file.
use pyo3::prelude::*;

mod blur;
mod diff;
mod errors;
mod fit;
mod formats;
mod io;
mod perturb;
mod pool;
mod render;
mod scene;
mod ssim;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    errors::register(m)?;
    scene::register(m)?;
    io::register(m)?;
    blur::register(m)?;
    render::register(m)?;
    diff::register(m)?;
    fit::register(m)?;
    formats::register(m)?;
    perturb::register(m)?;
    ssim::register(m)?;
    m.add_function(wrap_pyfunction!(num_threads, m)?)?;
    Ok(())
}

/// Number of worker threads morphgs uses in this process (RAYON_NUM_THREADS or
/// MORPHGS_NUM_THREADS, else the CPU count).
#[pyfunction]
fn num_threads(py: Python<'_>) -> usize {
    py.detach(pool::num_threads)
}
