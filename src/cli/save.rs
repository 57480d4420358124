//! Writing results (edge layer): encode in memory, then write atomically (a reader never
//! sees half a file, and a failed write leaves what was there before untouched).

use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageFormat};
use thiserror::Error;

use crate::daemon::emit::atomic_write;

/// A result that could not be written.
#[derive(Debug, Error)]
pub enum SaveError {
    #[error("{path}: unknown image format (use .png, .jpg, .tif or .webp)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: cannot encode: {source}")]
    Encode { path: PathBuf, source: image::ImageError },
    #[error("{path}: cannot write: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

/// The image format a path's extension names, if clearview writes it.
pub fn output_format(path: &Path) -> Result<ImageFormat, SaveError> {
    match ImageFormat::from_path(path) {
        Ok(f @ (ImageFormat::Png | ImageFormat::Jpeg | ImageFormat::Tiff | ImageFormat::WebP)) => Ok(f),
        _ => Err(SaveError::UnknownFormat { path: path.to_owned() }),
    }
}

/// Encodes `img` in the format `path`'s extension names and writes it atomically.
pub fn save_image(path: &Path, img: &DynamicImage) -> Result<(), SaveError> {
    let format = output_format(path)?;
    let mut bytes = std::io::Cursor::new(Vec::new());
    // JPEG has no alpha and no 16-bit; our results are 8-bit RGB anyway.
    img.write_to(&mut bytes, format).map_err(|source| SaveError::Encode { path: path.to_owned(), source })?;
    write_atomic(path, bytes.get_ref())
}

/// Writes `bytes` to `path` atomically (the daemon's writer: temporary name beside it,
/// synced, renamed), naming the path in the error.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), SaveError> {
    atomic_write(path, bytes).map_err(|source| SaveError::Io { path: path.to_owned(), source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_atomically_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.png");
        std::fs::write(&p, b"old").unwrap();
        write_atomic(&p, b"new contents").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new contents");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("missing-folder").join("out.png");
        assert!(matches!(write_atomic(&p, b"x"), Err(SaveError::Io { .. })));
        assert!(matches!(output_format(Path::new("a.bmpx")), Err(SaveError::UnknownFormat { .. })));
    }
}
