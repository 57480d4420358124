//! End-to-end tests of video input: the real binary on videos made here with FFmpeg from
//! rendered frames (a camera panning past a facade with a tree in front, some frames
//! blurred), read from a file and from a local MJPEG stream that drops and comes back.

mod daemon_common;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use clearview::geometry::Homography;
use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::imaging::filter::gaussian_blur;
use clearview::imaging::{GrayF32, Mask, RgbF32};
use clearview::synth::{self, Occluder};
use serde_json::Value;

const W: usize = 480;
const H: usize = 360;
/// Facade pixels the camera pans per frame; the tree, nearer, moves three times as fast.
const PAN: f64 = 4.0;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_clearview")
}

fn have_ffmpeg() -> bool {
    let ok = |p: &str| Command::new(p).arg("-version").stdout(Stdio::null()).stderr(Stdio::null()).status();
    if ok("ffmpeg").is_ok_and(|s| s.success()) && ok("ffprobe").is_ok_and(|s| s.success()) {
        true
    } else {
        eprintln!("skipping: ffmpeg/ffprobe not found (CI installs them with apt-get install ffmpeg)");
        false
    }
}

/// The world: a facade larger than the frame, and a tree standing in front of it.
struct World {
    scene: RgbF32,
}

impl World {
    fn new() -> Self {
        Self { scene: synth::facade(W * 2, H * 3 / 2, 7) }
    }

    /// The camera's position (facade pixels panned) at frame `i` of a pan starting at
    /// `start` (frames before `start` see the first position).
    fn pan(i: usize, start: usize) -> f64 {
        i.saturating_sub(start) as f64 * PAN
    }

    /// The facade as seen with pan `p` (no tree).
    fn facade(&self, p: f64) -> RgbF32 {
        // A slight zoom as well, so views differ by more than a translation.
        let s = 1.0 + p / 4000.0;
        let view_to_scene = Homography::translation(60.0 + p, H as f64 / 4.0)
            .after(&Homography::from_rows([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, 1.0]]).unwrap());
        synth::render_view(&self.scene, &view_to_scene, W, H, [0.5; 3])
    }

    /// Keyframe → view homography between pans `from` and `to`.
    fn key_to_view(&self, from: f64, to: f64) -> Homography {
        let v = |p: f64| {
            let s = 1.0 + p / 4000.0;
            Homography::translation(60.0 + p, H as f64 / 4.0)
                .after(&Homography::from_rows([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, 1.0]]).unwrap())
        };
        v(to).inverse().unwrap().after(&v(from))
    }

    /// A frame with pan `p`: the tree moves three times as fast as the facade (parallax).
    fn frame(&self, p: f64, mask: Option<&mut Mask>) -> RgbF32 {
        let mut img = self.facade(p);
        let tree_x = 400.0 - 3.0 * p as f32;
        synth::paint_occluder(&mut img, mask, Occluder::Tree, tree_x, 200.0, 120.0, 3);
        img
    }
}

fn blur_rgb(img: &RgbF32, sigma: f32) -> RgbF32 {
    let ch: Vec<GrayF32> = (0..3).map(|c| gaussian_blur(&img.map(|p| p[c]), sigma)).collect();
    RgbF32::from_fn(img.width(), img.height(), |x, y| [ch[0].get(x, y), ch[1].get(x, y), ch[2].get(x, y)])
}

/// Mean absolute error over `mask`'s holes of an 8-bit image against `truth`.
fn masked_error(truth: &RgbF32, mask: &Mask, img: &image::RgbImage) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for y in 0..H {
        for x in 0..W {
            if mask.is_hole(x, y) {
                let t = truth.get(x, y);
                let p = img.get_pixel(x as u32, y as u32).0;
                sum += (0..3).map(|c| (t[c] as f64 - p[c] as f64 / 255.0).abs()).sum::<f64>() / 3.0;
                n += 1;
            }
        }
    }
    sum / n.max(1) as f64
}

