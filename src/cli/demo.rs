//! `clearview demo [DIR]`: a capture session played into the service, running in-process,
//! so a newcomer sees clearview work without preparing a single file (edge layer).
//!
//! It renders a facade with a tree in front of it (the keyframe and its mask), then
//! photographs it from other places, each shot with its own passer-by, car or tree, and
//! drops the shots one by one into the service's inbox. After each update it prints where
//! the result is and how much of the mask now comes from real views.

use std::path::Path;
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

use super::exit;
use crate::config::Config;
use crate::daemon;
use crate::geometry::Homography;
use crate::imaging::convert::{mask_to_luma8, to_rgb8};
use crate::imaging::{Mask, RgbF32};
use crate::synth::{self, Occluder};

const WIDTH: usize = 800;
const HEIGHT: usize = 600;
const SESSION: &str = "facade";

/// Each shot's occluder: kind, centre x in the view, size (0: nothing in front).
const SHOTS: [(Occluder, f32, f32); 6] = [
    (Occluder::Tree, 430.0, 330.0),
    (Occluder::Person, 360.0, 250.0),
    (Occluder::Car, 250.0, 200.0),
    (Occluder::Person, 560.0, 230.0),
    (Occluder::Tree, 650.0, 260.0),
    (Occluder::Car, 150.0, 0.0),
];

pub fn run(dir: &Path) -> u8 {
    match play(dir) {
        Ok(()) => exit::OK,
        Err(e) => {
            eprintln!("clearview demo: {e}");
            exit::FAILURE
        }
    }
}

fn write_png_atomically(path: &Path, img: image::DynamicImage) -> Result<(), String> {
    // A hidden name while writing: the service never reads a file that starts with a dot.
    let tmp = path
        .with_file_name(format!(".{}.writing.png", path.file_name().unwrap_or_default().to_string_lossy()));
    img.save(&tmp).map_err(|e| format!("{}: cannot write: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: cannot rename: {e}", path.display()))
}

/// Mean absolute error over the mask between a result file and the truth.
fn masked_error(result: &Path, truth: &RgbF32, mask: &Mask) -> Option<f64> {
    let img = image::open(result).ok()?.to_rgb8();
    let (mut sum, mut n) = (0.0, 0usize);
    for y in 0..mask.height() {
        for x in 0..mask.width() {
            if mask.is_hole(x, y) {
                let (t, p) = (truth.get(x, y), img.get_pixel(x as u32, y as u32).0);
                sum += (0..3).map(|c| (f64::from(t[c]) - f64::from(p[c]) / 255.0).abs()).sum::<f64>() / 3.0;
                n += 1;
            }
        }
    }
    Some(sum / n.max(1) as f64)
}

fn events(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// Waits for an event after the first `seen` that satisfies `pred`.
fn wait_event(
    log: &Path,
    seen: usize,
    timeout: Duration,
    pred: impl Fn(&Value) -> bool,
) -> Option<(usize, Value)> {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        let ev = events(log);
        if let Some((i, e)) = ev.iter().enumerate().skip(seen).find(|(_, e)| pred(e)) {
            return Some((i + 1, e.clone()));
        }
        std::thread::sleep(Duration::from_millis(40));
    }
    None
}

