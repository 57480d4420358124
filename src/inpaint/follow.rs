//! The keyframe's occluders followed into another frame of a walk by their motion against
//! the facade (pure layer).
//!
//! A near tree or car stands still in the world; the camera's walk carries it across the
//! facade. In the keyframe's coordinates (the facade's, once a frame is aligned), a frame
//! shows each occluder of the keyframe's mask displaced by one shift: its parallax against
//! the wall, the same for the whole object while its depth is about one. Where that shift
//! is found, the frame's pixels that the shifted occluder covers show the occluder, whatever
//! they look like: a car's flat body, which the frames around show displaced and so agree
//! with (no judgement from colours can mark it there), is marked by where it moved.
//!
//! The shift of each connected part of the mask is found by matching what of the part's
//! core moved (the mask less a rim, where the frame does not show in place what the keyframe
//! shows: the occluder, not the wall a generous brush took with it) against the frame taken
//! to the keyframe's coordinates, over every shift in range on a reduced copy, then refined
//! at full size. A part is followed only where the match is clear:
//! - most of what the frame shows of the core agrees at the shift, clearly more of it than
//!   at the shifts of the range's upper decile, and than at the best shift half the part's
//!   size away (a flat or dark occluder matches every dark pane of a glass wall);
//! - the shift lies along the way the facade moves in the frame (a thing in front of the
//!   wall moves across it with the camera's path, further), and near the shift the frames
//!   around predict (carried on from them by the caller), when they predict one.
//!
//! The frame is marked where a followed part's core, shifted, shows what the keyframe
//! shows there: a flat body, a crown's leaves; not the wall in a generous mask, nor another
//! occluder the part joins at another depth. Past the keyframe's border a part goes on as
//! it crosses it (a car the keyframe cuts): there the frame is marked where it has the
//! part's colours rather than the building's around it. A part the frame does not show
//! clearly (behind another occluder, mostly out of the frame) is marked where the
//! prediction puts it, by the same rule.

use nalgebra::Point2;
use rayon::prelude::*;

use super::automask::{ColourHistogram, each_component};
use crate::geometry::Homography;
use crate::imaging::{Mask, Plane, Rect, Rgb8, RgbPixel, bilinear_rgb};

/// Parameters of [`follow_occluders`].
#[derive(Debug, Clone, PartialEq)]
pub struct FollowParams {
    /// The coarse search runs on the keyframe reduced to about this many pixels.
    pub work_pixels: usize,
    /// How far a part may have moved, as shares of the keyframe's width and height.
    pub reach: [f32; 2],
    /// RGB distance (Euclidean, 0..=√3) under which the frame's pixel agrees with the core.
    pub agree: f32,
    /// The share of the core's pixels in the frame that must agree at the shift found.
    pub min_agreement: f32,
    /// The share of the core the frame must show at that shift.
    pub min_seen: f32,
    /// How much more of the core must agree at the shift found than at the shifts of the
    /// range's upper decile.
    pub min_lead: f32,
    /// Parts whose core has fewer reduced pixels are not followed.
    pub min_part: usize,
    /// The rim (full pixels) taken off the mask for the core.
    pub rim: usize,
    /// A shift found further than `surprise[0]` pixels plus `surprise[1]` times the
    /// predicted shift's length from the predicted one is not taken.
    pub surprise: [f64; 2],
    /// A shift is taken only along the way the facade moves in the frame (at the part's
    /// centre), off it by at most `across[0]` pixels plus `across[1]` times its length along.
    pub across: [f64; 2],
    /// How much more of the core must agree at the shift found than at the best shift
    /// [`UNIQUE_APART`] reduced pixels or more from it (a flat, dark car matches every dark
    /// pane of a glass wall).
    pub min_unique: f32,
    /// A part whose shift is larger than itself is not followed where more than this share
    /// of it is still shown in place (the wall in a generous mask).
    pub max_still: f32,
}

/// How far (reduced pixels, along either axis) a second place the part is found at must lie
/// from the first to count as another place, at least (and half the part's size).
const UNIQUE_APART: isize = 6;

impl Default for FollowParams {
    fn default() -> Self {
        Self {
            work_pixels: 40_000,
            reach: [1.0, 0.25],
            agree: 0.1,
            min_agreement: 0.6,
            min_seen: 0.3,
            min_lead: 0.3,
            min_part: 150,
            rim: 3,
            surprise: [8.0, 0.2],
            across: [4.0, 0.5],
            min_unique: 0.15,
            max_still: 0.3,
        }
    }
}

