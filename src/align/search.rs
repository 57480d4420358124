//! The scale and roll search: what alignment tries when the plain pipeline's descriptors
//! find no common viewpoint (issue 13).
//!
//! The oriented, scale-normalised patches of [`crate::features::descriptor`] hold over
//! moderate zoom and roll, but at a zoom of 4 the only corners with counterparts are the
//! keyframe's few coarse ones, and their per-corner orientations scatter (bark 1→6: 22°
//! median disagreement, a quarter beyond 60°; 4–5 correct matches of 41). So when the
//! plain path fails, the pair is brought to one scale and orientation instead. For each
//! candidate similarity (scales `2^(k/2)`, ×0.25..×4, and 16 equally spaced rolls) the two
//! images are resampled to one scale of the scene (the side that shows it smaller enlarged
//! up to ×2, as SIFT doubles its base image, the other shrunk), Harris corners are
//! detected afresh on them (so the keyframe's coarse scale gets a full corner budget), and
//! their patches are sampled *at the candidate's roll* (the keyframe's upright, the
//! view's turned by it), not at each corner's own unstable orientation. Each candidate is
//! scored by the matches that agree on one similarity close to it, and the best two go
//! through the unchanged pipeline ([`super::align_from_matches`]: MSAC, the race of
//! hypotheses, guided matching at full resolution, the verdict), with their matches
//! carried back to the original images' pixels. When a candidate's matches are too few
//! for a homography of their own, its similarity starts the guided fit, and the two
//! picks' fits race as the plain path's hypotheses do, under the same verdict and floors.
//!
//! It runs only when the plain path refuses a view (and not for a repeating pattern), so
//! views accepted today cost nothing more.

use nalgebra::Point2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use super::{AlignParams, Alignment, Frame, Rejection, align_from_matches, touches_hole};
use crate::features::{
    Corner, DescriptorParams, HarrisParams, Keypoint, descriptor, harris, match_descriptors,
};
use crate::geometry::homography::similarity_lsq;
use crate::geometry::{Correspondence, Homography};
use crate::imaging::pyramid::{Pyramid, scale};

/// Parameters of the scale and roll search.
#[derive(Debug, Clone, PartialEq)]
pub struct SearchParams {
    /// Run it at all (when the plain path fails).
    pub enabled: bool,
    /// Each resampled image has at most this many pixels.
    pub max_pixels: usize,
    /// Scales key → view tried: `2^(k/2)` for `k` in `-scale_steps..=scale_steps`
    /// (4: ×0.25..×4).
    pub scale_steps: i32,
    /// Rolls tried, equally spaced over the full turn.
    pub rolls: usize,
    /// Corners detected on the finest level of each resampled image.
    pub corners: usize,
    /// The side that shows the scene smaller is enlarged at most this much.
    pub max_enlarge: f64,
    /// A candidate needs this many descriptor matches agreeing on one similarity close to
    /// it to be tried.
    pub min_score: usize,
    /// The best candidates (by score, distinct similarities) handed to the pipeline.
    pub tries: usize,
    /// Agreement with a candidate's similarity, in pixels of the resampled images.
    pub threshold_px: f64,
}

impl Default for SearchParams {
    fn default() -> Self {
        Self {
            enabled: true,
            max_pixels: 250_000,
            scale_steps: 4,
            rolls: 16,
            corners: 800,
            max_enlarge: 2.0,
            min_score: 8,
            tries: 2,
            threshold_px: 4.0,
        }
    }
}

/// What the search found for an accepted view: the candidate scale and roll (key → view).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Searched {
    pub scale: f64,
    /// Radians, counter-clockwise in a y-down image (the roll of the keyframe's content
    /// as seen in the view).
    pub roll: f64,
    /// Matches agreeing on the candidate's similarity.
    pub score: usize,
}

/// One side resampled: its pyramid and corners, detected once; described upright or
/// turned by each roll tried.
struct Resampled {
    /// Original pixels → resampled pixels (a scaling).
    factor: f64,
    pyramid: Pyramid,
    /// Corners per detection level.
    corners: Vec<Vec<Corner>>,
}