fn events(out: &Path) -> Vec<Value> {
    daemon_common::whole_lines(&out.join("events.jsonl"))
}

fn of_kind<'a>(events: &'a [Value], kind: &str) -> Vec<&'a Value> {
    events.iter().filter(|e| e["event"] == kind).collect()
}

/// `mask` grown by `r` pixels (square neighbourhood).
fn dilate(mask: &Mask, r: usize) -> Mask {
    Mask::from_fn(W, H, |x, y| {
        let (x0, y0) = (x.saturating_sub(r), y.saturating_sub(r));
        let hit = (y0..(y + r + 1).min(H)).any(|yy| (x0..(x + r + 1).min(W)).any(|xx| mask.is_hole(xx, yy)));
        if hit { 255 } else { 0 }
    })
}

fn write_mask(path: &Path, mask: &Mask) {
    mask_to_luma8(mask).save(path).unwrap();
}

const FRAMES: usize = 50;
const FPS: usize = 10;
const KEY: usize = 6;

/// Frames with a blur: every third one from frame 8.
fn blurred(i: usize) -> bool {
    i >= 8 && i % 3 == 1
}

#[test]
fn a_video_file_is_selected_aligned_and_filled_until_its_end() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    for i in 0..FRAMES {
        let mut f = world.frame(World::pan(i, 0), None);
        if blurred(i) {
            f = blur_rgb(&f, 3.0);
        }
        to_rgb8(&f).save(frames.join(format!("{i:04}.png"))).unwrap();
    }
    let video = dir.join("walk.mp4");
    let st = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-framerate", &FPS.to_string(), "-i"])
        .arg(frames.join("%04d.png"))
        .args(["-c:v", "libx264", "-crf", "16", "-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(st.success());
    // The mask: the tree as it stands in the keyframe; the truth: the facade behind it.
    let mut mask = Mask::new(W, H, 0);
    let key_pan = World::pan(KEY, 0);
    let key = world.frame(key_pan, Some(&mut mask));
    // Drawn generously, as a person would: the leaves' soft edge is inside.
    let mask = dilate(&mask, 6);
    let truth = world.facade(key_pan);
    write_mask(&dir.join("mask.png"), &mask);
    let out = dir.join("out");
    let started = Instant::now();
    let run = Command::new(bin())
        .args(["run", "--video"])
        .arg(&video)
        .args(["--keyframe-frame", &KEY.to_string(), "--mask"])
        .arg(dir.join("mask.png"))
        .arg("--out")
        .arg(&out)
        .env("CLEARVIEW_LOG", "clearview=debug")
        .current_dir(dir)
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(0), "log:\n{log}");
    assert!(started.elapsed() < Duration::from_secs(120));
    assert!(!dir.join("inbox").exists(), "a video-only run watches no folder");

    let ev = events(&out);
    let ended = of_kind(&ev, "video_ended");
    assert_eq!(ended.len(), 1, "{ev:#?}");
    let end = ended[0];
    assert!(end["reason"].is_null(), "{end}");
    assert_eq!(end["frames_read"], FRAMES as u64, "{end}");
    // Every blurred frame after the keyframe is seen as blurred (x264 keeps the blur).
    let n_blurred = (KEY..FRAMES).filter(|&i| blurred(i)).count() as u64;
    let got = end["blurred"].as_u64().unwrap();
    assert!(got >= n_blurred && got <= n_blurred + 2, "blurred {got}, rendered {n_blurred}: {end}");
    assert!(end["rate_capped"].as_u64().unwrap() > 10, "{end}");
    assert_eq!(end["dropped"], 0, "a file not read in real time loses nothing: {end}");
    // No blurred frame was kept, and the kept ones chain from each other.
    let started_ev = of_kind(&ev, "session_started");
    assert_eq!(started_ev[0]["frame"], KEY as u64);
    let views: Vec<&Value> =
        of_kind(&ev, "view_accepted").into_iter().chain(of_kind(&ev, "view_rejected")).collect();
    assert!(views.len() >= 6, "{ev:#?}");
    for v in &views {
        let i = v["frame"].as_u64().unwrap() as usize;
        assert!(!blurred(i), "blurred frame {i} was kept: {v}");
    }
    let accepted = of_kind(&ev, "view_accepted");
    assert!(accepted.len() >= 6, "{ev:#?}");
    // Frames after the keyframe chain from each other; those kept before it (they wait for
    // the keyframe, then are aligned nearest first) are views too.
    let after: Vec<&&Value> =
        accepted.iter().filter(|v| v["frame"].as_u64().unwrap() as usize > KEY).collect();
    let chained = after.iter().filter(|v| v["from_prior"] == true).count();
    assert!(chained * 10 >= after.len() * 8, "{chained} of {} from the prior", after.len());
    // The keyframe is written beside the result for the mask to be painted on.
    let written = image::open(out.join("video").join("keyframe.png")).unwrap().to_rgb8();
    assert_eq!((written.width() as usize, written.height() as usize), (W, H));
    // Each kept frame's homography is the true one (the camera's pan since the keyframe).
    for v in &accepted {
        let i = v["frame"].as_u64().unwrap() as usize;
        let rows: [[f64; 3]; 3] = serde_json::from_value(v["homography"].clone()).unwrap();
        let got = Homography::from_rows(rows).unwrap();
        let err = got.mean_corner_error(&world.key_to_view(key_pan, World::pan(i, 0)), W, H);
        assert!(err < 1.0, "frame {i}: {err:.2} px from the truth");
    }

    // Results improve as the camera moves; the last one is close to the facade.
    let updates = of_kind(&ev, "result_updated");
    assert!(!updates.is_empty(), "{ev:#?}");
    let session = out.join("video");
    let result = image::open(session.join("result.png")).unwrap().to_rgb8();
    let report: Value = serde_json::from_slice(&std::fs::read(session.join("result.json")).unwrap()).unwrap();
    assert_eq!(report["keyframe"], format!("frame-{KEY:06}"));
    let final_err = masked_error(&truth, &mask, &result);
    let key_err = masked_error(&truth, &mask, &to_rgb8(&key));
    let first = image::open(session.join("history/result-0001.png")).unwrap().to_rgb8();
    let first_err = masked_error(&truth, &mask, &first);
    eprintln!(
        "masked error: keyframe {key_err:.4}, first result {first_err:.4}, final {final_err:.4} ({} results)",
        updates.len()
    );
    // For a look: the last result, and the first.
    let _ = result.save(std::env::temp_dir().join("clearview-video-result.png"));
    let _ = first.save(std::env::temp_dir().join("clearview-video-first.png"));
    if !multi_view_fill() {
        eprintln!(
            "skipping the masked-error checks: this build's fill takes nothing from views (placeholder)"
        );
        return;
    }
    assert!(updates.len() >= 2, "results improve as the camera moves: {ev:#?}");
    assert!(final_err < 0.035, "final masked error {final_err:.4} (keyframe {key_err:.4})");
    assert!(final_err < first_err, "first {first_err:.4}, final {final_err:.4}");
    assert!(final_err < key_err / 4.0);
}

