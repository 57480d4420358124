//! The compute threads (shell layer): each owns the sessions hashed to it and turns the
//! jobs of its bounded crossbeam queue into session changes, results, events and state.
//! Alignment and fill run here (rayon inside a step); re-reading a buffered view's file
//! (after a new keyframe or mask) is done inline, as part of the step.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, bounded};
use image::DynamicImage;
use serde_json::json;
use tokio_util::sync::CancellationToken;

use super::emit::{Emitter, rfc3339};
use super::job::{DecodeOutcome, FileId, Job};
use super::paths::Inbox;
use super::registry::{LegendEntry, Registry, SessionSnapshot, ViewSnapshot};
use super::state::{self, SavedResult, SessionState};
use super::watch::{self, Role};
use super::{Backlog, DaemonError, Stats};
use crate::config::{Config, KeyframeRule, MaskRule};
use crate::imaging::convert::{to_luminance, to_mask, to_rgb};
use crate::imaging::decode::DecodeLimits;
use crate::inpaint::{Observer, Stage};
use crate::session::{Admission, AlignRecord, Rgb8, Session};

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

pub(super) struct Ctx {
    pub(super) config: Arc<Config>,
    /// Cancelled when the service stops: long steps (a fill) give up and write nothing.
    pub(super) cancel: CancellationToken,
    pub(super) emitter: Arc<Emitter>,
    pub(super) backlog: Arc<Backlog>,
    pub(super) stats: Arc<Stats>,
    pub(super) registry: Arc<Registry>,
}

/// A view as the result report lists it.
#[derive(Debug, Clone)]
pub(super) struct ViewEntry {
    pub(super) id: String,
    pub(super) status: &'static str,
    pub(super) reason: Option<String>,
    pub(super) record: Option<AlignRecord>,
    pub(super) from_state: bool,
    pub(super) seq: u64,
}

/// Views listed in a session's report at most (the oldest go first).
pub(super) const MAX_LISTED: usize = 1000;

pub(super) struct Slot {
    pub(super) name: String,
    pub(super) dir: PathBuf,
    pub(super) session: Session,
    pub(super) state: SessionState,
    pub(super) key_path: Option<PathBuf>,
    /// Why the keyframe is the keyframe; `None` before there is one.
    pub(super) key_source: Option<KeySource>,
    /// A keyframe without a mask was reported waiting (`session_waiting`), once.
    waiting_said: bool,
    pub(super) mask_source: Option<String>,
    /// The mask (its content id) refused for the current keyframe: reported once, though
    /// it is read both beside the keyframe and as a file of its own.
    pub(super) refused_mask: Option<String>,
    /// Views waiting for their keyframe, by file name.
    pub(super) parked: BTreeMap<String, PathBuf>,
    /// Where each buffered view's file is (to re-read it).
    pub(super) paths: HashMap<String, PathBuf>,
    pub(super) views: BTreeMap<String, ViewEntry>,
    pub(super) seq: u64,
    pub(super) state_dirty: bool,
    /// A result that could not be written yet.
    pub(super) pending: Option<Pending>,
    /// When to try again to save a state that could not be saved.
    pub(super) state_retry: Backoff,
    /// For the status API: the latest result's report, provenance legend, the masked
    /// pixels each view filled in it, the history's numbers, and since when a view has
    /// been waiting for the result it may lead to.
    last_report: Option<serde_json::Value>,
    legend: Vec<LegendEntry>,
    filled_by: HashMap<String, usize>,
    history: Vec<u64>,
    pending_since: Option<Instant>,
}

