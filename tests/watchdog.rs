//! The service under `Type=notify` with a watchdog, without systemd: the test plays
//! systemd's part by binding `NOTIFY_SOCKET` and asking for a watchdog through
//! `WATCHDOG_USEC`, then reads what the real binary sends: READY, STATUS, WATCHDOG pings
//! for as long as it runs (watching a folder, and reading only a video), and STOPPING.

mod daemon_common;

use std::os::unix::net::UnixDatagram;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use daemon_common::*;

/// The watchdog interval asked for: pings are due every half of it.
const WATCHDOG_MS: u64 = 800;

/// systemd's end of the notification socket.
struct Notify {
    socket: UnixDatagram,
    path: std::path::PathBuf,
}

impl Notify {
    fn bind(dir: &Path) -> Self {
        let path = dir.join("notify.sock");
        let socket = UnixDatagram::bind(&path).unwrap();
        socket.set_read_timeout(Some(Duration::from_millis(100))).unwrap();
        Self { socket, path }
    }

    /// Every message received until `until`, each with when it came.
    fn read_for(&self, span: Duration) -> Vec<(Instant, String)> {
        let end = Instant::now() + span;
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        while Instant::now() < end {
            if let Ok(n) = self.socket.recv(&mut buf) {
                got.push((Instant::now(), String::from_utf8_lossy(&buf[..n]).into_owned()));
            }
        }
        got
    }

    fn command(&self, args: &[&str], log: &Path) -> Child {
        Command::new(env!("CARGO_BIN_EXE_clearview"))
            .args(args)
            .env("NOTIFY_SOCKET", &self.path)
            .env("WATCHDOG_USEC", (WATCHDOG_MS * 1000).to_string())
            .env_remove("WATCHDOG_PID")
            .env("CLEARVIEW_LOG", "clearview=debug")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap()
    }
}

/// The longest gap between watchdog pings from the first on, and how many there were.
fn pings(messages: &[(Instant, String)]) -> (usize, Duration) {
    let times: Vec<Instant> =
        messages.iter().filter(|(_, m)| m.lines().any(|l| l == "WATCHDOG=1")).map(|(t, _)| *t).collect();
    let gap = times.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(Duration::MAX);
    (times.len(), gap)
}

fn have_ffmpeg() -> bool {
    Command::new("ffmpeg").arg("-version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok()
}

#[test]
fn a_watched_folder_is_ready_pings_the_watchdog_and_says_it_is_stopping() {
    let f = folders("");
    let notify = Notify::bind(&f.root);
    let log = f.root.join("service.log");
    let mut child = notify.command(&["run", "--config", f.config.to_str().unwrap()], &log);
    let got = notify.read_for(Duration::from_millis(4 * WATCHDOG_MS));
    let text = || format!("{got:#?}\nlog:\n{}", std::fs::read_to_string(&log).unwrap_or_default());
    assert!(got.first().is_some_and(|(_, m)| m.contains("READY=1")), "READY first: {}", text());
    assert!(got.iter().any(|(_, m)| m.contains("STATUS=")), "a status line: {}", text());
    let (n, gap) = pings(&got);
    assert!(n >= 4, "{n} watchdog pings in {} ms: {}", 4 * WATCHDOG_MS, text());
    assert!(gap < Duration::from_millis(WATCHDOG_MS), "a gap of {gap:?} between pings: {}", text());
    let ok = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(ok.success());
    let status = child.wait().unwrap();
    let after = notify.read_for(Duration::from_millis(200));
    assert_eq!(status.code(), Some(0));
    assert!(after.iter().any(|(_, m)| m.contains("STOPPING=1")), "STOPPING on SIGTERM: {after:#?}");
}

#[test]
fn reading_only_a_video_still_pings_the_watchdog() {
    if !have_ffmpeg() {
        eprintln!("skipped: ffmpeg is not installed (.ci/run installs it)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let video = dir.path().join("walk.mp4");
    // Six seconds of a moving test pattern, read at its own rate: no folder is watched.
    let made = Command::new("ffmpeg")
        .args(["-v", "error", "-f", "lavfi", "-i", "testsrc2=size=320x240:rate=10", "-t", "6"])
        .args(["-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(made.success());
    let notify = Notify::bind(dir.path());
    let log = dir.path().join("service.log");
    let out = dir.path().join("out");
    let state = dir.path().join("state");
    let mut child = notify.command(
        &[
            "run",
            "--video",
            video.to_str().unwrap(),
            "--mask",
            "auto",
            "--realtime",
            "--out",
            out.to_str().unwrap(),
            "--state",
            state.to_str().unwrap(),
        ],
        &log,
    );
    let got = notify.read_for(Duration::from_millis(5 * WATCHDOG_MS));
    let text = || format!("{got:#?}\nlog:\n{}", std::fs::read_to_string(&log).unwrap_or_default());
    assert!(child.try_wait().unwrap().is_none(), "the service is still reading the video: {}", text());
    assert!(got.first().is_some_and(|(_, m)| m.contains("READY=1")), "READY first: {}", text());
    let (n, gap) = pings(&got);
    assert!(n >= 5, "{n} watchdog pings in {} ms: {}", 5 * WATCHDOG_MS, text());
    assert!(gap < Duration::from_millis(WATCHDOG_MS), "a gap of {gap:?} between pings: {}", text());
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < deadline, "the service did not end with its video: {}", text());
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(status.code(), Some(0), "{}", text());
}

/// A manager that stops reading the notification socket (its queue holds 10 datagrams on a
/// stock kernel; pings come every 400 ms here) must not stop the service: before, the send
/// waited for room, first in the watchdog's task and then in the shutdown itself, and the
/// service never ended (a CI run saw it after a video: "the service did not end with its
/// video"). Now a message that finds the queue full is dropped and SIGTERM still stops it.
#[test]
fn a_manager_that_stops_reading_does_not_hold_up_the_service() {
    let f = folders("");
    let notify = Notify::bind(&f.root);
    let log = f.root.join("service.log");
    let mut child = notify.command(&["run", "--config", f.config.to_str().unwrap()], &log);
    let got = notify.read_for(Duration::from_millis(WATCHDOG_MS));
    let text = || format!("{got:#?}\nlog:\n{}", std::fs::read_to_string(&log).unwrap_or_default());
    assert!(got.first().is_some_and(|(_, m)| m.contains("READY=1")), "READY first: {}", text());
    // Twenty pings' time, read by nobody.
    std::thread::sleep(Duration::from_millis(10 * WATCHDOG_MS));
    assert!(child.try_wait().unwrap().is_none(), "the service is still watching: {}", text());
    let ok = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(ok.success());
    let deadline = Instant::now() + Duration::from_secs(10);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            panic!("SIGTERM did not stop the service while its notifications went unread: {}", text());
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(status.code(), Some(0), "{}", text());
    let log = std::fs::read_to_string(&log).unwrap();
    assert!(log.contains("notification queue is full"), "the dropped messages are said: {log}");
}
