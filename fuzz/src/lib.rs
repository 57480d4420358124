//! What each fuzz target does with its bytes (test harness, outside the library): the
//! same functions run under libFuzzer (`fuzz/fuzz_targets/*.rs`) and over the kept
//! regression inputs in `cargo test` (`tests/fuzz_regressions.rs` includes this file).
//!
//! Each function must return, whatever the bytes: `Ok` or the library's refusal in words
//! (`Err`). A panic, a hang or an absurd allocation is a bug in clearview. Sizes are kept small (a low pixel limit, tiny
//! keyframes) so the fuzzer explores code rather than allocating.

use std::path::Path;
use std::sync::OnceLock;

use clearview::align::{AlignParams, Frame, align as align_pair};
use clearview::config::Config;
use clearview::daemon::job::decode_as;
use clearview::daemon::state;
use clearview::daemon::watch::Role;
use clearview::geometry::Homography;
use clearview::imaging::convert::{luminance, to_luminance, to_mask, to_rgb};
use clearview::imaging::decode::DecodeLimits;
use clearview::imaging::{GrayF32, Mask, RgbF32};
use clearview::session::{Rgb8, Session, SessionParams};
use clearview::synth;

/// Pixel limit of the decoding targets: 512 × 512.
pub const MAX_PIXELS: u64 = 1 << 18;

/// Pixel limit of images fed to the alignment: 256 × 256.
pub const ALIGN_MAX_PIXELS: u64 = 1 << 16;

/// Size of the fixed keyframe the alignment, mask and state targets use.
pub const KEY_W: usize = 160;
pub const KEY_H: usize = 120;

/// The fixed keyframe: a rendered facade.
pub fn key_rgb() -> &'static RgbF32 {
    static KEY: OnceLock<RgbF32> = OnceLock::new();
    KEY.get_or_init(|| synth::facade(KEY_W, KEY_H, 7))
}

fn key_frame() -> &'static Frame {
    static FRAME: OnceLock<Frame> = OnceLock::new();
    FRAME.get_or_init(|| Frame::new(luminance(key_rgb()), &AlignParams::default()))
}

/// A session on the fixed keyframe with small parameters.
fn session() -> Session {
    let params = SessionParams { margin_px: 8, min_new_pixels: 4, ..SessionParams::default() };
    let mut s = Session::new(params);
    s.set_key("key|1|1".into(), key_rgb().clone());
    s
}

/// Image loading as the service and the commands do it: decode (limits, EXIF
/// orientation), the service's conversion per role, the commands' float conversions.
pub fn decode(data: &[u8]) -> Result<(), String> {
    let limits = DecodeLimits { max_pixels: MAX_PIXELS };
    match decode_as(data, Role::View, &limits) {
        Ok(img) => {
            let (w, h) = (img.width() as usize, img.height() as usize);
            assert!(w > 0 && h > 0 && (w * h) as u64 <= MAX_PIXELS, "{w}x{h} passed the limits");
            let gray = to_luminance(&img);
            let rgb = to_rgb(&img);
            assert_eq!((gray.width(), gray.height(), rgb.width(), rgb.height()), (w, h, w, h));
            assert!(gray.as_slice().iter().all(|v| v.is_finite()));
        }
        Err(e) => return Err(e.to_string()),
    }
    let m = decode_as(data, Role::Mask, &limits).map_err(|e| e.to_string())?;
    let mask = to_mask(&m);
    assert_eq!((mask.width(), mask.height()), (m.width() as usize, m.height() as usize));
    Ok(())
}

/// Raw grey pixels: a width and a height byte (1..=256 each), then pixel values, cycled.
fn raw_gray(data: &[u8]) -> Option<GrayF32> {
    let (&[w, h], pixels) = data.split_first_chunk::<2>()?;
    let (w, h) = (usize::from(w) + 1, usize::from(h) + 1);
    Some(GrayF32::from_fn(w, h, |x, y| {
        if pixels.is_empty() { 0.0 } else { f32::from(pixels[(y * w + x) % pixels.len()]) / 255.0 }
    }))
}

/// A prior near the identity from 8 bytes (what a previous view's homography looks like),
/// or anything when the bytes say so.
fn prior(b: &[u8; 8]) -> Option<Homography> {
    let s = |v: u8| f64::from(v as i8) / 128.0;
    let rows = if b[0] & 1 == 0 {
        [
            [1.0 + 0.3 * s(b[1]), 0.3 * s(b[2]), 60.0 * s(b[3])],
            [0.3 * s(b[4]), 1.0 + 0.3 * s(b[5]), 60.0 * s(b[6])],
            [0.002 * s(b[7]), 0.002 * s(b[0] & 0xfe), 1.0],
        ]
    } else {
        let e = |v: u8| f64::from(v as i8) * 10f64.powi(i32::from(v % 13) - 6);
        [[e(b[1]), e(b[2]), e(b[3])], [e(b[4]), e(b[5]), e(b[6])], [e(b[7]), e(b[0]), 1.0]]
    };
    Homography::from_rows(rows)
}

