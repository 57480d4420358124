//! The capture service (shell layer, async): owns all I/O and time around the pure
//! [`crate::session`] core.
//!
//! ```text
//!  notify / polling ─► hints ─► intake ─────────────► worker threads ──► emit
//!  (watch)            (bounded) quiet period,   (one bounded       Session per      results, history,
//!  start-up scan                decode in       crossbeam queue    session: align,  result.json,
//!                               spawn_blocking  per worker)        admit, fill      events.jsonl, state
//! ```
//!
//! - [`watch`]: which files are candidates (names, extensions, sessions), the notify
//!   watcher and the full scan.
//! - [`intake`]: a file is taken when its size and modification time have stood still for
//!   the quiet period; it is decoded in `spawn_blocking` behind a semaphore and queued to
//!   the worker that owns its session. **A full queue leaves the file pending on disk**: it
//!   stays "ready" and is queued as soon as the worker has room, so memory is bounded by
//!   `workers × queue` decoded images and nothing is dropped.
//! - [`worker`]: a fixed set of threads; sessions are spread over them by name, so a
//!   session's files are handled in arrival order by one thread (no locks). Views that
//!   arrive while more of the same session are waiting are aligned one by one and filled
//!   together (batching), at most `batch_max` at a time.
//! - [`emit`]: atomic files (temporary name in the same folder, fsync, rename) and the
//!   event log. A worker writes its own results: writing is part of the step, so a
//!   SIGTERM lets it finish, and no queue of full-size images builds up between a fast
//!   fill and a slow disk. [`state`]: what a restart needs. [`systemd`]: readiness, status, watchdog.
//!
//! Shutdown: the shutdown future (SIGTERM/SIGINT) cancels a token; the intake stops
//! queueing, each worker finishes the step in hand (an alignment or a fill with its
//! files) and exits; jobs still queued are left to the next start (their files are on
//! disk). The whole is bounded by the grace period.

pub mod cluster;
pub mod emit;
pub(crate) mod engine;
pub mod event;
pub(crate) mod folder;
pub mod http;
pub mod intake;
pub mod job;
pub mod paths;
pub mod policy;
pub mod provenance;
pub mod registry;
pub mod state;
pub mod systemd;
pub mod video;
pub mod watch;
pub mod worker;

use std::collections::HashMap;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use thiserror::Error;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::config::Config;

/// Why the service could not run. Per-file problems are never here: they are events.
#[derive(Debug, Error)]
pub enum DaemonError {
    #[error("{path}: cannot create folder: {source}")]
    CreateDir { path: PathBuf, source: std::io::Error },
    #[error("{path}: cannot open the event log: {source}")]
    EventLog { path: PathBuf, source: std::io::Error },
    #[error("{path}: cannot watch: {source}")]
    Watch { path: PathBuf, source: notify::Error },
    #[error("cannot start a worker thread: {0}")]
    Thread(std::io::Error),
    #[error("{addr}: cannot listen for HTTP: {source}")]
    Http { addr: std::net::SocketAddr, source: std::io::Error },
    #[error(transparent)]
    Video(#[from] video::VideoError),
    /// A run with videos and no watched folder, whose videos ended, one or more of them
    /// with an error (a keyframe refused, a file that could not be decoded): `input:
    /// reason` for each, also in their `video_ended` events.
    #[error("{}", .0.join("; "))]
    VideosFailed(Vec<String>),
}

/// Files of each session that the intake has noticed (still being written, complete, or
/// queued) but no worker has handled yet. A session's fill waits while it has some (they
/// are filled together, up to `session.batch_max` views).
#[derive(Debug, Default)]
pub struct Backlog(Mutex<HashMap<String, usize>>);

impl Backlog {
    pub fn add(&self, session: &str) {
        *self.0.lock().expect("backlog lock").entry(session.to_owned()).or_default() += 1;
    }

    pub fn done(&self, session: &str) {
        let mut map = self.0.lock().expect("backlog lock");
        if let Some(n) = map.get_mut(session) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                map.remove(session);
            }
        }
    }

    pub fn get(&self, session: &str) -> usize {
        self.0.lock().expect("backlog lock").get(session).copied().unwrap_or(0)
    }

    /// Files waiting over all sessions.
    pub fn total(&self) -> usize {
        self.0.lock().expect("backlog lock").values().sum()
    }
}

/// Counters for the systemd status line, and the heartbeats the watchdog vouches for.
#[derive(Debug, Default)]
pub struct Stats {
    pub views: AtomicU64,
    pub results: AtomicU64,
    pub skipped: AtomicU64,
    pub heartbeats: Arc<Heartbeats>,
}

