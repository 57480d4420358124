//! Encoding of results (pure layer: pixels and metadata in, bytes out), one path for the
//! commands and the service: the working-space pixels are put back into the keyframe's
//! colour space (or sRGB, on request), quantised to 8 bits (16 for PNG and TIFF when the
//! keyframe had more than 8), and written with the keyframe's metadata as a result keeps it
//! ([`super::meta`]): EXIF, XMP, IPTC (JPEG and TIFF) and the ICC profile.

use std::io::Cursor;

use exif::experimental::Writer;
use exif::{Context, Field, In, Tag, Value};
use rayon::prelude::*;
use thiserror::Error;

use super::RgbF32;
use super::colour::{Space, from_working, srgb_icc};
use super::meta::{Metadata, Provenance, result_exif, result_fields, result_xmp};

/// The formats results are written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Png,
    Jpeg,
    Tiff,
    WebP,
}

impl Format {
    /// The format a file extension names, if clearview writes it.
    pub fn from_extension(ext: &str) -> Option<Self> {
        match ext.to_ascii_lowercase().as_str() {
            "png" => Some(Format::Png),
            "jpg" | "jpeg" => Some(Format::Jpeg),
            "tif" | "tiff" => Some(Format::Tiff),
            "webp" => Some(Format::WebP),
            _ => None,
        }
    }
}

/// The colour space a result is written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum OutputSpace {
    /// The keyframe's own, with its profile (sRGB when it had none).
    #[default]
    Keyframe,
    /// sRGB, with an sRGB profile when the keyframe had a profile.
    Srgb,
}

impl std::str::FromStr for OutputSpace {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "keyframe" => Ok(OutputSpace::Keyframe),
            "srgb" => Ok(OutputSpace::Srgb),
            other => Err(format!("{other:?}: the colour space is `keyframe` or `srgb`")),
        }
    }
}

/// How a result is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncodeOptions {
    /// Quality of the lossy formats, 1 to 100. JPEG: [`DEFAULT_QUALITY`] when `None`. WebP:
    /// lossy (VP8) at this quality, lossless (VP8L) when `None`.
    pub quality: Option<u8>,
    pub space: OutputSpace,
}

/// JPEG quality of results by default: `image`'s default, which clearview has always used.
pub const DEFAULT_QUALITY: u8 = 75;

impl Default for EncodeOptions {
    fn default() -> Self {
        Self { quality: None, space: OutputSpace::Keyframe }
    }
}

/// An encoded result and what it had to leave out.
#[derive(Debug)]
pub struct Encoded {
    pub bytes: Vec<u8>,
    pub warnings: Vec<String>,
}

