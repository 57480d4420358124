//! Peak memory of aligning the benchmark's 12 MP pair (4000×3000, already decoded): renders
//! the pair, then converts both images to luminance, builds both frames and aligns them
//! once, reporting resident memory from `/proc/self/status` before and the peak after.
//! The peak is reset after rendering (`5` into `/proc/self/clear_refs`), so the reported
//! increase is what alignment adds on top of the decoded images.
//!
//! `cargo run --release --example align_12mp [-- WIDTH HEIGHT]`
//! (`/usr/bin/time -v` on it gives the whole process's peak as a cross-check.)

#[path = "../benches/common/mod.rs"]
mod common;

use anyhow::{Context, Result};
use clearview::align::{AlignParams, Frame, align};
use clearview::imaging::convert::luminance;

/// A `kB` field of `/proc/self/status`, in MB.
fn status_mb(field: &str) -> Result<f64> {
    let status = std::fs::read_to_string("/proc/self/status")?;
    let line = status.lines().find(|l| l.starts_with(field)).with_context(|| format!("no {field}"))?;
    let kb: f64 = line.split_whitespace().nth(1).context("no value")?.parse()?;
    Ok(kb / 1024.0)
}

fn main() -> Result<()> {
    let args: Vec<usize> = std::env::args().skip(1).map(|a| a.parse()).collect::<Result<_, _>>()?;
    let (width, height) = match args.as_slice() {
        [w, h] => (*w, *h),
        _ => (4000, 3000),
    };
    let pair = common::pair(width, height);
    let rendered = status_mb("VmRSS:")?;
    let render_peak = status_mb("VmHWM:")?;
    std::fs::write("/proc/self/clear_refs", "5").context("resetting the peak (Linux ≥ 4.0)")?;
    let params = AlignParams::default();
    let start = std::time::Instant::now();
    let key = Frame::new(luminance(&pair.key), &params);
    let view = Frame::new(luminance(&pair.view), &params);
    let a = align(&key, &view, &params, None);
    let ms = start.elapsed().as_secs_f64() * 1e3;
    let peak = status_mb("VmHWM:")?;
    let err = a.homography.map_or(f64::INFINITY, |h| h.mean_corner_error(&pair.truth, width, height));
    println!(
        "{width}x{height}: accepted {} error {err:.3} px in {ms:.0} ms; RSS after rendering {rendered:.0} MB \
         (rendering peak {render_peak:.0} MB); peak during alignment {peak:.0} MB; increase {:.0} MB",
        a.accepted(),
        peak - rendered
    );
    Ok(())
}
