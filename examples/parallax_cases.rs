//! Writes the generated non-planar facade cases of issue 14 (`synth::facade::parallax_case`)
//! as case folders for `bench/fill_peer.py` (key.png, mask.png, truth.png, view-N.png), plus
//! `truth-planes.json` with each view's true per-plane homographies.
//!
//! `cargo run --release --example parallax_cases -- OUT_DIR [--seeds N] [--size WxH] [--views N] [--flat]`

use std::path::PathBuf;

use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::synth::facade::parallax_case;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(out) = args.first().map(PathBuf::from) else {
        eprintln!("usage: parallax_cases OUT_DIR [--seeds N] [--size WxH] [--views N] [--flat]");
        std::process::exit(64);
    };
    let mut seeds = 8u64;
    let (mut w, mut h) = (640usize, 480usize);
    let mut n = 3usize;
    let mut flat = false;
    let mut it = args.iter().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--seeds" => seeds = it.next().and_then(|v| v.parse().ok()).expect("--seeds N"),
            "--views" => n = it.next().and_then(|v| v.parse().ok()).expect("--views N"),
            "--size" => {
                let s = it.next().expect("--size WxH");
                let (a, b) = s.split_once('x').expect("--size WxH");
                (w, h) = (a.parse().expect("width"), b.parse().expect("height"));
            }
            "--flat" => flat = true,
            other => {
                eprintln!("unknown argument {other}");
                std::process::exit(64);
            }
        }
    }
    for seed in 1..=seeds {
        let c = parallax_case(w, h, n, seed, flat);
        let dir = out.join(format!("{}-{seed}", if flat { "flat" } else { "parallax" }));
        std::fs::create_dir_all(&dir).unwrap();
        to_rgb8(&c.key).save(dir.join("key.png")).unwrap();
        mask_to_luma8(&c.mask).save(dir.join("mask.png")).unwrap();
        to_rgb8(&c.truth).save(dir.join("truth.png")).unwrap();
        for (i, v) in c.views.iter().enumerate() {
            to_rgb8(v).save(dir.join(format!("view-{}.png", i + 1))).unwrap();
        }
        let planes: Vec<Vec<[[f64; 3]; 3]>> =
            c.planes.iter().map(|p| p.iter().map(|h| h.rows()).collect()).collect();
        std::fs::write(dir.join("truth-planes.json"), serde_json::to_string(&planes).unwrap()).unwrap();
        println!(
            "{}: {} masked pixels, {} views, {} slabs",
            dir.display(),
            c.mask.hole_count(),
            n,
            c.slabs.len()
        );
    }
}