/// Described corners of a [`Resampled`] image, in resampled pixels.
struct Described {
    keypoints: Vec<Keypoint>,
    descriptors: Vec<descriptor::Descriptor>,
}

/// Which image a spec resamples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Side {
    Key,
    View,
}

/// A candidate similarity: the resampled images (indices into the built ones) and the
/// roll the view's patches are turned by.
struct Candidate {
    scale: f64,
    roll: usize,
    key: usize,
    view: usize,
}

/// Tries the scale and roll search for a pair the plain path refused; `None` when no
/// candidate is accepted by the pipeline's own verdict.
pub(super) fn rescue(key: &Frame, view: &Frame, params: &AlignParams) -> Option<Alignment> {
    let sp = &params.search;
    if !sp.enabled || sp.rolls == 0 {
        return None;
    }
    let budget = |f: &Frame| (sp.max_pixels as f64 / (f.width * f.height) as f64).sqrt().min(1.0);
    let (bk, bv) = (budget(key), budget(view));
    let mut specs: Vec<(Side, f64)> = Vec::new();
    let mut spec_index = |side: Side, factor: f64| -> usize {
        if let Some(i) = specs.iter().position(|&(s, f)| s == side && (f - factor).abs() < 1e-9) {
            return i;
        }
        specs.push((side, factor));
        specs.len() - 1
    };
    let mut candidates = Vec::new();
    for k in -sp.scale_steps..=sp.scale_steps {
        let scale = 2f64.powf(k as f64 / 2.0);
        // Both images are brought to one scale of the scene: the side that shows it
        // smaller is enlarged (at most `max_enlarge`, as SIFT doubles its base image, so
        // that its finest detail is described at the other side's coarse scale), the other
        // shrunk; each starts from its pixel budget.
        let (fk, fv) = if scale <= 1.0 {
            let fv = bv * (1.0 / scale).min(sp.max_enlarge);
            let fk = scale * fv;
            if fk > bk { (bk, bk / scale) } else { (fk, fv) }
        } else {
            let fk = bk * scale.min(sp.max_enlarge);
            let fv = fk / scale;
            if fv > bv { (bv * scale, bv) } else { (fk, fv) }
        };
        let (ki, vi) = (spec_index(Side::Key, fk), spec_index(Side::View, fv));
        for roll in 0..sp.rolls {
            candidates.push(Candidate { scale, roll, key: ki, view: vi });
        }
    }
    let built: Vec<Resampled> = specs
        .par_iter()
        .map(|&(side, factor)| detect(if side == Side::Key { key } else { view }, factor, params))
        .collect();
    // The keyframe's patches upright, the view's turned by each roll.
    let keys: Vec<Option<Described>> = specs
        .par_iter()
        .enumerate()
        .map(|(i, &(side, _))| (side == Side::Key).then(|| describe_at(&built[i], Some(key), 0.0, params)))
        .collect();
    let views: Vec<Vec<Option<Described>>> = specs
        .par_iter()
        .enumerate()
        .map(|(i, &(side, _))| {
            (0..sp.rolls)
                .map(|r| {
                    (side == Side::View)
                        .then(|| describe_at(&built[i], None, roll_angle(r, sp.rolls), params))
                })
                .collect()
        })
        .collect();
    let scored: Vec<(usize, Vec<Correspondence>, Option<Homography>)> = candidates
        .par_iter()
        .map(|c| {
            let (k, v) = (
                keys[c.key].as_ref().expect("a key side"),
                views[c.view][c.roll].as_ref().expect("a view side"),
            );
            score(k, v, built[c.key].factor, built[c.view].factor, c, params)
        })
        .collect();
    let mut order: Vec<usize> = (0..candidates.len()).filter(|&i| scored[i].0 >= sp.min_score).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(scored[i].0), i));
    // The best candidates with distinct similarities.
    let mut picks: Vec<(usize, Homography)> = Vec::new();
    for i in order {
        if picks.len() >= sp.tries.max(1) {
            break;
        }
        let Some(sim) = scored[i].2 else { continue };
        if picks.iter().all(|(_, t)| super::maps_differ(t, &sim, key.detect_octave + 1, key, view)) {
            picks.push((i, sim));
        }
    }
    // 1. Each pick's matches through the unchanged pipeline: its own MSAC, race of
    //    hypotheses and verdict.
    let mut fits = Vec::new();
    for &(i, sim) in &picks {
        let c = &candidates[i];
        let putative = scored[i].1.clone();
        // The matches' positions are as good as the resampled images' pixels: the coarse
        // threshold, in view pixels, grows with the view's shrink factor.
        let detect_px = (1u32 << key.detect_octave) as f64;
        let mut p = params.clone();
        p.coarse.threshold_px =
            params.coarse.threshold_px * (1.0 / built[c.view].factor / detect_px).max(1.0);
        let a = align_from_matches(key, view, &p, &putative);
        if a.accepted() {
            return Some(found(a, c, scored[i].0, sp.rolls));
        }
        // Too few matches for a homography of their own (bark 1→6: 11 of 21 agree, 12
        // needed): the candidate's similarity (least squares on the matches that agree with
        // it) starts the guided fit instead.
        if let Ok(f) = super::fit(key, view, params, sim) {
            fits.push((i, f, putative));
        }
    }
    // 2. The picks' guided fits race as the plain path's hypotheses do: the best supported
    //    is accepted on the strict floor, or on the lower one when no other pick comes
    //    close with other places for the same points and the descriptor matches of its
    //    candidate agree with it.
    let best = (0..fits.len()).max_by_key(|&j| (fits[j].1.inliers.len(), std::cmp::Reverse(j)))?;
    let rival = fits
        .iter()
        .enumerate()
        .filter(|&(j, (_, f, _))| {
            j != best
                && super::models_differ(&fits[best].1, f, key, view)
                && super::claim_same_points(&fits[best].1, f)
        })
        .map(|(_, (_, f, _))| f.inliers.len())
        .max()
        .unwrap_or(0);
    let (i, f, putative) = fits.swap_remove(best);
    let tol = super::coarse_threshold_sq(params, key);
    let in_view: Vec<&Correspondence> =
        putative.iter().filter(|c| super::lands_inside(&f.h, c.key, view)).collect();
    let agreement =
        in_view.iter().filter(|c| c.residual_sq(&f.h) <= tol).count() as f64 / in_view.len().max(1) as f64;
    let a = f.into_alignment_with_rival(params, rival, agreement, putative.len());
    a.accepted().then(|| found(a, &candidates[i], scored[i].0, sp.rolls))
}

