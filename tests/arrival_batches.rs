//! Issues 12 and 17: a session's views may be handled one at a time (`clearview run`, a
//! camera uploading) or in batches (a cluster worker that finds several files waiting, a
//! restart). Wherever the publish rule keeps a result, it must be the better one: the last
//! published result may not fall more than the issues' 0.5 dB (masked PSNR against the
//! truth) below the fill of all the views at once, whatever the batches were.

mod common;
mod daemon_common;

use clearview::imaging::metrics::masked_psnr;
use clearview::imaging::{Mask, RgbF32};
use clearview::inpaint::occlusion::OcclusionParams;
use clearview::session::{Session, SessionParams};
use common::fill_in_batches;
use daemon_common::Scene;

/// Feeds `views` to a fresh session, filling after each batch (`batches` are the batch
/// sizes, in order), and returns the masked PSNR of the last published result.
fn run(scene: &Scene, views: &[RgbF32], batches: &[usize]) -> f64 {
    let mut s = Session::new(SessionParams::default());
    s.set_key("key".into(), scene.key.clone());
    s.set_mask("mask".into(), scene.mask.clone()).unwrap();
    let published = fill_in_batches(&mut s, views, batches).into_iter().filter_map(|o| o.image).next_back();
    masked_psnr(&published.expect("a published result"), &scene.truth, &scene.mask)
}

#[test]
fn views_one_by_one_or_in_batches_end_within_half_a_db_of_the_fill_of_all() {
    let mut failures = Vec::new();
    // The seeds of tests/nats_cluster.rs' sessions, and more: on the rule before the
    // near-tie margin, 702 kept a two-view result 0.94 dB below the fill of all three.
    for seed in 700..712 {
        let mut scene = Scene::new(seed);
        let views: Vec<RgbF32> = (0..3).map(|i| scene.view(i, 60.0 + 120.0 * i as f32, 40.0)).collect();
        let all = run(&scene, &views, &[3]);
        for batches in [&[1, 2][..], &[2, 1], &[1, 1, 1]] {
            let ended = run(&scene, &views, batches);
            println!("seed {seed} batches {batches:?}: {ended:.2} dB, all at once {all:.2} dB");
            if ended < all - 0.5 {
                failures.push(format!("seed {seed} batches {batches:?}: {ended:.2} dB against {all:.2}"));
            }
        }
    }
    assert!(failures.is_empty(), "ended below the fill of all views:\n{}", failures.join("\n"));
}

