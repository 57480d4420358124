//! The whole alignment pipeline on rendered scenes whose true homography is known: hard
//! camera motion, exposure change, noise, and 40 % outliers among the matches (issue 2).

use clearview::align::{AlignParams, Frame, align_from_matches, putative_matches};
use clearview::geometry::{Correspondence, Homography};
use clearview::imaging::RgbF32;
use clearview::imaging::convert::luminance;
use clearview::synth;
use nalgebra::Point2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const WIDTH: usize = 640;
const HEIGHT: usize = 480;

/// One case: the keyframe, a view of the same facade and the true keyframe → view map.
struct Case {
    key: RgbF32,
    view: RgbF32,
    truth: Homography,
}

/// A facade larger than the frame, the keyframe looking at its middle, the view through a
/// random camera motion within the bounds: rotation up to 30°, out-of-plane tilt
/// up to 35°, scale 0.7–1.4, exposure ±25 %, noise.
fn case(seed: u64) -> Case {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let scene = synth::facade(WIDTH * 2, HEIGHT * 2, seed);
    let centre = Homography::translation(WIDTH as f64 / 2.0, HEIGHT as f64 / 2.0);
    let key = synth::render_view(&scene, &centre, WIDTH, HEIGHT, [0.5; 3]);
    let truth =
        synth::random_homography(&mut rng, WIDTH, HEIGHT, 30f64.to_radians(), 35f64.to_radians(), (0.7, 1.4));
    let view_to_scene = centre.after(&truth.inverse().expect("regular"));
    let mut view = synth::render_view(&scene, &view_to_scene, WIDTH, HEIGHT, [0.5; 3]);
    let gain = rng.random_range(0.75..1.25f32);
    synth::expose(&mut view, gain, rng.random_range(-0.03..0.03f32));
    synth::add_noise(&mut view, 0.01, seed ^ 0x5eed);
    Case { key, view, truth }
}

/// The putative matches with wrong pairs added (each keyframe corner paired with another
/// match's view corner, as a bad descriptor match would) until outliers, counted against
/// the truth, make up `share` of them. Returns the matches and the share reached.
fn with_outliers(
    putative: &[Correspondence],
    truth: &Homography,
    share: f64,
    rng: &mut ChaCha8Rng,
) -> (Vec<Correspondence>, f64) {
    let is_outlier = |c: &Correspondence| c.residual(truth) > 3.0;
    let mut out = putative.to_vec();
    let inliers = out.iter().filter(|c| !is_outlier(c)).count();
    let target_total = (inliers as f64 / (1.0 - share)).ceil() as usize;
    while out.len() < target_total {
        let a = putative[rng.random_range(0..putative.len())];
        let b = putative[rng.random_range(0..putative.len())];
        let wrong = Correspondence::new(a.key, b.view);
        if is_outlier(&wrong) {
            out.push(wrong);
        }
    }
    let reached = out.iter().filter(|c| is_outlier(c)).count() as f64 / out.len() as f64;
    (out, reached)
}

/// The keyframe region that the view shows: the frame clipped by the view's outline
/// mapped back through `truth` (Sutherland–Hodgman against a convex quadrilateral).
fn overlap_polygon(truth: &Homography) -> Vec<Point2<f64>> {
    let inv = truth.inverse().expect("regular");
    let (w, h) = ((WIDTH - 1) as f64, (HEIGHT - 1) as f64);
    let frame = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)].map(|(x, y)| Point2::new(x, y));
    let outline: Vec<Point2<f64>> =
        frame.iter().map(|&p| inv.apply(p).expect("view corner in front")).collect();
    // Orientation of the outline, so "inside" is the same side for every edge.
    let area2: f64 = (0..4)
        .map(|i| {
            let (p, q) = (outline[i], outline[(i + 1) % 4]);
            p.x * q.y - q.x * p.y
        })
        .sum();
    let side = |a: Point2<f64>, b: Point2<f64>, p: Point2<f64>| area2.signum() * ((b - a).perp(&(p - a)));
    let mut poly: Vec<Point2<f64>> = frame.to_vec();
    for i in 0..4 {
        let (a, b) = (outline[i], outline[(i + 1) % 4]);
        let input = std::mem::take(&mut poly);
        for j in 0..input.len() {
            let (p, q) = (input[j], input[(j + 1) % input.len()]);
            let (sp, sq) = (side(a, b, p), side(a, b, q));
            if sp >= 0.0 {
                poly.push(p);
            }
            if (sp >= 0.0) != (sq >= 0.0) {
                let t = sp / (sp - sq);
                poly.push(p + (q - p) * t);
            }
        }
    }
    poly
}

