//! Helpers of the tests that run the real service (`clearview run`) on a temporary
//! folder: a rendered session, the folders and configuration, the binary itself (with or
//! without its HTTP server), its event log, and a small HTTP client.
#![allow(dead_code)]

pub mod nats;

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use clearview::geometry::Homography;
use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::imaging::{Mask, RgbF32};
use clearview::synth::{self, Occluder};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

pub const W: usize = 400;
pub const H: usize = 300;

/// A facade, its keyframe with a tree in front (and the truth without it), the tree's
/// mask, and views of it from elsewhere.
pub struct Scene {
    scene: RgbF32,
    centre: Homography,
    pub truth: RgbF32,
    pub key: RgbF32,
    pub mask: Mask,
    rng: ChaCha8Rng,
}

impl Scene {
    pub fn new(seed: u64) -> Self {
        let scene = synth::facade(W * 3 / 2, H * 3 / 2, seed);
        let centre = Homography::translation(W as f64 / 4.0, H as f64 / 4.0);
        let truth = synth::render_view(&scene, &centre, W, H, [0.5; 3]);
        let mut key = truth.clone();
        let mut mask = Mask::new(W, H, 0);
        synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 200.0, 160.0, 110.0, 3);
        Self { scene, centre, truth, key, mask, rng: ChaCha8Rng::seed_from_u64(seed) }
    }

    /// A view from elsewhere with its own occluder, a person at `cx` (keyframe
    /// coordinates roughly) of `size` (0: none), and its own exposure.
    pub fn view(&mut self, i: u64, cx: f32, size: f32) -> RgbF32 {
        let key_to_view = synth::random_homography(&mut self.rng, W, H, 0.1, 0.2, (0.9, 1.1));
        let view_to_scene = self.centre.after(&key_to_view.inverse().unwrap());
        let mut v = synth::render_view(&self.scene, &view_to_scene, W, H, [0.5; 3]);
        if size > 0.0 {
            synth::paint_occluder(&mut v, None, Occluder::Person, cx, 170.0, size, 100 + i);
        }
        synth::expose(&mut v, 0.9 + 0.03 * i as f32, 0.01);
        v
    }

    /// A view from elsewhere with a passer-by of `size` who stands where the keyframe's
    /// `(kx, ky)` is, and where he stands, in keyframe pixels.
    pub fn view_and_footprint(&mut self, i: u64, kx: f32, ky: f32, size: f32) -> (RgbF32, Mask) {
        let key_to_view = synth::random_homography(&mut self.rng, W, H, 0.1, 0.2, (0.9, 1.1));
        let view_to_scene = self.centre.after(&key_to_view.inverse().unwrap());
        let mut v = synth::render_view(&self.scene, &view_to_scene, W, H, [0.5; 3]);
        let mut his = Mask::new(W, H, 0);
        let at = key_to_view.apply(nalgebra::Point2::new(kx as f64, ky as f64)).unwrap();
        synth::paint_occluder(
            &mut v,
            Some(&mut his),
            Occluder::Person,
            at.x as f32,
            at.y as f32,
            size,
            100 + i,
        );
        synth::expose(&mut v, 0.9 + 0.03 * i as f32, 0.01);
        let mut footprint = Mask::new(W, H, 0);
        for y in 0..H {
            for x in 0..W {
                let Some(at) = key_to_view.apply(nalgebra::Point2::new(x as f64, y as f64)) else { continue };
                let (vx, vy) = (at.x.round(), at.y.round());
                if vx >= 0.0
                    && vy >= 0.0
                    && (vx as usize) < W
                    && (vy as usize) < H
                    && his.is_hole(vx as usize, vy as usize)
                {
                    footprint.set(x, y, 255);
                }
            }
        }
        (v, footprint)
    }

    /// A view from elsewhere showing the passer-by that the keyframe shows at `(kx, ky)`
    /// (keyframe coordinates; `seed` as the keyframe's was painted), where he stood: he had
    /// not moved.
    pub fn view_with_keys_person(&mut self, i: u64, kx: f32, ky: f32, size: f32, seed: u64) -> RgbF32 {
        let key_to_view = synth::random_homography(&mut self.rng, W, H, 0.1, 0.2, (0.9, 1.1));
        let view_to_scene = self.centre.after(&key_to_view.inverse().unwrap());
        let mut v = synth::render_view(&self.scene, &view_to_scene, W, H, [0.5; 3]);
        let at = key_to_view.apply(nalgebra::Point2::new(kx as f64, ky as f64)).unwrap();
        synth::paint_occluder(&mut v, None, Occluder::Person, at.x as f32, at.y as f32, size, seed);
        synth::expose(&mut v, 0.9 + 0.03 * i as f32, 0.01);
        v
    }

    /// A view from elsewhere with nothing in front.
    pub fn clear_view(&mut self, i: u64) -> RgbF32 {
        self.view(i, 0.0, 0.0)
    }

    /// Mean absolute error over the masked pixels of `img` against the truth.
    pub fn masked_error(&self, img: &image::RgbImage) -> f64 {
        let (mut sum, mut n) = (0.0, 0usize);
        for y in 0..H {
            for x in 0..W {
                if self.mask.is_hole(x, y) {
                    let t = self.truth.get(x, y);
                    let p = img.get_pixel(x as u32, y as u32).0;
                    sum += (0..3).map(|c| (t[c] as f64 - p[c] as f64 / 255.0).abs()).sum::<f64>() / 3.0;
                    n += 1;
                }
            }
        }
        sum / n.max(1) as f64
    }
}

