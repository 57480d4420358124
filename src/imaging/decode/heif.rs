//! HEIC/HEIF (and AVIF) decoding through libheif (pure layer: bytes in, pixels and
//! metadata out). libheif applies the file's rotation and mirror boxes itself, so the
//! pixels come out upright and the EXIF orientation (which libheif's writers set to 1, and
//! phones keep consistent with those boxes) is not applied a second time. Samples deeper
//! than 8 bits (10-bit HEIC) are read at full precision into 16-bit RGB.

use image::{DynamicImage, ImageBuffer, RgbImage};
use libheif_rs::{
    ColorPrimaries, ColorSpace, HeifContext, HeifError, HeifErrorCode, HeifErrorSubCode, ImageHandle, ItemId,
    LibHeif, RgbChroma,
};

use super::{DecodeError, DecodeLimits};
use crate::imaging::meta::Metadata;

/// Whether `bytes` start like an ISO base media file of the HEIF family (HEIC, HEIF, AVIF).
pub fn is_heif(bytes: &[u8]) -> bool {
    const BRANDS: [&[u8; 4]; 12] = [
        b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"hevm", b"hevs", b"mif1", b"msf1", b"avif",
        b"avis",
    ];
    bytes.len() >= 12 && &bytes[4..8] == b"ftyp" && BRANDS.iter().any(|b| &bytes[8..12] == *b)
}

/// The metadata of a HEIF file's primary image, without decoding it.
pub fn read_metadata(bytes: &[u8]) -> Result<Metadata, DecodeError> {
    let _lib = LibHeif::new();
    let ctx = HeifContext::read_from_bytes(bytes).map_err(heif_error)?;
    let handle = ctx.primary_image_handle().map_err(heif_error)?;
    Ok(metadata(&handle))
}

/// Decodes the primary image of a HEIF file, upright, within `limits`, with its metadata
/// (the ICC profile embedded, or made from the file's colour description, nclx).
pub fn decode(bytes: &[u8], limits: &DecodeLimits) -> Result<(DynamicImage, Metadata), DecodeError> {
    let lib = LibHeif::new();
    let ctx = HeifContext::read_from_bytes(bytes).map_err(heif_error)?;
    let handle = ctx.primary_image_handle().map_err(heif_error)?;
    let (width, height) = (handle.width(), handle.height());
    let pixels = u64::from(width) * u64::from(height);
    if pixels > limits.max_pixels {
        return Err(DecodeError::TooLarge { width, height, pixels, limit: limits.max_pixels });
    }
    if pixels == 0 {
        return Err(DecodeError::Degenerate { width, height });
    }
    let depth = handle.luma_bits_per_pixel();
    let deep = depth > 8;
    let chroma = if deep { RgbChroma::HdrRgbLe } else { RgbChroma::Rgb };
    let decoded = lib.decode(&handle, ColorSpace::Rgb(chroma), None).map_err(heif_error)?;
    let plane =
        decoded.planes().interleaved.ok_or_else(|| DecodeError::Heif("no RGB plane decoded".into()))?;
    let (w, h, stride) = (plane.width as usize, plane.height as usize, plane.stride);
    let image = if deep {
        let max = f64::from((1u32 << plane.bits_per_pixel.clamp(9, 16)) - 1);
        let mut data = Vec::with_capacity(3 * w * h);
        for y in 0..h {
            let row = &plane.data[y * stride..y * stride + 6 * w];
            data.extend(row.chunks_exact(2).map(|b| {
                let v = f64::from(u16::from_le_bytes([b[0], b[1]]));
                (v * 65535.0 / max).round().min(65535.0) as u16
            }));
        }
        DynamicImage::ImageRgb16(ImageBuffer::from_raw(w as u32, h as u32, data).expect("whole rows"))
    } else {
        let mut data = Vec::with_capacity(3 * w * h);
        for y in 0..h {
            data.extend_from_slice(&plane.data[y * stride..y * stride + 3 * w]);
        }
        DynamicImage::ImageRgb8(RgbImage::from_raw(w as u32, h as u32, data).expect("whole rows"))
    };

    Ok((image, metadata(&handle)))
}

fn metadata(handle: &ImageHandle) -> Metadata {
    let mut ids: Vec<ItemId> = vec![0; 16];
    let n = handle.metadata_block_ids(&mut ids, 0);
    let (mut exif, mut xmp) = (None, None);
    for &id in &ids[..n] {
        let kind = handle.metadata_type(id).unwrap_or_default().to_owned();
        let content = handle.metadata_content_type(id).unwrap_or_default().to_owned();
        let Ok(block) = handle.metadata(id) else { continue };
        if kind == "Exif" && exif.is_none() {
            // A 4-byte offset to the TIFF header, counted from just after it.
            if let Some(off) = block.get(..4).map(|b| u32::from_be_bytes([b[0], b[1], b[2], b[3]]) as usize)
                && let Some(tiff) = block.get(4 + off..)
            {
                exif = Some(tiff.to_vec());
            }
        } else if kind == "mime" && content == "application/rdf+xml" && xmp.is_none() {
            xmp = Some(block);
        }
    }
    let icc = match handle.color_profile_raw() {
        Some(raw) if !raw.data.is_empty() => Some(raw.data),
        _ => handle.color_profile_nclx().and_then(|nclx| match nclx.color_primaries() {
            ColorPrimaries::SMPTE_EG_432_1 => moxcms::ColorProfile::new_display_p3().encode().ok(),
            ColorPrimaries::ITU_R_BT_2020_2_and_2100_0 => moxcms::ColorProfile::new_bt2020().encode().ok(),
            _ => None,
        }),
    };
    let bits = if handle.luma_bits_per_pixel() > 8 { 16 } else { 8 };
    Metadata { exif, xmp, iptc: None, icc, space: crate::imaging::colour::Space::Srgb, bits }
}

/// libheif's error as ours: a file cut short, a codec libheif was built without, or the
/// library's own words.
fn heif_error(e: HeifError) -> DecodeError {
    match (e.code, e.sub_code) {
        (_, HeifErrorSubCode::EndOfData) => DecodeError::CutShort,
        (HeifErrorCode::UnsupportedFeature, HeifErrorSubCode::UnsupportedCodec)
        | (HeifErrorCode::DecoderPluginError, _) => DecodeError::HeifCodec(e.message),
        _ => DecodeError::Heif(e.message),
    }
}
