//! From "a path was touched" to a decoded job on a worker's queue (shell layer).
//!
//! Each candidate file is tracked by its size and modification time. It becomes *ready*
//! once they have not changed for the quiet period (measured on our clock, so a share's
//! skewed clock does not matter). Ready files are decoded (`spawn_blocking`, at most
//! `decoders` at a time) and queued to the worker that owns their session, keyframes and
//! masks before views, older before newer. A worker whose queue is full gets nothing more:
//! its files stay ready, on disk, and are queued at a later tick. A file that fails to
//! decode is reported once (event `file_skipped`) and not retried until it changes.
//! Keyframes and views must look like photographs: at least [`MIN_SIDE`] pixels a side
//! and at most [`MAX_ASPECT`]:1. A mask that a worker has taken and that is then deleted
//! is reported to that worker (a job without an image).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime};

use crossbeam_channel::{Sender, TrySendError};
use image::DynamicImage;
use tokio::sync::{Semaphore, mpsc};
use tokio_util::sync::CancellationToken;

use super::watch::{self, Role};
use super::worker::{FileId, Job};
use super::{Backlog, Stats, emit::Emitter};
use crate::config::{Config, WatchMode};
use crate::imaging::decode::{DecodeLimits, decode};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Status {
    /// Changed recently; waiting for the quiet period.
    Settling,
    /// Complete; waiting for room on its worker's queue.
    Ready,
    /// Handed to a worker (or being decoded for one).
    Queued,
    /// Failed to decode in this version.
    Failed,
}

#[derive(Debug)]
struct Tracked {
    session: String,
    role: Role,
    size: u64,
    mtime: SystemTime,
    since: Instant,
    status: Status,
}

/// The intake task's state.
pub struct Intake {
    config: Arc<Config>,
    senders: Vec<Sender<Job>>,
    backlog: Arc<Backlog>,
    emitter: Arc<Emitter>,
    stats: Arc<Stats>,
    started: Instant,
    files: HashMap<PathBuf, Tracked>,
    decoders: Arc<Semaphore>,
    /// Masks deleted after a worker took them, still to be told to it: (path, session).
    removed: Vec<(PathBuf, String)>,
}

/// Keyframes and views with a side shorter than this are refused: too few pixels for
/// corners to be found and matched.
pub const MIN_SIDE: u32 = 32;

/// Keyframes and views longer than this many times their other side are refused: strips,
/// not photographs of a facade.
pub const MAX_ASPECT: u32 = 10;

/// The worker that owns `session` (stable for the life of the process).
pub fn worker_for(session: &str, workers: usize) -> usize {
    let mut h = crate::session::Fnv::new();
    h.write(session.as_bytes());
    (h.finish() % workers as u64) as usize
}

impl Intake {
    pub fn new(
        config: Arc<Config>,
        senders: Vec<Sender<Job>>,
        backlog: Arc<Backlog>,
        emitter: Arc<Emitter>,
        stats: Arc<Stats>,
        started: Instant,
    ) -> Self {
        let decoders = Arc::new(Semaphore::new(config.decoders.get()));
        Self {
            config,
            senders,
            backlog,
            emitter,
            stats,
            started,
            files: HashMap::new(),
            decoders,
            removed: Vec::new(),
        }
    }

    pub async fn run(
        mut self,
        mut hints: mpsc::Receiver<PathBuf>,
        overflow: Arc<AtomicBool>,
        cancel: CancellationToken,
    ) {
        let scan_every = match self.config.watch_mode {
            WatchMode::Notify => self.config.rescan_interval,
            WatchMode::Poll { interval } => interval,
        };
        let mut tick = tokio::time::interval(super::tick_interval(&self.config));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut last_scan: Option<Instant> = None;
        loop {
            tokio::select! {
                () = cancel.cancelled() => break,
                Some(path) = hints.recv() => self.observe(path),
                _ = tick.tick() => {
                    self.stats.heartbeat_ms.store(super::millis_since(self.started), Ordering::Relaxed);
                    if last_scan.is_none_or(|t| t.elapsed() >= scan_every) || overflow.swap(false, Ordering::Relaxed) {
                        self.full_scan().await;
                        last_scan = Some(Instant::now());
                    }
                    self.settle();
                    self.dispatch(&cancel).await;
                }
            }
        }
        tracing::debug!("intake stopped");
    }

    async fn full_scan(&mut self) {
        let root = self.config.watch_dir.clone();
        let paths = tokio::task::spawn_blocking(move || watch::scan(&root)).await.unwrap_or_default();
        let present: std::collections::HashSet<&PathBuf> = paths.iter().collect();
        let gone: Vec<PathBuf> = self.files.keys().filter(|p| !present.contains(p)).cloned().collect();
        for p in gone {
            self.forget(&p);
        }
        for p in paths {
            self.observe(p);
        }
    }