/// Why a result could not be encoded.
#[derive(Debug, Error)]
pub enum EncodeError {
    #[error("cannot encode JPEG: {0}")]
    Jpeg(#[from] jpeg_encoder::EncodingError),
    #[error("cannot encode PNG: {0}")]
    Png(#[from] png::EncodingError),
    #[error("cannot encode TIFF: {0}")]
    Tiff(exif::Error),
    #[error("cannot encode WebP: {0}")]
    WebP(#[from] image_webp::EncodingError),
    #[error("cannot encode WebP: {0}")]
    WebPLossy(#[from] super::webp::WebPError),
    #[error("{width}x{height} is too large for JPEG (at most 65535 pixels a side)")]
    TooLargeForJpeg { width: usize, height: usize },
}

/// Largest payload of a JPEG APP segment.
const APP_MAX: usize = 65533;

/// `rgb` (working space) as a `format` file carrying `meta` (the keyframe's) and
/// `provenance` (in its XMP).
pub fn encode(
    rgb: &RgbF32,
    format: Format,
    opts: &EncodeOptions,
    meta: &Metadata,
    provenance: &Provenance,
) -> Result<Encoded, EncodeError> {
    let (w, h) = (rgb.width(), rgb.height());
    let mut warnings = Vec::new();
    let (space, icc) = match opts.space {
        OutputSpace::Keyframe => (meta.space.clone(), meta.icc.clone()),
        OutputSpace::Srgb => (Space::Srgb, meta.icc.as_ref().map(|_| srgb_icc())),
    };
    let converted;
    let pixels = if space.is_srgb() {
        rgb
    } else {
        converted = from_working(rgb, &space);
        &converted
    };
    let deep = meta.bits > 8 && matches!(format, Format::Png | Format::Tiff);
    let exif = meta.exif.as_deref().and_then(|e| match result_exif(e, w as u32, h as u32) {
        Ok(x) => Some(x),
        Err(err) => {
            warnings.push(format!("the keyframe's EXIF is unreadable ({err}): left out"));
            None
        }
    });
    let xmp = result_xmp(meta.xmp.as_deref(), provenance);
    // IPTC as Photoshop image resources: JPEG's APP13 carries them after its signature,
    // TIFF's tag 34377 as they are. PNG and WebP have no standard place for them.
    let iptc = meta.iptc.as_deref().map(|i| i.strip_prefix(b"\0").unwrap_or(i));
    if iptc.is_some() && matches!(format, Format::Png | Format::WebP) {
        warnings.push(
            "IPTC has no standard place in PNG or WebP: left out (its XMP copy, if any, is kept)".into(),
        );
    }
    let bytes = match format {
        Format::Jpeg => {
            let (Ok(wj), Ok(hj)) = (u16::try_from(w), u16::try_from(h)) else {
                return Err(EncodeError::TooLargeForJpeg { width: w, height: h });
            };
            let raw = quantise8(pixels);
            let mut out = Vec::with_capacity(raw.len() / 8);
            let quality = opts.quality.unwrap_or(DEFAULT_QUALITY).clamp(1, 100);
            let mut enc = jpeg_encoder::Encoder::new(&mut out, quality);
            enc.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_4_4);
            let mut app = |nr: u8, signature: &[u8], data: &[u8], what: &str| -> Result<(), EncodeError> {
                if signature.len() + data.len() > APP_MAX {
                    warnings.push(format!(
                        "{what} is {} bytes, more than a JPEG segment holds: left out",
                        data.len()
                    ));
                    return Ok(());
                }
                enc.add_app_segment(nr, [signature, data].concat())?;
                Ok(())
            };
            if let Some(e) = &exif {
                app(1, b"Exif\0\0", e, "the EXIF")?;
            }
            app(1, b"http://ns.adobe.com/xap/1.0/\0", &xmp, "the XMP")?;
            if let Some(i) = iptc {
                app(13, b"Photoshop 3.0\0", i, "the IPTC")?;
            }
            if let Some(p) = &icc {
                enc.add_icc_profile(p)?;
            }
            enc.encode(&raw, wj, hj, jpeg_encoder::ColorType::Rgb)?;
            out
        }
        Format::Png => {
            let mut out = Vec::new();
            let mut info = png::Info::with_size(w as u32, h as u32);
            info.color_type = png::ColorType::Rgb;
            info.bit_depth = if deep { png::BitDepth::Sixteen } else { png::BitDepth::Eight };
            info.icc_profile = icc.map(Into::into);
            info.exif_metadata = exif.map(Into::into);
            let mut enc = png::Encoder::with_info(&mut out, info)?;
            // Fast deflate with the Sub filter: a 12 MP result encodes in a fraction of a
            // second (adaptive filtering costs more than it saves on photographs).
            enc.set_compression(png::Compression::Fast);
            enc.set_filter(png::Filter::Sub);
            enc.add_itxt_chunk("XML:com.adobe.xmp".into(), String::from_utf8_lossy(&xmp).into_owned())?;
            let mut writer = enc.write_header()?;
            let data = if deep { quantise16(pixels, true) } else { quantise8(pixels) };
            writer.write_image_data(&data)?;
            writer.finish()?;
            out
        }
        Format::Tiff => tiff(pixels, deep, meta, icc.as_deref(), &xmp, iptc)?,
        Format::WebP => match opts.quality {
            Some(quality) => {
                use super::webp::{Chunk, encode_lossy};
                let mut chunks = vec![(Chunk::Xmp, xmp.as_slice())];
                chunks.extend(icc.as_deref().map(|p| (Chunk::Icc, p)));
                chunks.extend(exif.as_deref().map(|e| (Chunk::Exif, e)));
                encode_lossy(&quantise8(pixels), w, h, quality, &chunks)?
            }
            None => webp_lossless(pixels, icc, exif, xmp)?,
        },
    };
    Ok(Encoded { bytes, warnings })
}

/// A lossless WebP (VP8L) through `image-webp`, with the profile, EXIF and XMP.
fn webp_lossless(
    pixels: &RgbF32,
    icc: Option<Vec<u8>>,
    exif: Option<Vec<u8>>,
    xmp: Vec<u8>,
) -> Result<Vec<u8>, EncodeError> {
    let (w, h) = (pixels.width(), pixels.height());
    let mut out = Vec::new();
    let mut enc = image_webp::WebPEncoder::new(&mut out);
    if let Some(p) = icc {
        enc.set_icc_profile(p);
    }
    if let Some(e) = exif {
        enc.set_exif_metadata(e);
    }
    enc.set_xmp_metadata(xmp);
    enc.encode(&quantise8(pixels), w as u32, h as u32, image_webp::ColorType::Rgb8)?;
    Ok(out)
}

/// An uncompressed TIFF written with `kamadak-exif`'s writer, which lays out the EXIF and GPS
/// directories the keyframe's fields need; samples little-endian.
fn tiff(
    pixels: &RgbF32,
    deep: bool,
    meta: &Metadata,
    icc: Option<&[u8]>,
    xmp: &[u8],
    iptc: Option<&[u8]>,
) -> Result<Vec<u8>, EncodeError> {
    let (w, h) = (pixels.width() as u32, pixels.height() as u32);
    let data = if deep { quantise16(pixels, false) } else { quantise8(pixels) };
    let row = data.len() / h.max(1) as usize;
    let rows_per_strip = ((1usize << 20) / row.max(1)).max(1);
    let strips: Vec<&[u8]> = data.chunks(row * rows_per_strip).collect();
    let bits = if deep { 16 } else { 8 };
    // Fields that describe the stored pixels are ours; the keyframe's others are kept.
    let structural = [256u16, 257, 258, 259, 262, 273, 277, 278, 279, 284, 700, 33723, 34377, 34675];
    let mut fields: Vec<Field> = match meta.exif.as_deref().map(|e| result_fields(e, w, h)) {
        Some(Ok((f, _))) => {
            f.into_iter().filter(|f| !(f.tag.0 == Context::Tiff && structural.contains(&f.tag.1))).collect()
        }
        _ => Vec::new(),
    };
    let field = |n: u16, value| Field { tag: Tag(Context::Tiff, n), ifd_num: In::PRIMARY, value };
    fields.extend([
        field(256, Value::Long(vec![w])),
        field(257, Value::Long(vec![h])),
        field(258, Value::Short(vec![bits; 3])),
        field(259, Value::Short(vec![1])),
        field(262, Value::Short(vec![2])),
        field(277, Value::Short(vec![3])),
        field(278, Value::Long(vec![rows_per_strip as u32])),
        field(284, Value::Short(vec![1])),
        field(700, Value::Byte(xmp.to_vec())),
    ]);
    if meta.exif.is_none() {
        fields.push(field(305, Value::Ascii(vec![super::meta::SOFTWARE.as_bytes().to_vec()])));
    }
    if let Some(p) = icc {
        fields.push(field(34675, Value::Byte(p.to_vec())));
    }
    if let Some(i) = iptc {
        fields.push(field(34377, Value::Byte(i.to_vec())));
    }
    let mut writer = Writer::new();
    for f in &fields {
        writer.push_field(f);
    }
    writer.set_strips(&strips, In::PRIMARY);
    let mut out = Cursor::new(Vec::with_capacity(data.len() + 4096));
    writer.write(&mut out, true).map_err(EncodeError::Tiff)?;
    Ok(out.into_inner())
}

/// RGB 0..=1 to interleaved 8-bit, rows in parallel (as `convert::to_rgb8` rounds).
pub fn quantise8(image: &RgbF32) -> Vec<u8> {
    let w = image.width();
    let mut raw = vec![0u8; 3 * image.len()];
    if w == 0 {
        return raw;
    }
    raw.par_chunks_mut(3 * w).zip(image.as_slice().par_chunks(w)).for_each(|(dst, src)| {
        for (d, p) in dst.chunks_exact_mut(3).zip(src) {
            for k in 0..3 {
                // `as u8` saturates (and maps NaN to 0): the clamp comes free; + 0.5 then
                // truncation rounds half up, like `round` on non-negative values.
                d[k] = (p[k] * 255.0 + 0.5) as u8;
            }
        }
    });
    raw
}

/// RGB 0..=1 to interleaved 16-bit samples as bytes, big-endian (PNG) or little-endian.
fn quantise16(image: &RgbF32, big_endian: bool) -> Vec<u8> {
    let w = image.width();
    let mut raw = vec![0u8; 6 * image.len()];
    if w == 0 {
        return raw;
    }
    raw.par_chunks_mut(6 * w).zip(image.as_slice().par_chunks(w)).for_each(|(dst, src)| {
        for (d, p) in dst.chunks_exact_mut(6).zip(src) {
            for k in 0..3 {
                let v = (p[k] * 65535.0).round().clamp(0.0, 65535.0) as u16;
                let b = if big_endian { v.to_be_bytes() } else { v.to_le_bytes() };
                d[2 * k..2 * k + 2].copy_from_slice(&b);
            }
        }
    });
    raw
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::colour::adobe_rgb_icc;
    use crate::imaging::decode::{DecodeLimits, decode_photo};

    fn camera_exif() -> Vec<u8> {
        let f = |tag, value| Field { tag, ifd_num: In::PRIMARY, value };
        let fields = [
            f(Tag::Make, Value::Ascii(vec![b"Canon".to_vec()])),
            f(Tag::Orientation, Value::Short(vec![8])),
            f(Tag::DateTimeOriginal, Value::Ascii(vec![b"2023:01:02 03:04:05".to_vec()])),
            f(Tag::GPSAltitude, Value::Rational(vec![(4321, 10).into()])),
        ];
        let mut w = Writer::new();
        for x in &fields {
            w.push_field(x);
        }
        let mut out = Cursor::new(Vec::new());
        w.write(&mut out, true).unwrap();
        out.into_inner()
    }

    #[test]
    fn quantising_agrees_with_the_core_conversion() {
        let img = RgbF32::from_fn(7, 5, |x, y| [x as f32 / 6.0, y as f32 / 4.0, 0.5031]);
        assert_eq!(quantise8(&img), crate::imaging::convert::to_rgb8(&img).into_raw());
    }

    #[test]
    fn every_format_carries_exif_xmp_and_the_profile_and_deep_keyframes_give_16_bits() {
        let rgb = RgbF32::from_fn(40, 30, |x, y| [x as f32 / 39.0, y as f32 / 29.0, 0.25 + 0.001 * x as f32]);
        let provenance = Provenance { report: Some("result.json".into()), views: vec!["v1.jpg".into()] };
        let icc = adobe_rgb_icc();
        for bits in [8u8, 16] {
            let meta = Metadata {
                exif: Some(camera_exif()),
                xmp: None,
                iptc: None,
                icc: Some(icc.clone()),
                space: crate::imaging::colour::Space::from_icc(Some(&icc)).0,
                bits,
            };
            let lossless = [Format::Jpeg, Format::Png, Format::Tiff, Format::WebP].map(|f| (f, None));
            for (format, quality) in lossless.into_iter().chain([(Format::WebP, Some(90))]) {
                let opts = EncodeOptions { quality, ..EncodeOptions::default() };
                let enc = encode(&rgb, format, &opts, &meta, &provenance).unwrap();
                assert!(enc.warnings.is_empty(), "{format:?}: {:?}", enc.warnings);
                let back = decode_photo(&enc.bytes, &DecodeLimits::default()).unwrap();
                let what = format!("{format:?} (quality {quality:?}) from a {bits}-bit keyframe");
                assert_eq!(back.meta.icc.as_deref(), Some(icc.as_slice()), "{what}: profile");
                let xmp = String::from_utf8(back.meta.xmp.clone().expect("XMP")).unwrap();
                assert!(xmp.contains("<rdf:li>v1.jpg</rdf:li>"), "{what}: {xmp}");
                let exif_bytes = match format {
                    // `image` does not read a TIFF's EXIF directory: the file is one.
                    Format::Tiff => enc.bytes.clone(),
                    _ => back.meta.exif.clone().expect("EXIF"),
                };
                let e = exif::Reader::new().read_raw(exif_bytes).unwrap();
                assert_eq!(
                    e.get_field(Tag::Orientation, In::PRIMARY).unwrap().value.get_uint(0),
                    Some(1),
                    "{what}"
                );
                assert!(e.get_field(Tag::GPSAltitude, In::PRIMARY).is_some(), "{what}: GPS");
                assert!(
                    e.get_field(Tag::DateTimeOriginal, In::PRIMARY).is_some(),
                    "{what}: DateTimeOriginal"
                );
                let deep = bits == 16 && matches!(format, Format::Png | Format::Tiff);
                assert_eq!(back.meta.bits, if deep { 16 } else { 8 }, "{what}: depth");
                // Read back through the profile: the working-space pixels again.
                let got = crate::imaging::convert::to_rgb(&back.image);
                let errors: Vec<f32> = got
                    .as_slice()
                    .iter()
                    .flatten()
                    .zip(rgb.as_slice().iter().flatten())
                    .map(|(a, b)| (a - b).abs())
                    .collect();
                let mean = errors.iter().sum::<f32>() / errors.len() as f32;
                let worst = errors.iter().copied().fold(0.0, f32::max);
                // JPEG's loss, in Adobe RGB, is magnified in sRGB's dark toe: judged on average.
                let ok = match format {
                    _ if quality.is_some() || format == Format::Jpeg => mean < 0.02,
                    _ if deep => worst < 0.002,
                    _ => worst < 0.05 && mean < 0.004,
                };
                assert!(ok, "{what}: off by {mean} on average, {worst} at worst");
            }
        }
    }
}
