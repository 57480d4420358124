//! The HTTP floods of issue 16 against the real service (edge tool, loopback only, every
//! loop bounded in count and time): it starts `clearview run --http 127.0.0.1:0` on a
//! temporary folder with a session whose view is 6000x4500, then
//!
//! 1. holds `--streams` connections to `GET /api/events` for `--hold-s` seconds while it
//!    asks `/healthz` once a second (each with a 5 s timeout), and counts the event streams
//!    answered 200 and 503;
//! 2. asks the keyframe's and the view's thumbnails `--thumbs` times at once (twice: the
//!    cache cold, then warm), sampling the service's resident memory every 50 ms;
//! 3. sends `--masks` masks of 10000x10000 at once (declared small: a PNG header),
//!    sampling memory likewise.
//!
//! It prints a Markdown table (and exits 1 when /healthz failed during the flood, or the
//! peak memory went over `--ceiling-mb`).
//!
//! `cargo run --release --example http_flood -- --bin target/release/clearview
//!  [--streams 260] [--hold-s 20] [--thumbs 48] [--masks 16] [--ceiling-mb 600]`

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use clearview::imaging::convert::to_rgb8;

struct Args {
    bin: PathBuf,
    streams: usize,
    hold: Duration,
    thumbs: usize,
    masks: usize,
    ceiling_mb: f64,
}

fn args() -> Args {
    let mut a = Args {
        bin: PathBuf::from("target/release/clearview"),
        streams: 260,
        hold: Duration::from_secs(20),
        thumbs: 48,
        masks: 16,
        ceiling_mb: 600.0,
    };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let v = it.next().unwrap_or_else(|| panic!("{k} needs a value"));
        match k.as_str() {
            "--bin" => a.bin = v.into(),
            "--streams" => a.streams = v.parse().expect("--streams N"),
            "--hold-s" => a.hold = Duration::from_secs(v.parse().expect("--hold-s N")),
            "--thumbs" => a.thumbs = v.parse().expect("--thumbs N"),
            "--masks" => a.masks = v.parse().expect("--masks N"),
            "--ceiling-mb" => a.ceiling_mb = v.parse().expect("--ceiling-mb X"),
            other => panic!("unknown option {other}"),
        }
    }
    a
}

/// Resident memory of `pid` in MB.
fn rss_mb(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

/// Samples the resident memory every 50 ms while `f` runs; returns the peak in MB.
fn peak_during(pid: u32, f: impl FnOnce()) -> f64 {
    let stop = Arc::new(AtomicBool::new(false));
    let peak = Arc::new(AtomicU64::new(0));
    let sampler = {
        let (stop, peak) = (stop.clone(), peak.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                peak.fetch_max((rss_mb(pid) * 1024.0) as u64, Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(50));
            }
        })
    };
    f();
    std::thread::sleep(Duration::from_millis(200));
    stop.store(true, Ordering::Relaxed);
    sampler.join().unwrap();
    peak.load(Ordering::Relaxed) as f64 / 1024.0
}

/// One request over a fresh connection; the status, or `None` on a transport error or
/// timeout.
fn status(addr: &str, head: &str, body: &[u8], timeout: Duration) -> Option<u16> {
    let mut s = TcpStream::connect(addr).ok()?;
    s.set_read_timeout(Some(timeout)).ok()?;
    s.set_write_timeout(Some(timeout)).ok()?;
    s.write_all(head.as_bytes()).ok()?;
    s.write_all(body).ok()?;
    let mut buf = [0u8; 64];
    let n = s.read(&mut buf).ok()?;
    String::from_utf8_lossy(&buf[..n]).split_whitespace().nth(1)?.parse().ok()
}

fn get(addr: &str, path: &str, timeout: Duration) -> Option<u16> {
    status(
        addr,
        &format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"),
        b"",
        timeout,
    )
}

struct Service(Child);

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn write_png(path: &Path, img: &image::DynamicImage) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let tmp = path.with_file_name(".upload.tmp");
    img.save_with_format(&tmp, image::ImageFormat::Jpeg).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