/// What [`follow_occluders`] found in one frame.
#[derive(Debug, Clone)]
pub struct Followed {
    /// Frame-sized: 255 where the frame shows a followed part's core as the keyframe
    /// shows it, 0 elsewhere.
    pub marks: Mask,
    /// Per part of the mask (in the order of their first pixel, row by row), the shift
    /// (keyframe pixels) at which the frame shows it, when it was found (not predicted).
    pub shifts: Vec<Option<[f64; 2]>>,
}

/// Follows the parts of the keyframe's `mask` (keyframe `key`) into `frame`, whose map
/// from the keyframe is `h`, and marks (255) the frame's pixels where a shifted part's core
/// shows what the keyframe shows there. A part the frame does not show clearly enough to be
/// found (it is mostly out of the frame, or behind another occluder) is looked for where
/// `predicted` (per part, from the shifts found in the frames around) puts it, when it
/// gives a shift.
pub fn follow_occluders(
    key: &Rgb8,
    mask: &Mask,
    frame: &Rgb8,
    h: &Homography,
    predicted: &[Option<[f64; 2]>],
    params: &FollowParams,
) -> Followed {
    let (w, ht) = (key.width(), key.height());
    let (fw, fh) = (frame.width(), frame.height());
    let none = |n| Followed { marks: Mask::new(fw, fh, 0), shifts: vec![None; n] };
    if w == 0 || ht == 0 || (mask.width(), mask.height()) != (w, ht) {
        return none(0);
    }
    let inside = Plane::par_from_fn(w, ht, |x, y| mask.get(x, y) > 127);
    let core = erode(&inside, params.rim);
    let f = ((w * ht) as f64 / params.work_pixels.max(1) as f64).sqrt().ceil().max(1.0) as usize;
    let (rw, rh) = (w.div_ceil(f), ht.div_ceil(f));
    // Reduced: the keyframe's block means, the blocks wholly in the core, the parts.
    let key_r = block_mean(key, f);
    let core_r = Plane::par_from_fn(rw, rh, |x, y| block_all(&core, f, x, y));
    let any_r = Plane::par_from_fn(rw, rh, |x, y| block_any(&inside, f, x, y));
    let (labels, parts) = label(&any_r);
    let Some(to_key) = h.inverse() else { return none(parts) };
    // Per part, its blocks and its core's blocks (reduced), row by row.
    let (mut blocks, mut core_r_px) = (vec![Vec::new(); parts], vec![Vec::new(); parts]);
    for (x, y) in (0..rh).flat_map(|y| (0..rw).map(move |x| (x, y))).filter(|&(x, y)| any_r.get(x, y)) {
        let part = labels.get(x, y) as usize - 1;
        blocks[part].push((x, y));
        if core_r.get(x, y) {
            core_r_px[part].push((x, y));
        }
    }
    // The frame, reduced alike, taken to the keyframe's reduced coordinates over the range.
    let frame_r = block_mean(frame, f);
    let (ex, ey) =
        ((params.reach[0] * rw as f32).ceil() as isize, (params.reach[1] * rh as f32).ceil() as isize);
    let (cw, ch) = (rw + 2 * ex as usize, rh + 2 * ey as usize);
    let canvas: Plane<Option<[f32; 3]>> = Plane::par_from_fn(cw, ch, |cx, cy| {
        let kx = ((cx as isize - ex) as f64 + 0.5) * f as f64 - 0.5;
        let ky = ((cy as isize - ey) as f64 + 0.5) * f as f64 - 0.5;
        let q = h.apply(Point2::new(kx, ky))?;
        bilinear_rgb(&frame_r, ((q.x + 0.5) / f as f64 - 0.5) as f32, ((q.y + 0.5) / f as f64 - 0.5) as f32)
    });

    let shifts: Vec<Option<[f64; 2]>> = (0..parts)
        .into_par_iter()
        .map(|part| {
            // What moved: the core's pixels that the frame does not show in place. A part the
            // frame shows where the keyframe has it says nothing of a motion, and the wall a
            // generous brush took with the occluder stays in place.
            let moved = |x: usize, y: usize| match canvas.get(x + ex as usize, y + ey as usize) {
                Some(v) => dist(key_r.get(x, y), v) >= params.agree,
                None => true,
            };
            let whole = &core_r_px[part];
            let template: Vec<(usize, usize)> = whole.iter().copied().filter(|&(x, y)| moved(x, y)).collect();
            if template.len() < params.min_part {
                return None;
            }
            let coarse = coarse_shift(&key_r, &canvas, &template, (ex, ey), params)?;
            let d = refine(key, frame, &full_size(&core, &blocks[part], f), f, h, coarse, params);
            // Moved further than its own size, an occluder no longer covers any of the place
            // it had: what of the part the frame still shows in place is wall a generous
            // brush took (a rectangle around a car). Such a part is not followed: moved with
            // the car, a repeating wall looks like itself and would be marked.
            let span = Rect::around(whole);
            // (One the keyframe's border cuts may be longer than it shows.)
            let cut = span.x == 0 || span.y == 0 || span.x1() == rw || span.y1() == rh;
            let beyond = d[0].abs() > (span.width * f) as f64 || d[1].abs() > (span.height * f) as f64;
            if beyond && !cut {
                let seen =
                    whole.iter().filter(|&&(x, y)| canvas.get(x + ex as usize, y + ey as usize).is_some());
                let (n, still) =
                    seen.fold((0usize, 0usize), |(n, s), &(x, y)| (n + 1, s + usize::from(!moved(x, y))));
                if still as f32 > params.max_still * n as f32 {
                    return None;
                }
            }
            // Something standing in front of the facade moves across it the way the facade
            // moves in the frame, further: its parallax lies along the camera's path.
            let (sx, sy) =
                template.iter().fold((0.0, 0.0), |(sx, sy), &(x, y)| (sx + x as f64, sy + y as f64));
            let n = template.len() as f64;
            let centre = Point2::new((sx / n + 0.5) * f as f64 - 0.5, (sy / n + 0.5) * f as f64 - 0.5);
            let c = h.apply(centre).map(|q| [q.x - centre.x, q.y - centre.y])?;
            let along = (d[0] * c[0] + d[1] * c[1]) / c[0].hypot(c[1]).max(1e-9);
            let across = (d[0] * c[1] - d[1] * c[0]).abs() / c[0].hypot(c[1]).max(1e-9);
            if along <= 0.0 || across > params.across[0] + params.across[1] * along {
                return None;
            }
            // A shift far from where the frames around put the part is a look-alike found
            // elsewhere (a dark window for a dark car): the prediction stands.
            match predicted.get(part).copied().flatten() {
                Some(p)
                    if (d[0] - p[0]).hypot(d[1] - p[1])
                        > params.surprise[0] + params.surprise[1] * p[0].hypot(p[1]) =>
                {
                    None
                }
                _ => Some(d),
            }
        })
        .collect();
    let used: Vec<Option<[f64; 2]>> =
        shifts.iter().enumerate().map(|(i, d)| d.or_else(|| predicted.get(i).copied().flatten())).collect();
    if used.iter().all(Option::is_none) {
        return none(parts);
    }

    // Per followed part, its colours and the building's around it (reduced pixels).
    let colours: Vec<Option<(ColourHistogram, ColourHistogram)>> = used
        .iter()
        .enumerate()
        .map(|(part, d)| {
            d.as_ref()?;
            let label = part as u32 + 1;
            let of_part = |x: usize, y: usize| labels.get(x, y) == label;
            let span = Rect::around(&blocks[part]);
            let (x0, y0, x1, y1) = (span.x, span.y, span.x1(), span.y1());
            let m = span.width.max(span.height);
            let (bx0, by0, bx1, by1) =
                (x0.saturating_sub(m), y0.saturating_sub(m), (x1 + m).min(rw), (y1 + m).min(rh));
            let within = |take: &dyn Fn(usize, usize) -> bool| {
                ColourHistogram::of_colours(
                    LEVELS,
                    (by0..by1)
                        .flat_map(|y| (bx0..bx1).map(move |x| (x, y)))
                        .filter(|&(x, y)| take(x, y))
                        .map(|(x, y)| key_r.get(x, y)),
                )
            };
            Some((within(&|x, y| of_part(x, y) && core_r.get(x, y)), within(&|x, y| !any_r.get(x, y))))
        })
        .collect();
    let mark_at = |x: usize, y: usize| -> u8 {
        let Some(p) = to_key.apply(Point2::new(x as f64, y as f64)) else { return 0 };
        let mut mark = 0;
        for (part, d) in used.iter().enumerate() {
            let Some(d) = d else { continue };
            let (sx, sy) = ((p.x - d[0]).round(), (p.y - d[1]).round());
            let past = sx < 0.0 || sy < 0.0 || sx >= w as f64 || sy >= ht as f64;
            let (sx, sy) = (sx.clamp(0.0, (w - 1) as f64) as usize, sy.clamp(0.0, (ht - 1) as f64) as usize);
            if !inside.get(sx, sy) || labels.get(sx / f, sy / f) != part as u32 + 1 {
                continue;
            }
            // Past the keyframe's border, the part may go on as it crosses it: what the
            // frame shows there, moved in by the shift, is the rest of a car the keyframe
            // cut, where it has the part's colours rather than the building's.
            if past
                && let Some((own, building)) = &colours[part]
                && let c = frame.get(x, y).to_f32()
                && !own.typical(c, building, TYPICAL)
            {
                continue;
            }
            // The core is marked where the frame shows what the keyframe showed there (a
            // flat body, a crown's leaves; not the wall a generous brush took, moved along
            // with the occluder, nor another occluder the part joins, at another depth);
            // past the border, where it has the part's colours.
            let like = past || dist(key.get(sx, sy).to_f32(), frame.get(x, y).to_f32()) < 2.0 * params.agree;
            if core.get(sx, sy) && like {
                mark = 255;
            }
        }
        mark
    };
    let rows: Vec<u8> =
        (0..fh).into_par_iter().flat_map_iter(|y| (0..fw).map(move |x| mark_at(x, y))).collect();
    Followed { marks: Mask::from_vec(fw, fh, rows), shifts }
}