impl Slot {
    /// A new slot for session `name` whose files are in `dir`, with its saved state.
    pub(super) fn new(ctx: &Ctx, name: &str, dir: PathBuf) -> Self {
        let out = ctx.emitter.session_dir(name);
        let history = saved_history(&out.join("history"));
        let mut state = state::load(&ctx.config.state_dir, name);
        // The saved state is checked against the out folder, never trusted over it: a
        // result it remembers must be the one on disk, whole and agreeing with its
        // result.json, or it is made again; numbering goes on after every result on disk.
        let on_disk = super::emit::check_result(&out);
        if let Some(saved) = &state.result {
            match &on_disk {
                Ok(n) if *n == saved.number => {}
                Ok(n) => {
                    tracing::warn!(session = %watch::shown(name), saved = saved.number, on_disk = n, "the saved state names another result than the one on disk: it is made again");
                    state.result = None;
                }
                Err(reason) => {
                    tracing::warn!(session = %watch::shown(name), %reason, "the result on disk is not the one the state saved: it is made again");
                    state.result = None;
                }
            }
        }
        let newest = on_disk.iter().copied().chain(history.last().copied()).max().unwrap_or(0);
        if newest > state.last_number {
            tracing::info!(session = %watch::shown(name), saved = state.last_number, newest, "results on disk are newer than the saved state: numbering goes on after them");
            state.last_number = newest;
        }
        Slot {
            name: name.to_owned(),
            dir,
            session: Session::new(ctx.config.session.clone()),
            state,
            key_path: None,
            key_source: None,
            waiting_said: false,
            mask_source: None,
            refused_mask: None,
            parked: BTreeMap::new(),
            paths: HashMap::new(),
            views: BTreeMap::new(),
            seq: 0,
            state_dirty: false,
            pending: None,
            state_retry: Backoff::default(),
            last_report: std::fs::read(out.join("result.json"))
                .ok()
                .and_then(|b| serde_json::from_slice(&b).ok()),
            legend: Vec::new(),
            filled_by: HashMap::new(),
            history,
            pending_since: None,
        }
    }
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
            save_state(&self.ctx, slot);
            if let Some(p) = &slot.pending {
                tracing::warn!(
                    session = %watch::shown(&slot.name),
                    number = p.number,
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
            save_state(&self.ctx, &mut slot);
            let kept = slot.state.result.as_ref().map(|r| r.number);
            tracing::info!(session = %watch::shown(name), dir = %slot.dir.display(), "session folder removed: session ended, its results are kept");
            self.ctx.emitter.event(
                "session_removed",
                Some(name),
                json!({
                    "dir": slot.dir,
                    "reason": "its folder was removed",
                    "results_kept": self.ctx.emitter.session_dir(name),
                    "last_result": kept,
                    "unwritten_result": slot.pending.as_ref().map(|p| p.number),
                }),
            );
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
                .filter(|(name, s)| {
                    !s.session.needs_fill()
                        && self.ctx.backlog.get(name) == 0
                        && s.parked.is_empty()
                        && s.pending.is_none()
                        && !s.state_dirty
                })
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
    /// alignments are saved (none is realigned); an unchanged result is not rewritten.
    fn wake(&mut self, name: &str) {
        let Self { ctx, sessions, .. } = self;
        let slot = Self::slot(ctx, sessions, name);
        let span = tracing::info_span!("session", session = %watch::shown(name));
        let _enter = span.enter();
        let Some(key_name) = slot.state.key_file.clone() else { return };
        let key_path = slot.dir.join(&key_name);
        let Ok((file, img)) = load(ctx, &key_path, Role::View) else { return };
        let key_id = format!("{}|", file.id());
        for path in watch::scan(&slot.dir, ctx.config.follow_symlinks) {
            let Some(c) = watch::classify(&ctx.config.watch_dir, &path, &ctx.config.extensions) else {
                continue;
            };
            let saved = FileId::of(&path)
                .is_ok_and(|f| slot.state.has_alignment_for(&format!("{}|", f.id()), &key_id));
            if c.role == Role::View && path != key_path && saved {
                let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_owned();
                slot.parked.insert(name, path);
            }
        }
        let source = match (&ctx.config.keyframe, watch::stem(&key_name)) {
            (_, "key") => KeySource::NamedKey,
            (KeyframeRule::Named(n), s) if n == s => KeySource::Configured,
            (_, s) if has_own_mask(ctx, &slot.dir, s) => KeySource::Masked,
            _ => KeySource::First,
        };
        tracing::info!(views = slot.parked.len(), "waking the session up");
        take_key(ctx, slot, &file, &key_path, &img, source);
        fill(ctx, slot);
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
        let Some(image) = image else {
            match role {
                Role::Mask => mask_removed(ctx, slot, &file),
                // A view's file now holds nothing usable: its old pixels go.
                _ => {
                    let why = if path.exists() {
                        "its file was replaced by something unusable"
                    } else {
                        "its file was deleted"
                    };
                    forget_old_content(ctx, slot, &file.name, None, why);
                }
            }
            save_state(ctx, slot);
            publish(ctx, slot, None);
            return;
        };
        if role == Role::View {
            ctx.registry.metrics.views_received.fetch_add(1, Ordering::Relaxed);
        }
        match role {
            Role::Key => take_key(ctx, slot, &file, &path, &image, KeySource::NamedKey),
            Role::Mask => take_mask(ctx, slot, &file, &image),
            Role::View => match key_source_for(ctx, slot, &file.name) {
                Some(source) => take_key(ctx, slot, &file, &path, &image, source),
                None if slot.session.key_id().is_none() => {
                    tracing::info!(file = %watch::shown(&file.name), "waiting for the keyframe");
                    ctx.emitter.event(
                        "view_waiting",
                        Some(&slot.name),
                        json!({ "file": file.name, "reason": "no keyframe yet: it is aligned when the keyframe arrives" }),
                    );
                    slot.parked.insert(file.name.clone(), path);
                }
                None => process_view(ctx, slot, &file, &path, &image),
            },
        }
        save_state(ctx, slot);
        publish(ctx, slot, None);
    }

    fn maybe_fill(&mut self, name: &str) {
        let waiting = self.ctx.backlog.get(name);
        let batch_max = self.ctx.config.batch_max.get();
        let Some(slot) = self.sessions.get_mut(name) else { return };
        if let Some(number) = retry_pending(&self.ctx, slot) {
            save_state(&self.ctx, slot);
            publish(&self.ctx, slot, Some(number));
        }
        if slot.state_dirty && slot.state_retry.due() {
            // A save that failed earlier (full or read-only state folder).
            save_state(&self.ctx, slot);
        }
        if !slot.session.needs_fill() || (waiting > 0 && slot.session.admitted_since_fill() < batch_max) {
            return;
        }
        let span = tracing::info_span!("session", session = %watch::shown(name));
        let _enter = span.enter();
        let written = fill(&self.ctx, slot);
        save_state(&self.ctx, slot);
        publish(&self.ctx, slot, written);
    }
}

/// Why an image is (or would be) a session's keyframe, strongest first: a later image
/// with a stronger reason takes the keyframe's place, a weaker one never does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum KeySource {
    /// Named `key.<ext>`.
    NamedKey,
    /// Named by the configuration (`session.keyframe`).
    Configured,
    /// A mask beside it names it (`<stem>.mask.png`, `<stem>_mask.*`, `<stem>-mask.*`).
    Masked,
    /// The first image to arrive (`session.keyframe = "first"`).
    First,
}

/// Why file `name` would become the keyframe, or `None` if it is a view (or must wait for
/// the keyframe).
fn key_source_for(ctx: &Ctx, slot: &Slot, name: &str) -> Option<KeySource> {
    let stem = watch::stem(name);
    let current = slot.key_path.as_ref().and_then(|p| p.file_name()).and_then(|n| n.to_str());
    if current == Some(name) {
        // A new version of the keyframe.
        return slot.key_source;
    }
    let beats = |s: KeySource| slot.key_source.is_none_or(|k| s < k);
    match &ctx.config.keyframe {
        KeyframeRule::Named(n) if n == stem => beats(KeySource::Configured).then_some(KeySource::Configured),
        KeyframeRule::Named(_) => None,
        KeyframeRule::First => {
            if has_named_key(ctx, &slot.dir) {
                return None;
            }
            if has_own_mask(ctx, &slot.dir, stem) {
                // The image the user painted a mask for, whatever arrived first.
                return beats(KeySource::Masked).then_some(KeySource::Masked);
            }
            if slot.session.key_id().is_some() {
                return None;
            }
            if let Some(saved) = &slot.state.key_file
                && saved != name
                && slot.dir.join(saved).is_file()
            {
                return None;
            }
            Some(KeySource::First)
        }
    }
}

/// Whether the image of stem `stem` in `dir` has a mask of its own beside it.
fn has_own_mask(ctx: &Ctx, dir: &Path, stem: &str) -> bool {
    watch::mask_names(stem, &ctx.config.extensions).iter().any(|n| dir.join(n).is_file())
}

fn has_named_key(ctx: &Ctx, dir: &Path) -> bool {
    ctx.config.extensions.iter().any(|e| dir.join(format!("key.{e}")).is_file())
}

fn take_key(ctx: &Ctx, slot: &mut Slot, file: &FileId, path: &Path, image: &DynamicImage, source: KeySource) {
    let id = file.content_id(image);
    if slot.session.key_id() == Some(id.as_str()) {
        return;
    }
    let first = slot.session.key_id().is_none();
    let mut again: Vec<PathBuf> = slot
        .session
        .set_key(id.clone(), to_rgb(image))
        .iter()
        .filter_map(|i| slot.paths.get(i).cloned())
        .collect();
    if let Some(old) = slot.key_path.take()
        && old != path
        && watch::classify(&ctx.config.watch_dir, &old, &ctx.config.extensions)
            .is_some_and(|c| c.role == Role::View)
    {
        // The previous keyframe was an ordinary image: it is a view now.
        again.push(old);
    }
    again.extend(std::mem::take(&mut slot.parked).into_values());
    // Views rejected against the old keyframe may well match the new one.
    again.extend(
        slot.views
            .iter()
            .filter(|(_, v)| matches!(v.status, "rejected" | "outside_mask"))
            .map(|(name, _)| slot.dir.join(name))
            .filter(|p| p.is_file()),
    );
    again.retain(|p| p != path);
    again.sort();
    again.dedup();
    slot.key_path = Some(path.to_owned());
    slot.key_source = Some(source);
    slot.waiting_said = false;
    slot.mask_source = None;
    slot.refused_mask = None;
    slot.paths.clear();
    for v in slot.views.values_mut() {
        v.status = "superseded";
    }
    if slot.state.key_file.as_deref() != Some(&file.name) {
        slot.state.key_file = Some(file.name.clone());
        slot.state_dirty = true;
    }
    let (w, h) = (image.width(), image.height());
    tracing::info!(key = %watch::shown(&file.name), width = w, height = h, views = again.len(), "keyframe set");
    ctx.emitter.event(
        if first { "session_started" } else { "keyframe_changed" },
        Some(&slot.name),
        json!({ "keyframe": file.name, "width": w, "height": h }),
    );
    if let Some(mask_path) = find_mask(ctx, &slot.dir, &file.name) {
        match load(ctx, &mask_path, Role::Mask) {
            Ok((f, img)) => apply_mask(ctx, slot, &f, &img),
            Err(e) => skip(ctx, slot, &mask_path, &e.reason()),
        }
    }
    say_waiting(ctx, slot);
    for p in again {
        reprocess(ctx, slot, &p);
    }
    auto_mask(ctx, slot);
}

/// A keyframe without a mask (and no automatic mask configured) makes no result: said
/// once per keyframe (event `session_waiting`, naming the files it waits for).
fn say_waiting(ctx: &Ctx, slot: &mut Slot) {
    if slot.waiting_said || slot.session.mask_id().is_some() || !matches!(ctx.config.mask, MaskRule::File) {
        return;
    }
    let Some(key) =
        slot.key_path.as_ref().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned())
    else {
        return;
    };
    let names = watch::mask_names(watch::stem(&key), &["png".to_owned()]);
    let reason = format!(
        "waiting for a mask of the keyframe {key}: {} or mask.png beside it (white = remove), or paint one on the preview page",
        names.join(", ")
    );
    tracing::info!(keyframe = %watch::shown(&key), "session waiting for a mask");
    ctx.emitter.event(
        "session_waiting",
        Some(&slot.name),
        json!({ "keyframe": key, "waiting_for": "mask", "expected": names, "reason": reason }),
    );
    slot.waiting_said = true;
}

