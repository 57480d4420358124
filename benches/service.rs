//! The service's budget on 12 MP photographs (4000 × 3000):
//! - time from a JPEG view landing (bytes in memory: the quiet period is configuration,
//!   not work) to its updated result written, with 8 views already buffered: decode,
//!   align (from the previous view's homography when it helps), crop into the buffer,
//!   fill, encode and write atomically with the maps beside it (confidence, provenance,
//!   surfaces) — the worker's path. Target ≤ 1.5 s median, on a
//!   flat wall (`jpeg_12mp_view_to_result_8_buffered`) and on a facade with a pier standing
//!   off it, where every fill sweeps for the surfaces off the wall
//!   (`jpeg_12mp_depth_view_to_result_8_buffered`).
//! - resident memory with 16 buffered views (printed once before the timings). Target
//!   ≤ 1 GB.
//!
//! On the depth facade a landing whose fill the session judges no better than its current
//! result writes nothing (the time to that verdict is timed); each result written is
//! checked against the facade's truth instead, and the count of landings that kept the
//! current result is printed.
//!
//! `cargo bench --bench service`
//!
//! The timed session holds 9 views: each landing evicts the view that contributes least,
//! so every fill has the new view and 8 buffered ones. Before the twenty-ninth session it
//! held 16 and grew to them during the timing. The report before the timings gives one
//! pass by step and a few steady passes by stage of the fill. Figures: BENCHMARKS.md,
//! "Capture service".

use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use image::DynamicImage;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use clearview::config::Config;
use clearview::daemon::emit::Emitter;
use clearview::daemon::provenance::result_maps;
use clearview::imaging::convert::{crop_rgb8, to_luminance, to_rgb, to_rgb8};
use clearview::imaging::decode::{DecodeLimits, decode};
use clearview::imaging::metrics::masked_psnr;
use clearview::imaging::{Mask, Rect, RgbF32};
use clearview::inpaint::reduced::reduce_rgb;
use clearview::inpaint::{Observer, Stage};
use clearview::session::{Rgb8, Session, SessionParams};
use clearview::synth::{self, Occluder};

const W: usize = 4000;
const H: usize = 3000;

struct Shoot {
    key_png: Vec<u8>,
    mask: Mask,
    views: Vec<Vec<u8>>,
    /// The facade behind the keyframe's occluders and the mask, at a quarter of the size
    /// (`shoot_depth`): a landing may keep the current result there, and the timed loop
    /// checks each published result against the truth instead.
    truth: Option<(RgbF32, Mask)>,
}

fn jpeg(img: &RgbF32) -> Vec<u8> {
    jpeg_of(&to_rgb8(img))
}

fn jpeg_of(img: &image::RgbImage) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90).encode_image(img).unwrap();
    out.into_inner()
}

/// A 12 MP keyframe with a tree (about 4 % of the frame masked) and `n` views, each with
/// a passer-by, as JPEG bytes. The facade itself is dropped before anything is measured.
fn shoot(n: usize) -> Shoot {
    let scene = synth::facade(W, H, 77);
    let mut key = scene.clone();
    let mut mask = Mask::new(W, H, 0);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 2000.0, 1500.0, 900.0, 1);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let views = (0..n)
        .map(|i| {
            let h = synth::random_homography(&mut rng, W, H, 0.05, 0.1, (0.95, 1.05));
            let mut v = synth::render_view(&scene, &h.inverse().unwrap(), W, H, [0.5; 3]);
            synth::paint_occluder(
                &mut v,
                None,
                Occluder::Person,
                800.0 + 150.0 * i as f32,
                1700.0,
                700.0,
                10 + i as u64,
            );
            jpeg(&v)
        })
        .collect();
    let mut key_png = std::io::Cursor::new(Vec::new());
    to_rgb8(&key).write_to(&mut key_png, image::ImageFormat::Png).unwrap();
    Shoot { key_png: key_png.into_inner(), mask, views, truth: None }
}

/// The same session on a facade that is not flat: `synth::facade::parallax_case` (slabs
/// standing off the wall, a tree in front of the first in the keyframe, passers-by in the
/// views), rendered at 1000 × 750 and enlarged four times (as soft as a real 12 MP frame),
/// so that every fill sweeps for the surfaces off the wall and finds them.
fn shoot_depth(n: usize) -> Shoot {
    let case = synth::facade::parallax_case(W / 4, H / 4, n, 3, false);
    let big = |img: &RgbF32| {
        image::imageops::resize(&to_rgb8(img), W as u32, H as u32, image::imageops::FilterType::Triangle)
    };
    let mask = Mask::from_fn(W, H, |x, y| case.mask.get(x / 4, y / 4));
    let mut key_png = std::io::Cursor::new(Vec::new());
    big(&case.key).write_to(&mut key_png, image::ImageFormat::Png).unwrap();
    Shoot {
        key_png: key_png.into_inner(),
        mask,
        views: case.views.iter().map(|v| jpeg_of(&big(v))).collect(),
        truth: Some((case.truth.clone(), case.mask.clone())),
    }
}

