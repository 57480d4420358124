//! Throughput of the NATS scale-out against `clearview run` on the same files (issue 17):
//! views per minute from "every file is in the watched folder" to "every view is named by
//! an event and every session has its result", for `run` with 1 and 2 worker threads and
//! for ingest + N workers + collect on one local `nats-server` (JetStream, 1 replica:
//! `nats N`) or on a cluster of three local servers with every stream and bucket on three
//! replicas (`nats3 N`, as the deployment: each write is acknowledged by a quorum).
//!
//! `cargo run --release --example nats_throughput -- [SESSIONS] [VIEWS] [WIDTHxHEIGHT] [MODES]`
//! (default 8 sessions of 4 views, 640x480, modes `run 1,run 2,nats 1,nats 2,nats 4`;
//! e.g. `"run 1,nats 1,nats3 1,nats3 2"`). Needs `nats-server` (`.ci/setup`).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use clearview::geometry::Homography;
use clearview::imaging::Mask;
use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::synth::{self, Occluder};
use rand::SeedableRng;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let sessions: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(8);
    let views: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(4);
    let (w, h) = args
        .get(3)
        .and_then(|a| a.split_once('x'))
        .map(|(a, b)| (a.parse().unwrap(), b.parse().unwrap()))
        .unwrap_or((640usize, 480usize));
    let bin = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/release/clearview");
    let tmp = tempfile::tempdir().unwrap();
    let src = tmp.path().join("src");
    for s in 0..sessions {
        render_session(&src.join(format!("site{s}")), w, h, views, 900 + s as u64);
    }
    println!("{sessions} sessions x {views} views, {w}x{h}; views per minute (median of 3 runs):");
    let total = (sessions * views) as f64;
    let mut base = None;
    let modes = args.get(4).map_or("run 1,run 2,nats 1,nats 2,nats 4", String::as_str);
    for mode in modes.split(',').map(str::trim) {
        let mut times: Vec<f64> =
            (0..3).map(|i| once(&bin, tmp.path(), &src, mode, i, sessions, views)).collect();
        times.sort_by(f64::total_cmp);
        let t = times[1];
        let vpm = total / t * 60.0;
        let base = *base.get_or_insert(vpm);
        println!("  {mode:7} {vpm:7.1} views/min  ({t:.2} s; x{:.2} of run 1)", vpm / base);
    }
}

fn render_session(dir: &Path, w: usize, h: usize, views: usize, seed: u64) {
    std::fs::create_dir_all(dir).unwrap();
    let scene = synth::facade(w * 3 / 2, h * 3 / 2, seed);
    let centre = Homography::translation(w as f64 / 4.0, h as f64 / 4.0);
    let mut key = synth::render_view(&scene, &centre, w, h, [0.5; 3]);
    let mut mask = Mask::new(w, h, 0);
    let (wf, hf) = (w as f32, h as f32);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, wf * 0.5, hf * 0.53, wf * 0.27, 3);
    mask_to_luma8(&mask).save(dir.join("key.mask.png")).unwrap();
    to_rgb8(&key).save(dir.join("key.png")).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for i in 0..views {
        let k2v = synth::random_homography(&mut rng, w, h, 0.1, 0.2, (0.9, 1.1));
        let v2s = centre.after(&k2v.inverse().unwrap());
        let mut v = synth::render_view(&scene, &v2s, w, h, [0.5; 3]);
        let cx = wf * (0.15 + 0.3 * i as f32 % 0.9);
        synth::paint_occluder(&mut v, None, Occluder::Person, cx, hf * 0.57, wf * 0.1, 100 + i as u64);
        to_rgb8(&v).save(dir.join(format!("view{i}.png"))).unwrap();
    }
}

struct Kill(Vec<Child>);

impl Drop for Kill {
    fn drop(&mut self) {
        for c in self.0.iter().rev() {
            let _ = Command::new("kill").args(["-TERM", &c.id().to_string()]).status();
        }
        for c in &mut self.0 {
            let _ = c.wait();
        }
    }
}

