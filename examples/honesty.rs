//! The occlusion model's honesty figures: on cases whose every occluder is known, how good
//! the fill is (masked PSNR), how much of the mask it says it is sure of, how often it is
//! grossly wrong where it says so (confident precision) and how many of its gross errors it
//! flags (flagged recall); with the model and with it bypassed.
//!
//! `cargo run --release --example honesty -- [--seeds N] [--size WxH] [--views N]`
//!     generated cases (`synth::occlusion_case`: planar, shared-occluder, non-planar), true
//!     homographies, so that only the model is judged;
//! `cargo run --release --example honesty -- --dir CASE...`
//!     case folders as `fill_cases` writes them (key.png, mask.png, truth.png, view-N.png),
//!     the views aligned as the fill command aligns them.
//! `--dump DIR` writes each result, a map of its honesty, the keyframe, the truth and the
//! views there; `--prior X`, `--cut X`
//! try other values of the model's parameters; `--select off` uses every view, `--select M`
//! lets a view into the fill unless it costs more than M of the judge's agreement.
//!
//! The targets: confident error rate <= 8 %, flagged recall >= 60 %, confident share
//! >= 50 %.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clearview::align::{AlignParams, Frame, align};
use clearview::geometry::Homography;
use clearview::imaging::Plane;
use clearview::imaging::convert::{luminance, to_mask, to_rgb, to_rgb8};
use clearview::imaging::metrics::{Honesty, honesty, masked_psnr};
use clearview::imaging::photometric::{GainParams, fit_gain};
use clearview::imaging::warp::{Interpolation, Rect, warp};
use clearview::imaging::{Mask, RgbF32};
use clearview::inpaint::automask::dilate;
use clearview::inpaint::occlusion::{KeyRegion, OcclusionParams, RegionInput, occlusion_map};
use clearview::inpaint::{FillParams, Source, fill};
use clearview::synth::{CaseFamily, occlusion_case};

struct Case {
    name: String,
    /// Per view, keyframe-sized: where it truly shows an occluder (generated cases only).
    occluders: Option<Vec<Mask>>,
    key: RgbF32,
    mask: Mask,
    truth: RgbF32,
    views: Vec<(RgbF32, Homography)>,
}

fn load_dir(dir: &Path) -> Case {
    let rgb = |n: &str| {
        to_rgb(&image::open(dir.join(n)).unwrap_or_else(|e| panic!("{}: {e}", dir.join(n).display())))
    };
    let key = rgb("key.png");
    let mask = to_mask(&image::open(dir.join("mask.png")).expect("mask.png"));
    let truth = rgb("truth.png");
    let params = AlignParams::default();
    let kf = Frame::new(luminance(&key), &params);
    let mut views = Vec::new();
    for i in 1.. {
        let p = dir.join(format!("view-{i}.png"));
        if !p.exists() {
            break;
        }
        let v = rgb(&format!("view-{i}.png"));
        let a = align(&kf, &Frame::new(luminance(&v), &params), &params, None);
        match (a.accepted(), a.homography) {
            (true, Some(h)) => views.push((v, h)),
            _ => eprintln!("{}: rejected", p.display()),
        }
    }
    Case {
        name: dir.file_name().unwrap().to_string_lossy().into_owned(),
        occluders: None,
        key,
        mask,
        truth,
        views,
    }
}

