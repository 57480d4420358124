//! Who sees what: per view and per keyframe pixel of a region, the probability that the view
//! shows something standing in front of the building there, and from it how sure the fill
//! can be of each pixel it fills (pure layer).
//!
//! Five kinds of evidence, each measured on the region's warped, compensated views and
//! combined as log-odds (none is enough alone):
//! - **consensus**: the share of the *other* views that agree with this one at the pixel,
//!   each view weighted by how independent it is (two shots from the same spot agree on
//!   their tree as much as on the wall, so near-duplicates share one vote);
//! - **resemblance to the keyframe's masked content**: inside the mask the keyframe shows
//!   the occluder; a view that shows the same colours there, where those colours belong to
//!   the occluder and not to the building around it, shows the same occluder;
//! - **the view's own occluders, followed into the mask**: outside the mask the keyframe
//!   shows the building, so where the view disagrees with it there the view has something in
//!   front (unless that disagreement is the keyframe's building moved by one shift, as
//!   ground or a surface off the wall is with parallax: displaced, not in front); such an
//!   object is connected, so it is grown into the mask through the view's
//!   pixels that look like it rather than like the building, and, where too few views see a
//!   pixel for a consensus, through the pixels where the view disagrees with one that is not
//!   suspected (the disagreement is explained by the object that reaches it);
//! - **the building's own colours**: the keyframe's unmasked surroundings say what the
//!   building looks like; a view's pixel unlike all of it is suspect (what carries one or
//!   two views, where a consensus cannot be had);
//! - **outlines**, where two views disagree and no third sees the pixel: something standing
//!   in front has an outline, across which the view showing it steps from the building's
//!   colours to its own, while the view that sees past it continues what is around (see
//!   [`outlines`]).
//!
//! Last, inside the hole, a view that agrees with views sure they show the keyframe's
//! occluder there shows it too (a shared occluder: agreement among views is not always the
//! building).
//!
//! The fill uses the probabilities twice: as a cost when it chooses a view, and as a cut
//! (a view's pixel that is probably an occluder is never copied: the pixel goes to another
//! view or to the single-image fallback). [`confidence`] then says, per filled pixel, how
//! sure the result is that it shows the building.

use rayon::prelude::*;

/// Parameters of the model. The defaults were set on the generated cases of
/// `examples/honesty.rs` (planar, shared-occluder, non-planar families) and checked on the
/// real photographs; see BENCHMARKS.md.
#[derive(Debug, Clone, PartialEq)]
pub struct OcclusionParams {
    /// Views are compared box-averaged over `(2·r + 1)²` (misregistration, noise).
    pub blur_radius: usize,
    /// RGB distance (Euclidean, 0..=√3) under which two views agree.
    pub agree: f32,
    /// A view differs from the keyframe outside the mask by more than this: it shows
    /// something in front of the building there (a seed of its own occluder).
    pub seed_distance: f32,
    /// A view agreeing with the keyframe's pixel within this many pixels of it is not
    /// disagreeing there (the fill's local search absorbs that much misregistration).
    pub shift_tolerance: usize,
    /// Seeds count only in connected groups of at least this many pixels (an object, not
    /// the misregistration of an edge).
    pub min_object: usize,
    /// A group of seeds that is the keyframe's building moved by one shift of up to this
    /// share of the keyframe's diagonal is not an object: it is ground or a surface off
    /// the wall seen with parallax (or the alignment a little off), and it disagrees
    /// because it is displaced.
    pub displaced_share: f32,
    /// Log-odds weights of the evidence.
    pub w_consensus: f32,
    pub w_resemblance: f32,
    pub w_own: f32,
    pub w_foreign: f32,
    pub w_outline: f32,
    /// Log-odds before any evidence (negative: a view shows the building unless told).
    pub prior: f32,
    /// A view's pixel with an occlusion probability above this is not copied while another
    /// view's pixel there is below it...
    pub cut: f32,
    /// ...and not at all above this one: where every view is doubtful, the least doubtful
    /// is copied (and flagged) rather than invented, unless the model is this sure it shows
    /// an occluder.
    pub sure: f32,
}

impl Default for OcclusionParams {
    fn default() -> Self {
        Self {
            blur_radius: 2,
            agree: 0.1,
            seed_distance: 0.2,
            shift_tolerance: 2,
            min_object: 24,
            displaced_share: 0.035,
            w_consensus: 4.0,
            w_resemblance: 4.0,
            w_own: 4.0,
            w_foreign: 1.5,
            w_outline: 4.0,
            prior: -0.75,
            cut: 0.85,
            sure: 0.95,
        }
    }
}

/// Views (independence-weighted) that must agree with a view's pixel, and be sure they show
/// the keyframe's occluder there, for it to be taken as showing that occluder too.
const SHARED_WITNESSES: f32 = 1.5;
/// Fewer other witnesses than this (independence-weighted) cannot outvote a view: there
/// a disagreement is explained by the objects the views are known to have in front.
const FEW_WITNESSES: f32 = 1.5;

/// Colour histogram bins per channel (8 levels: 512 bins, coarse enough to generalise).
const LEVELS: usize = 8;

#[inline]
fn bin(p: [f32; 3]) -> usize {
    let q = |v: f32| ((v.clamp(0.0, 0.9999) * LEVELS as f32) as usize).min(LEVELS - 1);
    (q(p[0]) * LEVELS + q(p[1])) * LEVELS + q(p[2])
}

#[inline]
fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[inline]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// A normalised colour histogram with its neighbouring bins blurred in (so that a colour
/// just across a bin edge is not "never seen").
#[derive(Debug, Clone)]
pub(crate) struct Histogram {
    p: Vec<f32>,
}

impl Histogram {
    pub(crate) fn new(colours: impl Iterator<Item = [f32; 3]>) -> Self {
        let mut raw = vec![0.0f32; LEVELS * LEVELS * LEVELS];
        let mut n = 0.0;
        for c in colours {
            raw[bin(c)] += 1.0;
            n += 1.0;
        }
        let l = LEVELS as isize;
        let mut p = vec![0.0f32; raw.len()];
        for r in 0..l {
            for g in 0..l {
                for b in 0..l {
                    let mut s = 0.0;
                    for (dr, dg, db) in
                        [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
                    {
                        let (rr, gg, bb) = (r + dr, g + dg, b + db);
                        if (0..l).contains(&rr) && (0..l).contains(&gg) && (0..l).contains(&bb) {
                            let wgt = if (dr, dg, db) == (0, 0, 0) { 1.0 } else { 0.25 };
                            s += wgt * raw[((rr * l + gg) * l + bb) as usize];
                        }
                    }
                    p[((r * l + g) * l + b) as usize] = s;
                }
            }
        }
        let total: f32 = p.iter().sum();
        if n > 0.0 && total > 0.0 {
            p.iter_mut().for_each(|v| *v /= total);
        }
        Self { p }
    }

    fn prob(&self, c: [f32; 3]) -> f32 {
        self.p[bin(c)]
    }

    /// How foreign a colour is to the colours counted (0 common .. 1 never seen).
    pub(crate) fn foreign(&self, c: [f32; 3]) -> f32 {
        1.0 - (self.prob(c) / 2e-3).min(1.0)
    }
}

/// A region's keyframe side: its pixels and masks, all `width × height`. What the
/// occlusion model ([`RegionInput`]) and the plane choice (`parallax::PlaneInput`) read of
/// the keyframe.
#[derive(Debug, Clone, Copy)]
pub struct KeyRegion<'a> {
    pub width: usize,
    pub height: usize,
    pub key: &'a [[f32; 3]],
    /// Pixels to fill.
    pub hole: &'a [bool],
    /// Pixels the views were warped over (the hole and its margin).
    pub need: &'a [bool],
    /// Other regions' hole pixels (neither building nor ours).
    pub blocked: &'a [bool],
}

