//! Which part of a view the fill needs: the footprint of the mask's neighbourhood, so that
//! only that much is decoded into floats, kept in a buffer and warped (pure layer).

use nalgebra::Point2;

use crate::geometry::Homography;
use crate::imaging::Rect;

/// The part of a `view_width × view_height` view that `key_to_view` maps `key_region`
/// onto, grown by `margin` view pixels (and two more for interpolation), clamped to the
/// view; `None` when that leaves less than 2 × 2 pixels. Where the region reaches the
/// horizon (part of it maps behind the camera) the whole view is returned.
pub fn footprint(
    key_region: &Rect,
    key_to_view: &Homography,
    view_width: usize,
    view_height: usize,
    margin: usize,
) -> Option<Rect> {
    let (x0, y0) = (key_region.x as f64, key_region.y as f64);
    let (x1, y1) = ((key_region.x1() - 1) as f64, (key_region.y1() - 1) as f64);
    let corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)].map(|(x, y)| Point2::new(x, y));
    let whole = Rect::full(view_width, view_height);
    if corners.iter().any(|&p| key_to_view.w(p) <= 0.0) {
        return Some(whole);
    }
    // A rectangle in front of the camera maps to a convex quadrilateral: its corners bound it.
    let mapped: Vec<Point2<f64>> = corners.iter().filter_map(|&p| key_to_view.apply(p)).collect();
    if mapped.len() < 4 {
        return Some(whole);
    }
    let m = (margin + 2) as f64;
    let min_x = mapped.iter().map(|p| p.x).fold(f64::INFINITY, f64::min).floor() - m;
    let min_y = mapped.iter().map(|p| p.y).fold(f64::INFINITY, f64::min).floor() - m;
    let max_x = mapped.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max).ceil() + m + 1.0;
    let max_y = mapped.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max).ceil() + m + 1.0;
    let clamp = |v: f64, hi: usize| v.clamp(0.0, hi as f64) as usize;
    let r = Rect::from_corners(
        clamp(min_x, view_width),
        clamp(min_y, view_height),
        clamp(max_x, view_width),
        clamp(max_y, view_height),
    );
    (r.width >= 2 && r.height >= 2).then_some(r)
}

/// The homography to use with a crop of a view that starts at `(x0, y0)`.
pub fn into_crop(key_to_view: &Homography, crop: &Rect) -> Homography {
    Homography::translation(-(crop.x as f64), -(crop.y as f64)).after(key_to_view)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn footprint_covers_every_mapped_pixel_and_the_crop_keeps_the_map() {
        let h = Homography::from_rows([[0.9, 0.12, 30.0], [-0.1, 1.1, 12.0], [2e-4, -1e-4, 1.0]]).unwrap();
        let region = Rect::from_corners(40, 30, 120, 90);
        for margin in [0, 10] {
            let f = footprint(&region, &h, 400, 300, margin).unwrap();
            let shifted = into_crop(&h, &f);
            for y in region.y..region.y1() {
                for x in region.x..region.x1() {
                    let p = Point2::new(x as f64, y as f64);
                    let q = h.apply(p).unwrap();
                    let m = margin as f64;
                    assert!(q.x - m >= f.x as f64 && q.x + m < f.x1() as f64 - 1.0);
                    assert!(q.y - m >= f.y as f64 && q.y + m < f.y1() as f64 - 1.0);
                    let c = shifted.apply(p).unwrap();
                    assert!(
                        (c.x - (q.x - f.x as f64)).abs() < 1e-9 && (c.y - (q.y - f.y as f64)).abs() < 1e-9
                    );
                }
            }
            assert!(f.area() < 400 * 300 / 3, "the footprint should be small: {f:?}");
        }
    }

    #[test]
    fn a_region_outside_the_view_has_no_footprint() {
        let h = Homography::translation(-1000.0, 0.0);
        assert_eq!(footprint(&Rect::from_corners(0, 0, 50, 50), &h, 400, 300, 4), None);
    }
}