fn run(case: &Case, params: &FillParams, dump: Option<&Path>) -> (f64, Honesty, f64) {
    let sources: Vec<Source<'_>> =
        case.views.iter().map(|(image, h)| Source { image, homography: *h }).collect();
    let t = Instant::now();
    let f = fill(&case.key, &case.mask, &sources, params, 1, &mut ());
    let ms = t.elapsed().as_secs_f64() * 1e3;
    if let Some(d) = dump {
        // The result, and a map: grey = keyframe, green = confident and right, red =
        // confident and grossly wrong, yellow = flagged and wrong, blue = flagged and right.
        std::fs::create_dir_all(d).unwrap();
        to_rgb8(&f.image).save(d.join(format!("{}-result.png", case.name))).unwrap();
        to_rgb8(&case.truth).save(d.join(format!("{}-truth.png", case.name))).unwrap();
        to_rgb8(&case.key).save(d.join(format!("{}-key.png", case.name))).unwrap();
        for (v, (image, _)) in case.views.iter().enumerate() {
            to_rgb8(image).save(d.join(format!("{}-view-{}.png", case.name, v + 1))).unwrap();
        }
        let map = RgbF32::from_fn(case.key.width(), case.key.height(), |x, y| {
            if !case.mask.is_hole(x, y) {
                return case.key.get(x, y).map(|v| 0.3 * v);
            }
            let (a, b) = (f.image.get(x, y), case.truth.get(x, y));
            let gross = (0..3).any(|k| ((a[k] - b[k]) * 255.0).abs() > 30.0);
            match (f.confidence.get(x, y) >= 128, gross) {
                (true, false) => [0.0, 0.7, 0.0],
                (true, true) => [1.0, 0.0, 0.0],
                (false, true) => [1.0, 1.0, 0.0],
                (false, false) => [0.0, 0.3, 1.0],
            }
        });
        to_rgb8(&map).save(d.join(format!("{}-honesty.png", case.name))).unwrap();
    }
    (
        masked_psnr(&f.image, &case.truth, &case.mask),
        honesty(&f.image, &case.truth, &case.mask, &f.confidence),
        ms,
    )
}