/// The decoded view's pixels as the worker buffers them.
fn rgb8(img: &DynamicImage) -> Rgb8 {
    crop_rgb8(img, Rect::full(img.width() as usize, img.height() as usize))
}

/// Decode, align, admit: what a worker does with a view before the fill.
fn offer(session: &mut Session, id: String, bytes: &[u8]) {
    let img = decode(bytes, &DecodeLimits::default()).unwrap();
    let record = session.align(to_luminance(&img)).unwrap();
    assert!(record.accepted, "{:?}", record.reason);
    let pixels = rgb8(&img);
    drop(img);
    session.admit(id, record, Some(&pixels)).unwrap();
}

fn session_for(shoot: &Shoot, buffer: usize) -> Session {
    let mut s = Session::new(SessionParams { buffer, ..SessionParams::default() });
    let key = decode(&shoot.key_png, &DecodeLimits::default()).unwrap();
    s.set_key("key".into(), to_rgb(&key));
    s.set_mask("mask".into(), shoot.mask.clone()).unwrap();
    s
}

/// Wall time per stage of a fill, in the order they ran (a stage entered again adds up).
struct StageTimes {
    last: Option<(Stage, Instant)>,
    spent: Vec<(Stage, Duration)>,
}

impl StageTimes {
    fn new() -> Self {
        Self { last: None, spent: Vec::new() }
    }
    fn close(&mut self) {
        if let Some((stage, since)) = self.last.take() {
            match self.spent.iter_mut().find(|(s, _)| *s == stage) {
                Some((_, d)) => *d += since.elapsed(),
                None => self.spent.push((stage, since.elapsed())),
            }
        }
    }
    fn report(&mut self) -> String {
        self.close();
        let parts: Vec<String> =
            self.spent.iter().map(|(s, d)| format!("{} {:.0} ms", s.name(), d.as_secs_f64() * 1e3)).collect();
        parts.join(", ")
    }
}

impl Observer for StageTimes {
    fn stage(&mut self, stage: Stage) {
        self.close();
        self.last = Some((stage, Instant::now()));
    }
}

