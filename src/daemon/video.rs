//! Video stream input (shell layer): for each `[[video]]` source, an `ffmpeg` child that
//! decodes to raw RGB24 on a pipe, a decoder thread that measures every frame and keeps
//! the few worth aligning ([`crate::imaging::sharpness`]), and a session thread that
//! aligns each kept frame (chained from the previous one), admits and fills it as the
//! photo workers do, and writes to the same outputs (`<out>/<session>/result.<ext>`,
//! `history/`, `result.json`, `events.jsonl`).
//!
//! ```text
//!  ffmpeg ─► pipe (rgb24) ─► decoder thread ─► bounded queue ─► session thread ─► emit
//!  (child)                   measure, select    full: drop and   align (prior: last kept
//!                            keyframe choice    count, never     frame), admit, fill
//!                            reconnect          wait (live)
//! ```
//!
//! - The decoder thread never stops reading the pipe for a live stream (or a file read in
//!   real time): when the queue is full the frame is dropped and counted. A file read as
//!   fast as it is processed waits on the queue instead (nothing is lost, ffmpeg waits).
//! - A live stream that ends or fails is reconnected after a wait that doubles from
//!   `reconnect_min` to `reconnect_max`; the session (keyframe, mask, buffer, result) is
//!   kept. The end of a file ends the session with a final fill.
//! - The child is in its own process group, dies with its parent thread
//!   (`PR_SET_PDEATHSIG`, Linux), is killed on shutdown and always reaped.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use crossbeam_channel::{Receiver, RecvTimeoutError, SendTimeoutError, Sender, TrySendError, bounded};
use image::{DynamicImage, RgbImage};
use serde_json::json;
use thiserror::Error;
use tokio_util::sync::CancellationToken;

use super::emit::Emitter;
use super::registry::Registry;
use super::worker::{self, Ctx, MAX_LISTED, Slot, ViewEntry};
use super::{Backlog, Stats, state};
use crate::config::{Config, VideoKeyframe, VideoMask, VideoSource};
use crate::geometry::Homography;
use crate::imaging::convert::{to_luminance, to_mask, to_rgb};
use crate::imaging::sharpness::{FrameMeasure, FrameSelector, Verdict};
use crate::imaging::{Mask, RgbF32};
use crate::session::{Admission, AlignRecord, Rgb8};

/// Why a video source could not start. Problems after the start are events.
#[derive(Debug, Error)]
pub enum VideoError {
    #[error(
        "{program}: cannot run it ({reason}); install FFmpeg (apt-get install ffmpeg) or set video.{key}"
    )]
    Missing { program: PathBuf, key: &'static str, reason: String },
    #[error("{input}: ffprobe cannot read a video stream: {reason}")]
    Probe { input: String, reason: String },
    #[error("{path}: cannot read the mask: {reason}")]
    Mask { path: PathBuf, reason: String },
    #[error("{path}: the mask is {mask_w}x{mask_h} but the video is {width}x{height}")]
    MaskSize { path: PathBuf, mask_w: usize, mask_h: usize, width: usize, height: usize },
    #[error("cannot start a video thread: {0}")]
    Thread(std::io::Error),
}

/// What ffprobe says of a stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Probe {
    pub width: usize,
    pub height: usize,
    /// Frames per second (25 when the header does not say).
    pub fps: f64,
}

/// Counters of one source, shared by its threads and reported in events.
#[derive(Debug, Default)]
pub struct VideoStats {
    pub read: AtomicU64,
    pub warmup: AtomicU64,
    pub before_key: AtomicU64,
    pub blurred: AtomicU64,
    pub still: AtomicU64,
    pub rate_capped: AtomicU64,
    pub kept: AtomicU64,
    /// Kept frames dropped because the queue was full (the service was behind).
    pub dropped: AtomicU64,
    pub aligned: AtomicU64,
    pub reconnects: AtomicU64,
    /// Sum and count of the time from a frame's arrival to the end of the fill it caused.
    pub latency_ms_sum: AtomicU64,
    pub latency_n: AtomicU64,
}

impl VideoStats {
    fn json(&self) -> serde_json::Value {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let n = g(&self.latency_n);
        json!({
            "frames_read": g(&self.read),
            "warmup": g(&self.warmup),
            "before_key": g(&self.before_key),
            "blurred": g(&self.blurred),
            "still": g(&self.still),
            "rate_capped": g(&self.rate_capped),
            "kept": g(&self.kept),
            "dropped": g(&self.dropped),
            "aligned": g(&self.aligned),
            "reconnects": g(&self.reconnects),
            "mean_update_latency_ms": g(&self.latency_ms_sum).checked_div(n),
        })
    }
}

/// A frame handed from the decoder thread to the session thread.
enum Msg {
    Frame {
        index: u64,
        /// Stream time, seconds.
        t: f64,
        key: bool,
        width: usize,
        height: usize,
        rgb: Vec<u8>,
        arrived: Instant,
    },
    /// The file ended (or could not be read again): final fill, then stop.
    End { reason: Option<String> },
}

/// The process id of the running ffmpeg child, to kill it from another thread.
type ChildPid = Arc<Mutex<Option<u32>>>;

/// The video sources of a running service.
#[derive(Default)]
pub struct Videos {
    threads: Vec<JoinHandle<()>>,
    done: Vec<tokio::sync::oneshot::Receiver<()>>,
    children: Vec<ChildPid>,
}

