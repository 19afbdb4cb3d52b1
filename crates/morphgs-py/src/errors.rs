//! The Python exception hierarchy and the one place core errors become Python exceptions.
use pyo3::create_exception;
use pyo3::exceptions::{
    PyFileExistsError, PyFileNotFoundError, PyIsADirectoryError, PyNotADirectoryError, PyOSError,
    PyPermissionError, PyUserWarning, PyValueError,
};
use pyo3::prelude::*;
use splat_core::Error;

create_exception!(
    morphgs._core,
    MorphgsError,
    PyValueError,
    "Base class of every morphgs error (a ValueError)."
);
create_exception!(
    morphgs._core,
    SceneFormatError,
    MorphgsError,
    "A scene file is malformed or unsupported. Attributes: path, element, property."
);
create_exception!(
    morphgs._core,
    MorphgsWarning,
    PyUserWarning,
    "Something was repaired or skipped, e.g. Gaussians dropped for NaN values."
);

/// Newtype so `?` converts core errors in binding code.
pub struct CoreError(pub Error);

impl From<Error> for CoreError {
    fn from(e: Error) -> Self {
        CoreError(e)
    }
}

impl From<CoreError> for PyErr {
    fn from(CoreError(err): CoreError) -> PyErr {
        let msg = err.to_string();
        match err {
            Error::Io { path, source } => {
                let _ = msg;
                let text = source.to_string();
                let strerror = match text.find(" (os error") {
                    Some(i) => text[..i].to_owned(),
                    None => text,
                };
                let args = (
                    source.raw_os_error().unwrap_or(0),
                    strerror,
                    path.to_string_lossy().into_owned(),
                );
                use std::io::ErrorKind as K;
                match source.kind() {
                    K::NotFound => PyFileNotFoundError::new_err(args),
                    K::PermissionDenied => PyPermissionError::new_err(args),
                    K::AlreadyExists => PyFileExistsError::new_err(args),
                    K::IsADirectory => PyIsADirectoryError::new_err(args),
                    K::NotADirectory => PyNotADirectoryError::new_err(args),
                    _ => PyOSError::new_err(args),
                }
            }
            Error::Format {
                path,
                element,
                property,
                ..
            } => {
                let e = SceneFormatError::new_err(msg);
                Python::attach(|py| {
                    let v = e.value(py);
                    let _ = v.setattr("path", path.to_string_lossy().into_owned());
                    let _ = v.setattr("element", element);
                    let _ = v.setattr("property", property);
                });
                e
            }
            Error::InvalidArgument(_) => PyValueError::new_err(msg),
        }
    }
}

/// Run `f` with the GIL released, inside this process's rayon pool (fork-safe, see `pool`), and
/// convert its error: the one chokepoint for long calls.
pub fn detach<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> splat_core::Result<T> + Send,
) -> PyResult<T> {
    py.detach(|| crate::pool::install(f))
        .map_err(|e| CoreError(e).into())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("MorphgsError", py.get_type::<MorphgsError>())?;
    m.add("SceneFormatError", py.get_type::<SceneFormatError>())?;
    m.add("MorphgsWarning", py.get_type::<MorphgsWarning>())?;
    Ok(())
}
