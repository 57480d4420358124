//! How much of the other views to average into each copied pixel (pure layer).
//!
//! The fill copies one view per patch. Where the views' errors are independent of one
//! another (sensor noise, JPEG, a reflection in glass that each viewpoint sees differently,
//! a curved facade that one homography puts a pixel off in a different direction in each
//! view) an average of the views is closer to the building than any one of them; where they
//! share their error (the same blur of an oblique warp, the same misregistration) it is not,
//! and it softens what the copy had sharp. The ring of keyframe pixels around a hole says
//! which holds: there the truth is known, so the combination of the views that comes
//! closest to it is measured (least squares under "the weights sum to one, none negative":
//! the minimum-variance combination given how the views' errors correlate), and it is used
//! only as far as it clearly beats the best view alone there. The copied view keeps at least
//! the largest weight: it was chosen where the others may show an occluder.

use nalgebra::{DMatrix, DVector};

use super::{RING_MIN, RING_TRUST};

/// Parameters of the fusion (see [`super::FillParams::fuse`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FuseParams {
    /// The combination is used in full when its error on the ring is at most this share of
    /// the best view's...
    pub full_below: f64,
    /// ...not at all from this share up, and in proportion between. The copy is better than
    /// its view at the homography's prediction (each patch is the best of a local search),
    /// so a combination that gains little on the ring loses in the hole: on the Oxford wall
    /// (ring ratio 0.97) and graffiti (0.83) cases the full combination cost 0.3 and 0.9 dB,
    /// where HPatches (0.61), photo-building (0.73) and leuven (0.77) gained 0.5 to 1.9 dB.
    pub none_above: f64,
    /// A view's pixel counts less the further it is from the copied one: its weight is
    /// multiplied by `exp(-(d / gate)²)`, `d` the RGB distance (0..=√3): a last guard
    /// against an occluder the model missed.
    pub gate: f32,
    /// ...and by `(1 − p)^occlusion_power`, `p` the model's probability that the view
    /// shows an occluder there.
    pub occlusion_power: f32,
}

impl Default for FuseParams {
    fn default() -> Self {
        Self { full_below: 0.7, none_above: 0.85, gate: 1.0, occlusion_power: 2.0 }
    }
}

/// The combination [`mix`] found: per view its weight (summing to one) and how far it is
/// used (0..=1).
#[derive(Debug, Clone, PartialEq)]
pub struct Mix {
    pub weights: Vec<f32>,
    pub strength: f32,
}