impl Videos {
    /// Checks FFmpeg, the masks and (for files) the streams, then starts every source.
    pub fn start(
        config: &Arc<Config>,
        emitter: &Arc<Emitter>,
        stats: &Arc<Stats>,
        registry: &Arc<Registry>,
        cancel: &CancellationToken,
    ) -> Result<Self, VideoError> {
        let mut videos = Self::default();
        for src in &config.videos {
            check_program(&src.ffmpeg, "ffmpeg")?;
            check_program(&src.ffprobe, "ffprobe")?;
            let probe = if src.live {
                None
            } else {
                Some(
                    probe(src, cancel)
                        .map_err(|reason| VideoError::Probe { input: src.input.clone(), reason })?,
                )
            };
            let mask = match &src.mask {
                VideoMask::File(path) => {
                    let img = image::open(path)
                        .map_err(|e| VideoError::Mask { path: path.clone(), reason: e.to_string() })?;
                    let mask = to_mask(&img);
                    if let Some(p) = probe
                        && (mask.width(), mask.height()) != (p.width, p.height)
                    {
                        return Err(VideoError::MaskSize {
                            path: path.clone(),
                            mask_w: mask.width(),
                            mask_h: mask.height(),
                            width: p.width,
                            height: p.height,
                        });
                    }
                    Some(mask)
                }
                VideoMask::Auto { .. } => None,
            };
            let (tx, rx) = bounded(src.queue.get());
            let vstats = Arc::new(VideoStats::default());
            let pid: ChildPid = Arc::default();
            let (done_tx, done_rx) = tokio::sync::oneshot::channel();
            let decoder = Decoder {
                src: src.clone(),
                out: tx,
                stats: vstats.clone(),
                pid: pid.clone(),
                cancel: cancel.clone(),
                emitter: emitter.clone(),
            };
            let ctx = Ctx {
                config: config.clone(),
                cancel: cancel.clone(),
                emitter: emitter.clone(),
                backlog: Arc::new(Backlog::default()),
                stats: stats.clone(),
                registry: registry.clone(),
            };
            let runner = Runner::new(ctx, src.clone(), vstats, mask);
            let name = &src.session;
            let c = cancel.clone();
            videos.threads.push(
                std::thread::Builder::new()
                    .name(format!("clearview-video-{name}"))
                    .spawn(move || {
                        runner.run(&rx, &c);
                        let _ = done_tx.send(());
                    })
                    .map_err(VideoError::Thread)?,
            );
            videos.threads.push(
                std::thread::Builder::new()
                    .name(format!("clearview-decode-{name}"))
                    .spawn(move || decoder.run(probe))
                    .map_err(VideoError::Thread)?,
            );
            videos.done.push(done_rx);
            videos.children.push(pid);
        }
        Ok(videos)
    }

    pub fn is_empty(&self) -> bool {
        self.threads.is_empty()
    }

    /// Completes when every source's session has ended (files at their end; a live
    /// stream only on shutdown).
    pub async fn finished(&mut self) {
        for rx in &mut self.done {
            let _ = rx.await;
        }
    }

    /// Kills the ffmpeg children (their threads then see the pipe close and reap them).
    pub fn kill_children(&self) {
        for pid in &self.children {
            if let Some(p) = *pid.lock().expect("child pid lock") {
                kill_group(p);
            }
        }
    }

    /// Waits for the threads (blocking).
    pub fn join(self) {
        for t in self.threads {
            let _ = t.join();
        }
    }
}

fn kill_group(pid: u32) {
    #[cfg(unix)]
    // SAFETY: kill(2) has no memory effects; the group is the child's own (process_group(0)),
    // and the pid is only set while the child is not yet reaped, so it cannot be reused.
    unsafe {
        libc::kill(-(pid as i32), libc::SIGKILL);
    }
    #[cfg(not(unix))]
    let _ = pid;
}

fn check_program(program: &PathBuf, key: &'static str) -> Result<(), VideoError> {
    match Command::new(program).arg("-version").stdout(Stdio::null()).stderr(Stdio::null()).status() {
        Ok(s) if s.success() => Ok(()),
        Ok(s) => Err(VideoError::Missing { program: program.clone(), key, reason: format!("-version: {s}") }),
        Err(e) => Err(VideoError::Missing { program: program.clone(), key, reason: e.to_string() }),
    }
}

/// Gives a command its own process group and, on Linux, SIGKILL when the spawning thread
/// dies: the child never outlives the service.
fn contain(cmd: &mut Command) {
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt;
        cmd.process_group(0);
        #[cfg(target_os = "linux")]
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
    }
}

/// A child that is killed and reaped when dropped.
struct Reaped {
    child: Child,
    pid: Option<ChildPid>,
}

