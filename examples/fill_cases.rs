//! Writes the fill comparison cases for `bench/fill_peer.py`: per case a keyframe with
//! occluders, its mask, the occluder-free truth and the other views.
//!
//! `cargo run --release --example fill_cases -- OUT_DIR [SHARED_DATA_DIR]`
//! `cargo run --release --example fill_cases -- --large OUT_DIR` (the 12 MP command case)
//!
//! Synthetic cases are rendered (also the occlusion model's shared-occluder and non-planar
//! families, `synth::occlusion_case`); the Oxford cases (graf, wall, leuven) paste occluders
//! into the real img1, whose clean original is then the truth.

use std::path::{Path, PathBuf};

use clearview::geometry::Homography;
use clearview::imaging::convert::{mask_to_luma8, to_rgb, to_rgb8};
use clearview::imaging::{Mask, RgbF32};
use clearview::synth::{self, CaseFamily, Occluder};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[path = "common/case_dir.rs"]
mod case_dir;
use case_dir::save_case;

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

/// The 12 MP case of the command target: a 4000×3000 keyframe with trees over
/// 15 % of it and 6 views, written as JPEG (quality 92) as a camera would.
fn large(out: &Path) {
    let (w, h) = (4000, 3000);
    let facade = synth::facade(w * 5 / 4, h * 5 / 4, 40);
    let centre = Homography::translation(w as f64 / 8.0, h as f64 / 8.0);
    let truth = synth::render_view(&facade, &centre, w, h, [0.5; 3]);
    let mut key = truth.clone();
    let mut mask = Mask::new(w, h, 0);
    let target = w * h * 15 / 100;
    for (k, &(cx, cy)) in
        [(900.0, 1900.0), (2300.0, 2100.0), (3400.0, 1200.0), (1700.0, 900.0)].iter().enumerate()
    {
        if mask.hole_count() + w * h / 200 >= target {
            break;
        }
        for size in [1100.0, 900.0, 700.0, 550.0, 400.0, 300.0] {
            let (mut k2, mut m2) = (key.clone(), mask.clone());
            synth::paint_occluder(&mut k2, Some(&mut m2), Occluder::Tree, cx, cy, size, k as u64);
            if m2.hole_count() <= target + w * h / 200 || size <= 300.0 {
                (key, mask) = (k2, m2);
                break;
            }
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let dir = out.join("large-12mp");
    std::fs::create_dir_all(&dir).unwrap();
    let jpeg = |img: &RgbF32, name: &str| {
        let f = std::fs::File::create(dir.join(name)).unwrap();
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(std::io::BufWriter::new(f), 92);
        enc.encode_image(&to_rgb8(img)).unwrap();
    };
    jpeg(&key, "key.jpg");
    mask_to_luma8(&mask).save(dir.join("mask.png")).unwrap();
    for i in 0..6 {
        let hv = synth::random_homography(&mut rng, w, h, 0.05, 0.1, (0.95, 1.05));
        let mut v = synth::render_view(&facade, &centre.after(&hv.inverse().unwrap()), w, h, [0.5; 3]);
        synth::paint_occluder(
            &mut v,
            None,
            Occluder::Person,
            600.0 + 500.0 * i as f32,
            1800.0,
            900.0,
            100 + i as u64,
        );
        jpeg(&v, &format!("view-{}.jpg", i + 1));
    }
    println!(
        "{}: 4000x3000, {:.1} % masked, 6 views",
        dir.display(),
        100.0 * mask.hole_count() as f64 / (w * h) as f64
    );
}

fn main() {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    if args.first().is_some_and(|a| a == "--large") {
        let Some(out) = args.get(1) else {
            eprintln!("usage: fill_cases --large OUT_DIR");
            std::process::exit(64);
        };
        large(out);
        return;
    }
    let Some(out) = args.first() else {
        eprintln!("usage: fill_cases OUT_DIR [SHARED_DATA_DIR]");
        std::process::exit(64);
    };
    let data = args.get(1).cloned().unwrap_or_else(|| PathBuf::from("../shared/data"));
    for seed in [1, 2, 3] {
        synthetic(out, seed, 5);
    }
    // The occlusion model's families: a tree every view shows too, and a facade with a pier.
    for family in [CaseFamily::Shared, CaseFamily::NonPlanar] {
        for seed in [1, 2] {
            let c = synth::occlusion_case(family, 640, 480, 4, seed);
            save_case(&out.join(format!("{}-{seed}", family.name())), &c.key, &c.mask, &c.truth, &c.views);
        }
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
