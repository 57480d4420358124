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
    std::fs::read_to_string(out.join("events.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
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
