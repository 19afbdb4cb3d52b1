//! One error type for the whole core. The Python binding maps every variant to a typed exception.
use std::path::PathBuf;

/// Everything that can go wrong in `splat-core`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The operating system refused a read or write.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A scene file is malformed or unsupported. `element` and `property` name where, when known.
    #[error("{path}: {}{message}", location(.element, .property))]
    Format {
        path: PathBuf,
        element: Option<String>,
        property: Option<String>,
        message: String,
    },
    /// A caller passed a value that is out of range or inconsistent.
    #[error("{0}")]
    InvalidArgument(String),
}

fn location(element: &Option<String>, property: &Option<String>) -> String {
    match (element, property) {
        (Some(e), Some(p)) => format!("element '{e}', property '{p}': "),
        (Some(e), None) => format!("element '{e}': "),
        (None, Some(p)) => format!("property '{p}': "),
        (None, None) => String::new(),
    }
}

impl Error {
    /// A format error with no element or property attached.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            element: None,
            property: None,
            message: message.into(),
        }
    }

    /// A format error located at an element (and optionally a property).
    pub fn format_at(
        path: impl Into<PathBuf>,
        element: impl Into<String>,
        property: Option<&str>,
        message: impl Into<String>,
    ) -> Self {
        Error::Format {
            path: path.into(),
            element: Some(element.into()),
            property: property.map(str::to_owned),
            message: message.into(),
        }
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