/// `clearview run --video VIDEO FLAGS --mask DIR/mask.png --out OUT`, run in `dir`.
fn run_video(dir: &Path, video: &Path, flags: &[&str], out: &Path) -> std::process::Output {
    Command::new(bin())
        .args(["run", "--video"])
        .arg(video)
        .args(flags)
        .arg("--mask")
        .arg(dir.join("mask.png"))
        .arg("--out")
        .arg(out)
        .current_dir(dir)
        .output()
        .unwrap()
}

/// Writes `frames` as an H.264 file (CRF 16, `FPS`) in `dir`; its path.
fn encode(dir: &Path, frames: &[RgbF32]) -> std::path::PathBuf {
    let pngs = dir.join("frames");
    std::fs::create_dir_all(&pngs).unwrap();
    for (i, f) in frames.iter().enumerate() {
        to_rgb8(f).save(pngs.join(format!("{i:04}.png"))).unwrap();
    }
    let video = dir.join("walk.mp4");
    let st = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-framerate", &FPS.to_string(), "-i"])
        .arg(pngs.join("%04d.png"))
        .args(["-c:v", "libx264", "-crf", "16", "-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(st.success());
    video
}

/// A keyframe named past the end of a file cannot be: the run says so, naming the file and
/// the frame, and exits 1. Before, the stream ended as if it had run: exit 0, no result and
/// not a word of why.
#[test]
fn a_keyframe_named_past_the_end_of_the_file_is_refused_and_the_run_fails() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    let frames: Vec<RgbF32> = (0..12).map(|i| world.frame(World::pan(i, 0), None)).collect();
    let video = encode(dir, &frames);
    let mut mask = Mask::new(W, H, 0);
    world.frame(World::pan(0, 0), Some(&mut mask));
    write_mask(&dir.join("mask.png"), &dilate(&mask, 6));
    for (flag, value, says) in [
        (
            "--keyframe-frame",
            "40",
            "frame 40 (keyframe_frame) is past the end of the video: its frames are 0 to 11",
        ),
        (
            "--keyframe-at",
            "9",
            "9 s (keyframe_at_s) is past the end of the video: its last frame is at 1.100 s",
        ),
    ] {
        let out = dir.join(format!("out{flag}"));
        let run = run_video(dir, &video, &[flag, value], &out);
        let log = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(1), "log:\n{log}");
        assert!(log.contains(&format!("{}: {says}", video.display())), "log:\n{log}");
        let ev = events(&out);
        let refused = of_kind(&ev, "keyframe_refused");
        assert_eq!(refused.len(), 1, "{ev:#?}");
        assert_eq!(refused[0]["reason"], says);
        assert_eq!(of_kind(&ev, "video_ended")[0]["reason"], says);
        assert!(!out.join("video").join("result.png").exists());
    }
}