/// A shift's score: the share of the core that agrees there, and the share the frame shows
/// there when the agreement is clear enough to take (`None` otherwise).
type Score = (f32, Option<f32>);

/// The reduced shift (in reduced pixels) at which the `template` pixels of `key_r` agree
/// best with `canvas` (the frame on the keyframe's reduced grid, extended by `ext` on each
/// side), when that agreement is clear (see the module docs).
fn coarse_shift(
    key_r: &Plane<[f32; 3]>,
    canvas: &Plane<Option<[f32; 3]>>,
    template: &[(usize, usize)],
    ext: (isize, isize),
    params: &FollowParams,
) -> Option<[isize; 2]> {
    // At most this many template pixels are compared per shift (evenly spread).
    const SAMPLES: usize = 600;
    let stride = template.len().div_ceil(SAMPLES).max(1);
    let samples: Vec<(usize, usize)> = template.iter().step_by(stride).copied().collect();
    let n = samples.len();
    // Half the part's size, and at least UNIQUE_APART: nearer, the same match is only off.
    let span = Rect::around(template);
    let far = (((span.width.max(span.height) - 1) / 2) as isize).max(UNIQUE_APART);
    // Shifts are ranked by the share of the whole core that agrees (where only a flat part
    // of it is in the frame, a share of what is seen would be high anywhere); a shift that
    // shows too little of it, or where too little of what it shows agrees, is not taken.
    let score = |dx: isize, dy: isize| -> Option<Score> {
        let (mut seen, mut agree) = (0usize, 0usize);
        for &(x, y) in &samples {
            let (cx, cy) = (x as isize + dx + ext.0, y as isize + dy + ext.1);
            let Some(Some(v)) = canvas.get_checked(cx, cy) else { continue };
            seen += 1;
            agree += usize::from(dist(key_r.get(x, y), v) < params.agree);
        }
        let clear =
            seen as f32 >= params.min_seen * n as f32 && agree as f32 >= params.min_agreement * seen as f32;
        Some((agree as f32 / n as f32, clear.then_some(seen as f32 / n as f32))).filter(|_| seen > 0)
    };
    // Every other shift first, then around the best of those.
    let mut all = Vec::new();
    let mut best: Option<(Score, [isize; 2])> = None;
    for dy in (-ext.1..=ext.1).step_by(2) {
        for dx in (-ext.0..=ext.0).step_by(2) {
            if let Some(s) = score(dx, dy) {
                all.push((s.0, [dx, dy]));
                if best.is_none_or(|(b, _)| s.0 > b.0) {
                    best = Some((s, [dx, dy]));
                }
            }
        }
    }
    let mut best = best?;
    let [bx, by] = best.1;
    for dy in by - 1..=by + 1 {
        for dx in bx - 1..=bx + 1 {
            if let Some(s) = score(dx, dy)
                && s.0 > best.0.0
            {
                best = (s, [dx, dy]);
            }
        }
    }
    // The best shift away from this one: a second place the part looks as it does here.
    let ((share, seen), shift) = best;
    let apart = |d: &[isize; 2]| (d[0] - shift[0]).abs().max((d[1] - shift[1]).abs()) > far;
    let second = all.iter().filter(|(_, d)| apart(d)).map(|&(s, _)| s).fold(0.0f32, f32::max);
    let mut shares: Vec<f32> = all.iter().map(|&(s, _)| s).collect();
    shares.sort_unstable_by(f32::total_cmp);
    let decile = shares[(shares.len() * 9 / 10).min(shares.len() - 1)];
    // The lead is asked of the part of the core the frame shows.
    seen.filter(|&seen| {
        share - decile >= params.min_lead * seen && share - second >= params.min_unique * seen
    })
    .map(|_| shift)
}