/// One region's inputs: the keyframe's side, the views warped and compensated over it.
#[derive(Debug, Clone, Copy)]
pub struct RegionInput<'a> {
    pub region: KeyRegion<'a>,
    pub views: &'a [(&'a [[f32; 3]], &'a [bool])],
    /// The keyframe's diagonal in pixels (parallax and misregistration scale with it).
    pub diagonal: f32,
}

/// The model over one region.
#[derive(Debug, Clone)]
pub struct OcclusionMap {
    /// Per view, region-sized: probability that the view shows an occluder at the pixel
    /// (0 where it does not cover it).
    pub occluded: Vec<Vec<f32>>,
    /// Per view, its weight as an independent witness (1 for a view unlike all others).
    pub independence: Vec<f32>,
}

/// Box average over `(2r + 1)²` of the pixels `valid` marks (separable, O(1) per pixel).
fn box_blur(img: &[[f32; 3]], valid: &[bool], w: usize, h: usize, r: usize) -> Vec<[f32; 3]> {
    if r == 0 || w == 0 {
        return img.to_vec();
    }
    let mut rows = vec![[0.0f32; 4]; w * h];
    rows.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let mut acc = [0.0f32; 4];
        let add = |acc: &mut [f32; 4], i: usize, s: f32| {
            if valid[i] {
                for c in 0..3 {
                    acc[c] += s * img[i][c];
                }
                acc[3] += s;
            }
        };
        for x in 0..r.min(w) {
            add(&mut acc, y * w + x, 1.0);
        }
        for (x, o) in out.iter_mut().enumerate() {
            if x + r < w {
                add(&mut acc, y * w + x + r, 1.0);
            }
            if x > r {
                add(&mut acc, y * w + x - r - 1, -1.0);
            }
            *o = acc;
        }
    });
    let mut out = vec![[0.0f32; 3]; w * h];
    // Columns: a running sum per column, rows in order.
    let mut acc = vec![[0.0f32; 4]; w];
    for y in 0..r.min(h) {
        for x in 0..w {
            for c in 0..4 {
                acc[x][c] += rows[y * w + x][c];
            }
        }
    }
    for y in 0..h {
        if y + r < h {
            for x in 0..w {
                for c in 0..4 {
                    acc[x][c] += rows[(y + r) * w + x][c];
                }
            }
        }
        if y > r {
            for x in 0..w {
                for c in 0..4 {
                    acc[x][c] -= rows[(y - r - 1) * w + x][c];
                }
            }
        }
        for x in 0..w {
            let a = acc[x];
            out[y * w + x] =
                if a[3] > 0.5 { [a[0] / a[3], a[1] / a[3], a[2] / a[3]] } else { img[y * w + x] };
        }
    }
    out
}

/// The weight of each view as an independent witness: views that agree with each other
/// everywhere, their occluders included, came from (nearly) the same spot and share a vote.
fn independence(blurred: &[Vec<[f32; 3]>], valid: &[&[bool]], need: &[bool], agree: f32) -> Vec<f32> {
    let nv = blurred.len();
    let pairs = pairs_of(nv);
    let twins: Vec<f32> = pairs
        .par_iter()
        .map(|&(a, b)| {
            let (mut both, mut differ) = (0usize, 0usize);
            for i in (0..need.len()).step_by(3) {
                if need[i] && valid[a][i] && valid[b][i] {
                    both += 1;
                    if dist(blurred[a][i], blurred[b][i]) > 0.5 * agree {
                        differ += 1;
                    }
                }
            }
            // Independent shots of a wall differ by noise, resampling and parallax at the
            // edges; shots from one spot differ by almost nothing.
            let frac = if both > 0 { differ as f32 / both as f32 } else { 1.0 };
            (1.0 - frac / 0.03).clamp(0.0, 1.0)
        })
        .collect();
    let mut twin = vec![vec![0.0f32; nv]; nv];
    for (&(a, b), &t) in pairs.iter().zip(&twins) {
        twin[a][b] = t;
        twin[b][a] = t;
    }
    (0..nv).map(|a| 1.0 / (1.0 + twin[a].iter().sum::<f32>())).collect()
}

/// Every pair `(a, b)` of `n` views with `a < b`, in order.
fn pairs_of(n: usize) -> Vec<(usize, usize)> {
    (0..n).flat_map(|a| (a + 1..n).map(move |b| (a, b))).collect()
}

/// 4-connected components of `seed` with at least `min` pixels that `keep` keeps.
fn objects(
    seed: &[bool],
    w: usize,
    h: usize,
    min: usize,
    mut keep: impl FnMut(&[usize]) -> bool,
) -> Vec<bool> {
    let mut out = vec![false; seed.len()];
    let mut seen = vec![false; seed.len()];
    let mut stack = Vec::new();
    let mut members = Vec::new();
    for s in 0..seed.len() {
        if !seed[s] || seen[s] {
            continue;
        }
        seen[s] = true;
        stack.push(s);
        members.clear();
        while let Some(i) = stack.pop() {
            members.push(i);
            neighbours4(i, w, h, |j| {
                if seed[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            });
        }
        if members.len() >= min && keep(&members) {
            for &i in &members {
                out[i] = true;
            }
        }
    }
    out
}

/// Whether a view's pixels `members` (box-averaged: `view`) are the keyframe's building
/// (`key`, where `building` marks it) moved by one shift of at most `max_shift` pixels:
/// their mean distance to it there is under `agree`. Every shift is tried with 64 of them
/// (where at least 60 % land on the building), the three best again with up to 256.
#[allow(clippy::too_many_arguments)]
fn displaced(
    members: &[usize],
    view: &[[f32; 3]],
    key: &[[f32; 3]],
    building: &[bool],
    w: usize,
    h: usize,
    max_shift: usize,
    agree: f32,
) -> bool {
    if max_shift == 0 || members.is_empty() {
        return false;
    }
    let sample = |count: usize| -> Vec<(isize, isize, [f32; 3])> {
        let step = members.len().div_ceil(count);
        members.iter().step_by(step).map(|&i| ((i % w) as isize, (i / w) as isize, view[i])).collect()
    };
    // Mean distance at shift (dx, dy), if enough of `at` lands on the building.
    let mean = |at: &[(isize, isize, [f32; 3])], dx: isize, dy: isize| -> Option<f32> {
        let (mut n, mut sum) = (0usize, 0.0f32);
        for &(x, y, c) in at {
            let (xx, yy) = (x + dx, y + dy);
            if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                let j = yy as usize * w + xx as usize;
                if building[j] {
                    n += 1;
                    sum += dist(c, key[j]);
                }
            }
        }
        (5 * n >= 3 * at.len()).then(|| sum / n as f32)
    };
    let (coarse, fine) = (sample(64), sample(256));
    let m = max_shift as isize;
    let mut best: Vec<(f32, isize, isize)> = (-m..=m)
        .into_par_iter()
        .flat_map_iter(|dy| {
            let coarse = &coarse;
            (-m..=m).filter_map(move |dx| mean(coarse, dx, dy).map(|d| (d, dx, dy)))
        })
        .filter(|b| b.0 < 2.0 * agree)
        .collect();
    best.sort_by(|a, b| a.0.total_cmp(&b.0));
    best.iter().take(3).any(|&(_, dx, dy)| mean(&fine, dx, dy).is_some_and(|d| d < agree))
}