/// `img` turned a quarter clockwise.
fn turned_clockwise(img: &RgbF32) -> RgbF32 {
    let h = img.height();
    RgbF32::from_fn(h, img.width(), |x, y| img.get(y, h - 1 - x))
}

/// A phone held upright stores its frames on their side, with a quarter turn for the
/// player (ffprobe's `rotation`); FFmpeg turns them upright as it decodes. The frames, the
/// mask and `keyframe.png` are the upright picture the user sees. Before, the stored size
/// was taken for the frames': the upright mask was refused as the wrong size, and a mask of
/// the stored size was laid on the upright frames squeezed into that size.
#[test]
fn a_video_filmed_with_the_phone_upright_is_read_upright() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    let stored: Vec<RgbF32> =
        (0..24).map(|i| turned_clockwise(&world.frame(World::pan(i, 0), None))).collect();
    let plain = encode(dir, &stored);
    // FFmpeg 5 writes the turn when it copies a stream, not when it encodes one.
    let video = dir.join("upright.mp4");
    let st = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-i"])
        .arg(&plain)
        .args(["-c", "copy", "-metadata:s:v:0", "rotate=90"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(st.success());
    let probe = Command::new("ffprobe")
        .args([
            "-v",
            "error",
            "-select_streams",
            "v:0",
            "-show_entries",
            "stream_side_data=rotation:stream_tags=rotate",
        ])
        .arg(&video)
        .output()
        .unwrap();
    if !String::from_utf8_lossy(&probe.stdout).contains("rotat") {
        eprintln!("skipping: this FFmpeg wrote no rotation into the file");
        return;
    }
    let mut mask = Mask::new(W, H, 0);
    let key = world.frame(World::pan(0, 0), Some(&mut mask));
    let mask = dilate(&mask, 6);
    write_mask(&dir.join("mask.png"), &mask);
    let out = dir.join("out");
    let run = run_video(dir, &video, &[], &out);
    let log = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(0), "log:\n{log}");
    // The keyframe written for painting is the upright first frame.
    let written = image::open(out.join("video").join("keyframe.png")).unwrap().to_rgb8();
    assert_eq!(written.dimensions(), (W as u32, H as u32));
    let all = Mask::new(W, H, 255);
    let off = masked_error(&key, &all, &written);
    assert!(off < 0.03, "keyframe.png is {off:.4} off the upright first frame");
    let result = image::open(out.join("video").join("result.png")).unwrap().to_rgb8();
    let truth = world.facade(World::pan(0, 0));
    let (err, key_err) = (masked_error(&truth, &mask, &result), masked_error(&truth, &mask, &to_rgb8(&key)));
    eprintln!("masked error: keyframe {key_err:.4}, result {err:.4}");
    if multi_view_fill() {
        assert!(err < 0.035 && err < key_err / 4.0, "result {err:.4}, keyframe {key_err:.4}");
    }
}

