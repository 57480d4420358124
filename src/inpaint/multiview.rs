//! The multi-view fill of one region: Criminisi's fill front, with candidate patches taken
//! from the warped views near the homography's prediction, chosen by SSD on the patch's
//! known part and by agreement with the other views (pure layer).
//!
//! Everything here works in a region's own coordinates (a rectangle of the keyframe around
//! one connected part of the hole); [`super::fill`] cuts the regions, warps and compensates
//! the views, and blends afterwards.

use rayon::prelude::*;

use super::priority::{FrontQueue, confidence_term, data_term};
use crate::imaging::convert::luma;

/// Pixel states of a region.
/// A keyframe pixel outside the hole: known, never changed.
pub const KNOWN: u8 = 0;
/// A pixel to fill.
pub const HOLE: u8 = 1;
/// A hole pixel filled from a view: known from now on.
pub const FILLED: u8 = 2;
/// A hole pixel no view covers: left for the single-image fallback.
pub const UNSEEN: u8 = 3;
/// Not this region's business (another region's hole): never read, never written.
pub const BLOCKED: u8 = 4;

/// Where a filled pixel came from: view `view`, shifted by `(dx, dy)` from the
/// homography's prediction. `view == NO_VIEW` for pixels not filled from a view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pick {
    pub view: u16,
    pub dx: i8,
    pub dy: i8,
}

/// [`Pick::view`] of a pixel no view filled.
pub const NO_VIEW: u16 = u16::MAX;

impl Pick {
    pub const NONE: Self = Self { view: NO_VIEW, dx: 0, dy: 0 };
}

/// Parameters of [`fill_region`].
#[derive(Debug, Clone, PartialEq)]
pub struct MultiviewParams {
    /// Patches are `(2·r + 1)²` pixels (the paper's window): the SSD is taken on these.
    pub patch_radius: usize,
    /// The chosen candidate's hole pixels are copied within this radius (at least
    /// `patch_radius`). The views are registered, so the patch only decides *which* view
    /// (and shift) to take; copying a larger block from it costs nothing in accuracy and
    /// divides the number of front steps.
    pub copy_radius: usize,
    /// Candidates are searched up to this many pixels around the homography's prediction
    /// (absorbs small misregistration and parallax); 0 takes the prediction as is.
    pub search_radius: usize,
    /// Only the this many best views (at the prediction) get the local search.
    pub search_views: usize,
    /// Weight of a candidate's disagreement with the views' consensus (0 switches the
    /// occlusion reasoning off). In squared RGB units per pixel, as the SSD.
    pub occlusion_weight: f32,
    /// Cost per pixel² of shift away from the prediction (keeps neighbours coherent).
    pub shift_penalty: f32,
    /// A shifted candidate must cost less than this share of the same view unshifted: a
    /// shift is taken for a clear gain, not to chase noise and aliasing.
    pub search_gain: f32,
    /// Squared error charged for a known target pixel the candidate view does not cover.
    pub miss_penalty: f32,
}

impl Default for MultiviewParams {
    fn default() -> Self {
        Self {
            patch_radius: 4,
            copy_radius: 4,
            search_radius: 2,
            search_views: 2,
            occlusion_weight: 1.0,
            shift_penalty: 2e-4,
            search_gain: 0.7,
            miss_penalty: 0.05,
        }
    }
}

/// One warped, compensated view over a region: `image`, `valid` and `occlusion` (its
/// disagreement with the consensus, see [`occlusion_costs`]) are region-sized.
#[derive(Debug, Clone, Copy)]
pub struct ViewData<'a> {
    pub image: &'a [[f32; 3]],
    pub valid: &'a [bool],
    pub occlusion: &'a [f32],
    /// What every candidate of this view costs besides its SSD: the error the view is
    /// expected to make beyond the best view's (squared RGB per pixel, as the SSD), from how
    /// well it reproduces the keyframe around the hole (blur of a magnifying warp,
    /// misregistration). 0 for the best view.
    pub expected_error: f32,
}

