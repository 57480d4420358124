//! Views arriving one by one: how often a new view makes the published result worse.
//!
//! The sessions of `tests/arrival_batches.rs`' guard (seeds 700–759: a facade, a tree over
//! the keyframe's mask, three views with a passer-by each, arriving one at a time), printed
//! per step: the masked PSNR of the published result against the truth, the pixels each
//! view filled, the fallback's and the fused pixels, and each view's key-to-view scale at
//! the mask's centre (below 1: coarser than the keyframe there).
//!
//! `cargo run --release --example arrivals -- [--band] [--seeds A-B] [--view-error X]
//! [--no-fuse] [--dump DIR]`
//!
//! `--band` renders every image at twice the size and box-averages it, as a camera's pixels
//! integrate light (the guard renders bilinearly from the facade raster, aliased); the
//! facade is then generated at twice the size, so its content differs. `--dump DIR` writes,
//! per step, the mask's surroundings as result | |result − truth|·4 | truth.

use std::path::PathBuf;

use clearview::geometry::Homography;
use clearview::imaging::convert::{luminance, to_rgb8};
use clearview::imaging::metrics::masked_psnr;
use clearview::imaging::{Mask, RgbF32};
use clearview::session::{Session, SessionParams};
use clearview::synth::{self, Occluder};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const W: usize = 400;
const H: usize = 300;
/// The mask's centre in the keyframe.
const MASK_CENTRE: (f64, f64) = (200.0, 160.0);

/// One session's scene: the facade, where the keyframe looks at it, the truth, the keyframe
/// with its tree and the tree's mask.
struct Scene {
    facade: RgbF32,
    centre: Homography,
    truth: RgbF32,
    key: RgbF32,
    mask: Mask,
    rng: ChaCha8Rng,
    band: bool,
}

/// `facade` as seen through `to_scene` (image pixel → facade pixel), `W × H`; with `band`,
/// rendered at twice the size on both sides (pixel centres kept: x₂ = 2·x + 0.5) and
/// box-averaged.
fn render(facade: &RgbF32, to_scene: &Homography, band: bool) -> RgbF32 {
    if band {
        synth::render_view_band(facade, to_scene, W, H, [0.5; 3])
    } else {
        synth::render_view(facade, to_scene, W, H, [0.5; 3])
    }
}

impl Scene {
    fn new(seed: u64, band: bool) -> Self {
        let k = if band { 2 } else { 1 };
        let facade = synth::facade(k * W * 3 / 2, k * H * 3 / 2, seed);
        let centre = Homography::translation(W as f64 / 4.0, H as f64 / 4.0);
        let truth = render(&facade, &centre, band);
        let mut key = truth.clone();
        let mut mask = Mask::new(W, H, 0);
        let (mx, my) = (MASK_CENTRE.0 as f32, MASK_CENTRE.1 as f32);
        synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, mx, my, 110.0, 3);
        Self { facade, centre, truth, key, mask, rng: ChaCha8Rng::seed_from_u64(seed), band }
    }

    /// View `i` with a passer-by at `cx`, and its key-to-view scale at the mask's centre.
    fn view(&mut self, i: u64, cx: f32) -> (RgbF32, f64) {
        let key_to_view = synth::random_homography(&mut self.rng, W, H, 0.1, 0.2, (0.9, 1.1));
        let to_scene = self.centre.after(&key_to_view.inverse().expect("regular"));
        let mut v = render(&self.facade, &to_scene, self.band);
        synth::paint_occluder(&mut v, None, Occluder::Person, cx, 170.0, 40.0, 100 + i);
        synth::expose(&mut v, 0.9 + 0.03 * i as f32, 0.01);
        let scale = key_to_view.area_scale(nalgebra::Point2::new(MASK_CENTRE.0, MASK_CENTRE.1)).abs().sqrt();
        (v, scale)
    }
}

struct Args {
    band: bool,
    seeds: std::ops::Range<u64>,
    view_error: Option<f32>,
    fuse: bool,
    dump: Option<PathBuf>,
}

