//! The bad-input corpus of issue 7, generated here and fed to the real service
//! (`clearview run`). For every case: the service stays up, an event and a log line name
//! the file and say why it was refused (or that it was used), the other sessions go on
//! (a healthy session gets its results alongside), and no result already written is
//! damaged (unchanged, or replaced by a whole, no worse one).
//!
//! Most cases share one service and run as parallel sessions of one inbox; the flood of
//! 5 000 files and the growing file have a service each (their figures must not mix
//! with the rest). The minute-long growing file is `#[ignore]`d; a 20-second one runs
//! by default.

mod daemon_common;

use std::collections::{BTreeMap, HashMap};
use std::ffi::{OsStr, OsString};
use std::io::{Cursor, Write};
use std::os::unix::ffi::OsStrExt;
use std::path::Path;
use std::time::{Duration, Instant};

use clearview::imaging::convert::to_rgb8;
use clearview::imaging::{Mask, RgbF32};
use clearview::synth;
use daemon_common::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

// ---------------------------------------------------------------------------------------
// The corpus: bytes made here.

fn jpeg(img: &RgbF32) -> Vec<u8> {
    let mut out = Vec::new();
    to_rgb8(img)
        .write_with_encoder(image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 92))
        .unwrap();
    out
}

fn random_bytes(n: usize, seed: u64) -> Vec<u8> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random()).collect()
}

/// The first `share` of `bytes`.
fn cut(bytes: &[u8], share: f64) -> Vec<u8> {
    bytes[..(bytes.len() as f64 * share) as usize].to_vec()
}

/// CRC-32 (IEEE) as PNG chunks carry it.
fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in data {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xedb8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// A valid small PNG whose header (IHDR, CRC fixed up) declares `w × h`: a
/// decompression bomb as far as its header goes.
fn png_declaring(w: u32, h: u32) -> Vec<u8> {
    let mut p = png(&RgbF32::new(16, 16, [0.5; 3]));
    assert_eq!(&p[12..16], b"IHDR");
    p[16..20].copy_from_slice(&w.to_be_bytes());
    p[20..24].copy_from_slice(&h.to_be_bytes());
    let crc = crc32(&p[12..29]);
    p[29..33].copy_from_slice(&crc.to_be_bytes());
    p
}

/// A valid small JPEG whose frame header (SOF0) declares `w × h` (JPEG cannot say more
/// than 65 535).
fn jpeg_declaring(w: u16, h: u16) -> Vec<u8> {
    let mut j = jpeg(&RgbF32::new(16, 16, [0.5; 3]));
    let sof = j.windows(2).position(|m| m == [0xff, 0xc0]).expect("a baseline JPEG");
    j[sof + 5..sof + 7].copy_from_slice(&h.to_be_bytes());
    j[sof + 7..sof + 9].copy_from_slice(&w.to_be_bytes());
    j
}

/// The image's header (its first `keep` bytes) and then random bytes, as much again.
fn header_then_garbage(bytes: &[u8], keep: usize, seed: u64) -> Vec<u8> {
    let mut out = bytes[..keep].to_vec();
    out.extend(random_bytes(bytes.len() - keep, seed));
    out
}

fn png_16bit(img: &RgbF32) -> Vec<u8> {
    let raw: Vec<u16> =
        img.as_slice().iter().flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16)).collect();
    let buf =
        image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(img.width() as u32, img.height() as u32, raw)
            .unwrap();
    let mut out = Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb16(buf).write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

fn png_grey(img: &RgbF32) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb8(to_rgb8(img))
        .to_luma8()
        .write_to(&mut out, image::ImageFormat::Png)
        .unwrap();
    out.into_inner()
}

fn png_rgba(img: &RgbF32) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb8(to_rgb8(img))
        .to_rgba8()
        .write_to(&mut out, image::ImageFormat::Png)
        .unwrap();
    out.into_inner()
}

/// A four-component (CMYK, Adobe) JPEG as print workflows write them.
fn jpeg_cmyk(img: &RgbF32) -> Vec<u8> {
    let rgb = to_rgb8(img);
    let cmyk: Vec<u8> = rgb.pixels().flat_map(|p| [255 - p[0], 255 - p[1], 255 - p[2], 0]).collect();
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, 92)
        .encode(&cmyk, rgb.width() as u16, rgb.height() as u16, jpeg_encoder::ColorType::Cmyk)
        .unwrap();
    out
}

