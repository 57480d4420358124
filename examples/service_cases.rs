//! Writes the cases of `bench/service_eval.py` (views arriving one by one in the service):
//! per case a keyframe with occluders, the mask a person paints over them, the
//! occluder-free truth and the other views, in the order they arrive.
//!
//! `cargo run --release --example service_cases -- OUT_DIR [--seed N] [--data DIR] [--views N]`
//!
//! Families (the seed moves every occluder and every generated viewpoint, so a new seed
//! is a case never seen):
//! - `planar`, `shared`, `nonplanar`: `synth::occlusion_case` (640×480, 4 views, or N: a
//!   session whose views outnumber those a view's own occluders are judged against);
//! - `oxford-*` (graf, wall, leuven), `hpatches-*` (v_churchill, v_wormhole) and
//!   `photo-*` (multiview/parapano_building, parapano_ece, parapano_hunt, vlfeat_roofs):
//!   a real photograph with generated occluders pasted on it (the clean photograph is the
//!   truth), the set's other photographs as the views, with whatever they show.

use std::path::{Path, PathBuf};

use clearview::imaging::convert::to_rgb;
use clearview::imaging::{Mask, RgbF32};
use clearview::synth::{self, CaseFamily, Occluder};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[path = "common/case_dir.rs"]
mod case_dir;
use case_dir::save_case;

/// The photograph `key` of `set` with two or three occluders pasted at places drawn from
/// `seed` (the central part of the frame, where a wall is), and `views` as they are.
fn photo(out: &Path, name: &str, set: &Path, key: &str, views: &[&str], seed: u64) {
    let load = |f: &str| to_rgb(&image::open(set.join(f)).unwrap());
    let truth = load(key);
    let (w, h) = (truth.width() as f32, truth.height() as f32);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
    let mut img = truth.clone();
    let mut painted = Mask::new(truth.width(), truth.height(), 0);
    let s = w.min(h);
    let kinds = [Occluder::Tree, [Occluder::Person, Occluder::Car][(seed % 2) as usize], Occluder::Person];
    for (i, &kind) in kinds.iter().enumerate().take(2 + (seed % 2) as usize) {
        let size = match kind {
            Occluder::Tree => rng.random_range(0.3..0.42) * s,
            Occluder::Person => rng.random_range(0.25..0.35) * s,
            Occluder::Car => rng.random_range(0.16..0.22) * s,
        };
        let cx = rng.random_range(0.22..0.78) * w;
        let cy = rng.random_range(0.35..0.65) * h;
        synth::paint_occluder(&mut img, Some(&mut painted), kind, cx, cy, size, seed * 10 + i as u64);
    }
    let mask = synth::dilate_mask(&painted, 2);
    let views: Vec<RgbF32> = views.iter().map(|f| load(f)).collect();
    save_case(&out.join(format!("{name}-{seed}")), &img, &mask, &truth, &views);
}

fn main() {
    let mut args = std::env::args().skip(1);
    let (mut out, mut seed, mut data) = (None, 1u64, PathBuf::from("../shared/data"));
    let mut views = 4;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seed" => seed = args.next().and_then(|s| s.parse().ok()).expect("--seed N"),
            "--data" => data = PathBuf::from(args.next().expect("--data DIR")),
            "--views" => views = args.next().and_then(|s| s.parse().ok()).expect("--views N"),
            _ => out = Some(PathBuf::from(a)),
        }
    }
    let Some(out) = out else {
        eprintln!("usage: service_cases OUT_DIR [--seed N] [--data DIR] [--views N]");
        std::process::exit(64);
    };
    for family in CaseFamily::ALL {
        let c = synth::occlusion_case(family, 640, 480, views, seed);
        save_case(&out.join(format!("{}-{seed}", family.name())), &c.key, &c.mask, &c.truth, &c.views);
    }
    let sets: [(&str, &str, &str, &[&str]); 9] = [
        ("oxford-graf", "oxford/graf", "img1.png", &["img2.png", "img3.png", "img4.png"]),
        ("oxford-wall", "oxford/wall", "img1.png", &["img2.png", "img3.png", "img4.png"]),
        ("oxford-leuven", "oxford/leuven", "img1.png", &["img2.png", "img3.png", "img4.png", "img5.png"]),
        ("hpatches-churchill", "hpatches/v_churchill", "img1.jpg", &["img2.jpg", "img3.jpg", "img4.jpg"]),
        ("hpatches-wormhole", "hpatches/v_wormhole", "img1.jpg", &["img2.jpg", "img3.jpg", "img4.jpg"]),
        (
            "photo-building",
            "multiview/parapano_building",
            "building2.png",
            &["building1.png", "building3.png"],
        ),
        (
            "photo-ece",
            "multiview/parapano_ece",
            "ece4.jpeg",
            &["ece3.jpeg", "ece5.jpeg", "ece2.jpeg", "ece6.jpeg"],
        ),
        (
            "photo-hunt",
            "multiview/parapano_hunt",
            "hunt3.jpg",
            &["hunt2.jpg", "hunt4.jpg", "hunt1.jpg", "hunt5.jpg"],
        ),
        ("photo-roofs", "multiview/vlfeat_roofs", "roofs1.jpg", &["roofs2.jpg"]),
    ];
    for (name, dir, key, views) in sets {
        let set = data.join(dir);
        if set.join(key).is_file() {
            photo(&out, name, &set, key, views, seed);
        } else {
            eprintln!("{}: absent; {name} skipped", set.display());
        }
    }
}