fn spawn(bin: &Path, args: &[&str], log: &Path) -> Child {
    Command::new(bin)
        .args(args)
        // The roles say " started" once their streams and consumers are ready.
        .env("CLEARVIEW_LOG", "warn,clearview::daemon::cluster=info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap()
}

/// One timed run of `mode` ("run N": the folder service with N worker threads; "nats N":
/// ingest, N workers, collect); seconds from the copy to the last event needed.
fn once(bin: &Path, tmp: &Path, src: &Path, mode: &str, run: usize, sessions: usize, views: usize) -> f64 {
    let (kind, n) = mode.split_once(' ').unwrap();
    let root = tmp.join(format!("{kind}{n}-{run}"));
    let (inbox, out) = (root.join("inbox"), root.join("out"));
    std::fs::create_dir_all(&inbox).unwrap();
    let config = root.join("c.toml");
    let replicas = if kind == "nats3" { 3 } else { 1 };
    let held: Vec<_> =
        (0..2 * replicas).map(|_| std::net::TcpListener::bind("127.0.0.1:0").unwrap()).collect();
    let ports: Vec<u16> = held.iter().map(|l| l.local_addr().unwrap().port()).collect();
    drop(held);
    std::fs::write(
        &config,
        format!(
            "[watch]\nquiet_period_ms = 200\n[output]\ndir = {out:?}\n[state]\ndir = {:?}\n[compute]\nworkers = {n}\n\
             [nats]\nreplicas = {replicas}\n",
            root.join("state")
        ),
    )
    .unwrap();
    let c = config.to_str().unwrap();
    let url = ports[..replicas].iter().map(|p| format!("nats://127.0.0.1:{p}")).collect::<Vec<_>>().join(",");
    let mut procs = Kill(Vec::new());
    if kind == "run" {
        procs.0.push(spawn(
            bin,
            &["run", "-c", c, "--watch", inbox.to_str().unwrap()],
            &root.join("run.log"),
        ));
    } else {
        procs.0.extend(servers(&root, &ports, replicas));
        let o = out.to_str().unwrap();
        procs.0.push(spawn(
            bin,
            &["collect", "-c", c, "--nats", &url, "--out", o],
            &root.join("collect.log"),
        ));
        for i in 0..n.parse::<usize>().unwrap() {
            let scratch = root.join(format!("w{i}"));
            let args = [
                "worker",
                "-c",
                c,
                "--nats",
                &url,
                "--id",
                &format!("w{i}"),
                "--scratch",
                scratch.to_str().unwrap(),
            ];
            procs.0.push(spawn(bin, &args, &root.join(format!("w{i}.log"))));
        }
        let st = root.join("ingest");
        let args = [
            "ingest",
            "-c",
            c,
            "--nats",
            &url,
            "--watch",
            inbox.to_str().unwrap(),
            "--state",
            st.to_str().unwrap(),
        ];
        procs.0.push(spawn(bin, &args, &root.join("ingest.log")));
    }
    // Every role ready (streams made, a cluster's leaders elected).
    let ready = Instant::now() + Duration::from_secs(60);
    for log in std::fs::read_dir(&root).unwrap().flatten().map(|e| e.path()) {
        let role = kind != "run"
            && log
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.ends_with(".log") && !n.starts_with('n'));
        while role && !std::fs::read_to_string(&log).unwrap_or_default().contains(" started") {
            assert!(Instant::now() < ready, "{} did not start", log.display());
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    std::thread::sleep(Duration::from_secs(1));
    let start = Instant::now();
    // Each session moved in whole (a rename: no partial files).
    for s in 0..sessions {
        let from = src.join(format!("site{s}"));
        let staged = root.join(format!(".site{s}"));
        copy_dir(&from, &staged);
        std::fs::rename(&staged, inbox.join(format!("site{s}"))).unwrap();
    }
    let deadline = Instant::now() + Duration::from_secs(600);
    loop {
        let log = std::fs::read_to_string(out.join("events.jsonl")).unwrap_or_default();
        let named = log
            .lines()
            .filter(|l| {
                l.contains("\"event\":\"view_accepted\"") || l.contains("\"event\":\"view_rejected\"")
            })
            .count();
        let results = (0..sessions).filter(|s| out.join(format!("site{s}/result.json")).is_file()).count();
        if named >= sessions * views && results == sessions && last_fill_done(&log, sessions) {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{mode}: not done within 10 minutes ({named} views, {results} results)"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    start.elapsed().as_secs_f64()
}

/// `replicas` local JetStream servers (client ports `ports[..replicas]`, cluster routes on
/// the others when there are several), each answering.
fn servers(root: &Path, ports: &[u16], replicas: usize) -> Vec<Child> {
    let mut children = Vec::new();
    for i in 0..replicas {
        let store = root.join(format!("js{i}"));
        let mut conf = format!(
            "server_name: n{i}\nlisten: 127.0.0.1:{}\njetstream {{ store_dir: {store:?} }}\n",
            ports[i]
        );
        if replicas > 1 {
            let routes: Vec<String> = (0..replicas)
                .filter(|&j| j != i)
                .map(|j| format!("nats-route://127.0.0.1:{}", ports[replicas + j]))
                .collect();
            conf.push_str(&format!(
                "cluster {{ name: bench\n listen: 127.0.0.1:{}\n routes: [{}] }}\n",
                ports[replicas + i],
                routes.join(", ")
            ));
        }
        let path = root.join(format!("n{i}.conf"));
        std::fs::write(&path, conf).unwrap();
        let child = Command::new("nats-server")
            .args(["-c", path.to_str().unwrap()])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(root.join(format!("n{i}.log"))).unwrap())
            .spawn()
            .expect("nats-server (run .ci/setup)");
        children.push(child);
    }
    for &p in &ports[..replicas] {
        while std::net::TcpStream::connect(("127.0.0.1", p)).is_err() {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    children
}

/// Every session's last view event is followed by a result event (updated, not better or
/// unchanged): its final fill is done.
fn last_fill_done(log: &str, sessions: usize) -> bool {
    (0..sessions).all(|s| {
        let tag = format!("\"session\":\"site{s}\"");
        let mine: Vec<&str> = log.lines().filter(|l| l.contains(&tag)).collect();
        let last_view = mine.iter().rposition(|l| l.contains("\"event\":\"view_"));
        let last_fill = mine.iter().rposition(|l| l.contains("\"event\":\"result_"));
        matches!((last_view, last_fill), (Some(v), Some(f)) if f > v)
    })
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}
