//! Decoding of image bytes with limits and EXIF orientation (pure layer: bytes in, pixels
//! out; reading the file is the caller's business). Pixels come out in the working colour
//! space (sRGB, see [`super::colour`]), read through the file's embedded profile; the
//! metadata a result keeps of its keyframe comes out beside them.

use std::io::Cursor;

use image::{DynamicImage, ImageDecoder, ImageReader, Limits};
use thiserror::Error;

use super::colour::{Space, to_working};
use super::convert::{to_mask, to_rgb};
use super::meta::{Metadata, strip_exif_header};
use super::{Mask, RgbF32};

/// HEIC and AVIF through libheif: a backend of this module's, behind [`decode`].
mod heif;

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
    #[error("not an image in a format clearview reads (JPEG, PNG, TIFF, WebP, HEIC/HEIF)")]
    UnknownFormat,
    #[error("{width}x{height} is {pixels} pixels, more than the limit of {limit}")]
    TooLarge { width: u32, height: u32, pixels: u64, limit: u64 },
    #[error("image has no pixels ({width}x{height})")]
    Degenerate { width: u32, height: u32 },
    #[error("the file ends before the image does (cut short: an upload that did not finish?)")]
    CutShort,
    #[error("cannot decode: {}", .0.to_string().trim_end())]
    Corrupt(#[source] image::ImageError),
    #[error("cannot decode HEIF: {0}")]
    Heif(String),
    #[error("a HEIF image in a codec this build of libheif cannot decode: {0}")]
    HeifCodec(String),
}

/// A decoded photograph: pixels upright in the working space (sRGB), its metadata, and
/// what was wrong with it but did not stop it (an unusable colour profile).
pub struct Photo {
    pub image: DynamicImage,
    pub meta: Metadata,
    pub warnings: Vec<String>,
}

/// Decodes `bytes` into an image, upright (EXIF orientation applied), within `limits`, in
/// the working colour space; a warning (an unusable profile, read as sRGB) is logged.
pub fn decode(bytes: &[u8], limits: &DecodeLimits) -> Result<DynamicImage, DecodeError> {
    let photo = decode_photo(bytes, limits)?;
    for w in &photo.warnings {
        tracing::warn!(warning = %w, "image read with a warning");
    }
    Ok(photo.image)
}

/// Decodes a mask: upright, within `limits`, with its pixels as stored (a mask's white is
/// white in any colour space, and an embedded profile would cost it its transparency), read
/// as [`to_mask`] reads an image.
pub fn decode_mask(bytes: &[u8], limits: &DecodeLimits) -> Result<Mask, DecodeError> {
    let (image, _) = decode_stored(bytes, limits)?;
    Ok(to_mask(&image))
}

/// [`decode`] with the metadata and the warnings.
pub fn decode_photo(bytes: &[u8], limits: &DecodeLimits) -> Result<Photo, DecodeError> {
    let (image, mut meta) = decode_stored(bytes, limits)?;
    let (space, warning) = Space::from_icc(meta.icc.as_deref());
    if warning.is_some() {
        meta.icc = None;
    }
    let image = to_working(image, &space);
    meta.space = space;
    Ok(Photo { image, meta, warnings: warning.into_iter().collect() })
}

/// Pixels as stored (upright, in the file's own colour space) and the metadata.
fn decode_stored(bytes: &[u8], limits: &DecodeLimits) -> Result<(DynamicImage, Metadata), DecodeError> {
    if bytes.is_empty() {
        return Err(DecodeError::Empty);
    }
    if heif::is_heif(bytes) {
        return heif::decode(bytes, limits);
    }
    let img = decode_image(bytes, limits)?;
    Ok(img)
}

/// The formats `image` reads: pixels upright, metadata as the decoder reports it (a
/// metadata block it cannot read is left out, never fatal).
fn decode_image(bytes: &[u8], limits: &DecodeLimits) -> Result<(DynamicImage, Metadata), DecodeError> {
    let mut reader = ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| DecodeError::Corrupt(image::ImageError::IoError(e)))?;
    // Our own limits are set below, once the size is known.
    reader.no_limits();
    if reader.format().is_none() {
        return Err(DecodeError::UnknownFormat);
    }
    if reader.format() == Some(image::ImageFormat::Jpeg) && jpeg_cut_short(bytes) {
        // The JPEG decoder pads a missing end with grey rather than failing: a cut file
        // would become a view with a grey band.
        return Err(DecodeError::CutShort);
    }
    let tiff = reader.format() == Some(image::ImageFormat::Tiff);
    let mut decoder = reader.into_decoder().map_err(DecodeError::Corrupt)?;
    let mut meta = decoder_metadata(&mut decoder);
    if tiff {
        tiff_metadata(bytes, &mut meta);
    }
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
    Ok((img, meta))
}

/// What a decoder reports besides pixels (a block it cannot read is left out).
fn decoder_metadata(decoder: &mut impl ImageDecoder) -> Metadata {
    let color = decoder.color_type();
    Metadata {
        exif: decoder.exif_metadata().ok().flatten().map(|e| strip_exif_header(&e).to_vec()),
        xmp: decoder.xmp_metadata().ok().flatten(),
        iptc: decoder.iptc_metadata().ok().flatten(),
        icc: decoder.icc_profile().ok().flatten(),
        space: Space::Srgb,
        bits: if color.bytes_per_pixel() > color.channel_count() { 16 } else { 8 },
    }
}