/// The mask file for the keyframe `key_name` in `dir`: its own (`<stem>.mask.<ext>`,
/// `<stem>_mask.<ext>`, `<stem>-mask.<ext>`), else the session's `mask.<ext>`.
fn find_mask(ctx: &Ctx, dir: &Path, key_name: &str) -> Option<PathBuf> {
    let own = watch::mask_names(watch::stem(key_name), &ctx.config.extensions);
    let shared = ctx.config.extensions.iter().map(|e| format!("mask.{e}"));
    own.into_iter().chain(shared).map(|n| dir.join(n)).find(|p| p.is_file())
}

/// The image of stem `owner` in `dir` (any configured extension, any case), if any.
fn image_of(ctx: &Ctx, dir: &Path, owner: &str) -> Option<PathBuf> {
    let entries = std::fs::read_dir(dir).ok()?;
    entries.flatten().map(|e| e.path()).find(|p| {
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        watch::stem(name) == owner
            && watch::classify(&ctx.config.watch_dir, p, &ctx.config.extensions)
                .is_some_and(|c| c.role != Role::Mask)
            && p.is_file()
    })
}

fn take_mask(ctx: &Ctx, slot: &mut Slot, file: &FileId, image: &DynamicImage) {
    let owner = watch::mask_owner(watch::stem(&file.name)).unwrap_or_default().to_owned();
    // A mask names its image: that image is the keyframe unless one was named more
    // strongly (`key.*`, the configuration), whatever the order the files landed in.
    let weaker = slot.key_source.is_none_or(|k| k > KeySource::Masked);
    let current_stem =
        slot.key_path.as_ref().and_then(|p| p.file_name()).and_then(|n| n.to_str()).map(watch::stem);
    if !owner.is_empty()
        && weaker
        && current_stem != Some(owner.as_str())
        && matches!(ctx.config.keyframe, KeyframeRule::First)
        && let Some(image_path) = image_of(ctx, &slot.dir, &owner)
        && let Ok((f, img)) = load(ctx, &image_path, Role::View)
    {
        tracing::info!(mask = %watch::shown(&file.name), key = %watch::shown(&f.name), "the mask names its image: it is the keyframe");
        // take_key finds and applies this mask.
        take_key(ctx, slot, &f, &image_path, &img, KeySource::Masked);
        return;
    }
    let Some(key_path) = &slot.key_path else {
        tracing::debug!(mask = %file.name, "mask waits for its keyframe");
        return;
    };
    let key_name = key_path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    let key_stem = watch::stem(key_name);
    if !owner.is_empty() && owner != key_stem {
        skip(
            ctx,
            slot,
            &slot.dir.join(&file.name),
            &format!("a mask for another image ({owner}) than the keyframe {key_name}"),
        );
        return;
    }
    if owner.is_empty() && has_own_mask(ctx, &slot.dir, key_stem) {
        tracing::info!(mask = %file.name, "ignored: the keyframe has a mask of its own");
        return;
    }
    apply_mask(ctx, slot, file, image);
}