/// An accepted alignment marked with the candidate that found it.
fn found(mut a: Alignment, c: &Candidate, score: usize, rolls: usize) -> Alignment {
    a.searched = Some(Searched { scale: c.scale, roll: roll_angle(c.roll, rolls) as f64, score });
    a
}

/// The `r`-th of `rolls` angles over the full turn, radians.
fn roll_angle(r: usize, rolls: usize) -> f32 {
    std::f32::consts::TAU * r as f32 / rolls as f32
}

/// Whether the plain path's refusal leaves room for a scale and roll the descriptors
/// missed. A repeating pattern is refused whatever the scale.
pub(super) fn worth_searching(a: &Alignment) -> bool {
    !a.accepted() && !matches!(a.rejection, Some(Rejection::Ambiguous { .. }))
}

/// The frame's image scaled by `factor` (shrunk from the octave that suits it, or
/// enlarged from full resolution), its half-octave pyramid and Harris corners, with the
/// budget of [`SearchParams::corners`] on the finest level as [`Frame::new`] does.
fn detect(frame: &Frame, factor: f64, params: &AlignParams) -> Resampled {
    let octave = ((1.0 / factor).log2().floor().max(0.0) as usize).min(frame.octaves.len() - 1);
    let rest = (factor * (1u32 << octave) as f64) as f32;
    let img = if (rest - 1.0).abs() < 1e-6 {
        frame.octaves[octave].clone()
    } else {
        scale(&frame.octaves[octave], rest)
    };
    // `scale` maps x_out = x_in · rest; the octave x_o = x / 2^o: together x · factor
    // (up to the rounding of `rest`, which the factor below carries).
    let factor = rest as f64 / (1u32 << octave) as f64;
    let pyramid = Pyramid::half_octaves(img, params.pyramid_levels, 24);
    let corners = (0..pyramid.levels.len().saturating_sub(2))
        .map(|level| {
            let budget = (params.search.corners as f32 / pyramid.scales[level]).round() as usize;
            let hp = HarrisParams { max_corners: budget.max(16), ..params.harris.clone() };
            harris(&pyramid.levels[level], &hp)
        })
        .collect();
    Resampled { factor, pyramid, corners }
}

