//! `clearview demo`: a capture session rendered by the program itself, so a newcomer sees
//! clearview work without preparing a single file (edge layer).

use std::path::Path;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::exit;
use crate::align::{AlignParams, Frame, align};
use crate::geometry::Homography;
use crate::imaging::convert::{luminance, to_rgb8};
use crate::synth::{self, Occluder};

const WIDTH: usize = 1024;
const HEIGHT: usize = 768;
const VIEWS: usize = 5;

pub fn run(dir: &Path) -> u8 {
    if let Err(e) = std::fs::create_dir_all(dir) {
        eprintln!("clearview demo: {}: cannot create: {e}", dir.display());
        return exit::FAILURE;
    }
    // The scene is larger than a frame so the camera can move over it.
    let scene = synth::facade(WIDTH * 3 / 2, HEIGHT * 3 / 2, 2026);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let params = AlignParams::default();
    let centre = Homography::translation(WIDTH as f64 / 4.0, HEIGHT as f64 / 4.0);

    let mut key = synth::render_view(&scene, &centre, WIDTH, HEIGHT, [0.5; 3]);
    synth::paint_occluder(&mut key, None, Occluder::Tree, 380.0, 420.0, 330.0, 1);
    let key_path = dir.join("key.png");
    if let Err(e) = to_rgb8(&key).save(&key_path) {
        eprintln!("clearview demo: {}: cannot write: {e}", key_path.display());
        return exit::FAILURE;
    }
    println!("keyframe: {} (a tree stands in front of the facade)", key_path.display());
    let key_frame = Frame::new(luminance(&key), &params);

    for i in 1..=VIEWS {
        // A shot from elsewhere: the camera turned, tilted and moved.
        let key_to_view = synth::random_homography(&mut rng, WIDTH, HEIGHT, 0.15, 0.3, (0.85, 1.15));
        let view_to_scene = centre.after(&key_to_view.inverse().expect("regular"));
        let mut view = synth::render_view(&scene, &view_to_scene, WIDTH, HEIGHT, [0.5; 3]);
        let kind = [Occluder::Person, Occluder::Car, Occluder::Tree][i % 3];
        synth::paint_occluder(&mut view, None, kind, 200.0 + 130.0 * i as f32, 500.0, 260.0, 100 + i as u64);
        synth::expose(&mut view, 0.85 + 0.06 * i as f32, 0.0);
        let path = dir.join(format!("view-{i}.png"));
        if let Err(e) = to_rgb8(&view).save(&path) {
            eprintln!("clearview demo: {}: cannot write: {e}", path.display());
            return exit::FAILURE;
        }
        let start = Instant::now();
        let frame = Frame::new(luminance(&view), &params);
        let a = align(&key_frame, &frame, &params, None);
        let ms = start.elapsed().as_secs_f64() * 1e3;
        match (&a.homography, &a.rejection) {
            (Some(h), None) => println!(
                "{}: aligned in {ms:.0} ms, {} inliers, error against the truth {:.2} px",
                path.display(),
                a.inliers,
                h.mean_corner_error(&key_to_view, WIDTH, HEIGHT)
            ),
            (_, Some(r)) => println!("{}: rejected: {r}", path.display()),
            (None, None) => unreachable!("accepted without a homography"),
        }
    }
    exit::OK
}