    /// A hint that `path` may have changed.
    fn observe(&mut self, path: PathBuf) {
        if path.parent() == Some(self.config.watch_dir.as_path()) && path.is_dir() {
            // A new session folder: files can land in it before the watcher watches it.
            if let Ok(entries) = std::fs::read_dir(&path) {
                for e in entries.flatten() {
                    if e.file_type().is_ok_and(|t| t.is_file()) {
                        self.observe(e.path());
                    }
                }
            }
            return;
        }
        let Some(candidate) = watch::classify(&self.config.watch_dir, &path, &self.config.extensions) else {
            return;
        };
        let meta = match std::fs::metadata(&path) {
            Ok(m) if m.is_file() => m,
            _ => {
                self.forget(&path);
                return;
            }
        };
        let (size, mtime) = (meta.len(), meta.modified().unwrap_or(SystemTime::UNIX_EPOCH));
        match self.files.get_mut(&path) {
            Some(t) if t.size == size && t.mtime == mtime => {}
            Some(t) => {
                if t.status == Status::Ready {
                    self.backlog.done(&t.session);
                }
                (t.size, t.mtime, t.since, t.status) = (size, mtime, Instant::now(), Status::Settling);
            }
            None => {
                tracing::debug!(file = %watch::shown_path(&path), session = %candidate.session, "noticed");
                self.files.insert(
                    path,
                    Tracked {
                        session: candidate.session,
                        role: candidate.role,
                        size,
                        mtime,
                        since: Instant::now(),
                        status: Status::Settling,
                    },
                );
            }
        }
    }

    /// `path` is gone from the folder: it stops being tracked, and a mask a worker took is
    /// reported to it.
    fn forget(&mut self, path: &std::path::Path) {
        let Some(t) = self.files.remove(path) else { return };
        if t.status == Status::Ready {
            self.backlog.done(&t.session);
        }
        if t.role == Role::Mask && t.status == Status::Queued {
            self.removed.push((path.to_owned(), t.session));
        }
    }

    /// Tells workers about deleted masks while their queues have room.
    fn report_removed(&mut self) {
        let workers = self.senders.len();
        self.removed.retain(|(path, session)| {
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let file = FileId { name, size: 0, mtime: SystemTime::UNIX_EPOCH };
            let job =
                Job { session: session.clone(), path: path.clone(), role: Role::Mask, file, image: None };
            // Full: kept for the next tick. Disconnected: nobody to tell.
            matches!(self.senders[worker_for(session, workers)].try_send(job), Err(TrySendError::Full(_)))
        });
    }

    /// Re-checks settling files; those quiet for long enough become ready.
    fn settle(&mut self) {
        let quiet = self.config.quiet_period;
        let settling: Vec<PathBuf> =
            self.files.iter().filter(|(_, t)| t.status == Status::Settling).map(|(p, _)| p.clone()).collect();
        for path in settling {
            self.observe(path.clone());
            if let Some(t) = self.files.get_mut(&path)
                && t.status == Status::Settling
                && t.since.elapsed() >= quiet
            {
                t.status = Status::Ready;
                self.backlog.add(&t.session);
            }
        }
    }

