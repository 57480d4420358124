//! A fill's inputs at a lower resolution, for a judge that needs shares of the mask, not
//! pixels ([`super::swept::fill_swept`] on a 12 MP keyframe): the keyframe, its mask, the
//! views and everything that comes with them halved `levels` times (pure layer).
//!
//! Images are averaged over 2 × 2 blocks; masks keep the strongest mark of the block (a
//! hole or an occluder is never lost by halving); maps between images follow the pixel
//! centres (a halved pixel `x` is centred on the full pixel `2x + 0.5`).

use super::parallax::SurfacePlane;
use super::{FillExtras, Source};
use crate::geometry::Homography;
use crate::imaging::warp::Rect;
use crate::imaging::{Mask, Plane, RgbF32, RgbPixel};

/// How many times a `width × height` image is halved to have at most `max_pixels` (0 when it
/// has that many already).
pub fn levels_for(width: usize, height: usize, max_pixels: usize) -> u32 {
    let mut levels = 0;
    while (width >> levels) * (height >> levels) > max_pixels.max(1) {
        levels += 1;
    }
    levels
}

/// The map from full-resolution pixel coordinates to those of the image halved `levels`
/// times.
pub fn reduction(levels: u32) -> Homography {
    let s = f64::from(1u32 << levels);
    // Halved pixel x covers full pixels s·x .. s·x + s − 1: its centre is s·x + (s − 1)/2.
    Homography::scaling(1.0 / s).after(&Homography::translation(-(s - 1.0) / 2.0, -(s - 1.0) / 2.0))
}

/// `img` averaged over `2^levels`-wide blocks (the right and bottom remainders dropped).
pub fn reduce_rgb<P: RgbPixel>(img: &Plane<P>, levels: u32) -> RgbF32 {
    let s = 1usize << levels;
    let (w, h) = (img.width() / s, img.height() / s);
    let norm = 1.0 / (s * s) as f32;
    RgbF32::from_fn(w, h, |x, y| {
        let mut acc = [0.0f32; 3];
        for yy in y * s..(y + 1) * s {
            for p in &img.row(yy)[x * s..(x + 1) * s] {
                let c = p.to_f32();
                for k in 0..3 {
                    acc[k] += c[k];
                }
            }
        }
        acc.map(|a| a * norm)
    })
}

/// `mask` over `2^levels`-wide blocks, each taking its block's strongest mark.
pub fn reduce_mask(mask: &Mask, levels: u32) -> Mask {
    let s = 1usize << levels;
    let (w, h) = (mask.width() / s, mask.height() / s);
    Mask::from_fn(w, h, |x, y| {
        (y * s..(y + 1) * s)
            .map(|yy| mask.row(yy)[x * s..(x + 1) * s].iter().copied().max().unwrap_or(0))
            .max()
            .unwrap_or(0)
    })
}

/// `r` (full resolution) as the pixels of the halved image it touches, within `w × h`.
fn reduce_rect(r: Rect, levels: u32, w: usize, h: usize) -> Rect {
    let s = 1usize << levels;
    let (x0, y0) = ((r.x / s).min(w), (r.y / s).min(h));
    Rect::from_corners(x0, y0, r.x1().div_ceil(s).clamp(x0, w), r.y1().div_ceil(s).clamp(y0, h))
}

/// A fill's keyframe, mask, sources and extras halved `levels` times ([`Reduced::sources`],
/// [`Reduced::extras`] give them as the fill takes them).
#[derive(Debug, Clone)]
pub struct Reduced {
    pub key: RgbF32,
    pub mask: Mask,
    images: Vec<RgbF32>,
    homographies: Vec<Homography>,
    occluders: Vec<Option<Mask>>,
    own: Option<Vec<Option<Mask>>>,
    whole: Option<(usize, usize)>,
    levels: u32,
}

impl Reduced {
    /// The inputs of a fill halved `levels` times: its keyframe, mask, sources, and the
    /// extras' marks and whole size ([`Reduced::extras`] gives them back with surfaces
    /// reduced by [`Reduced::planes`]).
    pub fn new<P: RgbPixel>(
        key: &RgbF32,
        mask: &Mask,
        sources: &[Source<'_, P>],
        extras: &FillExtras<'_>,
        levels: u32,
    ) -> Self {
        let t = reduction(levels);
        let t_inv = t.inverse().expect("regular");
        let shrink = |m: &Option<&Mask>| m.map(|m| reduce_mask(m, levels));
        Self {
            key: reduce_rgb(key, levels),
            mask: reduce_mask(mask, levels),
            images: sources.iter().map(|s| reduce_rgb(s.image, levels)).collect(),
            homographies: sources.iter().map(|s| t.after(&s.homography).after(&t_inv)).collect(),
            occluders: extras.occluders.iter().map(shrink).collect(),
            own: extras.own.map(|o| o.iter().map(shrink).collect()),
            whole: extras.whole.map(|(w, h)| (w >> levels, h >> levels)),
            levels,
        }
    }

    /// How many times the inputs were halved.
    pub fn levels(&self) -> u32 {
        self.levels
    }

    /// The sources at the reduced size.
    pub fn sources(&self) -> Vec<Source<'_>> {
        self.images
            .iter()
            .zip(&self.homographies)
            .map(|(image, &homography)| Source { image, homography })
            .collect()
    }