/// Calls `visit` with the index of each 4-neighbour of pixel `i` in a `w × h` grid.
fn neighbours4(i: usize, w: usize, h: usize, mut visit: impl FnMut(usize)) {
    let (x, y) = (i % w, i / w);
    if x > 0 {
        visit(i - 1);
    }
    if x + 1 < w {
        visit(i + 1);
    }
    if y > 0 {
        visit(i - w);
    }
    if y + 1 < h {
        visit(i + w);
    }
}

/// Grows `from` through the pixels `allowed` marks (4-connected).
fn grow(from: &[bool], allowed: &[bool], w: usize, h: usize) -> Vec<bool> {
    let mut out = from.to_vec();
    let mut stack: Vec<usize> = (0..from.len()).filter(|&i| from[i]).collect();
    while let Some(i) = stack.pop() {
        neighbours4(i, w, h, |j| {
            if allowed[j] && !out[j] {
                out[j] = true;
                stack.push(j);
            }
        });
    }
    out
}

/// Two views differ grossly, at the core of an area of disagreement, where their box
/// averages are further apart than this share of `seed_distance` (a passer-by's shirt a
/// little unlike the bricks behind him still makes a core)...
const OUTLINE_CORE: f32 = 0.6;
/// ...and the area takes in the pixels where they differ at all (more than `agree`) up to
/// this many steps from its core: the parts of the object nearer the building's colours.
const OUTLINE_GROW: usize = 6;
/// Outer layers (4-connected steps from an area of disagreement) whose agreed colours an
/// outline is measured from: the first is left out (the box average spreads the area by
/// about the blur radius, so the views there are mixed with what is inside).
const OUTLINE_OUTSIDE: std::ops::RangeInclusive<usize> = 2..=4;
/// Depths inside the area (steps from its edge) where each view's step is measured.
const OUTLINE_INSIDE: std::ops::RangeInclusive<usize> = 3..=6;
/// Added to the larger step before the two steps' difference is divided by it: two small
/// steps (both views continue the outside, as where one is a little misregistered) say
/// little.
const OUTLINE_SOFT: f32 = 0.05;
/// An inner pixel's colour is looked for among the agreed outside pixels within this many
/// pixels of it.
const OUTLINE_REACH: usize = 16;
/// Fewer pixels than this on either side of an outline: it says nothing.
const OUTLINE_MIN: usize = 12;

/// Evidence from the outlines of what two lone views disagree on (no third view sees the
/// pixel to say which is right): per view, region-sized, from -1 (it surely sees the building
/// there) to +1 (it surely shows something in front). Something standing in front of the
/// building has an outline: across it, the view that shows it steps from the building's
/// colours to the object's, while the view that sees past it shows the building continuing
/// from just outside, where the two agree. So, per connected area where two lone views
/// disagree, each view's step from the agreed colours just outside to its own just inside:
/// the larger step is the occluder's. (The keyframe's colours cannot say: a passer-by wholly
/// inside the mask, in front of a window whose glass the ring does not show, is as foreign
/// to the ring as the glass.)
#[allow(clippy::too_many_arguments)]
fn outlines(
    views: &[Vec<[f32; 3]>],
    raw: &[(&[[f32; 3]], &[bool])],
    valid: &[&[bool]],
    hole: &[bool],
    witnesses: &[f32],
    ind: &[f32],
    w: usize,
    h: usize,
    max_shift: usize,
    params: &OcclusionParams,
) -> Vec<Vec<f32>> {
    let nv = views.len();
    let n = w * h;
    let mut out = vec![vec![0.0f32; n]; nv];
    if params.w_outline == 0.0 {
        return out;
    }
    // Each pair's areas are found on every core; their evidence is added in the pairs'
    // order, as it always was.
    let pairs = pairs_of(nv);
    let steps: Vec<Vec<(Vec<usize>, f32)>> = pairs
        .par_iter()
        .map(|&(u, v)| {
            let seen: Vec<bool> = (0..n).map(|i| valid[u][i] && valid[v][i]).collect();
            // Where the two disagree: grossly (the cores of areas), or at all (what an area
            // takes in around its core).
            let lone = |i: usize| hole[i] && seen[i] && witnesses[i] - ind[u] - ind[v] < 0.5;
            let differ: Vec<bool> =
                (0..n).map(|i| lone(i) && dist(views[u][i], views[v][i]) > params.agree).collect();
            let gross: Vec<bool> = (0..n)
                .map(|i| differ[i] && dist(views[u][i], views[v][i]) > OUTLINE_CORE * params.seed_distance)
                .collect();
            let core = super::automask::erode(&crate::imaging::Plane::from_vec(w, h, gross), 1);
            let mut areas = Vec::new();
            objects(core.as_slice(), w, h, params.min_object, |members| {
                areas.push(members.to_vec());
                false
            });
            areas
                .into_iter()
                .filter_map(|members| {
                    outline_step(
                        &members,
                        &differ,
                        [&views[u], &views[v]],
                        [raw[u].0, raw[v].0],
                        &seen,
                        w,
                        h,
                        max_shift,
                        params,
                    )
                })
                .collect()
        })
        .collect();
    for (&(u, v), found) in pairs.iter().zip(steps) {
        for (area, e) in found {
            for i in area {
                out[v][i] += e;
                out[u][i] -= e;
            }
        }
    }
    for o in &mut out {
        o.iter_mut().for_each(|e| *e = e.clamp(-1.0, 1.0));
    }
    out
}