impl Drop for Reaped {
    fn drop(&mut self) {
        if let Some(pid) = &self.pid {
            // Cleared before the reap, so nobody signals a reused pid.
            *pid.lock().expect("child pid lock") = None;
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Asks ffprobe for the first video stream's size and rate (within 20 s).
pub fn probe(src: &VideoSource, cancel: &CancellationToken) -> Result<Probe, String> {
    let mut cmd = Command::new(&src.ffprobe);
    cmd.args(["-v", "error", "-select_streams", "v:0", "-show_entries"])
        .arg("stream=width,height,avg_frame_rate,r_frame_rate")
        .args(["-of", "json"])
        .arg(&src.input)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    contain(&mut cmd);
    let child = cmd.spawn().map_err(|e| format!("cannot run {}: {e}", src.ffprobe.display()))?;
    let mut child = Reaped { child, pid: None };
    let (mut out, mut err) = (child.child.stdout.take(), child.child.stderr.take());
    let reader = std::thread::spawn(move || {
        let (mut o, mut e) = (String::new(), String::new());
        if let Some(s) = out.as_mut() {
            let _ = s.read_to_string(&mut o);
        }
        if let Some(s) = err.as_mut() {
            let _ = s.read_to_string(&mut e);
        }
        (o, e)
    });
    let deadline = Instant::now() + Duration::from_secs(20);
    let status = loop {
        match child.child.try_wait() {
            Ok(Some(s)) => break s,
            Ok(None) if cancel.is_cancelled() => return Err("shutting down".into()),
            Ok(None) if Instant::now() > deadline => {
                let _ = child.child.kill();
                return Err("no answer within 20 s".into());
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => return Err(e.to_string()),
        }
    };
    let (stdout, stderr) = reader.join().unwrap_or_default();
    if !status.success() {
        return Err(last_line(&stderr).unwrap_or_else(|| status.to_string()));
    }
    parse_probe(&stdout).ok_or_else(|| "no video stream".to_owned())
}

fn last_line(text: &str) -> Option<String> {
    text.lines().rev().map(str::trim).find(|l| !l.is_empty()).map(str::to_owned)
}

fn parse_probe(json: &str) -> Option<Probe> {
    let v: serde_json::Value = serde_json::from_str(json).ok()?;
    let s = v["streams"].as_array()?.first()?;
    let width = s["width"].as_u64()? as usize;
    let height = s["height"].as_u64()? as usize;
    let rate = |k: &str| {
        let t = s[k].as_str()?;
        let (n, d) = t.split_once('/').unwrap_or((t, "1"));
        let (n, d): (f64, f64) = (n.parse().ok()?, d.parse().ok()?);
        (d > 0.0 && n > 0.0 && (n / d).is_finite()).then_some(n / d)
    };
    let fps = rate("avg_frame_rate").or_else(|| rate("r_frame_rate")).unwrap_or(25.0);
    (width > 0 && height > 0).then_some(Probe { width, height, fps })
}

/// Which frame becomes the keyframe, judged with a look at the frames around it (pure
/// policy, tested without a stream).
///
/// The frame the user names (`keyframe_frame` N, or the first frame at or after
/// `keyframe_at_s`) is the keyframe, exactly: the mask was painted on it. It is judged
/// sharp against its neighbours (up to `window` frames before and after it): blurred when
/// its Laplacian variance is below `min_sharpness` times theirs at best. A blurred named
/// frame is refused with a reason, never replaced by another. Without a name, the
/// keyframe is the first frame unless it is blurred, then the next sharp one.
#[derive(Debug, Clone)]
struct KeyPick {
    rule: VideoKeyframe,
    min_sharpness: f32,
    window: usize,
    /// Sharpness of the last `window` frames read.
    recent: VecDeque<f32>,
    pending: Option<PendingKey>,
    done: bool,
}

/// A candidate keyframe waiting for its neighbours after it.
#[derive(Debug, Clone)]
struct PendingKey {
    index: u64,
    t: f64,
    rgb: Vec<u8>,
    sharpness: f32,
    /// The sharpest neighbour so far.
    best_neighbour: f32,
    after: usize,
}

/// What the chooser made of a frame.
#[derive(Debug, Clone, PartialEq)]
enum KeyStep {
    /// Nothing decided (the frame is an ordinary one).
    Wait,
    /// The frame at `index` is the keyframe.
    Key { index: u64, t: f64, rgb: Vec<u8> },
    /// The named frame is blurred: the session cannot start.
    Refused { reason: String },
}

impl KeyPick {
    fn new(rule: VideoKeyframe, min_sharpness: f32, window: usize) -> Self {
        Self { rule, min_sharpness, window, recent: VecDeque::new(), pending: None, done: false }
    }

    /// Whether the keyframe is decided (accepted; a refusal ends the stream).
    fn decided(&self) -> bool {
        self.done
    }

    /// Whether a frame is waiting to be judged as the keyframe.
    fn pending(&self) -> bool {
        self.pending.is_some()
    }

    fn is_candidate(&self, index: u64, t: f64) -> bool {
        !self.done
            && self.pending.is_none()
            && match self.rule {
                VideoKeyframe::First => true,
                VideoKeyframe::AtFrame(n) => index == n,
                VideoKeyframe::AtSeconds(at) => t + 1e-9 >= at,
            }
    }

    /// Offers the frame at `index` (its pixels and sharpness).
    fn offer(&mut self, index: u64, t: f64, rgb: &[u8], sharpness: f32) -> KeyStep {
        if self.done {
            return KeyStep::Wait;
        }
        let mut step = KeyStep::Wait;
        if let Some(p) = &mut self.pending {
            p.best_neighbour = p.best_neighbour.max(sharpness);
            p.after += 1;
            if p.after >= self.window {
                step = self.judge();
            }
        } else if self.is_candidate(index, t) {
            let best_before = self.recent.iter().copied().fold(0.0f32, f32::max);
            self.pending = Some(PendingKey {
                index,
                t,
                rgb: rgb.to_vec(),
                sharpness,
                best_neighbour: best_before,
                after: 0,
            });
            if self.window == 0 {
                step = self.judge();
            }
        }
        if self.recent.len() == self.window.max(1) {
            self.recent.pop_front();
        }
        self.recent.push_back(sharpness);
        step
    }

    /// The stream ended: judge a waiting candidate on the neighbours it had.
    fn finish(&mut self) -> KeyStep {
        if self.pending.is_some() { self.judge() } else { KeyStep::Wait }
    }

    fn judge(&mut self) -> KeyStep {
        let p = self.pending.take().expect("a pending keyframe");
        let share = if p.best_neighbour > 0.0 { p.sharpness / p.best_neighbour } else { 1.0 };
        if share >= self.min_sharpness {
            self.done = true;
            return KeyStep::Key { index: p.index, t: p.t, rgb: p.rgb };
        }
        let named = match self.rule {
            VideoKeyframe::First => None,
            VideoKeyframe::AtFrame(n) => Some(format!("frame {n} (keyframe_frame)")),
            VideoKeyframe::AtSeconds(at) => {
                Some(format!("frame {} at {:.3} s (keyframe_at_s = {at})", p.index, p.t))
            }
        };
        match named {
            Some(which) => {
                self.done = true;
                KeyStep::Refused {
                    reason: format!(
                        "{which} is blurred ({:.0} % of the sharpness of the frames around it, {:.0} % needed): \
                         name a sharp frame and paint the mask on that one",
                        100.0 * share,
                        100.0 * self.min_sharpness
                    ),
                }
            }
            // The first frame was blurred: the next frame is the next candidate.
            None => KeyStep::Wait,
        }
    }
}

/// Why the decoder stops feeding frames.
enum Stop {
    /// The session thread is gone.
    Gone,
    /// The named keyframe was refused: the session cannot start.
    Refused(String),
}

/// The decoder thread of one source.
struct Decoder {
    src: VideoSource,
    out: Sender<Msg>,
    stats: Arc<VideoStats>,
    pid: ChildPid,
    cancel: CancellationToken,
    emitter: Arc<Emitter>,
}

/// Kept frames from before the keyframe that wait for it (the latest ones).
const PRE_KEY_FRAMES: usize = 8;

/// The keyframe as chosen, beside the results.
pub const KEYFRAME_FILE: &str = "keyframe.png";

/// Frames buffered without calling for a fill after which a video refills anyway.
const REFILL_AFTER: usize = 4;

/// How often the decoder logs its counters.
const PROGRESS_EVERY: Duration = Duration::from_secs(5);

impl Decoder {
    fn run(self, mut first: Option<Probe>) {
        let session = self.src.session.as_str();
        let span = tracing::info_span!("video", session);
        let _enter = span.enter();
        let mut backoff = self.src.reconnect_min;
        let mut size: Option<(usize, usize, f64)> = None;
        let mut selector = FrameSelector::new(self.src.select.clone());
        let mut index = 0u64;
        let select = &self.src.select;
        let mut pick = KeyPick::new(self.src.keyframe, select.min_sharpness, select.warmup_frames);
        let started = Instant::now();
        let mut last_progress = Instant::now();
        let mut connections = 0u64;
        let mut end_reason = None;
        loop {
            if self.cancel.is_cancelled() {
                break;
            }
            let p = match first.take().map_or_else(|| probe(&self.src, &self.cancel), Ok) {
                Ok(p) => p,
                Err(reason) if !self.src.live => {
                    end_reason = Some(reason);
                    break;
                }
                Err(reason) => {
                    tracing::warn!(%reason, wait_ms = backoff.as_millis() as u64, "stream unavailable");
                    self.emitter.event(
                        "stream_unavailable",
                        Some(session),
                        json!({ "input": self.src.input, "reason": reason, "retry_ms": backoff.as_millis() as u64 }),
                    );
                    if !self.sleep(backoff) {
                        break;
                    }
                    backoff = (backoff * 2).min(self.src.reconnect_max);
                    continue;
                }
            };
            let (w, h, fps) = *size.get_or_insert((p.width, p.height, p.fps));
            let mut child = match self.spawn_ffmpeg(w, h) {
                Ok(c) => c,
                Err(e) => {
                    end_reason = Some(e);
                    break;
                }
            };
            connections += 1;
            let kind = if connections == 1 { "stream_started" } else { "stream_reconnected" };
            tracing::info!(input = %self.src.input, width = w, height = h, fps, "{kind}");
            self.emitter.event(
                kind,
                Some(session),
                json!({ "input": self.src.input, "width": w, "height": h, "fps": fps,
                        "source_size": [p.width, p.height], "live": self.src.live }),
            );
            let tail = Arc::new(Mutex::new(VecDeque::new()));
            let stderr_thread = child.child.stderr.take().map(|e| {
                let tail = tail.clone();
                std::thread::spawn(move || {
                    for line in BufReader::new(e).lines().map_while(Result::ok) {
                        tracing::debug!(ffmpeg = %line);
                        let mut t = tail.lock().expect("stderr tail lock");
                        if t.len() == 4 {
                            t.pop_front();
                        }
                        t.push_back(line);
                    }
                })
            });
            let mut pipe = child.child.stdout.take().expect("stdout is piped");
            let frame_len = w * h * 3;
            let mut buf = vec![0u8; frame_len];
            let mut got = 0u64;
            let mut gone = false;
            while pipe.read_exact(&mut buf).is_ok() {
                got += 1;
                let t = if self.src.live { started.elapsed().as_secs_f64() } else { index as f64 / fps };
                match self.offer(&mut selector, &mut pick, &mut buf, index, t, (w, h)) {
                    Ok(()) => {}
                    Err(stop) => {
                        if let Stop::Refused(reason) = stop {
                            self.refuse_key(reason, &mut end_reason);
                        }
                        gone = true;
                        break;
                    }
                }
                index += 1;
                if last_progress.elapsed() >= PROGRESS_EVERY {
                    last_progress = Instant::now();
                    self.progress("video_progress");
                }
            }
            // The stream ended with the keyframe still waiting for neighbours after it.
            if !gone && pick.pending() {
                match pick.finish() {
                    KeyStep::Key { index, t, rgb } => gone |= self.send_key(index, t, (w, h), rgb).is_err(),
                    KeyStep::Refused { reason } => {
                        self.refuse_key(reason, &mut end_reason);
                        gone = true;
                    }
                    KeyStep::Wait => {}
                }
            }
            drop(pipe);
            drop(child);
            if let Some(t) = stderr_thread {
                let _ = t.join();
            }
            if gone || self.cancel.is_cancelled() {
                break;
            }
            let reason = tail.lock().expect("stderr tail lock").back().cloned();
            if !self.src.live {
                if got == 0 {
                    end_reason = Some(reason.unwrap_or_else(|| "no frame decoded".into()));
                }
                break;
            }
            if got > 0 {
                backoff = self.src.reconnect_min;
            }
            self.stats.reconnects.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                frames = got,
                reason = reason.as_deref().unwrap_or("end of stream"),
                wait_ms = backoff.as_millis() as u64,
                "stream lost: reconnecting"
            );
            self.emitter.event(
                "stream_lost",
                Some(session),
                json!({ "input": self.src.input, "frames": got, "reason": reason, "retry_ms": backoff.as_millis() as u64 }),
            );
            if !self.sleep(backoff) {
                break;
            }
            backoff = (backoff * 2).min(self.src.reconnect_max);
        }
        self.progress("video_progress");
        // A stream that is not live ends its session; on shutdown the session thread stops
        // by itself.
        if !self.cancel.is_cancelled() {
            let _ = self.out.send(Msg::End { reason: end_reason });
        }
    }

    /// Sleeps for `d` unless the service stops first (then `false`).
    fn sleep(&self, d: Duration) -> bool {
        let until = Instant::now() + d;
        while Instant::now() < until {
            if self.cancel.is_cancelled() {
                return false;
            }
            std::thread::sleep((until - Instant::now()).min(Duration::from_millis(50)));
        }
        !self.cancel.is_cancelled()
    }

    fn progress(&self, kind: &str) {
        let v = self.stats.json();
        tracing::info!(stats = %v, "video progress");
        self.emitter.event(kind, Some(&self.src.session), v);
    }

    fn spawn_ffmpeg(&self, w: usize, h: usize) -> Result<Reaped, String> {
        let mut cmd = Command::new(&self.src.ffmpeg);
        cmd.args(["-nostdin", "-hide_banner", "-loglevel", "error"]);
        if self.src.realtime && !self.src.live {
            cmd.arg("-re");
        }
        cmd.arg("-i")
            .arg(&self.src.input)
            .args(["-map", "0:v:0", "-an", "-sn", "-s"])
            .arg(format!("{w}x{h}"))
            .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        contain(&mut cmd);
        // The lock is held across the spawn so a shutdown cannot miss the new child.
        let mut pid = self.pid.lock().expect("child pid lock");
        if self.cancel.is_cancelled() {
            return Err("shutting down".into());
        }
        let child = cmd.spawn().map_err(|e| format!("cannot run {}: {e}", self.src.ffmpeg.display()))?;
        *pid = Some(child.id());
        Ok(Reaped { child, pid: Some(self.pid.clone()) })
    }

    /// The keyframe was refused: says so (event and log) and ends the session with it.
    fn refuse_key(&self, reason: String, end_reason: &mut Option<String>) {
        tracing::error!(%reason, "keyframe refused");
        self.emitter.event(
            "keyframe_refused",
            Some(&self.src.session),
            json!({ "input": self.src.input, "reason": reason }),
        );
        *end_reason = Some(reason);
    }

    /// Queues the keyframe, waiting for room.
    fn send_key(&self, index: u64, t: f64, (w, h): (usize, usize), rgb: Vec<u8>) -> Result<(), Stop> {
        self.stats.kept.fetch_add(1, Ordering::Relaxed);
        let msg = Msg::Frame { index, t, key: true, width: w, height: h, rgb, arrived: Instant::now() };
        self.send_waiting(msg)
    }

    fn send_waiting(&self, mut msg: Msg) -> Result<(), Stop> {
        loop {
            match self.out.send_timeout(msg, Duration::from_millis(100)) {
                Ok(()) => return Ok(()),
                Err(SendTimeoutError::Timeout(m)) if !self.cancel.is_cancelled() => msg = m,
                Err(_) => return Err(Stop::Gone),
            }
        }
    }

    /// Judges one frame and queues it when kept: the keyframe once it is judged sharp
    /// against the frames around it ([`KeyPick`]), any other frame (before the keyframe
    /// too) when the selector keeps it.
    fn offer(
        &self,
        selector: &mut FrameSelector,
        pick: &mut KeyPick,
        buf: &mut Vec<u8>,
        index: u64,
        t: f64,
        (w, h): (usize, usize),
    ) -> Result<(), Stop> {
        let s = &self.stats;
        s.read.fetch_add(1, Ordering::Relaxed);
        let m = FrameMeasure::of_rgb24(buf, w, h, selector.params().thumb_width);
        let candidate = pick.is_candidate(index, t);
        let step = pick.offer(index, t, buf, m.sharpness);
        let verdict = selector.offer(t, &m, candidate);
        match step {
            KeyStep::Key { index, t, rgb } => self.send_key(index, t, (w, h), rgb)?,
            KeyStep::Refused { reason } => return Err(Stop::Refused(reason)),
            KeyStep::Wait => {}
        }
        if candidate {
            // Its pixels travel with the keyframe once it is judged.
            return Ok(());
        }
        if !pick.decided() {
            s.before_key.fetch_add(1, Ordering::Relaxed);
        }
        let counter = match verdict {
            Verdict::Keep => &s.kept,
            Verdict::Warmup => &s.warmup,
            Verdict::Blurred => &s.blurred,
            Verdict::Still => &s.still,
            Verdict::RateCapped => &s.rate_capped,
        };
        counter.fetch_add(1, Ordering::Relaxed);
        if verdict != Verdict::Keep {
            tracing::trace!(
                index,
                sharpness = m.sharpness,
                level = selector.level(),
                verdict = verdict.name(),
                "frame skipped"
            );
            return Ok(());
        }
        let rgb = std::mem::replace(buf, vec![0u8; w * h * 3]);
        let msg = Msg::Frame { index, t, key: false, width: w, height: h, rgb, arrived: Instant::now() };
        if !self.src.realtime {
            // A file read at the service's pace: wait for room.
            return self.send_waiting(msg);
        }
        match self.out.try_send(msg) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(_)) => {
                let n = s.dropped.fetch_add(1, Ordering::Relaxed) + 1;
                if n == 1 || n.is_multiple_of(50) {
                    tracing::warn!(
                        index,
                        dropped = n,
                        "the service is behind the stream: kept frame dropped"
                    );
                }
                Ok(())
            }
            Err(TrySendError::Disconnected(_)) => Err(Stop::Gone),
        }
    }
}

/// The session thread of one source.
struct Runner {
    ctx: Ctx,
    src: VideoSource,
    stats: Arc<VideoStats>,
    slot: Slot,
    mask: Option<Mask>,
    /// Stream times and homographies of the last two accepted frames: the next frame's
    /// prior is their motion carried on ([`predict`]), or the last one's alone.
    track: VecDeque<(f64, Homography)>,
    /// Accepted frames waiting for the automatic mask.
    stash: Vec<(String, String, AlignRecord, Rgb8)>,
    /// Kept frames that arrived before the keyframe (at most [`PRE_KEY_FRAMES`], the
    /// latest): aligned once it is set, since they saw what the keyframe's occluders hide.
    pre_key: VecDeque<(u64, f64, DynamicImage, Instant)>,
    /// Frames buffered since the last fill (improving or not).
    buffered_since_fill: usize,
    /// Arrival time of the oldest frame admitted since the last fill.
    pending_since: Option<Instant>,
    run_id: u128,
}

impl Runner {
    fn new(ctx: Ctx, src: VideoSource, stats: Arc<VideoStats>, mask: Option<Mask>) -> Self {
        let slot = Slot::new(&ctx, &src.session, PathBuf::new());
        let run_id = SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        Self {
            ctx,
            src,
            stats,
            slot,
            mask,
            track: VecDeque::new(),
            stash: Vec::new(),
            pre_key: VecDeque::new(),
            buffered_since_fill: 0,
            pending_since: None,
            run_id,
        }
    }

