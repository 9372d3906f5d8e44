//! What can stop a fit, a render or an evaluation: bad input (named by file and path), an I/O
//! failure, a diverged fit.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("{0}")]
    Scene(#[from] crate::scene::SceneError),
    #[error("{0}")]
    Schedule(#[from] crate::schedule::ScheduleError),
    #[error("{0}")]
    Input(String),
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
    #[error("the fit diverged at iteration {iteration}: {what} is not finite; {checkpoint}")]
    NonFinite {
        iteration: usize,
        what: String,
        /// What became of the checkpoint, as a sentence for the user.
        checkpoint: String,
    },
}

pub fn io(path: &Path, e: impl std::fmt::Display) -> FitError {
    FitError::Io { path: path.to_path_buf(), message: e.to_string() }
}
