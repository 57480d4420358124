//! What an idle service costs (edge tool, issue 16): the real `clearview run` on a
//! temporary folder with `--sessions` rendered sessions, each with its keyframe, mask and a
//! view; once every session has its result, the service's CPU time (user + system, from
//! `/proc`) is sampled over `--seconds` one-second windows, in notify mode and in poll mode.
//! Prints a Markdown table: the median and the largest share of one core per window.
//!
//! `cargo run --release --example idle_cpu -- --bin target/release/clearview [--seconds 30]
//!  [--sessions 4]`

use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use clearview::geometry::Homography;
use clearview::imaging::Mask;
use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::synth::{self, Occluder};
use rand::SeedableRng;

fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let Some(close) = stat.rfind(')') else { return 0.0 };
    let f: Vec<&str> = stat[close + 2..].split_whitespace().collect();
    let ticks: f64 = f[11].parse::<f64>().unwrap_or(0.0) + f[12].parse::<f64>().unwrap_or(0.0);
    // SAFETY: sysconf has no preconditions.
    ticks / unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64
}

fn put(path: &Path, bytes: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let tmp = path.with_file_name(".upload.tmp");
    std::fs::write(&tmp, bytes).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

fn png(img: image::DynamicImage) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

fn render(inbox: &Path, sessions: usize) {
    let (w, h) = (640, 480);
    for s in 0..sessions {
        let scene = synth::facade(w * 3 / 2, h * 3 / 2, s as u64);
        let centre = Homography::translation(w as f64 / 4.0, h as f64 / 4.0);
        let truth = synth::render_view(&scene, &centre, w, h, [0.5; 3]);
        let mut key = truth.clone();
        let mut mask = Mask::new(w, h, 0);
        synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 320.0, 260.0, 160.0, 3);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(s as u64);
        let k2v = synth::random_homography(&mut rng, w, h, 0.1, 0.2, (0.9, 1.1));
        let view = synth::render_view(&scene, &centre.after(&k2v.inverse().unwrap()), w, h, [0.5; 3]);
        let dir = inbox.join(format!("s{s}"));
        put(&dir.join("key.mask.png"), &png(image::DynamicImage::ImageLuma8(mask_to_luma8(&mask))));
        put(&dir.join("key.png"), &png(image::DynamicImage::ImageRgb8(to_rgb8(&key))));
        put(&dir.join("v1.png"), &png(image::DynamicImage::ImageRgb8(to_rgb8(&view))));
    }
}

struct Service(Child);

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn main() {
    let mut bin = PathBuf::from("target/release/clearview");
    let (mut seconds, mut sessions) = (30usize, 4usize);
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let v = it.next().unwrap_or_else(|| panic!("{k} needs a value"));
        match k.as_str() {
            "--bin" => bin = v.into(),
            "--seconds" => seconds = v.parse().expect("--seconds N"),
            "--sessions" => sessions = v.parse().expect("--sessions N"),
            other => panic!("unknown option {other}"),
        }
    }
    println!("| mode | sessions | windows | median share of a core | largest |");
    println!("|---|---:|---:|---:|---:|");
    for mode in ["notify", "poll"] {
        let tmp = tempfile::tempdir().unwrap();
        let (inbox, out) = (tmp.path().join("in"), tmp.path().join("out"));
        let config = tmp.path().join("c.toml");
        std::fs::write(
            &config,
            format!(
                "[watch]\ndir = {inbox:?}\nmode = {mode:?}\n[output]\ndir = {out:?}\n[state]\ndir = {:?}\n",
                tmp.path().join("state")
            ),
        )
        .unwrap();
        render(&inbox, sessions);
        let child = Command::new(&bin)
            .args(["run", "--config"])
            .arg(&config)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start the service");
        let pid = child.id();
        let _service = Service(child);
        let deadline = Instant::now() + Duration::from_secs(120);
        while (0..sessions).any(|s| !out.join(format!("s{s}/result.png")).exists()) {
            assert!(Instant::now() < deadline, "no result for every session");
            std::thread::sleep(Duration::from_millis(200));
        }
        std::thread::sleep(Duration::from_secs(2));
        let mut shares = Vec::with_capacity(seconds);
        for _ in 0..seconds {
            let (c0, t0) = (cpu_seconds(pid), Instant::now());
            std::thread::sleep(Duration::from_secs(1));
            shares.push((cpu_seconds(pid) - c0) / t0.elapsed().as_secs_f64());
        }
        shares.sort_by(f64::total_cmp);
        println!(
            "| {mode} | {sessions} | {seconds} | {:.2} % | {:.2} % |",
            shares[shares.len() / 2] * 100.0,
            shares[shares.len() - 1] * 100.0
        );
    }
}