/// The corners of `r` described with patches turned by `roll`; on the keyframe (`key`)
/// those whose Harris window touches its mask are left out, as [`Frame::set_mask`] does.
fn describe_at(r: &Resampled, key: Option<&Frame>, roll: f32, params: &AlignParams) -> Described {
    let dp = DescriptorParams { upright: true, roll, ..params.descriptor.clone() };
    let mut keypoints = Vec::new();
    let mut descriptors = Vec::new();
    for (level, corners) in r.corners.iter().enumerate() {
        for (kp, d) in descriptor::describe(&r.pyramid, level, corners, &dp) {
            if let Some(frame) = key
                && let Some(mask) = &frame.mask
            {
                let orig = Keypoint { x: kp.x / r.factor as f32, y: kp.y / r.factor as f32, ..kp };
                if touches_hole(mask, &orig, 3.0 * frame.harris_sigma * kp.scale / r.factor as f32) {
                    continue;
                }
            }
            keypoints.push(kp);
            descriptors.push(d);
        }
    }
    Described { keypoints, descriptors }
}

/// Scores a candidate: its descriptor matches (in original pixels) and how many of them
/// agree on one similarity close to the candidate's (2-point RANSAC in the resampled
/// images, where the candidate is the identity up to a shift), with that similarity
/// carried back to the original pixels.
fn score(
    key: &Described,
    view: &Described,
    key_factor: f64,
    view_factor: f64,
    c: &Candidate,
    params: &AlignParams,
) -> (usize, Vec<Correspondence>, Option<Homography>) {
    let sp = &params.search;
    let matches = match_descriptors(&key.descriptors, &view.descriptors, &params.matching);
    let pts: Vec<(Point2<f64>, Point2<f64>)> = matches
        .iter()
        .map(|m| {
            let (a, b) = (key.keypoints[m.key], view.keypoints[m.view]);
            (Point2::new(a.x as f64, a.y as f64), Point2::new(b.x as f64, b.y as f64))
        })
        .collect();
    if pts.len() < 2 {
        return (0, Vec::new(), None);
    }
    // In the resampled images the candidate is a pure shift: the similarity found may
    // turn by half a roll step (and some) and scale by half an octave around it.
    let roll = f64::from(roll_angle(c.roll, sp.rolls));
    let max_roll = 1.5 * std::f64::consts::PI / sp.rolls as f64;
    let (min_s, max_s) = (2f64.powf(-0.5), 2f64.powf(0.5));
    let t2 = sp.threshold_px * sp.threshold_px;
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed ^ ((c.roll as u64) << 8) ^ (c.scale.to_bits() >> 20));
    let n = pts.len();
    let pairs = n * (n - 1) / 2;
    let iterations = pairs.min(MAX_PAIRS);
    let mut best = (0usize, None);
    for it in 0..iterations {
        let (i, j) = if pairs <= MAX_PAIRS {
            pair_at(it, n)
        } else {
            let i = rng.random_range(0..n);
            let mut j = rng.random_range(0..n - 1);
            if j >= i {
                j += 1;
            }
            (i, j)
        };
        let (dk, dv) = (pts[j].0 - pts[i].0, pts[j].1 - pts[i].1);
        let nk = dk.norm_squared();
        if nk < 64.0 {
            continue;
        }
        // v = a·k + b with a complex a = dv / dk.
        let (ar, ai) = ((dv.x * dk.x + dv.y * dk.y) / nk, (dv.y * dk.x - dv.x * dk.y) / nk);
        let s = (ar * ar + ai * ai).sqrt();
        if s < min_s || s > max_s || angle_between(ai.atan2(ar), roll) > max_roll {
            continue;
        }
        let b = (
            pts[i].1.x - (ar * pts[i].0.x - ai * pts[i].0.y),
            pts[i].1.y - (ai * pts[i].0.x + ar * pts[i].0.y),
        );
        let count = pts
            .iter()
            .filter(|(k, v)| {
                let (px, py) = (ar * k.x - ai * k.y + b.0, ai * k.x + ar * k.y + b.1);
                (px - v.x).powi(2) + (py - v.y).powi(2) <= t2
            })
            .count();
        if count > best.0 {
            best = (count, Some([[ar, -ai, b.0], [ai, ar, b.1], [0.0, 0.0, 1.0]]));
        }
    }
    // Least squares on the agreeing matches.
    if let Some(m) = best.1 {
        let inl: Vec<&(Point2<f64>, Point2<f64>)> = pts
            .iter()
            .filter(|(k, v)| {
                let (px, py) =
                    (m[0][0] * k.x + m[0][1] * k.y + m[0][2], m[1][0] * k.x + m[1][1] * k.y + m[1][2]);
                (px - v.x).powi(2) + (py - v.y).powi(2) <= t2
            })
            .collect();
        best.1 = similarity_lsq(&inl).or(best.1);
    }
    let (kt, vf) = (Homography::scaling(key_factor), Homography::scaling(1.0 / view_factor));
    let kf = Homography::scaling(1.0 / key_factor);
    let sim = best.1.and_then(Homography::from_rows).map(|m| vf.after(&m).after(&kt));
    let putative =
        pts.iter().filter_map(|(k, v)| Some(Correspondence::new(kf.apply(*k)?, vf.apply(*v)?))).collect();
    (best.0, putative, sim)
}

