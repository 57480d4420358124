//! The provenance map as a picture (shell layer): which view filled each masked pixel of
//! a result, colour-coded into a transparent PNG with a legend, for the preview page; pixels
//! a view filled but the occlusion model is not sure of are shown apart, as doubtful; and the
//! surface map (`surfaces.png`: which surface off the wall filled each pixel) as an overlay.

use image::ImageEncoder;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};

use super::job::name_of;
use super::registry::LegendEntry;
use crate::inpaint::{CONFIDENT, Confidence, FALLBACK, KEYFRAME, Provenance};
use crate::session::{FillOutcome, Session};

/// The file beside a result that says which surface filled each pixel
/// ([`crate::session::FillOutcome::surface_map`]), named in `result.json` as `surfaces`.
pub const SURFACES: &str = "surfaces.png";

/// A result's maps, encoded: per name, its PNG, or `None` where the result has none.
pub type Maps = Vec<(&'static str, Option<Vec<u8>>)>;

/// The maps beside a result (each of [`crate::daemon::emit::MAPS`]), encoded, and the
/// provenance map's legend: the confidence (0 outside the mask, at least 128 where the fill
/// is sure the pixel shows the building), which surface off the wall filled each pixel when
/// the session sweeps for them, and where each pixel came from. A map that cannot be
/// encoded is not claimed (and one an earlier result left goes). `session` made `outcome`
/// (its provenance is the session's current result's).
pub fn result_maps(session: &Session, outcome: &FillOutcome) -> (Maps, Vec<LegendEntry>) {
    let png = |name: &str, map: &crate::imaging::Plane<u8>| {
        let mut png = std::io::Cursor::new(Vec::new());
        match crate::imaging::convert::plane_to_luma8(map).write_to(&mut png, image::ImageFormat::Png) {
            Ok(()) => Some(png.into_inner()),
            Err(e) => {
                tracing::warn!(error = %e, file = name, "cannot encode a map beside the result: it has none");
                None
            }
        }
    };
    let confidence = outcome.confidence.as_ref().and_then(|c| png("confidence.png", c));
    let surfaces = outcome.surface_map.as_ref().and_then(|m| png(SURFACES, m));
    let names: Vec<String> = outcome.views.iter().map(|id| name_of(id).to_owned()).collect();
    let (provenance, legend) = match session.provenance() {
        Some(map) => match render(&map, outcome.confidence.as_ref(), &names) {
            Ok((png, legend)) => (Some(png), legend),
            Err(e) => {
                tracing::warn!(error = %e, "cannot encode provenance.png: the result has none");
                (None, Vec::new())
            }
        },
        None => (None, Vec::new()),
    };
    (vec![("confidence.png", confidence), (SURFACES, surfaces), ("provenance.png", provenance)], legend)
}

/// Colours of sources 0, 1, ... (cycled), chosen apart from each other and from the
/// fallback's magenta.
const PALETTE: [[u8; 3]; 10] = [
    [0x1f, 0x77, 0xb4],
    [0xff, 0x7f, 0x0e],
    [0x2c, 0xa0, 0x2c],
    [0x17, 0xbe, 0xcf],
    [0xbc, 0xbd, 0x22],
    [0x94, 0x67, 0xbd],
    [0x8c, 0x56, 0x4b],
    [0x7f, 0x7f, 0x7f],
    [0x00, 0x33, 0x99],
    [0x66, 0xcc, 0x99],
];

/// The fallback's colour: pixels no view saw, invented from the keyframe alone.
pub const FALLBACK_COLOUR: [u8; 3] = [0xff, 0x00, 0xff];

/// The value shown for a pixel a view filled but the result is not sure of (it may show an
/// occluder, or the views disagree there): not a provenance value, a verdict over one.
pub const DOUBTFUL: u16 = FALLBACK - 1;
/// Its colour.
pub const DOUBTFUL_COLOUR: [u8; 3] = [0xd6, 0x27, 0x28];

/// The colour of provenance value `v` (`None`: transparent, the keyframe's own pixel).
pub fn colour(v: u16) -> Option<[u8; 3]> {
    match v {
        KEYFRAME => None,
        FALLBACK => Some(FALLBACK_COLOUR),
        DOUBTFUL => Some(DOUBTFUL_COLOUR),
        i => Some(PALETTE[usize::from(i - 1) % PALETTE.len()]),
    }
}

fn hex(c: [u8; 3]) -> String {
    format!("#{:02x}{:02x}{:02x}", c[0], c[1], c[2])
}

/// An RGBA PNG of `map` (keyframe pixels transparent, the others opaque in their source's
/// colour, those a view filled with a `confidence` below [`CONFIDENT`] in the doubtful
/// colour) and the legend of the values present, `names[i]` naming source `i`.
pub fn render(
    map: &Provenance,
    confidence: Option<&Confidence>,
    names: &[String],
) -> std::io::Result<(Vec<u8>, Vec<LegendEntry>)> {
    use rayon::prelude::*;
    use std::collections::BTreeMap;
    let (w, h) = (map.width(), map.height());
    // Row by row on every core: a 12 MP map took one core about 90 ms of every landing.
    let mut rgba = vec![0u8; w * h * 4];
    let counts = rgba
        .par_chunks_mut((4 * w).max(1))
        .enumerate()
        .map(|(y, out)| {
            let mut counts = BTreeMap::<u16, usize>::new();
            let mut run: Option<(u16, usize)> = None;
            for ((x, &v), px) in map.row(y).iter().enumerate().zip(out.chunks_exact_mut(4)) {
                let doubtful =
                    v != KEYFRAME && v != FALLBACK && confidence.is_some_and(|c| c.get(x, y) < CONFIDENT);
                let v = if doubtful { DOUBTFUL } else { v };
                match &mut run {
                    Some((value, n)) if *value == v => *n += 1,
                    _ => {
                        if let Some((value, n)) = run.replace((v, 1)) {
                            *counts.entry(value).or_default() += n;
                        }
                    }
                }
                if let Some(c) = colour(v) {
                    px.copy_from_slice(&[c[0], c[1], c[2], 255]);
                }
            }
            if let Some((value, n)) = run {
                *counts.entry(value).or_default() += n;
            }
            counts
        })
        .reduce(BTreeMap::new, |mut a, b| {
            for (value, n) in b {
                *a.entry(value).or_default() += n;
            }
            a
        });
    let mut png = Vec::new();
    PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Adaptive)
        .write_image(&rgba, w as u32, h as u32, image::ExtendedColorType::Rgba8)
        .map_err(std::io::Error::other)?;
    let legend = counts
        .into_iter()
        .map(|(value, pixels)| LegendEntry {
            source: match value {
                KEYFRAME => "keyframe".into(),
                FALLBACK => "fallback".into(),
                DOUBTFUL => "doubtful".into(),
                i => names.get(usize::from(i - 1)).cloned().unwrap_or_else(|| format!("source {}", i - 1)),
            },
            value,
            colour: colour(value).map_or_else(|| "transparent".into(), hex),
            pixels,
        })
        .collect();
    Ok((png, legend))
}

