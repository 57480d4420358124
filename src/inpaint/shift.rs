//! A view's local shift around a hole (core, no I/O).
//!
//! One homography holds a flat wall. A curved glass facade, a roof in front of the wall, or a
//! view taken from farther along puts a view a pixel or more off the keyframe near the mask,
//! though its homography is right on average: the fill then copies every edge that crosses
//! the hole a step off. Around each hole the keyframe shows the scene itself, so the shift
//! that brings the view onto the keyframe there is measured (the normalised cross-correlation
//! of their luminance over a band around the hole, searched on a grid and refined), and taken
//! only when it makes the two clearly more alike. The band is wider than the photometric
//! ring: a shift is a coarser thing to measure than a gain.

use crate::geometry::Homography;
use crate::imaging::warp::Rect;
use crate::imaging::{Mask, Plane, RgbF32, RgbPixel, bilinear_rgb};

use super::Source;
use super::automask::dilate;

/// Parameters of [`local_shift`].
#[derive(Debug, Clone, PartialEq)]
pub struct ShiftParams {
    /// The band the shift is measured on starts this many pixels from the hole (its halo)...
    pub gap: usize,
    /// ...and is this many pixels wide.
    pub band: usize,
    /// Shifts are searched up to this many keyframe pixels along each axis.
    pub reach: f64,
    /// The grid's step; the best point is refined to an eighth of it.
    pub step: f64,
    /// A shift is taken when it raises the band's correlation by at least this much. On the
    /// real photo cases the shifts that cost the hole a few tenths of a dB raised it by
    /// 0.001 or less; those worth a dB or more by 0.008 to 0.018.
    pub min_gain: f64,
    /// At most this many band pixels are compared (evenly spaced through the band).
    pub max_samples: usize,
    /// A view compares at least this share of them, else it is not shifted.
    pub min_seen: f64,
    /// The shift is one for the whole hole: it is not taken when the band on any side of
    /// the hole (quadrants about its centre) correlates worse by more than this with it
    /// than without (another depth on that side, such as a pier before the wall). On the
    /// real photo and HPatches cases the shifts worth a dB cost a side at most 0.03; on
    /// the generated piers, those that cost the hole 2 dB cost a side 0.05 to 0.37.
    pub side_slack: f64,
    /// ...and it is measured on at least this many sides (a band seen on one side alone
    /// does not pin a shift down).
    pub min_sides: usize,
}

impl Default for ShiftParams {
    fn default() -> Self {
        Self {
            gap: 3,
            band: 27,
            reach: 3.0,
            step: 1.0,
            min_gain: 0.005,
            max_samples: 5_000,
            min_seen: 0.3,
            side_slack: 0.04,
            min_sides: 2,
        }
    }
}

/// What [`local_shift`] measured: the correlation over the band as the homography puts the
/// view, and the best shift's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shift {
    /// Added to keyframe coordinates before the homography: the view's pixel for keyframe
    /// pixel `x` is `H·(x + d)`.
    pub d: (f64, f64),
    pub ncc_before: f64,
    pub ncc_after: f64,
}

impl Shift {
    /// The homography with the shift in it.
    pub fn apply(&self, h: &Homography) -> Homography {
        h.after(&Homography::translation(self.d.0, self.d.1))
    }
}