    fn run(mut self, rx: &Receiver<Msg>, cancel: &CancellationToken) {
        let span = tracing::info_span!("session", session = %self.src.session);
        let _enter = span.enter();
        let heart = self.ctx.stats.heartbeats.register(format!("video {}", self.src.session));
        loop {
            heart.beat();
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(Msg::Frame { index, t, key, width, height, rgb, arrived }) => {
                    if cancel.is_cancelled() {
                        break;
                    }
                    let Some(image) = RgbImage::from_raw(width as u32, height as u32, rgb) else { continue };
                    let image = DynamicImage::ImageRgb8(image);
                    if key {
                        self.take_key(index, t, &image);
                        self.take_pre_key();
                    } else if self.slot.session.key_id().is_none() {
                        if self.pre_key.len() == PRE_KEY_FRAMES {
                            self.pre_key.pop_front();
                        }
                        self.pre_key.push_back((index, t, image, arrived));
                        continue;
                    } else {
                        self.take_frame(index, t, &image, arrived);
                    }
                    let batch = self.ctx.config.batch_max.get();
                    // A file read at the service's pace fills after every frame that calls
                    // for it (results follow the camera); a stream fills when it has caught
                    // up, or after `batch_max` frames.
                    if !self.src.realtime || rx.is_empty() || self.slot.session.admitted_since_fill() >= batch
                    {
                        self.fill();
                    }
                }
                Ok(Msg::End { reason }) => {
                    // The final result: with every witness buffered since the last fill.
                    if self.buffered_since_fill > 0 {
                        self.slot.session.request_fill();
                    }
                    self.fill();
                    let mut fields = self.stats.json();
                    fields["input"] = json!(self.src.input);
                    fields["reason"] = json!(reason);
                    fields["results"] = json!(self.slot.state.last_number);
                    match &reason {
                        Some(r) => tracing::error!(reason = %r, "video ended with an error"),
                        None => tracing::info!("video ended"),
                    }
                    self.ctx.emitter.event("video_ended", Some(&self.src.session), fields);
                    break;
                }
                Err(RecvTimeoutError::Timeout) => {
                    if cancel.is_cancelled() {
                        break;
                    }
                    self.fill();
                }
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        if self.slot.state_dirty {
            state::save(&self.ctx.config.state_dir, &self.slot.name, &self.slot.state);
        }
    }

    /// Writes the keyframe beside the results (`keyframe.png`), so that a mask can be
    /// painted on exactly that frame.
    fn write_keyframe(&self, image: &DynamicImage) {
        let dir = self.ctx.config.out_dir.join(&self.slot.name);
        let mut png = Vec::new();
        let written = std::fs::create_dir_all(&dir)
            .and_then(|()| {
                image
                    .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                    .map_err(std::io::Error::other)
            })
            .and_then(|()| super::emit::atomic_write(&dir.join(KEYFRAME_FILE), &png));
        if let Err(e) = written {
            tracing::error!(error = %e, dir = %dir.display(), "cannot write {KEYFRAME_FILE}");
        }
    }

    fn frame_name(index: u64) -> String {
        format!("frame-{index:06}")
    }

    fn take_key(&mut self, index: u64, t: f64, image: &DynamicImage) {
        let name = Self::frame_name(index);
        let id = format!("{name}|{}", self.run_id);
        let first = self.slot.session.key_id().is_none();
        self.slot.session.set_key(id, to_rgb(image));
        self.slot.key_path = Some(PathBuf::from(&name));
        self.slot.mask_source = None;
        for v in self.slot.views.values_mut() {
            v.status = "superseded";
        }
        self.track.clear();
        self.track.push_back((t, Homography::identity()));
        let (w, h) = (image.width(), image.height());
        tracing::info!(key = %name, t, width = w, height = h, "keyframe set");
        self.write_keyframe(image);
        self.ctx.emitter.event(
            if first { "session_started" } else { "keyframe_changed" },
            Some(&self.slot.name),
            json!({ "keyframe": name, "frame": index, "t": t, "width": w, "height": h, "input": self.src.input }),
        );
        if let Some(mask) = self.mask.clone() {
            let masked = mask.hole_count();
            match self.slot.session.set_mask(format!("file|{}", self.run_id), mask) {
                Ok(_) => {
                    let file = match &self.src.mask {
                        VideoMask::File(p) => p.display().to_string(),
                        VideoMask::Auto { .. } => String::new(),
                    };
                    self.slot.mask_source = Some(format!("file:{file}"));
                    self.ctx.emitter.event(
                        "mask_set",
                        Some(&self.slot.name),
                        json!({ "mask": file, "source": "file", "masked": masked }),
                    );
                }
                Err(e) => {
                    tracing::error!(error = %e, "the mask does not fit the video");
                    self.ctx.emitter.event(
                        "mask_rejected",
                        Some(&self.slot.name),
                        json!({ "reason": e.to_string() }),
                    );
                }
            }
        }
    }

    /// Aligns the frames kept before the keyframe, nearest first (each one's homography
    /// is the next one's prior), then restarts the track from the keyframe.
    fn take_pre_key(&mut self) {
        let Some(&(t_key, _)) = self.track.back() else { return };
        while let Some((index, t, image, arrived)) = self.pre_key.pop_back() {
            self.take_frame(index, t, &image, arrived);
        }
        self.track.clear();
        self.track.push_back((t_key, Homography::identity()));
    }

    fn take_frame(&mut self, index: u64, t: f64, image: &DynamicImage, arrived: Instant) {
        if self.slot.session.key_id().is_none() {
            return;
        }
        let name = Self::frame_name(index);
        let id = format!("{name}|{}", self.run_id);
        let start = Instant::now();
        let prior = predict(&self.track, t);
        let record = match self.slot.session.align_with_prior(to_luminance(image), prior) {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!(frame = index, error = %e, "frame skipped");
                return;
            }
        };
        let align_ms = start.elapsed().as_secs_f64() * 1e3;
        self.stats.aligned.fetch_add(1, Ordering::Relaxed);
        if record.accepted
            && let Some(h) = record.homography()
        {
            if self.track.len() == 2 {
                self.track.pop_front();
            }
            self.track.push_back((t, h));
        }
        let common = json!({
            "file": name,
            "frame": index,
            "t": (t * 1000.0).round() / 1000.0,
            "from_prior": record.from_prior,
            "inliers": record.inliers,
            "matches": record.matches,
            "median_residual_px": record.median_residual_px,
            "homography": record.homography,
            "align_ms": (align_ms * 10.0).round() / 10.0,
        });
        if self.slot.session.mask_id().is_none()
            && let VideoMask::Auto { views } = self.src.mask
        {
            if !record.accepted {
                self.admit(&name, id, record, None, common);
                return;
            }
            self.stash.push((name, id, record, rgb8(image)));
            if self.stash.len() >= views {
                self.auto_mask();
            }
            return;
        }
        let pixels = record.accepted.then(|| rgb8(image));
        let before = self.slot.session.inputs_digest();
        if self.admit(&name, id, record, pixels.as_ref(), common) {
            self.pending_since.get_or_insert(arrived);
        }
        if self.slot.session.inputs_digest() != before {
            self.buffered_since_fill += 1;
            // Frames that see only well-witnessed pixels do not call for a fill by the
            // improvement rule, but a few of them can outvote views that saw the
            // occluder there: refill after REFILL_AFTER of them.
            if self.buffered_since_fill >= REFILL_AFTER {
                self.slot.session.request_fill();
                self.pending_since.get_or_insert(arrived);
            }
        }
    }

