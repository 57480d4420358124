//! Helpers of the tests that run the NATS JetStream roles (`clearview ingest`, `worker`,
//! `collect`) against real `nats-server`s: child processes killed when dropped, free
//! ports, the collected event log.

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use serde_json::Value;

/// A child process killed when dropped (a failing test leaves nothing running).
pub struct Proc {
    pub name: String,
    pub child: Child,
    /// Its standard error (the log); its standard output goes to `<name>.stdout` beside it.
    pub log: PathBuf,
}

impl Proc {
    pub fn start(name: &str, program: &Path, args: &[&str], dir: &Path) -> Self {
        let log = dir.join(format!("{name}.log"));
        let child = Command::new(program)
            .args(args)
            .env("CLEARVIEW_LOG", "clearview=debug,async_nats=warn")
            .stdout(std::fs::File::create(dir.join(format!("{name}.stdout"))).unwrap())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap_or_else(|e| panic!("{name}: cannot start {}: {e}", program.display()));
        Self { name: name.to_owned(), child, log }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill").args([sig, &self.child.id().to_string()]).status().unwrap();
        assert!(ok.success(), "kill {sig} {}", self.name);
    }

    /// SIGTERM, then the exit code (within 30 s).
    pub fn terminate(mut self) -> Option<i32> {
        self.signal("-TERM");
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status.code();
            }
            assert!(
                Instant::now() < deadline,
                "{} did not stop within 30 s of SIGTERM:\n{}",
                self.name,
                self.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Fails the test (with its log) if the process has ended.
    pub fn check_alive(&mut self) {
        if let Some(status) = self.child.try_wait().unwrap() {
            panic!("{} ended ({status}) during the run:\n{}", self.name, self.log());
        }
    }

    /// SIGKILL, and reaped.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn nats_server() -> PathBuf {
    let on_path = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .map(|d| d.join("nats-server"))
        .chain([PathBuf::from("/usr/sbin/nats-server"), PathBuf::from("/usr/bin/nats-server")])
        .find(|p| p.is_file());
    on_path.unwrap_or_else(|| {
        panic!("nats-server is not installed: run .ci/setup (it installs Debian's nats-server package)")
    })
}

pub fn free_ports(n: usize) -> Vec<u16> {
    let held: Vec<TcpListener> = (0..n).map(|_| TcpListener::bind("127.0.0.1:0").unwrap()).collect();
    held.iter().map(|l| l.local_addr().unwrap().port()).collect()
}

pub fn wait_port(port: u16, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "nats-server on port {port} did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Reads `events.jsonl` (lines may be added while it is read: only whole ones count).
pub fn events(out: &Path) -> Vec<Value> {
    super::whole_lines(&out.join("events.jsonl"))
}

/// One JetStream `nats-server` on the loopback, its store under `dir`: the process and its
/// URL.
pub fn single_server(dir: &Path) -> (Proc, String, u16) {
    let port = free_ports(1)[0];
    let (port_s, store) = (port.to_string(), dir.join("store"));
    let server = Proc::start(
        "nats",
        &nats_server(),
        &["-a", "127.0.0.1", "-p", &port_s, "-js", "-sd", store.to_str().unwrap()],
        dir,
    );
    wait_port(port, 20);
    (server, format!("nats://127.0.0.1:{port}"), port)
}

/// `DIR/clearview.toml` for the roles: a 300 ms quiet period, the state in `DIR/state`,
/// then `more` (the `[nats]` table and any other); its path as a string.
pub fn write_config(dir: &Path, more: &str) -> String {
    let path = dir.join("clearview.toml");
    let state = dir.join("state");
    std::fs::write(&path, format!("[watch]\nquiet_period_ms = 300\n[state]\ndir = {state:?}\n{more}"))
        .unwrap();
    path.to_str().unwrap().to_owned()
}

/// `clearview collect` with config `config` into `out`, its logs in `dir`.
pub fn start_collect(config: &str, urls: &str, out: &Path, dir: &Path) -> Proc {
    let args = ["collect", "-c", config, "--nats", urls, "--out", out.to_str().unwrap()];
    Proc::start("collect", Path::new(super::bin()), &args, dir)
}

/// `clearview worker` `id` with config `config`, its scratch folder and logs in `dir`.
pub fn start_worker(config: &str, urls: &str, id: &str, dir: &Path) -> Proc {
    let scratch = dir.join(format!("scratch-{id}"));
    let args = ["worker", "-c", config, "--nats", urls, "--id", id, "--scratch", scratch.to_str().unwrap()];
    Proc::start(id, Path::new(super::bin()), &args, dir)
}

/// Waits up to `secs` for `done`; fails with `what` and the logs of `logs`.
pub fn wait_until(what: &str, secs: u64, logs: &[&Proc], mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while !done() {
        if Instant::now() >= deadline {
            let said: Vec<String> = logs.iter().map(|p| format!("{}:\n{}", p.name, p.log())).collect();
            panic!("{what} within {secs} s\n{}", said.join("\n"));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Waits until every role has said it started (streams and buckets made, consumers ready).
pub fn wait_started(roles: &[&Proc], secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    for p in roles {
        while !p.log().contains(" started") {
            assert!(Instant::now() < deadline, "{} did not start:\n{}", p.name, p.log());
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

/// `clearview ingest` with config `config`, watching `inbox`, its state in `state`, its
/// logs in `dir`.
pub fn start_ingest(config: &str, urls: &str, inbox: &Path, state: &Path, dir: &Path) -> Proc {
    Proc::start(
        "ingest",
        Path::new(super::bin()),
        &[
            "ingest",
            "-c",
            config,
            "--nats",
            urls,
            "--watch",
            inbox.to_str().unwrap(),
            "--state",
            state.to_str().unwrap(),
        ],
        dir,
    )
}

/// A TCP relay between clients and a `nats-server` that stalls a connection the way a
/// congested or partitioned link does: once [`Stall::arm`]ed, the first client-to-server
/// chunk that contains `needle` is held back (and every byte after it, both ways) for
/// `hold`, then all of it goes through, late. Clients' requests meanwhile time out; no
/// byte is lost.
pub struct Stall {
    pub port: u16,
    /// How many times the link stalled (it stalls once).
    pub stalled: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    armed: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl Stall {
    pub fn start(server_port: u16, needle: &'static [u8], hold: Duration) -> Self {
        use std::sync::Arc;
        use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let stalled = Arc::new(AtomicUsize::new(0));
        // Until when the link is held, as milliseconds since `epoch` (0: not held).
        let epoch = Instant::now();
        let until = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let armed = Arc::new(AtomicBool::new(false));
        let (count, arm) = (stalled.clone(), armed.clone());
        std::thread::spawn(move || {
            for client in listener.incoming() {
                let Ok(client) = client else { return };
                let Ok(server) = std::net::TcpStream::connect(("127.0.0.1", server_port)) else { return };
                let pump = |from: std::net::TcpStream, to: std::net::TcpStream, watch: bool| {
                    let (until, armed, count) = (until.clone(), armed.clone(), count.clone());
                    move || {
                        use std::io::{Read, Write};
                        let (mut from, mut to) = (from, to);
                        let mut buf = vec![0u8; 64 * 1024];
                        loop {
                            let n = match from.read(&mut buf) {
                                Ok(0) | Err(_) => break,
                                Ok(n) => n,
                            };
                            let chunk = &buf[..n];
                            if watch
                                && chunk.windows(needle.len()).any(|w| w == needle)
                                && armed.swap(false, Ordering::SeqCst)
                            {
                                let end = epoch.elapsed() + hold;
                                until.store(end.as_millis() as u64, Ordering::SeqCst);
                                count.fetch_add(1, Ordering::SeqCst);
                            }
                            loop {
                                let held = until.load(Ordering::SeqCst);
                                let now = epoch.elapsed().as_millis() as u64;
                                if now >= held {
                                    break;
                                }
                                std::thread::sleep(Duration::from_millis((held - now).min(50)));
                            }
                            if to.write_all(chunk).is_err() {
                                break;
                            }
                        }
                        let _ = to.shutdown(std::net::Shutdown::Both);
                    }
                };
                let (c2, s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
                std::thread::spawn(pump(client, server, true));
                std::thread::spawn(pump(s2, c2, false));
            }
        });
        Self { port, stalled, armed: arm }
    }

    /// From now on, the next chunk with the needle stalls the link.
    pub fn arm(&self) {
        self.armed.store(true, std::sync::atomic::Ordering::SeqCst);
    }
}
