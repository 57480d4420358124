//! The decoder thread of one video source (shell layer): runs `ffmpeg`, reads raw RGB24
//! frames from its pipe, measures each ([`crate::imaging::sharpness`]), lets
//! [`KeyPick`] choose the keyframe, and queues the frames worth aligning to the session
//! thread ([`super::runner`]). Reconnects a live stream that ends or fails.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read};
use std::process::{Command, Stdio};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crossbeam_channel::{SendTimeoutError, Sender, TrySendError};
use tokio_util::sync::CancellationToken;

use super::keypick::{KeyPick, KeyStep};
use super::{ChildPid, Msg, Probe, Reaped, VideoStats, contain, probe};
use crate::config::VideoSource;
use crate::daemon::emit::Emitter;
use crate::daemon::event::{Event, StreamOpened};
use crate::imaging::sharpness::{FrameMeasure, FrameSelector, Verdict};

/// How often the decoder logs its counters.
const PROGRESS_EVERY: Duration = Duration::from_secs(5);

/// Why the decoder stops feeding frames.
pub(super) enum Stop {
    /// The session thread is gone.
    Gone,
    /// The named keyframe was refused: the session cannot start.
    Refused(String),
}

/// The decoder thread of one source.
pub(super) struct Decoder {
    pub(super) src: VideoSource,
    pub(super) out: Sender<Msg>,
    pub(super) stats: Arc<VideoStats>,
    pub(super) pid: ChildPid,
    pub(super) cancel: CancellationToken,
    pub(super) emitter: Arc<Emitter>,
    /// Frames with more pixels are not read ([`super::too_large`]).
    pub(super) max_pixels: u64,
}