fn luma(p: [f32; 3]) -> f64 {
    f64::from(0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
}

/// The keyframe pixels of the band around `hole` (`rect`-sized, keyframe pixels of `rect`),
/// outside every hole of `mask`, evenly thinned to at most `params.max_samples` pixels.
fn band_pixels(mask: &Mask, hole: &Plane<bool>, rect: Rect, params: &ShiftParams) -> Vec<(usize, usize)> {
    let (w, h) = (mask.width(), mask.height());
    let grow = params.gap + params.band;
    let outer = Rect {
        x: rect.x.saturating_sub(grow),
        y: rect.y.saturating_sub(grow),
        width: (rect.x + rect.width + grow).min(w) - rect.x.saturating_sub(grow),
        height: (rect.y + rect.height + grow).min(h) - rect.y.saturating_sub(grow),
    };
    let (ox, oy) = (rect.x - outer.x, rect.y - outer.y);
    let own = Plane::from_fn(outer.width, outer.height, |x, y| {
        x >= ox && y >= oy && x - ox < rect.width && y - oy < rect.height && hole.get(x - ox, y - oy)
    });
    let near = dilate(&own, params.gap);
    let far = dilate(&own, grow);
    let mut out = Vec::new();
    for y in 0..outer.height {
        for x in 0..outer.width {
            let (kx, ky) = (outer.x + x, outer.y + y);
            if far.get(x, y) && !near.get(x, y) && !mask.is_hole(kx, ky) {
                out.push((kx, ky));
            }
        }
    }
    let stride = out.len().div_ceil(params.max_samples.max(1)).max(1);
    out.into_iter().step_by(stride).collect()
}

/// Whether any of the 2×2 pixels a bilinear sample at `(x, y)` reads is marked.
fn taps_occluded(occ: &Mask, x: f64, y: f64) -> bool {
    let (x0, y0) = (x.floor(), y.floor());
    [(x0, y0), (x0 + 1.0, y0), (x0, y0 + 1.0), (x0 + 1.0, y0 + 1.0)].iter().any(|&(tx, ty)| {
        tx >= 0.0
            && ty >= 0.0
            && (tx as usize) < occ.width()
            && (ty as usize) < occ.height()
            && occ.is_hole(tx as usize, ty as usize)
    })
}

/// The keyframe's side of a hole's band, the same for every view: per band pixel its
/// position, the side of the hole it is on (four quadrants about the hole's centre) and the
/// keyframe's luminance there.
#[derive(Debug, Clone)]
pub struct ShiftBand {
    pixels: Vec<(usize, usize, usize, f64)>,
}

impl ShiftBand {
    /// The band around `hole` (a part's hole pixels, `rect`-sized) of keyframe `key`.
    pub fn new(key: &RgbF32, mask: &Mask, hole: &Plane<bool>, rect: Rect, params: &ShiftParams) -> Self {
        let (cx, cy) = (rect.x as f64 + 0.5 * rect.width as f64, rect.y as f64 + 0.5 * rect.height as f64);
        let pixels = band_pixels(mask, hole, rect, params)
            .into_iter()
            .map(|(x, y)| {
                let side = usize::from(x as f64 >= cx) + 2 * usize::from(y as f64 >= cy);
                (x, y, side, luma(key.get(x, y)))
            })
            .collect();
        Self { pixels }
    }
}

/// The shift (keyframe pixels) that best brings `source` (its view and keyframe → view
/// homography) onto the keyframe over `band`; view pixels its `occluders` mark (view-sized,
/// 255 = occluder) are not compared. `None` when the view sees too little of the band, or
/// no shift makes it clearly more alike than none.
pub fn local_shift<P: RgbPixel>(
    band: &ShiftBand,
    source: &Source<'_, P>,
    occluders: Option<&Mask>,
    params: &ShiftParams,
) -> Option<Shift> {
    if band.pixels.is_empty() {
        return None;
    }
    let (view, m) = (source.image, source.homography.matrix());
    let (c0, c1) = (m.column(0).into_owned(), m.column(1).into_owned());
    // Per band pixel: its side, the keyframe's luminance and H·x (homogeneous); a shift adds
    // dx·H₀ + dy·H₁.
    let samples: Vec<(usize, f64, nalgebra::Vector3<f64>)> = band
        .pixels
        .iter()
        .map(|&(x, y, side, k)| (side, k, m * nalgebra::Vector3::new(x as f64, y as f64, 1.0)))
        .collect();
    let need = ((samples.len() as f64 * params.min_seen).ceil() as usize).max(64);
    let per_side = (need / 8).max(32);
    // The correlation over the whole band and over each side (`None` for a side with too
    // few pixels seen).
    let ncc = |dx: f64, dy: f64| -> Option<(f64, [Option<f64>; SIDES])> {
        let mut sums = [Sums::default(); SIDES];
        for (side, k, q) in &samples {
            let p = q + c0 * dx + c1 * dy;
            if p.z.abs() < 1e-12 {
                continue;
            }
            let (vx, vy) = (p.x / p.z, p.y / p.z);
            if occluders.is_some_and(|occ| taps_occluded(occ, vx, vy)) {
                continue;
            }
            let Some(v) = bilinear_rgb(view, vx as f32, vy as f32).map(luma) else { continue };
            sums[*side].add(*k, v);
        }
        let all = sums.iter().fold(Sums::default(), |a, b| a.merged(b));
        if all.n < need {
            return None;
        }
        Some((all.ncc()?, sums.map(|s| if s.n >= per_side { s.ncc() } else { None })))
    };
    let (before, sides_before) = ncc(0.0, 0.0)?;
    let mut best = (before, 0.0, 0.0);
    let steps = (params.reach / params.step).round() as i64;
    let consider = |dx: f64, dy: f64, best: &mut (f64, f64, f64)| {
        if let Some((z, _)) = ncc(dx, dy)
            && z > best.0
        {
            *best = (z, dx, dy);
        }
    };
    for j in -steps..=steps {
        for i in -steps..=steps {
            consider(i as f64 * params.step, j as f64 * params.step, &mut best);
        }
    }
    // Refined around the best point: its neighbours at half the step, then at an eighth.
    for (reach, fine) in [(1i64, params.step / 2.0), (3, params.step / 8.0)] {
        let (gx, gy) = (best.1, best.2);
        for j in -reach..=reach {
            for i in -reach..=reach {
                if i != 0 || j != 0 {
                    consider(gx + i as f64 * fine, gy + j as f64 * fine, &mut best);
                }
            }
        }
    }
    let (after, dx, dy) = best;
    if after - before < params.min_gain {
        return None;
    }
    // One shift for the whole hole: where one side of it is better off without (a pier
    // in front of the wall on that side, another depth), the view is left as it is.
    let (_, sides_after) = ncc(dx, dy)?;
    let pairs: Vec<(f64, f64)> =
        sides_before.iter().zip(&sides_after).filter_map(|(b, a)| Some(((*b)?, (*a)?))).collect();
    let worse = pairs.iter().any(|&(b, a)| a < b - params.side_slack);
    (pairs.len() >= params.min_sides && !worse).then_some(Shift {
        d: (dx, dy),
        ncc_before: before,
        ncc_after: after,
    })
}

const SIDES: usize = 4;

/// Running sums for a normalised cross-correlation.
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    n: usize,
    k: f64,
    v: f64,
    kk: f64,
    vv: f64,
    kv: f64,
}

