//! Alignment speed on rendered pairs: 1 MP and 12 MP (already decoded), the issue's
//! targets being 30 ms and 250 ms median on a 2-core machine. The images are held as
//! decoded 8-bit RGB (what `clearview align` has after decoding a JPEG or PNG); each
//! iteration converts both to luminance, builds both frames and aligns them, as the
//! command does: the whole cost of a new pair. `bench/run_align.sh` runs this beside the
//! OpenCV peer on the same pixels.
//!
//! `cargo bench --bench align`

mod common;

use criterion::{Criterion, criterion_group, criterion_main};

use clearview::align::{AlignParams, Frame, align};
use clearview::imaging::convert::{to_luminance, to_rgb8};
use image::DynamicImage;

fn bench_pair(c: &mut Criterion, name: &str, width: usize, height: usize) {
    let common::Pair { key, view, truth } = common::pair(width, height);
    let params = AlignParams::default();
    let (key, view) = (DynamicImage::ImageRgb8(to_rgb8(&key)), DynamicImage::ImageRgb8(to_rgb8(&view)));
    c.bench_function(name, |b| {
        b.iter(|| {
            let kf = Frame::new(to_luminance(&key), &params);
            let vf = Frame::new(to_luminance(&view), &params);
            let a = align(&kf, &vf, &params, None);
            assert!(a.accepted());
            a
        })
    });
    // A fast wrong answer is no answer: check the last one against the truth.
    let kf = Frame::new(to_luminance(&key), &params);
    let vf = Frame::new(to_luminance(&view), &params);
    let h = align(&kf, &vf, &params, None).homography.expect("accepted above");
    let err = h.mean_corner_error(&truth, width, height);
    assert!(err < 1.0, "{name}: mean corner error {err:.3} px");
}

fn benches(c: &mut Criterion) {
    bench_pair(c, "align 1 MP (1155x866)", 1155, 866);
    bench_pair(c, "align 12 MP (4000x3000)", 4000, 3000);
}

criterion_group! {
    name = align_benches;
    config = Criterion::default().sample_size(10).measurement_time(std::time::Duration::from_secs(8));
    targets = benches
}
criterion_main!(align_benches);