/// The full-size shift of a part whose core is `core` (full-size pixels) around the coarse
/// one (reduced by `f`): the one, within a reduced pixel of it, at which most of the core
/// that moved agrees with the frame.
fn refine(
    key: &Rgb8,
    frame: &Rgb8,
    core: &[(usize, usize)],
    f: usize,
    h: &Homography,
    coarse: [isize; 2],
    params: &FollowParams,
) -> [f64; 2] {
    const SAMPLES: usize = 4000;
    let shown = |x: usize, y: usize| {
        let q = h.apply(Point2::new(x as f64, y as f64))?;
        bilinear_rgb(frame, q.x as f32, q.y as f32)
    };
    let moved =
        |x: usize, y: usize| shown(x, y).is_none_or(|v| dist(key.get(x, y).to_f32(), v) >= params.agree);
    let pixels: Vec<(usize, usize)> = core.iter().copied().filter(|&(x, y)| moved(x, y)).collect();
    let stride = pixels.len().div_ceil(SAMPLES).max(1);
    let samples: Vec<(usize, usize)> = pixels.into_iter().step_by(stride).collect();
    let centre = [(coarse[0] * f as isize) as f64, (coarse[1] * f as isize) as f64];
    let reach = f as isize;
    let mut best = (f32::MIN, centre);
    for dy in -reach..=reach {
        for dx in -reach..=reach {
            let d = [centre[0] + dx as f64, centre[1] + dy as f64];
            let (mut seen, mut agree) = (0usize, 0usize);
            for &(x, y) in &samples {
                let Some(q) = h.apply(Point2::new(x as f64 + d[0], y as f64 + d[1])) else { continue };
                let Some(v) = bilinear_rgb(frame, q.x as f32, q.y as f32) else { continue };
                seen += 1;
                agree += usize::from(dist(key.get(x, y).to_f32(), v) < params.agree);
            }
            let s = if seen == 0 { 0.0 } else { agree as f32 / seen as f32 };
            if s > best.0 {
                best = (s, d);
            }
        }
    }
    best.1
}

