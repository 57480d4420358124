//! Conversions between the `image` crate's types and the core's planes (pure layer).

use image::{DynamicImage, GrayImage, RgbImage};
use rayon::prelude::*;

use super::{GrayF32, Mask, Rect, Rgb8, RgbF32, RgbPixel};

/// Rec. 601 luma weights, as most cameras' JPEG encoders use: the one definition of
/// grey in the project (alignment, the fill's isophotes, frame sharpness).
pub const LUMA: [f32; 3] = [0.299, 0.587, 0.114];

/// The luma of an RGB pixel ([`LUMA`]).
#[inline]
pub fn luma(p: [f32; 3]) -> f32 {
    LUMA[0] * p[0] + LUMA[1] * p[1] + LUMA[2] * p[2]
}

/// Any decoded image as RGB in 0..=1 (16-bit and float inputs keep their precision;
/// alpha is dropped: a photograph's alpha carries nothing the fill can use). 8-bit RGB (what
/// cameras write) goes straight into the plane, rows in parallel, without `image`'s
/// intermediate `f32` buffer: for a 12 MP photograph one 144 MB allocation instead of two.
pub fn to_rgb(img: &DynamicImage) -> RgbF32 {
    if let DynamicImage::ImageRgb8(c) = img {
        let (w, h) = (c.width() as usize, c.height() as usize);
        let mut out = RgbF32::new(w, h, [0.0; 3]);
        if w > 0 {
            out.as_mut_slice().par_chunks_mut(w).zip(c.as_raw().par_chunks(3 * w)).for_each(|(dst, src)| {
                for (d, p) in dst.iter_mut().zip(src.chunks_exact(3)) {
                    *d = [p[0], p[1], p[2]].to_f32();
                }
            });
        }
        return out;
    }
    let rgb = img.to_rgb32f();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let data = rgb.into_raw();
    let pixels = data.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
    RgbF32::from_vec(w, h, pixels)
}

/// The pixels of `img` inside `r` (which must lie inside it) in 8-bit RGB: what the fill
/// keeps of a view (the whole image with [`Rect::full`]). 8-bit RGB is copied row by row; other layouts are converted as `image`'s
/// `to_rgb8` does (16-bit rounded to 8 bits, alpha dropped).
pub fn crop_rgb8(img: &DynamicImage, r: Rect) -> Rgb8 {
    assert!(
        r.x1() <= img.width() as usize && r.y1() <= img.height() as usize,
        "crop {r:?} outside a {}x{} image",
        img.width(),
        img.height()
    );
    let converted;
    let (raw, stride, x0, y0) = match img {
        DynamicImage::ImageRgb8(c) => (c.as_raw(), c.width() as usize, r.x, r.y),
        other => {
            converted = other.crop_imm(r.x as u32, r.y as u32, r.width as u32, r.height as u32).to_rgb8();
            (converted.as_raw(), r.width, 0, 0)
        }
    };
    // Row by row on every core: a 12 MP view is 36 MB, on each landing's path.
    let mut data = vec![[0u8; 3]; r.area()];
    if r.width > 0 {
        data.par_chunks_mut(r.width).enumerate().for_each(|(j, out)| {
            let y = y0 + j;
            let row = &raw[3 * (y * stride + x0)..3 * (y * stride + x0 + r.width)];
            for (d, p) in out.iter_mut().zip(row.chunks_exact(3)) {
                *d = [p[0], p[1], p[2]];
            }
        });
    }
    Rgb8::from_vec(r.width, r.height, data)
}

/// Luminance of an RGB plane, 8-bit or float (pixel by pixel as [`luma`] gives it).
pub fn luminance<P: RgbPixel>(rgb: &super::Plane<P>) -> GrayF32 {
    let mut out = GrayF32::new(0, 0, 0.0);
    luminance_into(rgb, &mut out);
    out
}

/// [`luminance`] into a reused buffer (rows in parallel: 35 ms of one core at 12 MP, in
/// every fill of the service's plane sweep).
pub fn luminance_into<P: RgbPixel>(rgb: &super::Plane<P>, out: &mut GrayF32) {
    out.reset(rgb.width(), rgb.height(), 0.0);
    let w = rgb.width().max(1);
    out.as_mut_slice().par_chunks_mut(w).zip(rgb.as_slice().par_chunks(w)).for_each(|(o, p)| {
        for (o, p) in o.iter_mut().zip(p) {
            *o = luma(p.to_f32());
        }
    });
}