    /// Decodes and queues ready files while their workers have room.
    async fn dispatch(&mut self, cancel: &CancellationToken) {
        self.report_removed();
        let workers = self.senders.len();
        let mut room: Vec<usize> =
            self.senders.iter().map(|s| s.capacity().unwrap_or(usize::MAX).saturating_sub(s.len())).collect();
        let mut ready: Vec<(&PathBuf, &Tracked)> =
            self.files.iter().filter(|(_, t)| t.status == Status::Ready).collect();
        if ready.is_empty() {
            return;
        }
        ready.sort_by(|a, b| {
            (&a.1.session, a.1.role, a.1.mtime, a.0).cmp(&(&b.1.session, b.1.role, b.1.mtime, b.0))
        });
        let mut planned = Vec::new();
        for (path, t) in ready {
            let w = worker_for(&t.session, workers);
            if room[w] == 0 {
                continue;
            }
            room[w] -= 1;
            planned.push((path.clone(), w));
        }
        let limits = DecodeLimits { max_pixels: self.config.max_pixels };
        let mut decodes = Vec::with_capacity(planned.len());
        for (path, w) in planned {
            let t = self.files.get_mut(&path).expect("planned from the map");
            t.status = Status::Queued;
            let (role, size, mtime) = (t.role, t.size, t.mtime);
            let semaphore = self.decoders.clone();
            let p = path.clone();
            let handle = tokio::spawn(async move {
                let _permit = semaphore.acquire_owned().await.expect("never closed");
                tokio::task::spawn_blocking(move || read_and_decode(&p, role, size, mtime, &limits)).await
            });
            decodes.push((path, w, handle));
        }
        for (path, w, handle) in decodes {
            let outcome = handle.await.ok().and_then(|r| r.ok());
            let t = self.files.get_mut(&path).expect("planned from the map");
            let session = t.session.clone();
            match outcome {
                Some(Ok(image)) => {
                    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                    let file = FileId { name, size: t.size, mtime: t.mtime };
                    let job = Job {
                        session: session.clone(),
                        path: path.clone(),
                        role: t.role,
                        file,
                        image: Some(image),
                    };
                    if cancel.is_cancelled() {
                        // Left on disk for the next start.
                        t.status = Status::Ready;
                        continue;
                    }
                    match self.senders[w].try_send(job) {
                        Ok(()) => {}
                        Err(TrySendError::Full(_)) => t.status = Status::Ready,
                        Err(TrySendError::Disconnected(_)) => {
                            t.status = Status::Ready;
                            tracing::error!("a worker thread has stopped: restart the service");
                        }
                    }
                }
                Some(Err(DecodeOutcome::Changed)) => {
                    // Written to while we read it: wait for it to settle again.
                    t.status = Status::Settling;
                    t.since = Instant::now();
                    self.backlog.done(&session);
                }
                Some(Err(DecodeOutcome::Failed(reason))) | Some(Err(DecodeOutcome::Io(reason))) => {
                    t.status = Status::Failed;
                    self.backlog.done(&session);
                    self.stats.skipped.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!(file = %watch::shown_path(&path), session = %session, %reason, "file skipped");
                    self.emitter.event(
                        "file_skipped",
                        Some(&session),
                        serde_json::json!({ "file": path.file_name().map(|n| n.to_string_lossy()), "path": path.to_string_lossy(), "reason": reason }),
                    );
                }
                None => {
                    // The decoder panicked on this file: never again until it changes.
                    t.status = Status::Failed;
                    self.backlog.done(&session);
                    tracing::error!(file = %watch::shown_path(&path), reason = "the decoder crashed", "file skipped");
                    self.emitter.event(
                        "file_skipped",
                        Some(&session),
                        serde_json::json!({ "file": path.file_name().map(|n| n.to_string_lossy()), "path": path.to_string_lossy(), "reason": "the decoder crashed" }),
                    );
                }
            }
        }
    }
}

/// Why a ready file did not become a job.
#[derive(Debug)]
pub enum DecodeOutcome {
    /// Its size or time changed while it was read.
    Changed,
    Io(String),
    Failed(String),
}

/// Reads and decodes a file, checking it did not change meanwhile; views and keyframes
/// come back as 8-bit RGB, masks as 8-bit grey.
pub fn read_and_decode(
    path: &std::path::Path,
    role: Role,
    size: u64,
    mtime: SystemTime,
    limits: &DecodeLimits,
) -> Result<DynamicImage, DecodeOutcome> {
    let bytes = std::fs::read(path).map_err(|e| DecodeOutcome::Io(format!("cannot read: {e}")))?;
    let meta = std::fs::metadata(path).map_err(|e| DecodeOutcome::Io(format!("cannot read: {e}")))?;
    if meta.len() != size || meta.modified().ok() != Some(mtime) || bytes.len() as u64 != size {
        return Err(DecodeOutcome::Changed);
    }
    let img = decode(&bytes, limits).map_err(|e| DecodeOutcome::Failed(e.to_string()))?;
    if role != Role::Mask
        && let Some(reason) = shape_problem(img.width(), img.height())
    {
        return Err(DecodeOutcome::Failed(reason));
    }
    Ok(match (role, img) {
        (Role::Mask, DynamicImage::ImageLuma8(g)) => DynamicImage::ImageLuma8(g),
        (Role::Mask, other) => DynamicImage::ImageLuma8(other.to_luma8()),
        (_, DynamicImage::ImageRgb8(c)) => DynamicImage::ImageRgb8(c),
        (_, other) => DynamicImage::ImageRgb8(other.to_rgb8()),
    })
}

/// Why a `width × height` image cannot be a keyframe or a view, if it cannot.
pub fn shape_problem(width: u32, height: u32) -> Option<String> {
    let (short, long) = (width.min(height), width.max(height));
    if short < MIN_SIDE {
        Some(format!("{width}x{height} is too small to align (at least {MIN_SIDE} pixels a side)"))
    } else if u64::from(long) > u64::from(short) * u64::from(MAX_ASPECT) {
        Some(format!(
            "{width}x{height} is a strip ({}:1), not a photograph of a facade (at most {MAX_ASPECT}:1)",
            long / short
        ))
    } else {
        None
    }
}

/// Time a test or a caller may wait for a file to be taken: quiet period plus two ticks.
pub fn settle_time(config: &Config) -> Duration {
    config.quiet_period + 2 * super::tick_interval(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn photographs_pass_and_dots_and_strips_do_not() {
        for (w, h) in [(400, 300), (32, 32), (320, 32), (4000, 3000), (300, 3000)] {
            assert_eq!(shape_problem(w, h), None, "{w}x{h}");
        }
        for (w, h) in [(1, 1), (31, 400), (400, 0), (20_000, 50), (33, 331)] {
            assert!(shape_problem(w, h).is_some(), "{w}x{h}");
        }
    }
}