/// The loops whose liveness the systemd watchdog vouches for: the intake and each video
/// source's runner. Each beats as it turns; systemd is pinged only while every loop still
/// registered has beaten within the watchdog's interval, so a stuck loop gets the service
/// restarted, whether it watches a folder, reads a video, or both.
#[derive(Debug)]
pub struct Heartbeats {
    epoch: std::time::Instant,
    next_id: AtomicU64,
    loops: Mutex<Vec<(u64, String, Arc<AtomicU64>)>>,
}

impl Default for Heartbeats {
    fn default() -> Self {
        Self { epoch: std::time::Instant::now(), next_id: AtomicU64::new(0), loops: Mutex::default() }
    }
}

impl Heartbeats {
    /// A loop named `name` starts: it counts as having just beaten, until its [`Beat`] is dropped.
    pub fn register(self: &Arc<Self>, name: impl Into<String>) -> Beat {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let last = Arc::new(AtomicU64::new(millis_since(self.epoch)));
        self.loops.lock().expect("heartbeats lock").push((id, name.into(), last.clone()));
        Beat { owner: self.clone(), id, last }
    }

    /// The registered loop that has gone longest without beating, and for how long.
    pub fn stalest(&self) -> Option<(String, Duration)> {
        let now = millis_since(self.epoch);
        let loops = self.loops.lock().expect("heartbeats lock");
        loops
            .iter()
            .map(|(_, name, last)| (name, now.saturating_sub(load(last))))
            .max_by_key(|&(_, age)| age)
            .map(|(name, age)| (name.clone(), Duration::from_millis(age)))
    }
}

/// One loop's heartbeat; unregistered when dropped (a video that ended is not stuck).
#[derive(Debug)]
pub struct Beat {
    owner: Arc<Heartbeats>,
    id: u64,
    last: Arc<AtomicU64>,
}

impl Beat {
    pub fn beat(&self) {
        self.last.store(millis_since(self.owner.epoch), Ordering::Relaxed);
    }
}

impl Drop for Beat {
    fn drop(&mut self) {
        self.owner.loops.lock().expect("heartbeats lock").retain(|(id, ..)| *id != self.id);
    }
}

/// Runs the service on `config` until `shutdown` completes, then stops cleanly within the
/// grace period. Creates the folders it needs.
pub async fn run(mut config: Config, shutdown: impl Future<Output = ()>) -> Result<(), DaemonError> {
    let watching = config.watch_enabled;
    for (i, dir) in
        [&mut config.watch_dir, &mut config.out_dir, &mut config.state_dir].into_iter().enumerate()
    {
        if i == 0 && !watching {
            // Video only: no folder is watched, none is created.
            continue;
        }
        create_dir(dir)?;
        // Absolute from here on: notifications, scans and logs all name files the same way.
        if let Ok(abs) = std::fs::canonicalize(&*dir) {
            *dir = abs;
        }
    }
    create_dir(&state::sessions_dir(&config.state_dir))?;
    emit::remove_stale_temporaries(&config.out_dir);
    emit::remove_stale_temporaries(&state::sessions_dir(&config.state_dir));
    let config = Arc::new(config);
    let emitter = Arc::new(emit::Emitter::open(&config)?);
    let backlog = Arc::new(Backlog::default());
    let stats = Arc::new(Stats::default());
    let cancel = CancellationToken::new();
    let tracker = TaskTracker::new();
    let started = std::time::Instant::now();

    let registry = Arc::new(registry::Registry::default());
    let (senders, workers) = worker::spawn(&config, &emitter, &backlog, &stats, &registry, &cancel)?;
    // Video sources: started first so that a missing ffmpeg fails the start-up.
    let mut videos = video::Videos::start(&config, &emitter, &stats, &registry, &cancel)?;
    if let Some(h) = &config.http {
        // The status API and preview page (issue 6).
        let token = h.token.clone().unwrap_or_else(http::generate_token);
        let server =
            http::bind(h, &token).await.map_err(|source| DaemonError::Http { addr: h.listen, source })?;
        tracing::info!(addr = %server.addr, "HTTP server listening");
        http::announce(&server);
        let shared = Arc::new(http::Shared {
            config: config.clone(),
            registry: registry.clone(),
            stats: stats.clone(),
            backlog: backlog.clone(),
            emitter: emitter.clone(),
            queues: senders.clone(),
            token,
            loopback: server.addr.ip().is_loopback(),
            started,
            cancel: cancel.clone(),
            limits: http::limits::Limits::default(),
            read_only: None,
        });
        tracker.spawn(http::serve(server, shared, h.max_body_bytes));
    }
    let (hint_tx, hint_rx) = tokio::sync::mpsc::channel(watch::HINT_QUEUE);
    let overflow = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watcher = match config.watch_mode {
        _ if !watching => None,
        crate::config::WatchMode::Notify => Some(
            watch::start_notify(&config.watch_dir, config.follow_symlinks, hint_tx.clone(), overflow.clone())
                .map_err(|source| DaemonError::Watch { path: config.watch_dir.clone(), source })?,
        ),
        crate::config::WatchMode::Poll { .. } => None,
    };
    drop(hint_tx);
    tracing::info!(
        watch = %config.watch_dir.display(),
        out = %config.out_dir.display(),
        state = %config.state_dir.display(),
        workers = config.workers.get(),
        "service started"
    );
    emitter.emit(
        None,
        &event::Event::ServiceStarted { watch: config.watch_dir.clone(), pid: std::process::id() },
    );
    let intake =
        intake::Intake::new(config.clone(), senders, backlog.clone(), emitter.clone(), stats.clone());
    if watching {
        tracker.spawn(intake.run(hint_rx, overflow, cancel.clone(), watcher));
    }
    systemd::ready();
    tracker.spawn(systemd::supervise(stats.clone(), cancel.clone()));
    tracker.close();

    let mut failed = Vec::new();
    tokio::select! {
        () = shutdown => tracing::info!("shutdown requested: finishing the step in hand"),
        () = cancel.cancelled() => {}
        // Without a watched folder, the service ends when its videos do (files at their end).
        ended = videos.finished(), if !watching && !videos.is_empty() => {
            tracing::info!("every video ended");
            failed = ended;
        }
    }
    systemd::stopping();
    cancel.cancel();
    videos.kill_children();
    let grace = config.grace_period;
    let joined = tokio::task::spawn_blocking(move || {
        for w in workers {
            let _ = w.join();
        }
        videos.join();
    });
    let finished = tokio::time::timeout(grace, async {
        tracker.wait().await;
        let _ = joined.await;
    })
    .await;
    match finished {
        Ok(()) => tracing::info!("service stopped"),
        Err(_) => tracing::warn!(grace_ms = grace.as_millis() as u64, "grace period over: stopping mid-step"),
    }
    // The last line: a worker still busy past the grace period writes nothing after it.
    emitter.close(finished.is_ok());
    if failed.is_empty() { Ok(()) } else { Err(DaemonError::VideosFailed(failed)) }
}