impl Sums {
    fn add(&mut self, k: f64, v: f64) {
        self.n += 1;
        self.k += k;
        self.v += v;
        self.kk += k * k;
        self.vv += v * v;
        self.kv += k * v;
    }

    fn merged(self, o: &Sums) -> Sums {
        Sums {
            n: self.n + o.n,
            k: self.k + o.k,
            v: self.v + o.v,
            kk: self.kk + o.kk,
            vv: self.vv + o.vv,
            kv: self.kv + o.kv,
        }
    }

    fn ncc(&self) -> Option<f64> {
        let n = self.n as f64;
        let (vk, vv) = (self.kk - self.k * self.k / n, self.vv - self.v * self.v / n);
        if self.n == 0 || vk <= 1e-12 || vv <= 1e-12 {
            return None;
        }
        Some((self.kv - self.k * self.v / n) / (vk * vv).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured scene sampled at `(x + ox, y + oy)`.
    fn scene(w: usize, h: usize, ox: f64, oy: f64) -> RgbF32 {
        Plane::from_fn(w, h, |x, y| {
            let (u, v) = (x as f64 + ox, y as f64 + oy);
            // Fine detail as well as coarse (a facade's edges make a pixel's offset count).
            let t = 0.5
                + 0.2 * (u * 0.31).sin() * (v * 0.17).cos()
                + 0.15 * ((u + 2.0 * v) * 0.11).sin()
                + 0.1 * (u * 0.83).sin() * (v * 0.61).sin();
            [t as f32, (0.8 * t) as f32, (1.0 - t) as f32]
        })
    }

    /// The shift of `view` (the identity its homography) around the square hole.
    fn shift_of(key: &RgbF32, view: &RgbF32, occ: Option<&Mask>, p: &ShiftParams) -> Option<Shift> {
        let (mask, hole, rect) = square_hole(key.width(), key.height());
        let band = ShiftBand::new(key, &mask, &hole, rect, p);
        local_shift(&band, &Source { image: view, homography: Homography::identity() }, occ, p)
    }

    fn square_hole(w: usize, h: usize) -> (Mask, Plane<bool>, Rect) {
        let rect = Rect { x: 50, y: 40, width: 60, height: 50 };
        let mask = Mask::from_fn(w, h, |x, y| {
            u8::from(
                (rect.x..rect.x + rect.width).contains(&x) && (rect.y..rect.y + rect.height).contains(&y),
            ) * 255
        });
        (mask, Plane::new(rect.width, rect.height, true), rect)
    }

    #[test]
    fn a_view_a_pixel_and_a_half_off_is_brought_back() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        // The view shows the scene 1.5 px to the right and 0.75 px down of where the
        // homography (the identity) puts it.
        let view = scene(w, h, -1.5, -0.75);
        let s = shift_of(&key, &view, None, &ShiftParams::default()).expect("a shift");
        assert!((s.d.0 - 1.5).abs() <= 0.07 && (s.d.1 - 0.75).abs() <= 0.07, "{s:?}");
        assert!(s.ncc_after > 0.99 && s.ncc_before < s.ncc_after, "{s:?}");
    }

    #[test]
    fn a_view_in_place_is_not_shifted() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        let got = shift_of(&key, &key, None, &ShiftParams::default());
        assert_eq!(got, None);
    }