/// A TIFF's ICC profile and XMP, read with the `tiff` crate: `image`'s TIFF decoder, once
/// its limits are set (`into_decoder` always sets them), no longer finds them.
fn tiff_metadata(bytes: &[u8], meta: &mut Metadata) {
    use tiff::tags::Tag;
    let Ok(mut d) = tiff::decoder::Decoder::new(Cursor::new(bytes)) else { return };
    meta.icc = meta.icc.take().or_else(|| d.get_tag_u8_vec(Tag::Unknown(34675)).ok());
    meta.xmp = meta.xmp.take().or_else(|| d.get_tag_u8_vec(Tag::Unknown(700)).ok());
    meta.exif = meta.exif.take().or_else(|| tiff_exif(bytes));
}

/// A TIFF's camera fields (its EXIF and GPS directories, and the main directory's tags that
/// describe the picture rather than how its pixels are stored) as a compact EXIF structure.
fn tiff_exif(bytes: &[u8]) -> Option<Vec<u8>> {
    use exif::{Context, In};
    // Make, Model, ImageDescription, Orientation, resolution, Software, DateTime, Artist,
    // Copyright: the main directory's fields that say nothing of the stored pixels.
    const PICTURE: [u16; 11] = [270, 271, 272, 274, 282, 283, 296, 305, 306, 315, 33432];
    let parsed = exif::Reader::new().read_raw(bytes.to_vec()).ok()?;
    let mut w = exif::experimental::Writer::new();
    let fields: Vec<&exif::Field> = parsed
        .fields()
        .filter(|f| f.ifd_num == In::PRIMARY && !matches!(f.value, exif::Value::Unknown(..)))
        .filter(|f| match f.tag.0 {
            Context::Tiff => PICTURE.contains(&f.tag.1),
            Context::Exif | Context::Gps => true,
            _ => false,
        })
        .collect();
    if !fields.iter().any(|f| f.tag.0 != Context::Tiff || f.tag.1 != 274) {
        return None;
    }
    for f in &fields {
        w.push_field(f);
    }
    let mut out = Cursor::new(Vec::new());
    w.write(&mut out, parsed.little_endian()).ok()?;
    Some(out.into_inner())
}

/// The metadata of an image without decoding its pixels (the service reads its keyframe's
/// again when it writes a result); the colour space resolved as [`decode_photo`] does.
pub fn read_metadata(bytes: &[u8]) -> Result<Metadata, DecodeError> {
    let mut meta = if heif::is_heif(bytes) {
        heif::read_metadata(bytes)?
    } else {
        let mut reader = ImageReader::new(Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| DecodeError::Corrupt(image::ImageError::IoError(e)))?;
        // Nothing is decoded but the headers (see `decode_image`).
        reader.no_limits();
        let tiff = reader.format() == Some(image::ImageFormat::Tiff);
        let mut meta = decoder_metadata(&mut reader.into_decoder().map_err(DecodeError::Corrupt)?);
        if tiff {
            tiff_metadata(bytes, &mut meta);
        }
        meta
    };
    let (space, warning) = Space::from_icc(meta.icc.as_deref());
    if warning.is_some() {
        meta.icc = None;
    }
    meta.space = space;
    Ok(meta)
}

/// What a result needs of its keyframe's file (the service reads it again when it writes
/// one): the metadata, and the pixels in the working space at full precision when the file
/// holds more than the service keeps of a keyframe, 8-bit sRGB (samples deeper than 8 bits,
/// or a colour profile whose levels fall between sRGB's); `None` for an 8-bit sRGB file.
pub fn read_key(bytes: &[u8], limits: &DecodeLimits) -> Result<(Metadata, Option<RgbF32>), DecodeError> {
    let meta = read_metadata(bytes)?;
    if meta.bits <= 8 && meta.space.is_srgb() {
        return Ok((meta, None));
    }
    let photo = decode_photo(bytes, limits)?;
    Ok((photo.meta, Some(to_rgb(&photo.image))))
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

    #[test]
    fn a_mask_keeps_its_transparency_under_a_colour_profile() {
        // A PNG mask with an embedded profile (an editor's export): a photograph is read
        // through the profile into RGB, which drops the alpha; the mask is read as stored.
        let img = image::RgbaImage::from_fn(40, 30, |x, _| {
            if x < 10 { image::Rgba([255, 255, 255, 255]) } else { image::Rgba([255, 255, 255, 0]) }
        });
        let mut bytes = Vec::new();
        let mut enc = image::codecs::png::PngEncoder::new(&mut bytes);
        image::ImageEncoder::set_icc_profile(&mut enc, super::super::colour::adobe_rgb_icc()).unwrap();
        image::ImageEncoder::write_image(enc, img.as_raw(), 40, 30, image::ExtendedColorType::Rgba8).unwrap();
        let limits = DecodeLimits::default();
        assert!(decode_photo(&bytes, &limits).unwrap().meta.icc.is_some(), "the profile is read");
        let mask = decode_mask(&bytes, &limits).unwrap();
        assert_eq!(mask.hole_count(), 10 * 30);
        assert!(mask.is_hole(0, 0) && !mask.is_hole(10, 0));
        assert!(matches!(
            decode_mask(&bytes, &DecodeLimits { max_pixels: 100 }),
            Err(DecodeError::TooLarge { .. })
        ));
    }
}
