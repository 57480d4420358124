//! From "a path was touched" to a decoded job on a worker's queue (shell layer).
//!
//! Each candidate file is tracked by its size and modification time. It becomes *ready*
//! once they have not changed for the quiet period (measured on our clock, so a share's
//! skewed clock does not matter). Ready files are decoded (`spawn_blocking`, at most
//! `decoders` at a time) and queued to the worker that owns their session, keyframes and
//! masks before views, older before newer. A worker whose queue is full gets nothing more:
//! its files stay ready, on disk, and are queued at a later tick. A file that fails to
//! decode is reported once (event `file_skipped`) and not retried until it changes.
//! Keyframes and views must look like photographs: at least [`MIN_SIDE`](super::job::MIN_SIDE) pixels a side
//! and at most [`MAX_ASPECT`](super::job::MAX_ASPECT):1. A mask that a worker has taken and that is then deleted
//! is reported to that worker (a job without an image).

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime};

use crossbeam_channel::{Sender, TrySendError};
use tokio::sync::{Semaphore, mpsc};
use tokio_util::sync::CancellationToken;

use super::event::{Event, FileSkipped};
use super::job::{DecodeOutcome, FileId, Job, read_and_decode};
use super::paths::Inbox;
use super::watch::{self, Role};
use super::{Backlog, Stats, emit::Emitter};
use crate::config::{Config, WatchMode};
use crate::imaging::decode::DecodeLimits;

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
    /// Which file it is and when its inode last changed: a file renamed over it (rsync,
    /// sync clients) with the same size and time is another inode; a `chmod` that makes
    /// it readable changes the change time.
    inode: Inode,
    since: Instant,
    status: Status,
    /// A version of it reached a worker: a later version that cannot be used must be told
    /// to the worker too (it holds the old one's pixels).
    delivered: bool,
}

/// A file's device, inode and change time (seconds, nanoseconds).
type Inode = (u64, u64, i64, i64);

fn inode_of(meta: &std::fs::Metadata) -> Inode {
    use std::os::unix::fs::MetadataExt;
    (meta.dev(), meta.ino(), meta.ctime(), meta.ctime_nsec())
}

/// What a `file_skipped` event says of the next try.
/// How soon a new session folder is listed a second time (and a third, four times later).
const RELIST_AFTER: Duration = Duration::from_millis(500);

const RETRIED: &str = "when the file changes (its content, its permissions, or a new file under its name)";

/// The intake task's state.
pub struct Intake {
    config: Arc<Config>,
    senders: Vec<Sender<Job>>,
    backlog: Arc<Backlog>,
    emitter: Arc<Emitter>,
    stats: Arc<Stats>,
    files: HashMap<PathBuf, Tracked>,
    decoders: Arc<Semaphore>,
    inbox: Inbox,
    /// Symbolic links refused and reported (each once, while it is there).
    refused: HashSet<PathBuf>,
    root: Root,
    /// Files a worker holds a version of that are gone (a mask or a view deleted) or no
    /// longer usable (a view replaced by what cannot be decoded), still to be told to it.
    removed: Vec<(PathBuf, String, Role)>,
    /// New session folders to list again, and when: a file renamed into a folder just made
    /// can land before the kernel watches the folder, and its event is then lost.
    relist: Vec<(PathBuf, Instant)>,
}

/// The watched folder's identity (device and inode), to notice it being removed and
/// recreated (or a file system mounted over it): kernel watches do not survive that.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Root(Option<(u64, u64)>);

#[derive(Debug, PartialEq, Eq)]
enum RootChange {
    Same,
    Vanished,
    Back,
}

impl Root {
    fn of(dir: &std::path::Path) -> Self {
        use std::os::unix::fs::MetadataExt;
        Self(std::fs::metadata(dir).ok().filter(|m| m.is_dir()).map(|m| (m.dev(), m.ino())))
    }

    fn present(&self) -> bool {
        self.0.is_some()
    }