/// Luminance straight from a decoded image, without an intermediate RGB plane. The 8-bit
/// layouts (what cameras write) go through lookup tables, rows in parallel: for a 12 MP
/// photograph this is a few milliseconds rather than the largest sequential step of an
/// alignment.
pub fn to_luminance(img: &DynamicImage) -> GrayF32 {
    match img {
        DynamicImage::ImageLuma8(g) => {
            let lut: [f32; 256] = std::array::from_fn(|v| v as f32 / 255.0);
            map_rows(g.width() as usize, g.height() as usize, g.as_raw(), 1, |p| lut[p[0] as usize])
        }
        DynamicImage::ImageRgb8(c) => {
            let lut: [[f32; 256]; 3] =
                std::array::from_fn(|k| std::array::from_fn(|v| LUMA[k] * v as f32 / 255.0));
            map_rows(c.width() as usize, c.height() as usize, c.as_raw(), 3, |p| {
                lut[0][p[0] as usize] + lut[1][p[1] as usize] + lut[2][p[2] as usize]
            })
        }
        other => luminance(&to_rgb(other)),
    }
}

/// A grey plane from interleaved 8-bit pixels of `channels` samples, one row per task.
fn map_rows(
    width: usize,
    height: usize,
    raw: &[u8],
    channels: usize,
    f: impl Fn(&[u8]) -> f32 + Sync,
) -> GrayF32 {
    let mut out = GrayF32::new(width, height, 0.0);
    if width == 0 {
        return out;
    }
    out.as_mut_slice().par_chunks_mut(width).zip(raw.par_chunks(width * channels)).for_each(|(dst, src)| {
        for (d, p) in dst.iter_mut().zip(src.chunks_exact(channels)) {
            *d = f(p);
        }
    });
    out
}

/// RGB plane to an 8-bit image, rounding and clamping (rows in parallel).
pub fn to_rgb8(rgb: &RgbF32) -> RgbImage {
    let (w, h) = (rgb.width(), rgb.height());
    let mut raw = vec![0u8; 3 * w * h];
    if w > 0 {
        raw.par_chunks_mut(3 * w).zip(rgb.as_slice().par_chunks(w)).for_each(|(dst, src)| {
            for (d, p) in dst.chunks_exact_mut(3).zip(src) {
                d.copy_from_slice(&p.map(quantise));
            }
        });
    }
    RgbImage::from_raw(w as u32, h as u32, raw).expect("buffer matches the size")
}

/// Grey plane to an 8-bit image, rounding and clamping.
pub fn gray_to_luma8(gray: &GrayF32) -> GrayImage {
    GrayImage::from_fn(gray.width() as u32, gray.height() as u32, |x, y| {
        image::Luma([quantise(gray.get(x as usize, y as usize))])
    })
}

/// A decoded image as a mask: luminance > 127 (of 255) means "fill".
///
/// A mask painted in an editor on a transparent layer is read as the user sees it there:
/// what is transparent is kept, whatever colour the file stores under the transparency (an
/// editor may keep white there, which read by luminance alone marked the whole keyframe).
/// Where the opaque part holds both near-black and brighter pixels, it is a black-and-white
/// mask with transparent parts and is read by luminance (laid on black); otherwise every
/// opaque pixel was painted, in whatever colour (a red or a black brush), and is removed.
pub fn to_mask(img: &DynamicImage) -> Mask {
    let (w, h) = (img.width() as usize, img.height() as usize);
    if img.color().has_alpha() {
        let la = img.to_luma_alpha8();
        let opaque = |p: &[u8]| p[1] > 127;
        if la.as_raw().chunks_exact(2).any(|p| !opaque(p)) {
            let (mut painted, mut black, mut bright) = (0usize, 0usize, 0usize);
            for p in la.as_raw().chunks_exact(2).filter(|p| opaque(p)) {
                painted += 1;
                black += usize::from(p[0] < NEAR_BLACK);
                bright += usize::from(p[0] > 127);
            }
            let share = |n: usize, of: f64| n > 0 && n as f64 >= of * painted as f64;
            let by_luminance = share(black, BLACK_SHARE) && share(bright, BRIGHT_SHARE);
            let data = la
                .as_raw()
                .chunks_exact(2)
                .map(|p| if opaque(p) && (!by_luminance || p[0] > 127) { 255 } else { 0 })
                .collect();
            return Mask::from_vec(w, h, data);
        }
    }
    Mask::from_vec(w, h, img.to_luma8().into_raw())
}

