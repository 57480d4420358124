//! Reading image files for the commands (edge layer): the path and the reason travel
//! together so every error names the file.

use std::path::{Path, PathBuf};

use image::DynamicImage;
use thiserror::Error;

use crate::imaging::Mask;
use crate::imaging::decode::{DecodeError, DecodeLimits, Photo, decode_mask, decode_photo};

/// A file that did not become an image.
#[derive(Debug, Error)]
pub enum LoadError {
    #[error("{path}: cannot read: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {source}")]
    Decode { path: PathBuf, source: DecodeError },
}

/// Reads and decodes `path` within `limits`, upright, in the working colour space; what was
/// wrong with it but did not stop it is told on standard error, naming the file.
pub fn load_image(path: &Path, limits: &DecodeLimits) -> Result<DynamicImage, LoadError> {
    load_photo(path, limits).map(|p| p.image)
}

/// [`load_image`] with the file's metadata.
pub fn load_photo(path: &Path, limits: &DecodeLimits) -> Result<Photo, LoadError> {
    let bytes = std::fs::read(path).map_err(|source| LoadError::Io { path: path.to_owned(), source })?;
    let photo =
        decode_photo(&bytes, limits).map_err(|source| LoadError::Decode { path: path.to_owned(), source })?;
    for w in &photo.warnings {
        eprintln!("clearview: {}: {w}", path.display());
    }
    Ok(photo)
}

/// Reads and decodes the mask `path` within `limits`, upright, as
/// [`crate::imaging::convert::to_mask`] reads it (transparency is what is kept).
pub fn load_mask(path: &Path, limits: &DecodeLimits) -> Result<Mask, LoadError> {
    let bytes = std::fs::read(path).map_err(|source| LoadError::Io { path: path.to_owned(), source })?;
    decode_mask(&bytes, limits).map_err(|source| LoadError::Decode { path: path.to_owned(), source })
}
