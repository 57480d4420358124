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

use nalgebra::{Matrix3, Point2, SMatrix, SVector, Vector3};

use crate::geometry::Homography;
use crate::imaging::filter::gaussian_blur;
use crate::imaging::warp::Rect;
use crate::imaging::{GrayF32, Mask, Plane, RgbF32, RgbPixel, bilinear, bilinear_rgb};

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
    /// After the shift, the view is brought onto the keyframe by a small homography over
    /// the band (the correlation maximised, as ECC does), where one shift cannot hold the
    /// whole hole: a facade that turns or bends across it (parapano_building's glass, a
    /// roof at an angle to the wall). `None`: the shift only.
    pub refine: Option<RefineParams>,
}

/// Parameters of the homography that refines a local shift ([`ShiftParams::refine`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RefineParams {
    /// Iterations per level (the band and view blurred, then sharp).
    pub iterations: usize,
    /// The σ of the blur of the first level, pixels (a wider basin for thin lines).
    pub blur: f32,
    /// The refined map is taken when it raises the band's correlation by at least this much
    /// over the shift's (over none, when no shift was taken)...
    pub min_gain: f64,
    /// ...and moves no point of the hole's part by more than this from where the shift (or
    /// none) put it, keyframe pixels: a fit that bends the hole's inside far is one the band
    /// around it does not pin down...
    pub reach: f64,
    /// ...and no side of the hole (as [`ShiftParams::side_slack`]) correlates worse with it
    /// by more than this than with the better of the shift and none: a step in depth on
    /// one side (a pier) is fitted by a ramp that costs the other sides (0.011 on the
    /// test's 2 px step; BENCHMARKS.md, "A view bent onto the keyframe around each hole").
    pub side_slack: f64,
    /// ...and, fitted again to the band's outer half alone, it foretells the inner half on
    /// every side no worse than the shift (or none) by more than this: the hole continues
    /// what lies nearest it. `None`: not checked. Over the 86 real-photo, HPatches, Oxford
    /// and non-planar cases this keeps the glass curtain wall and the generated slabs from
    /// being bent (+0.17 and +0.19 dB per case there) and costs HPatches and Oxford 0.03
    /// (BENCHMARKS.md, "A bend must foretell the band nearer the hole").
    pub held_out: Option<f64>,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            iterations: 30,
            blur: 1.5,
            min_gain: 0.005,
            reach: 3.0,
            side_slack: 0.01,
            held_out: Some(0.01),
        }
    }
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
            refine: Some(RefineParams::default()),
        }
    }
}

/// What [`local_shift`] measured: the correlation over the band as the homography puts the
/// view, and the best map's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shift {
    /// Where the map moves the hole's centre (keyframe pixels): for a shift alone, the view's
    /// pixel for keyframe pixel `x` is `H·(x + d)`.
    pub d: (f64, f64),
    /// The map applied to keyframe coordinates before the homography: a translation by `d`,
    /// or the refined homography ([`ShiftParams::refine`]).
    pub correction: Homography,
    /// The most it moves a point of the hole's part (keyframe pixels).
    pub moved_px: f64,
    pub ncc_before: f64,
    pub ncc_after: f64,
}

impl Shift {
    /// The homography with the shift in it.
    pub fn apply(&self, h: &Homography) -> Homography {
        h.after(&self.correction)
    }
}

