//! Why a `nebel` command failed: [`CommandError`], one line on stderr.

use std::path::PathBuf;

use nebel_core::field::FieldError;
use nebel_core::transfer::TransferError;
use nebel_reference::ReferenceError;
use nebel_reference::image_metrics::ImageMetricsError;
use nebel_scene::SceneError;
use thiserror::Error;

use crate::headless::HeadlessError;

/// Why a command failed. Every message names the file or option at fault.
#[derive(Debug, Error)]
pub enum CommandError {
    /// The scene file could not be read, parsed, validated or built.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The headless render failed (no adapter, no image back).
    #[error(transparent)]
    Headless(#[from] HeadlessError),
    /// The exact reference could not be rendered.
    #[error(transparent)]
    Reference(#[from] ReferenceError),
    /// An image could not be read, written or compared.
    #[error(transparent)]
    Image(#[from] ImageMetricsError),
    /// A field the command builds itself was refused.
    #[error(transparent)]
    Field(#[from] FieldError),
    /// A transfer function the command builds itself was refused.
    #[error(transparent)]
    Transfer(#[from] TransferError),
    /// A file or folder could not be written.
    #[error("{}: {source}", path.display())]
    Write {
        /// The file or folder.
        path: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// The scene does not suit the command (it needs exactly one grid volume,
    /// say).
    #[error("{}: {reason}", path.display())]
    Unsuitable {
        /// The scene file.
        path: PathBuf,
        /// What the command needs.
        reason: String,
    },
    /// The plot could not be drawn.
    #[error("{}: cannot draw the plot: {reason}", path.display())]
    Plot {
        /// The plot file.
        path: PathBuf,
        /// The plotting library's error.
        reason: String,
    },
}

impl CommandError {
    /// A write error for `path`.
    pub fn write(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Write { path, source }
    }
}