pub fn png(img: &RgbF32) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    to_rgb8(img).write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

pub fn mask_png(mask: &Mask) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    mask_to_luma8(mask).write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// `mask` as a user paints it in an editor on a transparent layer: a red stroke, and
/// transparency stored as white elsewhere.
pub fn painted_layer_png(mask: &Mask) -> Vec<u8> {
    let layer = image::RgbaImage::from_fn(mask.width() as u32, mask.height() as u32, |x, y| {
        if mask.is_hole(x as usize, y as usize) {
            image::Rgba([220, 30, 30, 255])
        } else {
            image::Rgba([255, 255, 255, 0])
        }
    });
    let mut out = std::io::Cursor::new(Vec::new());
    layer.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// Writes under a hidden name and renames, as a careful uploader does.
pub fn put(path: &Path, bytes: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let tmp = path.with_file_name(format!(".{}.upload", path.file_name().unwrap().to_string_lossy()));
    std::fs::write(&tmp, bytes).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

/// The session's keyframe `key.png` and its mask `key.mask.png` (the mask first, so the
/// session starts with it).
pub fn put_key_and_mask(dir: &Path, s: &Scene) {
    put(&dir.join("key.mask.png"), &mask_png(&s.mask));
    put(&dir.join("key.png"), &png(&s.key));
}

pub struct Folders {
    pub tmp: tempfile::TempDir,
    pub root: PathBuf,
    pub inbox: PathBuf,
    pub outbox: PathBuf,
    pub state: PathBuf,
    pub config: PathBuf,
}

/// Temporary folders and a configuration with a short quiet period; `extra` is appended
/// (it starts inside `[compute]`).
pub fn folders(extra: &str) -> Folders {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_owned();
    let (inbox, outbox, state) = (root.join("inbox"), root.join("outbox"), root.join("state"));
    let config = root.join("clearview.toml");
    std::fs::write(
        &config,
        format!(
            "[watch]\ndir = {inbox:?}\nquiet_period_ms = 300\n[output]\ndir = {outbox:?}\nhistory = 3\n\
             [state]\ndir = {state:?}\n[compute]\ngrace_period_ms = 15000\n{extra}"
        ),
    )
    .unwrap();
    Folders { tmp, root, inbox, outbox, state, config }
}

pub fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_clearview")
}

/// The running service; killed when dropped (a test that fails leaves no process).
pub struct Service {
    pub child: Child,
    /// Where its standard error (the log) goes: `service-N.log` in the folders' root, one
    /// per start.
    pub log: PathBuf,
    /// With the HTTP server: `http://127.0.0.1:PORT`, the address, the token and the URL
    /// the service printed. Empty without it.
    pub base: String,
    pub addr: String,
    pub token: String,
    pub url: String,
}

impl Service {
    /// Starts `clearview run --config F`.
    pub fn start(f: &Folders) -> Self {
        Self::started(f, None)
    }

    /// Starts `clearview run --config F` as user `uid` (the caller must be root, and the
    /// folders must be that user's).
    pub fn start_as(f: &Folders, uid: u32) -> Self {
        Self::started(f, Some(uid))
    }

    fn started(f: &Folders, uid: Option<u32>) -> Self {
        let (child, log) = Self::spawn_with(f, &[], &[], Stdio::null(), uid);
        Self {
            child,
            log,
            base: String::new(),
            addr: String::new(),
            token: String::new(),
            url: String::new(),
        }
    }

    /// Starts `clearview run --config F --http LISTEN` and reads the printed URL.
    pub fn start_http(f: &Folders, listen: &str, env: &[(&str, &str)]) -> Self {
        let (mut child, log) = Self::spawn(f, &["--http", listen], env, Stdio::piped());
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let line = rx.recv_timeout(Duration::from_secs(20)).unwrap_or_else(|_| {
            panic!("no URL printed; log:\n{}", std::fs::read_to_string(&log).unwrap_or_default())
        });
        let url = line.split_whitespace().last().unwrap().to_owned();
        assert!(line.starts_with("clearview: preview page at http://"), "{line}");
        let rest = url.strip_prefix("http://").unwrap();
        let (addr, query) = rest.split_once('/').unwrap();
        let token = query.strip_prefix("?token=").unwrap_or("").to_owned();
        let addr = addr.replace("0.0.0.0", "127.0.0.1");
        Self { child, log, base: format!("http://{addr}"), addr, token, url }
    }

    fn spawn(f: &Folders, args: &[&str], env: &[(&str, &str)], stdout: Stdio) -> (Child, PathBuf) {
        Self::spawn_with(f, args, env, stdout, None)
    }

    fn spawn_with(
        f: &Folders,
        args: &[&str],
        env: &[(&str, &str)],
        stdout: Stdio,
        uid: Option<u32>,
    ) -> (Child, PathBuf) {
        use std::os::unix::process::CommandExt;
        let run = (1..).find(|n| !f.root.join(format!("service-{n}.log")).exists()).unwrap();
        let log = f.root.join(format!("service-{run}.log"));
        let mut command = Command::new(bin());
        if let Some(uid) = uid {
            command.uid(uid).gid(uid);
        }
        let child = command
            .args(["run", "--config"])
            .arg(&f.config)
            .args(args)
            .envs(env.iter().copied())
            .env("CLEARVIEW_LOG", "clearview=debug")
            .stdout(stdout)
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        (child, log)
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Whether the process is still running.
    pub fn alive(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }

    /// SIGTERM, then the exit code.
    pub fn terminate(mut self) -> i32 {
        let ok = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status().unwrap();
        assert!(ok.success());
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status.code().expect("exited, not killed by a signal");
            }
            assert!(Instant::now() < deadline, "the service did not stop within 30 s of SIGTERM");
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The event log (`events.jsonl` in the out folder), parsed.
pub fn events(f: &Folders) -> Vec<Value> {
    whole_lines(&f.outbox.join("events.jsonl"))
}

/// The whole lines of a JSON-lines log another process may be appending to, each parsed
/// (a line that is not JSON fails). A last line without its newline is being written: a
/// reader can see the first part of a single `write` that crosses a page of the file, so
/// it is left for the next read.
pub fn whole_lines(path: &Path) -> Vec<Value> {
    let Ok(text) = std::fs::read_to_string(path) else { return Vec::new() };
    let whole = text.rfind('\n').map_or("", |end| &text[..end]);
    whole.lines().map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON: {l}: {e}"))).collect()
}

pub fn of_kind<'a>(events: &'a [Value], kind: &str) -> Vec<&'a Value> {
    events.iter().filter(|e| e["event"] == kind).collect()
}

/// Events about `file` (its `file` field).
pub fn about<'a>(events: &'a [Value], file: &str) -> Vec<&'a Value> {
    events.iter().filter(|e| e["file"] == file).collect()
}