fn luma(p: [f32; 3]) -> f64 {
    f64::from(0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
}

/// The keyframe pixels of the band around `hole` (`rect`-sized, keyframe pixels of `rect`),
/// outside every hole of `mask`, evenly thinned to at most `params.max_samples` pixels; each
/// with whether it lies in the band's inner half.
fn band_pixels(
    mask: &Mask,
    hole: &Plane<bool>,
    rect: Rect,
    params: &ShiftParams,
) -> Vec<(usize, usize, bool)> {
    let (w, h) = (mask.width(), mask.height());
    let outer = rect.grown(params.gap + params.band, w, h);
    let (ox, oy) = (rect.x - outer.x, rect.y - outer.y);
    let own = Plane::from_fn(outer.width, outer.height, |x, y| {
        x >= ox && y >= oy && x - ox < rect.width && y - oy < rect.height && hole.get(x - ox, y - oy)
    });
    let near = dilate(&own, params.gap);
    let far = dilate(&own, params.gap + params.band);
    let mid = dilate(&own, params.gap + params.band / 2);
    let mut out = Vec::new();
    for y in 0..outer.height {
        for x in 0..outer.width {
            let (kx, ky) = (outer.x + x, outer.y + y);
            if far.get(x, y) && !near.get(x, y) && !mask.is_hole(kx, ky) {
                out.push((kx, ky, mid.get(x, y)));
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

/// A band pixel: its position, whether it lies in the band's inner half (nearer the hole),
/// the side of the hole it is on (four quadrants about the hole's centre), the keyframe's
/// luminance there and, for the refinement, blurred.
#[derive(Debug, Clone, Copy)]
struct BandPixel {
    x: usize,
    y: usize,
    inner: bool,
    side: usize,
    k: f64,
    blurred: f64,
}

/// The keyframe's side of a hole's band, the same for every view.
#[derive(Debug, Clone)]
pub struct ShiftBand {
    pixels: Vec<BandPixel>,
    /// The box of the hole's part (the hole and the context around it; keyframe pixels).
    rect: Rect,
}

impl ShiftBand {
    /// The band around `hole` (a part's hole pixels, `rect`-sized) of keyframe `key`.
    pub fn new(key: &RgbF32, mask: &Mask, hole: &Plane<bool>, rect: Rect, params: &ShiftParams) -> Self {
        let c = centre(rect);
        let positions = band_pixels(mask, hole, rect, params);
        // The keyframe blurred as the refinement's first level sees the view (its own
        // neighbourhood: the blur reaches past the band, not into the hole's content, which
        // the band never nears by less than `gap`).
        let blurred = params.refine.as_ref().filter(|_| !positions.is_empty()).map(|rp| {
            let outer = rect.grown(params.gap + params.band + 8, key.width(), key.height());
            let lum = GrayF32::from_fn(outer.width, outer.height, |x, y| {
                luma(key.get(outer.x + x, outer.y + y)) as f32
            });
            (outer, gaussian_blur(&lum, rp.blur))
        });
        let pixels = positions
            .into_iter()
            .map(|(x, y, inner)| {
                let side = usize::from(x as f64 >= c.x) + 2 * usize::from(y as f64 >= c.y);
                let k = luma(key.get(x, y));
                let blurred = blurred.as_ref().map_or(k, |(o, b)| f64::from(b.get(x - o.x, y - o.y)));
                BandPixel { x, y, inner, side, k, blurred }
            })
            .collect();
        Self { pixels, rect }
    }
}

/// The correlation of the keyframe's band (the pixels `which` takes) with `view` seen
/// through `map` (band pixel index → homogeneous view point), over those pixels and over
/// each side (`None` for a side with fewer than `per_side` pixels seen); `None` when fewer
/// than `need` pixels are seen.
fn band_ncc<P: RgbPixel>(
    band: &ShiftBand,
    view: &Plane<P>,
    occluders: Option<&Mask>,
    (need, per_side): (usize, usize),
    map: impl Fn(usize) -> Vector3<f64>,
    which: impl Fn(&BandPixel) -> bool,
) -> Option<(f64, [Option<f64>; SIDES])> {
    let mut sums = [Sums::default(); SIDES];
    for (i, b) in band.pixels.iter().enumerate() {
        if !which(b) {
            continue;
        }
        let p = map(i);
        if p.z.abs() < 1e-12 {
            continue;
        }
        let (vx, vy) = (p.x / p.z, p.y / p.z);
        if occluders.is_some_and(|occ| taps_occluded(occ, vx, vy)) {
            continue;
        }
        let Some(v) = bilinear_rgb(view, vx as f32, vy as f32).map(luma) else { continue };
        sums[b.side].add(b.k, v);
    }
    let all = sums.iter().fold(Sums::default(), |a, b| a.merged(b));
    if all.n < need {
        return None;
    }
    Some((all.ncc()?, sums.map(|s| if s.n >= per_side { s.ncc() } else { None })))
}

/// Whether no side seen both ways correlates worse by more than `slack` after than before,
/// and at least `min_sides` are.
fn sides_hold(before: &[Option<f64>; SIDES], after: &[Option<f64>; SIDES], params: &ShiftParams) -> bool {
    let pairs: Vec<(f64, f64)> = before.iter().zip(after).filter_map(|(b, a)| Some(((*b)?, (*a)?))).collect();
    pairs.len() >= params.min_sides && !pairs.iter().any(|&(b, a)| a < b - params.side_slack)
}

/// The map (shift, or shift refined) that best brings `source` (its view and keyframe → view
/// homography) onto the keyframe over `band`; view pixels its `occluders` mark (view-sized,
/// 255 = occluder) are not compared. `None` when the view sees too little of the band, or
/// no map makes it clearly more alike than none.
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
    // Per band pixel H·x (homogeneous); a shift adds dx·H₀ + dy·H₁.
    let hx: Vec<Vector3<f64>> =
        band.pixels.iter().map(|b| m * Vector3::new(b.x as f64, b.y as f64, 1.0)).collect();
    let need = ((band.pixels.len() as f64 * params.min_seen).ceil() as usize).max(64);
    let counts = (need, (need / 8).max(32));
    let ncc =
        |dx: f64, dy: f64| band_ncc(band, view, occluders, counts, |i| hx[i] + c0 * dx + c1 * dy, |_| true);
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
    let sides_shifted = ncc(dx, dy).map(|(_, sides)| sides);
    // One shift for the whole hole: where one side of it is better off without (a pier
    // in front of the wall on that side, another depth), the view is left as it is.
    let shifted = (after - before >= params.min_gain)
        .then_some(sides_shifted)
        .flatten()
        .filter(|sides_after| sides_hold(&sides_before, sides_after, params))
        .map(|_| Shift {
            d: (dx, dy),
            correction: Homography::translation(dx, dy),
            moved_px: dx.hypot(dy),
            ncc_before: before,
            ncc_after: after,
        });
    let refined = params.refine.as_ref().and_then(|rp| {
        let correction = refine(band, source, occluders, (dx, dy), counts.0, rp, |_| true)?;
        let h = source.homography.after(&correction);
        let (z, sides) = band_ncc(band, view, occluders, counts, through(band, &h), |_| true)?;
        let base = shifted.map_or(Homography::identity(), |s| s.correction);
        let (gained, moved) =
            (z - shifted.map_or(before, |s| s.ncc_after), farthest(&correction, &base, band.rect));
        // Every side at least as alike as with the shift or none: a map that bends to fit
        // another depth on one side (a ramp where the facade steps) costs the others.
        let best_rigid: [Option<f64>; SIDES] =
            std::array::from_fn(|k| match (sides_before[k], sides_shifted.and_then(|s| s[k])) {
                (Some(b), Some(t)) => Some(b.max(t)),
                (b, t) => b.or(t),
            });
        let each = best_rigid.iter().zip(&sides).all(|(b, a)| match (b, a) {
            (Some(b), Some(a)) => *a >= b - rp.side_slack,
            _ => true,
        });
        let fits =
            gained >= rp.min_gain && moved <= rp.reach && each && sides_hold(&sides_before, &sides, params);
        let foretold = || {
            rp.held_out.is_none_or(|slack| {
                let rigid = source.homography.after(&base);
                foretells_inner(band, source, occluders, (dx, dy), counts, rp, &rigid, slack)
            })
        };
        (fits && foretold()).then(|| {
            let c = centre(band.rect);
            let d = correction.apply(c).map_or((0.0, 0.0), |q| (q.x - c.x, q.y - c.y));
            Shift {
                d,
                correction,
                moved_px: farthest(&correction, &Homography::identity(), band.rect),
                ncc_before: before,
                ncc_after: z,
            }
        })
    });
    refined.or(shifted)
}

/// Whether the refinement, fitted again to the outer half of the band alone, foretells the
/// inner half (nearer the hole) on every side no worse than the rigid map (`rigid`: the
/// homography with the shift or none) by more than `slack`. The map is fitted around the
/// hole and used inside it; one that a surface nearer the hole does not follow (a sign or a
/// reveal around it, another depth beyond it, glass whose reflections move) is not carried
/// in. Where the inner half is seen too little to tell, the map stands.
#[allow(clippy::too_many_arguments)]
fn foretells_inner<P: RgbPixel>(
    band: &ShiftBand,
    source: &Source<'_, P>,
    occluders: Option<&Mask>,
    start: (f64, f64),
    (need, per_side): (usize, usize),
    rp: &RefineParams,
    rigid: &Homography,
    slack: f64,
) -> bool {
    let inner = |b: &BandPixel| b.inner;
    let counts = (need / 4, per_side / 2);
    let Some((_, before)) = band_ncc(band, source.image, occluders, counts, through(band, rigid), inner)
    else {
        return true;
    };
    let outer = |b: &BandPixel| !b.inner;
    let Some(fitted) = refine(band, source, occluders, start, need / 2, rp, outer) else { return false };
    let h = source.homography.after(&fitted);
    let Some((_, after)) = band_ncc(band, source.image, occluders, counts, through(band, &h), inner) else {
        return false;
    };
    before.iter().zip(&after).all(|(b, a)| match (b, a) {
        (Some(b), Some(a)) => *a >= b - slack,
        _ => true,
    })
}

/// Band pixel index → its homogeneous point in the view `h` maps the keyframe to.
fn through<'a>(band: &'a ShiftBand, h: &Homography) -> impl Fn(usize) -> Vector3<f64> + 'a {
    let m = *h.matrix();
    move |i| m * Vector3::new(band.pixels[i].x as f64, band.pixels[i].y as f64, 1.0)
}

fn centre(r: Rect) -> Point2<f64> {
    Point2::new(r.x as f64 + 0.5 * r.width as f64, r.y as f64 + 0.5 * r.height as f64)
}

/// The farthest apart `a` and `b` put a point of box `r` (a 5 × 5 grid over it, corners
/// included), keyframe pixels.
fn farthest(a: &Homography, b: &Homography, r: Rect) -> f64 {
    let mut most = 0.0f64;
    for j in 0..5 {
        for i in 0..5 {
            let p = Point2::new(
                r.x as f64 + r.width as f64 * i as f64 / 4.0,
                r.y as f64 + r.height as f64 * j as f64 / 4.0,
            );
            match (a.apply(p), b.apply(p)) {
                (Some(u), Some(v)) => most = most.max((u - v).norm()),
                _ => return f64::INFINITY,
            }
        }
    }
    most
}

/// The homography `A` (keyframe → keyframe, near the translation `start`) for which the
/// view seen through `H·A` correlates best with the keyframe over the band: the enhanced
/// correlation coefficient's iterations (Evangelidis and Psarakis, 2008), on the band (the
/// pixels `fit_on` takes) and view blurred, then sharp. `None` when it cannot be fitted
/// (fewer than `need` band pixels seen, a flat band, or the fit diverging); how far it may
/// move is the caller's to judge.
fn refine<P: RgbPixel>(
    band: &ShiftBand,
    source: &Source<'_, P>,
    occluders: Option<&Mask>,
    start: (f64, f64),
    need: usize,
    rp: &RefineParams,
    fit_on: impl Fn(&BandPixel) -> bool,
) -> Option<Homography> {
    let r = band.rect;
    // Keyframe pixels normalised over the part's box (a well-conditioned fit): u = (x − c)/s.
    let c = centre(r);
    let s = 0.5 * r.width.max(r.height).max(1) as f64;
    let n_inv = Matrix3::new(s, 0.0, c.x, 0.0, s, c.y, 0.0, 0.0, 1.0);
    let n = Matrix3::new(1.0 / s, 0.0, -c.x / s, 0.0, 1.0 / s, -c.y / s, 0.0, 0.0, 1.0);
    let hm = *source.homography.matrix();
    let m = hm * n_inv;
    // The view's luminance over the band's footprint, with room to move (`reach` and the
    // gradient's taps, in keyframe pixels, as the view's scale there makes them).
    let view = source.image;
    let pad = (rp.reach + 4.0) * source.homography.area_scale(c).abs().sqrt().max(1.0);
    let (mut x0, mut y0, mut x1, mut y1) =
        (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for b in &band.pixels {
        let q = source.homography.apply(Point2::new(b.x as f64 + start.0, b.y as f64 + start.1))?;
        (x0, y0, x1, y1) = (x0.min(q.x), y0.min(q.y), x1.max(q.x), y1.max(q.y));
    }
    let clip = |v: f64, hi: usize| v.clamp(0.0, hi as f64) as usize;
    let (cx0, cy0) = (clip((x0 - pad).floor(), view.width()), clip((y0 - pad).floor(), view.height()));
    let (cx1, cy1) =
        (clip((x1 + pad).ceil() + 1.0, view.width()), clip((y1 + pad).ceil() + 1.0, view.height()));
    if cx1 < cx0 + 8 || cy1 < cy0 + 8 {
        return None;
    }
    let sharp =
        GrayF32::from_fn(cx1 - cx0, cy1 - cy0, |x, y| luma(view.get(cx0 + x, cy0 + y).to_f32()) as f32);
    let soft = gaussian_blur(&sharp, rp.blur);
    let uv: Vec<(f64, f64)> =
        band.pixels.iter().map(|b| ((b.x as f64 - c.x) / s, (b.y as f64 - c.y) / s)).collect();
    // The correction in normalised coordinates, [[1+p0, p1, p2], [p3, 1+p4, p5], [p6, p7, 1]].
    let mut p = [0.0, 0.0, start.0 / s, 0.0, 0.0, start.1 / s, 0.0, 0.0];
    let correction =
        |p: &[f64; 8]| Matrix3::new(1.0 + p[0], p[1], p[2], p[3], 1.0 + p[4], p[5], p[6], p[7], 1.0);
    for (level, image) in [(0, &soft), (1, &sharp)] {
        for _ in 0..rp.iterations {
            let cm = correction(&p);
            // Per sample: the keyframe's value, the view's, and the view's change with p.
            let mut rows: Vec<(f64, f64, [f64; 8])> = Vec::with_capacity(band.pixels.len());
            for (b, &(u, v)) in band.pixels.iter().zip(&uv) {
                if !fit_on(b) {
                    continue;
                }
                let y = cm * Vector3::new(u, v, 1.0);
                let q = m * y;
                if q.z.abs() < 1e-12 {
                    continue;
                }
                let (qx, qy) = (q.x / q.z, q.y / q.z);
                if occluders.is_some_and(|occ| taps_occluded(occ, qx, qy)) {
                    continue;
                }
                let (lx, ly) = ((qx - cx0 as f64) as f32, (qy - cy0 as f64) as f32);
                let at = |dx: f32, dy: f32| bilinear(image, lx + dx, ly + dy);
                let (Some(val), Some(l), Some(rr), Some(t), Some(bt)) =
                    (at(0.0, 0.0), at(-1.0, 0.0), at(1.0, 0.0), at(0.0, -1.0), at(0.0, 1.0))
                else {
                    continue;
                };
                let (gx, gy) = (0.5 * f64::from(rr - l), 0.5 * f64::from(bt - t));
                // ∂q/∂y = [(M₀ − qx·M₂) / q_z; (M₁ − qy·M₂) / q_z], then along ∂y/∂p.
                let g: [f64; 3] = std::array::from_fn(|j| {
                    (gx * (m[(0, j)] - qx * m[(2, j)]) + gy * (m[(1, j)] - qy * m[(2, j)])) / q.z
                });
                let jac = [g[0] * u, g[0] * v, g[0], g[1] * u, g[1] * v, g[1], g[2] * u, g[2] * v];
                let k = if level == 0 { b.blurred } else { b.k };
                rows.push((k, f64::from(val), jac));
            }
            if rows.len() < need {
                return None;
            }
            let dp = ecc_step(&rows)?;
            for (a, d) in p.iter_mut().zip(&dp) {
                *a += d;
            }
            if p.iter().any(|a| !a.is_finite()) {
                return None;
            }
            if dp.iter().map(|d| d.abs()).fold(0.0, f64::max) * s < 0.01 {
                break;
            }
        }
    }
    Homography::from_matrix(n_inv * correction(&p) * n)
}

/// One step of the enhanced correlation coefficient's maximisation: per sample the
/// template's value, the warped image's and its Jacobian in the parameters.
fn ecc_step(rows: &[(f64, f64, [f64; 8])]) -> Option<[f64; 8]> {
    let n = rows.len() as f64;
    let (mut mk, mut mv, mut mj) = (0.0, 0.0, [0.0; 8]);
    for (k, v, j) in rows {
        mk += k;
        mv += v;
        for (a, b) in mj.iter_mut().zip(j) {
            *a += b;
        }
    }
    (mk, mv) = (mk / n, mv / n);
    mj.iter_mut().for_each(|a| *a /= n);
    // Zero-mean: the Hessian GᵀG, Gᵀ·i_r, Gᵀ·i_w, and the products of the two images.
    let mut hess = SMatrix::<f64, 8, 8>::zeros();
    let (mut gr, mut gw) = (SVector::<f64, 8>::zeros(), SVector::<f64, 8>::zeros());
    let (mut rw, mut ww) = (0.0, 0.0);
    for (k, v, j) in rows {
        let (r, w) = (k - mk, v - mv);
        let g = SVector::<f64, 8>::from_fn(|i, _| j[i] - mj[i]);
        hess += g * g.transpose();
        gr += g * r;
        gw += g * w;
        rw += r * w;
        ww += w * w;
    }
    let inv = hess.try_inverse()?;
    let (proj_w, proj_r) = ((gw.transpose() * inv * gw)[0], (gr.transpose() * inv * gw)[0]);
    let den = rw - proj_r;
    if den <= 1e-12 {
        return None;
    }
    let lambda = (ww - proj_w) / den;
    let dp = inv * (gr * lambda - gw);
    Some(std::array::from_fn(|i| dp[i]))
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

    /// A view whose map onto the keyframe turns across the hole (a scale and a touch of
    /// perspective: the facade bends, or the view stands farther along): no one shift holds
    /// the band, the refined map does, inside the hole too.
    #[test]
    fn a_view_that_turns_across_the_hole_is_refined_beyond_a_shift() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        // The view shows keyframe point x at A·x.
        let a = Homography::from_rows([[1.03, 0.01, -2.6], [-0.008, 0.975, 2.6], [4e-5, -3e-5, 1.0]])
            .expect("regular");
        let a_inv = a.inverse().expect("regular");
        let view = Plane::from_fn(w, h, |x, y| {
            let p = a_inv.apply(Point2::new(x as f64, y as f64)).expect("finite");
            let (u, v) = (p.x - x as f64, p.y - y as f64);
            scene(1, 1, x as f64 + u, y as f64 + v).get(0, 0)
        });
        // How far the map puts the hole's points from where the view shows them.
        let (_, _, rect) = square_hole(w, h);
        let error = |s: Option<Shift>| {
            let c = s.map_or(Homography::identity(), |s| s.correction);
            let mut worst = 0.0f64;
            for y in (rect.y..rect.y + rect.height).step_by(5) {
                for x in (rect.x..rect.x + rect.width).step_by(5) {
                    let p = Point2::new(x as f64, y as f64);
                    worst = worst.max((c.apply(p).unwrap() - a.apply(p).unwrap()).norm());
                }
            }
            worst
        };
        let p = ShiftParams::default();
        let refined = shift_of(&key, &view, None, &p);
        assert!(refined.is_some_and(|s| s.ncc_after > 0.99), "{refined:?}");
        assert!(error(refined) < 0.15, "refined: {:.3} px off in the hole", error(refined));
        let shifted = shift_of(&key, &view, None, &ShiftParams { refine: None, ..p });
        assert!(error(shifted) > 0.8, "a shift alone: {:.3} px off", error(shifted));
    }

    #[test]
    fn a_view_in_place_is_not_shifted() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        let got = shift_of(&key, &key, None, &ShiftParams::default());
        assert_eq!(got, None);
    }

    /// A keyframe, and a view of it whose right half (x ≥ 80, through the hole) is `step` px
    /// off: a pier standing out of the wall.
    fn stepped(step: f64) -> (RgbF32, RgbF32) {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        let off = scene(w, h, -step, 0.0);
        let view = Plane::from_fn(w, h, |x, y| if x >= 80 { off.get(x, y) } else { key.get(x, y) });
        (key, view)
    }

    #[test]
    fn a_hole_with_another_depth_on_one_side_is_not_shifted() {
        // Left of the hole the view is in place (the wall); right of it, 2 px off (a pier
        // standing out of the wall): no one shift holds both sides.
        let (key, view) = stepped(2.0);
        let p = ShiftParams::default();
        assert_eq!(shift_of(&key, &view, None, &p), None);
        // Without the rule, the right side's gain would move the whole view.
        let loose = ShiftParams { side_slack: 1.0, ..p };
        assert!(shift_of(&key, &view, None, &loose).is_some());
    }

    /// A step in depth across the hole (the right half of the band 3 px off: a pier) is not
    /// bent into a ramp: the ramp would raise the band's correlation, and costs the flat
    /// sides. Without the per-side rule and the check nearer the hole the ramp is taken.
    #[test]
    fn a_step_in_depth_is_not_bent_into_a_ramp() {
        let (key, view) = stepped(3.0);
        let p = ShiftParams::default();
        assert_eq!(shift_of(&key, &view, None, &p), None);
        let rp = p.refine.clone().expect("refined by default");
        // The check against the band nearer the hole turns the ramp down as well.
        let sides_loose =
            ShiftParams { refine: Some(RefineParams { side_slack: 1.0, ..rp.clone() }), ..p.clone() };
        assert_eq!(shift_of(&key, &view, None, &sides_loose), None);
        let loose = ShiftParams { refine: Some(RefineParams { side_slack: 1.0, held_out: None, ..rp }), ..p };
        let ramp = shift_of(&key, &view, None, &loose).expect("a ramp without the rules");
        // A ramp: the map stretches the hole along x (a shift would not).
        let m = ramp.correction.matrix();
        assert!(m[(0, 0)] / m[(2, 2)] > 1.01, "{ramp:?}");
    }

    /// The hole lies on a board that reaches 14 px beyond it, in place in the view; the wall
    /// behind it is seen through a scale about the hole (another depth). A bend fitted to the
    /// whole band follows the wall and raises the band's correlation on every side; fitted to
    /// the outer half alone, it puts the board's edge, nearer the hole, worse than no bend,
    /// so the hole (the board) is not bent. Without the check the bend is taken.
    #[test]
    fn a_bend_the_band_nearer_the_hole_does_not_follow_is_not_taken() {
        let (w, h) = (160, 130);
        let key = scene(w, h, 0.0, 0.0);
        let (_, _, rect) = square_hole(w, h);
        let board = rect.grown(14, w, h);
        let c = centre(rect);
        let view = Plane::from_fn(w, h, |x, y| {
            if board.contains(x, y) {
                key.get(x, y)
            } else {
                // The wall: keyframe point p is seen at c + 1.04·(p − c).
                let (u, v) = (c.x + (x as f64 - c.x) / 1.04, c.y + (y as f64 - c.y) / 1.04);
                scene(1, 1, u, v).get(0, 0)
            }
        });
        let p = ShiftParams::default();
        let got = shift_of(&key, &view, None, &p);
        assert!(got.is_none_or(|s| s.moved_px < 0.3), "{got:?}");
        let rp = p.refine.clone().expect("refined by default");
        let unchecked = ShiftParams { refine: Some(RefineParams { held_out: None, ..rp }), ..p };
        let bent = shift_of(&key, &view, None, &unchecked).expect("a bend without the check");
        assert!(bent.moved_px > 0.5, "{bent:?}");
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