/// Alignment of arbitrary pixels. The first byte picks the mode: the view decoded from
/// the rest as a file (`% 3 == 0`), the view as raw pixels (`1`), or both keyframe and
/// view as raw pixels (`2`); bit 7 takes a prior from the next 8 bytes.
pub fn align(data: &[u8]) -> Result<(), String> {
    let Some((&mode, mut rest)) = data.split_first() else { return Err("no mode byte".into()) };
    let params = AlignParams::default();
    let mut guess = None;
    if mode & 0x80 != 0 {
        let Some((b, r)) = rest.split_first_chunk::<8>() else { return Err("no prior".into()) };
        guess = prior(b);
        rest = r;
    }
    let own_key;
    let (key, view) = match mode % 3 {
        0 => {
            let limits = DecodeLimits { max_pixels: ALIGN_MAX_PIXELS };
            let img = decode_as(rest, Role::View, &limits).map_err(|e| e.to_string())?;
            (key_frame(), to_luminance(&img))
        }
        1 => {
            let v = raw_gray(rest).ok_or("no size")?;
            (key_frame(), v)
        }
        _ => {
            let (a, b) = rest.split_at(rest.len() / 2);
            let (Some(k), Some(v)) = (raw_gray(a), raw_gray(b)) else { return Err("no size".into()) };
            own_key = Frame::new(k, &params);
            (&own_key, v)
        }
    };
    let view = Frame::new(view, &params);
    let a = align_pair(key, &view, &params, guess.as_ref());
    if a.accepted() {
        let h = a.homography.expect("an accepted alignment has a homography");
        assert!(h.matrix().iter().all(|v| v.is_finite()));
    }
    match a.rejection {
        Some(r) => Err(r.to_string()),
        None => Ok(()),
    }
}

/// Configuration text: parse and validate; errors must render.
pub fn config(data: &[u8]) -> Result<(), String> {
    let text = String::from_utf8_lossy(data);
    match Config::parse(&text, Path::new("fuzz.toml")) {
        Ok(c) => {
            let _ = format!("{c:?}");
            Ok(())
        }
        Err(e) => Err(e.to_string()),
    }
}

/// A mask file for the fixed keyframe: decoded as the service decodes masks, set on a
/// session (wrong sizes are refused) and, when taken, filled from the keyframe alone.
pub fn mask(data: &[u8]) -> Result<(), String> {
    let limits = DecodeLimits { max_pixels: MAX_PIXELS };
    let img = decode_as(data, Role::Mask, &limits).map_err(|e| e.to_string())?;
    let mut s = session();
    let mask = to_mask(&img);
    let right_size = (mask.width(), mask.height()) == (KEY_W, KEY_H);
    match s.set_mask("mask|1|1".into(), mask) {
        Ok(_) => {
            assert!(right_size);
            let out = s.fill(&mut ()).expect("a keyframe and a mask");
            if let Some(image) = out.image {
                assert_eq!((image.width(), image.height()), (KEY_W, KEY_H));
                assert!(image.as_slice().iter().flatten().all(|v| v.is_finite()));
            }
            Ok(())
        }
        Err(e) => {
            assert!(!right_size, "{e}");
            Err(e.to_string())
        }
    }
}

/// A saved session state: parsed as the service loads it, then its alignments taken as
/// the service takes them (trusted for a view of the recorded size) and a fill.
pub fn state(data: &[u8]) -> Result<(), String> {
    let mut saved = state::parse(data).map_err(|e| e.to_string())?;
    let mut s = session();
    let hole =
        Mask::from_fn(
            KEY_W,
            KEY_H,
            |x, y| if (60..100).contains(&x) && (40..80).contains(&y) { 255 } else { 0 },
        );
    s.set_mask("mask|1|1".into(), hole).expect("the keyframe's size");
    let key_id = s.key_id().expect("a keyframe").to_owned();
    for (id, a) in saved.alignments.iter().take(8) {
        let (w, h) = a.record.view_size;
        let small = w > 0 && h > 0 && w.checked_mul(h).is_some_and(|n| n <= ALIGN_MAX_PIXELS as usize);
        let pixels = Rgb8::from_fn(if small { w } else { 8 }, if small { h } else { 8 }, |x, y| {
            [(x * 7) as u8, (y * 5) as u8, 128]
        });
        let _ = saved.alignment(id, &a.key);
        if let Err(e) = s.admit(id.clone(), a.record.clone(), Some(&pixels)) {
            let _ = e.to_string();
        }
    }
    if let Some(r) = &saved.result {
        s.assume_result(r.score);
    }
    if s.needs_fill() {
        let _ = s.fill(&mut ());
    }
    // The service counts on from loaded counters: the next save and the next result.
    assert!(saved.last_number.checked_add(1).is_some(), "result number {} cannot grow", saved.last_number);
    if let Some(a) = saved.alignments.values().next().cloned() {
        let before = saved.seq;
        saved.remember("view|2|2".into(), key_id, a.record);
        assert!(saved.seq > before, "save counter {before} did not grow");
    }
    Ok(())
}
