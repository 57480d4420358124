//! Writing results (edge layer): encode in memory, then write atomically (a reader never
//! sees half a file, and a failed write leaves what was there before untouched).

use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageFormat};
use thiserror::Error;

use crate::fsio::atomic_write;
use crate::imaging::RgbF32;
use crate::imaging::encode::{EncodeError, EncodeOptions, Format, encode};
use crate::imaging::meta::{Metadata, Provenance};

/// A result that could not be written.
#[derive(Debug, Error)]
pub enum SaveError {
    #[error("{path}: unknown image format (use .png, .jpg, .tif or .webp)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: cannot encode: {source}")]
    Encode { path: PathBuf, source: image::ImageError },
    #[error("{path}: cannot encode: {source}")]
    EncodeJpeg { path: PathBuf, source: jpeg_encoder::EncodingError },
    #[error("{path}: {source}")]
    EncodeResult { path: PathBuf, source: EncodeError },
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

/// The result format a path's extension names, if clearview writes it.
pub fn result_format(path: &Path) -> Result<Format, SaveError> {
    path.extension()
        .and_then(|e| e.to_str())
        .and_then(Format::from_extension)
        .ok_or_else(|| SaveError::UnknownFormat { path: path.to_owned() })
}

/// Writes a result (working-space RGB) atomically in the format `path` names, in the
/// keyframe's colour space with its metadata (see [`crate::imaging::encode`]); returns what
/// had to be left out.
pub fn save_result(
    path: &Path,
    rgb: &RgbF32,
    opts: &EncodeOptions,
    meta: &Metadata,
    provenance: &Provenance,
) -> Result<Vec<String>, SaveError> {
    let format = result_format(path)?;
    let encoded = encode(rgb, format, opts, meta, provenance)
        .map_err(|source| SaveError::EncodeResult { path: path.to_owned(), source })?;
    write_atomic(path, &encoded.bytes)?;
    Ok(encoded.warnings)
}

/// JPEG quality of masks and other non-result images: the results' default.
pub const JPEG_QUALITY: u8 = crate::imaging::encode::DEFAULT_QUALITY;

/// Encodes `img` in the format `path`'s extension names and writes it atomically.
///
/// 8-bit RGB and grey JPEGs go through `jpeg-encoder` (SIMD colour conversion and DCT), with
/// the settings `image`'s own encoder uses (quality 75, no chroma subsampling, baseline):
/// the same quality (40.35 dB against 40.34 dB on a 12 MP photograph) in less than half the
/// time (0.33 s against 0.69 s, minimum of 8 runs on a loaded machine).
pub fn save_image(path: &Path, img: &DynamicImage) -> Result<(), SaveError> {
    let format = output_format(path)?;
    let fast = match img {
        DynamicImage::ImageRgb8(c) => Some((c.as_raw(), jpeg_encoder::ColorType::Rgb)),
        DynamicImage::ImageLuma8(g) => Some((g.as_raw(), jpeg_encoder::ColorType::Luma)),
        _ => None,
    };
    if let (ImageFormat::Jpeg, Some((raw, color)), Ok(w), Ok(h)) =
        (format, fast, u16::try_from(img.width()), u16::try_from(img.height()))
    {
        let mut bytes = Vec::new();
        let mut encoder = jpeg_encoder::Encoder::new(&mut bytes, JPEG_QUALITY);
        encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_4_4);
        encoder
            .encode(raw, w, h, color)
            .map_err(|source| SaveError::EncodeJpeg { path: path.to_owned(), source })?;
        return write_atomic(path, &bytes);
    }
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
    fn jpeg_results_decode_close_to_what_was_saved() {
        use image::{GrayImage, RgbImage};
        let dir = tempfile::tempdir().unwrap();
        let rgb =
            RgbImage::from_fn(67, 41, |x, y| image::Rgb([(x * 3) as u8, (y * 5) as u8, ((x + y) * 2) as u8]));
        let grey = GrayImage::from_fn(33, 20, |x, y| image::Luma([(x * 7 + y) as u8]));
        for img in [DynamicImage::ImageRgb8(rgb), DynamicImage::ImageLuma8(grey)] {
            let p = dir.path().join("out.jpg");
            save_image(&p, &img).unwrap();
            let back = image::open(&p).unwrap();
            assert_eq!((back.width(), back.height(), back.color()), (img.width(), img.height(), img.color()));
            let (a, b) = (back.to_rgb8(), img.to_rgb8());
            let worst = a.as_raw().iter().zip(b.as_raw()).map(|(&p, &q)| p.abs_diff(q)).max().unwrap();
            assert!(worst <= 12, "{:?}: off by {worst}", img.color());
        }
    }

    #[test]
    fn a_failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("missing-folder").join("out.png");
        assert!(matches!(write_atomic(&p, b"x"), Err(SaveError::Io { .. })));
        assert!(matches!(output_format(Path::new("a.bmpx")), Err(SaveError::UnknownFormat { .. })));
    }
}