/// In a mask with transparent parts, luminance below this (of 255) is black...
const NEAR_BLACK: u8 = 32;
/// ...and its opaque part is a black-and-white mask when at least this share of it is black
/// (a black brush's anti-aliased edge is partly transparent, not an opaque share)...
const BLACK_SHARE: f64 = 0.01;
/// ...and this share brighter than mid-grey (a small white stroke on a black layer still
/// counts; a stray pixel does not).
const BRIGHT_SHARE: f64 = 0.001;

/// The share of a mask's pixels that are neither near black nor near white (32..=223). A
/// painted mask has grey only along its edges (a soft brush, a JPEG's ringing); a
/// photograph given as the mask by mistake is mostly grey and would mark half the frame
/// (every pixel over 127) for removal.
pub fn mask_grey_share(mask: &Mask) -> f64 {
    let grey = mask.as_slice().iter().filter(|&&v| (32..=223).contains(&v)).count();
    grey as f64 / mask.as_slice().len().max(1) as f64
}

/// A mask with more than this share of grey ([`mask_grey_share`]) is not taken as a mask.
pub const MASK_MAX_GREY: f64 = 0.25;

/// A pixel is coloured when two of its channels are more than this apart (0..=1: 4 levels
/// of 255)...
pub const MONOCHROME_SPREAD: f32 = 4.0 / 255.0;
/// ...and a picture is black and white when fewer than this share of its pixels are
/// ([`monochrome`]).
pub const MONOCHROME_COLOURED_SHARE: f64 = 0.005;

/// Whether a picture is black and white: fewer than [`MONOCHROME_COLOURED_SHARE`] of its
/// pixels (about 100 000 looked at, spread evenly) have channels more than
/// [`MONOCHROME_SPREAD`] apart. A black-and-white export, a monochrome camera's frame or a
/// grey PNG decodes with its three channels equal, and so does a grey picture saved as a
/// colour JPEG; every colour photograph in `../shared/data` has 26 % or more of its pixels
/// past that (a night street under sodium light, Oxford's `ubc` at its worst JPEG), and one
/// with nine tenths of its saturation taken out still 1 %.
pub fn monochrome<P: RgbPixel>(img: &super::Plane<P>) -> bool {
    let n = img.as_slice().len();
    if n == 0 {
        return false;
    }
    let step = (n / 100_000).max(1);
    let (mut looked, mut coloured) = (0usize, 0usize);
    for p in img.as_slice().iter().step_by(step) {
        let [r, g, b] = p.to_f32();
        looked += 1;
        coloured += usize::from(r.max(g).max(b) - r.min(g).min(b) > MONOCHROME_SPREAD);
    }
    (coloured as f64) < MONOCHROME_COLOURED_SHARE * looked as f64
}

/// An 8-bit plane as a grey image, every value as it is (a confidence map keeps its grades;
/// [`mask_to_luma8`] would make it 0 or 255).
pub fn plane_to_luma8(plane: &crate::imaging::Plane<u8>) -> GrayImage {
    GrayImage::from_raw(plane.width() as u32, plane.height() as u32, plane.as_slice().to_vec())
        .expect("a plane holds width × height values")
}

/// A mask as an 8-bit grey image (0 or 255).
pub fn mask_to_luma8(mask: &Mask) -> GrayImage {
    GrayImage::from_fn(mask.width() as u32, mask.height() as u32, |x, y| {
        image::Luma([if mask.is_hole(x as usize, y as usize) { 255 } else { 0 }])
    })
}

