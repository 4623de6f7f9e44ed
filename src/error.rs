//! Typed errors and exit codes. Every variant carries enough context (file,
//! field, tensor, expected and found values) for the CLI to print one human
//! sentence; the library never prints and never exits.
//!
//! [`exit_code`] is the one place a command's result becomes a process exit
//! code: 0 success ([`Outcome::Success`]), 1 a check or comparison failed
//! ([`Outcome::CheckFailed`]), 2 unusable input (any [`Error`]: bad
//! arguments, missing or malformed files).

use std::path::PathBuf;

/// The library's error type.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An operating-system error while reading or writing `path`.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder the operation concerned.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },

    /// A file exists but its content is not what the format requires.
    #[error("{path}: {what}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong with it, as a phrase.
        what: String,
    },

    /// A named field of a structured file (JSON key, PLY property, tensor
    /// metadata key) is missing or has an unusable value.
    #[error("{path}: field `{field}`: {what}")]
    Field {
        /// The file.
        path: PathBuf,
        /// The field's name (a dotted path for nested fields).
        field: String,
        /// What is wrong with its value, as a phrase.
        what: String,
    },

    /// A tensor has the wrong shape or element type.
    #[error("{context}: tensor `{name}`: expected {expected}, found {found}")]
    Tensor {
        /// Where the tensor comes from (a file or a stage).
        context: String,
        /// The tensor's name.
        name: String,
        /// The required shape or element type.
        expected: String,
        /// The shape or element type found.
        found: String,
    },

    /// A required tensor is absent.
    #[error("{context}: missing tensor `{name}`")]
    MissingTensor {
        /// Where the tensor was looked for (a file or a stage).
        context: String,
        /// The missing tensor's name.
        name: String,
    },

    /// Tensors present that nothing uses.
    #[error("{context}: unexpected tensor(s): {names} (the tensors it may hold: {known})")]
    UnexpectedTensors {
        /// Where the tensors were found (a file or a stage).
        context: String,
        /// Their names, comma-separated.
        names: String,
        /// The names it may hold, comma-separated (the first 40, then how
        /// many more).
        known: String,
    },

    /// An argument or configuration value is out of its domain.
    #[error("invalid {what}: {why}")]
    Invalid {
        /// The argument or setting, as the user names it (e.g. `--threads`).
        what: String,
        /// Why its value is unusable, as a phrase.
        why: String,
    },
}

/// Shorthand result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An [`Error::Io`] of `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    /// An [`Error::Format`] of `path`.
    pub fn format(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            what: what.into(),
        }
    }
    /// An [`Error::Field`]: `field` of `path` is `what`.
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
    /// An [`Error::Invalid`]: setting `what` is unusable because `why`.
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

/// How a command that ran to its end went: exit code 0 or 1. A command
/// that could not run returns an [`Error`] instead (exit code 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// The command did what was asked (and every check it ran passed).
    Success,
    /// The command ran, but a check or comparison it ran failed.
    CheckFailed,
}

/// Exit code of a command that succeeded.
pub const EXIT_SUCCESS: u8 = 0;
/// Exit code of a command whose check or comparison failed.
pub const EXIT_CHECK_FAILED: u8 = 1;
/// Exit code of a command given unusable input (arguments, files).
pub const EXIT_UNUSABLE_INPUT: u8 = 2;

impl Outcome {
    /// [`Outcome::Success`] when `passed`, else [`Outcome::CheckFailed`].
    pub fn of_check(passed: bool) -> Self {
        if passed {
            Outcome::Success
        } else {
            Outcome::CheckFailed
        }
    }
}

/// An [`Error::Invalid`] for argument `name` unless every one of `values`
/// is finite; the error names the first other one and its flat index.
pub fn check_finite<T: crate::math::Real>(name: &str, values: &[T]) -> Result<()> {
    match crate::math::first_non_finite(values) {
        Some((i, v)) => Err(Error::invalid(
            name,
            format!("{v} at flat index {i} is not finite"),
        )),
        None => Ok(()),
    }
}

/// `v` for a message: as `{}` writes it, but in exponent form when that
/// would be long (`1e308` is 309 digits in `{}`, `1e-300` over 300).
pub fn shown(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-4..1e15).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// The process exit code of a command's result: [`EXIT_SUCCESS`],
/// [`EXIT_CHECK_FAILED`], or [`EXIT_UNUSABLE_INPUT`] for every error. The one
/// place results become exit codes (the CLI, the binary and the Python
/// package's `cli` all go through it).
pub fn exit_code(result: &Result<Outcome>) -> u8 {
    match result {
        Ok(Outcome::Success) => EXIT_SUCCESS,
        Ok(Outcome::CheckFailed) => EXIT_CHECK_FAILED,
        Err(_) => EXIT_UNUSABLE_INPUT,
    }
}