    /// `planes` (full-resolution keyframe → views) at the reduced size.
    pub fn planes(&self, planes: &[SurfacePlane]) -> Vec<SurfacePlane> {
        let t = reduction(self.levels);
        let t_inv = t.inverse().expect("regular");
        let (w, h) = (self.key.width(), self.key.height());
        planes
            .iter()
            .map(|p| SurfacePlane {
                views: p.views.iter().map(|v| v.map(|v| t.after(&v).after(&t_inv))).collect(),
                region: reduce_rect(p.region, self.levels, w, h),
            })
            .collect()
    }

    /// The extras at the reduced size: `planes` reduced already ([`Reduced::planes`]), the
    /// marks of [`Reduced::marks`], the full-resolution fill's `choice` of views, no rival.
    pub fn extras<'a>(
        &'a self,
        planes: &'a [SurfacePlane],
        occluders: &'a [Option<&'a Mask>],
        own: Option<&'a [Option<&'a Mask>]>,
        choice: &'a [Option<bool>],
    ) -> FillExtras<'a> {
        FillExtras { planes, occluders, choice, whole: self.whole, own, ..FillExtras::default() }
    }

    /// The reduced occluder marks and own marks as the extras take them (borrowed).
    pub fn marks(&self) -> (Vec<Option<&Mask>>, Option<Vec<Option<&Mask>>>) {
        (
            self.occluders.iter().map(Option::as_ref).collect(),
            self.own.as_ref().map(|o| o.iter().map(Option::as_ref).collect()),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point2;

    #[test]
    fn the_reduction_follows_pixel_centres() {
        let t = reduction(1);
        // Halved pixel 0 averages full pixels 0 and 1: its centre is 0.5.
        let p = t.apply(Point2::new(0.5, 2.5)).unwrap();
        assert!((p.x - 0.0).abs() < 1e-12 && (p.y - 1.0).abs() < 1e-12, "{p:?}");
        let p = reduction(2).apply(Point2::new(1.5, 5.5)).unwrap();
        assert!((p.x - 0.0).abs() < 1e-12 && (p.y - 1.0).abs() < 1e-12, "{p:?}");
    }

    #[test]
    fn images_average_masks_keep_their_strongest_mark_and_rects_cover() {
        let img = RgbF32::from_fn(5, 4, |x, y| [x as f32, y as f32, 1.0]);
        let r = reduce_rgb(&img, 1);
        assert_eq!((r.width(), r.height()), (2, 2));
        assert_eq!(r.get(1, 0), [2.5, 0.5, 1.0]);
        let mut m = Mask::new(4, 4, 0);
        m.set(3, 2, 200);
        m.set(2, 3, 130);
        let rm = reduce_mask(&m, 1);
        assert_eq!((rm.get(1, 1), rm.get(0, 0), rm.get(0, 1)), (200, 0, 0));
        assert_eq!(reduce_rect(Rect::from_corners(3, 1, 7, 4), 1, 3, 3), Rect::from_corners(1, 0, 3, 2));
        assert_eq!(levels_for(4000, 3000, 1_300_000), 2);
        assert_eq!(levels_for(640, 480, 1_300_000), 0);
    }

    #[test]
    fn a_view_maps_onto_its_reduced_self() {
        // A view that is the keyframe shifted by (6, -4) pixels: reduced twice, by (1.5, -1).
        let key = RgbF32::new(64, 48, [0.5; 3]);
        let view = key.clone();
        let h = Homography::translation(6.0, -4.0);
        let mask = Mask::new(64, 48, 0);
        let sources = [Source { image: &view, homography: h }];
        let r = Reduced::new(&key, &mask, &sources, &FillExtras::default(), 2);
        let q = r.sources()[0].homography.apply(Point2::new(3.0, 5.0)).unwrap();
        assert!((q.x - 4.5).abs() < 1e-9 && (q.y - 4.0).abs() < 1e-9, "{q:?}");
        assert_eq!((r.key.width(), r.key.height()), (16, 12));
    }
}
