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
//!
//! Files: [`decoder`] (the decoder thread), [`keypick`] (the keyframe choice, pure),
//! [`runner`] (the session thread, a source of the session engine); this file starts
//! them and owns the `ffmpeg` children.

mod decoder;
mod keypick;
mod runner;

use std::io::Read;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::bounded;
use thiserror::Error;
use tokio_util::sync::CancellationToken;

use super::emit::Emitter;
use super::engine::Ctx;
use super::event::VideoCounters;
use super::registry::Registry;
use super::{Backlog, Stats};
use crate::config::{Config, VideoMask, VideoSource};
use crate::imaging::decode::{DecodeLimits, decode_mask};
use decoder::Decoder;
use runner::Runner;

/// The keyframe as chosen, beside the results.
pub const KEYFRAME_FILE: &str = "keyframe.png";

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
    #[error("{input}: {reason}")]
    TooLarge { input: String, reason: String },
    #[error("{path}: the mask is {mask_w}x{mask_h} but the video is {width}x{height}")]
    MaskSize { path: PathBuf, mask_w: usize, mask_h: usize, width: usize, height: usize },
    #[error("cannot start a video thread: {0}")]
    Thread(std::io::Error),
}

/// What ffprobe says of a stream. The size is the frame's as a player shows it, which is
/// what FFmpeg decodes to: turned upright when the stream says it was filmed on its side
/// (a phone held upright stores a 1920 × 1080 picture and a quarter turn), and with square
/// pixels when its pixels are not square. A mask is painted on that picture.
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
    /// Frames of the warm-up never judged (the stream ended during it); the others are
    /// counted by their verdict once judged.
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
    /// The counters as events write them.
    pub fn counters(&self) -> VideoCounters {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let n = g(&self.latency_n);
        VideoCounters {
            frames_read: g(&self.read),
            warmup: g(&self.warmup),
            before_key: g(&self.before_key),
            blurred: g(&self.blurred),
            still: g(&self.still),
            rate_capped: g(&self.rate_capped),
            kept: g(&self.kept),
            dropped: g(&self.dropped),
            aligned: g(&self.aligned),
            reconnects: g(&self.reconnects),
            mean_update_latency_ms: g(&self.latency_ms_sum).checked_div(n),
        }
    }
}