/// For one area where two views disagree (the eroded core `members`, taken back to
/// `differ`), the area's pixels and the evidence that the second view, not the first, shows
/// something in front there (see [`outlines`]); `None` when its outline is too short to say.
#[allow(clippy::too_many_arguments)]
fn outline_step(
    members: &[usize],
    differ: &[bool],
    pair: [&[[f32; 3]]; 2],
    raw: [&[[f32; 3]]; 2],
    seen: &[bool],
    w: usize,
    h: usize,
    max_shift: usize,
    params: &OcclusionParams,
) -> Option<(Vec<usize>, f32)> {
    // A box around the area with room for the outside layers.
    let pad = OUTLINE_GROW + *OUTLINE_OUTSIDE.end() + OUTLINE_REACH;
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for &i in members {
        let (x, y) = (i % w, i / w);
        (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
    }
    let (x0, y0) = (x0.saturating_sub(pad), y0.saturating_sub(pad));
    let (x1, y1) = ((x1 + pad).min(w - 1), (y1 + pad).min(h - 1));
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    let global = |j: usize| (y0 + j / bw) * w + x0 + j % bw;
    // The area: the core and the disagreeing pixels connected to it, up to a few steps out.
    let mut inside = vec![false; bw * bh];
    let mut queue: std::collections::VecDeque<(usize, usize)> = members
        .iter()
        .map(|&i| {
            let j = (i / w - y0) * bw + i % w - x0;
            inside[j] = true;
            (j, 0)
        })
        .collect();
    while let Some((j, d)) = queue.pop_front() {
        if d < OUTLINE_GROW {
            neighbours4(j, bw, bh, |k| {
                if !inside[k] && differ[global(k)] {
                    inside[k] = true;
                    queue.push_back((k, d + 1));
                }
            });
        }
    }
    // Steps from the area's edge: outwards (over everything), and inwards.
    let layers = |from: &dyn Fn(usize) -> bool, through: &dyn Fn(usize) -> bool| -> Vec<usize> {
        let mut depth = vec![usize::MAX; bw * bh];
        let mut queue = std::collections::VecDeque::new();
        for (j, d) in depth.iter_mut().enumerate() {
            if from(j) {
                *d = 0;
                queue.push_back(j);
            }
        }
        while let Some(j) = queue.pop_front() {
            let next = depth[j] + 1;
            neighbours4(j, bw, bh, |k| {
                if depth[k] == usize::MAX && through(k) {
                    depth[k] = next;
                    queue.push_back(k);
                }
            });
        }
        depth
    };
    let out_depth = layers(&|j| inside[j], &|j| !inside[j]);
    let in_depth = layers(&|j| !inside[j], &|j| inside[j]);
    let agreed = |j: usize| {
        let i = global(j);
        seen[i] && dist(pair[0][i], pair[1][i]) < params.agree
    };
    // The agreed colour (the two views' mean) of each outside pixel.
    let outside: Vec<Option<[f32; 3]>> = (0..bw * bh)
        .map(|j| {
            let s = global(j);
            (OUTLINE_OUTSIDE.contains(&out_depth[j]) && agreed(j))
                .then(|| std::array::from_fn(|c| 0.5 * (raw[0][s][c] + raw[1][s][c])))
        })
        .collect();
    if outside.iter().flatten().count() < OUTLINE_MIN {
        return None;
    }
    // Each inner pixel's closest colour among the agreed outside pixels near it: what the
    // building shows around the area continues into it in the view that sees past the
    // object (a muntin hidden by legs meets itself where it leaves the area), while the
    // object's colours are not there.
    let reach = OUTLINE_REACH as isize;
    let (mut steps, mut count) = ([0.0f32; 2], 0usize);
    for j in 0..bw * bh {
        if !inside[j] || !OUTLINE_INSIDE.contains(&in_depth[j]) {
            continue;
        }
        let (jx, jy) = ((j % bw) as isize, (j / bw) as isize);
        let i = global(j);
        let mut best = [f32::INFINITY; 2];
        for yy in (jy - reach).max(0)..=(jy + reach).min(bh as isize - 1) {
            for xx in (jx - reach).max(0)..=(jx + reach).min(bw as isize - 1) {
                let Some(agreed) = outside[yy as usize * bw + xx as usize] else { continue };
                for (b, view) in best.iter_mut().zip(raw) {
                    *b = b.min(dist(view[i], agreed));
                }
            }
        }
        if best[0].is_finite() {
            steps[0] += best[0];
            steps[1] += best[1];
            count += 1;
        }
    }
    if count < OUTLINE_MIN {
        return None;
    }
    let [a, b] = steps.map(|s| s / count as f32);
    // The view that steps further may show the other's building moved (a corner or a
    // muntin seen with parallax, the two a few pixels apart): that is no object in front.
    let (stepped, other) = if b > a { (1, 0) } else { (0, 1) };
    let area: Vec<usize> = (0..bw * bh).filter(|&j| inside[j]).map(global).collect();
    if displaced(&area, pair[stepped], pair[other], seen, w, h, max_shift, params.agree) {
        return None;
    }
    Some((area, (b - a) / (a.max(b) + OUTLINE_SOFT)))
}

/// The model over one region (see the module docs).
pub fn occlusion_map(input: &RegionInput<'_>, params: &OcclusionParams) -> OcclusionMap {
    let (w, h) = (input.region.width, input.region.height);
    let n = w * h;
    let nv = input.views.len();
    let r = params.blur_radius;
    let max_shift = (params.displaced_share * input.diagonal).round() as usize;
    let all = vec![true; n];
    let valid: Vec<&[bool]> = input.views.iter().map(|v| v.1).collect();
    let (key_b, views_b): (Vec<[f32; 3]>, Vec<Vec<[f32; 3]>>) = rayon::join(
        || box_blur(input.region.key, &all, w, h, r),
        || input.views.par_iter().map(|(img, ok)| box_blur(img, ok, w, h, r)).collect(),
    );
    let ind = independence(&views_b, &valid, input.region.need, params.agree);
    // Per pixel, each view's support among the others (weighted share agreeing with it),
    // and the best support any view has there: a view is an outlier only where others
    // agree among themselves; where nobody agrees with anybody (an edge off, parallax) the
    // consensus says nothing.
    let support: Vec<Vec<f32>> = (0..nv)
        .into_par_iter()
        .map(|v| {
            (0..n)
                .map(|i| {
                    if !valid[v][i] || !input.region.need[i] {
                        return 0.0;
                    }
                    let (mut wsum, mut agree) = (0.0f32, 0.0f32);
                    for u in 0..nv {
                        if u != v && valid[u][i] {
                            wsum += ind[u];
                            if dist(views_b[u][i], views_b[v][i]) < params.agree {
                                agree += ind[u];
                            }
                        }
                    }
                    if wsum > 0.0 { agree / wsum } else { 0.0 }
                })
                .collect()
        })
        .collect();
    let witnesses: Vec<f32> = (0..n)
        .into_par_iter()
        .map(|i| (0..nv).filter(|&u| valid[u][i]).map(|u| ind[u]).sum::<f32>())
        .collect();
    let best: Vec<f32> =
        (0..n).into_par_iter().map(|i| (0..nv).map(|v| support[v][i]).fold(0.0, f32::max)).collect();

    let outline =
        outlines(&views_b, input.views, &valid, input.region.hole, &witnesses, &ind, w, h, max_shift, params);
    // The building: the keyframe around the hole. The occluder: the keyframe inside it.
    let around: Vec<bool> = (0..n)
        .into_par_iter()
        .map(|i| input.region.need[i] && !input.region.hole[i] && !input.region.blocked[i])
        .collect();
    let building = Histogram::new((0..n).filter(|&i| around[i]).map(|i| input.region.key[i]));
    let inner = super::automask::erode(&crate::imaging::Plane::from_vec(w, h, input.region.hole.to_vec()), 2);
    let occluder = Histogram::new((0..n).filter(|&i| inner.as_slice()[i]).map(|i| input.region.key[i]));
    // How much a colour belongs to the keyframe's occluder rather than to its building.
    let occluder_like = |c: [f32; 3]| -> f32 {
        let (o, b) = (occluder.prob(c), building.prob(c));
        (o / (o + b + 1e-4)).clamp(0.0, 1.0) * (o / (o + 1e-3)).min(1.0)
    };

    // Each view's own occluders (outside the mask, followed into it).
    let own: Vec<Vec<bool>> = (0..nv)
        .into_par_iter()
        .map(|v| {
            let (img_b, ok) = (&views_b[v], valid[v]);
            // The view's own occluders: where it disagrees with the keyframe's building...
            // (at every shift the fill's local search could take: a view a pixel or two
            // off is misregistered there, not occluded)
            let s = params.shift_tolerance as isize;
            let seeds: Vec<bool> = (0..n)
                .map(|i| {
                    if !(around[i] && ok[i]) {
                        return false;
                    }
                    let (x, y) = ((i % w) as isize, (i / w) as isize);
                    !(-s..=s).any(|dy| {
                        (-s..=s).any(|dx| {
                            let (xx, yy) = (x + dx, y + dy);
                            if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
                                return false;
                            }
                            let j = yy as usize * w + xx as usize;
                            ok[j] && dist(img_b[j], key_b[i]) <= params.seed_distance
                        })
                    })
                })
                .collect();
            // Thin lines of disagreement are edges a little off (parallax, registration): an
            // object survives an erosion.
            let core = super::automask::erode(&crate::imaging::Plane::from_vec(w, h, seeds), 1);
            let objs = objects(core.as_slice(), w, h, params.min_object, |_| true);
            // Disagreement that is the keyframe's building moved (ground or a surface off the
            // wall, with parallax) is not an object. Objects near each other are judged
            // together: the part of a displaced band next to the hole lands, moved back, in
            // the hole, where the keyframe cannot say; the rest of the band can.
            let near = super::automask::dilate(
                &crate::imaging::Plane::from_vec(w, h, objs.clone()),
                2 + max_shift / 4,
            );
            let kept = objects(near.as_slice(), w, h, 1, |cluster| {
                let members: Vec<usize> = cluster.iter().copied().filter(|&i| objs[i]).collect();
                !displaced(&members, img_b, &key_b, &around, w, h, max_shift, params.agree)
            });
            let seeds: Vec<bool> = (0..n).map(|i| objs[i] && kept[i]).collect();
            if seeds.iter().any(|&s| s) {
                // ...followed into the hole through pixels that look like the object.
                let object = Histogram::new((0..n).filter(|&i| seeds[i]).map(|i| input.views[v].0[i]));
                let allowed: Vec<bool> = (0..n)
                    .map(|i| {
                        input.region.hole[i] && ok[i] && {
                            let c = input.views[v].0[i];
                            object.prob(c) > 2.0 * building.prob(c) + 1e-4
                        }
                    })
                    .collect();
                // The seeds stop short of the hole: the keyframe's pixels next to it are
                // blurred with its occluder, and the seeds were eroded. The object is taken
                // across that gap (outside the hole only) before it is followed in.
                let gap = 1 + r + params.shift_tolerance;
                let near =
                    super::automask::dilate(&crate::imaging::Plane::from_vec(w, h, seeds.clone()), gap);
                let start: Vec<bool> = (0..n)
                    .map(|i| seeds[i] || (near.as_slice()[i] && ok[i] && !input.region.hole[i]))
                    .collect();
                grow(&start, &allowed, w, h)
            } else {
                vec![false; n]
            }
        })
        .collect();
    // A view's probability of showing an occluder, given its own occluders `own`.
    let probability = |v: usize, own: &[bool]| -> Vec<f32> {
        let (img_b, ok) = (&views_b[v], valid[v]);
        (0..n)
            .map(|i| {
                if !ok[i] || !input.region.need[i] {
                    return 0.0;
                }
                let c = img_b[i];
                let mut l = params.prior;
                // Consensus of the other views, by independence. One other view cannot
                // say which of the two is occluded; the consensus carries weight from
                // two other witnesses, fully from three.
                let others = witnesses[i] - ind[v];
                let trust = ((others - 0.5) / 2.5).clamp(0.0, 1.0);
                l += params.w_consensus * trust * (best[i] - support[v][i] - 0.5 * best[i]) * 2.0;
                if input.region.hole[i] {
                    // The keyframe's own occluder, seen again.
                    // At the same place, or anywhere: colours the keyframe's occluder has
                    // and its building has not (a tree shifted by parallax is still green).
                    let same = (1.0 - dist(c, key_b[i]) / params.agree).clamp(0.0, 1.0);
                    let kind = (2.0 * occluder_like(c) - 1.0).max(0.0);
                    l += params.w_resemblance * (same * occluder_like(key_b[i])).max(kind);
                    l += params.w_outline * outline[v][i];
                }
                if own[i] {
                    l += params.w_own;
                }
                l += params.w_foreign * (building.foreign(c) - 0.5);
                sigmoid(l)
            })
            .collect()
    };
    let first: Vec<Vec<f32>> = (0..nv).into_par_iter().map(|v| probability(v, &own[v])).collect();
    // Explaining away, where too few witnesses for a consensus see a hole pixel: where a
    // view disagrees grossly with every other view there and one of those is not
    // suspected, the disagreement belongs to whichever of them has an object in front that
    // reaches that place. An object is connected, so a view's own occluder is followed
    // further through such pixels, whatever their colour: the roof of a car whose body
    // crosses the mask's edge, with one other view that saw the wall behind it. The other
    // view's disagreement there is explained by this object, so its own objects do not
    // grow through it.
    let grown: Vec<Vec<bool>> = (0..nv)
        .into_par_iter()
        .map(|v| {
            if !own[v].iter().any(|&o| o) {
                return own[v].clone();
            }
            let allowed: Vec<bool> = (0..n)
                .map(|i| {
                    input.region.hole[i]
                        && valid[v][i]
                        && witnesses[i] - ind[v] < FEW_WITNESSES
                        && support[v][i] == 0.0
                        && (0..nv).any(|u| {
                            u != v
                                && valid[u][i]
                                && !own[u][i]
                                && first[u][i] < 0.5
                                && dist(views_b[u][i], views_b[v][i]) > params.seed_distance
                        })
                })
                .collect();
            grow(&own[v], &allowed, w, h)
        })
        .collect();
    let occluded: Vec<Vec<f32>> = (0..nv)
        .into_par_iter()
        .zip(first)
        .map(|(v, p)| if grown[v] == own[v] { p } else { probability(v, &grown[v]) })
        .collect();
    let shared = Shared { views: &views_b, valid: &valid, hole: input.region.hole, independence: &ind };
    let occluded = shared.raise(occluded, |c| occluder_like(c) >= 0.5, params);
    OcclusionMap { occluded, independence: ind }
}