/// The combination of `n` views closest to the truth on the ring, from `rows`: per ring
/// pixel, each view's error there (view − keyframe, RGB), `None` where it does not see the
/// pixel. The pixels' worst 30 % (most often a view's own occluder over the ring) are left
/// out, as for the views' expected errors; each pair's error covariance is taken over the
/// pixels both see, at least `RING_MIN` of them. `None` when fewer
/// than two views are measured, or when the combination is not used at all.
pub fn mix(rows: &[Vec<Option<[f32; 3]>>], n: usize, params: &FuseParams) -> Option<Mix> {
    let mut ranked: Vec<(f32, &Vec<Option<[f32; 3]>>)> = rows
        .iter()
        .filter(|e| e.len() == n && e.iter().filter(|x| x.is_some()).count() >= 2)
        .map(|e| (e.iter().flatten().map(|d| d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).fold(0.0, f32::max), e))
        .collect();
    if ranked.len() < RING_MIN {
        return None;
    }
    let keep = ((ranked.len() as f32 * RING_TRUST) as usize).max(1);
    ranked.select_nth_unstable_by(keep - 1, |a, b| a.0.total_cmp(&b.0));
    let mut g = DMatrix::<f64>::zeros(n, n);
    let mut count = DMatrix::<f64>::zeros(n, n);
    for (_, e) in &ranked[..keep] {
        for a in 0..n {
            let Some(ea) = e[a] else { continue };
            for b in a..n {
                let Some(eb) = e[b] else { continue };
                g[(a, b)] += f64::from(ea[0] * eb[0] + ea[1] * eb[1] + ea[2] * eb[2]);
                count[(a, b)] += 1.0;
            }
        }
    }
    for a in 0..n {
        for b in a..n {
            let c = count[(a, b)];
            g[(a, b)] = if c >= RING_MIN as f64 {
                g[(a, b)] / c
            } else if a == b {
                f64::INFINITY
            } else {
                0.0
            };
            g[(b, a)] = g[(a, b)];
        }
    }
    let mut active: Vec<usize> = (0..n).filter(|&a| g[(a, a)].is_finite()).collect();
    if active.len() < 2 {
        return None;
    }
    let ridge = 1e-3 * active.iter().map(|&a| g[(a, a)]).sum::<f64>() / active.len() as f64 + 1e-12;
    // Minimum variance under Σw = 1: w ∝ G⁻¹·1; a view with a negative weight leaves, and
    // the rest are solved again.
    let weights = loop {
        let m = active.len();
        let sub = DMatrix::from_fn(m, m, |a, b| g[(active[a], active[b])] + if a == b { ridge } else { 0.0 });
        let x = sub.lu().solve(&DVector::from_element(m, 1.0))?;
        let total: f64 = x.iter().sum();
        if !(total.is_finite() && total > 0.0) {
            return None;
        }
        let w: Vec<f64> = x.iter().map(|v| v / total).collect();
        match w.iter().enumerate().filter(|(_, v)| **v < 0.0).min_by(|a, b| a.1.total_cmp(b.1)) {
            Some((j, _)) if m > 1 => {
                active.remove(j);
            }
            _ => break w,
        }
    };
    let single = active.iter().map(|&j| g[(j, j)]).fold(f64::INFINITY, f64::min);
    let mut combined = 0.0;
    for (a, &j) in active.iter().enumerate() {
        for (b, &k) in active.iter().enumerate() {
            combined += weights[a] * weights[b] * g[(j, k)];
        }
    }
    let ratio = if single > 0.0 { combined / single } else { 1.0 };
    let span = (params.none_above - params.full_below).max(1e-9);
    let strength = ((params.none_above - ratio) / span).clamp(0.0, 1.0) as f32;
    if strength <= 0.0 {
        return None;
    }
    let mut out = vec![0.0f32; n];
    for (a, &j) in active.iter().enumerate() {
        out[j] = weights[a].max(0.0) as f32;
    }
    Some(Mix { weights: out, strength })
}

