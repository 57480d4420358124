//! Renders a large synthetic facade with trees in front to a PNG: the source image of the
//! video benchmark (`bench/video_stream.sh` pans a 1080p window over it with FFmpeg).
//!
//! `cargo run --release --example render_facade -- OUT.png [WIDTH HEIGHT]`

use clearview::imaging::convert::to_rgb8;
use clearview::synth::{self, Occluder};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let out = args.get(1).map_or("facade.png", String::as_str);
    let width = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(4800);
    let height = args.get(3).and_then(|a| a.parse().ok()).unwrap_or(1400);
    let mut img = synth::facade(width, height, 2026);
    // Trees along the street, painted on the facade (they move with it).
    for (i, x) in (400..width).step_by(1100).enumerate() {
        synth::paint_occluder(&mut img, None, Occluder::Tree, x as f32, height as f32 * 0.6, 380.0, i as u64);
    }
    to_rgb8(&img).save(out).unwrap_or_else(|e| panic!("{out}: {e}"));
    println!("{out}: {width}x{height}");
}
