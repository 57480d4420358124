//! Wall and CPU time of aligning the benchmark's rendered pair, for a machine shared
//! with other work: the wall time per pair depends on how much of the two cores this
//! process gets, the CPU time (user + system over all threads, from `/proc/self/stat`)
//! much less. Each iteration does what `cargo bench --bench align` times: luminance of
//! both decoded 8-bit images, both frames, the alignment.
//!
//! `cargo run --release --example align_cpu -- WIDTH HEIGHT ITERATIONS`

#[path = "../benches/common/mod.rs"]
mod common;

use anyhow::{Context, Result, bail};
use clearview::align::{AlignParams, Frame, align};
use clearview::imaging::convert::{to_luminance, to_rgb8};
use image::DynamicImage;

/// User + system CPU time of the whole process so far, ms (clock ticks of 10 ms, so only
/// sums over many iterations are meaningful).
fn cpu_ms() -> Result<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat")?;
    let fields: Vec<&str> = stat.rsplit(')').next().context("stat")?.split_whitespace().collect();
    let ticks: f64 = fields[11].parse::<f64>()? + fields[12].parse::<f64>()?;
    Ok(ticks * 10.0)
}

fn main() -> Result<()> {
    let args: Vec<usize> = std::env::args().skip(1).map(|a| a.parse()).collect::<Result<_, _>>()?;
    let [width, height, n] = args.as_slice() else {
        bail!("usage: align_cpu WIDTH HEIGHT ITERATIONS");
    };
    let (width, height, n) = (*width, *height, (*n).max(1));
    let pair = common::pair(width, height);
    let key = DynamicImage::ImageRgb8(to_rgb8(&pair.key));
    let view = DynamicImage::ImageRgb8(to_rgb8(&pair.view));
    let params = AlignParams::default();
    let mut walls = Vec::with_capacity(n);
    let (mut lum, mut frames) = (Vec::with_capacity(n), Vec::with_capacity(n));
    let cpu0 = cpu_ms()?;
    for _ in 0..n {
        let t0 = std::time::Instant::now();
        let (gk, gv) = (to_luminance(&key), to_luminance(&view));
        let t1 = std::time::Instant::now();
        let (kf, vf) = (Frame::new(gk, &params), Frame::new(gv, &params));
        let t2 = std::time::Instant::now();
        let a = align(&kf, &vf, &params, None);
        let t3 = std::time::Instant::now();
        let err = a.homography.map_or(f64::INFINITY, |h| h.mean_corner_error(&pair.truth, width, height));
        if !a.accepted() || err > 1.0 {
            bail!("wrong answer: accepted {} error {err:.3} px", a.accepted());
        }
        walls.push((t3 - t0).as_secs_f64() * 1e3);
        lum.push((t1 - t0).as_secs_f64() * 1e3);
        frames.push((t2 - t1).as_secs_f64() * 1e3);
    }
    let cpu = (cpu_ms()? - cpu0) / n as f64;
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!(
        "{width}x{height}: {n} iterations, wall median {:.1} ms (luminance {:.1}, frames {:.1}), CPU {cpu:.1} ms per pair",
        median(&mut walls),
        median(&mut lum),
        median(&mut frames)
    );
    Ok(())
}