/// An indexed-colour PNG (a 6 × 6 × 6 colour cube).
fn png_palette(img: &RgbF32) -> Vec<u8> {
    let level = |v: f32| (v.clamp(0.0, 1.0) * 5.0).round() as u8;
    let indices: Vec<u8> =
        img.as_slice().iter().map(|p| level(p[0]) * 36 + level(p[1]) * 6 + level(p[2])).collect();
    let palette: Vec<u8> =
        (0..216u32).flat_map(|i| [i / 36, i / 6 % 6, i % 6].map(|l| (l * 51) as u8)).collect();
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, img.width() as u32, img.height() as u32);
    enc.set_color(png::ColorType::Indexed);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_palette(palette);
    enc.write_header().unwrap().write_image_data(&indices).unwrap();
    out
}

/// `upright` stored as a camera held at EXIF orientation `o` stores it, with the tag.
fn with_orientation(upright: &RgbF32, o: u16, as_jpeg: bool) -> Vec<u8> {
    use image::ImageEncoder;
    let stored = to_rgb8(&synth::stored_for_orientation(upright, o));
    let mut out = Vec::new();
    let (w, h) = (stored.width(), stored.height());
    let t = image::ExtendedColorType::Rgb8;
    if as_jpeg {
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 92);
        enc.set_exif_metadata(synth::exif_orientation(o)).unwrap();
        enc.write_image(stored.as_raw(), w, h, t).unwrap();
    } else {
        let mut enc = image::codecs::png::PngEncoder::new(&mut out);
        enc.set_exif_metadata(synth::exif_orientation(o)).unwrap();
        enc.write_image(stored.as_raw(), w, h, t).unwrap();
    }
    out
}

fn blurred(img: &RgbF32, sigma: f32) -> Vec<u8> {
    let b = image::imageops::blur(&to_rgb8(img), sigma);
    let mut out = Cursor::new(Vec::new());
    b.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

// ---------------------------------------------------------------------------------------
// What the service said.

/// What a case must come to.
#[derive(Debug, Clone, Copy)]
enum Want {
    /// Refused before alignment (`file_skipped`), the reason containing this.
    Skipped(&'static str),
    /// Aligned and refused (`view_rejected`), the reason containing this.
    Rejected(&'static str),
    /// Refused, before or after alignment, with a reason containing this.
    Refused(&'static str),
    /// Aligned and buffered (`view_accepted`).
    Used,
}

struct Case {
    session: &'static str,
    name: OsString,
    what: &'static str,
    bytes: Vec<u8>,
    want: Want,
}

impl Case {
    fn new(
        session: &'static str,
        name: impl AsRef<OsStr>,
        what: &'static str,
        bytes: Vec<u8>,
        want: Want,
    ) -> Self {
        Self { session, name: name.as_ref().to_owned(), what, bytes, want }
    }

    /// The name as events carry it (lossy for bytes that are not UTF-8).
    fn shown(&self) -> String {
        self.name.to_string_lossy().into_owned()
    }
}

/// The decisive events about `file` in `session`.
fn outcome<'a>(ev: &'a [Value], session: &str, file: &str) -> Vec<&'a Value> {
    ev.iter()
        .filter(|e| e["session"] == session && e["file"] == file)
        .filter(|e| {
            ["file_skipped", "view_rejected", "view_accepted"].contains(&e["event"].as_str().unwrap_or(""))
        })
        .collect()
}

/// How the log shows a file name: control characters escaped, so a name cannot break a
/// log line.
fn logged(name: &str) -> String {
    name.chars()
        .map(|c| if c.is_control() { c.escape_default().to_string() } else { c.to_string() })
        .collect()
}

/// Fails unless a line of `log` names `file` and contains `words`.
fn log_says(log: &str, file: &str, words: &str) {
    let file = logged(file);
    assert!(
        log.lines().any(|l| l.contains(&file) && l.contains(words)),
        "no log line names {file} with {words:?}; log:\n{log}"
    );
}

fn sha(path: &Path) -> Option<Vec<u8>> {
    std::fs::read(path).ok()
}

fn result_json(f: &Folders, session: &str) -> Option<Value> {
    serde_json::from_slice(&std::fs::read(f.outbox.join(session).join("result.json")).ok()?).ok()
}

/// The service's peak resident memory (VmHWM), bytes.
fn peak_rss(pid: u32) -> u64 {
    status_field(pid, "VmHWM:")
}

fn rss(pid: u32) -> u64 {
    status_field(pid, "VmRSS:")
}

fn status_field(pid: u32, field: &str) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = s.lines().find(|l| l.starts_with(field)).unwrap();
    line.split_whitespace().nth(1).unwrap().parse::<u64>().unwrap() * 1024
}

fn open_fds(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).map(|d| d.count()).unwrap_or(0)
}