/// Issue 12: a second view whose passer-by stands inside the keyframe's mask, in front
/// of the facade the first view shows clear, is not copied into the published result. Two
/// views cannot outvote each other and the passer-by's colours are as foreign to the ring as
/// a window's glass; only his outline tells (`OcclusionParams::w_outline`). Per session, the
/// share of his pixels (inside the mask) that the published result gets grossly wrong (a
/// channel more than 30 levels off), after the first view and after the second: with the
/// outline, no session adds more than 15 points and the mean adds under 3 (measured: 0.9,
/// one session +12); without it, most sessions paste him back (15 of 24 add more than 5
/// points, 12 more than 15; the mean adds 30).
#[test]
fn a_second_views_passer_by_inside_the_mask_is_not_pasted_back() {
    let gross_share = |img: &RgbF32, truth: &RgbF32, at: &[(usize, usize)]| {
        let wrong = at
            .iter()
            .filter(|&&(x, y)| {
                let (p, t) = (img.get(x, y), truth.get(x, y));
                (0..3).any(|c| (p[c].clamp(0.0, 1.0) - t[c]).abs() > 30.0 / 255.0)
            })
            .count();
        wrong as f64 / at.len() as f64
    };
    // Per session, the points of his pixels the second view's result adds to the first's.
    let added = |w_outline: f32| -> Vec<f64> {
        (700..724)
            .map(|seed| {
                let mut scene = Scene::new(seed);
                let first = scene.view(0, 60.0, 40.0);
                // Somewhere across the tree's crown (most of him inside the mask).
                let kx = 165.0 + 15.0 * (seed % 5) as f32;
                let (second, footprint): (RgbF32, Mask) = scene.view_and_footprint(1, kx, 150.0, 40.0);
                let at: Vec<(usize, usize)> = (0..footprint.height())
                    .flat_map(|y| (0..footprint.width()).map(move |x| (x, y)))
                    .filter(|&(x, y)| footprint.is_hole(x, y) && scene.mask.is_hole(x, y))
                    .collect();
                assert!(at.len() > 100, "seed {seed}: only {} of his pixels in the mask", at.len());
                let mut params = SessionParams::default();
                params.fill.occlusion_model = OcclusionParams { w_outline, ..params.fill.occlusion_model.clone() };
                let mut s = Session::new(params);
                s.set_key("key".into(), scene.key.clone());
                s.set_mask("mask".into(), scene.mask.clone()).unwrap();
                let outcomes = fill_in_batches(&mut s, &[first, second], &[1, 1]);
                let one = outcomes[0].image.as_ref().expect("the first view's result");
                let two = outcomes[1].image.as_ref().unwrap_or(one);
                let (before, after) = (gross_share(one, &scene.truth, &at), gross_share(two, &scene.truth, &at));
                println!(
                    "seed {seed}, outline weight {w_outline}: {:.0} % of his {} pixels grossly wrong, then {:.0} %",
                    100.0 * before,
                    at.len(),
                    100.0 * after
                );
                100.0 * (after - before)
            })
            .collect()
    };
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let with = added(OcclusionParams::default().w_outline);
    let worst = with.iter().copied().fold(f64::MIN, f64::max);
    assert!(
        worst <= 15.0 && mean(&with) < 3.0,
        "pasted back: {worst:.0} points at worst, {:.1} on average",
        mean(&with)
    );
    // The sessions test the outline: without it he is pasted back.
    let without = added(0.0);
    let pasted = without.iter().filter(|&&a| a > 15.0).count();
    assert!(pasted >= 8, "without the outline only {pasted} of 24 sessions paste him back");
}

/// Issue 12's first target, over 60 sessions of three views arriving one by one (each with a
/// passer-by, the second's inside the mask): the sessions where a view makes the published
/// result worse by more than 0.3 dB (masked PSNR against the truth). Not yet none: 13 of 60
/// (the rest of the drops are views of the same wall copied less sharply, which the publish
/// rule cannot tell, see BENCHMARKS.md); 19 without the outline evidence. A guard that the
/// count does not grow, and the table behind BENCHMARKS.md's figures
/// (`cargo test --release --test arrival_batches seldom -- --nocapture`).
#[test]
fn views_one_by_one_seldom_make_the_published_result_worse() {
    let mut over = Vec::new();
    let (mut worst_sum, mut last_sum) = (0.0, 0.0);
    for seed in 700..760 {
        let mut scene = Scene::new(seed);
        let views: Vec<RgbF32> = (0..3).map(|i| scene.view(i, 60.0 + 120.0 * i as f32, 40.0)).collect();
        let mut s = Session::new(SessionParams::default());
        s.set_key("key".into(), scene.key.clone());
        s.set_mask("mask".into(), scene.mask.clone()).unwrap();
        let (mut current, mut worst, mut steps) = (None::<f64>, 0.0f64, Vec::new());
        for outcome in fill_in_batches(&mut s, &views, &[1, 1, 1]) {
            if let Some(img) = &outcome.image {
                let p = masked_psnr(img, &scene.truth, &scene.mask);
                worst = current.map_or(worst, |c| worst.max(c - p));
                current = Some(p);
            }
            steps.push(current.map_or("-".to_string(), |p| format!("{p:.2}")));
        }
        println!("seed {seed}: {}  worst drop {worst:.2} dB", steps.join(" → "));
        if worst > 0.3 {
            over.push(seed);
        }
        worst_sum += worst / 60.0;
        last_sum += current.expect("a published result") / 60.0;
    }
    println!(
        "{} of 60 sessions with a drop over 0.3 dB {over:?}; mean worst drop {worst_sum:.3} dB, mean last {last_sum:.3} dB",
        over.len()
    );
    assert!(over.len() <= 15, "{} of 60 sessions with a drop over 0.3 dB: {over:?}", over.len());
}
