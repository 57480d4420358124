//! The single-image fallback on its own, judged against the truth: real facades (the
//! multi-view photographs and Oxford's wall and leuven in `../shared/data`) and rendered
//! ones, each with holes shaped like the occluders it meets (a tree, a person, a car), some
//! of them against the image's border, where a video walk leaves what no frame saw. Every
//! hole goes through the product's path with no view (`inpaint::fill`: the fallback steered
//! by the membrane of its border), and is scored by masked PSNR against the image as it was.
//!
//! `cargo run --release --example fallback_eval -- [--radius R] [--guide-weight X] [--holes N] [--save DIR] [DATA_DIR]`
//!
//! `--radius` and `--guide-weight` set the exemplar fill's patch radius and guide weight
//! (`ExemplarParams`); `--save DIR` writes, per hole, the truth, the hole and the fill side
//! by side (a crop around the hole, at 1:1).

use std::path::{Path, PathBuf};

use clearview::imaging::convert::{to_rgb, to_rgb8};
use clearview::imaging::metrics::masked_psnr;
use clearview::imaging::{Mask, RgbF32};
use clearview::inpaint::{FillParams, fill};
use clearview::synth::{self, Occluder};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The longest side the photographs are brought down to (the fallback's cost grows with the
/// hole; the figures are about its choices, not its speed).
const SIDE: u32 = 800;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut params = FillParams::default();
    let mut holes = 6usize;
    let mut save: Option<PathBuf> = None;
    let mut data = PathBuf::from("../shared/data");
    let mut i = 0;
    while i < args.len() {
        match args[i].as_str() {
            "--radius" => params.exemplar.patch_radius = args[i + 1].parse().expect("--radius R"),
            "--guide-weight" => params.exemplar.guide_weight = args[i + 1].parse().expect("--guide-weight X"),
            "--holes" => holes = args[i + 1].parse().expect("--holes N"),
            "--save" => save = Some(PathBuf::from(&args[i + 1])),
            other if !other.starts_with("--") => {
                data = PathBuf::from(other);
                i += 1;
                continue;
            }
            other => panic!("unknown argument {other}"),
        }
        i += 2;
    }
    if let Some(dir) = &save {
        std::fs::create_dir_all(dir).expect("--save folder");
    }
    let mut images: Vec<(String, RgbF32)> =
        (1..=4u64).map(|s| (format!("rendered-{s}"), synth::facade(800, 600, s))).collect();
    for rel in [
        "multiview/parapano_building/building1.png",
        "multiview/parapano_building/building2.png",
        "multiview/parapano_building/building3.png",
        "multiview/parapano_ece/ece1.jpeg",
        "multiview/parapano_ece/ece3.jpeg",
        "multiview/parapano_ece/ece5.jpeg",
        "multiview/parapano_ece/ece7.jpeg",
        "multiview/parapano_hunt/hunt1.jpg",
        "multiview/parapano_hunt/hunt3.jpg",
        "multiview/parapano_hunt/hunt5.jpg",
        "multiview/vlfeat_roofs/roofs1.jpg",
        "multiview/cmu_incline/incline_L.png",
        "oxford/wall/img1.png",
        "oxford/leuven/img1.png",
    ] {
        match load(&data.join(rel)) {
            Some(img) => images.push((rel.to_string(), img)),
            None => eprintln!("skipping {rel}: not readable under {}", data.display()),
        }
    }
    println!("| image | hole | shape | px | at the border | PSNR dB |");
    println!("|---|---|---|---:|---|---:|");
    let (mut all, mut border, mut inner) = (Vec::new(), Vec::new(), Vec::new());
    for (k, (name, truth)) in images.iter().enumerate() {
        for j in 0..holes {
            let seed = 1000 * k as u64 + j as u64;
            let (mask, shape, at_border) = hole(truth, j, seed);
            let filled = fill::<[f32; 3]>(truth, &mask, &[], &params, seed, &mut ());
            let psnr = masked_psnr(&filled.image, truth, &mask);
            println!(
                "| {name} | {j} | {shape} | {} | {} | {psnr:.2} |",
                mask.hole_count(),
                if at_border { "yes" } else { "no" }
            );
            all.push(psnr);
            if at_border {
                border.push(psnr)
            } else {
                inner.push(psnr)
            }
            if let Some(dir) = &save {
                let file = format!("{}-{j}.png", name.replace('/', "_"));
                side_by_side(truth, &mask, &filled.image).save(dir.join(file)).expect("write a crop");
            }
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!();
    println!(
        "holes {}: mean masked PSNR {:.2} dB (at the border {:.2} over {}, inside {:.2} over {})",
        all.len(),
        mean(&all),
        mean(&border),
        border.len(),
        mean(&inner),
        inner.len()
    );
}

/// An image brought down to [`SIDE`] on its longest side.
fn load(path: &Path) -> Option<RgbF32> {
    let img = image::open(path).ok()?;
    let img = if img.width().max(img.height()) > SIDE {
        img.resize(SIDE, SIDE, image::imageops::FilterType::Triangle)
    } else {
        img
    };
    Some(to_rgb(&img))
}

/// Hole `j` of an image: an occluder's silhouette (grown by 3 px, as a person paints); holes
/// 2, 3 and 5 of every six (half of them) against the left, right or bottom border.
fn hole(img: &RgbF32, j: usize, seed: u64) -> (Mask, &'static str, bool) {
    let (w, h) = (img.width() as f32, img.height() as f32);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (kind, shape) =
        [(Occluder::Tree, "tree"), (Occluder::Person, "person"), (Occluder::Car, "car")][j % 3];
    let size = h * rng.random_range(0.22..0.36f32);
    let at_border = j % 3 == 2 || j % 4 == 3;
    let (cx, cy) = if at_border {
        match rng.random_range(0..3) {
            0 => (size * 0.1, rng.random_range(0.35..0.75) * h),
            1 => (w - size * 0.1, rng.random_range(0.35..0.75) * h),
            _ => (rng.random_range(0.2..0.8) * w, h - size * 0.2),
        }
    } else {
        (rng.random_range(0.2..0.8) * w, rng.random_range(0.3..0.7) * h)
    };
    let mut scratch = img.clone();
    let mut mask = Mask::new(img.width(), img.height(), 0);
    synth::paint_occluder(&mut scratch, Some(&mut mask), kind, cx, cy, size, seed);
    (synth::dilate_mask(&mask, 3), shape, at_border)
}

/// Truth | hole (magenta) | fill, cropped to the hole's box grown by 24 px.
fn side_by_side(truth: &RgbF32, mask: &Mask, filled: &RgbF32) -> image::RgbImage {
    let b = mask.hole_bounds().expect("a hole").grown(24, truth.width(), truth.height());
    let holed = RgbF32::from_fn(truth.width(), truth.height(), |x, y| {
        if mask.is_hole(x, y) { [1.0, 0.0, 1.0] } else { truth.get(x, y) }
    });
    let mut out = image::RgbImage::new(3 * b.width as u32, b.height as u32);
    for (k, img) in [truth, &holed, filled].into_iter().enumerate() {
        let crop = to_rgb8(&img.crop(b));
        image::imageops::replace(&mut out, &crop, (k * b.width) as i64, 0);
    }
    out
}