/// `(v · 255).round()` clamped to 0..=255, without a call to libm's `roundf` (the baseline
/// x86-64 target has no rounding instruction): in 0..=255 the truncation is exact, and so is
/// the fraction it leaves. NaN gives 0, as `as u8` does.
#[inline]
fn quantise(v: f32) -> u8 {
    let s = (v * 255.0).clamp(0.0, 255.0);
    let i = s as u8;
    i + u8::from(s - f32::from(i) >= 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;

    #[test]
    fn rgb8_round_trips() {
        let src = RgbImage::from_fn(5, 3, |x, y| Rgb([(x * 40) as u8, (y * 90) as u8, 7]));
        let back = to_rgb8(&to_rgb(&DynamicImage::ImageRgb8(src.clone())));
        assert_eq!(src, back);
    }

    #[test]
    fn quantise_rounds_like_round() {
        let reference = |v: f32| (v * 255.0).round().clamp(0.0, 255.0) as u8;
        for i in 0..1_000_000 {
            let v = -0.1 + 1.2 * i as f32 / 1e6;
            assert_eq!(quantise(v), reference(v), "{v}");
        }
        for k in 0..=255 {
            let half = (k as f32 + 0.5) / 255.0;
            for x in [half, f32::from_bits(half.to_bits() - 1), f32::from_bits(half.to_bits() + 1)] {
                assert_eq!(quantise(x), reference(x), "{x}");
            }
        }
        assert_eq!(quantise(f32::NAN), reference(f32::NAN));
    }

    #[test]
    fn crops_keep_the_pixels_in_every_layout() {
        use image::{ImageBuffer, Rgba};
        let px = |x: u32, y: u32| [(x * 20) as u8, (y * 30) as u8, (x * y) as u8];
        let rgb = DynamicImage::ImageRgb8(RgbImage::from_fn(9, 7, |x, y| Rgb(px(x, y))));
        let rgba16 = DynamicImage::ImageRgba16(ImageBuffer::from_fn(9, 7, |x, y| {
            let p = px(x, y).map(|v| v as u16 * 257);
            Rgba([p[0], p[1], p[2], 1])
        }));
        let r = Rect { x: 2, y: 3, width: 5, height: 4 };
        for img in [&rgb, &rgba16] {
            let c = crop_rgb8(img, r);
            assert_eq!((c.width(), c.height()), (5, 4));
            for y in 0..4 {
                for x in 0..5 {
                    assert_eq!(c.get(x, y), px(x as u32 + 2, y as u32 + 3), "{:?} at {x},{y}", img.color());
                }
            }
        }
        let f = to_rgb(&rgb);
        assert_eq!(f.get(4, 5), px(4, 5).map(|v| v as f32 / 255.0));
        assert!(f == to_rgb(&DynamicImage::ImageRgba8(rgb.to_rgba8())), "the 8-bit path differs");
    }

    #[test]
    fn every_pixel_layout_gives_the_same_luminance() {
        use image::{ImageBuffer, Luma, LumaA, Rgba};
        let grey = |x: u32, y: u32| (x * 37 + y * 11) as u8;
        let reference =
            to_luminance(&DynamicImage::ImageLuma8(GrayImage::from_fn(6, 4, |x, y| Luma([grey(x, y)]))));
        let layouts = [
            DynamicImage::ImageRgb8(RgbImage::from_fn(6, 4, |x, y| Rgb([grey(x, y); 3]))),
            DynamicImage::ImageRgba8(ImageBuffer::from_fn(6, 4, |x, y| {
                Rgba([grey(x, y), grey(x, y), grey(x, y), 9])
            })),
            DynamicImage::ImageLumaA8(ImageBuffer::from_fn(6, 4, |x, y| LumaA([grey(x, y), 200]))),
            DynamicImage::ImageLuma16(ImageBuffer::from_fn(6, 4, |x, y| Luma([grey(x, y) as u16 * 257]))),
            DynamicImage::ImageRgb16(ImageBuffer::from_fn(6, 4, |x, y| Rgb([grey(x, y) as u16 * 257; 3]))),
            DynamicImage::ImageRgba16(ImageBuffer::from_fn(6, 4, |x, y| {
                Rgba([grey(x, y) as u16 * 257, grey(x, y) as u16 * 257, grey(x, y) as u16 * 257, 1])
            })),
        ];
        for img in &layouts {
            let l = to_luminance(img);
            assert_eq!((l.width(), l.height()), (6, 4));
            for (a, b) in l.as_slice().iter().zip(reference.as_slice()) {
                assert!((a - b).abs() < 1e-4, "{:?}: {a} vs {b}", img.color());
            }
        }
    }

    #[test]
    fn a_black_and_white_picture_is_told_from_a_colour_one() {
        let colour = crate::synth::facade(160, 120, 3);
        assert!(!monochrome(&colour));
        let grey = colour.map(|&p| [luma(p); 3]);
        assert!(monochrome(&grey));
        // A grey picture saved as a colour JPEG: its channels a level or two apart.
        let jpeg = RgbF32::from_fn(160, 120, |x, y| {
            let (l, d) = (grey.get(x, y)[0], ((x * 7 + y * 3) % 3) as f32 / 255.0);
            [l, l + d, l - d]
        });
        assert!(monochrome(&jpeg));
        // A tenth of the saturation left is still a colour photograph.
        let faint = colour.map(|&p| {
            let l = luma(p);
            p.map(|c| l + 0.1 * (c - l))
        });
        assert!(!monochrome(&faint));
        assert!(!monochrome(&RgbF32::new(0, 0, [0.0; 3])), "no pixels: nothing to say");
    }

    #[test]
    fn luminance_paths_agree() {
        let src = RgbImage::from_fn(4, 4, |x, y| Rgb([(x * 60) as u8, (y * 60) as u8, 200]));
        let dynamic = DynamicImage::ImageRgb8(src);
        let a = to_luminance(&dynamic);
        let b = luminance(&to_rgb(&dynamic));
        for (p, q) in a.as_slice().iter().zip(b.as_slice()) {
            assert!((p - q).abs() < 1e-5);
        }
    }

    /// A 40 × 30 mask painted as a user paints one on a transparent layer: `stroke` where
    /// `x < 10` (opaque), `under` elsewhere with alpha `alpha`.
    fn layer(stroke: [u8; 3], under: [u8; 3], alpha: u8) -> DynamicImage {
        DynamicImage::ImageRgba8(image::RgbaImage::from_fn(40, 30, |x, _| {
            if x < 10 {
                image::Rgba([stroke[0], stroke[1], stroke[2], 255])
            } else {
                image::Rgba([under[0], under[1], under[2], alpha])
            }
        }))
    }

    fn painted(m: &Mask) -> usize {
        m.hole_count()
    }

    #[test]
    fn what_is_transparent_in_a_mask_is_kept_whatever_colour_it_stores() {
        // The stroke alone is removed: white, black or red, over transparency stored white
        // (which read by luminance alone marked the whole keyframe) or black.
        for stroke in [[255, 255, 255], [0, 0, 0], [255, 0, 0]] {
            for under in [[255, 255, 255], [0, 0, 0]] {
                let m = to_mask(&layer(stroke, under, 0));
                assert_eq!(painted(&m), 10 * 30, "stroke {stroke:?} over {under:?}");
                assert!((0..30).all(|y| m.is_hole(5, y) && !m.is_hole(20, y)));
            }
        }
        // Opaque everywhere: luminance, as before (white removes, black keeps).
        assert_eq!(painted(&to_mask(&layer([255; 3], [0; 3], 255))), 10 * 30);
        assert_eq!(painted(&to_mask(&layer([0; 3], [255; 3], 255))), 30 * 30);
        assert_eq!(painted(&to_mask(&layer([255, 0, 0], [0; 3], 255))), 0, "red is darker than mid-grey");
    }

    #[test]
    fn a_black_and_white_mask_with_transparent_parts_is_read_by_luminance() {
        // Black with a white stroke, opaque, and a transparent strip at the top: the black
        // is kept, the stroke removed, the strip kept.
        let img = DynamicImage::ImageRgba8(image::RgbaImage::from_fn(40, 30, |x, y| match (x, y) {
            (_, 0..3) => image::Rgba([255, 255, 255, 0]),
            (0..10, _) => image::Rgba([255, 255, 255, 255]),
            _ => image::Rgba([0, 0, 0, 255]),
        }));
        let m = to_mask(&img);
        assert_eq!(painted(&m), 10 * 27);
        assert!(m.is_hole(5, 10) && !m.is_hole(5, 1) && !m.is_hole(20, 10));
        // Grey and alpha as 16 bits read the same.
        let grey = DynamicImage::ImageLumaA16(image::ImageBuffer::from_fn(40, 30, |x, _| {
            image::LumaA([65535, if x < 10 { 65535 } else { 0 }])
        }));
        assert_eq!(painted(&to_mask(&grey)), 10 * 30);
    }
}