    /// The automatic mask from the stashed frames, then their admission with pixels.
    fn auto_mask(&mut self) {
        let views: Vec<(RgbF32, Homography)> =
            self.stash.iter().filter_map(|(_, _, r, px)| Some((rgb8_to_f32(px), r.homography()?))).collect();
        let mask = match self.slot.session.auto_mask(&views) {
            Ok(m) => m,
            Err(e) => {
                tracing::warn!(error = %e, "automatic mask failed; trying with later frames");
                self.stash.remove(0);
                return;
            }
        };
        drop(views);
        let masked = mask.hole_count();
        let id = format!("auto|{}", self.stash.iter().map(|s| s.0.as_str()).collect::<Vec<_>>().join("|"));
        if self.slot.session.set_mask(id, mask).is_err() {
            return;
        }
        self.slot.mask_source = Some("auto".into());
        tracing::info!(masked, views = self.stash.len(), "automatic mask set");
        self.ctx.emitter.event(
            "mask_set",
            Some(&self.slot.name),
            json!({ "source": "auto", "masked": masked, "views": self.stash.len() }),
        );
        for (name, id, record, px) in std::mem::take(&mut self.stash) {
            let common = json!({ "file": name, "inliers": record.inliers, "homography": record.homography });
            if self.admit(&name, id, record, Some(&px), common) {
                self.pending_since.get_or_insert_with(Instant::now);
            }
        }
    }