fn apply_mask(ctx: &Ctx, slot: &mut Slot, file: &FileId, image: &DynamicImage) {
    let id = file.content_id(image);
    if slot.session.mask_id() == Some(id.as_str()) {
        return;
    }
    if slot.refused_mask.as_deref() == Some(id.as_str()) {
        tracing::debug!(mask = %watch::shown(&file.name), "refused already for this keyframe");
        return;
    }
    let mask = to_mask(image);
    let masked = mask.hole_count();
    let share = masked as f64 / mask.len().max(1) as f64;
    match slot.session.set_mask(id.clone(), mask) {
        Ok(again) => {
            slot.mask_source = Some(format!("file:{}", file.name));
            write_mask(ctx, slot);
            let mut fields = json!({ "mask": file.name, "file": file.name, "source": "file", "masked": masked, "share": share });
            // Masks that are probably mistakes say what will come of them.
            let warning = if masked == 0 {
                Some(
                    "the mask marks no pixel (all black): nothing to fill, the keyframe itself is the result",
                )
            } else if share >= 0.999 {
                Some(
                    "the mask covers the whole keyframe (all white): the result is made of the views alone, and what no view sees is invented",
                )
            } else {
                None
            };
            match warning {
                Some(w) => {
                    tracing::warn!(mask = %watch::shown(&file.name), masked, reason = w, "mask set");
                    fields["warning"] = w.into();
                }
                None => tracing::info!(mask = %watch::shown(&file.name), masked, "mask set"),
            }
            ctx.emitter.event("mask_set", Some(&slot.name), fields);
            let paths: Vec<PathBuf> = again.iter().filter_map(|i| slot.paths.get(i).cloned()).collect();
            for p in paths {
                reprocess(ctx, slot, &p);
            }
        }
        Err(e) => {
            skip(ctx, slot, &slot.dir.join(&file.name), &e.to_string());
            slot.refused_mask = Some(id);
        }
    }
}

/// The mask file `file` was deleted. If it was the session's mask, the session forgets
/// it: no new result until a mask arrives; the last result stays as it is.
fn mask_removed(ctx: &Ctx, slot: &mut Slot, file: &FileId) {
    let key_stem =
        slot.key_path.as_ref().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned());
    let current = slot.mask_source.as_deref() == Some(format!("file:{}", file.name).as_str());
    // A session rebuilt from disk since (put to sleep and woken) no longer has it.
    let was_its = key_stem.as_deref().is_some_and(|k| {
        let owner = watch::mask_owner(watch::stem(&file.name));
        slot.session.mask_id().is_none() && (owner == Some("") || owner == Some(watch::stem(k)))
    });
    if !current && !was_its {
        tracing::debug!(mask = %watch::shown(&file.name), "a mask that was not in use was deleted");
        return;
    }
    if current {
        slot.session.clear_mask();
        slot.mask_source = None;
    }
    let reason = "the mask file was deleted: no new result until a mask arrives; the last result is kept";
    tracing::warn!(file = %watch::shown(&file.name), reason, "mask removed");
    ctx.emitter.event("mask_removed", Some(&slot.name), json!({ "file": file.name, "reason": reason }));
    slot.waiting_said = false;
    // Another mask beside the keyframe (`mask.<ext>`) takes over.
    if let Some(k) = &key_stem
        && let Some(other) = find_mask(ctx, &slot.dir, k)
        && let Ok((f, img)) = load(ctx, &other, Role::Mask)
    {
        apply_mask(ctx, slot, &f, &img);
    }
}

/// With `mask = "auto"`: once enough views are accepted, the mask from their consensus.
fn auto_mask(ctx: &Ctx, slot: &mut Slot) {
    let MaskRule::Auto { views } = ctx.config.mask else { return };
    if slot.session.mask_id().is_some() || slot.session.key_id().is_none() {
        return;
    }
    let chosen: Vec<(String, PathBuf, crate::geometry::Homography)> = slot
        .session
        .buffered()
        .iter()
        .filter_map(|b| Some((b.id.clone(), slot.paths.get(&b.id)?.clone(), b.record.homography()?)))
        .take(views)
        .collect();
    if chosen.len() < views {
        return;
    }
    let mut images = Vec::new();
    for (_, path, h) in &chosen {
        let Ok((_, img)) = load(ctx, path, Role::View) else { return };
        images.push((to_rgb(&img), *h));
    }
    let Ok(mask) = slot.session.auto_mask(&images) else { return };
    drop(images);
    let masked = mask.hole_count();
    let id = format!("auto|{}", chosen.iter().map(|c| c.0.as_str()).collect::<Vec<_>>().join("|"));
    if let Ok(again) = slot.session.set_mask(id, mask) {
        slot.mask_source = Some("auto".into());
        write_mask(ctx, slot);
        tracing::info!(masked, views, "automatic mask set");
        ctx.emitter.event(
            "mask_set",
            Some(&slot.name),
            json!({ "source": "auto", "masked": masked, "views": views }),
        );
        let paths: Vec<PathBuf> = again.iter().filter_map(|i| slot.paths.get(i).cloned()).collect();
        for p in paths {
            reprocess(ctx, slot, &p);
        }
    }
}

