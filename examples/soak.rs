//! The soak test of the capture service (edge tool, run by `bench/soak.sh`): the real
//! `clearview run` on a temporary folder for N minutes, files landing at a steady rate over
//! a few sessions, a fifth of them bad; every `--sample-s` seconds the service's resident
//! memory, open descriptors and threads go to a CSV. At the end it checks that the service
//! lived throughout, that every good file yielded an event saying it was used or rejected
//! and why, that every session has a result, and that memory, descriptors and threads
//! stayed flat. Exits 1 when a check fails.
//!
//! `cargo run --release --example soak -- --bin target/release/clearview [--minutes 30]
//!  [--interval-ms 2500] [--sessions 4] [--size 800x600] [--sample-s 60] [--csv FILE]
//!  [--keep DIR]`

use std::collections::{BTreeMap, HashMap};
use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use clearview::geometry::Homography;
use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::imaging::{Mask, RgbF32};
use clearview::synth::{self, Occluder};
use image::{DynamicImage, ImageFormat};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

/// RSS tolerance: the last third's mean may exceed the middle third's by this share...
const RSS_SHARE: f64 = 0.10;
/// ...plus this many MB (allocator noise on a small service).
const RSS_SLACK_MB: f64 = 32.0;
/// Descriptors and threads: the last third's maximum may exceed the middle third's by this.
const COUNT_SLACK: u64 = 4;

struct Args {
    bin: PathBuf,
    minutes: f64,
    interval: Duration,
    sessions: usize,
    size: (usize, usize),
    sample: Duration,
    csv: Option<PathBuf>,
    keep: Option<PathBuf>,
}

fn parse_args() -> Args {
    let mut a = Args {
        bin: PathBuf::from("target/release/clearview"),
        minutes: 30.0,
        interval: Duration::from_millis(2500),
        sessions: 4,
        size: (800, 600),
        sample: Duration::from_secs(60),
        csv: None,
        keep: None,
    };
    let mut sample_given = false;
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().unwrap_or_else(|| die(&format!("{flag} needs a value")));
        match flag.as_str() {
            "--bin" => a.bin = value().into(),
            "--minutes" => a.minutes = value().parse().unwrap_or_else(|_| die("--minutes: a number")),
            "--interval-ms" => {
                a.interval = Duration::from_millis(value().parse().unwrap_or_else(|_| die("--interval-ms")))
            }
            "--sessions" => a.sessions = value().parse().unwrap_or_else(|_| die("--sessions: a number")),
            "--size" => {
                let v = value();
                let (w, h) = v.split_once('x').unwrap_or_else(|| die("--size: WxH"));
                a.size = (
                    w.parse().unwrap_or_else(|_| die("--size")),
                    h.parse().unwrap_or_else(|_| die("--size")),
                );
            }
            "--sample-s" => {
                a.sample = Duration::from_secs_f64(value().parse().unwrap_or_else(|_| die("--sample-s")));
                sample_given = true;
            }
            "--csv" => a.csv = Some(value().into()),
            "--keep" => a.keep = Some(value().into()),
            other => die(&format!("unknown argument {other}")),
        }
    }
    if !sample_given && a.minutes < 5.0 {
        a.sample = Duration::from_secs(10);
    }
    if a.sessions == 0 || a.minutes <= 0.0 {
        die("--sessions and --minutes must be positive");
    }
    a
}

fn die(msg: &str) -> ! {
    eprintln!("soak: {msg}");
    std::process::exit(64);
}

fn encode(img: &DynamicImage, format: ImageFormat) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, format).expect("encoding to memory");
    out.into_inner()
}

fn jpeg(img: &RgbF32) -> Vec<u8> {
    encode(&DynamicImage::ImageRgb8(to_rgb8(img)), ImageFormat::Jpeg)
}

/// One generated session: its keyframe, mask and a pool of good views, all encoded.
struct Scene {
    name: String,
    key: Vec<u8>,
    mask: Vec<u8>,
    wrong_mask: Vec<u8>,
    views: Vec<Vec<u8>>,
    foreign: Vec<u8>,
}

