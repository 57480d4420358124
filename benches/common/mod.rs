//! The rendered pair the alignment benchmark, `examples/align_12mp.rs` and
//! `examples/bench_pair.rs` share, so that clearview and the OpenCV peer
//! (`bench/align_peer.py`) time identical pixels.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use clearview::geometry::Homography;
use clearview::imaging::RgbF32;
use clearview::synth;

/// A keyframe and a view of a rendered facade, `width × height`, related by a moderate
/// camera motion (`truth` maps keyframe pixels to view pixels), quantised to 8 bits per
/// channel (what a PNG of them holds).
pub struct Pair {
    pub key: RgbF32,
    pub view: RgbF32,
    pub truth: Homography,
}

pub fn pair(width: usize, height: usize) -> Pair {
    let scene = synth::facade(width, height, 99);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let h = synth::random_homography(&mut rng, width, height, 0.1, 0.2, (0.9, 1.1));
    let view = synth::render_view(&scene, &h.inverse().unwrap(), width, height, [0.5; 3]);
    Pair { key: quantise(scene), view: quantise(view), truth: h }
}

fn quantise(mut img: RgbF32) -> RgbF32 {
    for p in img.as_mut_slice() {
        for c in p.iter_mut() {
            *c = (c.clamp(0.0, 1.0) * 255.0).round() / 255.0;
        }
    }
    img
}