    /// Offers an aligned frame to the session and reports it; `true` when it calls for a
    /// fill.
    fn admit(
        &mut self,
        name: &str,
        id: String,
        record: AlignRecord,
        pixels: Option<&Rgb8>,
        common: serde_json::Value,
    ) -> bool {
        let slot = &mut self.slot;
        let admission = match slot.session.admit(id.clone(), record.clone(), pixels) {
            Ok(a) => a,
            Err(e) => {
                tracing::warn!(frame = name, error = %e, "frame skipped");
                return false;
            }
        };
        self.ctx.stats.views.fetch_add(1, Ordering::Relaxed);
        slot.seq += 1;
        let mut fields = common.as_object().cloned().unwrap_or_default();
        let mut entry = ViewEntry {
            id,
            status: "buffered",
            reason: None,
            record: Some(record),
            from_state: false,
            seq: slot.seq,
        };
        let mut improves = false;
        match &admission {
            Admission::Rejected { reason } => {
                entry.status = "rejected";
                entry.reason = Some(reason.clone());
                tracing::info!(frame = name, %reason, "frame rejected");
                fields.insert("reason".into(), reason.clone().into());
                self.ctx.emitter.event("view_rejected", Some(&slot.name), fields.into());
            }
            Admission::OutsideMask => {
                entry.status = "outside_mask";
                entry.reason = Some("sees none of the mask".into());
                fields.insert("buffered".into(), false.into());
                self.ctx.emitter.event("view_accepted", Some(&slot.name), fields.into());
            }
            Admission::Accepted { improves: i, fallback_px, weak_px, doubtful_px, dropped } => {
                improves = *i;
                tracing::debug!(frame = name, improves, "frame accepted");
                fields.insert("buffered".into(), true.into());
                fields.insert("improves".into(), (*i).into());
                fields.insert("fallback_px".into(), (*fallback_px).into());
                fields.insert("weakly_witnessed_px".into(), (*weak_px).into());
                fields.insert("doubtful_px".into(), (*doubtful_px).into());
                self.ctx.emitter.event("view_accepted", Some(&slot.name), fields.into());
                for d in dropped {
                    if let Some(v) = slot.views.values_mut().find(|v| &v.id == d) {
                        v.status = "dropped";
                        v.reason = Some("contributed least when the buffer was full".into());
                    }
                }
            }
        }
        slot.views.insert(name.to_owned(), entry);
        if slot.views.len() > MAX_LISTED
            && let Some(oldest) = slot.views.iter().min_by_key(|(_, v)| v.seq).map(|(k, _)| k.clone())
        {
            slot.views.remove(&oldest);
        }
        improves
    }

