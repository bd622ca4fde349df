//! The library's error type: one enum whose messages name the file, field or value at fault.

use std::path::PathBuf;

/// Everything that can go wrong in procl's library code, with enough context to act on.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An environment name that procl does not know.
    #[error("unknown environment `{name}` (expected one of: {known})")]
    UnknownEnv { name: String, known: String },

    /// A configuration or command-line value outside its valid range.
    #[error("invalid value for `{field}`: {message}")]
    InvalidConfig { field: String, message: String },

    /// A dataset file that is missing, truncated, corrupt or of the wrong shape.
    #[error("dataset {path}: {message}")]
    Dataset { path: PathBuf, message: String },

    /// An output file that exists and would be overwritten.
    #[error("{0} already exists; pass --force to overwrite it")]
    WouldClobber(PathBuf),

    /// An output folder another procl process is writing.
    #[error(
        "{path} is being written by another procl (pid {pid}); wait for it to finish or choose another folder"
    )]
    Busy { path: PathBuf, pid: String },

    /// An operating-system error on a named file.
    /// (The OS error is part of the message, not a `source`, so chains print it once.)
    #[error("{path}: {cause}")]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },

    /// A state vector of the wrong length or with non-finite entries.
    #[error("invalid state for {env}: {message}")]
    InvalidState { env: &'static str, message: String },

    /// A checkpoint that is missing, corrupt or does not fit the model.
    #[error("checkpoint {path}: {message}")]
    Checkpoint { path: PathBuf, message: String },

    /// Training produced a non-finite loss.
    #[error("{0}")]
    Diverged(String),

    /// Training was stopped on request (a Python KeyboardInterrupt).
    #[error("{0}")]
    Interrupted(String),

    /// Encoding an image (PNG/GIF) failed.
    #[error("could not encode image {path}: {message}")]
    Image { path: PathBuf, message: String },
}

/// `Result` with procl's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// `message` on one line: a dependency's multi-line report (a parser's caret diagram) has its
/// line breaks and indentation folded into single spaces, so every error prints as one line.
fn one_line(message: String) -> String {
    if message.contains(['\n', '\r']) {
        message.split_whitespace().collect::<Vec<_>>().join(" ")
    } else {
        message
    }
}

impl Error {
    /// Shorthand for [`Error::InvalidConfig`].
    pub fn config(field: impl Into<String>, message: impl Into<String>) -> Self {
        Error::InvalidConfig {
            field: one_line(field.into()),
            message: one_line(message.into()),
        }
    }

    /// Shorthand for [`Error::Dataset`].
    pub fn dataset(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Dataset {
            path: path.into(),
            message: one_line(message.into()),
        }
    }

    /// Shorthand for [`Error::Checkpoint`].
    pub fn checkpoint(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Checkpoint {
            path: path.into(),
            message: one_line(message.into()),
        }
    }

    /// Shorthand for [`Error::Io`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            cause: source,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dependencys_multi_line_report_becomes_one_line() {
        let report =
            "syntax error:  --> 1:35\n  |\n1 | {'descr': FalsbT}\n  |     ^---\n  = expected value";
        let message = Error::dataset("d.npz", report).to_string();
        assert_eq!(
            message,
            "dataset d.npz: syntax error: --> 1:35 | 1 | {'descr': FalsbT} | ^--- = expected value"
        );
        // Messages without line breaks keep their spacing.
        assert_eq!(
            Error::config("f", "a  b").to_string(),
            "invalid value for `f`: a  b"
        );
    }
}