/// The absolute difference of two angles, in `[0, π]`.
fn angle_between(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::TAU);
    d.min(std::f64::consts::TAU - d)
}

/// Pairs of matches tried by the similarity RANSAC of [`score`] (all of them when there are
/// fewer).
const MAX_PAIRS: usize = 2000;

/// The `it`-th pair `(i, j)`, `i < j`, of `n` items in lexicographic order.
fn pair_at(mut it: usize, n: usize) -> (usize, usize) {
    for i in 0..n {
        let row = n - 1 - i;
        if it < row {
            return (i, i + 1 + it);
        }
        it -= row;
    }
    unreachable!("it < n(n-1)/2")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::convert::luminance;
    use crate::imaging::{GrayF32, bilinear, filter};
    use crate::synth;

    /// The grey image a camera sees of `scene` when `view_to_scene` maps its pixels to the
    /// scene's, blurred first by the map's shrink so that a zoomed-out view does not alias.
    fn render(scene: &GrayF32, view_to_scene: &Homography, shrink: f64, w: usize, h: usize) -> GrayF32 {
        let src = if shrink > 1.05 {
            filter::gaussian_blur(scene, (0.5 * (shrink * shrink - 1.0).sqrt()) as f32)
        } else {
            scene.clone()
        };
        GrayF32::from_fn(w, h, |x, y| {
            view_to_scene
                .apply(Point2::new(x as f64, y as f64))
                .and_then(|p| bilinear(&src, p.x as f32, p.y as f32))
                .unwrap_or(0.5)
        })
    }

    /// A view zoomed out by `1 / scale` and turned by `roll_deg` about the keyframe's
    /// centre; returns (key, view, truth key → view).
    fn pair(
        w: usize,
        scale: f64,
        roll_deg: f64,
        seed: u64,
        occluded: bool,
    ) -> (GrayF32, GrayF32, Homography) {
        let h = w * 3 / 4;
        let side = ((w as f64 / scale) * 1.3) as usize;
        let scene = luminance(&synth::facade(side, side, seed));
        let c = side as f64 / 2.0;
        let key_to_scene = Homography::translation(c - w as f64 / 2.0, c - h as f64 / 2.0);
        let (sn, cs) = (-roll_deg.to_radians()).sin_cos();
        let view_to_scene = Homography::from_rows([
            [cs / scale, -sn / scale, 0.0],
            [sn / scale, cs / scale, 0.0],
            [0.0, 0.0, 1.0],
        ])
        .unwrap();
        let view_to_scene = Homography::translation(c, c)
            .after(&view_to_scene)
            .after(&Homography::translation(-(w as f64) / 2.0, -(h as f64) / 2.0));
        let key = render(&scene, &key_to_scene, 1.0, w, h);
        let view = render(&scene, &view_to_scene, 1.0 / scale, w, h);
        let key = if occluded {
            // A tree and a car in front of the keyframe, as in the occl set (about 30 %).
            let mut rgb = crate::imaging::RgbF32::from_fn(w, h, |x, y| [key.get(x, y); 3]);
            let (wf, hf) = (w as f32, h as f32);
            synth::paint_occluder(&mut rgb, None, synth::Occluder::Tree, 0.25 * wf, 0.5 * hf, 0.8 * hf, seed);
            synth::paint_occluder(
                &mut rgb,
                None,
                synth::Occluder::Car,
                0.72 * wf,
                0.78 * hf,
                0.3 * hf,
                seed + 1,
            );
            luminance(&rgb)
        } else {
            key
        };
        let truth = view_to_scene.inverse().unwrap().after(&key_to_scene);
        (key, view, truth)
    }

    /// Median distance between where `h` and `truth` send a grid of keyframe points.
    fn error(h: &Homography, truth: &Homography) -> f64 {
        let mut d: Vec<f64> = (0..12)
            .flat_map(|j| (0..16).map(move |i| Point2::new(20.0 + 40.0 * i as f64, 20.0 + 40.0 * j as f64)))
            .map(|p| (h.apply(p).unwrap() - truth.apply(p).unwrap()).norm())
            .collect();
        d.sort_by(f64::total_cmp);
        d[d.len() / 2]
    }

    #[test]
    fn a_view_zoomed_out_three_times_and_turned_is_found_by_the_search() {
        let (key, view, truth) = pair(560, 0.3, 150.0, 7, true);
        let params = AlignParams::default();
        let (kf, vf) = (Frame::new(key, &params), Frame::new(view, &params));
        let plain = super::super::align(
            &kf,
            &vf,
            &AlignParams {
                search: SearchParams { enabled: false, ..SearchParams::default() },
                ..params.clone()
            },
            None,
        );
        assert!(!plain.accepted(), "the plain path alone accepts it: not the case tested ({plain:?})");
        let a = super::super::align(&kf, &vf, &params, None);
        assert!(a.accepted(), "{:?}", a.rejection);
        let s = a.searched.expect("found by the search");
        assert!((s.scale.log2() - 0.3f64.log2()).abs() <= 0.5, "{s:?}");
        assert!(angle_between(s.roll, 150f64.to_radians()) <= 0.3, "{s:?}");
        let e = error(&a.homography.unwrap(), &truth);
        assert!(e < 0.5, "median error {e} px");
    }

    #[test]
    fn the_search_turns_down_another_facade_at_any_scale() {
        // What the search finds is judged by the plain path's verdict: a different facade,
        // zoomed out and turned, stays refused.
        let (key, _, _) = pair(480, 1.0, 0.0, 8, false);
        let (_, other, _) = pair(480, 0.5, 120.0, 9, false);
        let params = AlignParams::default();
        let a = super::super::align(&Frame::new(key, &params), &Frame::new(other, &params), &params, None);
        assert!(!a.accepted(), "another facade accepted: {a:?}");
    }

    #[test]
    fn least_squares_similarity_recovers_a_known_one() {
        let (ar, ai, b) = (0.3f64, -0.4f64, (12.0, -7.0));
        let pts: Vec<(Point2<f64>, Point2<f64>)> = [(0.0, 0.0), (10.0, 3.0), (-4.0, 8.0), (7.0, -6.0)]
            .iter()
            .map(|&(x, y)| (Point2::new(x, y), Point2::new(ar * x - ai * y + b.0, ai * x + ar * y + b.1)))
            .collect();
        let refs: Vec<&(Point2<f64>, Point2<f64>)> = pts.iter().collect();
        let m = similarity_lsq(&refs).unwrap();
        for (got, want) in [m[0][0], m[1][0], m[0][2], m[1][2]].iter().zip([ar, ai, b.0, b.1]) {
            assert!((got - want).abs() < 1e-9, "{m:?}");
        }
        assert!((angle_between(3.0, -3.0) - (std::f64::consts::TAU - 6.0)).abs() < 1e-12);
    }
}
