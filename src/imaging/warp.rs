//! Warping a view into the keyframe's frame through a homography, over a region only, with
//! a validity mask for what the view does not cover (pure layer).
//!
//! The fill needs a view's pixels only around the hole, so a warp covers a rectangle of
//! the keyframe and, inside it, optionally only the pixels a `need` mask marks: a small
//! hole in a 12 MP photograph costs a small warp.

use nalgebra::Point2;
use rayon::prelude::*;

pub use super::Rect;
use super::{Plane, RgbF32, RgbPixel, bilinear_rgb};
use crate::geometry::Homography;

/// How a warp samples the view between pixel centres.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Interpolation {
    /// 2×2 neighbourhood: fast, slightly soft.
    #[default]
    Bilinear,
    /// 4×4 Catmull-Rom: sharper, keeps brick joints crisp; about three times the cost.
    Bicubic,
}

/// A view warped into a rectangle of the keyframe: `image` and `valid` are `rect`-sized;
/// `valid` is false where the view does not cover the pixel (or it was not needed), and
/// `image` is black there.
#[derive(Debug, Clone)]
pub struct Warped {
    pub rect: Rect,
    pub image: RgbF32,
    pub valid: Plane<bool>,
}

impl Warped {
    /// An empty warp, for reuse with [`warp_into`].
    pub fn empty() -> Self {
        Self { rect: Rect::default(), image: RgbF32::new(0, 0, [0.0; 3]), valid: Plane::new(0, 0, false) }
    }
}

/// Warps `view` into the keyframe's frame over `rect` (keyframe pixels): the result at key
/// pixel `p` is `view` sampled at `h · p` (`h` maps keyframe → view). Where `need` is given
/// (`rect`-sized), only pixels it marks are computed; the others are invalid. The view may
/// be 8-bit ([`super::Rgb8`]): it is read as `f32` tap by tap, with the same result as
/// warping its `f32` copy.
pub fn warp<P: RgbPixel>(
    view: &Plane<P>,
    h: &Homography,
    rect: Rect,
    need: Option<&Plane<bool>>,
    interpolation: Interpolation,
) -> Warped {
    let mut out = Warped::empty();
    warp_into(view, h, rect, need, interpolation, &mut out);
    out
}

/// [`warp`] into a reused buffer.
pub fn warp_into<P: RgbPixel>(
    view: &Plane<P>,
    h: &Homography,
    rect: Rect,
    need: Option<&Plane<bool>>,
    interpolation: Interpolation,
    out: &mut Warped,
) {
    if let Some(n) = need {
        assert_eq!((n.width(), n.height()), (rect.width, rect.height), "need mask size");
    }
    out.rect = rect;
    out.image.reset(rect.width, rect.height, [0.0; 3]);
    out.valid.reset(rect.width, rect.height, false);
    if rect.area() == 0 {
        return;
    }
    let m = h.matrix();
    let w = rect.width;
    out.image
        .as_mut_slice()
        .par_chunks_mut(w)
        .zip(out.valid.as_mut_slice().par_chunks_mut(w))
        .enumerate()
        .for_each(|(ry, (img_row, valid_row))| {
            let y = (rect.y + ry) as f64;
            let need_row = need.map(|n| n.row(ry));
            // Homogeneous image of (rect.x, y), then steps of one column.
            let x0 = rect.x as f64;
            let mut u = m[(0, 0)] * x0 + m[(0, 1)] * y + m[(0, 2)];
            let mut v = m[(1, 0)] * x0 + m[(1, 1)] * y + m[(1, 2)];
            let mut s = m[(2, 0)] * x0 + m[(2, 1)] * y + m[(2, 2)];
            let (du, dv, ds) = (m[(0, 0)], m[(1, 0)], m[(2, 0)]);
            for rx in 0..w {
                let wanted = need_row.is_none_or(|n| n[rx]);
                if wanted && s > 1e-12 {
                    let (px, py) = ((u / s) as f32, (v / s) as f32);
                    let sample = match interpolation {
                        Interpolation::Bilinear => bilinear_rgb(view, px, py),
                        Interpolation::Bicubic => bicubic_rgb(view, px, py),
                    };
                    if let Some(p) = sample {
                        img_row[rx] = p;
                        valid_row[rx] = true;
                    }
                }
                u += du;
                v += dv;
                s += ds;
            }
        });
}