/// The views of a region as [`Shared::raise`] reads them: blurred, where valid, the hole,
/// and each view's independence.
struct Shared<'a> {
    views: &'a [Vec<[f32; 3]>],
    valid: &'a [&'a [bool]],
    hole: &'a [bool],
    independence: &'a [f32],
}

impl Shared<'_> {
    /// Inside the hole, a view that shows what other views surely show the keyframe's
    /// occluder with (their pixels agree, and are of the occluder's colours) shows the same
    /// occluder: the tree every view sees a little shifted, where one view's colours
    /// resemble the keyframe's tree a little less than the others' do, or its tree does not
    /// cross the mask's edge to be followed in. Its probability is raised to theirs when
    /// the views surely showing the occluder weigh at least [`SHARED_WITNESSES`] and more
    /// than the other views that agree with it (a lone view sure by colour alone, the sky
    /// taken for a grey car, raises nothing).
    fn raise(
        &self,
        occluded: Vec<Vec<f32>>,
        occluder_colour: impl Fn([f32; 3]) -> bool + Sync,
        params: &OcclusionParams,
    ) -> Vec<Vec<f32>> {
        let nv = occluded.len();
        // Per view, the hole pixels where it surely shows the occluder (once, not per pair).
        let sure_of: Vec<Vec<bool>> = (0..nv)
            .into_par_iter()
            .map(|u| {
                (0..occluded[u].len())
                    .map(|i| {
                        self.hole[i]
                            && self.valid[u][i]
                            && occluded[u][i] >= params.sure
                            && occluder_colour(self.views[u][i])
                    })
                    .collect()
            })
            .collect();
        let n = occluded.first().map_or(0, Vec::len);
        let any_sure: Vec<bool> = (0..n).into_par_iter().map(|i| sure_of.iter().any(|s| s[i])).collect();
        (0..nv)
            .into_par_iter()
            .map(|v| {
                (0..occluded[v].len())
                    .map(|i| {
                        let p = occluded[v][i];
                        if !any_sure[i] || !self.valid[v][i] || p >= params.sure {
                            return p;
                        }
                        let (mut sure, mut other, mut most) = (0.0f32, 0.0f32, p);
                        for u in (0..nv).filter(|&u| u != v && self.valid[u][i]) {
                            if dist(self.views[u][i], self.views[v][i]) >= params.agree {
                                continue;
                            }
                            if sure_of[u][i] {
                                sure += self.independence[u];
                                most = most.max(occluded[u][i]);
                            } else {
                                other += self.independence[u];
                            }
                        }
                        if sure >= SHARED_WITNESSES && sure > other { most } else { p }
                    })
                    .collect()
            })
            .collect()
    }
}

