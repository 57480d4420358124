//! The compute threads of the folder source (shell layer): each owns the sessions hashed
//! to it ([`super::intake::worker_for`]) and takes the jobs of its bounded crossbeam
//! queue in order: it wakes a sleeping session, hands the job to [`super::folder`] (what
//! the file does to its session), then asks the session engine to fill
//! ([`super::engine::Slot::fill`]) once no more files of the session wait, and publishes
//! the session's snapshot. It also ends sessions whose folder is gone and puts idle
//! sessions to sleep beyond `resident_sessions`. Alignment and fill run here (rayon inside
//! a step); re-reading a buffered view's file (after a new keyframe or mask) is done
//! inline, as part of the step.

use std::collections::HashMap;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, bounded};
use tokio_util::sync::CancellationToken;

use super::emit::Emitter;
use super::engine::{Ctx, Slot};
use super::event::Event;
use super::folder;
use super::job::Job;
use super::policy;
use super::registry::Registry;
use super::state;
use super::watch::{self, Role};
use super::{Backlog, DaemonError, Stats};
use crate::config::Config;

/// The workers' queues and threads.
pub type Workers = (Vec<Sender<Job>>, Vec<JoinHandle<()>>);

/// Starts `config.workers` threads, each with a queue of `config.queue` jobs.
pub fn spawn(
    config: &Arc<Config>,
    emitter: &Arc<Emitter>,
    backlog: &Arc<Backlog>,
    stats: &Arc<Stats>,
    registry: &Arc<Registry>,
    cancel: &CancellationToken,
) -> Result<Workers, DaemonError> {
    let mut senders = Vec::new();
    let mut handles = Vec::new();
    for i in 0..config.workers.get() {
        let (tx, rx) = bounded(config.queue.get());
        let ctx = Ctx {
            config: config.clone(),
            cancel: cancel.clone(),
            emitter: emitter.clone(),
            backlog: backlog.clone(),
            stats: stats.clone(),
            registry: registry.clone(),
        };
        let cancel = cancel.clone();
        let handle = std::thread::Builder::new()
            .name(format!("clearview-worker-{i}"))
            .spawn(move || {
                let w = Worker {
                    ctx,
                    sessions: HashMap::new(),
                    asleep: Default::default(),
                    used: HashMap::new(),
                };
                w.run(&rx, &cancel)
            })
            .map_err(DaemonError::Thread)?;
        senders.push(tx);
        handles.push(handle);
    }
    Ok((senders, handles))
}

struct Worker {
    ctx: Ctx,
    sessions: HashMap<String, Slot>,
    /// Sessions put to sleep (rebuilt from disk when a file arrives).
    asleep: std::collections::HashSet<String>,
    /// When each resident session last had a job.
    used: HashMap<String, Instant>,
}

