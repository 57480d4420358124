//! The multi-view fill on real photographs: Oxford graf, wall and leuven, with occluders of
//! our own pasted into img1 (on the wall, not over graf's real car roof), img2..img4 as the
//! views, aligned by clearview's own `align` (not the ground truth). The filled region is
//! measured against the real img1 (PSNR, and SSIM on luminance).
//!
//! `CLEARVIEW_DUMP=/tmp` writes before/after PNGs.

mod common;

use std::path::Path;

use clearview::align::{AlignParams, Frame, align};
use clearview::imaging::convert::{luminance, to_rgb, to_rgb8};
use clearview::imaging::metrics::{masked_psnr, masked_ssim};
use clearview::imaging::{Mask, RgbF32};
use clearview::inpaint::{FillParams, Source, fill};
use clearview::synth::{Occluder, paint_occluder};

fn load(path: &Path) -> RgbF32 {
    to_rgb(&image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
}

struct Case {
    name: &'static str,
    /// Occluders pasted into img1: kind, centre, size.
    occluders: &'static [(Occluder, f32, f32, f32)],
    views: &'static [usize],
}

const CASES: &[Case] = &[
    // graf: the car roof is along the bottom; the occluders stand on the painted wall.
    Case {
        name: "graf",
        occluders: &[(Occluder::Tree, 300.0, 230.0, 200.0), (Occluder::Person, 560.0, 300.0, 180.0)],
        views: &[2, 3, 4],
    },
    Case {
        name: "wall",
        occluders: &[(Occluder::Tree, 380.0, 300.0, 240.0), (Occluder::Person, 720.0, 380.0, 220.0)],
        views: &[2, 3, 4],
    },
    // leuven: the views darken step by step, so the gains matter.
    Case {
        name: "leuven",
        occluders: &[(Occluder::Person, 300.0, 250.0, 180.0), (Occluder::Tree, 620.0, 220.0, 180.0)],
        views: &[2, 3, 4],
    },
];

#[test]
fn fills_real_sequences_from_their_other_views() {
    let Some(data) = common::data_dir() else { return };
    let params = AlignParams::default();
    let mut failures = Vec::new();
    println!(
        "{:<8} {:>6} {:>9} {:>9} {:>7} {:>7} {:>9}",
        "seq", "views", "PSNR bef", "PSNR aft", "SSIM b", "SSIM a", "fallback"
    );
    for case in CASES {
        let seq = data.join("oxford").join(case.name);
        let truth = load(&common::sequence_image(&seq, 1));
        let (w, h) = (truth.width(), truth.height());
        let mut key = truth.clone();
        let mut mask = Mask::new(w, h, 0);
        for (k, &(kind, cx, cy, size)) in case.occluders.iter().enumerate() {
            paint_occluder(&mut key, Some(&mut mask), kind, cx, cy, size, 10 + k as u64);
        }
        let key_frame = Frame::new(luminance(&key), &params);
        let mut views = Vec::new();
        let mut hs = Vec::new();
        for &n in case.views {
            let view = load(&common::sequence_image(&seq, n));
            let a = align(&key_frame, &Frame::new(luminance(&view), &params), &params, None);
            match (a.accepted(), a.homography) {
                (true, Some(hm)) => {
                    views.push(view);
                    hs.push(hm);
                }
                _ => println!("{}: img{n} rejected by align: {:?}", case.name, a.rejection),
            }
        }
        let sources: Vec<Source<'_>> =
            views.iter().zip(&hs).map(|(v, &homography)| Source { image: v, homography }).collect();
        let out = fill(&key, &mask, &sources, &FillParams::default(), 1, &mut ());
        let (pb, pa) = (masked_psnr(&key, &truth, &mask), masked_psnr(&out.image, &truth, &mask));
        let (sb, sa) = (masked_ssim(&key, &truth, &mask), masked_ssim(&out.image, &truth, &mask));
        let fb = out.report.fallback as f64 / out.report.masked as f64;
        println!(
            "{:<8} {:>6} {:>8.1}dB {:>8.1}dB {:>7.3} {:>7.3} {:>8.1}%",
            case.name,
            sources.len(),
            pb,
            pa,
            sb,
            sa,
            100.0 * fb
        );
        for (i, s) in out.report.sources.iter().enumerate() {
            println!("         view {i}: covered {} filled {} gain {:?}", s.covered, s.filled, s.gain);
        }
        if let Ok(dir) = std::env::var("CLEARVIEW_DUMP") {
            let dir = Path::new(&dir);
            to_rgb8(&key).save(dir.join(format!("fill_{}_before.png", case.name))).expect("write");
            to_rgb8(&out.image).save(dir.join(format!("fill_{}_after.png", case.name))).expect("write");
        }
        if sources.len() < 2 || pa < pb + 10.0 || sa < 0.5 {
            failures.push(format!(
                "{}: {} views, PSNR {pb:.1} → {pa:.1} dB, SSIM {sb:.3} → {sa:.3}",
                case.name,
                sources.len()
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