/// How sure the fill is that a filled pixel shows the building, and right (0..=1): the
/// picked view's occlusion probability at the pixel it was copied from, times the support of
/// the other views that see the building there, each at its own registration, at the pixel
/// itself (their spread is what misregistration and parallax do to an edge); and the picked
/// view's own local contrast: an edge a fraction of a pixel off is wrong by that fraction of
/// its step, however well the witnesses agree.
///
/// `value` is the filled colour (after compensation, before blending); `at` the pixel of the
/// picked view it came from (the prediction shifted by the local search), and `reach` how
/// many keyframe pixels one of that view's pixels spans there (a view at a third of the
/// keyframe's resolution: 3; its edges are that soft, and the step across one is measured
/// that far apart); `width` the region's.
#[allow(clippy::too_many_arguments)]
pub fn confidence(
    map: &OcclusionMap,
    views: &[(&[[f32; 3]], &[bool])],
    picked: usize,
    (at, reach): (usize, usize),
    i: usize,
    width: usize,
    value: [f32; 3],
) -> PixelConfidence {
    let own = 1.0 - map.occluded[picked][at];
    let (mut wsum, mut agree) = (0.0f32, 0.0f32);
    for (u, (img, ok)) in views.iter().enumerate() {
        if u == picked || !ok[i] {
            continue;
        }
        // A witness counts as far as it is itself not occluded there.
        let wgt = map.independence[u] * (1.0 - map.occluded[u][i]);
        wsum += wgt;
        agree += wgt * closeness(max_channel(img[i], value));
    }
    // The picked view's own contrast: an edge is wrong by a fraction of its step for every
    // fraction of a pixel the views are off (resampling, registration), however well the
    // witnesses agree (they are all resampled alike).
    let (img, ok) = views[picked];
    let (step, soft_step) = steps(img, ok, at, width, reach);
    // Without witnesses, the view alone (as sure as that can be).
    let support = (agree + SOLE_WITNESS * (WITNESSES - wsum).max(0.0)) / wsum.max(WITNESSES);
    PixelConfidence { building: own * support.clamp(0.0, 1.0), step, soft_step }
}

/// The largest step (0..=1) from pixel `i` of a view (`img`, where `ok`; rows `width`
/// long) to the pixels `d` away along a row or a column.
fn step_at(img: &[[f32; 3]], ok: &[bool], i: usize, width: usize, d: usize) -> f32 {
    let mut step = 0.0f32;
    for j in [i.wrapping_sub(d), i + d, i.wrapping_sub(d * width), i + d * width] {
        if j < img.len() && ok[j] {
            step = step.max(max_channel(img[j], img[i]));
        }
    }
    step
}

/// [`step_at`] one pixel apart, and across the view's own pixel (`reach` keyframe pixels):
/// a coarser view's edge is spread over `reach` pixels, and its whole step is that far
/// apart. (step, soft step).
pub(crate) fn steps(img: &[[f32; 3]], ok: &[bool], i: usize, width: usize, reach: usize) -> (f32, f32) {
    let step = step_at(img, ok, i, width, 1);
    (step, if reach > 1 { step.max(step_at(img, ok, i, width, reach)) } else { step })
}

/// A filled pixel's [`confidence`], in its two halves: how sure the fill is that the pixel
/// shows the building (the model and the witnesses), and the picked view's contrast there
/// (the largest step to a 4-neighbour, 0..=1), which says how wrong an edge may be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelConfidence {
    pub building: f32,
    pub step: f32,
    /// The step measured across the picked view's own pixel (`reach` keyframe pixels
    /// apart; `step` at the keyframe's resolution): the contrast of an edge a coarser view
    /// has spread over several pixels.
    pub soft_step: f32,
}

impl PixelConfidence {
    /// The confidence, an edge taken to be wrong by `edge_share` of its step: as the fill
    /// decides with it ([`GUIDE_EDGE_SHARE`]).
    pub fn value(&self, edge_share: f32) -> f32 {
        self.building * closeness(edge_share * self.step)
    }

    /// The confidence a result reports: an edge taken to be wrong by `edge_share` of its
    /// step across the picked view's own pixel (the share the view's ring shows, at least
    /// [`EDGE_SHARE`]). Where a view coarser than the keyframe filled, the copy cannot say
    /// where within that pixel the edge lies, nor how sharp it is (views at a half and a
    /// third of the keyframe's size made the report surer than the views themselves, while
    /// its fills lost 3–6 dB).
    pub fn reported(&self, edge_share: f32) -> f32 {
        self.building * closeness(edge_share * self.soft_step)
    }
}

/// Witness weight from which the witnesses alone decide.
const WITNESSES: f32 = 0.5;
/// The least share of an edge's step taken as its expected error in the confidence a result
/// reports (a view's ring may show more). At 0.25 most of the generated cases' gross errors
/// that were marked confident lay along brick and window edges (flagged recall 60 % with 4
/// views); at 0.4, 68 % (BENCHMARKS.md, "Confidence at edges").
pub const EDGE_SHARE: f32 = 0.4;
/// The same share in the confidence the fill decides with (which view pixels border the
/// fallback's guide): the value its thresholds were measured with.
pub const GUIDE_EDGE_SHARE: f32 = 0.25;

/// The largest per-channel difference.
#[inline]
pub(crate) fn max_channel(a: [f32; 3], b: [f32; 3]) -> f32 {
    (a[0] - b[0]).abs().max((a[1] - b[1]).abs()).max((a[2] - b[2]).abs())
}

/// 1 for a difference within [`CLOSE`], falling to 0 at [`FAR`] (8-bit levels / 255).
#[inline]
pub(crate) fn closeness(d: f32) -> f32 {
    ((FAR - d) / (FAR - CLOSE)).clamp(0.0, 1.0)
}

/// Witnesses within this many levels agree...
const CLOSE: f32 = 12.0 / 255.0;
/// ...and from this many on disagree (a gross error is 30).
const FAR: f32 = 36.0 / 255.0;

/// The support a pixel seen by one view only gets at best.
const SOLE_WITNESS: f32 = 0.8;

#[cfg(test)]
mod tests {
    use super::*;

    fn region(w: usize, h: usize, hole: impl Fn(usize, usize) -> bool) -> (Vec<bool>, Vec<bool>, Vec<bool>) {
        let hole: Vec<bool> = (0..w * h).map(|i| hole(i % w, i / w)).collect();
        (hole, vec![true; w * h], vec![false; w * h])
    }