/// The fused colour of a copied pixel: `picked` (from view `from`) and the other views'
/// colours there (`others`: view, colour, occlusion probability), each weighted as [`Mix`]
/// says, times the gate and the model's doubt. The copied view counts with at least the
/// largest weight. `None` when no other view adds anything.
pub fn fuse_pixel(
    picked: [f32; 3],
    from: usize,
    others: impl IntoIterator<Item = (usize, [f32; 3], f32)>,
    mix: &Mix,
    params: &FuseParams,
) -> Option<[f32; 3]> {
    let own = mix.weights.iter().copied().fold(mix.weights[from], f32::max);
    let inv = 1.0 / (params.gate * params.gate);
    let mut sum = [own * picked[0], own * picked[1], own * picked[2]];
    let mut total = own;
    let mut added = false;
    for (u, c, p) in others {
        if u == from {
            continue;
        }
        let d: f32 = (0..3).map(|k| (c[k] - picked[k]).powi(2)).sum();
        let w = mix.strength
            * mix.weights[u]
            * (-d * inv).exp()
            * (1.0 - p).clamp(0.0, 1.0).powf(params.occlusion_power);
        if w > 0.0 {
            for k in 0..3 {
                sum[k] += w * c[k];
            }
            total += w;
            added = true;
        }
    }
    (added && total > 0.0).then(|| sum.map(|s| s / total))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn noise(rng: &mut ChaCha8Rng, s: f32) -> [f32; 3] {
        [0; 3].map(|_| rng.random_range(-s..s))
    }

    #[test]
    fn independent_errors_are_averaged_in_proportion_to_their_precision() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // View 1's errors are twice view 0's: weights 4 : 1 (inverse variances), a little
        // less lopsided after the worst 30 % of pixels (mostly view 1's) are left out.
        let rows: Vec<Vec<Option<[f32; 3]>>> =
            (0..4000).map(|_| vec![Some(noise(&mut rng, 0.02)), Some(noise(&mut rng, 0.04))]).collect();
        let m = mix(&rows, 2, &FuseParams::default()).expect("a combination");
        assert!(m.weights[0] > 0.7 && m.weights[0] < 0.85, "{:?}", m.weights);
        assert!((m.weights[0] + m.weights[1] - 1.0).abs() < 1e-5, "{:?}", m.weights);
        // The combination's error is 0.7 to 0.8 of the best view's: used in part.
        assert!(m.strength > 0.0 && m.strength < 1.0, "{}", m.strength);
        let equal: Vec<Vec<Option<[f32; 3]>>> = (0..4000)
            .map(|_| {
                vec![Some(noise(&mut rng, 0.02)), Some(noise(&mut rng, 0.02)), Some(noise(&mut rng, 0.02))]
            })
            .collect();
        let m = mix(&equal, 3, &FuseParams::default()).expect("a combination");
        assert!(m.weights.iter().all(|&w| (w - 1.0 / 3.0).abs() < 0.05), "{:?}", m.weights);
        assert_eq!(m.strength, 1.0);
    }

    #[test]
    fn errors_the_views_share_are_not_averaged() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        // Both views blurred the same way: the same error, plus a little of their own.
        let rows: Vec<Vec<Option<[f32; 3]>>> = (0..4000)
            .map(|_| {
                let shared = noise(&mut rng, 0.05);
                let a = noise(&mut rng, 0.005);
                let b = noise(&mut rng, 0.005);
                vec![Some([0, 1, 2].map(|k| shared[k] + a[k])), Some([0, 1, 2].map(|k| shared[k] + b[k]))]
            })
            .collect();
        assert_eq!(mix(&rows, 2, &FuseParams::default()), None);
    }

    #[test]
    fn a_view_that_does_not_see_the_ring_gets_no_weight() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let rows: Vec<Vec<Option<[f32; 3]>>> =
            (0..4000).map(|_| vec![Some(noise(&mut rng, 0.02)), None, Some(noise(&mut rng, 0.02))]).collect();
        let m = mix(&rows, 3, &FuseParams::default()).expect("a combination");
        assert_eq!(m.weights[1], 0.0);
        assert!((m.weights[0] - 0.5).abs() < 0.05 && (m.weights[2] - 0.5).abs() < 0.05, "{:?}", m.weights);
        // Too few pixels: nothing measured.
        assert_eq!(mix(&rows[..10], 3, &FuseParams::default()), None);
    }

    #[test]
    fn the_copied_view_keeps_the_largest_weight_and_doubtful_pixels_count_less() {
        let m = Mix { weights: vec![0.2, 0.8], strength: 1.0 };
        let p = FuseParams::default();
        // View 0 was copied: it counts as much as view 1 (0.8 each).
        let out = fuse_pixel([0.2; 3], 0, [(1, [0.4; 3], 0.0)], &m, &p).expect("fused");
        let expect = (0.2 + 0.4 * (-0.12f32).exp()) / (1.0 + (-0.12f32).exp());
        assert!((out[0] - expect).abs() < 1e-5, "{out:?} against {expect}");
        // A view the model is sure shows an occluder adds nothing.
        assert_eq!(fuse_pixel([0.2; 3], 0, [(1, [0.4; 3], 1.0)], &m, &p), None);
        // Half strength: half the weight.
        let half = Mix { strength: 0.5, ..m.clone() };
        let out = fuse_pixel([0.2; 3], 0, [(1, [0.4; 3], 0.0)], &half, &p).expect("fused");
        let w = 0.5 * (-0.12f32).exp();
        assert!((out[0] - (0.2 + 0.4 * w) / (1.0 + w)).abs() < 1e-5);
    }
}
