//! Colour management (pure layer): every image is read through its embedded ICC profile
//! (sRGB when it has none) into one working space, gamma-encoded sRGB, where the fill
//! works; a result goes back into the keyframe's space before it is encoded.
//!
//! The transforms are `moxcms`'s (pure Rust, already in the tree through `image`):
//! matrix-shaper and LUT profiles, 8/16-bit and floating-point pipelines. Floating point is
//! used in extended range, so a keyframe's colours survive the round trip
//! keyframe space → sRGB → keyframe space even where they lie outside sRGB's gamut.

use std::fmt;
use std::sync::Arc;

use image::DynamicImage;
use moxcms::{ColorProfile, DataColorSpace, Layout, TransformOptions};
use rayon::prelude::*;

use super::RgbF32;

/// The colour space of an image's pixels, as far as clearview can tell.
#[derive(Clone)]
pub enum Space {
    /// sRGB: untagged, tagged with an sRGB profile, or a profile that could not be used.
    Srgb,
    /// A profile that is not sRGB, with its bytes (written back with the result).
    Icc(Arc<Profile>),
}

/// A usable RGB profile that is not sRGB.
pub struct Profile {
    pub bytes: Vec<u8>,
    pub description: String,
    parsed: ColorProfile,
}

impl fmt::Debug for Space {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Space::Srgb => f.write_str("sRGB"),
            Space::Icc(p) => write!(f, "ICC profile {:?} ({} bytes)", p.description, p.bytes.len()),
        }
    }
}

impl Space {
    /// The space an embedded profile names; `Err` carries the reason a profile was not used
    /// (the image is then treated as sRGB, and the caller warns).
    pub fn from_icc(icc: Option<&[u8]>) -> (Space, Option<String>) {
        let Some(bytes) = icc.filter(|b| !b.is_empty()) else { return (Space::Srgb, None) };
        let parsed = match ColorProfile::new_from_slice(bytes) {
            Ok(p) => p,
            Err(e) => return (Space::Srgb, Some(format!("ICC profile unreadable ({e}): treated as sRGB"))),
        };
        match parsed.color_space {
            DataColorSpace::Rgb => {}
            // A grey image's grey profile: its tone curve is close enough to sRGB's for a
            // mask or a grey photograph; nothing to warn about.
            DataColorSpace::Gray => return (Space::Srgb, None),
            other => {
                return (
                    Space::Srgb,
                    Some(format!("ICC profile for {other:?} data, not RGB: treated as sRGB")),
                );
            }
        }
        let description = description(&parsed);
        match is_srgb(&parsed) {
            Ok(true) => (Space::Srgb, None),
            Ok(false) => (Space::Icc(Arc::new(Profile { bytes: bytes.to_vec(), description, parsed })), None),
            Err(e) => {
                (Space::Srgb, Some(format!("ICC profile {description:?} unusable ({e}): treated as sRGB")))
            }
        }
    }

    pub fn is_srgb(&self) -> bool {
        matches!(self, Space::Srgb)
    }

    /// The profile's bytes, if the space is not sRGB.
    pub fn icc(&self) -> Option<&[u8]> {
        match self {
            Space::Srgb => None,
            Space::Icc(p) => Some(&p.bytes),
        }
    }
}

fn description(p: &ColorProfile) -> String {
    p.description
        .as_ref()
        .map(|d| match d {
            moxcms::ProfileText::PlainString(s) => s.clone(),
            moxcms::ProfileText::Localizable(v) => v.first().map(|l| l.value.clone()).unwrap_or_default(),
            moxcms::ProfileText::Description(d) => d.ascii_string.clone(),
        })
        .unwrap_or_default()
        .trim_end_matches('\0')
        .to_owned()
}

fn options() -> TransformOptions {
    TransformOptions {
        allow_extended_range_rgb_xyz: true,
        prefer_fixed_point: false,
        ..TransformOptions::default()
    }
}

/// Whether `p` maps every colour of a 9×9×9 grid onto itself in sRGB within half an 8-bit
/// level: an sRGB profile by content, whatever its name (cameras write several variants).
fn is_srgb(p: &ColorProfile) -> Result<bool, moxcms::CmsError> {
    let t = p.create_transform_f32(Layout::Rgb, &ColorProfile::new_srgb(), Layout::Rgb, options())?;
    let grid: Vec<f32> =
        (0..9 * 9 * 9).flat_map(|i| [i % 9, (i / 9) % 9, i / 81].map(|v| v as f32 / 8.0)).collect();
    let mut out = vec![0.0; grid.len()];
    t.transform(&grid, &mut out)?;
    Ok(grid.iter().zip(&out).all(|(a, b)| (a - b).abs() <= 0.5 / 255.0))
}

/// `img` in the working space (sRGB): unchanged when it is sRGB already, otherwise as
/// floating-point RGB through its profile (alpha dropped, as the fill drops it anyway).
pub fn to_working(img: DynamicImage, space: &Space) -> DynamicImage {
    let Space::Icc(p) = space else { return img };
    let mut rgb = img.to_rgb32f();
    drop(img);
    transform_in_place(rgb.as_mut(), &p.parsed, &ColorProfile::new_srgb());
    DynamicImage::ImageRgb32F(rgb)
}