fn status_kb(field: &str) -> u64 {
    let text = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    text.lines()
        .find(|l| l.starts_with(field))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

fn memory_report(shoot: &Shoot) {
    // Reset the peak so that rendering the test images does not count.
    let _ = std::fs::write("/proc/self/clear_refs", "5");
    let base = status_kb("VmRSS:");
    let start = Instant::now();
    let mut s = session_for(shoot, 16);
    for (i, v) in shoot.views.iter().take(16).enumerate() {
        offer(&mut s, format!("v{i}"), v);
    }
    let crops: usize = s.buffered().iter().filter_map(|b| b.crop_size()).map(|(w, h)| w * h * 3).sum();
    let filled = s.fill(&mut ()).unwrap();
    let (rss, peak) = (status_kb("VmRSS:"), status_kb("VmHWM:"));
    eprintln!(
        "memory with {} buffered 12 MP views: resident {:.0} MB (process before the session {:.0} MB), \
         peak {:.0} MB; the crops hold {:.0} MB; from views {:.2}; built in {:.1} s",
        s.buffered().len(),
        rss as f64 / 1024.0,
        base as f64 / 1024.0,
        peak as f64 / 1024.0,
        crops as f64 / 1e6,
        filled.score,
        start.elapsed().as_secs_f64()
    );
}

fn bench(c: &mut Criterion) {
    // RUST_LOG=clearview::session=debug prints each fill's judgement against the current result.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .try_init();
    let shoot = shoot(17);
    if std::env::var_os("SKIP_MEMORY").is_none() {
        memory_report(&shoot);
    }
    session_bench(c, "jpeg_12mp_view_to_result_8_buffered", &shoot);
    drop(shoot);
    session_bench(c, "jpeg_12mp_depth_view_to_result_8_buffered", &shoot_depth(17));
}

/// The timed landing (`name`) on `shoot`, with one pass by step and a few steady passes
/// by stage of the fill printed first.
fn session_bench(c: &mut Criterion, name: &str, shoot: &Shoot) {
    eprintln!("{name}:");
    let out = tempfile::tempdir().unwrap();
    let config = Config { out_dir: out.path().to_owned(), ..Config::default() };
    let emitter = Emitter::open(&config).unwrap();
    // Each landing evicts the view that contributes least: every fill has the new view and
    // 8 buffered ones (with the default buffer of 16 the session grew to 16 during the
    // timing, and the figure was that of 16 views).
    let mut session = session_for(shoot, 9);
    for (i, v) in shoot.views.iter().take(8).enumerate() {
        offer(&mut session, format!("v{i}"), v);
    }
    // One pass broken into its steps, for the report.
    let t = Instant::now();
    let img = decode(&shoot.views[8], &DecodeLimits::default()).unwrap();
    let t_decode = t.elapsed();
    let t = Instant::now();
    let record = session.align(to_luminance(&img)).unwrap();
    let t_align = t.elapsed();
    let t = Instant::now();
    let pixels = rgb8(&img);
    session.admit("probe".into(), record, Some(&pixels)).unwrap();
    let t_admit = t.elapsed();
    let t = Instant::now();
    let outcome = session.fill(&mut ()).unwrap();
    let t_fill = t.elapsed();
    let t = Instant::now();
    let (maps, _) = result_maps(&session, &outcome);
    let t_maps = t.elapsed();
    let t = Instant::now();
    emitter
        .write_result("probe", 1, outcome.image.as_ref().unwrap(), None, &mut serde_json::json!({}), &maps)
        .unwrap();
    let t_write = t.elapsed();
    eprintln!(
        "one pass: decode {:.0} ms, align {:.0} ms, crop+admit {:.0} ms, fill {:.0} ms ({} masked, {} from the fallback), maps {:.0} ms, encode+write {:.0} ms",
        t_decode.as_secs_f64() * 1e3,
        t_align.as_secs_f64() * 1e3,
        t_admit.as_secs_f64() * 1e3,
        t_fill.as_secs_f64() * 1e3,
        outcome.report.masked,
        outcome.report.fallback,
        t_maps.as_secs_f64() * 1e3,
        t_write.as_secs_f64() * 1e3
    );
    drop((img, pixels, outcome, maps));
    // Steady passes: one new view each, as in the timed loop, with the fill's stages timed
    // (a view is judged for its own occluders again only when the views it is judged
    // against changed, so passes differ).
    for (k, bytes) in shoot.views[9..13].iter().enumerate() {
        let mut stages = StageTimes::new();
        let t = Instant::now();
        offer(&mut session, format!("steady{k}"), bytes);
        let t_offer = t.elapsed();
        let t = Instant::now();
        let outcome = session.fill(&mut stages).unwrap();
        eprintln!(
            "steady pass {k}: decode+align+admit {:.0} ms, fill {:.0} ms ({} views): {}",
            t_offer.as_secs_f64() * 1e3,
            t.elapsed().as_secs_f64() * 1e3,
            outcome.views.len(),
            stages.report()
        );
    }

    // Timed: from the bytes to the result written, or to the fill judged no better than
    // the current result (the service then writes nothing). On the flat wall every landing
    // is published. On the depth facade a fill may be judged worse with the views' own
    // occluders marked and not published; there each published result is checked against
    // the truth instead (outside the timing): it may not fall more than 0.3 dB below the
    // one before (issue 12's bound).
    let (mut n, mut kept, mut last) = (0u64, 0u64, None::<f64>);
    let mut g = c.benchmark_group("service");
    g.sample_size(10).measurement_time(Duration::from_secs(30)).warm_up_time(Duration::from_secs(3));
    g.bench_function(name, |b| {
        b.iter_custom(|iters| {
            let mut spent = Duration::ZERO;
            for _ in 0..iters {
                n += 1;
                // A new file each time (the same pixels under a new identity): aligned afresh.
                let bytes = &shoot.views[8 + (n as usize % 9)];
                let t = Instant::now();
                offer(&mut session, format!("new{n}"), bytes);
                let outcome = session.fill(&mut ()).unwrap();
                let Some(image) = outcome.image.as_ref() else {
                    spent += t.elapsed();
                    assert!(shoot.truth.is_some(), "score fell: {}", outcome.score);
                    kept += 1;
                    continue;
                };
                let (maps, _) = result_maps(&session, &outcome);
                emitter
                    .write_result("bench", n, image, None, &mut serde_json::json!({ "number": n }), &maps)
                    .unwrap();
                spent += t.elapsed();
                if let Some((truth, mask)) = &shoot.truth {
                    let now = masked_psnr(&reduce_rgb(image, 2), truth, mask);
                    assert!(last.is_none_or(|l| now >= l - 0.3), "result fell: {last:?} → {now:.2} dB");
                    last = Some(now);
                }
            }
            spent
        })
    });
    g.finish();
    if shoot.truth.is_some() {
        eprintln!(
            "{name}: {kept} of {n} timed landings kept the current result; the last published {:.2} dB against the truth",
            last.unwrap_or(f64::NAN)
        );
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
