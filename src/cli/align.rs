//! `clearview align KEY VIEW`: the homography from keyframe to view and its quality
//! (edge layer).

use std::path::PathBuf;
use std::time::Instant;

use clap::Args;
use serde::Serialize;

use super::exit;
use super::load::{load_image, load_mask};
use crate::align::{AlignParams, Frame, align};
use crate::geometry::{Method, Rows};
use crate::imaging::convert::to_luminance;
use crate::imaging::decode::DecodeLimits;

#[derive(Debug, Args)]
pub struct AlignArgs {
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Robust estimator for the final fit: lmeds (the paper's), msac or ransac.
    #[arg(long, default_value = "lmeds")]
    pub estimator: Method,
    /// Refuse images with more pixels than this (decompression bombs).
    #[arg(long, default_value_t = DecodeLimits::default().max_pixels)]
    pub max_pixels: u64,
    /// Seed for the random sampling.
    #[arg(long)]
    pub seed: Option<u64>,
    /// The keyframe's mask, as `fill` takes it (white = to remove): corners under it
    /// belong to what is to be removed and are not matched.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// The keyframe.
    pub key: PathBuf,
    /// The view to align to it.
    pub view: PathBuf,
}

#[derive(Debug, Serialize)]
struct Report<'a> {
    key: &'a std::path::Path,
    view: &'a std::path::Path,
    accepted: bool,
    reason: Option<String>,
    /// Maps keyframe pixel coordinates to view pixel coordinates (0-based, pixel centres
    /// at integers), row-major, h33 = 1.
    homography: Option<Rows>,
    /// Putative matches from descriptors (0 when none were needed).
    putative_matches: usize,
    /// Correspondences the final fit used, from guided search around predictions.
    matches: usize,
    /// Those of `matches` the homography explains.
    inliers: usize,
    /// Keyframe points searched for in the view by the final guided stage.
    checked: usize,
    median_residual_px: Option<f64>,
    coverage: f64,
    /// The pyramid octave the final estimate was made at (0 = full resolution; a soft
    /// high-resolution image stops at a coarser one).
    octave: usize,
    /// Set when the plain path refused the view and the scale and roll search found it:
    /// the candidate scale (key → view) and roll in degrees.
    search: Option<[f64; 2]>,
    /// Keyframe corners used for matching (those under `--mask` left out).
    key_corners: usize,
    key_size: [usize; 2],
    view_size: [usize; 2],
    /// Alignment time, decoding excluded.
    time_ms: f64,
}

pub fn run(args: &AlignArgs) -> u8 {
    let limits = DecodeLimits { max_pixels: args.max_pixels };
    let (key, view) = match (load_image(&args.key, &limits), load_image(&args.view, &limits)) {
        (Ok(k), Ok(v)) => (k, v),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("clearview align: {e}");
            return exit::FAILURE;
        }
    };
    let mut params = AlignParams::default();
    params.fine.method = args.estimator;
    if let Some(seed) = args.seed {
        params.seed = seed;
    }
    let mask = match &args.mask {
        None => None,
        Some(path) => match load_mask(path, &limits) {
            Ok(m) if (m.width(), m.height()) == (key.width() as usize, key.height() as usize) => Some(m),
            Ok(m) => {
                eprintln!(
                    "clearview align: {}: the mask is {}x{} but the keyframe is {}x{}",
                    path.display(),
                    m.width(),
                    m.height(),
                    key.width(),
                    key.height()
                );
                return exit::USAGE;
            }
            Err(e) => {
                eprintln!("clearview align: {e}");
                return exit::FAILURE;
            }
        },
    };
    let start = Instant::now();
    let mut key_frame = Frame::new(to_luminance(&key), &params);
    key_frame.set_mask(mask.as_ref());
    let view_frame = Frame::new(to_luminance(&view), &params);
    let result = align(&key_frame, &view_frame, &params, None);
    let time_ms = start.elapsed().as_secs_f64() * 1e3;
    tracing::debug!(
        key_keypoints = key_frame.keypoints().len(),
        view_keypoints = view_frame.keypoints().len(),
        "features"
    );

    let report = Report {
        key: &args.key,
        view: &args.view,
        accepted: result.accepted(),
        reason: result.rejection.as_ref().map(|r| r.to_string()),
        homography: result.homography.as_ref().map(Rows::from),
        putative_matches: result.putative,
        matches: result.matches,
        inliers: result.inliers,
        checked: result.checked,
        median_residual_px: result.median_residual_px.is_finite().then_some(result.median_residual_px),
        coverage: result.coverage,
        octave: result.octave,
        search: result.searched.map(|s| [s.scale, s.roll.to_degrees()]),
        key_corners: key_frame.keypoints().len(),
        key_size: [key_frame.width(), key_frame.height()],
        view_size: [view_frame.width(), view_frame.height()],
        time_ms,
    };
    if args.json {
        println!("{}", serde_json::to_string(&report).expect("report serialises"));
    } else {
        print_text(&report);
    }
    if let Some(reason) = &report.reason {
        eprintln!("clearview align: {}: rejected: {reason}", args.view.display());
        return exit::REJECTED;
    }
    exit::OK
}

fn print_text(r: &Report<'_>) {
    println!("keyframe {} ({}x{})", r.key.display(), r.key_size[0], r.key_size[1]);
    println!("view     {} ({}x{})", r.view.display(), r.view_size[0], r.view_size[1]);
    if let Some(Rows(h)) = &r.homography {
        println!("homography (keyframe -> view):");
        for row in h {
            println!("  {:>14.8e} {:>14.8e} {:>14.8e}", row[0], row[1], row[2]);
        }
    }
    println!(
        "putative matches {}  guided matches {} of {} points  inliers {}  median residual {}  coverage {:.0} %  time {:.1} ms",
        r.putative_matches,
        r.matches,
        r.checked,
        r.inliers,
        r.median_residual_px.map_or("n/a".into(), |m| format!("{m:.2} px")),
        100.0 * r.coverage,
        r.time_ms
    );
    println!(
        "verdict  {}",
        if r.accepted {
            "accepted".to_string()
        } else {
            format!("rejected: {}", r.reason.as_deref().unwrap_or(""))
        }
    );
}