fn main() {
    let a = args();
    let tmp = tempfile::tempdir().unwrap();
    let (inbox, out, state) = (tmp.path().join("in"), tmp.path().join("out"), tmp.path().join("state"));
    // A 6000x4500 keyframe and view of the same facade, shifted.
    let scene = clearview::synth::facade(6200, 4600, 7);
    let crop = |x: usize, y: usize| {
        let c = clearview::imaging::RgbF32::from_fn(6000, 4500, |i, j| scene.get(i + x, j + y));
        image::DynamicImage::ImageRgb8(to_rgb8(&c))
    };
    write_png(&inbox.join("s1/key.jpg"), &crop(0, 0));
    write_png(&inbox.join("s1/view.jpg"), &crop(150, 80));
    let mut child = Command::new(&a.bin)
        .args(["run", "--watch"])
        .arg(&inbox)
        .arg("--out")
        .arg(&out)
        .arg("--state")
        .arg(&state)
        .args(["--http", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start the service");
    let pid = child.id();
    let mut line = String::new();
    {
        let mut stdout = child.stdout.take().unwrap();
        let mut byte = [0u8; 1];
        while stdout.read(&mut byte).unwrap_or(0) == 1 && byte[0] != b'\n' {
            line.push(byte[0] as char);
        }
    }
    let _service = Service(child);
    let url = line.split_whitespace().last().expect("the service prints its URL").to_owned();
    let addr = url.trim_start_matches("http://").split('/').next().unwrap().to_owned();
    // Wait for the view to be listed (aligned), without asking any thumbnail: the flood
    // below finds the thumbnail cache cold.
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        let listed = ureq::get(&format!("http://{addr}/api/sessions/s1"))
            .call()
            .ok()
            .and_then(|r| r.into_string().ok())
            .is_some_and(|body| body.contains("\"view.jpg\""));
        if listed {
            break;
        }
        assert!(Instant::now() < deadline, "the view never became listed");
        std::thread::sleep(Duration::from_millis(500));
    }
    let idle_mb = rss_mb(pid);

    // 1. Event streams held while /healthz is asked.
    let codes: Vec<Option<u16>> = {
        let held: Vec<_> = (0..a.streams)
            .map(|_| {
                let addr = addr.clone();
                let hold = a.hold;
                std::thread::spawn(move || {
                    let mut s = TcpStream::connect(&addr).ok()?;
                    s.set_read_timeout(Some(hold)).ok()?;
                    s.write_all(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").ok()?;
                    let mut buf = [0u8; 64];
                    let n = s.read(&mut buf).ok()?;
                    let code = String::from_utf8_lossy(&buf[..n]).split_whitespace().nth(1)?.parse().ok();
                    // Keep listening (bounded by the hold time).
                    let start = Instant::now();
                    while start.elapsed() < hold && s.read(&mut buf).is_ok_and(|n| n > 0) {}
                    code
                })
            })
            .collect();
        std::thread::sleep(Duration::from_secs(1));
        let mut health = Vec::new();
        let start = Instant::now();
        while start.elapsed() < a.hold.saturating_sub(Duration::from_secs(2)) {
            let t = Instant::now();
            let ok = get(&addr, "/healthz", Duration::from_secs(5)) == Some(200);
            health.push((ok, t.elapsed()));
            std::thread::sleep(Duration::from_secs(1));
        }
        let ok = health.iter().filter(|h| h.0).count();
        let mut ms: Vec<f64> = health.iter().map(|h| h.1.as_secs_f64() * 1e3).collect();
        ms.sort_by(f64::total_cmp);
        println!(
            "| event streams held {} s | {} asked | healthz {ok}/{} answered, median {:.1} ms, max {:.1} ms |",
            a.hold.as_secs(),
            a.streams,
            health.len(),
            ms[ms.len() / 2],
            ms[ms.len() - 1]
        );
        if ok != health.len() {
            println!("FAIL: /healthz did not answer during the event-stream flood");
            std::process::exit(1);
        }
        held.into_iter().map(|h| h.join().unwrap_or(None)).collect()
    };
    let n200 = codes.iter().filter(|c| **c == Some(200)).count();
    let n503 = codes.iter().filter(|c| **c == Some(503)).count();
    println!(
        "| event streams answered | 200: {n200} | 503: {n503} | other/none: {} |",
        codes.len() - n200 - n503
    );

    // 2. Thumbnails at once.
    let mut worst = 0.0f64;
    for round in 0..2 {
        let peak = peak_during(pid, || {
            // Half of them the keyframe's, half the view's: two files decoded, cold in the
            // first round, from the cache in the second.
            let hs: Vec<_> = (0..a.thumbs)
                .map(|i| {
                    let addr = addr.clone();
                    let file = if i % 2 == 0 { "view.jpg" } else { "key.jpg" };
                    let path = format!("/api/sessions/s1/views/{file}/thumb");
                    std::thread::spawn(move || get(&addr, &path, Duration::from_secs(120)))
                })
                .collect();
            let ok = hs.into_iter().map(|h| h.join().unwrap()).filter(|c| *c == Some(200)).count();
            println!("| thumbnails at once, round {} | {} asked | {ok} answered 200 |", round + 1, a.thumbs);
        });
        println!(
            "| thumbnails, round {} | resident memory before {idle_mb:.0} MB | peak {peak:.0} MB |",
            round + 1
        );
        worst = worst.max(peak);
    }

    // 3. Huge masks (a PNG header that says 10000x10000, then the rest of a real one).
    let big = {
        let img = image::GrayImage::new(10_000, 10_000);
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    };
    let token = url.split("token=").nth(1).unwrap_or("").to_owned();
    let peak = peak_during(pid, || {
        let big = Arc::new(big);
        let hs: Vec<_> = (0..a.masks)
            .map(|_| {
                let (addr, big, token) = (addr.clone(), big.clone(), token.clone());
                std::thread::spawn(move || {
                    let head = format!(
                        "PUT /api/sessions/s1/mask HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\nContent-Type: image/png\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                        big.len()
                    );
                    status(&addr, &head, &big, Duration::from_secs(60))
                })
            })
            .collect();
        let codes: Vec<Option<u16>> = hs.into_iter().map(|h| h.join().unwrap()).collect();
        println!("| 10000x10000 masks at once | {} sent | answers {codes:?} |", a.masks);
    });
    println!("| 10000x10000 masks | peak {peak:.0} MB |");
    worst = worst.max(peak);
    println!("| HTTP side, worst peak | {worst:.0} MB | ceiling {:.0} MB |", a.ceiling_mb);
    if worst > a.ceiling_mb {
        println!("FAIL: memory over the ceiling");
        std::process::exit(1);
    }
}