/// The model itself against the truth, over the mask: of the view pixels it cuts (occlusion
/// probability above the cut), how many are true occluders (precision), and of the true
/// occluders how many it cuts (recall).
fn model_accuracy(case: &Case, params: &OcclusionParams) -> Option<(usize, usize, usize)> {
    let truth = case.occluders.as_ref()?;
    let (w, h) = (case.key.width(), case.key.height());
    let rect = Rect::full(w, h);
    let hole = Plane::from_fn(w, h, |x, y| case.mask.is_hole(x, y));
    let need = dilate(&hole, 16);
    let mut warps: Vec<_> =
        case.views.iter().map(|(v, hm)| warp(v, hm, rect, Some(&need), Interpolation::Bilinear)).collect();
    // Compensated as the fill compensates them, on what lies around the mask.
    let ring: Vec<bool> = (0..w * h).map(|i| need.as_slice()[i] && !hole.as_slice()[i]).collect();
    for wv in &mut warps {
        let pairs: Vec<_> = (0..w * h)
            .filter(|&i| ring[i] && wv.valid.as_slice()[i])
            .step_by(7)
            .map(|i| (wv.image.as_slice()[i], case.key.as_slice()[i]))
            .collect();
        let g = fit_gain(&pairs, &GainParams::default());
        wv.image.as_mut_slice().iter_mut().for_each(|p| *p = g.apply(*p));
    }
    let refs: Vec<_> = warps.iter().map(|wv| (wv.image.as_slice(), wv.valid.as_slice())).collect();
    let blocked = vec![false; w * h];
    let region = KeyRegion {
        width: w,
        height: h,
        key: case.key.as_slice(),
        hole: hole.as_slice(),
        need: need.as_slice(),
        blocked: &blocked,
    };
    let input = RegionInput { region, views: &refs, diagonal: (w as f32).hypot(h as f32) };
    let map = occlusion_map(&input, params);
    let (mut tp, mut fp, mut fneg) = (0, 0, 0);
    for (v, t) in truth.iter().enumerate() {
        for i in 0..w * h {
            if !hole.as_slice()[i] || !warps[v].valid.as_slice()[i] {
                continue;
            }
            let (cut, occ) = (map.occluded[v][i] > params.cut, t.as_slice()[i] > 127);
            tp += usize::from(cut && occ);
            fp += usize::from(cut && !occ);
            fneg += usize::from(!cut && occ);
        }
    }
    Some((tp, fp, fneg))
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut seeds = 4u64;
    let (mut w, mut h, mut n) = (480usize, 360usize, 4usize);
    let mut dirs: Vec<PathBuf> = Vec::new();
    let mut dump: Option<PathBuf> = None;
    let mut on = FillParams::default();
    let mut i = 0;
    while i < args.len() {
        match args[i].as_str() {
            "--seeds" => seeds = args[i + 1].parse().expect("--seeds N"),
            "--prior" => on.occlusion_model.prior = args[i + 1].parse().expect("--prior X"),
            "--cut" => on.occlusion_model.cut = args[i + 1].parse().expect("--cut X"),
            "--weight" => on.occlusion_weight = args[i + 1].parse().expect("--weight X"),
            "--view-error" => on.view_error_weight = args[i + 1].parse().expect("--view-error X"),
            "--select" => match args[i + 1].as_str() {
                "off" => on.select_views = false,
                m => on.select_margin = m.parse().expect("--select off|MARGIN"),
            },
            "--dump" => dump = Some(PathBuf::from(&args[i + 1])),
            "--interpolation" => {
                on.interpolation = match args[i + 1].as_str() {
                    "bilinear" => clearview::imaging::warp::Interpolation::Bilinear,
                    "bicubic" => clearview::imaging::warp::Interpolation::Bicubic,
                    other => panic!("--interpolation bilinear|bicubic, not {other}"),
                }
            }
            "--views" => n = args[i + 1].parse().expect("--views N"),
            "--size" => {
                let (a, b) = args[i + 1].split_once('x').expect("--size WxH");
                (w, h) = (a.parse().unwrap(), b.parse().unwrap());
            }
            "--dir" => {
                dirs.extend(args[i + 1..].iter().map(PathBuf::from));
                break;
            }
            other => panic!("unknown argument {other}"),
        }
        i += 2;
    }
    let cases: Vec<Case> = if dirs.is_empty() {
        CaseFamily::ALL
            .iter()
            .flat_map(|&f| (1..=seeds).map(move |s| (f, s)))
            .map(|(f, s)| {
                let c = occlusion_case(f, w, h, n, s);
                Case {
                    name: format!("{}-{s}", f.name()),
                    key: c.key,
                    mask: c.mask,
                    truth: c.truth,
                    occluders: Some(c.view_occluders),
                    views: c.views.into_iter().zip(c.homographies).collect(),
                }
            })
            .collect()
    } else {
        dirs.iter().map(|d| load_dir(d)).collect()
    };
    let off = FillParams { occlusion: false, view_error_weight: 0.0, select_views: false, ..on.clone() };
    println!(
        "| case | views | PSNR model | PSNR bypassed | confident | confident wrong | flagged recall | bypassed: confident wrong / recall | fill ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let (mut all_on, mut all_off) = (Honesty::default(), Honesty::default());
    let (mut sum_on, mut sum_off) = (0.0, 0.0);
    for c in &cases {
        let (p_on, h_on, ms) = run(c, &on, dump.as_deref());
        let (p_off, h_off, _) = run(c, &off, None);
        all_on.add(&h_on);
        all_off.add(&h_off);
        sum_on += p_on;
        sum_off += p_off;
        println!(
            "| {} | {} | {:.2} | {:.2} | {:.1} % | {:.1} % | {:.1} % | {:.1} % / {:.1} % | {:.0} |",
            c.name,
            c.views.len(),
            p_on,
            p_off,
            100.0 * h_on.confident_share(),
            100.0 * h_on.confident_error_rate(),
            100.0 * h_on.flagged_recall(),
            100.0 * h_off.confident_error_rate(),
            100.0 * h_off.flagged_recall(),
            ms
        );
    }
    let k = cases.len().max(1) as f64;
    println!();
    println!("| case | model: cut pixels that are occluders | occluders cut |");
    println!("|---|---|---|");
    for c in &cases {
        if let Some((tp, fp, fneg)) = model_accuracy(c, &on.occlusion_model) {
            println!(
                "| {} | {:.1} % | {:.1} % |",
                c.name,
                100.0 * tp as f64 / (tp + fp).max(1) as f64,
                100.0 * tp as f64 / (tp + fneg).max(1) as f64
            );
        }
    }
    println!();
    println!(
        "| **all** | | {:.2} | {:.2} | {:.1} % | {:.1} % | {:.1} % | {:.1} % / {:.1} % | |",
        sum_on / k,
        sum_off / k,
        100.0 * all_on.confident_share(),
        100.0 * all_on.confident_error_rate(),
        100.0 * all_on.flagged_recall(),
        100.0 * all_off.confident_error_rate(),
        100.0 * all_off.flagged_recall(),
    );
}