/// The keyframe's metadata (EXIF, XMP, profile) its result carries, read again from its
/// file (headers only); none when it cannot be read.
fn key_metadata(ctx: &Ctx, slot: &Slot) -> Option<crate::imaging::meta::Metadata> {
    use std::io::Read;
    let mut bytes = Vec::new();
    Inbox::of(&ctx.config).open(slot.key_path.as_ref()?).ok()?.read_to_end(&mut bytes).ok()?;
    crate::imaging::decode::read_metadata(&bytes).ok()
}

/// Reads a file of the session's folder again, as it is now (see [`super::job::load`]).
fn load(ctx: &Ctx, path: &Path, role: Role) -> Result<(FileId, DynamicImage), DecodeOutcome> {
    let limits = DecodeLimits { max_pixels: ctx.config.max_pixels };
    super::job::load(path, role, &limits, &Inbox::of(&ctx.config))
}

fn skip(ctx: &Ctx, slot: &Slot, path: &Path, reason: &str) {
    ctx.stats.skipped.fetch_add(1, Ordering::Relaxed);
    tracing::warn!(file = %watch::shown_path(path), %reason, "file skipped");
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
    ctx.emitter.event(
        "file_skipped",
        Some(&slot.name),
        json!({ "file": name, "path": path.to_string_lossy(), "reason": reason }),
    );
}

/// Reads a view again from disk (after a keyframe or mask change) and offers it.
fn reprocess(ctx: &Ctx, slot: &mut Slot, path: &Path) {
    match load(ctx, path, Role::View) {
        Ok((file, img)) => process_view(ctx, slot, &file, path, &img),
        Err(DecodeOutcome::Gone(e)) => {
            tracing::debug!(file = %path.display(), error = %e, "gone before it could be read again");
        }
        // A change means the intake will bring the new version.
        Err(DecodeOutcome::Changed) => {}
        Err(e) => skip(ctx, slot, path, &e.reason()),
    }
}

fn rgb8(image: &DynamicImage) -> Rgb8 {
    let rgb = match image {
        DynamicImage::ImageRgb8(c) => std::borrow::Cow::Borrowed(c),
        other => std::borrow::Cow::Owned(other.to_rgb8()),
    };
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    Rgb8::from_vec(w, h, rgb.as_raw().chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect())
}

fn process_view(ctx: &Ctx, slot: &mut Slot, file: &FileId, path: &Path, image: &DynamicImage) {
    let span = tracing::info_span!("view", file = %watch::shown(&file.name));
    let _enter = span.enter();
    let id = file.content_id(image);
    let Some(key_id) = slot.session.key_id().map(str::to_owned) else { return };
    forget_old_content(ctx, slot, &file.name, Some(&id), "its file was replaced");
    let start = Instant::now();
    let (record, from_state) = match slot.state.alignment(&id, &key_id) {
        Some(r) => (r.clone(), true),
        None => match slot.session.align(to_luminance(image)) {
            Ok(r) => {
                slot.state.remember(id.clone(), key_id, r.clone());
                slot.state_dirty = true;
                (r, false)
            }
            Err(e) => return skip(ctx, slot, path, &e.to_string()),
        },
    };
    let align_ms = start.elapsed().as_secs_f64() * 1e3;
    let pixels = (record.accepted && slot.session.mask_id().is_some()).then(|| rgb8(image));
    let admission = match slot.session.admit(id.clone(), record.clone(), pixels.as_ref()) {
        Ok(a) => a,
        Err(e) => return skip(ctx, slot, path, &e.to_string()),
    };
    drop(pixels);
    ctx.stats.views.fetch_add(1, Ordering::Relaxed);
    slot.paths.insert(id.clone(), path.to_owned());
    slot.seq += 1;
    let common = json!({
        "file": file.name,
        "from_state": from_state,
        "from_prior": record.from_prior,
        "inliers": record.inliers,
        "matches": record.matches,
        "median_residual_px": record.median_residual_px,
        "homography": record.homography,
        "align_ms": (align_ms * 10.0).round() / 10.0,
    });
    let mut fields = common.as_object().cloned().unwrap_or_default();
    let mut entry = ViewEntry {
        id: id.clone(),
        status: "buffered",
        reason: None,
        record: Some(record.clone()),
        from_state,
        seq: slot.seq,
    };
    match &admission {
        Admission::Rejected { reason } => {
            ctx.registry.metrics.rejected(reason);
            entry.status = "rejected";
            entry.reason = Some(reason.clone());
            tracing::info!(%reason, from_state, "view rejected");
            fields.insert("reason".into(), reason.clone().into());
            ctx.emitter.event("view_rejected", Some(&slot.name), fields.into());
        }
        Admission::OutsideMask => {
            ctx.registry.metrics.views_accepted.fetch_add(1, Ordering::Relaxed);
            entry.status = "outside_mask";
            entry.reason = Some("sees none of the mask".into());
            tracing::info!(from_state, "view accepted, but it sees none of the mask");
            fields.insert("buffered".into(), false.into());
            fields.insert("reason".into(), "sees none of the mask".into());
            ctx.emitter.event("view_accepted", Some(&slot.name), fields.into());
        }
        Admission::Accepted { improves, fallback_px, weak_px, doubtful_px, dropped } => {
            tracing::info!(inliers = record.inliers, from_state, improves, "view accepted");
            ctx.registry.metrics.views_accepted.fetch_add(1, Ordering::Relaxed);
            slot.pending_since.get_or_insert(start);
            fields.insert("buffered".into(), true.into());
            fields.insert("improves".into(), (*improves).into());
            fields.insert("fallback_px".into(), (*fallback_px).into());
            fields.insert("weakly_witnessed_px".into(), (*weak_px).into());
            fields.insert("doubtful_px".into(), (*doubtful_px).into());
            ctx.emitter.event("view_accepted", Some(&slot.name), fields.into());
            for d in dropped {
                ctx.registry.metrics.views_dropped.fetch_add(1, Ordering::Relaxed);
                if let Some(v) = slot.views.values_mut().find(|v| &v.id == d) {
                    v.status = "dropped";
                    v.reason = Some("contributed least when the buffer was full".into());
                }
                let name = d.split('|').next().unwrap_or(d);
                tracing::info!(dropped = %watch::shown(name), "view dropped from the buffer");
                ctx.emitter.event(
                    "view_dropped",
                    Some(&slot.name),
                    json!({ "file": name, "reason": "contributed least when the buffer was full" }),
                );
            }
        }
    }
    slot.views.insert(file.name.clone(), entry);
    if slot.views.len() > MAX_LISTED
        && let Some(oldest) = slot.views.iter().min_by_key(|(_, v)| v.seq).map(|(k, _)| k.clone())
    {
        slot.views.remove(&oldest);
    }
    let buffered: std::collections::HashSet<&str> =
        slot.session.buffered().iter().map(|b| b.id.as_str()).collect();
    slot.paths.retain(|id, _| buffered.contains(id.as_str()));
    auto_mask(ctx, slot);
}

