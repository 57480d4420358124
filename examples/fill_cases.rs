//! Writes the fill comparison cases for `bench/fill_peer.py`: per case a keyframe with
//! occluders, its mask, the occluder-free truth and the other views.
//!
//! `cargo run --release --example fill_cases -- OUT_DIR [SHARED_DATA_DIR]`
//!
//! Synthetic cases are rendered; the Oxford cases (graf, wall, leuven) paste occluders
//! into the real img1, whose clean original is then the truth.

use std::path::{Path, PathBuf};

use clearview::geometry::Homography;
use clearview::imaging::convert::{mask_to_luma8, to_rgb, to_rgb8};
use clearview::imaging::{Mask, RgbF32};
use clearview::synth::{self, Occluder};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn save_case(dir: &Path, key: &RgbF32, mask: &Mask, truth: &RgbF32, views: &[RgbF32]) {
    std::fs::create_dir_all(dir).unwrap();
    to_rgb8(key).save(dir.join("key.png")).unwrap();
    mask_to_luma8(mask).save(dir.join("mask.png")).unwrap();
    to_rgb8(truth).save(dir.join("truth.png")).unwrap();
    for (i, v) in views.iter().enumerate() {
        to_rgb8(v).save(dir.join(format!("view-{}.png", i + 1))).unwrap();
    }
    println!("{}: {} masked pixels, {} views", dir.display(), mask.hole_count(), views.len());
}

/// A rendered facade seen from `n` places; the keyframe has a tree and a car in front,
/// every view its own occluders and exposure, and noise.
fn synthetic(out: &Path, seed: u64, n: usize) {
    let (w, h) = (960, 720);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let facade = synth::facade(w * 2, h * 2, seed);
    let centre = Homography::translation(w as f64 / 2.0, h as f64 / 2.0);
    let truth = synth::render_view(&facade, &centre, w, h, [0.5; 3]);
    let mut key = truth.clone();
    let mut mask = Mask::new(w, h, 0);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 380.0, 360.0, 330.0, seed);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Car, 700.0, 600.0, 170.0, seed + 1);
    let mut views = Vec::new();
    for i in 0..n {
        let hv = synth::random_homography(&mut rng, w, h, 0.12, 0.3, (0.85, 1.15));
        let mut v = synth::render_view(&facade, &centre.after(&hv.inverse().unwrap()), w, h, [0.5; 3]);
        let kind = [Occluder::Person, Occluder::Tree, Occluder::Car][i % 3];
        let x = rng.random_range(100.0..860.0f32);
        synth::paint_occluder(
            &mut v,
            None,
            kind,
            x,
            420.0,
            rng.random_range(200.0..320.0),
            seed * 100 + i as u64,
        );
        synth::expose(&mut v, rng.random_range(0.8..1.2), rng.random_range(-0.03..0.03));
        synth::add_noise(&mut v, 0.01, seed * 1000 + i as u64);
        views.push(v);
    }
    synth::add_noise(&mut key, 0.01, seed * 7);
    save_case(&out.join(format!("synthetic-{seed}")), &key, &mask, &truth, &views);
}

/// Oxford `seq`: img1 with occluders pasted on the planar scene, views `views`.
fn oxford(out: &Path, data: &Path, seq: &str, views: &[usize], occluders: &[(Occluder, f32, f32, f32)]) {
    let dir = data.join("oxford").join(seq);
    let load = |n: usize| to_rgb(&image::open(dir.join(format!("img{n}.png"))).unwrap());
    let truth = load(1);
    let mut key = truth.clone();
    let mut mask = Mask::new(truth.width(), truth.height(), 0);
    for (i, &(kind, x, y, size)) in occluders.iter().enumerate() {
        synth::paint_occluder(&mut key, Some(&mut mask), kind, x, y, size, 50 + i as u64);
    }
    let views: Vec<RgbF32> = views.iter().map(|&n| load(n)).collect();
    save_case(&out.join(format!("oxford-{seq}")), &key, &mask, &truth, &views);
}

fn main() {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let Some(out) = args.first() else {
        eprintln!("usage: fill_cases OUT_DIR [SHARED_DATA_DIR]");
        std::process::exit(64);
    };
    let data = args.get(1).cloned().unwrap_or_else(|| PathBuf::from("../shared/data"));
    for seed in [1, 2, 3] {
        synthetic(out, seed, 5);
    }
    if data.join("oxford").is_dir() {
        // graf img1 has a real car roof along the bottom: the occluders stand on the wall.
        oxford(
            out,
            &data,
            "graf",
            &[2, 3, 4],
            &[(Occluder::Tree, 330.0, 260.0, 260.0), (Occluder::Person, 600.0, 300.0, 220.0)],
        );
        oxford(
            out,
            &data,
            "wall",
            &[2, 3, 4],
            &[(Occluder::Tree, 450.0, 330.0, 300.0), (Occluder::Car, 700.0, 560.0, 160.0)],
        );
        oxford(
            out,
            &data,
            "leuven",
            &[2, 3, 4, 5, 6],
            &[(Occluder::Person, 300.0, 330.0, 240.0), (Occluder::Car, 600.0, 470.0, 150.0)],
        );
    } else {
        eprintln!("{}: no oxford folder; only the synthetic cases were written", data.display());
    }
}
