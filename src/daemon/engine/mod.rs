//! The session engine (shell layer): one [`Slot`] per session, owning everything that
//! happens to a session once a source has decided what a file or a frame *is*.
//!
//! ```text
//!  folder source (worker.rs, folder.rs)  ─┐   set_key / set_mask / admit    ┌─► events.jsonl (event.rs)
//!  video source (video/runner.rs)        ─┼─► Slot (this module) ─ fill ────┼─► result.<ext>, history/, result.json
//!  (later: scale-out workers)            ─┘   one typed outcome per step    └─► registry (HTTP), state/
//! ```
//!
//! Tracing a photo from landing to result:
//! 1. [`super::watch`] notices the path; [`super::intake`] waits for it to settle, decodes
//!    it ([`super::job::read_and_decode`]) and queues a [`super::job::Job`] to the worker
//!    that owns its session.
//! 2. [`super::worker`] wakes the session if it slept and hands the job to
//!    [`super::folder`], which applies the session's policy ([`super::policy`]: is it the
//!    keyframe, a mask, a view?) and calls the engine: [`Slot::set_key`], [`Slot::set_mask`],
//!    or aligns the view and calls [`Slot::admit`] ([`admit`]).
//! 3. The worker asks [`Slot::fill`] ([`publish`]) when no more files of the session are
//!    waiting; a better result is written by [`publish::write_result`] (image, history,
//!    `result.json`, provenance, confidence), and [`Slot::publish`] gives the HTTP server a
//!    new snapshot.
//!
//! A video frame takes the same path from step 2 on: [`super::video`]'s runner aligns it
//! against its keyframe and calls [`Slot::admit`] and [`Slot::fill`].
//!
//! The engine never decides what a file is and never reads the watched folder (only the
//! keyframe's metadata, for the result); sources never touch a slot's report, listing,
//! buffer bookkeeping or result writing.

mod admit;
pub(crate) mod publish;

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use image::DynamicImage;
use serde::Serialize;
use tokio_util::sync::CancellationToken;

use super::emit::Emitter;
use super::event::{Event, KeyframeSet, MaskSet};
use super::job::ViewId;
use super::policy::KeySource;
use super::registry::{LegendEntry, Registry};
use super::state::{self, SessionState};
use super::watch;
use super::{Backlog, Stats};
use crate::config::Config;
use crate::imaging::Mask;
use crate::imaging::convert::to_rgb;
use crate::session::{AlignRecord, Rgb8, Session};

pub(crate) use admit::{Admitted, Offer};

/// What the engine needs of the service: configuration, the stop signal and the shared
/// sinks. One per worker thread or video source.
pub(crate) struct Ctx {
    pub(crate) config: Arc<Config>,
    /// Cancelled when the service stops: long steps (a fill) give up and write nothing.
    pub(crate) cancel: CancellationToken,
    pub(crate) emitter: Arc<Emitter>,
    pub(crate) backlog: Arc<Backlog>,
    pub(crate) stats: Arc<Stats>,
    pub(crate) registry: Arc<Registry>,
}

#[cfg(test)]
impl Ctx {
    /// A context over `config` (its out folder made), for the shell's unit tests.
    pub(crate) fn for_test(config: Config) -> Self {
        std::fs::create_dir_all(&config.out_dir).unwrap();
        let config = Arc::new(config);
        Self {
            emitter: Arc::new(Emitter::open(&config).unwrap()),
            config,
            cancel: CancellationToken::new(),
            backlog: Arc::default(),
            stats: Arc::default(),
            registry: Arc::default(),
        }
    }
}

/// Where a view stands, as `result.json` and the status API list it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum ViewStatus {
    /// In the buffer, waiting for (or part of) a fill.
    Buffered,
    /// Filled some of the current result (reported only; never stored).
    Used,
    Rejected,
    /// Aligned, but sees none of the mask.
    OutsideMask,
    /// Left the buffer (it contributed least, or its file changed).
    Dropped,
    /// Aligned against a keyframe that is no longer the session's.
    Superseded,
}

