//! Decoding of image bytes with limits and EXIF orientation (pure layer: bytes in, pixels
//! out; reading the file is the caller's business).

use std::io::Cursor;

use image::{DynamicImage, ImageDecoder, ImageReader, Limits};
use thiserror::Error;

/// What the decoder may allocate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Largest accepted width × height. A file that declares more is refused before any
    /// pixel buffer is allocated (a decompression bomb costs nothing).
    pub max_pixels: u64,
}

impl Default for DecodeLimits {
    fn default() -> Self {
        Self { max_pixels: 100_000_000 }
    }
}

/// Why bytes did not become an image. Every variant is the input's fault, not ours.
#[derive(Debug, Error)]
pub enum DecodeError {
    #[error("empty file: 0 bytes (an upload that never started?)")]
    Empty,
    #[error("not an image in a format clearview reads (JPEG, PNG, TIFF, WebP)")]
    UnknownFormat,
    #[error("{width}x{height} is {pixels} pixels, more than the limit of {limit}")]
    TooLarge { width: u32, height: u32, pixels: u64, limit: u64 },
    #[error("image has no pixels ({width}x{height})")]
    Degenerate { width: u32, height: u32 },
    #[error("the file ends before the image does (cut short: an upload that did not finish?)")]
    CutShort,
    #[error("cannot decode: {}", .0.to_string().trim_end())]
    Corrupt(#[source] image::ImageError),
}

/// Decodes `bytes` into an image, upright (EXIF orientation applied), within `limits`.
pub fn decode(bytes: &[u8], limits: &DecodeLimits) -> Result<DynamicImage, DecodeError> {
    if bytes.is_empty() {
        return Err(DecodeError::Empty);
    }
    let reader = ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| DecodeError::Corrupt(image::ImageError::IoError(e)))?;
    if reader.format().is_none() {
        return Err(DecodeError::UnknownFormat);
    }
    if reader.format() == Some(image::ImageFormat::Jpeg) && jpeg_cut_short(bytes) {
        // The JPEG decoder pads a missing end with grey rather than failing: a cut file
        // would become a view with a grey band.
        return Err(DecodeError::CutShort);
    }
    let mut decoder = reader.into_decoder().map_err(DecodeError::Corrupt)?;
    let (width, height) = decoder.dimensions();
    let pixels = u64::from(width) * u64::from(height);
    if pixels > limits.max_pixels {
        return Err(DecodeError::TooLarge { width, height, pixels, limit: limits.max_pixels });
    }
    if pixels == 0 {
        return Err(DecodeError::Degenerate { width, height });
    }
    let mut alloc = Limits::default();
    // Room for the decoded buffer at 16 bits × 4 channels, plus the decoder's own scratch.
    alloc.max_alloc = Some(pixels.saturating_mul(8).saturating_add(64 << 20));
    decoder.set_limits(alloc).map_err(DecodeError::Corrupt)?;
    let orientation = decoder.orientation().ok();
    let mut img = DynamicImage::from_decoder(decoder).map_err(DecodeError::Corrupt)?;
    if let Some(o) = orientation {
        img.apply_orientation(o);
    }
    Ok(img)
}