impl Worker {
    fn run(mut self, rx: &Receiver<Job>, cancel: &CancellationToken) {
        loop {
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(job) => {
                    if cancel.is_cancelled() {
                        let left = rx.len() + 1;
                        tracing::info!(left, "stopping: queued files are left on disk for the next start");
                        break;
                    }
                    let session = job.session.clone();
                    if self.removed(&session) {
                        tracing::debug!(file = %job.path.display(), "its session folder is gone: dropped");
                        self.ctx.backlog.done(&session);
                        continue;
                    }
                    if self.asleep.remove(&session) {
                        self.wake(&session);
                    }
                    self.used.insert(session.clone(), Instant::now());
                    // A deletion was never in the backlog.
                    let counted = job.image.is_some();
                    self.handle(job);
                    if counted {
                        self.ctx.backlog.done(&session);
                    }
                    self.maybe_fill(&session);
                    self.sleep_beyond_capacity();
                }
                Err(RecvTimeoutError::Timeout) => {
                    if cancel.is_cancelled() {
                        break;
                    }
                    let names: Vec<String> = self.sessions.keys().cloned().collect();
                    for name in names {
                        if !self.removed(&name) {
                            self.maybe_fill(&name);
                        }
                    }
                }
                Err(RecvTimeoutError::Disconnected) => break,
            }
            if cancel.is_cancelled() {
                break;
            }
        }
        for slot in self.sessions.values_mut() {
            slot.save_state(&self.ctx);
            if let Some(number) = slot.unwritten() {
                tracing::warn!(
                    session = %watch::shown(&slot.name),
                    number,
                    "stopping with a result that could not be written: it is made again at the next start"
                );
            }
        }
    }

    /// Whether the inbox folder of session `name` is gone (deleted while it was handled,
    /// or with the whole watched folder). A resident session is ended then: its state is
    /// saved, its results in the out folder are kept (a user never wants them deleted)
    /// and event `session_removed` says so. If the folder comes back, the session starts
    /// again from its files.
    fn removed(&mut self, name: &str) -> bool {
        if name == watch::ROOT_SESSION || self.ctx.config.watch_dir.join(name).is_dir() {
            return false;
        }
        self.asleep.remove(name);
        self.used.remove(name);
        if let Some(mut slot) = self.sessions.remove(name) {
            slot.save_state(&self.ctx);
            let kept = slot.state.result.as_ref().map(|r| r.number);
            tracing::info!(session = %watch::shown(name), dir = %slot.dir.display(), "session folder removed: session ended, its results are kept");
            let e = Event::SessionRemoved {
                dir: slot.dir.clone(),
                reason: "its folder was removed".into(),
                results_kept: self.ctx.emitter.session_dir(name),
                last_result: kept,
                unwritten_result: slot.unwritten(),
            };
            self.ctx.emitter.emit(Some(name), &e);
        }
        true
    }

    /// Puts the least recently used idle sessions to sleep while more than
    /// `resident_sessions` are in memory: state saved, everything else dropped.
    fn sleep_beyond_capacity(&mut self) {
        while self.sessions.len() > self.ctx.config.resident_sessions.get() {
            let idle = self
                .sessions
                .iter()
                .filter(|(name, s)| !s.busy() && self.ctx.backlog.get(name) == 0)
                .min_by_key(|(name, _)| self.used.get(*name).copied())
                .map(|(name, _)| name.clone());
            let Some(name) = idle else { return };
            let slot = self.sessions.remove(&name).expect("chosen from the map");
            self.used.remove(&name);
            state::save(&self.ctx.config.state_dir, &name, &slot.state);
            tracing::info!(session = %watch::shown(&name), "session put to sleep (memory): it is rebuilt when a file arrives");
            self.asleep.insert(name);
        }
    }

    /// Rebuilds a sleeping session from disk: its keyframe, mask and the views whose
    /// alignments are saved (taken back by [`folder::take_key`]; none is realigned); an
    /// unchanged result is not rewritten.
    fn wake(&mut self, name: &str) {
        let Self { ctx, sessions, .. } = self;
        let slot = Self::slot(ctx, sessions, name);
        let span = tracing::info_span!("session", session = %watch::shown(name));
        let _enter = span.enter();
        let Some(key_name) = slot.state.key_file.clone() else { return };
        let key_path = slot.dir.join(&key_name);
        let Ok((file, img)) = folder::load(ctx, &key_path, Role::View) else { return };
        let listing = folder::listing(ctx, &slot.dir);
        let source = policy::saved_key_source(&ctx.config.keyframe, &listing, &key_name);
        tracing::info!("waking the session up");
        folder::take_key(ctx, slot, &file, &key_path, &img, source);
        slot.fill(ctx);
    }

    fn slot<'a>(ctx: &Ctx, sessions: &'a mut HashMap<String, Slot>, name: &str) -> &'a mut Slot {
        sessions.entry(name.to_owned()).or_insert_with(|| {
            let dir = if name == watch::ROOT_SESSION {
                ctx.config.watch_dir.clone()
            } else {
                ctx.config.watch_dir.join(name)
            };
            Slot::new(ctx, name, dir)
        })
    }

    fn handle(&mut self, job: Job) {
        let span = tracing::info_span!("session", session = %watch::shown(&job.session));
        let _enter = span.enter();
        let Job { session, path, role, file, image } = job;
        let Self { ctx, sessions, .. } = self;
        let slot = Self::slot(ctx, sessions, &session);
        folder::apply(ctx, slot, role, &file, &path, image.as_ref());
        slot.save_state(ctx);
        slot.publish(ctx, None);
    }

    fn maybe_fill(&mut self, name: &str) {
        let waiting = self.ctx.backlog.get(name);
        let batch_max = self.ctx.config.batch_max.get();
        let Some(slot) = self.sessions.get_mut(name) else { return };
        if let Some(number) = slot.retry_pending(&self.ctx) {
            slot.save_state(&self.ctx);
            slot.publish(&self.ctx, Some(number));
        }
        // A save that failed earlier (full or read-only state folder).
        slot.save_state_if_due(&self.ctx);
        if !slot.session.needs_fill() || (waiting > 0 && slot.session.admitted_since_fill() < batch_max) {
            return;
        }
        let span = tracing::info_span!("session", session = %watch::shown(name));
        let _enter = span.enter();
        let written = slot.fill(&self.ctx).written();
        slot.save_state(&self.ctx);
        slot.publish(&self.ctx, written);
    }
}
