//! Typed errors. Every variant carries enough context (file, field, tensor,
//! expected and found values) for the CLI to print one human sentence; the
//! library never prints and never exits.

use std::path::PathBuf;

/// The library's error type.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An operating-system error while reading or writing `path`.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A file exists but its content is not what the format requires.
    #[error("{path}: {what}")]
    Format { path: PathBuf, what: String },

    /// A named field of a structured file (JSON key, PLY property, tensor
    /// metadata key) is missing or has an unusable value.
    #[error("{path}: field `{field}`: {what}")]
    Field {
        path: PathBuf,
        field: String,
        what: String,
    },

    /// A tensor has the wrong shape or element type.
    #[error("{context}: tensor `{name}`: expected {expected}, found {found}")]
    Tensor {
        context: String,
        name: String,
        expected: String,
        found: String,
    },

    /// A required tensor is absent.
    #[error("{context}: missing tensor `{name}`")]
    MissingTensor { context: String, name: String },

    /// Tensors present that nothing uses.
    #[error("{context}: unexpected tensor(s): {names}")]
    UnexpectedTensors { context: String, names: String },

    /// An argument or configuration value is out of its domain.
    #[error("invalid {what}: {why}")]
    Invalid { what: String, why: String },
}

/// Shorthand result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    pub fn format(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            what: what.into(),
        }
    }
    pub fn field(
        path: impl Into<PathBuf>,
        field: impl Into<String>,
        what: impl Into<String>,
    ) -> Self {
        Error::Field {
            path: path.into(),
            field: field.into(),
            what: what.into(),
        }
    }
    pub fn invalid(what: impl Into<String>, why: impl Into<String>) -> Self {
        Error::Invalid {
            what: what.into(),
            why: why.into(),
        }
    }

    /// The error with the file it concerns: an [`Error::Invalid`] (which
    /// names a field or setting but no file) becomes an [`Error::Field`] of
    /// `path`; every other variant already names its file and is returned
    /// as it is.
    pub fn in_file(self, path: impl Into<PathBuf>) -> Self {
        match self {
            Error::Invalid { what, why } => Error::Field {
                path: path.into(),
                field: what,
                what: why,
            },
            e => e,
        }
    }
}

/// `Result` with [`Error::in_file`] applied to its error.
pub trait InFile<T> {
    /// Name `path` in an error that names no file (see [`Error::in_file`]).
    fn in_file(self, path: impl Into<PathBuf>) -> Result<T>;
}

impl<T> InFile<T> for Result<T> {
    fn in_file(self, path: impl Into<PathBuf>) -> Result<T> {
        self.map_err(|e| e.in_file(path))
    }
}