impl ViewStatus {
    pub(crate) fn as_str(self) -> &'static str {
        match self {
            Self::Buffered => "buffered",
            Self::Used => "used",
            Self::Rejected => "rejected",
            Self::OutsideMask => "outside_mask",
            Self::Dropped => "dropped",
            Self::Superseded => "superseded",
        }
    }
}

/// A view as the result report lists it.
#[derive(Debug, Clone)]
struct ViewEntry {
    id: ViewId,
    status: ViewStatus,
    reason: Option<String>,
    record: Option<AlignRecord>,
    from_state: bool,
    seq: u64,
}

/// Views listed in a session's report at most (the oldest go first).
const MAX_LISTED: usize = 1000;

/// Where a mask comes from.
pub(crate) enum MaskOrigin<'a> {
    /// A file (its name; a video's: its configured path).
    File(&'a str),
    /// Made from the consensus of this many views.
    Auto(usize),
}

/// One session: the core [`Session`] (keyframe, mask, buffer), its saved state, and what
/// the engine reports of it.
pub(crate) struct Slot {
    pub(crate) name: String,
    /// The session's folder in the inbox (empty for a video).
    pub(crate) dir: PathBuf,
    pub(crate) session: Session,
    pub(crate) state: SessionState,
    pub(crate) key_path: Option<PathBuf>,
    /// Why the keyframe is the keyframe; `None` before there is one.
    pub(crate) key_source: Option<KeySource>,
    /// A keyframe without a mask was reported waiting (`session_waiting`), once.
    pub(crate) waiting_said: bool,
    mask_source: Option<String>,
    /// How many views the current automatic mask was found from (0: none, or the mask is
    /// a file's).
    pub(crate) auto_views: usize,
    /// The mask (its content id) refused for the current keyframe: reported once, though
    /// it is read both beside the keyframe and as a file of its own.
    pub(crate) refused_mask: Option<String>,
    /// Views waiting for their keyframe, by file name.
    pub(crate) parked: BTreeMap<String, PathBuf>,
    /// Where each buffered view's file is (to re-read it).
    pub(crate) paths: HashMap<String, PathBuf>,
    views: BTreeMap<String, ViewEntry>,
    /// Ids of the views decided (admitted, rejected, seeing none of the mask) against the
    /// current keyframe and mask: offered again, they are not taken twice.
    decided: HashSet<String>,
    seq: u64,
    pub(crate) state_dirty: bool,
    /// A result that could not be written yet.
    pending: Option<publish::Pending>,
    /// When to try again to save a state that could not be saved.
    state_retry: Backoff,
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
    pub(crate) fn new(ctx: &Ctx, name: &str, dir: PathBuf) -> Self {
        let out = ctx.emitter.session_dir(name);
        let history = publish::saved_history(&out.join("history"));
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
            auto_views: 0,
            refused_mask: None,
            parked: BTreeMap::new(),
            paths: HashMap::new(),
            views: BTreeMap::new(),
            decided: HashSet::new(),
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

    /// The keyframe's file (or frame) name.
    pub(crate) fn key_name(&self) -> Option<String> {
        self.key_path.as_ref().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned())
    }

    /// Whether view `id` was decided against the current keyframe and mask.
    pub(crate) fn decided(&self, id: &ViewId) -> bool {
        self.decided.contains(id.as_str())
    }

    /// What a view's alignment depends on, as its saved alignment is keyed: the keyframe,
    /// and the mask when it came from a file (the keyframe's corners under it are not
    /// matched, so a view aligned before the mask arrived is aligned again once it has).
    /// An automatic mask is made from the views' own alignments, so it is not part of it.
    pub(crate) fn alignment_basis(&self) -> Option<String> {
        let key = self.session.key_id()?;
        match (self.session.mask_id(), self.mask_source.as_deref()) {
            (Some(mask), Some(source)) if source.starts_with("file:") => Some(format!("{key}|mask|{mask}")),
            _ => Some(key.to_owned()),
        }
    }