    /// A view at a third of the keyframe's resolution spreads an edge over three pixels:
    /// one pixel apart its steps are a third of the edge, which the report called sure;
    /// measured across the view's own pixel the edge is whole, and the pixel is doubted.
    /// The confidence the fill decides with is the same either way.
    #[test]
    fn an_edge_a_coarser_view_spread_over_its_pixel_is_doubted_in_the_report() {
        let w = 9;
        // A ramp from 0.2 to 0.8 over columns 3..=6 (three steps of 0.2), one row.
        let img: Vec<[f32; 3]> = (0..w).map(|x| [0.2 + 0.2 * (x as f32 - 3.0).clamp(0.0, 3.0); 3]).collect();
        let ok = vec![true; w];
        let map = OcclusionMap { occluded: vec![vec![0.0; w]], independence: vec![1.0] };
        let views = [(img.as_slice(), ok.as_slice())];
        let at = 4;
        let fine = confidence(&map, &views, 0, (at, 1), at, w, img[at]);
        let coarse = confidence(&map, &views, 0, (at, 3), at, w, img[at]);
        let sure = f32::from(crate::inpaint::CONFIDENT) / 255.0;
        assert!(fine.reported(EDGE_SHARE) >= sure, "one pixel apart: {:.3}", fine.reported(EDGE_SHARE));
        assert!(
            coarse.reported(EDGE_SHARE) < sure,
            "across the view's pixel: {:.3}",
            coarse.reported(EDGE_SHARE)
        );
        assert_eq!(fine.value(GUIDE_EDGE_SHARE), coarse.value(GUIDE_EDGE_SHARE));
    }