fn args() -> Args {
    let mut a = Args { band: false, seeds: 700..760, view_error: None, fuse: true, dump: None };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < argv.len() {
        let value =
            |what: &str| argv.get(i + 1).unwrap_or_else(|| panic!("{} needs {what}", argv[i])).clone();
        match argv[i].as_str() {
            "--band" => a.band = true,
            "--no-fuse" => a.fuse = false,
            "--seeds" => {
                let v = value("A-B");
                let (x, y) = v.split_once('-').expect("--seeds A-B");
                a.seeds = x.parse().expect("--seeds A-B")..y.parse().expect("--seeds A-B");
                i += 1;
            }
            "--view-error" => {
                a.view_error = Some(value("X").parse().expect("--view-error X"));
                i += 1;
            }
            "--dump" => {
                a.dump = Some(PathBuf::from(value("DIR")));
                i += 1;
            }
            other => panic!("unknown argument {other} (see the example's docs)"),
        }
        i += 1;
    }
    a
}

/// The mask's surroundings: `img` | |img − truth|·4 | truth.
fn crop(img: &RgbF32, truth: &RgbF32) -> RgbF32 {
    let (x0, y0, cw, ch) = (110, 60, 180, 200);
    RgbF32::from_fn(3 * cw, ch, |x, y| {
        let (a, b) = (img.get(x0 + x % cw, y0 + y), truth.get(x0 + x % cw, y0 + y));
        match x / cw {
            0 => a,
            1 => [0, 1, 2].map(|c| ((a[c] - b[c]).abs() * 4.0).min(1.0)),
            _ => b,
        }
    })
}

fn main() {
    let a = args();
    if let Some(dir) = &a.dump {
        std::fs::create_dir_all(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    }
    let mut params = SessionParams::default();
    if let Some(x) = a.view_error {
        params.fill.view_error_weight = x;
    }
    if !a.fuse {
        params.fill.fuse = None;
    }
    let (mut over, mut worst_sum, mut last_sum, mut n) = (Vec::new(), 0.0, 0.0, 0.0);
    for seed in a.seeds.clone() {
        let mut scene = Scene::new(seed, a.band);
        let views: Vec<(RgbF32, f64)> = (0..3).map(|i| scene.view(i, 60.0 + 120.0 * i as f32)).collect();
        let mut s = Session::new(params.clone());
        s.set_key("key".into(), scene.key.clone());
        s.set_mask("mask".into(), scene.mask.clone()).expect("the mask fits the keyframe");
        let (mut current, mut worst, mut steps) = (None::<f64>, 0.0f64, Vec::new());
        for (i, (v, _)) in views.iter().enumerate() {
            let record = s.align(luminance(v)).expect("a view of the keyframe's size");
            assert!(record.accepted, "seed {seed}, view {i} refused: {:?}", record.reason);
            let pixels = v.map(|p| p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8));
            s.admit(format!("view{i}"), record, Some(&pixels)).expect("admitted");
            s.request_fill();
            let outcome = s.fill(&mut ()).expect("a fill");
            if let Some(img) = &outcome.image {
                let p = masked_psnr(img, &scene.truth, &scene.mask);
                worst = current.map_or(worst, |c| worst.max(c - p));
                current = Some(p);
                if let Some(dir) = &a.dump {
                    let path = dir.join(format!("seed{seed}_step{}.png", i + 1));
                    to_rgb8(&crop(img, &scene.truth))
                        .save(&path)
                        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                }
            }
            let filled: Vec<String> = outcome.report.sources.iter().map(|s| s.filled.to_string()).collect();
            steps.push(format!(
                "{} [{} fallback {} fused {}]",
                current.map_or("-".into(), |p| format!("{p:.2}")),
                filled.join("/"),
                outcome.report.fallback,
                outcome.report.fused
            ));
        }
        let scales: Vec<String> = views.iter().map(|v| format!("{:.2}", v.1)).collect();
        println!("seed {seed}: {}  worst drop {worst:.2} dB  scales {}", steps.join(" → "), scales.join(" "));
        if worst > 0.3 {
            over.push(seed);
        }
        worst_sum += worst;
        last_sum += current.unwrap_or(f64::NAN);
        n += 1.0;
    }
    println!(
        "band {}: {} of {} sessions drop more than 0.3 dB {over:?}; mean worst drop {:.3} dB, mean last {:.3} dB",
        a.band,
        over.len(),
        n,
        worst_sum / n,
        last_sum / n
    );
}