/// The first frames of a stream only set the sharpness level, but they are views too: with
/// the keyframe named just after them, they may be the only frames that saw what its
/// occluder hides. Here the camera walks past the tree during the first five frames (the
/// warm-up) and then stands still: every later frame shows the tree where the keyframe
/// does. Before the warm-up's frames were held and judged, none of them was kept and the
/// session had no view to fill from.
#[test]
fn the_frames_of_the_warm_up_are_views_of_a_keyframe_named_after_them() {
    if !have_ffmpeg() {
        return;
    }
    const KEY_AT: usize = 8;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    // 30 facade pixels per frame for frames 0..=4, then still (the tree 90 px per frame).
    let pan = |i: usize| 30.0 * i.min(4) as f64;
    let frames: Vec<RgbF32> = (0..16).map(|i| world.frame(pan(i), None)).collect();
    let video = encode(dir, &frames);
    let mut mask = Mask::new(W, H, 0);
    let key = world.frame(pan(KEY_AT), Some(&mut mask));
    let mask = dilate(&mask, 6);
    write_mask(&dir.join("mask.png"), &mask);
    let out = dir.join("out");
    let run = run_video(dir, &video, &["--keyframe-frame", &KEY_AT.to_string()], &out);
    let log = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(0), "log:\n{log}");
    let ev = events(&out);
    let accepted: Vec<u64> =
        of_kind(&ev, "view_accepted").iter().map(|v| v["frame"].as_u64().unwrap()).collect();
    assert!(accepted.contains(&0), "frame 0 (in the warm-up) is not a view: {ev:#?}");
    let end = of_kind(&ev, "video_ended")[0];
    assert_eq!(end["warmup"], 0, "every frame of the warm-up was judged: {end}");
    let result = image::open(out.join("video").join("result.png")).unwrap().to_rgb8();
    let truth = world.facade(pan(KEY_AT));
    let (err, key_err) = (masked_error(&truth, &mask, &result), masked_error(&truth, &mask, &to_rgb8(&key)));
    eprintln!("masked error: keyframe {key_err:.4}, result {err:.4}; views {accepted:?}");
    if multi_view_fill() {
        assert!(err < 0.035 && err < key_err / 4.0, "result {err:.4}, keyframe {key_err:.4}");
    }
}

/// Whether the library's fill takes pixels from views (the multi-view fill has landed):
/// a hole in a flat grey keyframe with one view that sees it.
fn multi_view_fill() -> bool {
    let key = RgbF32::new(64, 64, [0.5; 3]);
    let mut mask = Mask::new(64, 64, 0);
    for y in 24..40 {
        for x in 24..40 {
            mask.set(x, y, 255);
        }
    }
    let view = RgbF32::new(64, 64, [0.5; 3]);
    let sources = [clearview::inpaint::Source { image: &view, homography: Homography::identity() }];
    let mut quiet = ();
    let filled = clearview::inpaint::fill(&key, &mask, &sources, &Default::default(), 1, &mut quiet);
    filled.report.from_views() > 0.0
}