/// A region being filled: `pixels` (hole pixels are overwritten), `state` (one of the
/// constants above) and `pick` (where each filled pixel came from), all `width × height`.
#[derive(Debug)]
pub struct Region<'a> {
    pub width: usize,
    pub height: usize,
    pub pixels: &'a mut [[f32; 3]],
    pub state: &'a mut [u8],
    pub pick: &'a mut [Pick],
}

#[inline]
fn sq(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

/// Per view and pixel, how far the view's colour is from the per-channel median of all
/// views that cover the pixel (squared RGB distance, truncated at `truncate`); zero where
/// fewer than two views cover it or `need` is false. A view that sees its own tree where
/// the others see the wall stands out here.
pub fn occlusion_costs(
    views: &[(&[[f32; 3]], &[bool])],
    need: &[bool],
    width: usize,
    truncate: f32,
) -> Vec<Vec<f32>> {
    let nv = views.len();
    let n = need.len();
    let mut inter = vec![0.0f32; n * nv];
    if nv >= 2 && width > 0 {
        inter.par_chunks_mut(width * nv).enumerate().for_each(|(y, row)| {
            let mut vals = [[0.0f32; 3]; 32];
            let mut chan = [0.0f32; 32];
            for x in 0..width {
                let i = y * width + x;
                if !need[i] {
                    continue;
                }
                let mut c = 0;
                for (img, valid) in views.iter().take(32) {
                    if valid[i] {
                        vals[c] = img[i];
                        c += 1;
                    }
                }
                if c < 2 {
                    continue;
                }
                let mut med = [0.0f32; 3];
                for (k, m) in med.iter_mut().enumerate() {
                    for j in 0..c {
                        chan[j] = vals[j][k];
                    }
                    let s = &mut chan[..c];
                    s.sort_unstable_by(f32::total_cmp);
                    *m = 0.5 * (s[(c - 1) / 2] + s[c / 2]);
                }
                for (v, (img, valid)) in views.iter().enumerate() {
                    if valid[i] {
                        row[x * nv + v] = sq(img[i], med).min(truncate);
                    }
                }
            }
        });
    }
    (0..nv).map(|v| (0..n).map(|i| inter[i * nv + v]).collect()).collect()
}

/// Fills the region's `HOLE` pixels from `views` in priority order; returns how many were
/// filled. Pixels no view covers become `UNSEEN`. Deterministic.
pub fn fill_region(region: &mut Region<'_>, views: &[ViewData<'_>], params: &MultiviewParams) -> usize {
    let (w, h) = (region.width, region.height);
    let n = w * h;
    assert!(region.pixels.len() == n && region.state.len() == n && region.pick.len() == n);
    // No view sees any of the hole (a keyframe and its mask alone): nothing to search, and
    // the front would walk the whole hole for nothing (seconds on a large one).
    if !(0..n).any(|i| region.state[i] == HOLE && views.iter().any(|v| v.valid[i])) {
        region.state.iter_mut().filter(|s| **s == HOLE).for_each(|s| *s = UNSEEN);
        return 0;
    }
    let r = params.patch_radius;
    let rc = params.copy_radius.max(r);
    let mut known: Vec<bool> = region.state.iter().map(|&s| s == KNOWN || s == FILLED).collect();
    let mut conf: Vec<f32> = known.iter().map(|&k| if k { 1.0 } else { 0.0 }).collect();
    let mut gray: Vec<f32> = region.pixels.iter().map(|&p| luma(p)).collect();
    let mut queue = FrontQueue::new(n);

    let on_front = |known: &[bool], i: usize| -> bool {
        let (x, y) = (i % w, i / w);
        (x > 0 && known[i - 1])
            || (x + 1 < w && known[i + 1])
            || (y > 0 && known[i - w])
            || (y + 1 < h && known[i + w])
    };
    for i in 0..n {
        if region.state[i] == HOLE && on_front(&known, i) {
            let (x, y) = (i % w, i / w);
            queue.push(
                i,
                confidence_term(&conf, &known, w, h, x, y, r) * data_term(&gray, &known, w, h, x, y),
            );
        }
    }

    let mut offsets: Vec<(isize, isize)> = Vec::new();
    let s = params.search_radius as isize;
    for dy in -s..=s {
        for dx in -s..=s {
            if (dx, dy) != (0, 0) {
                offsets.push((dx, dy));
            }
        }
    }
    let mut known_list: Vec<(usize, [f32; 3])> = Vec::with_capacity((2 * r + 1).pow(2));
    let mut hole_list: Vec<usize> = Vec::with_capacity((2 * rc + 1).pow(2));
    let mut ranked: Vec<(f32, usize)> = Vec::with_capacity(views.len());
    let mut filled = 0usize;

    loop {
        let Some(i) = queue.pop() else {
            if !reseed(region.state, w, h, &mut queue) {
                break;
            }
            continue;
        };
        if region.state[i] != HOLE {
            continue;
        }
        let (x, y) = (i % w, i / w);
        let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
        known_list.clear();
        hole_list.clear();
        let mut conf_sum = 0.0;
        for yy in y0..y1 {
            for xx in x0..x1 {
                let j = yy * w + xx;
                if known[j] {
                    known_list.push((j, region.pixels[j]));
                    conf_sum += conf[j];
                }
            }
        }
        let c_p = conf_sum / ((x1 - x0) * (y1 - y0)) as f32;
        let (x0, x1) = (x.saturating_sub(rc), (x + rc + 1).min(w));
        let (y0, y1) = (y.saturating_sub(rc), (y + rc + 1).min(h));
        for yy in y0..y1 {
            for xx in x0..x1 {
                let j = yy * w + xx;
                if region.state[j] == HOLE {
                    hole_list.push(j);
                }
            }
        }
        let inv_known = if known_list.is_empty() { 0.0 } else { 1.0 / known_list.len() as f32 };
        let inv_hole = 1.0 / hole_list.len() as f32;
        let bounds = (x0 as isize, x1 as isize, y0 as isize, y1 as isize);

        // Cost of view `v` shifted by (dx, dy), or infinity when it cannot beat `bound`.
        let eval = |v: &ViewData<'_>, dx: isize, dy: isize, bound: f32| -> f32 {
            let (bx0, bx1, by0, by1) = bounds;
            if bx0 + dx < 0 || by0 + dy < 0 || bx1 + dx > w as isize || by1 + dy > h as isize {
                return f32::INFINITY;
            }
            let off = dy * w as isize + dx;
            let at = |j: usize| (j as isize + off) as usize;
            if !v.valid[at(i)] {
                return f32::INFINITY;
            }
            let mut cost = params.shift_penalty * (dx * dx + dy * dy) as f32 + v.expected_error;
            if params.occlusion_weight > 0.0 {
                let occ: f32 =
                    hole_list.iter().map(|&j| if v.valid[at(j)] { v.occlusion[at(j)] } else { 0.0 }).sum();
                cost += params.occlusion_weight * occ * inv_hole;
            }
            if cost >= bound {
                return f32::INFINITY;
            }
            let mut ssd = 0.0;
            for (k, &(j, t)) in known_list.iter().enumerate() {
                let a = at(j);
                ssd += if v.valid[a] { sq(v.image[a], t) } else { params.miss_penalty };
                if k % 16 == 15 && cost + ssd * inv_known >= bound {
                    return f32::INFINITY;
                }
            }
            cost + ssd * inv_known
        };

        // At the prediction for every view; the local search for the best few.
        ranked.clear();
        let mut best = (f32::INFINITY, usize::MAX, 0isize, 0isize);
        for (vi, v) in views.iter().enumerate() {
            let c = eval(v, 0, 0, f32::INFINITY);
            if c.is_finite() {
                ranked.push((c, vi));
                if c < best.0 {
                    best = (c, vi, 0, 0);
                }
            }
        }
        if !offsets.is_empty() && params.search_views > 0 {
            ranked.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            for &(c0, vi) in ranked.iter().take(params.search_views) {
                for &(dx, dy) in &offsets {
                    let bound = best.0.min(params.search_gain * c0);
                    let c = eval(&views[vi], dx, dy, bound);
                    if c < bound {
                        best = (c, vi, dx, dy);
                    }
                }
            }
        }
        if best.1 == usize::MAX {
            region.state[i] = UNSEEN;
            continue;
        }
        let (_, vi, dx, dy) = best;
        let v = &views[vi];
        let off = dy * w as isize + dx;
        let pick = Pick { view: vi as u16, dx: dx as i8, dy: dy as i8 };
        for &j in &hole_list {
            let a = (j as isize + off) as usize;
            if v.valid[a] {
                region.pixels[j] = v.image[a];
                region.state[j] = FILLED;
                region.pick[j] = pick;
                known[j] = true;
                conf[j] = c_p;
                gray[j] = luma(v.image[a]);
                filled += 1;
            }
        }
        // The front moved: new front pixels and changed neighbours get fresh priorities.
        let (ux0, ux1) = (x0.saturating_sub(1), (x1 + 1).min(w));
        let (uy0, uy1) = (y0.saturating_sub(1), (y1 + 1).min(h));
        for yy in uy0..uy1 {
            for xx in ux0..ux1 {
                let j = yy * w + xx;
                if region.state[j] == HOLE && on_front(&known, j) {
                    let p = confidence_term(&conf, &known, w, h, xx, yy, r)
                        * data_term(&gray, &known, w, h, xx, yy);
                    queue.push(j, p);
                }
            }
        }
    }
    filled
}