/// Completes on SIGTERM or SIGINT (Ctrl-C). The handlers are installed when this is
/// called, not when the future is first polled: a signal that comes while the service is
/// still starting (its URL printed, its folders being scanned) is a clean stop, not the
/// default action that kills the process. Call it inside the runtime.
pub fn shutdown_signal() -> impl Future<Output = ()> + Send + 'static {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let handlers =
            signal(SignalKind::terminate()).and_then(|t| Ok((t, signal(SignalKind::interrupt())?)));
        async move {
            match handlers {
                Ok((mut term, mut int)) => {
                    tokio::select! {
                        _ = term.recv() => {}
                        _ = int.recv() => {}
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, "cannot listen for SIGTERM; only Ctrl-C stops the service");
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
        }
    }
    #[cfg(not(unix))]
    {
        async {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

fn create_dir(dir: &Path) -> Result<(), DaemonError> {
    std::fs::create_dir_all(dir).map_err(|source| DaemonError::CreateDir { path: dir.to_owned(), source })
}

/// How often the intake looks at settling files: often enough to notice a quiet period's
/// end within a quarter of it.
pub(crate) fn tick_interval(config: &Config) -> Duration {
    (config.quiet_period / 4).clamp(Duration::from_millis(20), Duration::from_millis(250))
}

pub(crate) fn millis_since(start: std::time::Instant) -> u64 {
    start.elapsed().as_millis() as u64
}

pub(crate) fn load(stats: &AtomicU64) -> u64 {
    stats.load(Ordering::Relaxed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stalest_loop_is_the_one_that_has_not_beaten_and_dropped_loops_do_not_count() {
        let hb = Arc::new(Heartbeats::default());
        assert!(hb.stalest().is_none(), "no loop, nothing stuck");
        let intake = hb.register("intake");
        let video = hb.register("video facade");
        std::thread::sleep(Duration::from_millis(30));
        intake.beat();
        let (name, age) = hb.stalest().unwrap();
        assert_eq!(name, "video facade");
        assert!(age >= Duration::from_millis(30), "{age:?}");
        drop(video);
        let (name, age) = hb.stalest().unwrap();
        assert_eq!(name, "intake");
        assert!(age < Duration::from_millis(30), "{age:?}");
        drop(intake);
        assert!(hb.stalest().is_none());
    }
}