/// The levels per channel a part's colours are told from the building's at.
const LEVELS: usize = 8;

/// The share of a part's colours that must fall in a colour's bin for it to be the part's.
const TYPICAL: f32 = 0.01;

#[inline]
fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Block means of `img` over `f × f` blocks (the last row and column of blocks partial).
fn block_mean(img: &Rgb8, f: usize) -> Plane<[f32; 3]> {
    let (w, h) = (img.width(), img.height());
    Plane::par_from_fn(w.div_ceil(f), h.div_ceil(f), |bx, by| {
        let (mut s, mut n) = ([0.0f32; 3], 0.0f32);
        for y in by * f..((by + 1) * f).min(h) {
            for x in bx * f..((bx + 1) * f).min(w) {
                let p = img.get(x, y).to_f32();
                (0..3).for_each(|c| s[c] += p[c]);
                n += 1.0;
            }
        }
        s.map(|v| v / n)
    })
}

/// The pixels of `m` (full size) within `blocks` (`f × f`, row by row), row by row.
fn full_size(m: &Plane<bool>, blocks: &[(usize, usize)], f: usize) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    for row in blocks.chunk_by(|a, b| a.1 == b.1) {
        let by = row[0].1;
        for y in by * f..((by + 1) * f).min(m.height()) {
            for &(bx, _) in row {
                out.extend((bx * f..((bx + 1) * f).min(m.width())).filter(|&x| m.get(x, y)).map(|x| (x, y)));
            }
        }
    }
    out
}

