//! Speed of the single-image fallback (`inpaint::exemplar_fill`) on rendered facades: a
//! 2000×1500 frame with a 200×300 hole, and a 12 MP frame with a hole of 15 % of it (the
//! worst case the fallback should meet: all of a large occluder seen by no view).
//!
//! `cargo bench --bench exemplar`

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};

use clearview::imaging::{Mask, RgbF32};
use clearview::inpaint::{ExemplarParams, exemplar_fill};
use clearview::synth;

/// A rendered facade of `width × height` and a rectangular hole of `hw × hh` centred in it.
fn scene(width: usize, height: usize, hw: usize, hh: usize) -> (RgbF32, Mask) {
    let image = synth::facade(width, height, 21);
    let (x0, y0) = ((width - hw) / 2, (height - hh) / 2);
    let hole =
        Mask::from_fn(
            width,
            height,
            |x, y| {
                if x >= x0 && x < x0 + hw && y >= y0 && y < y0 + hh { 255 } else { 0 }
            },
        );
    (image, hole)
}

fn bench_fill(c: &mut Criterion, name: &str, image: RgbF32, hole: Mask) {
    let params = ExemplarParams::default();
    let masked = hole.hole_count();
    c.bench_function(name, |b| {
        b.iter_batched_ref(
            || image.clone(),
            |img| {
                let n = exemplar_fill(img, &hole, &params, 1);
                assert_eq!(n, masked);
            },
            BatchSize::LargeInput,
        )
    });
}

fn benches(c: &mut Criterion) {
    let (image, hole) = scene(2000, 1500, 200, 300);
    bench_fill(c, "exemplar 2000x1500, 200x300 hole", image, hole);
    // 4000 × 3000 with a 1550 × 1161 hole: 15.0 % of the frame.
    let (image, hole) = scene(4000, 3000, 1550, 1161);
    bench_fill(c, "exemplar 12 MP, 15 % hole", image, hole);
}

criterion_group! {
    name = exemplar_benches;
    config = Criterion::default().sample_size(10).measurement_time(std::time::Duration::from_secs(10));
    targets = benches
}
criterion_main!(exemplar_benches);