/// When the front has run dry but hole pixels remain (cut off from the known pixels by
/// unseen ones), restarts from the hole pixels that touch anything else; `false` when the
/// hole is done.
fn reseed(state: &[u8], w: usize, h: usize, queue: &mut FrontQueue) -> bool {
    let mut any = false;
    let mut first = None;
    for i in 0..state.len() {
        if state[i] != HOLE {
            continue;
        }
        first.get_or_insert(i);
        let (x, y) = (i % w, i / w);
        let touches = x == 0
            || y == 0
            || x + 1 == w
            || y + 1 == h
            || state[i - 1] != HOLE
            || state[i + 1] != HOLE
            || state[i - w] != HOLE
            || state[i + w] != HOLE;
        if touches {
            queue.push(i, 0.0);
            any = true;
        }
    }
    if !any && let Some(i) = first {
        queue.push(i, 0.0);
        any = true;
    }
    any
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 30×30 region: a striped pattern, the centre 10×10 a hole.
    fn scene() -> (Vec<[f32; 3]>, Vec<u8>) {
        let truth: Vec<[f32; 3]> =
            (0..900).map(|i| if (i % 30 / 3) % 2 == 0 { [0.8, 0.7, 0.6] } else { [0.2, 0.3, 0.4] }).collect();
        let state: Vec<u8> = (0..900)
            .map(|i| if (10..20).contains(&(i % 30)) && (10..20).contains(&(i / 30)) { HOLE } else { KNOWN })
            .collect();
        (truth, state)
    }

    fn run(
        views: &[(Vec<[f32; 3]>, Vec<bool>)],
        params: &MultiviewParams,
    ) -> (Vec<[f32; 3]>, Vec<u8>, Vec<Pick>) {
        let (truth, mut state) = scene();
        let mut pixels: Vec<[f32; 3]> =
            truth.iter().zip(&state).map(|(&p, &s)| if s == HOLE { [1.0, 0.0, 1.0] } else { p }).collect();
        let mut pick = vec![Pick::NONE; 900];
        let need = vec![true; 900];
        let refs: Vec<_> = views.iter().map(|(i, v)| (i.as_slice(), v.as_slice())).collect();
        let occ = occlusion_costs(&refs, &need, 30, 0.1);
        let data: Vec<_> = views
            .iter()
            .zip(&occ)
            .map(|((i, v), o)| ViewData { image: i, valid: v, occlusion: o, expected_error: 0.0 })
            .collect();
        let mut region =
            Region { width: 30, height: 30, pixels: &mut pixels, state: &mut state, pick: &mut pick };
        fill_region(&mut region, &data, params);
        (pixels, state, pick)
    }

    #[test]
    fn a_shifted_view_is_found_by_the_local_search() {
        let (truth, _) = scene();
        // The view's content sits one pixel to the right of the prediction.
        let shifted: Vec<[f32; 3]> =
            (0..900).map(|i| if i % 30 == 0 { truth[i] } else { truth[i - 1] }).collect();
        let (out, state, pick) = run(&[(shifted, vec![true; 900])], &MultiviewParams::default());
        assert!(state.iter().all(|&s| s != HOLE && s != UNSEEN));
        assert_eq!(state.iter().filter(|&&s| s == FILLED).count(), 100);
        let wrong = (0..900).filter(|&i| sq(out[i], truth[i]) > 1e-6).count();
        assert_eq!(wrong, 0);
        assert!(pick.iter().any(|p| p.view == 0 && p.dx == 1 && p.dy == 0));
        // Without the search, the stripes come out one pixel off.
        let p0 = MultiviewParams { search_radius: 0, ..MultiviewParams::default() };
        let shifted: Vec<[f32; 3]> =
            (0..900).map(|i| if i % 30 == 0 { truth[i] } else { truth[i - 1] }).collect();
        let (out, _, _) = run(&[(shifted, vec![true; 900])], &p0);
        assert!((0..900).filter(|&i| sq(out[i], truth[i]) > 1e-6).count() > 10);
    }

    #[test]
    fn the_occluded_view_loses_to_the_consensus() {
        let (truth, _) = scene();
        // View 0 is exact but has a grey box inside the hole; views 1 and 2 are clean but
        // noisy, so SSD on the known ring alone prefers view 0 (and then its own fill).
        let occluded: Vec<[f32; 3]> = (0..900)
            .map(|i| {
                if (12..17).contains(&(i % 30)) && (12..18).contains(&(i / 30)) { [0.5; 3] } else { truth[i] }
            })
            .collect();
        let noisy = |sign: f32| -> Vec<[f32; 3]> {
            (0..900)
                .map(|i| truth[i].map(|c| c + sign * if (i * 7) % 3 == 0 { 0.03 } else { -0.03 }))
                .collect()
        };
        let views =
            vec![(occluded, vec![true; 900]), (noisy(1.0), vec![true; 900]), (noisy(-1.0), vec![true; 900])];
        let err = |out: &[[f32; 3]]| (0..900).map(|i| sq(out[i], truth[i])).sum::<f32>();
        let (with, _, _) = run(&views, &MultiviewParams::default());
        let off = MultiviewParams { occlusion_weight: 0.0, ..MultiviewParams::default() };
        let (without, _, _) = run(&views, &off);
        assert!(err(&with) < 0.5, "with occlusion reasoning: {}", err(&with));
        assert!(err(&without) > 4.0 * err(&with), "without: {} with: {}", err(&without), err(&with));
    }

    #[test]
    fn what_no_view_covers_is_left_unseen() {
        // The view covers only the left half of the image.
        let (truth, _) = scene();
        let valid: Vec<bool> = (0..900).map(|i| i % 30 < 15).collect();
        let (_, state, pick) = run(&[(truth, valid)], &MultiviewParams::default());
        for i in 0..900 {
            let (x, y) = (i % 30, i / 30);
            if (10..20).contains(&x) && (10..20).contains(&y) {
                if x < 15 {
                    assert_eq!(state[i], FILLED, "{x},{y}");
                    assert_eq!(pick[i].view, 0);
                } else {
                    assert_eq!(state[i], UNSEEN, "{x},{y}");
                }
            }
        }
    }
}
