//! [`SourceError`]: the error every reader of `import`'s source files returns, naming the
//! file and what is wrong with it.

use std::fmt;
use std::path::{Path, PathBuf};

/// Why a source file cannot be imported.
#[derive(Debug)]
pub struct SourceError {
    /// The file.
    pub path: PathBuf,
    /// What is wrong, e.g. "truncated: expected 2884802 bytes, got 1000".
    pub message: String,
}

impl SourceError {
    pub fn new(path: &Path, message: impl Into<String>) -> Self {
        SourceError {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

impl fmt::Display for SourceError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path.display(), self.message)
    }
}

impl std::error::Error for SourceError {}