impl Decoder {
    pub(super) fn run(self, mut first: Option<Probe>) {
        let session = self.src.session.as_str();
        let span = tracing::info_span!("video", session);
        let _enter = span.enter();
        let mut backoff = self.src.reconnect_min;
        let mut size: Option<(usize, usize, f64)> = None;
        let mut selector = FrameSelector::new(self.src.select.clone());
        let mut index = 0u64;
        let select = &self.src.select;
        let mut pick = KeyPick::new(self.src.keyframe, select.min_sharpness, select.warmup_frames);
        let mut held = Vec::new();
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
                    let retry_ms = backoff.as_millis() as u64;
                    let e = Event::StreamUnavailable { input: self.src.input.clone(), reason, retry_ms };
                    if !self.back_off(&e, &mut backoff) {
                        break;
                    }
                    continue;
                }
            };
            // A live stream is probed here, and may claim any size.
            if let Some(reason) = super::too_large(&p, self.max_pixels) {
                end_reason = Some(reason);
                break;
            }
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
            let opened = StreamOpened {
                input: self.src.input.clone(),
                width: w,
                height: h,
                fps,
                source_size: [p.width, p.height],
                live: self.src.live,
            };
            let e = if connections == 1 {
                Event::StreamStarted(opened)
            } else {
                Event::StreamReconnected(opened)
            };
            self.emitter.emit(Some(session), &e);
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
                match self.offer(&mut selector, &mut pick, &mut held, &mut buf, index, t, (w, h)) {
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
                    self.progress();
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
            // A file that ended before the frame it names (or with no sharp frame) has no
            // keyframe: the session ends saying so, not as if it had run.
            if !gone
                && !self.src.live
                && index > 0
                && let Some(reason) = pick.missed(index, (index - 1) as f64 / fps)
            {
                self.refuse_key(reason, &mut end_reason);
                gone = true;
            }
            // A file shorter than the warm-up: its frames are judged on the level they set.
            if !gone && !self.src.live {
                for f in std::mem::take(&mut held) {
                    if self.release(&mut selector, f, (w, h)).is_err() {
                        gone = true;
                        break;
                    }
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
            let retry_ms = backoff.as_millis() as u64;
            let e = Event::StreamLost { input: self.src.input.clone(), frames: got, reason, retry_ms };
            if !self.back_off(&e, &mut backoff) {
                break;
            }
        }
        self.drop_held(&mut held);
        self.progress();
        // A stream that is not live ends its session; on shutdown the session thread stops
        // by itself.
        if !self.cancel.is_cancelled() {
            let _ = self.out.send(Msg::End { reason: end_reason });
        }
    }

    /// Says `event` (the stream is gone for now), waits `backoff` and doubles it (up to
    /// `reconnect_max`); `false` when the service stopped meanwhile.
    fn back_off(&self, event: &Event, backoff: &mut Duration) -> bool {
        self.emitter.emit(Some(&self.src.session), event);
        if !self.sleep(*backoff) {
            return false;
        }
        *backoff = (*backoff * 2).min(self.src.reconnect_max);
        true
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

    fn progress(&self) {
        let v = self.stats.counters();
        tracing::info!(stats = %serde_json::to_string(&v).unwrap_or_default(), "video progress");
        self.emitter.emit(Some(&self.src.session), &Event::VideoProgress(v));
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
        let e = Event::KeyframeRefused { input: self.src.input.clone(), reason: reason.clone() };
        self.emitter.emit(Some(&self.src.session), &e);
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
    /// too) when the selector keeps it. Frames of the warm-up are held and judged once the
    /// level is known (they may be the only ones to see the keyframe's borders).
    #[allow(clippy::too_many_arguments)]
    fn offer(
        &self,
        selector: &mut FrameSelector,
        pick: &mut KeyPick,
        held: &mut Vec<Held>,
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
        let warm = selector.observe(t, &m);
        match step {
            KeyStep::Key { index, t, rgb } => self.send_key(index, t, (w, h), rgb)?,
            KeyStep::Refused { reason } => return Err(Stop::Refused(reason)),
            KeyStep::Wait => {}
        }
        if warm {
            for f in std::mem::take(held) {
                self.release(selector, f, (w, h))?;
            }
        }
        if !pick.decided() && !candidate {
            s.before_key.fetch_add(1, Ordering::Relaxed);
        }
        if !warm {
            // Held until the level is known: at most the warm-up's length of frames. The
            // keyframe candidate's pixels travel with the keyframe: only its place is held.
            let rgb = (!candidate).then(|| std::mem::replace(buf, vec![0u8; w * h * 3]));
            held.push(Held { index, t, measure: m, rgb });
            return Ok(());
        }
        if candidate {
            // The frames kept after it are spaced from it.
            selector.judge(t, &m, true);
            return Ok(());
        }
        if !self.judge(selector, index, t, &m) {
            return Ok(());
        }
        let rgb = std::mem::replace(buf, vec![0u8; w * h * 3]);
        self.queue(index, t, rgb, (w, h))
    }

    /// Judges a frame held through the warm-up, in its turn, and queues it when kept (the
    /// keyframe candidate only spaces the frames after it).
    fn release(&self, selector: &mut FrameSelector, f: Held, size: (usize, usize)) -> Result<(), Stop> {
        match f.rgb {
            None => {
                selector.judge(f.t, &f.measure, true);
                Ok(())
            }
            Some(rgb) if self.judge(selector, f.index, f.t, &f.measure) => {
                self.queue(f.index, f.t, rgb, size)
            }
            Some(_) => Ok(()),
        }
    }

    /// The stream ended during the warm-up: its held frames only set the level.
    fn drop_held(&self, held: &mut Vec<Held>) {
        let frames = held.iter().filter(|f| f.rgb.is_some()).count();
        self.stats.warmup.fetch_add(frames as u64, Ordering::Relaxed);
        held.clear();
    }

    /// Whether the selector keeps frame `index`; counts the verdict.
    fn judge(&self, selector: &mut FrameSelector, index: u64, t: f64, m: &FrameMeasure) -> bool {
        let verdict = selector.judge(t, m, false);
        let s = &self.stats;
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
        }
        verdict == Verdict::Keep
    }

    /// Queues a kept frame: waits for room for a file read at the service's pace, drops
    /// (and counts) it when a live stream's queue is full.
    fn queue(&self, index: u64, t: f64, rgb: Vec<u8>, (w, h): (usize, usize)) -> Result<(), Stop> {
        let s = &self.stats;
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

/// A frame of the warm-up, held until the sharpness level is known; without pixels, the
/// keyframe candidate's place.
pub(super) struct Held {
    index: u64,
    t: f64,
    measure: FrameMeasure,
    rgb: Option<Vec<u8>>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Config, VideoKeyframe};
    use crossbeam_channel::bounded;

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
            max_pixels: config.max_pixels,
        };
        let (w, h) = (32, 24);
        let mut selector = FrameSelector::new(decoder.src.select.clone());
        let mut pick = KeyPick::new(VideoKeyframe::First, 0.5, 5);
        pick.done = true;
        let mut held = Vec::new();
        let start = Instant::now();
        for i in 0..3u64 {
            let mut buf: Vec<u8> =
                (0..w * h * 3).map(|k| if (k / 3 + k / (3 * w)) % 2 == 0 { 220 } else { 30 }).collect();
            assert!(
                decoder.offer(&mut selector, &mut pick, &mut held, &mut buf, i, i as f64, (w, h)).is_ok()
            );
        }
        assert!(start.elapsed() < Duration::from_millis(100), "the decoder waited");
        assert_eq!(decoder.stats.kept.load(Ordering::Relaxed), 3);
        assert_eq!(decoder.stats.dropped.load(Ordering::Relaxed), 3);
        assert_eq!(rx.len(), 1, "nothing more was queued");
    }
}