    #[test]
    fn blur_averages_only_valid_pixels() {
        let img = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]];
        let valid = vec![true, false, true, true];
        let b = box_blur(&img, &valid, 2, 2, 1);
        for p in &b {
            assert!((p[0] - 2.0 / 3.0).abs() < 1e-6 && (p[1] - 1.0 / 3.0).abs() < 1e-6, "{p:?}");
        }
    }

    /// Ground seen with parallax disagrees with the keyframe beside the hole as much as a
    /// passer-by does, but it is the keyframe's own content moved: it is not followed into
    /// the hole as an object (on parapano_hunt, with `--mask auto` along a path's edge, the
    /// fill became a patchwork of squares where the views' displaced grass was cut). A real
    /// object crossing the hole's edge still is.
    #[test]
    fn displaced_ground_is_not_an_object_but_a_passer_by_is() {
        let (w, h) = (160, 100);
        let mut seed = 7u64;
        let cells: Vec<[f32; 3]> = (0..40 * 40)
            .map(|_| {
                let mut c = [0.0; 3];
                for v in &mut c {
                    seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    *v = 0.2 + 0.6 * ((seed >> 33) as f32 / (1u64 << 31) as f32);
                }
                c
            })
            .collect();
        let building =
            |x: isize, y: isize| cells[(y.rem_euclid(320) / 8 * 40 + x.rem_euclid(320) / 8) as usize];
        let in_hole = |x: usize, y: usize| (60..100).contains(&x) && (20..80).contains(&y);
        let key: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if in_hole(x, y) { [0.1, 0.5, 0.1] } else { building(x as isize, y as isize) }
            })
            .collect();
        let (hole, need, blocked) = region(w, h, in_hole);
        // The ground (the lower half) moved 12 px by parallax.
        let ground: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                if y >= 50 { building(x - 12, y) } else { building(x, y) }
            })
            .collect();
        let blob = |x: usize, y: usize| (40..75).contains(&x) && (25..45).contains(&y);
        let passer_by: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if blob(x, y) { [0.6, 0.1, 0.7] } else { building(x as isize, y as isize) }
            })
            .collect();
        let ok = vec![true; w * h];
        let views = [(ground.as_slice(), ok.as_slice()), (passer_by.as_slice(), ok.as_slice())];
        let region =
            KeyRegion { width: w, height: h, key: &key, hole: &hole, need: &need, blocked: &blocked };
        let input = RegionInput { region, views: &views, diagonal: 600.0 };
        let cut_share = |m: &OcclusionMap, v: usize, at: &dyn Fn(usize, usize) -> bool| {
            let px: Vec<usize> = (0..w * h).filter(|&i| hole[i] && at(i % w, i / w)).collect();
            px.iter().filter(|&&i| m.occluded[v][i] > 0.85).count() as f32 / px.len() as f32
        };
        let lower = |_x: usize, y: usize| y >= 52;
        let params = OcclusionParams::default();
        let m = occlusion_map(&input, &params);
        let (ground_cut, blob_cut) = (cut_share(&m, 0, &lower), cut_share(&m, 1, &blob));
        // Without the displacement test the ground is taken for an object.
        let blind = occlusion_map(&input, &OcclusionParams { displaced_share: 0.0, ..params });
        let blind_cut = cut_share(&blind, 0, &lower);
        assert!(ground_cut < 0.05, "displaced ground cut on {:.0} % of the hole", 100.0 * ground_cut);
        assert!(
            blob_cut > 0.8,
            "the passer-by cut on only {:.0} % of its part of the hole",
            100.0 * blob_cut
        );
        assert!(
            blind_cut > 0.3,
            "the case does not test the displacement: {:.0} % cut without it",
            100.0 * blind_cut
        );
    }

    /// `shared-2` of `service_cases`: every view shows the keyframe's tree, a little
    /// shifted; three are sure of it at a pixel, the fourth shows the same green there and
    /// was copied (1.9 dB lost when it arrived in the service).
    #[test]
    fn a_view_agreeing_with_views_sure_of_the_keyframes_occluder_shows_it_too() {
        let params = OcclusionParams::default();
        let (green, bluer, brick) = ([0.1, 0.55, 0.1], [0.12, 0.53, 0.15], [0.6, 0.4, 0.3]);
        let is_green = |c: [f32; 3]| c[1] > 2.0 * c[0];
        // The fourth view's probability after the rule, at one pixel.
        let raised = |p: [f32; 4], colours: [[f32; 3]; 4], in_hole: bool, independence: [f32; 4]| {
            let views: Vec<Vec<[f32; 3]>> = colours.iter().map(|&c| vec![c]).collect();
            let ok = [true];
            let valid: Vec<&[bool]> = vec![&ok; 4];
            let shared =
                Shared { views: &views, valid: &valid, hole: &[in_hole], independence: &independence };
            shared.raise(p.iter().map(|&q| vec![q]).collect(), is_green, &params)[3][0]
        };
        let raise = |p: [f32; 4], colours: [[f32; 3]; 4]| raised(p, colours, true, [1.0; 4]);
        let three_sure = [0.98, 0.99, 0.97, 0.6];
        // Three views sure of the tree, the fourth agreeing with them: the tree.
        assert_eq!(raise(three_sure, [green, green, green, bluer]), 0.99);
        // The same probabilities where the fourth shows brick: it does not agree, unchanged.
        assert_eq!(raise(three_sure, [green, green, green, brick]), 0.6);
        // Sure views whose colour is not the keyframe's occluder's (the sky taken for a grey
        // car, say): nothing is raised.
        assert_eq!(raise(three_sure, [brick, brick, brick, brick]), 0.6);
        // One sure view alone cannot make another an occluder.
        assert_eq!(raise([0.98, 0.3, 0.2, 0.6], [green, brick, brick, bluer]), 0.6);
        assert_eq!(raise([0.98, 0.3, 0.3, 0.6], [green, bluer, bluer, bluer]), 0.6);
        // Two sure views outweigh one unsure view that agrees with the fourth...
        assert_eq!(raise([0.98, 0.98, 0.3, 0.6], [green, green, bluer, bluer]), 0.98);
        // ...but not unsure views that weigh as much (here one view worth two).
        let heavy = [1.0, 1.0, 2.0, 1.0];
        assert_eq!(raised([0.98, 0.98, 0.3, 0.6], [green, green, bluer, bluer], true, heavy), 0.6);
        // Outside the hole nothing is raised.
        assert_eq!(raised(three_sure, [green, green, green, bluer], false, [1.0; 4]), 0.6);
    }

    /// A passer-by wholly inside the mask, in front of a window whose glass the keyframe's
    /// ring does not show, seen by one of two views (the daemon's `Scene::new(710)`: the
    /// second view's fill copied him into the window, 24.98 → 21.65 dB, and was published).
    /// His colours are as foreign to the ring as the glass, no third view can outvote him,
    /// and he does not cross the mask's edge to be followed in: only his outline tells, the
    /// glass and the muntin continuing past it in the other view.
    #[test]
    fn of_two_views_the_one_whose_disagreement_has_an_outline_shows_the_occluder() {
        let (w, h) = (120, 100);
        let window = |x: usize, y: usize| (35..85).contains(&x) && (25..80).contains(&y);
        let wall = |x: usize, y: usize| {
            if window(x, y) {
                let frame = !(38..82).contains(&x) || !(28..77).contains(&y) || (59..62).contains(&x);
                if frame { [0.9, 0.88, 0.8] } else { [0.15, 0.2, 0.35] }
            } else if (y / 4 + x / 12).is_multiple_of(2) {
                [0.65, 0.4, 0.3]
            } else {
                [0.55, 0.35, 0.28]
            }
        };
        let in_hole = |x: usize, y: usize| (20..100).contains(&x) && (15..90).contains(&y);
        // The keyframe's own occluder, a tree, fills the hole.
        let key: Vec<[f32; 3]> = (0..w * h)
            .map(|i| if in_hole(i % w, i / w) { [0.1, 0.5, 0.15] } else { wall(i % w, i / w) })
            .collect();
        let (hole, need, blocked) = region(w, h, in_hole);
        let person = |x: usize, y: usize| -> Option<[f32; 3]> {
            if (52..66).contains(&x) && (35..55).contains(&y) {
                Some([0.55, 0.55, 0.3])
            } else if (54..64).contains(&x) && (55..75).contains(&y) {
                Some([0.12, 0.14, 0.3])
            } else {
                None
            }
        };
        let clean: Vec<[f32; 3]> = (0..w * h).map(|i| wall(i % w, i / w)).collect();
        let passer_by: Vec<[f32; 3]> =
            (0..w * h).map(|i| person(i % w, i / w).unwrap_or_else(|| wall(i % w, i / w))).collect();
        let ok = vec![true; w * h];
        let on_him: Vec<usize> = (0..w * h).filter(|&i| person(i % w, i / w).is_some()).collect();
        let region =
            KeyRegion { width: w, height: h, key: &key, hole: &hole, need: &need, blocked: &blocked };
        let mean = |m: &OcclusionMap, v: usize| {
            on_him.iter().map(|&i| m.occluded[v][i]).sum::<f32>() / on_him.len() as f32
        };
        for (clean_view, views) in [
            (0, [(clean.as_slice(), ok.as_slice()), (passer_by.as_slice(), ok.as_slice())]),
            (1, [(passer_by.as_slice(), ok.as_slice()), (clean.as_slice(), ok.as_slice())]),
        ] {
            let input = RegionInput { region, views: &views, diagonal: 156.0 };
            let params = OcclusionParams::default();
            let m = occlusion_map(&input, &params);
            let (his, past) = (mean(&m, 1 - clean_view), mean(&m, clean_view));
            assert!(his > params.cut, "the passer-by's view at {his:.2} where he stands");
            assert!(past < 0.2, "the view past him at {past:.2}");
            // The case tests the outline: without it the two are not told apart.
            let blind = occlusion_map(&input, &OcclusionParams { w_outline: 0.0, ..params.clone() });
            let (his, past) = (mean(&blind, 1 - clean_view), mean(&blind, clean_view));
            assert!(
                his < params.cut && his - past < 0.3,
                "told apart without the outline: {his:.2} against {past:.2}"
            );
        }
    }

    /// Two clean views of a wall with dark panels, one six pixels off (parallax, a poor
    /// registration): they disagree grossly where a panel moved, and in each such area both
    /// show a panel's edge and the wall, so neither is made an occluder by an outline.
    #[test]
    fn a_misregistered_view_has_no_outline() {
        let (w, h) = (100, 80);
        let wall = |x: f32, y: f32| {
            if x.rem_euclid(30.0) < 12.0 && y.rem_euclid(30.0) < 12.0 {
                [0.2, 0.22, 0.3]
            } else {
                [0.7, 0.6, 0.5]
            }
        };
        let in_hole = |x: usize, y: usize| (20..80).contains(&x) && (15..65).contains(&y);
        let (hole, _, _) = region(w, h, in_hole);
        let a: Vec<[f32; 3]> = (0..w * h).map(|i| wall((i % w) as f32, (i / w) as f32)).collect();
        let b: Vec<[f32; 3]> = (0..w * h).map(|i| wall((i % w) as f32 + 6.0, (i / w) as f32 + 4.0)).collect();
        let ok = vec![true; w * h];
        let params = OcclusionParams::default();
        let blurred: Vec<Vec<[f32; 3]>> =
            [&a, &b].iter().map(|v| box_blur(v, &ok, w, h, params.blur_radius)).collect();
        let gross = (0..w * h)
            .filter(|&i| hole[i] && dist(blurred[0][i], blurred[1][i]) > params.seed_distance)
            .count();
        assert!(gross > 500, "the views hardly disagree ({gross} pixels): the case tests nothing");
        let raw = [(a.as_slice(), ok.as_slice()), (b.as_slice(), ok.as_slice())];
        let valid = [ok.as_slice(), ok.as_slice()];
        let e = outlines(&blurred, &raw, &valid, &hole, &vec![2.0; w * h], &[1.0, 1.0], w, h, 0, &params);
        let most = e.iter().flatten().fold(0.0f32, |m, x| m.max(x.abs()));
        assert!(most < 0.3, "an outline found in a misregistration: evidence {most:.2}");
    }

    #[test]
    fn a_view_showing_the_keyframes_occluder_is_occluded_and_a_clean_one_is_not() {
        // A grey-brown wall with stripes; the keyframe has a green square in the middle.
        let (w, h) = (40, 40);
        let wall =
            |x: usize, _y: usize| if (x / 3).is_multiple_of(2) { [0.6, 0.45, 0.35] } else { [0.5, 0.4, 0.3] };
        let in_sq = |x: usize, y: usize| (14..26).contains(&x) && (14..26).contains(&y);
        let key: Vec<[f32; 3]> = (0..w * h)
            .map(|i| if in_sq(i % w, i / w) { [0.1, 0.6, 0.1] } else { wall(i % w, i / w) })
            .collect();
        let (hole, need, blocked) = region(w, h, |x, y| (12..28).contains(&x) && (12..28).contains(&y));
        let clean: Vec<[f32; 3]> = (0..w * h).map(|i| wall(i % w, i / w)).collect();
        let same = key.clone();
        let ok = vec![true; w * h];
        let views = [(clean.as_slice(), ok.as_slice()), (same.as_slice(), ok.as_slice())];
        let region =
            KeyRegion { width: w, height: h, key: &key, hole: &hole, need: &need, blocked: &blocked };
        let input = RegionInput { region, views: &views, diagonal: 57.0 };
        let m = occlusion_map(&input, &OcclusionParams::default());
        let c = 20 * w + 20;
        assert!(m.occluded[0][c] < 0.3, "clean view {}", m.occluded[0][c]);
        assert!(m.occluded[1][c] > 0.7, "the view with the keyframe's occluder {}", m.occluded[1][c]);
    }
}