/// The file `name` now holds content `id` (`None`: nothing usable, `why` says): the pixels
/// buffered from what it held before leave the buffer, whatever becomes of the new
/// content (accepted, rejected, unreadable, deleted). A result must never be made of
/// pixels that no file holds any more.
fn forget_old_content(ctx: &Ctx, slot: &mut Slot, name: &str, id: Option<&str>, why: &str) {
    let Some(old) = slot.views.get(name).map(|v| v.id.clone()).filter(|old| Some(old.as_str()) != id) else {
        return;
    };
    slot.paths.remove(&old);
    if slot.session.forget_view(&old) {
        tracing::info!(file = %watch::shown(name), reason = why, "the view's old pixels leave the buffer");
        ctx.emitter.event(
            "view_dropped",
            Some(&slot.name),
            json!({ "file": name, "reason": format!("{why}: its old pixels are no longer used") }),
        );
    }
    if let Some(v) = slot.views.get_mut(name) {
        v.status = "dropped";
        v.reason = Some(why.to_owned());
    }
}

/// Times the fill's stages for the log, and tells the fill when the service stops.
struct Timings {
    current: Option<(Stage, Instant)>,
    done: Vec<(&'static str, f64)>,
    cancel: CancellationToken,
}

impl Timings {
    fn close(&mut self) {
        if let Some((s, t)) = self.current.take() {
            self.done.push((s.name(), t.elapsed().as_secs_f64() * 1e3));
        }
    }
}

impl Observer for Timings {
    fn stage(&mut self, stage: Stage) {
        self.close();
        self.current = Some((stage, Instant::now()));
    }

    fn cancelled(&self) -> bool {
        self.cancel.is_cancelled()
    }
}

/// Fills and writes a better result; returns its number when one was written.
pub(super) fn fill(ctx: &Ctx, slot: &mut Slot) -> Option<u64> {
    let digest = slot.session.inputs_digest();
    if slot.session.best_score().is_none()
        && let Some(saved) = &slot.state.result
        && saved.digest == digest
    {
        // Same inputs as the result already on disk (from before a restart).
        slot.session.assume_result(saved.score);
        tracing::info!(number = saved.number, "result unchanged since the last run: not rewritten");
        ctx.emitter.event(
            "result_unchanged",
            Some(&slot.name),
            json!({ "number": saved.number, "score": saved.score }),
        );
        return None;
    }
    if ctx.cancel.is_cancelled() {
        return None;
    }
    let start = Instant::now();
    let mut timings = Timings { current: None, done: Vec::new(), cancel: ctx.cancel.clone() };
    let Some(outcome) = slot.session.fill(&mut timings) else {
        if ctx.cancel.is_cancelled() {
            tracing::info!(
                fill_ms = start.elapsed().as_millis() as u64,
                "stopping: the fill in hand is given up, nothing written"
            );
        }
        return None;
    };
    timings.close();
    let fill_ms = start.elapsed().as_secs_f64() * 1e3;
    let stages: serde_json::Map<String, serde_json::Value> =
        timings.done.iter().map(|(n, ms)| ((*n).to_owned(), json!((ms * 10.0).round() / 10.0))).collect();
    tracing::debug!(fill_ms, ?timings.done, "fill done");
    let r = &outcome.report;
    let fallback_share = if r.masked == 0 { 0.0 } else { r.fallback as f64 / r.masked as f64 };
    if outcome.image.is_none() {
        tracing::info!(score = outcome.score, best = outcome.previous, "new fill scores lower: result kept");
        ctx.emitter.event(
            "result_not_better",
            Some(&slot.name),
            json!({ "score": outcome.score, "best": outcome.previous, "fill_ms": fill_ms.round() }),
        );
        ctx.registry.metrics.results_not_better.fetch_add(1, Ordering::Relaxed);
        slot.pending_since = None;
        return None;
    };
    let number = slot.state.last_number + 1;
    let report = result_json(ctx, slot, &outcome, number, fallback_share);
    if slot.pending.take().is_some() {
        tracing::info!(number, "a newer result replaces the one waiting to be written");
    }
    write(ctx, slot, Pending { outcome, report, number, digest, fill_ms, stages, retry: Backoff::default() })
}

/// Saves the session's state if it changed; a failure keeps it marked changed, to be tried
/// again (see [`Backoff`]).
pub(super) fn save_state(ctx: &Ctx, slot: &mut Slot) {
    if !slot.state_dirty || ctx.emitter.is_closed() {
        return;
    }
    if state::save(&ctx.config.state_dir, &slot.name, &slot.state) {
        slot.state_dirty = false;
        slot.state_retry = Backoff::default();
    } else {
        slot.state_retry.failed();
    }
}

/// A result that could not be written (full disk, read-only folder): kept in memory and
/// written again with a growing delay until it is, or until a newer result replaces it.
/// The files already on disk stay as they were meanwhile.
pub(super) struct Pending {
    outcome: crate::session::FillOutcome,
    report: serde_json::Value,
    number: u64,
    digest: u64,
    fill_ms: f64,
    stages: serde_json::Map<String, serde_json::Value>,
    retry: Backoff,
}

/// When to try again something that failed on the disk: 1 s, then twice as long each
/// time, at most 30 s.
#[derive(Debug, Default)]
pub(super) struct Backoff {
    failures: u32,
    next: Option<Instant>,
}

impl Backoff {
    const FIRST: Duration = Duration::from_secs(1);
    const MAX: Duration = Duration::from_secs(30);