/// A working-space (sRGB) plane in `space`, values in 0..=1 where they fit.
pub fn from_working(rgb: &RgbF32, space: &Space) -> RgbF32 {
    let Space::Icc(p) = space else { return rgb.clone() };
    let mut flat: Vec<f32> = rgb.as_slice().iter().flatten().copied().collect();
    transform_in_place(&mut flat, &ColorProfile::new_srgb(), &p.parsed);
    let pixels = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    RgbF32::from_vec(rgb.width(), rgb.height(), pixels)
}

/// Interleaved RGB floats from `src`'s space to `dst`'s, in parallel chunks.
fn transform_in_place(data: &mut [f32], src: &ColorProfile, dst: &ColorProfile) {
    const CHUNK: usize = 3 * 16 * 1024;
    // Both profiles were checked when the space was built: a transform between them exists.
    let Ok(t) = src.create_transform_f32(Layout::Rgb, dst, Layout::Rgb, options()) else {
        debug_assert!(false, "a checked profile has a transform");
        return;
    };
    data.par_chunks_mut(CHUNK).for_each_init(
        || vec![0.0f32; CHUNK],
        |scratch, chunk| {
            let out = &mut scratch[..chunk.len()];
            if t.transform(chunk, out).is_ok() {
                chunk.copy_from_slice(out);
            }
        },
    );
}

/// An ICC profile of sRGB, for results written in sRGB on request.
pub fn srgb_icc() -> Vec<u8> {
    ColorProfile::new_srgb().encode().unwrap_or_default()
}

/// An ICC profile of Adobe RGB (1998), as cameras embed it (tests and demos).
pub fn adobe_rgb_icc() -> Vec<u8> {
    ColorProfile::new_adobe_rgb().encode().expect("moxcms encodes its own profiles")
}

/// `rgb` (sRGB, 8-bit interleaved) in Adobe RGB, 8-bit: how a camera set to Adobe RGB stores
/// the same scene (tests and demos).
pub fn srgb8_to_adobe8(rgb: &[u8]) -> Vec<u8> {
    let t = ColorProfile::new_srgb()
        .create_transform_8bit(
            Layout::Rgb,
            &ColorProfile::new_adobe_rgb(),
            Layout::Rgb,
            TransformOptions::default(),
        )
        .expect("sRGB to Adobe RGB");
    let mut out = vec![0u8; rgb.len()];
    t.transform(rgb, &mut out).expect("whole pixels");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn untagged_srgb_and_srgb_profiles_are_srgb_and_garbage_is_refused_with_a_reason() {
        assert!(Space::from_icc(None).0.is_srgb());
        let (s, w) = Space::from_icc(Some(&srgb_icc()));
        assert!(s.is_srgb() && w.is_none(), "{s:?} {w:?}");
        let (s, w) = Space::from_icc(Some(b"definitely not an ICC profile, just some bytes here"));
        assert!(s.is_srgb());
        assert!(w.unwrap().contains("treated as sRGB"));
        let (s, w) = Space::from_icc(Some(&adobe_rgb_icc()));
        assert!(!s.is_srgb() && w.is_none(), "{s:?} {w:?}");
    }

    #[test]
    fn adobe_rgb_reads_back_as_the_srgb_it_was_made_from_and_round_trips() {
        let srgb: Vec<u8> =
            (0..512u32).flat_map(|i| [(i * 7 % 256) as u8, (i * 13 % 256) as u8, (i / 2) as u8]).collect();
        let adobe = srgb8_to_adobe8(&srgb);
        assert_ne!(adobe, srgb);
        let img = image::RgbImage::from_raw(512, 1, adobe.clone()).unwrap();
        let (space, _) = Space::from_icc(Some(&adobe_rgb_icc()));
        let working = to_working(DynamicImage::ImageRgb8(img), &space).to_rgb32f();
        // Within the quantisation of 8-bit Adobe RGB, which near the edge of sRGB's gamut
        // moves a weak channel by several sRGB levels per Adobe level.
        let errors: Vec<f32> =
            working.as_raw().iter().zip(&srgb).map(|(&w, &s)| (w * 255.0 - s as f32).abs()).collect();
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        let worst = errors.iter().copied().fold(0.0, f32::max);
        assert!(
            mean < 0.8 && worst < 10.0,
            "sRGB recovered within {mean} levels on average, {worst} at worst"
        );
        // Back into Adobe RGB: the stored values, exactly after rounding.
        let plane =
            RgbF32::from_vec(512, 1, working.as_raw().chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect());
        let back = from_working(&plane, &space);
        let worst = back
            .as_slice()
            .iter()
            .flatten()
            .zip(&adobe)
            .map(|(&b, &a)| (b * 255.0 - a as f32).abs())
            .fold(0.0, f32::max);
        assert!(worst < 0.5, "round trip off by {worst} levels");
    }
}