/// Colours of the surfaces off the wall 0, 1, ... (cycled) in the surface overlay: apart
/// from each other, and from the wall's grey. The page's legend (`app.js`) has the same.
pub const SURFACE_PALETTE: [[u8; 3]; 6] = [
    [0xe6, 0x19, 0x4b],
    [0x3c, 0xb4, 0x4b],
    [0x43, 0x63, 0xd8],
    [0xf5, 0x82, 0x31],
    [0x91, 0x1e, 0xb4],
    [0x42, 0xd4, 0xf4],
];

/// The wall's colour in the surface overlay, see-through: a pixel copied through its view's
/// wall (the paper's one homography).
pub const WALL_COLOUR: [u8; 4] = [0x80, 0x80, 0x80, 0x60];

/// The colour of surface-map value `v` (`surfaces.png`: 0 outside the mask, 1 the wall,
/// `2 + s` surface `s`) in the overlay.
pub fn surface_colour(v: u8) -> [u8; 4] {
    match v {
        0 => [0, 0, 0, 0],
        1 => WALL_COLOUR,
        s => {
            let c = SURFACE_PALETTE[usize::from(s - 2) % SURFACE_PALETTE.len()];
            [c[0], c[1], c[2], 255]
        }
    }
}

/// An RGBA PNG of a surface map (`surfaces.png`), for the preview page: outside the mask
/// transparent, the wall's pixels a see-through grey, each surface off the wall opaque in
/// its colour ([`surface_colour`]).
pub fn render_surfaces(map: &image::GrayImage) -> std::io::Result<Vec<u8>> {
    let rgba: Vec<u8> = map.as_raw().iter().flat_map(|&v| surface_colour(v)).collect();
    let mut png = Vec::new();
    PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Adaptive)
        .write_image(&rgba, map.width(), map.height(), image::ExtendedColorType::Rgba8)
        .map_err(std::io::Error::other)?;
    Ok(png)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_surface_overlay_shows_the_wall_see_through_and_each_surface_in_its_colour() {
        let map = image::GrayImage::from_raw(4, 2, vec![0, 1, 2, 3, 8, 1, 0, 2]).unwrap();
        let img = image::load_from_memory(&render_surfaces(&map).unwrap()).unwrap().to_rgba8();
        assert_eq!(img.get_pixel(0, 0).0[3], 0, "outside the mask: transparent");
        assert_eq!(img.get_pixel(1, 0).0, WALL_COLOUR);
        assert_eq!(img.get_pixel(2, 0).0, [0xe6, 0x19, 0x4b, 255], "surface 0");
        assert_eq!(img.get_pixel(3, 0).0, [0x3c, 0xb4, 0x4b, 255], "surface 1");
        assert_eq!(img.get_pixel(0, 1).0, img.get_pixel(2, 0).0, "surface 6 cycles to surface 0's colour");
        assert_eq!(img.get_pixel(3, 1).0, img.get_pixel(2, 0).0);
    }

    #[test]
    fn colours_and_legend_follow_the_values() {
        let map = Provenance::from_vec(3, 2, vec![KEYFRAME, 1, 2, FALLBACK, 1, KEYFRAME]);
        let (png, legend) = render(&map, None, &["a.jpg".into(), "b.jpg".into()]).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgba8();
        assert_eq!(img.get_pixel(0, 0).0[3], 0, "keyframe pixels are transparent");
        assert_eq!(img.get_pixel(1, 0).0, [0x1f, 0x77, 0xb4, 255]);
        assert_eq!(img.get_pixel(2, 0).0, [0xff, 0x7f, 0x0e, 255]);
        assert_eq!(img.get_pixel(0, 1).0, [0xff, 0x00, 0xff, 255]);
        let by: Vec<(&str, usize)> = legend.iter().map(|l| (l.source.as_str(), l.pixels)).collect();
        assert_eq!(by, [("keyframe", 2), ("a.jpg", 2), ("b.jpg", 1), ("fallback", 1)]);
        assert_eq!(legend[3].colour, "#ff00ff");
        // With a confidence map, a view's pixel the fill is not sure of is doubtful.
        let conf = Confidence::from_vec(3, 2, vec![0, 200, 40, 10, 255, 0]);
        let (png, legend) = render(&map, Some(&conf), &["a.jpg".into(), "b.jpg".into()]).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgba8();
        assert_eq!(img.get_pixel(2, 0).0, [0xd6, 0x27, 0x28, 255], "b.jpg's doubtful pixel");
        assert_eq!(img.get_pixel(0, 1).0, [0xff, 0x00, 0xff, 255], "the fallback stays the fallback");
        let by: Vec<(&str, usize)> = legend.iter().map(|l| (l.source.as_str(), l.pixels)).collect();
        assert_eq!(by, [("keyframe", 2), ("a.jpg", 2), ("doubtful", 1), ("fallback", 1)]);
    }
}