    pub(super) fn due(&self) -> bool {
        self.next.is_none_or(|t| Instant::now() >= t)
    }

    /// Records a failure; returns the delay before the next try.
    pub(super) fn failed(&mut self) -> Duration {
        let delay = Self::FIRST.saturating_mul(1 << self.failures.min(5)).min(Self::MAX);
        self.failures += 1;
        self.next = Some(Instant::now() + delay);
        delay
    }

    pub(super) fn failures(&self) -> u32 {
        self.failures
    }
}

/// Writes the result waiting to be written, when its next try is due; returns its number
/// when it was written.
pub(super) fn retry_pending(ctx: &Ctx, slot: &mut Slot) -> Option<u64> {
    if !slot.pending.as_ref()?.retry.due() {
        return None;
    }
    let p = slot.pending.take()?;
    let span = tracing::info_span!("session", session = %watch::shown(&slot.name));
    let _enter = span.enter();
    tracing::info!(number = p.number, tries = p.retry.failures() + 1, "writing the result again");
    write(ctx, slot, p)
}

/// Writes a result; on failure keeps it as the slot's pending result.
fn write(ctx: &Ctx, slot: &mut Slot, mut p: Pending) -> Option<u64> {
    let number = p.number;
    let ext = ctx.emitter.result_name();
    let write_start = Instant::now();
    let image = p.outcome.image.as_ref().expect("a pending result has an image");
    let key = key_metadata(ctx, slot);
    match ctx.emitter.write_result(&slot.name, number, image, key.as_ref(), &mut p.report) {
        Ok(path) => {
            let write_ms = write_start.elapsed().as_secs_f64() * 1e3;
            let Pending { outcome, report, digest, fill_ms, stages, retry, .. } = p;
            let r = &outcome.report;
            let fallback_share = if r.masked == 0 { 0.0 } else { r.fallback as f64 / r.masked as f64 };
            slot.state.last_number = number;
            slot.state.result = Some(SavedResult { digest, score: outcome.score, number });
            slot.state_dirty = true;
            ctx.stats.results.fetch_add(1, Ordering::Relaxed);
            let (masked, views, score, previous) =
                (r.masked, outcome.views.len(), outcome.score, outcome.previous);
            after_result(ctx, slot, &outcome, number, report);
            tracing::info!(
                number,
                score,
                confident = r.confident_share(),
                fallback = fallback_share,
                fill_ms = fill_ms.round(),
                tries = retry.failures() + 1,
                "result updated"
            );
            ctx.emitter.event(
                "result_updated",
                Some(&slot.name),
                json!({
                    "number": number,
                    "path": path,
                    "result": ext,
                    "views": views,
                    "masked": masked,
                    "from_views": r.from_views(),
                    "from_fallback": fallback_share,
                    "confident": r.confident_share(),
                    "doubtful": r.doubtful_share(),
                    "score": score,
                    "previous_score": previous,
                    "fill_ms": fill_ms.round(),
                    "write_ms": write_ms.round(),
                    "stages_ms": stages,
                    "tries": retry.failures() + 1,
                }),
            );
            Some(number)
        }
        Err(e) => {
            let delay = p.retry.failed();
            tracing::error!(
                file = %e.path.display(),
                error = %e.source,
                number,
                retry_in_ms = delay.as_millis() as u64,
                "cannot write the result: the previous one stays, this one is tried again"
            );
            ctx.emitter.event(
                "result_failed",
                Some(&slot.name),
                json!({
                    "number": number,
                    "file": e.path,
                    "reason": e.source.to_string(),
                    "tries": p.retry.failures(),
                    "retry_in_ms": delay.as_millis() as u64,
                }),
            );
            slot.pending = Some(p);
            None
        }
    }
}

fn result_json(
    ctx: &Ctx,
    slot: &Slot,
    outcome: &crate::session::FillOutcome,
    number: u64,
    fallback_share: f64,
) -> serde_json::Value {
    let r = &outcome.report;
    let by_id: HashMap<&str, &crate::inpaint::SourceReport> =
        outcome.views.iter().map(String::as_str).zip(r.sources.iter()).collect();
    let mut views: Vec<&ViewEntry> = slot.views.values().filter(|v| v.status != "superseded").collect();
    views.sort_by_key(|v| v.seq);
    let views: Vec<serde_json::Value> = views
        .iter()
        .map(|v| {
            let name = v.id.split('|').next().unwrap_or(&v.id);
            let used = by_id.get(v.id.as_str());
            json!({
                "file": name,
                "status": if used.is_some() { "used" } else { v.status },
                "accepted": v.record.as_ref().is_some_and(|r| r.accepted),
                "reason": v.reason,
                "from_state": v.from_state,
                "homography": v.record.as_ref().and_then(|r| r.homography),
                "quality": v.record.as_ref().map(|r| json!({
                    "inliers": r.inliers,
                    "matches": r.matches,
                    "checked": r.checked,
                    "median_residual_px": r.median_residual_px,
                    "coverage": r.coverage,
                    "from_prior": r.from_prior,
                })),
                "covered": used.map(|s| s.covered),
                "filled": used.map(|s| s.filled),
                "gain": used.map(|s| s.gain),
                "offset": used.map(|s| s.offset),
            })
        })
        .collect();
    let key_name =
        slot.key_path.as_ref().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned());
    json!({
        "version": 1,
        "session": slot.name,
        "number": number,
        "time": rfc3339(SystemTime::now()),
        "result": ctx.emitter.result_name(),
        "keyframe": key_name,
        "mask": slot.mask_source,
        "masked": r.masked,
        "from_views": r.from_views(),
        "from_fallback": fallback_share,
        "fallback_px": r.fallback,
        "confident": r.confident_share(),
        "confident_px": r.confident,
        "doubtful": r.doubtful_share(),
        "confidence": "confidence.png",
        "score": outcome.score,
        "score_rule": "expected quality: the mean over the mask of the confidence that each pixel shows the building (confidence.png); a result is replaced only by one expected to be at least as good",
        "views": views,
    })
}