    /// Looks again; says what changed.
    fn check(&mut self, dir: &std::path::Path) -> RootChange {
        let now = Self::of(dir);
        let change = match (self.0, now.0) {
            (a, b) if a == b => RootChange::Same,
            (_, None) => RootChange::Vanished,
            (_, Some(_)) => RootChange::Back,
        };
        *self = now;
        change
    }
}

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
    ) -> Self {
        let decoders = Arc::new(Semaphore::new(config.decoders.get()));
        let inbox = Inbox::of(&config);
        let root = Root::of(&config.watch_dir);
        Self {
            config,
            senders,
            backlog,
            emitter,
            stats,
            files: HashMap::new(),
            decoders,
            inbox,
            refused: HashSet::new(),
            root,
            removed: Vec::new(),
            relist: Vec::new(),
        }
    }

    /// Runs until `cancel`. `watcher` is the notify watcher (notify mode): it is kept here
    /// so that it can be armed again when the watched folder is removed and recreated.
    pub async fn run(
        mut self,
        mut hints: mpsc::Receiver<PathBuf>,
        overflow: Arc<AtomicBool>,
        cancel: CancellationToken,
        mut watcher: Option<notify::RecommendedWatcher>,
    ) {
        let scan_every = match self.config.watch_mode {
            WatchMode::Notify => self.config.rescan_interval,
            WatchMode::Poll { interval } => interval,
        };
        let mut tick = tokio::time::interval(super::tick_interval(&self.config));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut last_scan: Option<Instant> = None;
        let heart = self.stats.heartbeats.register("intake");
        loop {
            tokio::select! {
                () = cancel.cancelled() => break,
                Some(path) = hints.recv() => self.observe(path),
                _ = tick.tick() => {
                    heart.beat();
                    match self.root.check(&self.config.watch_dir) {
                        RootChange::Same => {}
                        RootChange::Vanished => {
                            tracing::warn!(dir = %self.config.watch_dir.display(), "the watched folder is gone: waiting for it to come back");
                            let reason = "the watched folder was removed or unmounted".into();
                            let dir = self.config.watch_dir.clone();
                            self.emitter.emit(None, &Event::WatchDirVanished { dir, reason });
                        }
                        RootChange::Back => {
                            // Kernel watches die with their folder: armed again, and a
                            // full scan finds what landed before they were.
                            let rearmed = watcher.as_mut().map(|w| {
                                let _ = notify::Watcher::unwatch(w, &self.config.watch_dir);
                                notify::Watcher::watch(w, &self.config.watch_dir, notify::RecursiveMode::Recursive)
                            });
                            if let Some(Err(e)) = &rearmed {
                                tracing::error!(error = %e, "cannot watch the folder again: relying on rescans");
                            }
                            tracing::info!(dir = %self.config.watch_dir.display(), "the watched folder is back: watching and scanning it again");
                            let rewatched = rearmed.as_ref().map(Result::is_ok);
                            let dir = self.config.watch_dir.clone();
                            self.emitter.emit(None, &Event::WatchDirRestored { dir, rewatched });
                            last_scan = None;
                        }
                    }
                    if !self.root.present() {
                        continue;
                    }
                    if last_scan.is_none_or(|t| t.elapsed() >= scan_every) || overflow.swap(false, Ordering::Relaxed) {
                        self.full_scan().await;
                        last_scan = Some(Instant::now());
                    }
                    self.relist_due();
                    self.settle();
                    self.dispatch(&cancel).await;
                }
            }
        }
        tracing::debug!("intake stopped");
    }

    async fn full_scan(&mut self) {
        let root = self.config.watch_dir.clone();
        let follow = self.config.follow_symlinks;
        let paths = tokio::task::spawn_blocking(move || watch::scan(&root, follow)).await.unwrap_or_default();
        let present: HashSet<&PathBuf> = paths.iter().collect();
        self.refused.retain(|p| present.contains(p));
        let gone: Vec<PathBuf> = self.files.keys().filter(|p| !present.contains(p)).cloned().collect();
        for p in gone {
            self.forget(&p);
        }
        for p in paths {
            self.observe(p);
        }
    }

    /// Observes every entry of session folder `dir`.
    fn list_folder(&mut self, dir: &Path) {
        if let Ok(entries) = std::fs::read_dir(dir) {
            for e in entries.flatten() {
                self.observe(e.path());
            }
        }
    }

    /// Lists the new session folders whose second look is due.
    fn relist_due(&mut self) {
        let now = Instant::now();
        let (due, later): (Vec<_>, Vec<_>) = self.relist.drain(..).partition(|(_, at)| *at <= now);
        self.relist = later;
        for (dir, _) in due {
            self.list_folder(&dir);
        }
    }

    /// A hint that `path` may have changed.
    fn observe(&mut self, path: PathBuf) {
        if let Some(link) = self.inbox.symlink_on_path(&path) {
            self.forget(&path);
            self.refuse_link(link);
            return;
        }
        if path.parent() == Some(self.config.watch_dir.as_path()) && path.is_dir() {
            // A new session folder: files can land in it before the watcher watches it. Listed
            // now, and again shortly, for what landed in between.
            if !self.relist.iter().any(|(p, _)| p == &path) {
                let now = Instant::now();
                self.relist.extend([RELIST_AFTER, 4 * RELIST_AFTER].map(|d| (path.clone(), now + d)));
            }
            self.list_folder(&path);
            return;
        }
        let Some(candidate) = watch::classify(&self.config.watch_dir, &path, &self.config.extensions) else {
            return;
        };
        let meta = match std::fs::metadata(&path) {
            Ok(m) if m.is_file() => m,
            Ok(m) => {
                // A FIFO, a socket, a device or a folder under an image's name: reported
                // once, never opened (a FIFO would block its reader).
                self.forget(&path);
                self.refuse_special(path, &candidate.session, special_kind(&m.file_type()));
                return;
            }
            Err(_) => {
                self.forget(&path);
                return;
            }
        };
        self.refused.remove(&path);
        let (size, mtime, inode) =
            (meta.len(), meta.modified().unwrap_or(SystemTime::UNIX_EPOCH), inode_of(&meta));
        match self.files.get_mut(&path) {
            Some(t) if t.size == size && t.mtime == mtime && t.inode == inode => {}
            Some(t) => {
                // A settling or ready file is counted already; a queued one is counted by
                // its job until its worker has it, and this new version is counted again.
                if matches!(t.status, Status::Queued | Status::Failed) {
                    self.backlog.add(&t.session);
                }
                (t.size, t.mtime, t.inode, t.since, t.status) =
                    (size, mtime, inode, Instant::now(), Status::Settling);
            }
            None => {
                tracing::debug!(file = %watch::shown_path(&path), session = %watch::shown(&candidate.session), "noticed");
                // Counted from now: the session does not fill while a file of it is still
                // being written (the files of a burst, or of a restart, noticed a little
                // apart, make one fill).
                self.backlog.add(&candidate.session);
                self.files.insert(
                    path,
                    Tracked {
                        session: candidate.session,
                        role: candidate.role,
                        size,
                        mtime,
                        inode,
                        since: Instant::now(),
                        status: Status::Settling,
                        delivered: false,
                    },
                );
            }
        }
    }

    /// `path` is gone from the folder: it stops being tracked, and a mask or a view a
    /// worker took is reported to it.
    fn forget(&mut self, path: &std::path::Path) {
        let Some(t) = self.files.remove(path) else { return };
        if matches!(t.status, Status::Settling | Status::Ready) {
            self.backlog.done(&t.session);
        }
        // A deleted mask is no mask; a deleted view's pixels are no file's any more. A mask
        // is always told: the worker may hold it without the intake's delivery (its own
        // listing of the session takes a mask the watcher had not yet seen), and one it
        // does not use is ignored there.
        let held = match t.role {
            Role::Mask => true,
            Role::View => t.delivered,
            Role::Key => false,
        };
        if held {
            self.removed.push((path.to_owned(), t.session, t.role));
        }
    }

    /// Tells workers about deleted masks and unusable new versions of views while their
    /// queues have room.
    fn report_removed(&mut self) {
        let workers = self.senders.len();
        self.removed.retain(|(path, session, role)| {
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let file = FileId { name, size: 0, mtime: SystemTime::UNIX_EPOCH };
            let job = Job { session: session.clone(), path: path.clone(), role: *role, file, image: None };
            // Full: kept for the next tick. Disconnected: nobody to tell.
            matches!(self.senders[worker_for(session, workers)].try_send(job), Err(TrySendError::Full(_)))
        });
    }

    /// Reports a symbolic link that is not followed: once, while it stays. Links in the
    /// root and linked session folders are reported whatever their name; a link inside a
    /// session when it is a candidate by name.
    fn refuse_link(&mut self, link: PathBuf) {
        if self.refused.contains(&link) {
            return;
        }
        let root = &self.config.watch_dir;
        let name = link.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let (session, what) = match watch::classify(root, &link, &self.config.extensions) {
            Some(c) => (c.session, "file"),
            None if link.parent() == Some(root.as_path()) && !watch::is_partial_or_hidden(&name) => {
                (name.clone(), "session folder")
            }
            None => return,
        };
        let target = std::fs::read_link(&link).ok();
        let reason = format!(
            "the {what} is a symbolic link{}: links are not followed (watch.follow_symlinks = false)",
            target.as_ref().map(|t| format!(" to {}", t.display())).unwrap_or_default()
        );
        self.stats.skipped.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(file = %watch::shown_path(&link), session = %watch::shown(&session), %reason, "file skipped");
        let path = link.to_string_lossy().into_owned();
        let e = FileSkipped { file: Some(name), path, reason, retried: None, symlink: true };
        self.emitter.emit(Some(&session), &Event::FileSkipped(e));
        self.refused.insert(link);
    }

    /// Reports a file that is not a regular file: once, while it stays.
    fn refuse_special(&mut self, path: PathBuf, session: &str, kind: &str) {
        if self.refused.contains(&path) {
            return;
        }
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let reason = format!("{kind}, not a regular file: it is not read");
        self.stats.skipped.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(file = %watch::shown_path(&path), session = %watch::shown(session), %reason, "file skipped");
        let e = FileSkipped {
            file: Some(name),
            path: path.to_string_lossy().into_owned(),
            reason,
            retried: Some(RETRIED),
            symlink: false,
        };
        self.emitter.emit(Some(session), &Event::FileSkipped(e));
        self.refused.insert(path);
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
            }
        }
    }

    /// Decodes and queues ready files while their workers have room.
    async fn dispatch(&mut self, cancel: &CancellationToken) {
        self.report_removed();
        let mut room: Vec<usize> =
            self.senders.iter().map(|s| s.capacity().unwrap_or(usize::MAX).saturating_sub(s.len())).collect();
        // A file refused at decoding never reaches a worker: the room it was given is given
        // back and more files are taken in the same tick, so a flood of bad files is
        // reported as fast as it decodes, not `workers × queue` files a tick.
        while self.dispatch_round(&mut room, cancel).await {}
    }

    /// Decodes as many ready files as the workers' queues have `room` for and queues them;
    /// whether room was given back by files that did not become jobs (another round may
    /// take more).
    async fn dispatch_round(&mut self, room: &mut [usize], cancel: &CancellationToken) -> bool {
        let workers = self.senders.len();
        let mut ready: Vec<(&PathBuf, &Tracked)> =
            self.files.iter().filter(|(_, t)| t.status == Status::Ready).collect();
        if ready.is_empty() || cancel.is_cancelled() {
            return false;
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
        if planned.is_empty() {
            return false;
        }
        let mut given_back = false;
        let limits = DecodeLimits { max_pixels: self.config.max_pixels };
        let mut decodes = Vec::with_capacity(planned.len());
        for (path, w) in planned {
            let t = self.files.get_mut(&path).expect("planned from the map");
            t.status = Status::Queued;
            let (role, size, mtime) = (t.role, t.size, t.mtime);
            let semaphore = self.decoders.clone();
            let p = path.clone();
            let inbox = self.inbox.clone();
            let handle = tokio::spawn(async move {
                let _permit = semaphore.acquire_owned().await.expect("never closed");
                tokio::task::spawn_blocking(move || read_and_decode(&p, role, size, mtime, &limits, &inbox))
                    .await
            });
            decodes.push((path, w, handle));
        }
        for (path, w, handle) in decodes {
            let outcome = handle.await.ok().and_then(|r| r.ok());
            // A decoder that panicked on this file: refused like any other, never again until
            // it changes.
            let crashed = outcome.is_none();
            let outcome = outcome.unwrap_or_else(|| Err(DecodeOutcome::Failed("the decoder crashed".into())));
            let t = self.files.get_mut(&path).expect("planned from the map");
            let session = t.session.clone();
            match outcome {
                Ok(image) => {
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
                        Ok(()) => t.delivered = true,
                        Err(TrySendError::Full(_)) => t.status = Status::Ready,
                        Err(TrySendError::Disconnected(_)) => {
                            t.status = Status::Ready;
                            tracing::error!("a worker thread has stopped: restart the service");
                        }
                    }
                }
                Err(DecodeOutcome::Changed) => {
                    // Written to while we read it: wait for it to settle again.
                    (room[w], given_back) = (room[w] + 1, true);
                    t.status = Status::Settling;
                    t.since = Instant::now();
                }
                Err(
                    DecodeOutcome::Failed(reason) | DecodeOutcome::Io(reason) | DecodeOutcome::Gone(reason),
                ) => {
                    (room[w], given_back) = (room[w] + 1, true);
                    t.status = Status::Failed;
                    if t.delivered && t.role == Role::View {
                        // Its worker holds the pixels of a version that is gone.
                        self.removed.push((path.clone(), session.clone(), t.role));
                        t.delivered = false;
                    }
                    self.backlog.done(&session);
                    self.stats.skipped.fetch_add(1, Ordering::Relaxed);
                    let (file, session_shown) = (watch::shown_path(&path), watch::shown(&session));
                    if crashed {
                        tracing::error!(%file, session = %session_shown, %reason, "file skipped");
                    } else {
                        tracing::warn!(%file, session = %session_shown, %reason, "file skipped");
                    }
                    let e = FileSkipped {
                        file: path.file_name().map(|n| n.to_string_lossy().into_owned()),
                        path: path.to_string_lossy().into_owned(),
                        reason,
                        retried: Some(RETRIED),
                        symlink: false,
                    };
                    self.emitter.emit(Some(&session), &Event::FileSkipped(e));
                }
            }
        }
        given_back
    }
}