fn scene(i: usize, (w, h): (usize, usize)) -> Scene {
    let seed = 100 + i as u64;
    let world = synth::facade(w * 3 / 2, h * 3 / 2, seed);
    let centre = Homography::translation(w as f64 / 4.0, h as f64 / 4.0);
    let mut key = synth::render_view(&world, &centre, w, h, [0.5; 3]);
    let mut mask = Mask::new(w, h, 0);
    let s = w as f32 / 400.0;
    synth::paint_occluder(
        &mut key,
        Some(&mut mask),
        Occluder::Tree,
        w as f32 * 0.5,
        h as f32 * 0.55,
        110.0 * s,
        seed,
    );
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let views = (0..10)
        .map(|k| {
            let key_to_view = synth::random_homography(&mut rng, w, h, 0.1, 0.2, (0.9, 1.1));
            let view_to_world = centre.after(&key_to_view.inverse().expect("regular"));
            let mut v = synth::render_view(&world, &view_to_world, w, h, [0.5; 3]);
            let cx = rng.random_range(0.15..0.85) * w as f32;
            synth::paint_occluder(
                &mut v,
                None,
                Occluder::Person,
                cx,
                h as f32 * 0.6,
                60.0 * s,
                seed * 100 + k,
            );
            synth::expose(&mut v, rng.random_range(0.85..1.1), 0.01);
            jpeg(&v)
        })
        .collect();
    let other = synth::facade(w, h, seed + 5000);
    let luma = |m: &Mask| DynamicImage::ImageLuma8(mask_to_luma8(m));
    Scene {
        name: format!("s{i}"),
        key: jpeg(&key),
        mask: encode(&luma(&mask), ImageFormat::Png),
        wrong_mask: encode(&luma(&Mask::new(w / 2, h / 2, 255)), ImageFormat::Png),
        views,
        foreign: jpeg(&other),
    }
}

/// What a file was, and so what the service must say about it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    Key,
    Mask,
    View,
    Empty,
    Truncated,
    Random,
    WrongMask,
    Foreign,
}

impl Kind {
    fn good(self) -> bool {
        matches!(self, Kind::Key | Kind::Mask | Kind::View)
    }
}

const BAD: [Kind; 5] = [Kind::Empty, Kind::Truncated, Kind::Random, Kind::WrongMask, Kind::Foreign];

struct Landed {
    session: String,
    name: String,
    kind: Kind,
}

/// Writes under a hidden name and renames: what a careful uploader does.
fn put(path: &Path, bytes: &[u8]) {
    let tmp = path.with_file_name(format!(".{}.upload", path.file_name().expect("a name").to_string_lossy()));
    std::fs::write(&tmp, bytes).unwrap_or_else(|e| panic!("{}: {e}", tmp.display()));
    std::fs::rename(&tmp, path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

#[derive(Debug, Clone, Copy)]
struct Sample {
    t: f64,
    rss_kb: u64,
    fds: u64,
    threads: u64,
}

fn sample(pid: u32, t: f64) -> Option<Sample> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let rss_kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())?;
    let count = |d: &str| std::fs::read_dir(format!("/proc/{pid}/{d}")).map(|r| r.count() as u64).ok();
    Some(Sample { t, rss_kb, fds: count("fd")?, threads: count("task")? })
}

fn events(out: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(out.join("events.jsonl")).unwrap_or_default();
    text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect()
}

/// The file an event names, if any.
fn event_file(e: &Value) -> Option<String> {
    ["file", "mask", "keyframe"].iter().find_map(|k| e.get(*k)?.as_str().map(str::to_owned))
}

fn stats(v: &mut [f64]) -> (f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[0], v[v.len() / 2], v[v.len() - 1])
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn alive(child: &mut Child) -> bool {
    matches!(child.try_wait(), Ok(None))
}