/// Waits until `pred` holds on the events, or fails with them and the newest log.
pub fn wait_for(f: &Folders, what: &str, secs: u64, pred: impl Fn(&[Value]) -> bool) -> Vec<Value> {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let ev = events(f);
        if pred(&ev) {
            return ev;
        }
        if Instant::now() > deadline {
            let mut logs: Vec<PathBuf> = std::fs::read_dir(&f.root)
                .unwrap()
                .flatten()
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|e| e == "log"))
                .collect();
            logs.sort();
            let log = logs.last().map(|p| std::fs::read_to_string(p).unwrap_or_default()).unwrap_or_default();
            panic!("timed out waiting for {what}\nevents:\n{ev:#?}\nlog:\n{log}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Fails if a temporary file of the atomic writer is left anywhere under `dir`.
pub fn no_temporaries(dir: &Path) {
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        assert!(!name.contains("clearview-tmp"), "temporary left behind: {}", entry.path().display());
        if entry.file_type().unwrap().is_dir() {
            no_temporaries(&entry.path());
        }
    }
}

/// A response: status, content type, body.
#[derive(Debug)]
pub struct Reply {
    pub status: u16,
    pub content_type: String,
    pub body: Vec<u8>,
}

impl Reply {
    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }

    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// One request; any status comes back as a [`Reply`] (transport errors panic).
