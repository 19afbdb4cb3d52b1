//! The extension module `morphgs._core`: thin wrappers over `splat-core`.
//! Each domain registers its names from its own file.
use pyo3::prelude::*;

mod errors;
mod io;
mod scene;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    errors::register(m)?;
    scene::register(m)?;
    io::register(m)?;
    Ok(())
}