/// The numbers of the results in a session's `history/` folder, oldest first.
fn saved_history(dir: &Path) -> Vec<u64> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut n: Vec<u64> = entries
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.strip_prefix("result-")?.split('.').next()?.parse().ok())
        .collect();
    n.sort_unstable();
    n
}

/// The current mask as `mask.png` beside the results (for the status API and the page).
fn write_mask(ctx: &Ctx, slot: &Slot) {
    let Some(mask) = slot.session.mask() else { return };
    let dir = ctx.emitter.session_dir(&slot.name);
    let mut png = std::io::Cursor::new(Vec::new());
    let r = std::fs::create_dir_all(&dir)
        .and_then(|()| {
            crate::imaging::convert::mask_to_luma8(mask)
                .write_to(&mut png, image::ImageFormat::Png)
                .map_err(std::io::Error::other)
        })
        .and_then(|()| super::emit::atomic_write(&dir.join("mask.png"), png.get_ref()));
    if let Err(e) = r {
        tracing::warn!(error = %e, "cannot write mask.png");
    }
}

/// The result's confidence map as `confidence.png` beside it (8-bit, the keyframe's size,
/// 0 outside the mask, >= 128 where the fill is sure the pixel shows the building).
fn write_confidence(ctx: &Ctx, slot: &Slot, conf: &crate::inpaint::Confidence) {
    let path = ctx.emitter.session_dir(&slot.name).join("confidence.png");
    let mut png = std::io::Cursor::new(Vec::new());
    let r = crate::imaging::convert::mask_to_luma8(conf)
        .write_to(&mut png, image::ImageFormat::Png)
        .map_err(std::io::Error::other)
        .and_then(|()| super::emit::atomic_write(&path, png.get_ref()));
    if let Err(e) = r {
        tracing::warn!(error = %e, "cannot write confidence.png");
    }
}

/// After result `number` is written: its provenance map and legend, the bookkeeping of
/// the status API, and the update latency.
fn after_result(
    ctx: &Ctx,
    slot: &mut Slot,
    outcome: &crate::session::FillOutcome,
    number: u64,
    report: serde_json::Value,
) {
    let names: Vec<String> =
        outcome.views.iter().map(|id| id.split('|').next().unwrap_or(id).to_owned()).collect();
    slot.legend.clear();
    if let Some(map) = slot.session.provenance() {
        let path = ctx.emitter.session_dir(&slot.name).join("provenance.png");
        match super::provenance::render(&map, outcome.confidence.as_ref(), &names)
            .and_then(|(png, legend)| super::emit::atomic_write(&path, &png).map(|()| legend))
        {
            Ok(legend) => slot.legend = legend,
            Err(e) => tracing::warn!(error = %e, "cannot write provenance.png"),
        }
    }
    if let Some(conf) = &outcome.confidence {
        write_confidence(ctx, slot, conf);
    }
    slot.filled_by =
        outcome.views.iter().cloned().zip(outcome.report.sources.iter().map(|s| s.filled)).collect();
    slot.last_report = Some(report);
    slot.history.push(number);
    let keep = ctx.config.history;
    if slot.history.len() > keep {
        slot.history.drain(..slot.history.len() - keep);
    }
    let m = &ctx.registry.metrics;
    m.results_written.fetch_add(1, Ordering::Relaxed);
    if let Some(t) = slot.pending_since.take() {
        m.update_latency.observe(t.elapsed().as_secs_f64());
    }
}

/// Publishes the session's snapshot for the HTTP server.
fn publish(ctx: &Ctx, slot: &Slot, new_result: Option<u64>) {
    let mut views: Vec<&ViewEntry> = slot.views.values().filter(|v| v.status != "superseded").collect();
    views.sort_by_key(|v| v.seq);
    let views = views
        .into_iter()
        .map(|v| {
            let file = v.id.split('|').next().unwrap_or(&v.id).to_owned();
            let filled = slot.filled_by.get(&v.id).copied();
            let r = v.record.as_ref();
            ViewSnapshot {
                path: slot.dir.join(&file),
                file,
                status: if filled.is_some() && v.status == "buffered" { "used" } else { v.status }.to_owned(),
                accepted: r.is_some_and(|r| r.accepted),
                reason: v.reason.clone(),
                from_state: v.from_state,
                homography: r.and_then(|r| r.homography),
                inliers: r.map_or(0, |r| r.inliers),
                matches: r.map_or(0, |r| r.matches),
                median_residual_px: r.and_then(|r| r.median_residual_px),
                coverage: r.map_or(0.0, |r| r.coverage),
                filled,
            }
        })
        .collect();
    let coverage =
        slot.last_report.as_ref().and_then(|r| r.get("from_views")).and_then(serde_json::Value::as_f64);
    ctx.registry.publish(
        SessionSnapshot {
            id: slot.name.clone(),
            keyframe: slot
                .key_path
                .as_ref()
                .and_then(|p| p.file_name())
                .map(|n| n.to_string_lossy().into_owned()),
            key_size: slot.session.key_size(),
            mask: slot.mask_source.clone(),
            masked_px: slot.session.mask().map(crate::imaging::Mask::hole_count),
            views,
            result: slot.last_report.clone(),
            coverage,
            legend: slot.legend.clone(),
            history: slot.history.clone(),
            revision: 0,
            updated: rfc3339(SystemTime::now()),
            key_path: slot.key_path.clone(),
            inbox_dir: slot.dir.clone(),
        },
        new_result,
    );
}