#[test]
fn a_missing_ffmpeg_is_a_clear_error_at_start() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("c.toml");
    std::fs::write(
        &config,
        format!(
            "[watch]\nenabled = false\n[output]\ndir = {:?}\n[state]\ndir = {:?}\n\
             [[video]]\ninput = \"walk.mp4\"\nffmpeg = \"/nonexistent/ffmpeg\"\n",
            tmp.path().join("out"),
            tmp.path().join("state")
        ),
    )
    .unwrap();
    let run = Command::new(bin()).args(["run", "--config"]).arg(&config).output().unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{err}");
    assert!(err.contains("/nonexistent/ffmpeg") && err.contains("install FFmpeg"), "{err}");
}

/// A stream whose frames have more pixels than `watch.max_pixels` (the limit every
/// photograph is held to) is refused at start, naming the file, its frames' size and the
/// limit: a stream can claim any size, and a frame is held several times over.
#[test]
fn frames_over_the_pixel_limit_are_refused_at_start() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    let frames: Vec<RgbF32> = (0..3).map(|i| world.frame(World::pan(i, 0), None)).collect();
    let video = encode(dir, &frames);
    std::fs::write(dir.join("c.toml"), "[watch]\nmax_pixels = 100000\n").unwrap();
    let run = Command::new(bin())
        .args(["run", "--config", "c.toml", "--video"])
        .arg(&video)
        .args(["--mask", "auto", "--out", "out"])
        .current_dir(dir)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{err}");
    let says =
        format!("{}: its frames are 480x360 (0.2 MP), more than watch.max_pixels (100000)", video.display());
    assert!(err.contains(&says), "{err}");
}

/// A tiny MJPEG-over-HTTP server on loopback that can be stopped and started again.
struct Mjpeg {
    port: u16,
    up: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
}

impl Mjpeg {
    fn start(frames: Arc<Vec<Vec<u8>>>, fps: u64) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        listener.set_nonblocking(true).unwrap();
        let up = Arc::new(AtomicBool::new(true));
        let stop = Arc::new(AtomicBool::new(false));
        // Like a camera: what is served is what it sees now, whoever is connected.
        let t0 = Instant::now();
        let (u, s) = (up.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut listener = Some(listener);
            while !s.load(Ordering::Relaxed) {
                if !u.load(Ordering::Relaxed) {
                    // Down: not even listening (connections are refused).
                    listener = None;
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                }
                let l = listener.get_or_insert_with(|| {
                    let l = TcpListener::bind(("127.0.0.1", port)).unwrap();
                    l.set_nonblocking(true).unwrap();
                    l
                });
                match l.accept() {
                    Ok((conn, _)) => {
                        let (frames, u) = (frames.clone(), u.clone());
                        std::thread::spawn(move || serve(conn, &frames, fps, &u, t0));
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
        });
        Self { port, up, stop }
    }
}

impl Drop for Mjpeg {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.up.store(false, Ordering::Relaxed);
    }
}

fn serve(mut conn: TcpStream, frames: &[Vec<u8>], fps: u64, up: &AtomicBool, t0: Instant) {
    conn.set_nonblocking(false).unwrap();
    let mut req = [0u8; 2048];
    let _ = conn.read(&mut req);
    let head = "HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n";
    if conn.write_all(head.as_bytes()).is_err() {
        return;
    }
    while up.load(Ordering::Relaxed) {
        let i = (t0.elapsed().as_secs_f64() * fps as f64) as usize;
        let f = &frames[i.min(frames.len() - 1)];
        let part = format!("--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\n\r\n", f.len());
        if conn
            .write_all(part.as_bytes())
            .and_then(|()| conn.write_all(f))
            .and_then(|()| conn.write_all(b"\r\n"))
            .is_err()
        {
            return;
        }
        std::thread::sleep(Duration::from_millis(1000 / fps));
    }
    let _ = conn.shutdown(std::net::Shutdown::Both);
}