    fn fill(&mut self) {
        worker::retry_pending(&self.ctx, &mut self.slot);
        if !self.slot.session.needs_fill() {
            worker::save_state(&self.ctx, &mut self.slot);
            return;
        }
        let before = self.slot.state.last_number;
        self.buffered_since_fill = 0;
        worker::fill(&self.ctx, &mut self.slot);
        if let Some(since) = self.pending_since.take()
            && self.slot.state.last_number > before
        {
            self.stats.latency_ms_sum.fetch_add(since.elapsed().as_millis() as u64, Ordering::Relaxed);
            self.stats.latency_n.fetch_add(1, Ordering::Relaxed);
        }
        worker::save_state(&self.ctx, &mut self.slot);
    }
}

/// The prior for a frame at time `t` from the last accepted frames: the latest
/// homography, carried on at the speed of the last two (entries extrapolated linearly in
/// time, at most three intervals ahead). A camera panning steadily is predicted to within
/// a few pixels, so guided matching finds it without descriptors.
fn predict(track: &VecDeque<(f64, Homography)>, t: f64) -> Option<Homography> {
    let (t2, h2) = *track.back()?;
    let Some(&(t1, h1)) = track.len().checked_sub(2).and_then(|i| track.get(i)) else { return Some(h2) };
    if t2 - t1 <= 1e-6 {
        return Some(h2);
    }
    let r = ((t - t2) / (t2 - t1)).clamp(0.0, 3.0);
    let (a, b) = (normalised(&h1), normalised(&h2));
    let mut rows = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            rows[i][j] = b[i][j] + (b[i][j] - a[i][j]) * r;
        }
    }
    Homography::from_rows(rows).or(Some(h2))
}

fn normalised(h: &Homography) -> [[f64; 3]; 3] {
    let r = h.rows();
    let s = if r[2][2].abs() > 1e-12 { 1.0 / r[2][2] } else { 1.0 };
    r.map(|row| row.map(|v| v * s))
}