fn main() {
    let args = parse_args();
    let tmp = tempfile::tempdir().expect("a temporary folder");
    let root = args.keep.clone().unwrap_or_else(|| tmp.path().to_owned());
    let (inbox, outbox, state) = (root.join("inbox"), root.join("outbox"), root.join("state"));
    for d in [&inbox, &outbox, &state] {
        std::fs::create_dir_all(d).unwrap_or_else(|e| die(&format!("{}: {e}", d.display())));
    }
    let config = root.join("clearview.toml");
    std::fs::write(
        &config,
        format!(
            "[watch]\ndir = {inbox:?}\nquiet_period_ms = 500\n[output]\ndir = {outbox:?}\nhistory = 5\n\
             [state]\ndir = {state:?}\n[session]\nkeyframe = \"key\"\n"
        ),
    )
    .expect("writing the configuration");

    let t0 = Instant::now();
    eprintln!("soak: rendering {} sessions of {}x{}", args.sessions, args.size.0, args.size.1);
    let scenes: Vec<Scene> = (0..args.sessions).map(|i| scene(i, args.size)).collect();
    eprintln!("soak: rendered in {:.1} s; starting {}", t0.elapsed().as_secs_f64(), args.bin.display());

    let log = std::fs::File::create(root.join("service.log")).expect("the log file");
    let mut child = Command::new(&args.bin)
        .args(["run", "--config"])
        .arg(&config)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap_or_else(|e| die(&format!("{}: {e}", args.bin.display())));
    let pid = child.id();

    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut landed: Vec<Landed> = Vec::new();
    let mut samples: Vec<Sample> = Vec::new();
    let mut died_at = None;
    let start = Instant::now();
    let end = start + Duration::from_secs_f64(args.minutes * 60.0);
    let mut next_file = start;
    let mut next_sample = start + args.sample;
    let mut restore: Vec<(Instant, usize)> = Vec::new();
    let mut n = 0usize;
    for (i, s) in scenes.iter().enumerate() {
        let dir = inbox.join(&s.name);
        std::fs::create_dir_all(&dir).expect("a session folder");
        put(&dir.join("key.mask.png"), &s.mask);
        put(&dir.join("key.jpg"), &s.key);
        for (name, kind) in [("key.mask.png", Kind::Mask), ("key.jpg", Kind::Key)] {
            landed.push(Landed { session: scenes[i].name.clone(), name: name.into(), kind });
        }
    }
    while Instant::now() < end {
        let now = Instant::now();
        if now >= next_sample {
            match sample(pid, start.elapsed().as_secs_f64()) {
                Some(s) if alive(&mut child) => samples.push(s),
                _ => {
                    died_at = Some(start.elapsed().as_secs_f64());
                    break;
                }
            }
            let s = samples.last().expect("just pushed");
            eprintln!(
                "soak: {:6.0} s  rss {:7.1} MB  fds {:3}  threads {:3}  files {}",
                s.t,
                s.rss_kb as f64 / 1024.0,
                s.fds,
                s.threads,
                landed.len()
            );
            next_sample += args.sample;
        }
        if now >= next_file {
            let si = n % scenes.len();
            let s = &scenes[si];
            let dir = inbox.join(&s.name);
            // Every fifth file is bad, cycling through the kinds of bad.
            let kind = if n % 5 == 3 { BAD[(n / 5) % BAD.len()] } else { Kind::View };
            let (name, bytes): (String, Vec<u8>) = match kind {
                Kind::View => (format!("v{n:05}.jpg"), s.views[rng.random_range(0..s.views.len())].clone()),
                Kind::Empty => (format!("bad{n:05}.jpg"), Vec::new()),
                Kind::Truncated => {
                    let v = &s.views[n % s.views.len()];
                    (format!("bad{n:05}.jpg"), v[..v.len() * rng.random_range(1..9) / 10].to_vec())
                }
                Kind::Random => (format!("bad{n:05}.png"), (0..50_000).map(|_| rng.random::<u8>()).collect()),
                Kind::WrongMask => {
                    restore.push((now + 2 * args.interval, si));
                    ("key.mask.png".into(), s.wrong_mask.clone())
                }
                Kind::Foreign => (format!("bad{n:05}.jpg"), s.foreign.clone()),
                Kind::Key | Kind::Mask => unreachable!("not drawn"),
            };
            put(&dir.join(&name), &bytes);
            landed.push(Landed { session: s.name.clone(), name, kind });
            n += 1;
            next_file += args.interval;
        }
        restore.retain(|&(at, si)| {
            if now < at {
                return true;
            }
            let s = &scenes[si];
            put(&inbox.join(&s.name).join("key.mask.png"), &s.mask);
            landed.push(Landed { session: s.name.clone(), name: "key.mask.png".into(), kind: Kind::Mask });
            false
        });
        std::thread::sleep(Duration::from_millis(50));
    }
    for (_, si) in restore.drain(..) {
        let s = &scenes[si];
        put(&inbox.join(&s.name).join("key.mask.png"), &s.mask);
        landed.push(Landed { session: s.name.clone(), name: "key.mask.png".into(), kind: Kind::Mask });
    }

    // Let the backlog drain: wait until every landed file is named by an event and every
    // session's mask, put right last, is set again (or 3 min).
    let named = |evs: &[Value]| -> HashMap<(String, String), Vec<Value>> {
        let mut m: HashMap<(String, String), Vec<Value>> = HashMap::new();
        for e in evs {
            if let (Some(s), Some(f)) = (e.get("session").and_then(Value::as_str), event_file(e)) {
                m.entry((s.to_owned(), f)).or_default().push(e.clone());
            }
        }
        m
    };
    let drain_start = Instant::now();
    while died_at.is_none() && drain_start.elapsed() < Duration::from_secs(180) {
        let m = named(&events(&outbox));
        let mask_settled = |s: &Scene| {
            m.get(&(s.name.clone(), "key.mask.png".to_owned()))
                .and_then(|evs| evs.last())
                .is_some_and(|e| e["event"] == "mask_set")
        };
        if landed.iter().all(|l| m.contains_key(&(l.session.clone(), l.name.clone())))
            && scenes.iter().all(mask_settled)
        {
            break;
        }
        if !alive(&mut child) {
            died_at = Some(start.elapsed().as_secs_f64());
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    let drain_s = drain_start.elapsed().as_secs_f64();
    if died_at.is_none() {
        if let Some(s) = sample(pid, start.elapsed().as_secs_f64()) {
            samples.push(s);
        }
        // SIGTERM: a clean stop is part of the contract.
        // SAFETY: plain kill(2) on our own child's pid.
        unsafe { libc::kill(pid as i32, libc::SIGTERM) };
    }
    let status = child.wait().expect("waiting for the service");
    let evs = events(&outbox);
    let by_file = named(&evs);

    // Checks.
    let mut failures: Vec<String> = Vec::new();
    if let Some(t) = died_at {
        failures.push(format!("the service died after {t:.0} s ({status})"));
    } else if !status.success() {
        failures.push(format!("the service did not stop cleanly on SIGTERM: {status}"));
    }
    let mut per_kind: BTreeMap<String, BTreeMap<String, usize>> = BTreeMap::new();
    let mut mask_kinds: HashMap<String, Vec<Kind>> = HashMap::new();
    for l in &landed {
        if matches!(l.kind, Kind::Mask | Kind::WrongMask) {
            mask_kinds.entry(l.session.clone()).or_default().push(l.kind);
            continue;
        }
        let evs = by_file.get(&(l.session.clone(), l.name.clone())).cloned().unwrap_or_default();
        let kinds: Vec<&str> = evs.iter().filter_map(|e| e.get("event")?.as_str()).collect();
        let said = |k: &str| kinds.contains(&k);
        let with_reason = |k: &str| {
            evs.iter().any(|e| e["event"] == k && e["reason"].as_str().is_some_and(|r| !r.is_empty()))
        };
        let outcome = if said("view_accepted") {
            "accepted"
        } else if with_reason("view_rejected") {
            "rejected"
        } else if with_reason("file_skipped") {
            "skipped"
        } else if said("session_started") || said("keyframe_changed") {
            "keyframe"
        } else {
            "no event"
        };
        *per_kind.entry(format!("{:?}", l.kind)).or_default().entry(outcome.into()).or_default() += 1;
        let ok = match l.kind {
            Kind::Key => outcome == "keyframe",
            Kind::View => matches!(outcome, "accepted" | "rejected"),
            Kind::Foreign => matches!(outcome, "rejected" | "skipped"),
            _ => outcome != "no event",
        };
        if !ok {
            failures.push(format!("{}/{} ({:?}): {outcome}, events {kinds:?}", l.session, l.name, l.kind));
        }
    }
    for s in &scenes {
        let evs = by_file.get(&(s.name.clone(), "key.mask.png".into())).cloned().unwrap_or_default();
        let set = evs.iter().filter(|e| e["event"] == "mask_set").count();
        let refused = evs
            .iter()
            .filter(|e| {
                e["event"] == "file_skipped" && e["reason"].as_str().is_some_and(|r| r.contains("mask is"))
            })
            .count();
        let wrong =
            mask_kinds.get(&s.name).map_or(0, |k| k.iter().filter(|&&k| k == Kind::WrongMask).count());
        let good = mask_kinds.get(&s.name).map_or(0, |k| k.len()) - wrong;
        let last = evs.last().and_then(|e| e["event"].as_str()).unwrap_or("none");
        per_kind.entry("Mask".into()).or_default().insert(format!("{} set", s.name), set);
        per_kind.entry("WrongMask".into()).or_default().insert(format!("{} refused", s.name), refused);
        // A wrong mask replaced within the quiet period may never be read: at least one of
        // each must be seen, and the last word on the mask must be that it was set.
        if set == 0 || (wrong > 0 && refused == 0) || last != "mask_set" || set > good {
            failures.push(format!(
                "{}/key.mask.png: {good} good and {wrong} wrong written, {set} set, {refused} refused, last {last}",
                s.name
            ));
        }
        let dir = outbox.join(&s.name);
        if !dir.join("result.png").is_file() || !dir.join("result.json").is_file() {
            failures.push(format!("{}: no result.png and result.json", s.name));
        }
    }
    let results = evs.iter().filter(|e| e["event"] == "result_updated").count();
    let good = landed.iter().filter(|l| l.kind.good()).count();
    let accepted = per_kind.get("View").and_then(|m| m.get("accepted")).copied().unwrap_or(0);
    let views = landed.iter().filter(|l| l.kind == Kind::View).count();
    if accepted * 2 < views {
        failures.push(format!(
            "only {accepted} of {views} good views accepted: the soak did not exercise the fill"
        ));
    }

    // Flatness: the last third against the middle third (the first third is warm-up).
    let tail: Vec<&Sample> = samples.iter().collect();
    let (mid, last): (Vec<&Sample>, Vec<&Sample>) = {
        let total = tail.last().map_or(0.0, |s| s.t);
        let mid = tail.iter().filter(|s| s.t > total / 3.0 && s.t <= 2.0 * total / 3.0).copied().collect();
        let last = tail.iter().filter(|s| s.t > 2.0 * total / 3.0).copied().collect();
        (mid, last)
    };
    if mid.is_empty() || last.is_empty() || samples.len() < 3 {
        failures.push(format!("too few samples to judge growth ({})", samples.len()));
    } else {
        let rss = |v: &[&Sample]| mean(&v.iter().map(|s| s.rss_kb as f64 / 1024.0).collect::<Vec<_>>());
        let (m, l) = (rss(&mid), rss(&last));
        let limit = m * (1.0 + RSS_SHARE) + RSS_SLACK_MB;
        println!("rss: middle third mean {m:.1} MB, last third mean {l:.1} MB (limit {limit:.1})");
        if l > limit {
            failures.push(format!("resident memory grows: {m:.1} MB → {l:.1} MB (limit {limit:.1})"));
        }
        for (what, get) in
            [("fds", (|s: &Sample| s.fds) as fn(&Sample) -> u64), ("threads", |s: &Sample| s.threads)]
        {
            let (m, l) = (
                mid.iter().map(|s| get(s)).max().unwrap_or(0),
                last.iter().map(|s| get(s)).max().unwrap_or(0),
            );
            println!("{what}: middle third max {m}, last third max {l} (limit {})", m + COUNT_SLACK);
            if l > m + COUNT_SLACK {
                failures.push(format!("{what} grow: {m} → {l}"));
            }
        }
    }

    // Report.
    let csv = args.csv.clone().unwrap_or_else(|| root.join("soak.csv"));
    let mut text = String::from("t_s,rss_kb,fds,threads\n");
    for s in &samples {
        text += &format!("{:.0},{},{},{}\n", s.t, s.rss_kb, s.fds, s.threads);
    }
    std::fs::write(&csv, text).unwrap_or_else(|e| eprintln!("soak: {}: {e}", csv.display()));
    let col = |f: fn(&Sample) -> f64| stats(&mut samples.iter().map(f).collect::<Vec<_>>());
    let (r0, r1, r2) = col(|s| s.rss_kb as f64 / 1024.0);
    let (f0, f1, f2) = col(|s| s.fds as f64);
    let (t0_, t1, t2) = col(|s| s.threads as f64);
    println!("samples: {} (every {:.0} s) in {}", samples.len(), args.sample.as_secs_f64(), csv.display());
    println!("rss MB   min {r0:.1}  median {r1:.1}  max {r2:.1}");
    println!("fds      min {f0:.0}  median {f1:.0}  max {f2:.0}");
    println!("threads  min {t0_:.0}  median {t1:.0}  max {t2:.0}");
    println!(
        "files in: {} ({} good, {} bad); results written: {results}; drained in {drain_s:.0} s; events: {}",
        landed.len(),
        good,
        landed.len() - good,
        evs.len()
    );
    for (kind, outcomes) in &per_kind {
        println!("  {kind:10} {outcomes:?}");
    }
    if failures.is_empty() {
        println!("soak: PASS ({:.1} min)", args.minutes);
    } else {
        for f in &failures {
            println!("FAIL: {f}");
        }
        println!("soak: FAIL ({} checks), log in {}", failures.len(), root.join("service.log").display());
        if args.keep.is_none() {
            let _ = tmp.keep();
        }
        std::process::exit(1);
    }
}
