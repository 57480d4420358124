//! Writes the benchmark's rendered pair as PNGs (and its true homography) so the OpenCV
//! peer in `bench/align_peer.py` times exactly the pixels `cargo bench --bench align` does.
//!
//! `cargo run --release --example bench_pair -- WIDTH HEIGHT OUT_DIR`
//! writes `OUT_DIR/key.png`, `OUT_DIR/view.png` and `OUT_DIR/H` (keyframe → view, three
//! rows of three numbers, the Oxford layout).

#[path = "../benches/common/mod.rs"]
mod common;

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clearview::imaging::convert::to_rgb8;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [w, h, out] = args.as_slice() else {
        bail!("usage: bench_pair WIDTH HEIGHT OUT_DIR");
    };
    let (width, height): (usize, usize) = (w.parse()?, h.parse()?);
    let out = PathBuf::from(out);
    std::fs::create_dir_all(&out).with_context(|| out.display().to_string())?;
    let pair = common::pair(width, height);
    to_rgb8(&pair.key).save(out.join("key.png"))?;
    to_rgb8(&pair.view).save(out.join("view.png"))?;
    let rows = pair.truth.rows();
    let text: String = rows.iter().map(|r| format!("{:.12e} {:.12e} {:.12e}\n", r[0], r[1], r[2])).collect();
    std::fs::write(out.join("H"), text)?;
    println!("wrote {} ({width}x{height})", out.display());
    Ok(())
}