pub fn request(method: &str, url: &str, token: Option<&str>, body: Option<(&str, &[u8])>) -> Reply {
    let mut req = ureq::request(method, url).timeout(Duration::from_secs(30));
    if let Some(t) = token {
        req = req.set("Authorization", &format!("Bearer {t}"));
    }
    let r = match body {
        Some((ct, bytes)) => req.set("Content-Type", ct).send_bytes(bytes),
        None => req.call(),
    };
    let resp = match r {
        Ok(r) => r,
        Err(ureq::Error::Status(_, r)) => r,
        Err(e) => panic!("{method} {url}: {e}"),
    };
    let status = resp.status();
    let content_type = resp.header("Content-Type").unwrap_or("").to_owned();
    let mut body = Vec::new();
    resp.into_reader().take(64 << 20).read_to_end(&mut body).unwrap();
    Reply { status, content_type, body }
}

pub fn get(url: &str) -> Reply {
    request("GET", url, None, None)
}

/// A raw HTTP/1.1 request (for headers a client would not let us forge); returns the
/// status code.
pub fn raw_status(addr: &str, head: &str) -> u16 {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.write_all(head.as_bytes()).unwrap();
    let mut buf = [0u8; 64];
    let n = s.read(&mut buf).unwrap();
    let line = String::from_utf8_lossy(&buf[..n]).into_owned();
    line.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or_else(|| panic!("no status: {line}"))
}

/// Polls the session's JSON until `pred` holds, or fails with the service's log.
pub fn wait_session(s: &Service, id: &str, what: &str, secs: u64, pred: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    let url = format!("{}/api/sessions/{id}", s.base);
    loop {
        let r = get(&url);
        if r.status == 200 {
            let v = r.json();
            if pred(&v) {
                return v;
            }
            if Instant::now() > deadline {
                panic!("timed out waiting for {what}\nsession: {v:#}\nlog:\n{}", s.log());
            }
        } else if Instant::now() > deadline {
            panic!("timed out waiting for {what}: {} {}\nlog:\n{}", r.status, r.text(), s.log());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

pub fn result_number(session: &Value) -> Option<u64> {
    session["result"]["number"].as_u64()
}