/// Catmull-Rom weights for a fractional position `t` in 0..1 (taps at −1, 0, 1, 2).
#[inline]
fn catmull_rom(t: f32) -> [f32; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// Samples an RGB image at a real-valued position with Catmull-Rom bicubic interpolation;
/// `None` outside the pixel-centre rectangle (taps beyond the border are clamped).
#[inline]
pub fn bicubic_rgb<P: RgbPixel>(img: &Plane<P>, x: f32, y: f32) -> Option<[f32; 3]> {
    if !(x >= 0.0 && y >= 0.0) || x > (img.width() - 1) as f32 || y > (img.height() - 1) as f32 {
        return None;
    }
    let (x0, y0) = (x.floor() as isize, y.floor() as isize);
    let (wx, wy) = (catmull_rom(x - x0 as f32), catmull_rom(y - y0 as f32));
    let mut out = [0.0f32; 3];
    for (j, wyj) in wy.iter().enumerate() {
        let mut row = [0.0f32; 3];
        for (i, wxi) in wx.iter().enumerate() {
            let p = img.get_clamped(x0 + i as isize - 1, y0 + j as isize - 1).to_f32();
            for c in 0..3 {
                row[c] += wxi * p[c];
            }
        }
        for c in 0..3 {
            out[c] += wyj * row[c];
        }
    }
    Some(out)
}

/// Where the keyframe rectangle `rect` lands in a `width × height` view under `h`: `true`
/// when at least one corner of `rect` maps inside the view or the view's centre maps inside
/// `rect` (a cheap test to skip views that cannot help).
pub fn overlaps(h: &Homography, rect: Rect, width: usize, height: usize) -> bool {
    if rect.area() == 0 {
        return false;
    }
    let corners = [
        (rect.x, rect.y),
        (rect.x + rect.width - 1, rect.y),
        (rect.x, rect.y + rect.height - 1),
        (rect.x + rect.width - 1, rect.y + rect.height - 1),
    ];
    let inside = |p: Option<Point2<f64>>| {
        p.is_some_and(|p| p.x >= 0.0 && p.y >= 0.0 && p.x <= width as f64 && p.y <= height as f64)
    };
    if corners.iter().any(|&(x, y)| inside(h.apply(Point2::new(x as f64, y as f64)))) {
        return true;
    }
    h.inverse()
        .and_then(|inv| inv.apply(Point2::new(width as f64 / 2.0, height as f64 / 2.0)))
        .is_some_and(|c| rect.contains(c.x.max(0.0) as usize, c.y.max(0.0) as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize) -> RgbF32 {
        RgbF32::from_fn(w, h, |x, y| [x as f32 * 0.01, y as f32 * 0.01, (x + y) as f32 * 0.005])
    }

    #[test]
    fn identity_warp_is_a_crop_and_valid_everywhere() {
        let img = ramp(40, 30);
        let rect = Rect { x: 5, y: 7, width: 20, height: 10 };
        for interp in [Interpolation::Bilinear, Interpolation::Bicubic] {
            let w = warp(&img, &Homography::identity(), rect, None, interp);
            assert!(w.valid.as_slice().iter().all(|&v| v));
            for y in 0..10 {
                for x in 0..20 {
                    let (a, b) = (w.image.get(x, y), img.get(x + 5, y + 7));
                    assert!((0..3).all(|c| (a[c] - b[c]).abs() < 1e-5), "{interp:?} at {x},{y}");
                }
            }
        }
    }

    #[test]
    fn translated_view_is_invalid_where_it_does_not_reach() {
        let img = ramp(40, 30);
        // Key pixel p sees view pixel p + (10.5, 0): the right 11 columns fall off the view.
        let h = Homography::translation(10.5, 0.0);
        let w = warp(&img, &h, Rect::full(40, 30), None, Interpolation::Bilinear);
        for x in 0..40 {
            assert_eq!(w.valid.get(x, 3), x <= 28, "column {x}");
        }
        // Linear ramp: bilinear is exact.
        let p = w.image.get(3, 3);
        assert!((p[0] - 0.135).abs() < 1e-5, "{p:?}");
        // Bicubic reproduces linear ramps too.
        let wc = warp(&img, &h, Rect::full(40, 30), None, Interpolation::Bicubic);
        let q = wc.image.get(3, 3);
        assert!((q[0] - 0.135).abs() < 1e-5 && wc.valid.get(28, 3) && !wc.valid.get(29, 3), "{q:?}");
    }

    #[test]
    fn only_needed_pixels_are_warped_and_into_reuses() {
        let img = ramp(20, 20);
        let rect = Rect { x: 2, y: 2, width: 6, height: 6 };
        let need = Plane::from_fn(6, 6, |x, y| x == y);
        let mut out = Warped::empty();
        warp_into(&img, &Homography::identity(), rect, Some(&need), Interpolation::Bilinear, &mut out);
        assert_eq!(out.valid.as_slice().iter().filter(|&&v| v).count(), 6);
        assert!(out.valid.get(3, 3) && !out.valid.get(3, 4));
        assert_eq!(out.image.get(3, 4), [0.0; 3]);
        warp_into(&img, &Homography::identity(), Rect::full(20, 20), None, Interpolation::Bilinear, &mut out);
        assert_eq!(out.image.len(), 400);
    }

    #[test]
    fn an_eight_bit_view_warps_like_its_f32_copy() {
        let img8 =
            super::super::Rgb8::from_fn(30, 20, |x, y| [(x * 8) as u8, (y * 12) as u8, ((x ^ y) * 9) as u8]);
        let img = img8.map(|p| p.map(|v| v as f32 / 255.0));
        let h = Homography::from_rows([[0.9, 0.1, 2.5], [-0.05, 1.05, 1.25], [1e-3, 0.0, 1.0]]).unwrap();
        let rect = Rect { x: 1, y: 2, width: 25, height: 15 };
        for interp in [Interpolation::Bilinear, Interpolation::Bicubic] {
            let (a, b) = (warp(&img8, &h, rect, None, interp), warp(&img, &h, rect, None, interp));
            assert_eq!(a.valid, b.valid, "{interp:?}");
            assert!(a.valid.as_slice().iter().filter(|&&v| v).count() > 200);
            assert!(a.image == b.image, "{interp:?}: the 8-bit warp differs");
        }
    }

    #[test]
    fn rect_grows_within_the_image() {
        let r = Rect { x: 2, y: 50, width: 10, height: 10 }.grown(5, 100, 58);
        assert_eq!(r, Rect { x: 0, y: 45, width: 17, height: 13 });
        assert!(overlaps(&Homography::identity(), r, 100, 58));
        assert!(!overlaps(&Homography::translation(1000.0, 0.0), r, 100, 58));
    }
}
