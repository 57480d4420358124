//! Which part of each image the fill needs: the mask's neighbourhood in the keyframe and
//! its footprint in a view, so that only that much is warped and kept (pure layer).

use nalgebra::Point2;

use crate::geometry::Homography;
use crate::imaging::Mask;

/// A pixel rectangle `[x0, x1) × [y0, y1)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }

    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }

    pub fn area(&self) -> usize {
        self.width() * self.height()
    }

    /// The rectangle grown by `margin` on every side, clamped to `width × height`.
    pub fn grown(&self, margin: usize, width: usize, height: usize) -> Rect {
        Rect {
            x0: self.x0.saturating_sub(margin),
            y0: self.y0.saturating_sub(margin),
            x1: (self.x1 + margin).min(width),
            y1: (self.y1 + margin).min(height),
        }
    }
}

/// The bounding box of the mask's holes, or `None` for an empty mask.
pub fn mask_bounds(mask: &Mask) -> Option<Rect> {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for y in 0..mask.height() {
        let row = mask.row(y);
        let (Some(first), Some(last)) =
            (row.iter().position(|&v| v > 127), row.iter().rposition(|&v| v > 127))
        else {
            continue;
        };
        x0 = x0.min(first);
        x1 = x1.max(last + 1);
        y0 = y0.min(y);
        y1 = y + 1;
    }
    (x0 != usize::MAX).then_some(Rect { x0, y0, x1, y1 })
}

/// The part of a `view_width × view_height` view that `key_to_view` maps `key_region`
/// onto, with one pixel to spare for interpolation, clamped to the view; `None` when the
/// region does not land in the view at all. Where the region reaches the horizon (part
/// of it maps behind the camera) the whole view is returned.
pub fn footprint(
    key_region: &Rect,
    key_to_view: &Homography,
    view_width: usize,
    view_height: usize,
) -> Option<Rect> {
    let (x0, y0) = (key_region.x0 as f64, key_region.y0 as f64);
    let (x1, y1) = ((key_region.x1 - 1) as f64, (key_region.y1 - 1) as f64);
    let corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)].map(|(x, y)| Point2::new(x, y));
    let whole = Rect { x0: 0, y0: 0, x1: view_width, y1: view_height };
    if corners.iter().any(|&p| key_to_view.w(p) <= 0.0) {
        return Some(whole);
    }
    // A rectangle in front of the camera maps to a convex quadrilateral: its corners bound it.
    let mapped: Vec<Point2<f64>> = corners.iter().filter_map(|&p| key_to_view.apply(p)).collect();
    if mapped.len() < 4 {
        return Some(whole);
    }
    let min_x = mapped.iter().map(|p| p.x).fold(f64::INFINITY, f64::min).floor() - 1.0;
    let min_y = mapped.iter().map(|p| p.y).fold(f64::INFINITY, f64::min).floor() - 1.0;
    let max_x = mapped.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max).ceil() + 2.0;
    let max_y = mapped.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max).ceil() + 2.0;
    let clamp = |v: f64, hi: usize| v.clamp(0.0, hi as f64) as usize;
    let r = Rect {
        x0: clamp(min_x, view_width),
        y0: clamp(min_y, view_height),
        x1: clamp(max_x, view_width),
        y1: clamp(max_y, view_height),
    };
    (r.x1 > r.x0 && r.y1 > r.y0).then_some(r)
}

/// The homography to use with a crop of a view that starts at `(x0, y0)`.
pub fn into_crop(key_to_view: &Homography, crop: &Rect) -> Homography {
    Homography::translation(-(crop.x0 as f64), -(crop.y0 as f64)).after(key_to_view)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_of_a_mask() {
        let mut m = Mask::new(20, 10, 0);
        assert_eq!(mask_bounds(&m), None);
        m.set(3, 4, 255);
        m.set(11, 7, 200);
        m.set(15, 2, 100); // not a hole
        assert_eq!(mask_bounds(&m), Some(Rect { x0: 3, y0: 4, x1: 12, y1: 8 }));
    }

    #[test]
    fn footprint_covers_every_mapped_pixel_and_the_crop_keeps_the_map() {
        let h = Homography::from_rows([[0.9, 0.12, 30.0], [-0.1, 1.1, 12.0], [2e-4, -1e-4, 1.0]]).unwrap();
        let region = Rect { x0: 40, y0: 30, x1: 120, y1: 90 };
        let f = footprint(&region, &h, 400, 300).unwrap();
        let shifted = into_crop(&h, &f);
        for y in region.y0..region.y1 {
            for x in region.x0..region.x1 {
                let p = Point2::new(x as f64, y as f64);
                let q = h.apply(p).unwrap();
                assert!(
                    q.x >= f.x0 as f64
                        && q.x < f.x1 as f64 - 1.0
                        && q.y >= f.y0 as f64
                        && q.y < f.y1 as f64 - 1.0
                );
                let c = shifted.apply(p).unwrap();
                assert!((c.x - (q.x - f.x0 as f64)).abs() < 1e-9 && (c.y - (q.y - f.y0 as f64)).abs() < 1e-9);
            }
        }
        assert!(f.area() < 400 * 300 / 3, "the footprint should be small: {f:?}");
    }

    #[test]
    fn a_region_outside_the_view_has_no_footprint() {
        let h = Homography::translation(-1000.0, 0.0);
        assert_eq!(footprint(&Rect { x0: 0, y0: 0, x1: 50, y1: 50 }, &h, 400, 300), None);
    }
}