    #[test]
    fn a_hole_with_another_depth_on_one_side_is_not_shifted() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        // Left of the hole the view is in place (the wall); right of it, 2 px off (a pier
        // standing out of the wall): no one shift holds both sides.
        let off = scene(w, h, -2.0, 0.0);
        let view = Plane::from_fn(w, h, |x, y| if x >= 80 { off.get(x, y) } else { key.get(x, y) });
        let p = ShiftParams::default();
        assert_eq!(shift_of(&key, &view, None, &p), None);
        // Without the rule, the right side's gain would move the whole view.
        let loose = ShiftParams { side_slack: 1.0, ..p };
        assert!(shift_of(&key, &view, None, &loose).is_some());
    }

    #[test]
    fn what_the_views_own_occluders_cover_is_not_compared() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        // The view is 1.5 px off on its right; its left is a passer-by who shows the same
        // texture 2.5 px the other way (the worst case: it correlates too).
        let (right, left) = (scene(w, h, -1.5, -0.75), scene(w, h, 2.5, 0.0));
        let view = Plane::from_fn(w, h, |x, y| if x < 80 { left.get(x, y) } else { right.get(x, y) });
        let occ = Mask::from_fn(w, h, |x, _| u8::from(x < 80) * 255);
        let p = ShiftParams::default();
        let marked = shift_of(&key, &view, Some(&occ), &p).expect("a shift");
        assert!((marked.d.0 - 1.5).abs() <= 0.07 && (marked.d.1 - 0.75).abs() <= 0.07, "{marked:?}");
        let unmarked = shift_of(&key, &view, None, &p);
        assert!(unmarked.is_none_or(|s| (s.d.0 - 1.5).abs() > 0.07), "{unmarked:?}");
    }
}