    /// The views accepted against the current keyframe and still held (buffered, or seeing
    /// none of the mask), in the order they came: their ids and keyframe → view homographies.
    pub(crate) fn accepted_views(&self) -> Vec<(ViewId, crate::geometry::Homography)> {
        let mut held: Vec<&ViewEntry> = self
            .views
            .values()
            .filter(|v| matches!(v.status, ViewStatus::Buffered | ViewStatus::OutsideMask))
            .collect();
        held.sort_by_key(|v| v.seq);
        held.iter()
            .filter_map(|v| Some((v.id.clone(), v.record.as_ref().filter(|r| r.accepted)?.homography()?)))
            .collect()
    }

    /// The current mask came from file `name`.
    pub(crate) fn mask_is_file(&self, name: &str) -> bool {
        self.mask_source.as_deref().and_then(|s| s.strip_prefix("file:")) == Some(name)
    }

    /// Whether the session has something that would stop it being put to sleep.
    pub(crate) fn busy(&self) -> bool {
        self.session.needs_fill() || !self.parked.is_empty() || self.pending.is_some() || self.state_dirty
    }

    /// The number of a result that could not be written yet.
    pub(crate) fn unwritten(&self) -> Option<u64> {
        self.pending.as_ref().map(|p| p.number)
    }

    /// Names of the listed views that were refused against the current keyframe (rejected,
    /// or seeing none of its mask): a new keyframe may take them.
    pub(crate) fn refused_views(&self) -> Vec<String> {
        self.views
            .iter()
            .filter(|(_, v)| matches!(v.status, ViewStatus::Rejected | ViewStatus::OutsideMask))
            .map(|(name, _)| name.clone())
            .collect()
    }

    /// Makes `image` (view `id`, file or frame `name` at `path`) the keyframe, for
    /// `source`'s reason; `frame` is a video frame's index, time and input. Every listed
    /// view is superseded and the mask forgotten; says `session_started` (the first) or
    /// `keyframe_changed`. Returns the paths of the buffered views to align again.
    pub(crate) fn set_key(
        &mut self,
        ctx: &Ctx,
        id: ViewId,
        path: PathBuf,
        image: &DynamicImage,
        source: KeySource,
        frame: Option<(u64, f64, &str)>,
    ) -> Vec<PathBuf> {
        let first = self.session.key_id().is_none();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let again: Vec<PathBuf> = self
            .session
            .set_key(id.into(), to_rgb(image))
            .iter()
            .filter_map(|i| self.paths.get(i).cloned())
            .collect();
        self.key_path = Some(path);
        self.key_source = Some(source);
        self.decided.clear();
        self.waiting_said = false;
        self.mask_source = None;
        self.auto_views = 0;
        self.refused_mask = None;
        self.paths.clear();
        for v in self.views.values_mut() {
            v.status = ViewStatus::Superseded;
        }
        let set = KeyframeSet {
            keyframe: name,
            width: image.width(),
            height: image.height(),
            key_source: source.as_str(),
            frame: frame.map(|f| f.0),
            t: frame.map(|f| f.1),
            input: frame.map(|f| f.2.to_owned()),
        };
        let event = if first { Event::SessionStarted(set) } else { Event::KeyframeChanged(set) };
        ctx.emitter.emit(Some(&self.name), &event);
        again
    }