/// A session with its keyframe, mask and a first view, for a result to exist before the
/// bad input comes.
fn start_session(f: &Folders, name: &str, seed: u64) -> Scene {
    let mut s = Scene::new(seed);
    let dir = f.inbox.join(name);
    put_key_and_mask(&dir, &s);
    put(&dir.join("v1.png"), &png(&s.view(1, 120.0, 60.0)));
    s
}

fn put_os(dir: &Path, name: &OsStr, bytes: &[u8]) {
    std::fs::create_dir_all(dir).unwrap();
    let mut tmp = OsString::from(".");
    tmp.push(name);
    tmp.push(".upload");
    std::fs::write(dir.join(&tmp), bytes).unwrap();
    std::fs::rename(dir.join(&tmp), dir.join(name)).unwrap();
}

// ---------------------------------------------------------------------------------------

#[test]
fn every_bad_file_is_refused_or_used_with_a_reason_and_no_result_is_damaged() {
    let t0 = Instant::now();
    let f = folders("workers = 2\n");
    let mut service = Service::start(&f);
    let pid = service.child.id();

    // Sessions with a first result before anything bad arrives; `healthy` gets nothing
    // bad and must go on getting results.
    let with_results = ["healthy", "junk", "scenes", "formats", "exif", "names", "unmask", "rekey"];
    let mut scenes: BTreeMap<&str, Scene> = BTreeMap::new();
    for (i, s) in with_results.iter().enumerate() {
        scenes.insert(s, start_session(&f, s, 700 + i as u64));
    }
    // Sessions whose masks are bad: a keyframe and a view, then the mask.
    for (i, s) in ["mask_size", "mask_black", "mask_white"].iter().enumerate() {
        let mut sc = Scene::new(800 + i as u64);
        let dir = f.inbox.join(s);
        put(&dir.join("key.png"), &png(&sc.key));
        put(&dir.join("v1.png"), &png(&sc.view(1, 120.0, 60.0)));
        scenes.insert(s, sc);
    }
    let ev = wait_for(&f, "a first result in every session", 60, |e| {
        with_results.iter().all(|s| of_kind(e, "result_updated").iter().any(|r| r["session"] == *s))
    });
    let first_results = ev.len();
    let before: HashMap<&str, (Vec<u8>, Value)> = with_results
        .iter()
        .map(|s| {
            let dir = f.outbox.join(s);
            (*s, (sha(&dir.join("result.png")).unwrap(), result_json(&f, s).unwrap()))
        })
        .collect();
    eprintln!("[{:.1} s] first results", t0.elapsed().as_secs_f64());
    let peak_before = peak_rss(pid);

    // The corpus.
    let mut cases = Vec::new();
    {
        let sc = scenes.get_mut("junk").unwrap();
        let view = sc.view(2, 300.0, 60.0);
        let (p, j) = (png(&view), jpeg(&view));
        cases.push(Case::new("junk", "empty.png", "zero-byte PNG", Vec::new(), Want::Skipped("empty")));
        cases.push(Case::new("junk", "empty.jpg", "zero-byte JPEG", Vec::new(), Want::Skipped("empty")));
        for (share, tag) in [(0.1, "10"), (0.5, "50"), (0.9, "90")] {
            let what: &'static str = Box::leak(format!("PNG cut at {tag} %").into_boxed_str());
            cases.push(Case::new("junk", format!("cut{tag}.png"), what, cut(&p, share), Want::Skipped("")));
            let what: &'static str = Box::leak(format!("JPEG cut at {tag} %").into_boxed_str());
            cases.push(Case::new(
                "junk",
                format!("cut{tag}.jpg"),
                what,
                cut(&j, share),
                Want::Skipped("cut short"),
            ));
        }
        cases.push(Case::new(
            "junk",
            "noise.jpg",
            "random bytes as .jpg",
            random_bytes(50_000, 1),
            Want::Skipped("not an image"),
        ));
        cases.push(Case::new(
            "junk",
            "noise.png",
            "random bytes as .png",
            random_bytes(50_000, 2),
            Want::Skipped("not an image"),
        ));
        cases.push(Case::new(
            "junk",
            "garbage.png",
            "PNG header, then garbage",
            header_then_garbage(&p, 64, 3),
            Want::Skipped(""),
        ));
        cases.push(Case::new(
            "junk",
            "garbage.jpg",
            "JPEG header, then garbage",
            header_then_garbage(&j, 700, 4),
            Want::Refused(""),
        ));
        cases.push(Case::new(
            "junk",
            "bomb.png",
            "PNG declaring 100 000 x 100 000",
            png_declaring(100_000, 100_000),
            Want::Skipped("more than the limit"),
        ));
        cases.push(Case::new(
            "junk",
            "bomb.jpg",
            "JPEG declaring 65 535 x 65 535",
            jpeg_declaring(65_535, 65_535),
            Want::Skipped("more than the limit"),
        ));
    }
    {
        let sc = scenes.get_mut("scenes").unwrap();
        let other = Scene::new(4242);
        cases.push(Case::new(
            "scenes",
            "other.png",
            "a view of another scene",
            png(&other.key),
            Want::Rejected(""),
        ));
        let v = sc.clear_view(3);
        cases.push(Case::new(
            "scenes",
            "blurred.png",
            "a view blurred beyond any corner",
            blurred(&v, 12.0),
            Want::Refused(""),
        ));
        cases.push(Case::new(
            "scenes",
            "same.png",
            "the keyframe's own file again",
            png(&sc.key),
            Want::Rejected("adds nothing"),
        ));
        cases.push(Case::new(
            "scenes",
            "v1-copy.png",
            "a buffered view's file again under another name",
            std::fs::read(f.inbox.join("scenes/v1.png")).unwrap(),
            Want::Rejected("already buffered: v1.png"),
        ));
        cases.push(Case::new(
            "scenes",
            "tiny.png",
            "1 x 1",
            png(&RgbF32::new(1, 1, [0.5; 3])),
            Want::Skipped("too small"),
        ));
        let wide =
            RgbF32::from_fn(20_000, 50, |x, y| [((x / 7 + y / 5) % 2) as f32, 0.5, (x % 13) as f32 / 13.0]);
        cases.push(Case::new("scenes", "wide.png", "20 000 x 50", png(&wide), Want::Skipped("strip")));
    }
    {
        let sc = scenes.get_mut("formats").unwrap();
        let vs: Vec<RgbF32> = (2..=6).map(|i| sc.view(i, 60.0 + 60.0 * i as f32, 50.0)).collect();
        cases.push(Case::new("formats", "deep.png", "16-bit RGB PNG", png_16bit(&vs[0]), Want::Used));
        cases.push(Case::new("formats", "rgba.png", "RGBA PNG", png_rgba(&vs[1]), Want::Used));
        cases.push(Case::new("formats", "cmyk.jpg", "CMYK JPEG", jpeg_cmyk(&vs[2]), Want::Used));
        cases.push(Case::new("formats", "palette.png", "palette PNG", png_palette(&vs[3]), Want::Used));
        // Read, aligned, and turned down: a black-and-white view has no colour to give the
        // colour keyframe (what it filled took one tint from around the hole).
        cases.push(Case::new(
            "formats",
            "grey.png",
            "grey PNG",
            png_grey(&vs[4]),
            Want::Rejected("a black-and-white picture of a colour keyframe"),
        ));
    }
    {
        let sc = scenes.get_mut("exif").unwrap();
        for o in 1..=8u16 {
            let v = sc.view(10 + u64::from(o), 40.0 * o as f32, 50.0);
            let as_jpeg = o % 2 == 0;
            let name = format!("turned{o}.{}", if as_jpeg { "jpg" } else { "png" });
            let what: &'static str = Box::leak(format!("EXIF orientation {o}").into_boxed_str());
            cases.push(Case::new("exif", name, what, with_orientation(&v, o, as_jpeg), Want::Used));
        }
    }
    {
        let sc = scenes.get_mut("names").unwrap();
        let names: [(&[u8], &'static str); 3] = [
            (b"with space.png", "a name with spaces"),
            (b"caf\xe9 \xff.png", "a name that is not UTF-8"),
            (b"new\nline.png", "a name with a newline"),
        ];
        for (i, (name, what)) in names.into_iter().enumerate() {
            let v = sc.view(20 + i as u64, 100.0 + 80.0 * i as f32, 50.0);
            cases.push(Case::new("names", OsStr::from_bytes(name), what, png(&v), Want::Used));
        }
    }
    for c in &cases {
        put_os(&f.inbox.join(c.session), &c.name, &c.bytes);
    }

    // Masks: the wrong size, all black, all white.
    let wrong = Mask::new(W / 2, H / 2, 255);
    put(&f.inbox.join("mask_size/key.mask.png"), &mask_png(&wrong));
    put(&f.inbox.join("mask_black/key.mask.png"), &mask_png(&Mask::new(W, H, 0)));
    put(&f.inbox.join("mask_white/key.mask.png"), &mask_png(&Mask::new(W, H, 255)));
    // Mid-session: the mask deleted, the keyframe replaced.
    std::fs::remove_file(f.inbox.join("unmask/key.mask.png")).unwrap();
    let rekey = scenes.get_mut("rekey").unwrap();
    let mut brighter = rekey.key.clone();
    synth::expose(&mut brighter, 1.1, 0.0);
    put(&f.inbox.join("rekey/key.png"), &png(&brighter));
    // The healthy session goes on.
    let v2 = scenes.get_mut("healthy").unwrap().view(2, 300.0, 60.0);
    put(&f.inbox.join("healthy/v2.png"), &png(&v2));

    let ev = wait_for(&f, "every case to be handled", 120, |e| {
        let e = &e[first_results..];
        cases.iter().all(|c| !outcome(e, c.session, &c.shown()).is_empty())
            && healthy_filled_with_v2(e)
            && ["mask_size", "mask_black", "mask_white"].iter().all(|s| {
                e.iter()
                    .any(|x| x["session"] == *s && (x["event"] == "mask_set" || x["event"] == "file_skipped"))
            })
            && e.iter().any(|x| x["session"] == "unmask" && x["event"] == "mask_removed")
            && of_kind(e, "result_updated").iter().any(|r| r["session"] == "rekey")
    });
    // After the mask is gone, a new view is aligned but makes no result.
    let gone = ev.len();
    let v2 = scenes.get_mut("unmask").unwrap().view(2, 300.0, 60.0);
    put(&f.inbox.join("unmask/v2.png"), &png(&v2));
    wait_for(&f, "unmask's new view", 30, |e| {
        e[gone..]
            .iter()
            .any(|x| x["session"] == "unmask" && x["file"] == "v2.png" && x["event"] == "view_accepted")
    });
    // Let the last fills finish: nothing more happens for a while.
    std::thread::sleep(Duration::from_secs(2));
    let ev = events(&f);
    let log = service.log();
    assert!(service.alive(), "the service died; log:\n{log}");
    let new = &ev[first_results..];

    // Each case: its outcome, in an event and a log line that name the file.
    let mut table = Vec::new();
    let mut failures = Vec::new();
    for c in &cases {
        let name = c.shown();
        let out = outcome(new, c.session, &name);
        let last = out.last().unwrap();
        let kind = last["event"].as_str().unwrap();
        let reason = last["reason"].as_str().unwrap_or("");
        let ok = match c.want {
            Want::Skipped(w) => kind == "file_skipped" && reason.contains(w),
            Want::Rejected(w) => kind == "view_rejected" && reason.contains(w),
            Want::Refused(w) => (kind == "file_skipped" || kind == "view_rejected") && reason.contains(w),
            Want::Used => kind == "view_accepted" && last["buffered"] == true,
        };
        table.push(format!("| {} | {} | `{kind}` | {reason} |", c.what, c.session));
        if !ok {
            failures.push(format!("{} ({name:?}): want {:?}, got {out:#?}", c.what, c.want));
        }
        if out.len() != 1 {
            failures.push(format!("{} reported {} times: {out:#?}", c.what, out.len()));
        }
        let words = if matches!(c.want, Want::Used) { "view accepted" } else { reason };
        if !matches!(c.want, Want::Used) && reason.split_whitespace().count() < 3 {
            failures.push(format!("{}: not a reason in words: {reason:?}", c.what));
        }
        let logged_name = logged(&name);
        if !log.lines().any(|l| l.contains(&logged_name) && l.contains(words)) {
            failures.push(format!("{}: no log line names {logged_name} with {words:?}", c.what));
        }
    }
    eprintln!("{}", table.join("\n"));
    assert!(failures.is_empty(), "{}\nlog:\n{log}", failures.join("\n"));

    // Masks. The wrong size: refused, saying both sizes.
    let skipped: Vec<&Value> =
        new.iter().filter(|e| e["session"] == "mask_size" && e["event"] == "file_skipped").collect();
    assert_eq!(skipped.len(), 1, "{skipped:#?}");
    assert_eq!(skipped[0]["file"], "key.mask.png");
    let reason = skipped[0]["reason"].as_str().unwrap();
    assert!(reason.contains("200x150") && reason.contains("400x300"), "{reason}");
    log_says(&log, "key.mask.png", reason);
    assert!(!f.outbox.join("mask_size/result.png").exists(), "a result without a usable mask");
    // All black: nothing to fill, said so; the keyframe itself is the result.
    // All white: everything to fill, said so; a whole result from the view.
    for (s, words) in [("mask_black", "nothing to fill"), ("mask_white", "whole keyframe")] {
        let set: Vec<&Value> = of_kind(new, "mask_set").into_iter().filter(|e| e["session"] == s).collect();
        let warning =
            set.last().and_then(|e| e["warning"].as_str()).unwrap_or_else(|| panic!("{s}: {set:#?}"));
        assert!(warning.contains(words), "{s}: {warning}");
        assert_eq!(set.last().unwrap()["file"], "key.mask.png");
        log_says(&log, "key.mask.png", warning);
        let result = image::open(f.outbox.join(s).join("result.png")).unwrap_or_else(|e| panic!("{s}: {e}"));
        assert_eq!((result.width() as usize, result.height() as usize), (W, H));
    }
    let black = image::open(f.outbox.join("mask_black/result.png")).unwrap().to_rgb8();
    assert!(black == to_rgb8(&scenes["mask_black"].key), "with nothing to fill, the result is the keyframe");
    // The mask deleted: said so, and no result since.
    let removed: Vec<&Value> =
        of_kind(new, "mask_removed").into_iter().filter(|e| e["session"] == "unmask").collect();
    assert_eq!(removed.len(), 1, "{removed:#?}");
    assert_eq!(removed[0]["file"], "key.mask.png");
    log_says(&log, "key.mask.png", removed[0]["reason"].as_str().unwrap());
    let at = new.iter().position(|e| e["event"] == "mask_removed").unwrap();
    assert!(
        !new[at..].iter().any(|e| e["session"] == "unmask" && e["event"] == "result_updated"),
        "a result after the mask was deleted"
    );
    assert_eq!(
        sha(&f.outbox.join("unmask/result.png")).unwrap(),
        before["unmask"].0,
        "the last result changed"
    );
    // The keyframe replaced: the session restarts on it.
    assert!(new.iter().any(|e| e["session"] == "rekey" && e["event"] == "keyframe_changed"));

    // The event log is one JSON object per line (events() parses each line), and names
    // that are not UTF-8 come through lossily.
    let text = std::fs::read_to_string(f.outbox.join("events.jsonl")).unwrap();
    assert_eq!(text.lines().count(), ev.len());

    // A result already written is never damaged: unchanged, or a whole image whose score
    // is no lower.
    for (s, (bytes, report)) in &before {
        let dir = f.outbox.join(s);
        let now = std::fs::read(dir.join("result.png")).unwrap();
        if &now == bytes {
            continue;
        }
        let img = image::load_from_memory(&now).unwrap_or_else(|e| panic!("{s}: result.png is damaged: {e}"));
        assert_eq!((img.width() as usize, img.height() as usize), (W, H), "{s}");
        let after = result_json(&f, s).unwrap();
        if *s != "rekey" {
            assert!(
                after["from_views"].as_f64() >= report["from_views"].as_f64(),
                "{s}: a result was replaced by a worse one: {report:#} -> {after:#}"
            );
        }
    }
    no_temporaries(&f.outbox);
    let peak = peak_rss(pid);
    eprintln!(
        "[{:.1} s] peak RSS {} MB before the corpus, {} MB after",
        t0.elapsed().as_secs_f64(),
        peak_before >> 20,
        peak >> 20
    );
    assert!(peak < 600 << 20, "the service's peak RSS is {} MB", peak >> 20);
    assert_eq!(service.terminate(), 0);
}

/// How long the growing file grows by default: long enough for dozens of quiet-period
/// checks to see it still changing (the quiet period is 1 s, the file grows every
/// 100 ms), short enough for CI. The full minute is the `#[ignore]`d twin.
const GROW_SECS: u64 = 20;

/// A file written in small pieces for `secs`, each piece well within the quiet period:
/// nothing reads it until it stops; then it is one whole view, used. A healthy session
/// gets its result meanwhile.
fn a_growing_file_is_read_once_whole(secs: u64) {
    let f = folders("workers = 2\n");
    let text = std::fs::read_to_string(&f.config).unwrap();
    std::fs::write(&f.config, text.replace("quiet_period_ms = 300", "quiet_period_ms = 1000")).unwrap();
    let service = Service::start(&f);
    let mut grow = start_session(&f, "grow", 901);
    let mut healthy = start_session(&f, "healthy", 902);
    wait_for(&f, "both first results", 60, |e| {
        ["grow", "healthy"].iter().all(|s| of_kind(e, "result_updated").iter().any(|r| r["session"] == *s))
    });
    let bytes = png(&grow.view(2, 300.0, 60.0));
    let path = f.inbox.join("grow/slow.png");
    let steps = secs * 10;
    let chunk = bytes.len().div_ceil(steps as usize);
    let mut file = std::fs::File::create(&path).unwrap();
    let start = Instant::now();
    let mut pieces = bytes.chunks(chunk);
    let mut healthy_sent = false;
    for step in 0..steps {
        // Time-driven, so a slow machine does not stretch the pauses between pieces.
        let due = start + Duration::from_millis(100 * step);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        if let Some(piece) = pieces.next() {
            file.write_all(piece).unwrap();
        } else {
            // The bytes are all there; keep it growing with a trailer (PNG readers ignore
            // what follows the end chunk).
            file.write_all(b"\0").unwrap();
        }
        file.flush().unwrap();
        if !healthy_sent && step * 2 >= steps {
            put(&f.inbox.join("healthy/v2.png"), &png(&healthy.view(2, 300.0, 60.0)));
            healthy_sent = true;
        }
        let ev = events(&f);
        assert!(
            about(&ev, "slow.png").is_empty(),
            "read while growing, after {:?}: {:#?}",
            start.elapsed(),
            about(&ev, "slow.png")
        );
    }
    drop(file);
    let grown = start.elapsed();
    let ev = wait_for(&f, "the grown file to be used", 30, |e| !about(e, "slow.png").is_empty());
    let got = about(&ev, "slow.png");
    assert_eq!(got.len(), 1, "{got:#?}");
    assert_eq!(got[0]["event"], "view_accepted", "{got:#?}");
    assert!(healthy_filled_with_v2(&ev), "the healthy session did not go on");
    eprintln!("grew for {grown:?}; read once, whole, after it stopped");
    assert_eq!(service.terminate(), 0);
}

#[test]
fn a_file_growing_for_20_seconds_is_read_once_whole_after_it_stops() {
    a_growing_file_is_read_once_whole(GROW_SECS);
}

/// The minute. Run with `cargo test --release --test bad_input -- --ignored`.
#[test]
#[ignore = "a minute long; the 20-second version runs by default"]
fn a_file_growing_for_a_minute_is_read_once_whole_after_it_stops() {
    a_growing_file_is_read_once_whole(60);
}

/// Files that land at once in one session: mostly garbage and empty files (cheap to make,
/// refused by the intake), one in twenty a small PNG (aligned by the worker, at some tens
/// of milliseconds each: a flood of real views is bound by alignment, not by the intake).
const FLOOD: usize = 5000;

#[test]
fn five_thousand_files_at_once_are_each_reported_with_bounded_memory_and_descriptors() {
    let f = folders("workers = 2\n");
    let mut service = Service::start(&f);
    let pid = service.child.id();
    let mut healthy = start_session(&f, "healthy", 911);
    wait_for(&f, "the healthy session's first result", 60, |e| !of_kind(e, "result_updated").is_empty());
    let (rss0, fds0) = (rss(pid), open_fds(pid));
    // Made in a hidden folder and moved in at once: they land together.
    let staging = f.root.join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let tiny: Vec<Vec<u8>> = (0..8u64)
        .map(|i| {
            png(&RgbF32::from_fn(64, 48, |x, y| {
                let v = ((x as u64 * 7 + y as u64 * 13 + i * 31) % 17) as f32 / 16.0;
                [v, 1.0 - v, 0.5]
            }))
        })
        .collect();
    let mut names = Vec::with_capacity(FLOOD);
    for i in 0..FLOOD {
        let (name, bytes) = match i % 20 {
            0 => (format!("f{i:04}.png"), tiny[i / 20 % tiny.len()].clone()),
            1..=5 => (format!("f{i:04}.jpg"), Vec::new()),
            _ => (format!("f{i:04}.png"), random_bytes(64 + i % 512, i as u64)),
        };
        std::fs::write(staging.join(&name), bytes).unwrap();
        names.push(name);
    }
    let t = Instant::now();
    std::fs::rename(&staging, f.inbox.join("flood")).unwrap();
    put(&f.inbox.join("healthy/v2.png"), &png(&healthy.view(2, 300.0, 60.0)));
    let (mut top_rss, mut peak_fds) = (0u64, 0usize);
    let ev = loop {
        assert!(service.alive(), "the service died; log:\n{}", service.log());
        top_rss = top_rss.max(rss(pid));
        peak_fds = peak_fds.max(open_fds(pid));
        let ev = events(&f);
        let named: std::collections::HashSet<&str> = ev
            .iter()
            .filter(|e| e["session"] == "flood")
            .filter_map(|e| e["file"].as_str().or(e["keyframe"].as_str()))
            .collect();
        if names.iter().all(|n| named.contains(n.as_str())) && healthy_filled_with_v2(&ev) {
            break ev;
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "after 2 minutes, {} of {FLOOD} files reported; log tail:\n{}",
            names.iter().filter(|n| named.contains(n.as_str())).count(),
            service.log().lines().rev().take(30).collect::<Vec<_>>().join("\n")
        );
        std::thread::sleep(Duration::from_millis(250));
    };
    let took = t.elapsed();
    let flood: Vec<&Value> = ev.iter().filter(|e| e["session"] == "flood").collect();
    let skipped = flood.iter().filter(|e| e["event"] == "file_skipped").count();
    eprintln!(
        "{FLOOD} files reported in {took:.1?} ({skipped} skipped); RSS {} -> peak {} MB, fds {fds0} -> peak {peak_fds}, peak RSS (VmHWM) {} MB",
        rss0 >> 20,
        top_rss >> 20,
        peak_rss(pid) >> 20
    );
    for e in flood.iter().filter(|e| e["event"] == "file_skipped") {
        assert!(e["reason"].as_str().is_some_and(|r| r.split_whitespace().count() >= 3), "{e}");
    }
    assert!(peak_fds < fds0 + 64, "descriptors grew from {fds0} to {peak_fds}");
    assert!(top_rss < rss0 + (300 << 20), "memory grew from {} MB to {} MB", rss0 >> 20, top_rss >> 20);
    assert_eq!(service.terminate(), 0);
}

/// The healthy session went on: after its v2.png was accepted it filled with both views,
/// whether the fill was published or judged no better than the result it had (the publish
/// rule judges both on the same views).
fn healthy_filled_with_v2(ev: &[serde_json::Value]) -> bool {
    let Some(at) = ev
        .iter()
        .position(|e| e["session"] == "healthy" && e["file"] == "v2.png" && e["event"] == "view_accepted")
    else {
        return false;
    };
    ev[at..].iter().any(|e| {
        e["session"] == "healthy"
            && ((e["event"] == "result_updated" && e["views"] == 2) || e["event"] == "result_not_better")
    })
}
