//! Reading image files for the commands (edge layer): the path and the reason travel
//! together so every error names the file.

use std::path::{Path, PathBuf};

use image::DynamicImage;
use thiserror::Error;

use crate::imaging::decode::{DecodeError, DecodeLimits, decode};

/// A file that did not become an image.
#[derive(Debug, Error)]
pub enum LoadError {
    #[error("{path}: cannot read: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {source}")]
    Decode { path: PathBuf, source: DecodeError },
}

/// Reads and decodes `path` within `limits`, upright.
pub fn load_image(path: &Path, limits: &DecodeLimits) -> Result<DynamicImage, LoadError> {
    let bytes = std::fs::read(path).map_err(|source| LoadError::Io { path: path.to_owned(), source })?;
    decode(&bytes, limits).map_err(|source| LoadError::Decode { path: path.to_owned(), source })
}