fn play(dir: &Path) -> Result<(), String> {
    let inbox = dir.join("inbox");
    let outbox = dir.join("outbox");
    let state = dir.join("state");
    // A previous tour's session is replayed from scratch; anything else is left alone.
    for p in
        [inbox.join(SESSION), outbox.join(SESSION), state.join("sessions").join(format!("{SESSION}.json"))]
    {
        let _ = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
    }
    let _ = std::fs::remove_file(outbox.join("events.jsonl"));
    let config = Config {
        watch_dir: inbox.clone(),
        out_dir: outbox.clone(),
        state_dir: state,
        quiet_period: Duration::from_millis(150),
        history: 10,
        ..Config::default()
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .worker_threads(2)
        .build()
        .map_err(|e| format!("cannot start the runtime: {e}"))?;
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let service = runtime.spawn(daemon::run(config, async move {
        let _ = stopped.await;
    }));
    println!("service started: watching {}, writing {}", inbox.display(), outbox.display());
    let session = inbox.join(SESSION);
    std::fs::create_dir_all(&session).map_err(|e| format!("{}: cannot create: {e}", session.display()))?;
    let log = outbox.join("events.jsonl");

    // The scene is larger than a frame so the camera can move over it.
    let scene = synth::facade(WIDTH * 3 / 2, HEIGHT * 3 / 2, 2026);
    let centre = Homography::translation(WIDTH as f64 / 4.0, HEIGHT as f64 / 4.0);
    let truth = synth::render_view(&scene, &centre, WIDTH, HEIGHT, [0.5; 3]);
    let mut key = truth.clone();
    let mut mask = Mask::new(WIDTH, HEIGHT, 0);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 400.0, 330.0, 240.0, 1);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Person, 610.0, 420.0, 220.0, 2);
    grow_mask(&mut mask, 3);
    write_png_atomically(&session.join("key.mask.png"), mask_to_luma8(&mask).into())?;
    write_png_atomically(&session.join("key.png"), to_rgb8(&key).into())?;
    println!(
        "keyframe: {} (a tree and a passer-by in front of the facade; {} pixels to clear, marked in key.mask.png)",
        session.join("key.png").display(),
        mask.hole_count()
    );
    println!(
        "  (\"error against the truth\": the mean difference, over those pixels, between the result and the \
         facade as it is behind the tree and the passer-by, on a 0-1 scale per colour channel; 0 is perfect, \
         0.01 is about 2.5 levels of 255)"
    );
    let (mut seen, _) = wait_event(&log, 0, Duration::from_secs(20), |e| e["event"] == "result_updated")
        .ok_or("the service did not take the keyframe within 20 s")?;
    let result_path = outbox.join(SESSION).join("result.png");
    if let Some(err) = masked_error(&result_path, &truth, &mask) {
        println!("  result #1 (nothing seen yet, all invented): error against the truth {:.3}", err);
    }

    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for (i, &(kind, cx, size)) in SHOTS.iter().enumerate() {
        let n = i + 1;
        // A shot from elsewhere: the camera turned, tilted and moved.
        let key_to_view = synth::random_homography(&mut rng, WIDTH, HEIGHT, 0.12, 0.25, (0.85, 1.15));
        let view_to_scene = centre.after(&key_to_view.inverse().ok_or("a singular camera")?);
        let mut view = synth::render_view(&scene, &view_to_scene, WIDTH, HEIGHT, [0.5; 3]);
        if size > 0.0 {
            synth::paint_occluder(&mut view, None, kind, cx, 380.0, size, 100 + n as u64);
        }
        synth::expose(&mut view, 0.85 + 0.05 * n as f32, 0.02);
        synth::add_noise(&mut view, 0.01, n as u64);
        let name = format!("shot-{n}.png");
        write_png_atomically(&session.join(&name), to_rgb8(&view).into())?;
        let what = if size > 0.0 { format!("{kind:?}").to_lowercase() } else { "nothing".into() };
        let (next, ev) = wait_event(&log, seen, Duration::from_secs(30), |e| e["file"] == name.as_str())
            .ok_or_else(|| format!("the service did not take {name} within 30 s"))?;
        seen = next;
        match ev["event"].as_str() {
            Some("view_accepted") => {
                println!(
                    "{name} ({what} in front): aligned, {} inliers, {:.2} px median residual{}",
                    ev["inliers"],
                    ev["median_residual_px"].as_f64().unwrap_or(f64::NAN),
                    if ev["improves"] == true { "" } else { " (adds nothing new: no refill)" }
                );
                if ev["improves"] == true {
                    let (next, r) = wait_event(&log, seen, Duration::from_secs(60), |e| {
                        matches!(e["event"].as_str(), Some("result_updated" | "result_not_better"))
                    })
                    .ok_or("no result within 60 s")?;
                    seen = next;
                    if r["event"] == "result_updated" {
                        let err = masked_error(&result_path, &truth, &mask).unwrap_or(f64::NAN);
                        println!(
                            "  result #{} → {}: {:.0} % of the mask from real views, {:.0} % invented; error against the truth {:.3}",
                            r["number"],
                            result_path.display(),
                            100.0 * r["from_views"].as_f64().unwrap_or(0.0),
                            100.0 * r["from_fallback"].as_f64().unwrap_or(0.0),
                            err
                        );
                    } else {
                        println!("  the new fill scored lower: result kept");
                    }
                }
            }
            Some(other) => println!("{name}: {other}: {}", ev["reason"]),
            None => {}
        }
    }
    let _ = stop.send(());
    let outcome = runtime.block_on(service).map_err(|e| format!("the service panicked: {e}"))?;
    outcome.map_err(|e| e.to_string())?;
    println!(
        "done: the service stopped cleanly. Results: {}, report: {}, history: {}, events: {}",
        result_path.display(),
        outbox.join(SESSION).join("result.json").display(),
        outbox.join(SESSION).join("history").display(),
        log.display()
    );
    println!(
        "try it on your own photographs (see README.md): a keyframe, a mask the keyframe's size (white = remove, \
         or `--mask auto`) and other shots of the facade:\n  \
         clearview fill --keyframe key.jpg --mask key.mask.png --out clear.jpg shot-*.jpg\n  \
         clearview run --watch DIR --out DIR --http 127.0.0.1:8080\n  \
         (the service: one sub-folder of DIR per session, with key.jpg, key.mask.png and the shots; \
         --http serves the preview page at the address it prints)"
    );
    Ok(())
}

/// Grows the mask by `r` pixels (a hand-drawn mask has a margin around the object too).
fn grow_mask(mask: &mut Mask, r: usize) {
    let src = mask.clone();
    let (w, h) = (mask.width(), mask.height());
    for y in 0..h {
        for x in 0..w {
            if src.is_hole(x, y) {
                continue;
            }
            let near = (y.saturating_sub(r)..(y + r + 1).min(h))
                .any(|yy| (x.saturating_sub(r)..(x + r + 1).min(w)).any(|xx| src.is_hole(xx, yy)));
            if near {
                mask.set(x, y, 255);
            }
        }
    }
}
