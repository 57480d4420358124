//! `--mask auto` against the truth: on generated cases whose keyframe occluders are known,
//! how well the automatic mask matches the mask a person would paint (IoU with the true
//! occluders dilated by 2 px), and how much worse the fill is with it than with the true mask
//! (masked PSNR over the true mask, where the occluder stands).
//!
//! `cargo run --release --example automask_eval -- [--seeds N] [--first SEED] [--size WxH] [--views 2,3,4]
//!  [--families planar,shared,nonplanar] [--align] [--dump DIR (masks, fills, keyframe, truth, views)] [--parallax N] [--colour X] [--background X]
//!  [--sky GRADIENT (0: no sky looked for)] [--reach N (AutoMaskParams::unjudged_reach)]
//!  [--epipolar SHARE (AutoMaskParams::epipolar_reach; 0: not looked for)]`
//!
//! With `--align` the views are aligned as the fill command aligns them (otherwise the true
//! homographies are used, so that only the mask is judged). The targets: mean IoU
//! >= 0.8, and a fill within 1.5 dB of the fill with the true mask.

use std::path::PathBuf;

use clearview::align::{AlignParams, Frame, align};
use clearview::geometry::Homography;
use clearview::imaging::convert::{luminance, to_rgb8};
use clearview::imaging::metrics::{mask_iou, masked_psnr};
use clearview::inpaint::{AutoMaskParams, FillParams, Source, auto_mask, fill};
use clearview::synth::{CaseFamily, occlusion_case};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut seeds = 4u64;
    let mut first = 1000u64;
    let (mut w, mut h) = (480usize, 360usize);
    let mut counts = vec![2usize, 3, 4];
    let mut aligned = false;
    let mut dump: Option<PathBuf> = None;
    let mut am = AutoMaskParams::default();
    let mut families: Vec<String> = Vec::new();
    let mut i = 0;
    while i < args.len() {
        match args[i].as_str() {
            "--seeds" => seeds = args[i + 1].parse().expect("--seeds N"),
            "--first" => first = args[i + 1].parse().expect("--first N"),
            "--views" => counts = args[i + 1].split(',').map(|v| v.parse().expect("--views 2,3")).collect(),
            "--parallax" => am.parallax_radius = args[i + 1].parse().expect("--parallax N"),
            "--colour" => am.colour_ratio = args[i + 1].parse().expect("--colour X"),
            "--background" => am.background_ratio = args[i + 1].parse().expect("--background X"),
            "--epipolar" => am.epipolar_reach = args[i + 1].parse().expect("--epipolar SHARE"),
            "--reach" => am.unjudged_reach = args[i + 1].parse().expect("--reach N"),
            "--sky" => am.sky_gradient = args[i + 1].parse().expect("--sky X"),
            "--families" => families = args[i + 1].split(',').map(str::to_owned).collect(),
            "--dump" => dump = Some(PathBuf::from(&args[i + 1])),
            "--size" => {
                let (a, b) = args[i + 1].split_once('x').expect("--size WxH");
                (w, h) = (a.parse().unwrap(), b.parse().unwrap());
            }
            "--align" => {
                aligned = true;
                i += 1;
                continue;
            }
            other => panic!("unknown argument {other}"),
        }
        i += 2;
    }
    let params = FillParams::default();
    println!("| case | views | true mask px | auto px | IoU | PSNR true mask | PSNR auto mask | loss dB |");
    println!("|---|---|---|---|---|---|---|---|");
    let (mut ious, mut losses) = (Vec::new(), Vec::new());
    let chosen =
        CaseFamily::ALL.into_iter().filter(|f| families.is_empty() || families.iter().any(|n| n == f.name()));
    for family in chosen {
        for seed in 1..=seeds {
            for &n in &counts {
                let c = occlusion_case(family, w, h, n, first + seed);
                let homographies: Vec<Homography> = if aligned {
                    let ap = AlignParams::default();
                    let kf = Frame::new(luminance(&c.key), &ap);
                    c.views
                        .iter()
                        .zip(&c.homographies)
                        .map(|(v, truth)| {
                            let a = align(&kf, &Frame::new(luminance(v), &ap), &ap, None);
                            if a.accepted() { a.homography.unwrap_or(*truth) } else { *truth }
                        })
                        .collect()
                } else {
                    c.homographies.clone()
                };
                let sources: Vec<Source<'_>> = c
                    .views
                    .iter()
                    .zip(&homographies)
                    .map(|(image, &homography)| Source { image, homography })
                    .collect();
                let auto = auto_mask(&c.key, &sources, &am);
                let score = mask_iou(&auto, &c.mask);
                let with_true = fill(&c.key, &c.mask, &sources, &params, 1, &mut ());
                let with_auto = fill(&c.key, &auto, &sources, &params, 1, &mut ());
                let p_true = masked_psnr(&with_true.image, &c.truth, &c.mask);
                let p_auto = masked_psnr(&with_auto.image, &c.truth, &c.mask);
                let name = format!("{}-{seed}", family.name());
                if let Some(d) = &dump {
                    std::fs::create_dir_all(d).unwrap();
                    let overlay = clearview::imaging::RgbF32::from_fn(w, h, |x, y| {
                        let (t, a) = (c.mask.is_hole(x, y), auto.is_hole(x, y));
                        let k = c.key.get(x, y);
                        match (t, a) {
                            (true, true) => [0.0, 0.8, 0.0],
                            (true, false) => [1.0, 1.0, 0.0],
                            (false, true) => [1.0, 0.0, 0.0],
                            (false, false) => k,
                        }
                    });
                    to_rgb8(&overlay).save(d.join(format!("{name}-v{n}-mask.png"))).unwrap();
                    to_rgb8(&with_auto.image).save(d.join(format!("{name}-v{n}-fill.png"))).unwrap();
                    to_rgb8(&with_true.image).save(d.join(format!("{name}-v{n}-fill-true.png"))).unwrap();
                    to_rgb8(&c.key).save(d.join(format!("{name}-v{n}-key.png"))).unwrap();
                    to_rgb8(&c.truth).save(d.join(format!("{name}-v{n}-truth.png"))).unwrap();
                    for (k, v) in c.views.iter().enumerate() {
                        to_rgb8(v).save(d.join(format!("{name}-v{n}-view-{}.png", k + 1))).unwrap();
                    }
                }
                println!(
                    "| {name} | {n} | {} | {} | {score:.3} | {p_true:.2} | {p_auto:.2} | {:.2} |",
                    c.mask.hole_count(),
                    auto.hole_count(),
                    p_true - p_auto
                );
                ious.push(score);
                losses.push(p_true - p_auto);
            }
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let worst_iou = ious.iter().copied().fold(f64::INFINITY, f64::min);
    let worst_loss = losses.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    println!();
    println!(
        "mean IoU {:.3} (worst {worst_iou:.3}); mean fill loss {:.2} dB (worst {worst_loss:.2} dB); {} cases",
        mean(&ious),
        mean(&losses),
        ious.len()
    );
}