    /// Makes `mask` (content `id`, from `origin`) the keyframe's mask; says `mask_set`
    /// (with a warning when it is probably a mistake) and writes `mask.png` beside the
    /// results. Returns the paths of the buffered views to admit again, or why the mask
    /// does not fit the keyframe.
    pub(crate) fn set_mask(
        &mut self,
        ctx: &Ctx,
        id: String,
        mask: Mask,
        origin: MaskOrigin,
    ) -> Result<Vec<PathBuf>, String> {
        let masked = mask.hole_count();
        let share = masked as f64 / mask.len().max(1) as f64;
        // Masks that are probably mistakes say what will come of them.
        let warning = match origin {
            MaskOrigin::File(_) => mask.mistake().or_else(|| mask.inverted()),
            MaskOrigin::Auto(_) => mask.mistake(),
        };
        let again = self.session.set_mask(id, mask).map_err(|e| e.to_string())?;
        self.decided.clear();
        let (file, views) = match origin {
            MaskOrigin::File(f) => (Some(f.to_owned()), None),
            MaskOrigin::Auto(n) => (None, Some(n)),
        };
        self.auto_views = views.unwrap_or(0);
        self.mask_source = Some(file.as_ref().map_or_else(|| "auto".to_owned(), |f| format!("file:{f}")));
        publish::write_mask(ctx, self);
        let shown = file.as_deref().map_or("auto".into(), watch::shown);
        match warning {
            Some(w) => tracing::warn!(mask = %shown, masked, reason = w, "mask set"),
            None => tracing::info!(mask = %shown, masked, "mask set"),
        }
        let source = if file.is_some() { "file" } else { "auto" };
        let set = MaskSet { mask: file.clone(), file, source, masked, share, views, warning };
        ctx.emitter.emit(Some(&self.name), &Event::MaskSet(set));
        Ok(again.iter().filter_map(|i| self.paths.get(i).cloned()).collect())
    }

    /// Forgets the mask taken from file `name` (deleted); says `mask_removed`.
    pub(crate) fn clear_mask(&mut self, ctx: &Ctx, name: &str, in_use: bool) {
        if in_use {
            self.session.clear_mask();
            self.mask_source = None;
            self.auto_views = 0;
            self.decided.clear();
        }
        let reason = "the mask file was deleted: no new result until a mask arrives; the last result is kept";
        tracing::warn!(file = %watch::shown(name), reason, "mask removed");
        ctx.emitter
            .emit(Some(&self.name), &Event::MaskRemoved { file: name.to_owned(), reason: reason.into() });
        self.waiting_said = false;
    }

    /// Saves the session's state if it changed; a failure keeps it marked changed, to be
    /// tried again (see [`Backoff`]).
    pub(crate) fn save_state(&mut self, ctx: &Ctx) {
        if !self.state_dirty || ctx.emitter.is_closed() {
            return;
        }
        if state::save(&ctx.config.state_dir, &self.name, &self.state) {
            self.state_dirty = false;
            self.state_retry = Backoff::default();
        } else {
            self.state_retry.failed();
        }
    }

    /// Saves a state that could not be saved earlier, when its next try is due.
    pub(crate) fn save_state_if_due(&mut self, ctx: &Ctx) {
        if self.state_dirty && self.state_retry.due() {
            self.save_state(ctx);
        }
    }
}

/// 8-bit RGB pixels of a decoded image, as the core buffers them.
pub(crate) fn rgb8(image: &DynamicImage) -> Rgb8 {
    let whole = crate::imaging::Rect::full(image.width() as usize, image.height() as usize);
    crate::imaging::convert::crop_rgb8(image, whole)
}

/// When to try again something that failed on the disk: 1 s, then twice as long each
/// time, at most 30 s.
#[derive(Debug, Default)]
pub(crate) struct Backoff {
    failures: u32,
    next: Option<Instant>,
}

impl Backoff {
    const FIRST: Duration = Duration::from_secs(1);
    const MAX: Duration = Duration::from_secs(30);

    pub(crate) fn due(&self) -> bool {
        self.next.is_none_or(|t| Instant::now() >= t)
    }

    /// Records a failure; returns the delay before the next try.
    pub(crate) fn failed(&mut self) -> Duration {
        let delay = Self::FIRST.saturating_mul(1 << self.failures.min(5)).min(Self::MAX);
        self.failures += 1;
        self.next = Some(Instant::now() + delay);
        delay
    }

    pub(crate) fn failures(&self) -> u32 {
        self.failures
    }
}