/// ffmpeg processes whose command line names `needle`.
fn processes_naming(needle: &str) -> Vec<u32> {
    let mut found = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
        if let Ok(cmd) = std::fs::read(e.path().join("cmdline"))
            && String::from_utf8_lossy(&cmd).contains(needle)
            && !String::from_utf8_lossy(&cmd).contains("clearview")
        {
            found.push(pid);
        }
    }
    found
}

#[test]
fn a_live_stream_that_drops_is_reconnected_and_the_session_goes_on() {
    if !have_ffmpeg() || !Path::new("/proc").is_dir() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    // The camera stands still for 4 s (the keyframe is taken then), then pans slowly for
    // 20 s: time enough for a first result, a loss and a reconnection under load.
    const STILL: usize = 40;
    let jpegs: Vec<Vec<u8>> = (0..STILL + 200)
        .map(|i| {
            let mut b = std::io::Cursor::new(Vec::new());
            let f = world.frame(World::pan(i, STILL) * 0.375, None);
            to_rgb8(&f).write_to(&mut b, image::ImageFormat::Jpeg).unwrap();
            b.into_inner()
        })
        .collect();
    let mut mask = Mask::new(W, H, 0);
    let _ = world.frame(0.0, Some(&mut mask));
    let mask = dilate(&mask, 6);
    write_mask(&dir.join("mask.png"), &mask);
    let server = Mjpeg::start(Arc::new(jpegs), 10);
    let url = format!("http://127.0.0.1:{}/cam", server.port);
    let out = dir.join("out");
    let log = std::fs::File::create(dir.join("service.log")).unwrap();
    let mut child = Command::new(bin())
        .args(["run", "--video", &url, "--mask"])
        .arg(dir.join("mask.png"))
        .arg("--out")
        .arg(&out)
        .env("CLEARVIEW_LOG", "clearview=debug")
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();
    let service_log = || std::fs::read_to_string(dir.join("service.log")).unwrap_or_default();
    let wait = |what: &str, secs: u64, pred: &dyn Fn(&[Value]) -> bool| -> Vec<Value> {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let ev = events(&out);
            if pred(&ev) {
                return ev;
            }
            assert!(
                Instant::now() < deadline,
                "timed out waiting for {what}\n{ev:#?}\nlog:\n{}",
                service_log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    };
    wait("a first result", 40, &|ev| !of_kind(ev, "result_updated").is_empty());
    // The camera goes away for a while.
    server.up.store(false, Ordering::Relaxed);
    let ev = wait("the loss", 20, &|ev| !of_kind(ev, "stream_lost").is_empty());
    let results_before = of_kind(&ev, "result_updated").len();
    std::thread::sleep(Duration::from_millis(1500));
    server.up.store(true, Ordering::Relaxed);
    let ev = wait("a reconnection and a later result", 60, &|ev| {
        !of_kind(ev, "stream_reconnected").is_empty() && of_kind(ev, "result_updated").len() > results_before
    });
    let reconnected = ev.iter().position(|e| e["event"] == "stream_reconnected").unwrap();
    assert!(ev[reconnected + 1..].iter().any(|e| e["event"] == "view_accepted"), "{ev:#?}");
    // One session throughout: the keyframe was set once.
    assert_eq!(of_kind(&ev, "session_started").len(), 1);
    assert!(of_kind(&ev, "keyframe_changed").is_empty());
    assert!(!processes_naming(&url).is_empty(), "ffmpeg is reading the stream");
    // SIGTERM: the service stops, and its ffmpeg with it.
    let ok = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(ok.success());
    let deadline = Instant::now() + Duration::from_secs(30);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < deadline, "no stop within 30 s of SIGTERM\n{}", service_log());
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(status.code(), Some(0), "{}", service_log());
    assert!(processes_naming(&url).is_empty(), "ffmpeg outlived the service");
}