/// What a file that is not a regular file is, in words.
fn special_kind(t: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_dir() {
        "a folder"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_block_device() || t.is_char_device() {
        "a device node"
    } else {
        "not a file"
    }
}

/// Time a test or a caller may wait for a file to be taken: quiet period plus two ticks.
pub fn settle_time(config: &Config) -> Duration {
    config.quiet_period + 2 * super::tick_interval(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file counts in its session's backlog from the moment it is noticed, not only once
    /// it has been quiet for the quiet period: files of a burst (or of a restart) noticed a
    /// few milliseconds apart become ready in different ticks, and a session that filled
    /// between them published a result of some of them over one of all (seen in
    /// tests/faults.rs under load). A file deleted while it settles leaves the count.
    #[test]
    fn a_file_waits_in_the_backlog_from_when_it_is_noticed() {
        let tmp = tempfile::tempdir().unwrap();
        let config = Config {
            watch_dir: tmp.path().join("inbox"),
            out_dir: tmp.path().join("out"),
            state_dir: tmp.path().join("state"),
            quiet_period: Duration::from_secs(3600),
            ..Config::default()
        };
        let session = config.watch_dir.join("s");
        std::fs::create_dir_all(&session).unwrap();
        std::fs::create_dir_all(&config.out_dir).unwrap();
        let emitter = Arc::new(Emitter::open(&config).unwrap());
        let backlog = Arc::new(Backlog::default());
        let (tx, _rx) = crossbeam_channel::bounded(4);
        let mut intake = Intake::new(Arc::new(config), vec![tx], backlog.clone(), emitter, Arc::default());
        for name in ["v1.png", "v2.png"] {
            std::fs::write(session.join(name), b"not yet a whole file").unwrap();
            intake.observe(session.join(name));
        }
        assert_eq!(backlog.get("s"), 2, "both files wait, though neither has settled");
        intake.settle();
        assert_eq!(backlog.get("s"), 2, "settling again does not count them twice");
        std::fs::write(session.join("v1.png"), b"written to again").unwrap();
        intake.observe(session.join("v1.png"));
        assert_eq!(backlog.get("s"), 2, "a new version of a waiting file is one file");
        std::fs::remove_file(session.join("v2.png")).unwrap();
        intake.forget(&session.join("v2.png"));
        assert_eq!(backlog.get("s"), 1, "a file deleted while it settles no longer waits");
    }
}
