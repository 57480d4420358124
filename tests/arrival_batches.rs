//! Issues 12 and 17: a session's views may be handled one at a time (`clearview run`, a
//! camera uploading) or in batches (a cluster worker that finds several files waiting, a
//! restart). Wherever the publish rule keeps a result, it must be the better one: the last
//! published result may not fall more than the issues' 0.5 dB (masked PSNR against the
//! truth) below the fill of all the views at once, whatever the batches were.

mod common;
mod daemon_common;

use clearview::imaging::RgbF32;
use clearview::imaging::metrics::masked_psnr;
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