/// A walk with near trees over the keyframe's right half, the side the frames further
/// along the walk keep: they share only a sliver of the keyframe clear of the mask, and
/// they are the frames that see what the trees hide. The keyframe alone places them badly
/// (on the rendered walks of `bench/align_video.py` it refuses them: too few details; on
/// this repeating facade its descriptors accept frame 10 on an alias, 233 px off). Each is
/// aligned to the last accepted frame instead (most of the picture in common, the prior
/// the camera's motion so far) and the maps chained. Before, frame 10 was accepted 233 px
/// off the truth.
#[test]
fn frames_that_share_a_sliver_with_a_hidden_keyframe_are_chained_through_the_last_accepted_one() {
    if !have_ffmpeg() {
        return;
    }
    const STEP: f64 = 12.0;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let world = World::new();
    // Two trees over the keyframe's right half, three times nearer than the facade: they
    // move 36 px a frame to the left.
    let frame = |i: usize, mut mask: Option<&mut Mask>| {
        let p = STEP * i as f64;
        let mut img = world.facade(p);
        let x = 400.0 - 3.0 * p as f32;
        synth::paint_occluder(&mut img, mask.as_deref_mut(), Occluder::Tree, x, 120.0, 260.0, 5);
        synth::paint_occluder(&mut img, mask, Occluder::Tree, x + 30.0, 330.0, 260.0, 6);
        img
    };
    let frames: Vec<RgbF32> = (0..24).map(|i| frame(i, None)).collect();
    let video = encode(dir, &frames);
    let mut mask = Mask::new(W, H, 0);
    let key = frame(0, Some(&mut mask));
    let mask = dilate(&mask, 6);
    write_mask(&dir.join("mask.png"), &mask);
    let out = dir.join("out");
    let run = run_video(dir, &video, &[], &out);
    let log = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(0), "log:\n{log}");
    let ev = events(&out);
    let mut accepted = Vec::new();
    for v in of_kind(&ev, "view_accepted") {
        let k = v["frame"].as_u64().unwrap() as usize;
        let rows: [[f64; 3]; 3] = serde_json::from_value(v["homography"].clone()).unwrap();
        let found = Homography::from_rows(rows).unwrap();
        let truth = world.key_to_view(0.0, STEP * k as f64);
        // Transfer error at keyframe points the frame sees (a chained map drifts if wrong).
        let mut worst = 0.0f64;
        for y in (20..H).step_by(40) {
            for x in (20..W).step_by(40) {
                let p = nalgebra::Point2::new(x as f64, y as f64);
                let t = truth.apply(p).unwrap();
                if t.x < 0.0 || t.x >= W as f64 || t.y < 0.0 || t.y >= H as f64 {
                    continue;
                }
                let f = found.apply(p).unwrap();
                worst = worst.max((f - t).norm());
            }
        }
        assert!(worst < 2.0, "frame {k}: {worst:.2} px off the truth");
        accepted.push(k);
    }
    eprintln!("accepted {accepted:?}");
    assert!(
        accepted.iter().filter(|&&k| k >= 15).count() >= 2,
        "the frames far along the walk are not views: {accepted:?}; log:\n{log}"
    );
    let result = image::open(out.join("video").join("result.png")).unwrap().to_rgb8();
    let truth = world.facade(0.0);
    let (err, key_err) = (masked_error(&truth, &mask, &result), masked_error(&truth, &mask, &to_rgb8(&key)));
    eprintln!("masked error: keyframe {key_err:.4}, result {err:.4}");
    if multi_view_fill() {
        assert!(err < key_err / 4.0, "result {err:.4}, keyframe {key_err:.4}");
    }
}