/// A frame handed from the decoder thread to the session thread.
pub(super) enum Msg {
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
pub(super) type ChildPid = Arc<Mutex<Option<u32>>>;

/// The video sources of a running service.
#[derive(Default)]
pub struct Videos {
    threads: Vec<JoinHandle<()>>,
    /// Each source's end: its input and, when it ended with an error, the reason.
    done: Vec<tokio::sync::oneshot::Receiver<(String, Option<String>)>>,
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
            if let Some(reason) = probe.and_then(|p| too_large(&p, config.max_pixels)) {
                return Err(VideoError::TooLarge { input: src.input.clone(), reason });
            }
            let mask = match &src.mask {
                VideoMask::File(path) => {
                    let limits = DecodeLimits { max_pixels: config.max_pixels };
                    let mask = std::fs::read(path)
                        .map_err(|e| e.to_string())
                        .and_then(|bytes| decode_mask(&bytes, &limits).map_err(|e| e.to_string()))
                        .map_err(|reason| VideoError::Mask { path: path.clone(), reason })?;
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
                max_pixels: config.max_pixels,
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
            let input = src.input.clone();
            videos.threads.push(
                std::thread::Builder::new()
                    .name(format!("clearview-video-{name}"))
                    .spawn(move || {
                        let failed = runner.run(&rx, &c);
                        let _ = done_tx.send((input, failed));
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
    /// stream only on shutdown): what went wrong with those that ended with an error, as
    /// `input: reason`.
    pub async fn finished(&mut self) -> Vec<String> {
        let mut failed = Vec::new();
        for rx in &mut self.done {
            if let Ok((input, Some(reason))) = rx.await {
                failed.push(format!("{input}: {reason}"));
            }
        }
        failed
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
pub(super) fn contain(cmd: &mut Command) {
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
pub(super) struct Reaped {
    pub(super) child: Child,
    pub(super) pid: Option<ChildPid>,
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

/// Why frames of `p`'s size are not read: more pixels than `max_pixels`
/// (`watch.max_pixels`, the limit every photograph is held to). A frame is held several
/// times over (the pipe's buffer, the kept frames, the session's crops), and a stream can
/// claim any size.
pub fn too_large(p: &Probe, max_pixels: u64) -> Option<String> {
    let pixels = p.width as u64 * p.height as u64;
    (pixels > max_pixels).then(|| {
        format!(
            "its frames are {}x{} ({:.1} MP), more than watch.max_pixels ({max_pixels})",
            p.width,
            p.height,
            pixels as f64 / 1e6
        )
    })
}

/// Asks ffprobe for the first video stream's size and rate (within 20 s).
pub fn probe(src: &VideoSource, cancel: &CancellationToken) -> Result<Probe, String> {
    let mut cmd = Command::new(&src.ffprobe);
    cmd.args(["-v", "error", "-select_streams", "v:0", "-show_entries"])
        .arg("stream=width,height,avg_frame_rate,r_frame_rate,sample_aspect_ratio:stream_tags=rotate:stream_side_data=rotation")
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
        let (n, d) = t.split_once(['/', ':']).unwrap_or((t, "1"));
        let (n, d): (f64, f64) = (n.parse().ok()?, d.parse().ok()?);
        (d > 0.0 && n > 0.0 && (n / d).is_finite()).then_some(n / d)
    };
    let fps = rate("avg_frame_rate").or_else(|| rate("r_frame_rate")).unwrap_or(25.0);
    // Pixels that are not square (`sample_aspect_ratio` 8:9, 4:3…) are shown stretched:
    // the width as shown, rounded to an even number as FFmpeg's scaler wants it. A ratio
    // beyond 1:4 or 4:1 is no camera's and is not believed (it would only blow the frame
    // up).
    let width = match rate("sample_aspect_ratio") {
        Some(sar) if (sar - 1.0).abs() > 1e-3 && (0.25..=4.0).contains(&sar) => {
            (((width as f64 * sar) / 2.0).round() as usize * 2).max(2)
        }
        _ => width,
    };
    // A quarter turn (the display matrix's `rotation`, or the older `rotate` tag) swaps the
    // sides: FFmpeg turns the frames upright as it decodes them.
    let turn = s["side_data_list"]
        .as_array()
        .into_iter()
        .flatten()
        .find_map(|d| d["rotation"].as_f64())
        .or_else(|| s["tags"]["rotate"].as_str().and_then(|t| t.trim().parse().ok()))
        .unwrap_or(0.0);
    let quarter = ((turn / 90.0).round() as i64).rem_euclid(2) == 1;
    let (width, height) = if quarter { (height, width) } else { (width, height) };
    (width > 0 && height > 0).then_some(Probe { width, height, fps })
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn frames_larger_than_a_photograph_may_be_are_not_read() {
        let p = |width, height| Probe { width, height, fps: 25.0 };
        assert_eq!(too_large(&p(4000, 3000), 12_000_000), None);
        assert_eq!(
            too_large(&p(4000, 3001), 12_000_000).as_deref(),
            Some("its frames are 4000x3001 (12.0 MP), more than watch.max_pixels (12000000)")
        );
    }

    #[test]
    fn a_stream_filmed_on_its_side_or_with_wide_pixels_is_sized_as_it_is_shown() {
        // FFmpeg 5's display matrix, either way round, and the older tag.
        for turned in [
            r#"{"streams":[{"width":1920,"height":1080,"r_frame_rate":"30/1","side_data_list":[{"rotation":-90}]}]}"#,
            r#"{"streams":[{"width":1920,"height":1080,"r_frame_rate":"30/1","side_data_list":[{"rotation":90}]}]}"#,
            r#"{"streams":[{"width":1920,"height":1080,"r_frame_rate":"30/1","tags":{"rotate":"270"}}]}"#,
        ] {
            let p = parse_probe(turned).unwrap();
            assert_eq!((p.width, p.height), (1080, 1920), "{turned}");
        }
        // Upside down keeps its sides.
        let p = parse_probe(
            r#"{"streams":[{"width":1920,"height":1080,"r_frame_rate":"30/1","side_data_list":[{"rotation":180}]}]}"#,
        )
        .unwrap();
        assert_eq!((p.width, p.height), (1920, 1080));
        // DV's 720 × 480 with 8:9 pixels is shown 640 wide; square pixels change nothing.
        let p = parse_probe(
            r#"{"streams":[{"width":720,"height":480,"r_frame_rate":"30000/1001","sample_aspect_ratio":"8:9"}]}"#,
        )
        .unwrap();
        assert_eq!((p.width, p.height), (640, 480));
        for plain in ["1:1", "0:1", "1000:1"] {
            let p = parse_probe(&format!(
                r#"{{"streams":[{{"width":640,"height":480,"r_frame_rate":"25/1","sample_aspect_ratio":"{plain}"}}]}}"#
            ))
            .unwrap();
            assert_eq!((p.width, p.height), (640, 480), "{plain}");
        }
    }
}