fn block_all(m: &Plane<bool>, f: usize, bx: usize, by: usize) -> bool {
    (by * f..((by + 1) * f).min(m.height()))
        .all(|y| (bx * f..((bx + 1) * f).min(m.width())).all(|x| m.get(x, y)))
}

fn block_any(m: &Plane<bool>, f: usize, bx: usize, by: usize) -> bool {
    (by * f..((by + 1) * f).min(m.height()))
        .any(|y| (bx * f..((bx + 1) * f).min(m.width())).any(|x| m.get(x, y)))
}

/// `m` eroded by a `(2r + 1)²` square.
fn erode(m: &Plane<bool>, r: usize) -> Plane<bool> {
    super::automask::erode(m, r)
}

/// 8-connected components of `m`: labels from 1 in the order of their first pixel (row by
/// row), 0 off `m`; and their count.
fn label(m: &Plane<bool>) -> (Plane<u32>, usize) {
    let mut labels = Plane::new(m.width(), m.height(), 0u32);
    let mut count = 0;
    each_component(m, |members| {
        count += 1;
        members.iter().for_each(|&(x, y)| labels.set(x, y, count));
    });
    (labels, count as usize)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::{Rect, RgbF32};
    use crate::synth::{facade, render_view};

    fn to_rgb8(img: &RgbF32) -> Rgb8 {
        img.map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
    }

    const W: usize = 320;
    const H: usize = 240;

    /// A car with a flat body (a box of one colour: its inside looks the same displaced) and
    /// a dark cabin, its lower body `half` pixels either side of `cx`, painted into `img`
    /// and marked in `cover`.
    fn car(img: &mut RgbF32, cover: &mut Mask, cx: f64, cy: f64, half: f64) {
        for y in 0..img.height() {
            for x in 0..img.width() {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let colour = if dx.abs() < half && (0.0..40.0).contains(&dy) {
                    Some([0.42, 0.45, 0.47])
                } else if dx.abs() < half * 0.6 && (-30.0..0.0).contains(&dy) {
                    Some([0.12, 0.11, 0.1])
                } else {
                    None
                };
                if let Some(c) = colour {
                    img.set(x, y, c);
                    cover.set(x, y, 255);
                }
            }
        }
    }

    /// The keyframe and a frame of a walk along `wall`, the camera `pan` pixels further; the
    /// car at `cx` in the keyframe, moved `moved` against the wall in the frame. Returns the
    /// keyframe, its mask (the car grown by 4 px, as a brush paints), the frame, the car's
    /// cover in the frame and the keyframe → frame map.
    fn walk(
        wall: &RgbF32,
        pan: f64,
        cx: f64,
        half: f64,
        moved: [f64; 2],
    ) -> (Rgb8, Mask, Rgb8, Mask, Homography) {
        let mut key = render_view(wall, &Homography::translation(100.0, 40.0), W, H, [0.0; 3]);
        let mut key_cover = Mask::new(W, H, 0);
        car(&mut key, &mut key_cover, cx, 150.0, half);
        let mut frame = render_view(wall, &Homography::translation(100.0 + pan, 40.0), W, H, [0.0; 3]);
        let mut cover = Mask::new(W, H, 0);
        car(&mut frame, &mut cover, cx + moved[0] - pan, 150.0 + moved[1], half);
        let grown =
            super::super::automask::dilate(&key_cover.map(|&v| v > 127), 4).map(|&b| if b { 255 } else { 0 });
        (to_rgb8(&key), grown, to_rgb8(&frame), cover, Homography::translation(-pan, 0.0))
    }

    fn count(m: &Mask, f: impl Fn(usize, usize, u8) -> bool) -> usize {
        (0..m.height())
            .flat_map(|y| (0..m.width()).map(move |x| (x, y)))
            .filter(|&(x, y)| f(x, y, m.get(x, y)))
            .count()
    }

    #[test]
    fn a_flat_car_is_followed_by_where_its_outline_moved() {
        let wall = facade(800, 400, 3);
        let (key, mask, frame, cover, h) = walk(&wall, 20.0, 170.0, 70.0, [-44.0, 3.0]);
        let (car, astray) = followed_by_its_shift(&key, &mask, &frame, &cover, &h, [-44.0, 3.0]);
        // Its flat body is marked whole, and little beyond a brush's margin of it.
        assert!(astray * 50 < car, "{astray} pixels marked away from the car");
    }

    /// Follows the car in `frame`, checks it is found at `shift` (within a pixel) and marked
    /// whole; returns the car's pixel count and the marks more than 6 px away from it.
    fn followed_by_its_shift(
        key: &Rgb8,
        mask: &Mask,
        frame: &Rgb8,
        cover: &Mask,
        h: &Homography,
        shift: [f64; 2],
    ) -> (usize, usize) {
        let found = follow_occluders(key, mask, frame, h, &[], &FollowParams::default());
        let d = found.shifts[0].expect("the car is followed");
        assert!((d[0] - shift[0]).abs() <= 1.0 && (d[1] - shift[1]).abs() <= 1.0, "shift {d:?}");
        let car = count(cover, |_, _, c| c > 127);
        let missed = count(cover, |x, y, c| c > 127 && found.marks.get(x, y) < 255);
        assert!(missed * 50 < car, "{missed} of the car's {car} pixels not marked");
        let near = super::super::automask::dilate(&cover.map(|&v| v > 127), 6);
        (car, count(&found.marks, |x, y, m| m > 0 && !near.get(x, y)))
    }

    #[test]
    fn past_the_keyframes_border_a_cut_car_goes_on_only_where_the_frame_shows_it() {
        let wall = facade(800, 400, 5);
        // The car reaches 30 px past the keyframe's left border; the camera has walked 60 px
        // left and the car moved 120 px right against the wall: in keyframe coordinates the
        // frame shows its cut part at 90..120 and the wall at 0..90.
        let (key, mask, frame, cover, h) = walk(&wall, -60.0, 40.0, 70.0, [120.0, 0.0]);
        let found = follow_occluders(&key, &mask, &frame, &h, &[], &FollowParams::default());
        let d = found.shifts[0].expect("the cut car is followed");
        assert!((d[0] - 120.0).abs() <= 2.0 && d[1].abs() <= 1.0, "shift {d:?}");
        // In the frame the keyframe's x = 0..120 is frame x = 60..180.
        let cut = Rect::from_corners(60, 150, 178, 190);
        let shown = count(&cover, |x, y, c| cut.contains(x, y) && c > 127);
        let marked = count(&cover, |x, y, c| cut.contains(x, y) && c > 127 && found.marks.get(x, y) > 127);
        assert!(
            shown > 800 && marked * 10 >= shown * 9,
            "{marked} of the {shown} pixels of the cut part marked"
        );
        let wall_px = count(&cover, |x, y, c| cut.contains(x, y) && x < 140 && c == 0);
        let wall_marked =
            count(&cover, |x, y, c| cut.contains(x, y) && x < 140 && c == 0 && found.marks.get(x, y) > 127);
        assert!(wall_px > 200 && wall_marked * 10 < wall_px, "{wall_marked} of {wall_px} wall pixels marked");
    }

    #[test]
    fn what_matches_anywhere_is_not_followed() {
        // A mask over plain wall: every shift shows the same, none is the part's.
        let plain = RgbF32::new(800, 400, [0.6, 0.55, 0.5]);
        let key = to_rgb8(&render_view(&plain, &Homography::translation(100.0, 40.0), W, H, [0.0; 3]));
        let frame = to_rgb8(&render_view(&plain, &Homography::translation(120.0, 40.0), W, H, [0.0; 3]));
        let mask = Mask::from_fn(W, H, |x, y| {
            if (x as i64 - 160).pow(2) + (y as i64 - 120).pow(2) < 1600 { 255 } else { 0 }
        });
        let found = follow_occluders(
            &key,
            &mask,
            &frame,
            &Homography::translation(-20.0, 0.0),
            &[],
            &FollowParams::default(),
        );
        assert_eq!(found.shifts, vec![None]);
        assert!(found.marks.as_slice().iter().all(|&m| m == 0));
    }

    #[test]
    fn a_part_the_frame_hides_is_marked_where_it_is_predicted() {
        let wall = facade(800, 400, 7);
        let (key, mask, _, _, h) = walk(&wall, 20.0, 170.0, 70.0, [-44.0, 3.0]);
        // The frame without the car (something hid it): nothing to find, the prediction marks.
        let frame = to_rgb8(&render_view(&wall, &Homography::translation(120.0, 40.0), W, H, [0.0; 3]));
        let found =
            follow_occluders(&key, &mask, &frame, &h, &[Some([-44.0, 3.0])], &FollowParams::default());
        assert_eq!(found.shifts, vec![None]);
        // The keyframe's car centre (170, 170) moved by (-44, 3), in the frame (20 px on).
        assert_eq!(found.marks.get(106, 173), 255);
        assert_eq!(found.marks.get(300, 60), 0);
        let none = follow_occluders(&key, &mask, &frame, &h, &[], &FollowParams::default());
        assert!(none.marks.as_slice().iter().all(|&m| m == 0));
    }

    #[test]
    fn a_rectangle_brushed_around_a_car_is_not_followed_as_if_it_were_the_car() {
        let wall = facade(800, 400, 11);
        // The car moved further than the rectangle is wide: the frame shows the rectangle's
        // wall where it was, and that wall, moved with the car, looks like wall elsewhere.
        let (key, tight, frame, _, h) = walk(&wall, 30.0, 230.0, 30.0, [-150.0, 2.0]);
        let (mut x0, mut y0, mut x1, mut y1) = (W, H, 0, 0);
        for y in 0..H {
            for x in (0..W).filter(|&x| tight.get(x, y) > 127) {
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
            }
        }
        let rect = Rect::from_corners(x0 - 30, y0 - 30, x1 + 30, y1 + 30);
        let mask = Mask::from_fn(W, H, |x, y| if rect.contains(x, y) { 255 } else { 0 });
        let found = follow_occluders(&key, &mask, &frame, &h, &[], &FollowParams::default());
        assert_eq!(found.shifts, vec![None]);
        assert!(found.marks.as_slice().iter().all(|&m| m == 0));
        // With the mask the car's own outline, it is.
        let found = follow_occluders(&key, &tight, &frame, &h, &[], &FollowParams::default());
        assert!(found.shifts[0].is_some_and(|d| (d[0] + 150.0).abs() <= 2.0), "{:?}", found.shifts);
    }

    #[test]
    fn a_generous_brush_marks_the_car_not_the_wall_it_took() {
        let wall = facade(800, 400, 17);
        let (key, tight, frame, cover, h) = walk(&wall, 20.0, 170.0, 70.0, [-44.0, 3.0]);
        // Painted 16 px wider than the car: the core holds a band of wall around it, which
        // moves with the car's shift onto other wall in the frame.
        let mask =
            super::super::automask::dilate(&tight.map(|&v| v > 127), 12).map(|&b| if b { 255 } else { 0 });
        let (car, astray) = followed_by_its_shift(&key, &mask, &frame, &cover, &h, [-44.0, 3.0]);
        // The band's wall is marked only where the frame's wall happens to look like it.
        assert!(astray * 5 < car, "{astray} pixels marked away from the car (the car: {car})");
    }

    #[test]
    fn a_look_alike_against_the_camera_s_way_is_not_followed() {
        let wall = facade(800, 400, 13);
        // The camera walked right (the wall moves left in the frame). A car moved left
        // against the wall is followed; one moved right, or up across the camera's path,
        // clearly found as it is, is not: nothing standing in front of the wall moves so.
        let (key, mask, frame, _, h) = walk(&wall, 20.0, 170.0, 30.0, [-44.0, 0.0]);
        let found = follow_occluders(&key, &mask, &frame, &h, &[], &FollowParams::default());
        assert!(found.shifts[0].is_some_and(|d| (d[0] + 44.0).abs() <= 1.0), "{:?}", found.shifts);
        for moved in [[44.0, 0.0], [70.0, 0.0], [0.0, 40.0], [-10.0, 40.0]] {
            let (key, mask, frame, _, h) = walk(&wall, 20.0, 170.0, 30.0, moved);
            let found = follow_occluders(&key, &mask, &frame, &h, &[], &FollowParams::default());
            assert_eq!(found.shifts, vec![None], "moved {moved:?}");
            assert!(found.marks.as_slice().iter().all(|&m| m == 0), "moved {moved:?}");
        }
        // Where the frames around put it, a shift found far away is not taken either.
        let (key, mask, frame, _, h) = walk(&wall, 20.0, 170.0, 70.0, [-44.0, 0.0]);
        let found =
            follow_occluders(&key, &mask, &frame, &h, &[Some([-100.0, 0.0])], &FollowParams::default());
        assert_eq!(found.shifts, vec![None]);
        let found =
            follow_occluders(&key, &mask, &frame, &h, &[Some([-46.0, 0.0])], &FollowParams::default());
        assert!(found.shifts[0].is_some());
    }
}
