//! [`DataError`]: why a data set could not be loaded (a file's content, or reading it),
//! naming the file, the field and what was expected.

use std::io;
use std::path::{Path, PathBuf};

use crate::terrain::map::MapError;
use crate::terrain::pnm::PnmError;

/// Why a data set could not be loaded. The message always starts with the file's path.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The content of a file is wrong: `field` is a header field (`magic`, `width`, `height`,
    /// `maxval`, `data`), a `map` key (`hScale`, `start.x`, …) or `syntax`.
    #[error("{}{}: {field}: {message}", file.display(), line.map(|l| format!(":{l}")).unwrap_or_default())]
    Invalid {
        /// The file, as given (directory joined with the file name).
        file: PathBuf,
        /// 1-based line, for the `map` file.
        line: Option<usize>,
        /// The field or key.
        field: String,
        /// What was expected and what was found.
        message: String,
    },
    /// A file could not be opened or read.
    #[error("{}: cannot {action}: {error}", file.display())]
    Io {
        /// The file.
        file: PathBuf,
        /// `open`, `read`, `stat`.
        action: &'static str,
        /// The operating system's error.
        error: io::Error,
    },
}

impl DataError {
    pub(crate) fn from_pnm(file: &Path, e: PnmError) -> DataError {
        match e {
            PnmError::Format { field, message } => DataError::Invalid {
                file: file.to_path_buf(),
                line: None,
                field: field.into(),
                message,
            },
            PnmError::Io { action, error } => DataError::Io {
                file: file.to_path_buf(),
                action,
                error,
            },
        }
    }

    pub(crate) fn from_map(file: &Path, e: MapError) -> DataError {
        DataError::Invalid {
            file: file.to_path_buf(),
            line: e.line,
            field: e.field,
            message: e.message,
        }
    }

    /// The file the error is about.
    pub fn file(&self) -> &Path {
        match self {
            DataError::Invalid { file, .. } | DataError::Io { file, .. } => file,
        }
    }
}