/// Mean distance between where `h` and `truth` send the corners of the keyframe region the
/// view shows. When the view sees the whole keyframe these are the frame's corners and
/// this is the usual mean corner error; when it sees only part of it (a 1.4× zoom with a
/// 35° tilt can leave 10 % of the frame in view), the frame's corners lie far outside
/// anything either image shows and their error measures extrapolation, not alignment.
fn overlap_corner_error(h: &Homography, truth: &Homography) -> f64 {
    let poly = overlap_polygon(truth);
    let errors: Vec<f64> =
        poly.iter().filter_map(|&p| Some((h.apply(p)? - truth.apply(p)?).norm())).collect();
    if errors.is_empty() { f64::INFINITY } else { errors.iter().sum::<f64>() / errors.len() as f64 }
}

#[test]
fn recovers_95_percent_of_200_hard_scenes_within_half_a_pixel_with_40_percent_outliers() {
    let params = AlignParams::default();
    let mut rng = ChaCha8Rng::seed_from_u64(2026);
    let mut recovered = 0;
    let mut misses = Vec::new();
    let mut shares = Vec::new();
    let mut worst_accepted = 0.0f64;
    const CASES: u64 = 200;
    for seed in 0..CASES {
        let c = case(seed);
        let key = Frame::new(luminance(&c.key), &params);
        let view = Frame::new(luminance(&c.view), &params);
        let putative = putative_matches(&key, &view, &params);
        let (matches, share) = with_outliers(&putative, &c.truth, 0.4, &mut rng);
        shares.push(share);
        let a = align_from_matches(&key, &view, &params, &matches);
        let (err, frame_err) = a.homography.map_or((f64::INFINITY, f64::INFINITY), |h| {
            (overlap_corner_error(&h, &c.truth), h.mean_corner_error(&c.truth, WIDTH, HEIGHT))
        });
        worst_accepted = if a.accepted() { worst_accepted.max(err) } else { worst_accepted };
        if a.accepted() && err <= 0.5 {
            recovered += 1;
        } else {
            let why = a.rejection.map_or("accepted".into(), |r| r.to_string());
            misses.push(format!(
                "seed {seed}: overlap corner error {err:.3} px, frame corner error {frame_err:.3} px, {why}"
            ));
        }
    }
    let min_share = shares.iter().copied().fold(1.0, f64::min);
    println!(
        "recovered {recovered} of {CASES}; outlier share at least {min_share:.2}; worst accepted error {worst_accepted:.3} px"
    );
    for m in &misses {
        println!("  {m}");
    }
    assert!(
        worst_accepted <= 0.5,
        "a view was accepted {worst_accepted:.3} px off: a wrong H corrupts a fill"
    );
    assert!(min_share >= 0.4 - 1e-9, "a case had only {min_share:.2} outliers");
    assert!(
        recovered * 100 >= 95 * CASES as usize,
        "recovered {recovered} of {CASES}:\n{}",
        misses.join("\n")
    );
}

/// A scene against noise: nothing in common, so nothing may be accepted.
#[test]
fn a_scene_against_random_noise_is_rejected() {
    let params = AlignParams::default();
    let c = case(7);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let noise = RgbF32::from_fn(WIDTH, HEIGHT, |_, _| {
        let v = rng.random_range(0.0..1.0f32);
        [v, v, v]
    });
    let key = Frame::new(luminance(&c.key), &params);
    let other = Frame::new(luminance(&noise), &params);
    let a = clearview::align::align(&key, &other, &params, None);
    assert!(!a.accepted(), "noise was accepted: {a:?}");
}

/// The scale and roll search runs when the plain path refuses; on the two scenes whose
/// repeating facade aliases a model by one period (seeds 4 and 178: 392 and 196 px off
/// before the race), what it finds must not be accepted either. Scene 4's search found a
/// ×1.4 candidate 399 px off on 47 points, where the plain model had matched 80.
#[test]
fn the_scale_and_roll_search_accepts_no_aliased_facade() {
    let params = AlignParams::default();
    for seed in [4u64, 178] {
        let c = case(seed);
        let key = Frame::new(luminance(&c.key), &params);
        let view = Frame::new(luminance(&c.view), &params);
        let a = clearview::align::align(&key, &view, &params, None);
        let err = a.homography.map(|h| overlap_corner_error(&h, &c.truth));
        assert!(
            !a.accepted() || err.is_some_and(|e| e < 1.0),
            "scene {seed} accepted {err:?} px off (searched {:?})",
            a.searched
        );
    }
}