fn rgb8(image: &DynamicImage) -> Rgb8 {
    let rgb = image.to_rgb8();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    Rgb8::from_vec(w, h, rgb.as_raw().chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect())
}

fn rgb8_to_f32(px: &Rgb8) -> RgbF32 {
    px.map(|p| p.map(|v| v as f32 / 255.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_steady_pan_is_predicted() {
        let mut track = VecDeque::new();
        assert!(predict(&track, 1.0).is_none());
        track.push_back((0.0, Homography::translation(-10.0, 0.0)));
        let h = predict(&track, 1.0).unwrap();
        assert!((h.rows()[0][2] + 10.0).abs() < 1e-9, "one frame: its homography");
        track.push_back((0.5, Homography::translation(-30.0, 2.0)));
        let h = predict(&track, 1.0).unwrap().rows();
        assert!((h[0][2] + 50.0).abs() < 1e-9 && (h[1][2] - 4.0).abs() < 1e-9, "{h:?}");
        // Far ahead: at most three intervals.
        let h = predict(&track, 10.0).unwrap().rows();
        assert!((h[0][2] + 90.0).abs() < 1e-9, "{h:?}");
    }

    #[test]
    fn a_live_stream_never_waits_for_a_full_queue_it_drops_and_counts() {
        let tmp = tempfile::tempdir().unwrap();
        let config = Config { out_dir: tmp.path().to_owned(), ..Config::default() };
        let raw = crate::config::RawVideo {
            input: "rtsp://127.0.0.1/x".into(),
            warmup_frames: 0,
            min_motion: 0.0,
            max_kept_fps: 0.0,
            ..Default::default()
        };
        let (tx, rx) = bounded(1);
        tx.send(Msg::End { reason: None }).unwrap();
        let decoder = Decoder {
            src: raw.validate().unwrap(),
            out: tx,
            stats: Arc::default(),
            pid: Arc::default(),
            cancel: CancellationToken::new(),
            emitter: Arc::new(Emitter::open(&config).unwrap()),
        };
        let (w, h) = (32, 24);
        let mut selector = FrameSelector::new(decoder.src.select.clone());
        let mut pick = KeyPick { done: true, ..KeyPick::new(VideoKeyframe::First, 0.5, 5) };
        let start = Instant::now();
        for i in 0..3u64 {
            let mut buf: Vec<u8> =
                (0..w * h * 3).map(|k| if (k / 3 + k / (3 * w)) % 2 == 0 { 220 } else { 30 }).collect();
            assert!(decoder.offer(&mut selector, &mut pick, &mut buf, i, i as f64, (w, h)).is_ok());
        }
        assert!(start.elapsed() < Duration::from_millis(100), "the decoder waited");
        assert_eq!(decoder.stats.kept.load(Ordering::Relaxed), 3);
        assert_eq!(decoder.stats.dropped.load(Ordering::Relaxed), 3);
        assert_eq!(rx.len(), 1, "nothing more was queued");
    }

    /// Feeds sharpness values to a chooser; the frame's pixels are its index.
    fn pick_over(rule: VideoKeyframe, sharpness: &[f32]) -> Vec<(u64, KeyStep)> {
        let mut pick = KeyPick::new(rule, 0.5, 3);
        let mut out = Vec::new();
        for (i, &s) in sharpness.iter().enumerate() {
            let step = pick.offer(i as u64, i as f64 / 10.0, &[i as u8], s);
            if step != KeyStep::Wait {
                out.push((i as u64, step));
            }
        }
        let step = pick.finish();
        if step != KeyStep::Wait {
            out.push((sharpness.len() as u64, step));
        }
        out
    }

    fn key_index(steps: &[(u64, KeyStep)]) -> Option<u64> {
        steps.iter().find_map(|(_, s)| match s {
            KeyStep::Key { index, .. } => Some(*index),
            _ => None,
        })
    }

    #[test]
    fn the_named_frame_is_the_keyframe_exactly_even_at_the_start() {
        let sharp = [10.0; 40];
        // Frame 0 without a name, frame 0 and frame 30 by number, 30 by time: exactly those.
        assert_eq!(key_index(&pick_over(VideoKeyframe::First, &sharp)), Some(0));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(0), &sharp)), Some(0));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(30), &sharp)), Some(30));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtSeconds(3.0), &sharp)), Some(30));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtSeconds(2.95), &sharp)), Some(30));
        // The last frame is judged on the neighbours it has when the stream ends.
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(39), &sharp)), Some(39));
        // A frame past the end is never the keyframe.
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(40), &sharp)), None);
    }

    #[test]
    fn a_blurred_named_frame_is_refused_and_a_blurred_first_frame_skipped() {
        let mut s = [10.0f32; 40];
        s[0] = 2.0;
        s[30] = 3.0;
        let steps = pick_over(VideoKeyframe::AtFrame(30), &s);
        assert!(
            matches!(&steps[..], [(_, KeyStep::Refused { reason })] if reason.contains("frame 30") && reason.contains("blurred")),
            "{steps:?}"
        );
        assert!(matches!(&pick_over(VideoKeyframe::AtSeconds(3.0), &s)[..], [(_, KeyStep::Refused { .. })]));
        // Without a name the blurred first frame gives way to the next sharp one.
        let first = key_index(&pick_over(VideoKeyframe::First, &s)).unwrap();
        assert!(first > 0 && first < 10, "{first}");
        // Sharp enough against its neighbours (a uniformly soft video): accepted.
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(5), &[2.0; 10])), Some(5));
    }

    #[test]
    fn probe_output_is_parsed() {
        let p = parse_probe(
            r#"{"streams":[{"width":480,"height":360,"r_frame_rate":"30/1","avg_frame_rate":"30000/1001"}]}"#,
        )
        .unwrap();
        assert_eq!((p.width, p.height), (480, 360));
        assert!((p.fps - 29.97).abs() < 0.01);
        let p = parse_probe(
            r#"{"streams":[{"width":320,"height":240,"r_frame_rate":"25/1","avg_frame_rate":"0/0"}]}"#,
        )
        .unwrap();
        assert_eq!(p.fps, 25.0);
        assert!(parse_probe(r#"{"streams":[]}"#).is_none());
        assert!(parse_probe("not json").is_none());
    }
}