/// Whether a JPEG stream stops before its end-of-image marker: its segments are walked
/// from the start, the entropy-coded data of each scan skipped, until the marker that ends
/// the image (anything after it, such as a camera's trailer, is allowed).
fn jpeg_cut_short(bytes: &[u8]) -> bool {
    const EOI: u8 = 0xd9;
    const SOS: u8 = 0xda;
    let mut i = 2;
    loop {
        // A marker: 0xFF (fill bytes allowed), then its code.
        while bytes.get(i) == Some(&0xff) && bytes.get(i + 1) == Some(&0xff) {
            i += 1;
        }
        let (Some(0xff), Some(&code)) = (bytes.get(i), bytes.get(i + 1)) else { return true };
        i += 2;
        match code {
            EOI => return false,
            0x01 | 0xd0..=0xd7 => continue,
            _ => {}
        }
        let Some(len) = bytes.get(i..i + 2).map(|b| usize::from(u16::from_be_bytes([b[0], b[1]]))) else {
            return true;
        };
        i += len;
        if i > bytes.len() {
            return true;
        }
        if code == SOS {
            // Entropy-coded data: up to the next 0xFF that is not a stuffed zero or a restart.
            loop {
                match (bytes.get(i), bytes.get(i + 1)) {
                    (Some(0xff), Some(0x00 | 0xd0..=0xd7)) => i += 2,
                    (Some(0xff), Some(_)) => break,
                    (Some(_), _) => i += 1,
                    (None, _) => return true,
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{ImageFormat, RgbImage};

    fn png_bytes(w: u32, h: u32) -> Vec<u8> {
        let img = RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 0]));
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, ImageFormat::Png).unwrap();
        out.into_inner()
    }

    #[test]
    fn decodes_png() {
        let img = decode(&png_bytes(7, 5), &DecodeLimits::default()).unwrap();
        assert_eq!((img.width(), img.height()), (7, 5));
    }

    #[test]
    fn refuses_empty_garbage_and_truncated() {
        let limits = DecodeLimits::default();
        assert!(matches!(decode(&[], &limits), Err(DecodeError::Empty)));
        assert!(matches!(decode(b"hello world, not an image", &limits), Err(DecodeError::UnknownFormat)));
        let png = png_bytes(64, 64);
        assert!(matches!(decode(&png[..png.len() / 2], &limits), Err(DecodeError::Corrupt(_))));
    }

    #[test]
    fn a_jpeg_cut_anywhere_is_refused_and_a_whole_one_with_a_trailer_is_not() {
        let img = RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, (x ^ y) as u8]));
        let mut jpeg = Vec::new();
        img.write_to(&mut Cursor::new(&mut jpeg), ImageFormat::Jpeg).unwrap();
        let limits = DecodeLimits::default();
        assert!(decode(&jpeg, &limits).is_ok());
        for share in [0.1, 0.5, 0.9, 0.99] {
            let cut = &jpeg[..(jpeg.len() as f64 * share) as usize];
            let err = decode(cut, &limits).unwrap_err();
            assert!(matches!(err, DecodeError::CutShort | DecodeError::Corrupt(_)), "{share}: {err}");
        }
        // The decoder alone pads the missing end: without the check, the cut file is an image.
        assert!(jpeg_cut_short(&jpeg[..jpeg.len() - 40]));
        let mut trailer = jpeg.clone();
        trailer.extend(b"camera trailer after the end marker");
        assert!(!jpeg_cut_short(&trailer));
        assert!(decode(&trailer, &limits).is_ok());
    }

    fn encode_with_exif(mut enc: impl image::ImageEncoder, img: &RgbImage, orientation: u16) {
        enc.set_exif_metadata(crate::synth::exif_orientation(orientation)).unwrap();
        enc.write_image(img.as_raw(), img.width(), img.height(), image::ExtendedColorType::Rgb8).unwrap();
    }

    #[test]
    fn every_exif_orientation_comes_out_upright() {
        use image::codecs::jpeg::JpegEncoder;
        use image::codecs::png::PngEncoder;
        // Flat 16-pixel blocks, so JPEG's loss cannot confuse one block with another.
        let (bw, bh) = (3u32, 2u32);
        let block = |bx: u32, by: u32| [(40 + 70 * bx) as u8, (30 + 150 * by) as u8, 128];
        let stored = RgbImage::from_fn(bw * 16, bh * 16, |x, y| image::Rgb(block(x / 16, y / 16)));
        for o in 1..=8u16 {
            for format in ["png", "jpeg"] {
                let mut bytes = Vec::new();
                match format {
                    "png" => encode_with_exif(PngEncoder::new(&mut bytes), &stored, o),
                    _ => encode_with_exif(JpegEncoder::new_with_quality(&mut bytes, 95), &stored, o),
                }
                let img = decode(&bytes, &DecodeLimits::default()).unwrap().to_rgb8();
                let turned = o >= 5;
                let (w, h) = if turned { (bh, bw) } else { (bw, bh) };
                assert_eq!((img.width(), img.height()), (w * 16, h * 16), "{format} orientation {o}");
                for by in 0..h {
                    for bx in 0..w {
                        let (sx, sy) = crate::synth::stored_position(
                            o,
                            bx as usize,
                            by as usize,
                            bw as usize,
                            bh as usize,
                        );
                        let got = img.get_pixel(bx * 16 + 8, by * 16 + 8).0;
                        let want = block(sx as u32, sy as u32);
                        let close = got.iter().zip(want).all(|(&g, w)| (g as i32 - w as i32).abs() <= 8);
                        assert!(
                            close,
                            "{format} orientation {o}: block ({bx}, {by}) is {got:?}, want {want:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn refuses_more_pixels_than_the_limit_before_decoding() {
        let limits = DecodeLimits { max_pixels: 100 };
        let err = decode(&png_bytes(11, 10), &limits).unwrap_err();
        assert!(matches!(err, DecodeError::TooLarge { pixels: 110, .. }), "{err}");
    }
}
