//! `clearview worker` (shell layer): stateless compute of the NATS scale-out. Pulls one
//! work message at a time from the durable consumer, takes the session's lease, brings
//! its scratch copy of the session up to the session's record (rebuilding it from the
//! object store when another worker touched it since), applies the listing entries not
//! yet applied, fills, publishes the result and the step's events, saves the record, acks
//! (see [`super`] for the whole design). The engine and the folder source run unchanged on
//! the scratch copy.
//!
//! The engine is synchronous and CPU-bound: it runs on the thread that drives this
//! future (the runtime's `block_on` thread, not one of its workers), so the tasks that
//! keep the lease and the message alive (renewals, in-progress acks) go on meanwhile on
//! the runtime's threads.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use async_nats::jetstream::{self, AckKind, consumer::pull};
use tokio_stream::StreamExt;
use tokio_util::sync::CancellationToken;

use super::{
    ClusterError, Context, DEAD_PREFIX, DeadLetter, EVENTS_PREFIX, Entry, FileMsg, IN_PREFIX, NO_SESSION,
    Nats, OUT_PREFIX, OpError, Record, ResultMsg, ResultRef, SessionMsg,
};
use crate::config::Config;
use crate::daemon::engine::publish::FillStep;
use crate::daemon::engine::{Ctx, Slot};
use crate::daemon::event::{Event, FileSkipped};
use crate::daemon::job::FileId;
use crate::daemon::provenance::SURFACES;
use crate::daemon::{Backlog, Stats, emit, folder, state, watch};

/// What `clearview worker` is told beyond the configuration.
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    /// This worker's name in leases and records (unique in the cluster).
    pub id: String,
    /// Its scratch folder (a cache: emptied at start).
    pub scratch: PathBuf,
    /// Serve `/metrics` here.
    pub metrics: Option<SocketAddr>,
}

/// Stages whose time `/metrics` reports.
const STAGES: [&str; 5] = ["fetch", "rebuild", "apply", "fill", "publish"];

/// The worker's counters for `/metrics`.
#[derive(Debug, Default)]
pub struct Metrics {
    messages: AtomicU64,
    redelivered: AtomicU64,
    lease_busy: AtomicU64,
    /// Messages put back because the listing read did not have their file yet.
    behind: AtomicU64,
    takeovers: AtomicU64,
    rebuilds: AtomicU64,
    entries: AtomicU64,
    results: AtomicU64,
    replays: AtomicU64,
    failures: AtomicU64,
    dead_letters: AtomicU64,
    /// Messages the consumer has not delivered yet, and delivered but not acknowledged.
    pending: AtomicU64,
    ack_pending: AtomicU64,
    stage_ms: [AtomicU64; 5],
    stage_n: [AtomicU64; 5],
}

impl Metrics {
    fn stage(&self, i: usize, since: Instant) {
        self.stage_ms[i].fetch_add(since.elapsed().as_millis() as u64, Ordering::Relaxed);
        self.stage_n[i].fetch_add(1, Ordering::Relaxed);
    }

    /// Prometheus text.
    pub fn render(&self, id: &str) -> String {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let mut s = String::new();
        let mut counter = |name: &str, help: &str, kind: &str, v: u64| {
            s.push_str(&format!(
                "# HELP clearview_worker_{name} {help}\n# TYPE clearview_worker_{name} {kind}\nclearview_worker_{name}{{worker=\"{id}\"}} {v}\n"
            ));
        };
        counter("messages_total", "work messages received", "counter", l(&self.messages));
        counter("redeliveries_total", "messages received more than once", "counter", l(&self.redelivered));
        counter(
            "lease_busy_total",
            "messages put back: another worker held the session",
            "counter",
            l(&self.lease_busy),
        );
        counter(
            "listing_behind_total",
            "messages put back: the session's listing as read did not have their file yet",
            "counter",
            l(&self.behind),
        );
        counter(
            "lease_takeovers_total",
            "sessions taken over from another worker",
            "counter",
            l(&self.takeovers),
        );
        counter("rebuilds_total", "sessions rebuilt from the object store", "counter", l(&self.rebuilds));
        counter("entries_applied_total", "listing entries applied", "counter", l(&self.entries));
        counter("results_total", "results published", "counter", l(&self.results));
        counter(
            "replays_total",
            "results made again from the same inputs: nothing uploaded",
            "counter",
            l(&self.replays),
        );
        counter(
            "step_failures_total",
            "steps that failed (the message was put back)",
            "counter",
            l(&self.failures),
        );
        counter("dead_letters_total", "poison messages dead-lettered", "counter", l(&self.dead_letters));
        counter(
            "queue_lag_messages",
            "work messages not yet delivered (consumer)",
            "gauge",
            l(&self.pending),
        );
        counter(
            "ack_pending_messages",
            "work messages delivered, not yet acknowledged",
            "gauge",
            l(&self.ack_pending),
        );
        s.push_str("# HELP clearview_worker_stage_seconds_total time spent per stage\n# TYPE clearview_worker_stage_seconds_total counter\n");
        for (i, name) in STAGES.iter().enumerate() {
            s.push_str(&format!(
                "clearview_worker_stage_seconds_total{{worker=\"{id}\",stage=\"{name}\"}} {:.3}\n",
                l(&self.stage_ms[i]) as f64 / 1e3
            ));
        }
        s.push_str("# HELP clearview_worker_stage_runs_total runs per stage\n# TYPE clearview_worker_stage_runs_total counter\n");
        for (i, name) in STAGES.iter().enumerate() {
            s.push_str(&format!(
                "clearview_worker_stage_runs_total{{worker=\"{id}\",stage=\"{name}\"}} {}\n",
                l(&self.stage_n[i])
            ));
        }
        s
    }
}

/// A session this worker has a copy of, and the record revision the copy is at.
struct Local {
    slot: Slot,
    revision: u64,
    used: Instant,
}

/// Events of the step in hand, published after its result.
type Said = Arc<Mutex<Vec<(Option<String>, String)>>>;

struct Worker {
    nats: Arc<Nats>,
    ctx: Ctx,
    id: String,
    local: HashMap<String, Local>,
    said: Said,
    /// While a session is rebuilt, what it says again is not said.
    muted: Arc<AtomicBool>,
    metrics: Arc<Metrics>,
}

/// Why a step did not finish.
enum StepError {
    /// The service is stopping: the message goes back, nothing half-done is saved.
    Stopping,
    /// Another worker saved the session meanwhile (this one's lease lapsed).
    TakenOver,
    /// The session's listing, as read, does not have the message's file: a server
    /// answered from behind (ingest lists a file before it sends its message).
    /// Acknowledging would lose the file: the message comes again.
    Behind,
    Failed(OpError),
}

/// The longest wait, in seconds, before a message whose step failed comes again.
const RETRY_CAP_S: i64 = 30;

/// How long a message delivered `delivered` times waits before it comes again after a
/// failure: longer each time, up to [`RETRY_CAP_S`].
fn retry_delay(delivered: i64) -> Duration {
    Duration::from_secs(delivered.clamp(1, RETRY_CAP_S) as u64)
}

/// How long a message delivered `delivered` times waits before it comes again when it
/// could not be handled yet (the session leased by another worker, its listing read from
/// behind): a quarter second more each time, up to 5 s.
fn put_back_delay(delivered: i64) -> Duration {
    Duration::from_millis(250 * delivered.clamp(1, 20) as u64)
}

impl From<OpError> for StepError {
    fn from(e: OpError) -> Self {
        Self::Failed(e)
    }
}

/// Runs a worker until `shutdown`; the step in hand is finished or given back.
pub async fn run(
    mut config: Config,
    opts: WorkerOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ClusterError> {
    let scratch = &opts.scratch;
    // A cache: whatever an earlier run left is stale.
    let _ = std::fs::remove_dir_all(scratch);
    config.watch_dir = scratch.join("inbox");
    config.out_dir = scratch.join("out");
    config.state_dir = scratch.join("state");
    for dir in [config.watch_dir.clone(), config.out_dir.clone(), state::sessions_dir(&config.state_dir)] {
        std::fs::create_dir_all(&dir).map_err(|source| ClusterError::Io { path: dir.clone(), source })?;
    }
    config.watch_dir = std::fs::canonicalize(&config.watch_dir).unwrap_or(config.watch_dir);
    let nats = Arc::new(Nats::connect(&config.nats, &format!("clearview-worker {}", opts.id)).await?);
    let cancel = CancellationToken::new();
    {
        let cancel = cancel.clone();
        tokio::spawn(async move {
            shutdown.await;
            tracing::info!("shutdown requested: finishing the step in hand");
            cancel.cancel();
        });
    }
    let said: Said = Arc::default();
    let muted = Arc::new(AtomicBool::new(false));
    let tee: emit::Tee = {
        let (said, muted) = (said.clone(), muted.clone());
        Arc::new(move |session: Option<&str>, line: &str| {
            if !muted.load(Ordering::Relaxed) {
                said.lock().expect("events lock").push((session.map(str::to_owned), line.to_owned()));
            }
        })
    };
    let config = Arc::new(config);
    let emitter = Arc::new(emit::Emitter::open(&config)?.with_tee(tee));
    let ctx = Ctx {
        config: config.clone(),
        cancel: cancel.clone(),
        emitter,
        backlog: Arc::new(Backlog::default()),
        stats: Arc::new(Stats::default()),
        registry: Arc::default(),
    };
    let consumer = super::settled("the workers' consumer", || consumer(&nats)).await?;
    let metrics = Arc::new(Metrics::default());
    if let Some(addr) = opts.metrics {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|source| crate::daemon::DaemonError::Http { addr, source })?;
        let addr = listener.local_addr().unwrap_or(addr);
        println!("clearview: worker metrics at http://{addr}/metrics");
        tokio::spawn(serve_metrics(listener, metrics.clone(), opts.id.clone()));
        tokio::spawn(watch_lag(consumer.clone(), metrics.clone()));
    }
    tracing::info!(worker = %opts.id, servers = %config.nats.servers.join(","), "worker started");
    crate::daemon::systemd::ready();
    let mut w = Worker { nats, ctx, id: opts.id.clone(), local: HashMap::new(), said, muted, metrics };
    while !cancel.is_cancelled() {
        let fetched = tokio::select! {
            () = cancel.cancelled() => break,
            f = consumer.fetch().max_messages(1).expires(Duration::from_secs(1)).messages() => f,
        };
        let mut batch = match fetched {
            Ok(b) => b,
            Err(e) => {
                tracing::warn!(error = %e, "cannot fetch work: trying again");
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
        };
        while let Some(next) = batch.next().await {
            match next {
                Ok(msg) => w.handle(msg).await,
                Err(e) => tracing::debug!(error = %e, "fetch ended"),
            }
        }
    }
    crate::daemon::systemd::stopping();
    tracing::info!("worker stopped");
    Ok(())
}

/// The workers' durable pull consumer (made if missing). Redeliveries are not limited by
/// the server: the worker dead-letters a message whose step failed `max_deliver` times,
/// with the reason (see [`Worker::handle`]).
async fn consumer(nats: &Nats) -> Result<jetstream::consumer::Consumer<pull::Config>, ClusterError> {
    let c = &nats.config;
    let setup = |e: &dyn std::fmt::Display| ClusterError::Setup {
        what: format!("consumer {} on {}", c.consumer, c.stream),
        reason: e.to_string(),
    };
    let stream = nats.js.get_stream(&c.stream).await.map_err(|e| setup(&e))?;
    stream
        .get_or_create_consumer(
            &c.consumer,
            pull::Config {
                durable_name: Some(c.consumer.clone()),
                ack_policy: jetstream::consumer::AckPolicy::Explicit,
                ack_wait: c.ack_wait,
                max_deliver: -1,
                filter_subject: format!("{IN_PREFIX}.>"),
                max_ack_pending: 10_000,
                num_replicas: c.replicas,
                ..Default::default()
            },
        )
        .await
        .map_err(|e| setup(&e))
}

impl Worker {
    /// One work message: lease, step, ack (or NAK, or dead letter).
    async fn handle(&mut self, msg: jetstream::Message) {
        let m = &self.metrics;
        m.messages.fetch_add(1, Ordering::Relaxed);
        let (delivered, seq) = msg.info().map_or((1, 0), |i| (i.delivered, i.stream_sequence));
        if delivered > 1 {
            m.redelivered.fetch_add(1, Ordering::Relaxed);
        }
        let subject = msg.subject.to_string();
        let parsed: Result<FileMsg, OpError> =
            serde_json::from_slice(&msg.payload).lasting("malformed message");
        let file = match parsed.and_then(|f| check_names(&f).map(|()| f)) {
            Ok(f) => f,
            Err(e) => return self.dead_letter(&msg, None, None, delivered, seq, &e.reason).await,
        };
        let session = file.session.clone();
        let tok = super::token(&session);
        // A message delivered far more often than poison allows never finished a step:
        // it kills the worker that takes it (or it waited out many leases). The cluster
        // failing meanwhile takes `max_deliver` × 10 NAKs, later each time up to
        // RETRY_CAP_S apart: 50 take some 18 minutes.
        let limit = self.nats.config.max_deliver;
        if delivered > limit.saturating_mul(10) {
            let reason = format!("delivered {delivered} times without finishing a step");
            return self
                .dead_letter(&msg, Some(&session), Some(&file.entry.name), delivered, seq, &reason)
                .await;
        }
        let lease = match Lease::take(&self.nats, &tok, &self.id).await {
            Ok(Some(l)) => l,
            Ok(None) => {
                m.lease_busy.fetch_add(1, Ordering::Relaxed);
                let delay = put_back_delay(delivered);
                tracing::debug!(session = %watch::shown(&session), delay_ms = delay.as_millis() as u64, "session leased by another worker: later");
                let _ = msg.ack_with(AckKind::Nak(Some(delay))).await;
                return;
            }
            Err(e) => {
                tracing::warn!(session = %watch::shown(&session), error = %e, "cannot take the lease: later");
                let _ = msg.ack_with(AckKind::Nak(Some(retry_delay(delivered)))).await;
                return;
            }
        };
        let (msg, acker) = msg.split();
        let acker = Arc::new(acker);
        let keeper = lease.keep(&self.nats, acker.clone());
        let span = tracing::info_span!("session", session = %watch::shown(&session));
        let outcome = {
            let _enter = span.enter();
            self.step(&session, &tok, &file.entry).await
        };
        keeper.abort();
        let lost = lease.lost.load(Ordering::Relaxed);
        lease.release(&self.nats).await;
        if outcome.is_err() {
            // What a step that saved no record said is not said (its views accepted, its
            // result numbered): none of it was committed, and the step is done again.
            self.said.lock().expect("events lock").clear();
        }
        match outcome {
            Ok(()) => {
                if let Err(e) = acker.ack().await {
                    tracing::warn!(error = %e, "cannot acknowledge (the message will come again: a no-op)");
                }
            }
            Err(StepError::Stopping) => {
                let _ = acker.ack_with(AckKind::Nak(None)).await;
            }
            Err(StepError::TakenOver) => {
                tracing::warn!(
                    lease_lost = lost,
                    "another worker saved the session meanwhile: its copy here is dropped"
                );
                self.local.remove(&session);
                let _ = acker.ack_with(AckKind::Nak(Some(Duration::from_millis(500)))).await;
            }
            Err(StepError::Behind) => {
                self.metrics.behind.fetch_add(1, Ordering::Relaxed);
                let delay = put_back_delay(delivered);
                tracing::info!(file = %file.entry.name, delay_ms = delay.as_millis() as u64, "the session's listing as read does not have the file yet: later");
                let _ = acker.ack_with(AckKind::Nak(Some(delay))).await;
            }
            Err(StepError::Failed(e)) => {
                self.metrics.failures.fetch_add(1, Ordering::Relaxed);
                self.local.remove(&session);
                if e.lasting && delivered >= limit {
                    let name = file.entry.name.as_str();
                    self.send_dead(
                        &subject,
                        &msg.payload,
                        Some(&session),
                        Some(name),
                        delivered,
                        seq,
                        &e.reason,
                    )
                    .await;
                    let _ = acker.ack_with(AckKind::Term).await;
                } else {
                    // A failure of the cluster (a server died, no leader yet) is not the
                    // message's: it comes again, later each time, and is never poison.
                    tracing::warn!(error = %e, lasting = e.lasting, delivered, "step failed: the message comes again");
                    let _ = acker.ack_with(AckKind::Nak(Some(retry_delay(delivered)))).await;
                }
            }
        }
    }

    /// Brings the session up to date: applies every listing entry its record has not
    /// applied, fills, publishes, saves; again while entries keep arriving.
    /// `entry` is the message's file: a listing read without it is behind.
    async fn step(&mut self, session: &str, tok: &str, entry: &Entry) -> Result<(), StepError> {
        loop {
            if self.ctx.cancel.is_cancelled() {
                return Err(StepError::Stopping);
            }
            let t = Instant::now();
            let (listing, _) = self.nats.listing(tok).await?;
            if !listing.entries.contains(entry) {
                return Err(StepError::Behind);
            }
            let (record, rev) = self.nats.record(tok).await?;
            self.metrics.stage(0, t);
            let n = listing.entries.len();
            if self.local.get(session).is_none_or(|l| l.revision != rev) {
                if !record.worker.is_empty() && record.worker != self.id {
                    self.metrics.takeovers.fetch_add(1, Ordering::Relaxed);
                }
                // The worker that saved the record may have died before publishing what it
                // says: published again (the stream drops what it already has).
                self.flush(tok, &record, rev).await?;
                if record.applied >= n {
                    return Ok(());
                }
                self.rebuild(session, &listing.entries[..record.applied.min(n)], &record, rev).await?;
            } else if record.applied >= n {
                return Ok(());
            }
            let t = Instant::now();
            let dir = self.local[session].slot.dir.clone();
            for e in &listing.entries[record.applied..] {
                materialize(&self.nats, &dir, e).await?;
                let local = self.local.get_mut(session).expect("rebuilt above");
                apply_entry(&self.ctx, &mut local.slot, session, e);
                self.metrics.entries.fetch_add(1, Ordering::Relaxed);
            }
            self.metrics.stage(2, t);
            let t = Instant::now();
            let local = self.local.get_mut(session).expect("rebuilt above");
            let filled = local.slot.fill(&self.ctx);
            local.slot.save_state(&self.ctx);
            // The snapshot the record carries to `collect --http` (as `run`'s worker
            // publishes it for its page).
            local.slot.publish(&self.ctx, filled.written());
            self.metrics.stage(3, t);
            if filled == FillStep::Cancelled {
                return Err(StepError::Stopping);
            }
            let t = Instant::now();
            let result = match filled.written() {
                Some(number) => Some(self.upload_result(session, tok, number).await?),
                None => record.result.clone(),
            };
            // The record is the step's commit: its result and events are published after
            // it is saved, by this worker or, if it dies first, by the next one.
            let events = std::mem::take(&mut *self.said.lock().expect("events lock"))
                .into_iter()
                .map(|(session, line)| super::Said { session, line })
                .collect();
            let state_text = std::fs::read_to_string(state::path(&self.ctx.config.state_dir, session)).ok();
            let shown = self.shown(session, &listing.entries);
            let new = Record {
                applied: n,
                state: state_text,
                result,
                events,
                worker: self.id.clone(),
                session: shown,
            };
            let bytes = serde_json::to_vec(&new).ctx("record")?;
            let saved = Nats::kv_swap(&self.nats.sessions, &format!("state.{tok}"), bytes, rev).await?;
            let Some(new_rev) = saved else { return Err(StepError::TakenOver) };
            let local = self.local.get_mut(session).expect("rebuilt above");
            local.revision = new_rev;
            local.used = Instant::now();
            let cancel = self.ctx.cancel.clone();
            if let Err(e) = super::ingest::retry(&cancel, 5, || self.flush(tok, &new, new_rev)).await {
                // Committed but not published: the copy here is dropped, so whoever handles
                // the session next (this worker too) publishes the record again.
                self.local.remove(session);
                return Err(e.into());
            }
            self.metrics.stage(4, t);
        }
    }

    /// The session as the engine's snapshot shows it after the step, with the object of
    /// each file it names (the listing's latest entry of that name).
    fn shown(&self, session: &str, entries: &[Entry]) -> Option<SessionMsg> {
        let snapshot = (*self.ctx.registry.get(session)?).clone();
        let mut digests: HashMap<&str, &str> = HashMap::new();
        for e in entries {
            match &e.digest {
                Some(d) => digests.insert(&e.name, d),
                None => digests.remove(e.name.as_str()),
            };
        }
        let names = snapshot.keyframe.iter().chain(snapshot.views.iter().map(|v| &v.file));
        let files = names.filter_map(|n| Some((n.clone(), (*digests.get(n.as_str())?).to_owned()))).collect();
        Some(SessionMsg { session: session.to_owned(), snapshot, record: 0, files })
    }

    /// Publishes what record `rev` says: its result's message, the session's snapshot and
    /// its step's events, each with a message id of its own (result: session, inputs and
    /// number; snapshot: session and record revision; event: session, record revision and place),
    /// so that publishing a record twice adds nothing. The snapshot follows the result it
    /// names, so a collector has the result's files before it shows them.
    async fn flush(&self, tok: &str, record: &Record, rev: u64) -> Result<(), OpError> {
        if let Some(r) = &record.result {
            let session = super::untoken(tok);
            let msg = serde_json::to_vec(&ResultMsg { session, result: r.clone() }).ctx("result")?;
            self.nats
                .publish(
                    format!("{OUT_PREFIX}.{tok}"),
                    Some(&format!("result:{tok}:{}:{}", r.inputs, r.number)),
                    msg,
                )
                .await?;
        }
        if let Some(shown) = &record.session {
            let msg = serde_json::to_vec(&SessionMsg { record: rev, ..shown.clone() }).ctx("session")?;
            self.nats
                .publish(super::session_subject(tok), Some(&format!("session:{tok}:{rev}")), msg)
                .await?;
        }
        for (i, e) in record.events.iter().enumerate() {
            let t = e.session.as_deref().map_or_else(|| NO_SESSION.to_owned(), super::token);
            let id = format!("event:{tok}:{rev}:{i}");
            self.nats.publish(format!("{EVENTS_PREFIX}.{t}"), Some(&id), e.line.clone().into_bytes()).await?;
        }
        Ok(())
    }

    /// Makes this worker's copy of the session the one its record describes: the result
    /// files it names, its saved state, and its applied entries replayed (with their saved
    /// alignments; nothing said again).
    async fn rebuild(
        &mut self,
        session: &str,
        applied: &[Entry],
        record: &Record,
        rev: u64,
    ) -> Result<(), StepError> {
        let t = Instant::now();
        self.metrics.rebuilds.fetch_add(1, Ordering::Relaxed);
        self.local.remove(session);
        self.evict();
        let config = &self.ctx.config;
        let dir = session_dir(config, session);
        clear_files(&dir);
        std::fs::create_dir_all(&dir).ctx("scratch")?;
        let out = self.ctx.emitter.session_dir(session);
        let _ = std::fs::remove_dir_all(&out);
        let state_path = state::path(&config.state_dir, session);
        match &record.state {
            Some(text) => crate::fsio::atomic_write(&state_path, text.as_bytes()).ctx("scratch state")?,
            None => {
                let _ = std::fs::remove_file(&state_path);
            }
        }
        if let Some(r) = &record.result {
            // The result on disk that the saved state names: a fill of the same inputs is
            // then "unchanged", not a new result.
            std::fs::create_dir_all(&out).ctx("scratch")?;
            for rel in r.files.iter().filter(|f| !f.contains('/')) {
                if let Some(bytes) = self.nats.result_file(&super::token(session), r, rel).await? {
                    crate::fsio::atomic_write(&out.join(rel), &bytes).ctx("scratch result")?;
                }
            }
        }
        let mut slot = Slot::new(&self.ctx, session, dir.clone());
        self.muted.store(true, Ordering::Relaxed);
        let mut replayed = Ok(());
        for e in applied {
            if let Err(err) = materialize(&self.nats, &dir, e).await {
                replayed = Err(err);
                break;
            }
            apply_entry(&self.ctx, &mut slot, session, e);
        }
        slot.save_state(&self.ctx);
        self.muted.store(false, Ordering::Relaxed);
        replayed?;
        tracing::info!(entries = applied.len(), from = %record.worker, ms = t.elapsed().as_millis() as u64, "session rebuilt from the cluster");
        self.local.insert(session.to_owned(), Local { slot, revision: rev, used: Instant::now() });
        self.metrics.stage(1, t);
        Ok(())
    }

    /// Keeps at most `resident_sessions` copies: the least recently used go (their scratch
    /// files too); they are rebuilt when needed.
    fn evict(&mut self) {
        while self.local.len() >= self.ctx.config.resident_sessions.get() {
            let Some(oldest) = self.local.iter().min_by_key(|(_, l)| l.used).map(|(k, _)| k.clone()) else {
                return;
            };
            if let Some(l) = self.local.remove(&oldest) {
                clear_files(&l.slot.dir);
            }
        }
    }

    /// Uploads result `number`'s files under the digest of its inputs (unless they are
    /// there: the same inputs made the same result before).
    async fn upload_result(&mut self, session: &str, tok: &str, number: u64) -> Result<ResultRef, StepError> {
        let local = &self.local[session];
        let inputs = local
            .slot
            .state
            .result
            .as_ref()
            .map(|r| format!("{:016x}", r.digest))
            .ok_or_else(|| OpError::lasting("a result without its inputs' digest"))?;
        let out = self.ctx.emitter.session_dir(session);
        let ext = self.ctx.emitter.result_name();
        let mut files: Vec<String> = Vec::new();
        let hist = format!("history/result-{number:04}.{}", ext.trim_start_matches("result."));
        for rel in [
            hist.as_str(),
            "confidence.png",
            SURFACES,
            "provenance.png",
            "mask.png",
            ext.as_str(),
            "result.json",
        ] {
            if out.join(rel).is_file() {
                files.push(rel.to_owned());
            }
        }
        let marker = super::result_object(tok, &inputs, number, "result.json");
        if self.nats.has_object(&marker).await? {
            self.metrics.replays.fetch_add(1, Ordering::Relaxed);
            tracing::info!(number, %inputs, "result of these inputs already uploaded: nothing uploaded");
        } else {
            // result.json last: its presence says the others are there.
            for rel in &files {
                let bytes = std::fs::read(out.join(rel)).ctx(rel)?;
                self.nats.put_object(&super::result_object(tok, &inputs, number, rel), &bytes).await?;
            }
        }
        self.metrics.results.fetch_add(1, Ordering::Relaxed);
        Ok(ResultRef { number, inputs, files })
    }

    /// Sends a message that will never be processed to the dead-letter subject, says so,
    /// and terminates it.
    async fn dead_letter(
        &self,
        msg: &jetstream::Message,
        session: Option<&str>,
        file: Option<&str>,
        deliveries: i64,
        seq: u64,
        reason: &str,
    ) {
        self.send_dead(&msg.subject, &msg.payload, session, file, deliveries, seq, reason).await;
        let _ = msg.ack_with(AckKind::Term).await;
    }

    #[allow(clippy::too_many_arguments)]
    async fn send_dead(
        &self,
        subject: &str,
        payload: &[u8],
        session: Option<&str>,
        file: Option<&str>,
        deliveries: i64,
        seq: u64,
        reason: &str,
    ) {
        self.metrics.dead_letters.fetch_add(1, Ordering::Relaxed);
        tracing::error!(subject, deliveries, %reason, "poison message: dead-lettered");
        let tok = session.map_or_else(|| NO_SESSION.to_owned(), super::token);
        let letter = DeadLetter {
            session: session.map(str::to_owned),
            subject: subject.to_owned(),
            stream_sequence: seq,
            deliveries,
            reason: reason.to_owned(),
            payload: String::from_utf8_lossy(payload).chars().take(4096).collect(),
        };
        let bytes = serde_json::to_vec(&letter).unwrap_or_default();
        let never = CancellationToken::new();
        let subject = format!("{DEAD_PREFIX}.{tok}");
        if let Err(e) =
            super::ingest::retry(&never, 5, || self.nats.publish(subject.clone(), None, bytes.clone())).await
        {
            tracing::error!(error = %e, "cannot publish the dead letter");
        }
        let e = Event::MessageDeadLettered {
            file: file.map(str::to_owned),
            reason: reason.to_owned(),
            deliveries,
        };
        self.ctx.emitter.emit(session, &e);
        let lines = std::mem::take(&mut *self.said.lock().expect("events lock"));
        for (s, line) in lines {
            let t = s.as_deref().map_or_else(|| NO_SESSION.to_owned(), super::token);
            let subject = format!("{EVENTS_PREFIX}.{t}");
            let line = line.into_bytes();
            if let Err(e) =
                super::ingest::retry(&never, 5, || self.nats.publish(subject.clone(), None, line.clone()))
                    .await
            {
                tracing::error!(error = %e, "cannot publish the dead letter's event");
            }
        }
    }
}

/// A session name and file name that can be folders and files of the scratch copy.
fn check_names(f: &FileMsg) -> Result<(), OpError> {
    let plain = |s: &str| !s.is_empty() && !s.contains(['/', '\\', '\0']) && !s.starts_with('.');
    if !plain(&f.session) {
        return Err(OpError::lasting(format!("session {:?} cannot be a folder name", f.session)));
    }
    if !plain(&f.entry.name) {
        return Err(OpError::lasting(format!("file {:?} cannot be a file name", f.entry.name)));
    }
    Ok(())
}

fn session_dir(config: &Config, session: &str) -> PathBuf {
    if session == watch::ROOT_SESSION { config.watch_dir.clone() } else { config.watch_dir.join(session) }
}

/// Removes the regular files of a scratch folder (not its sub-folders: the root session's
/// folder holds the others).
fn clear_files(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        if e.file_type().is_ok_and(|t| t.is_file()) {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// Makes the scratch copy's file of entry `e` what ingest saw: its bytes from the object
/// store and its modification time (so view ids, and the alignments saved by them, are
/// the same on every worker); a deletion removes it.
async fn materialize(nats: &Nats, dir: &Path, e: &Entry) -> Result<(), OpError> {
    let path = dir.join(&e.name);
    let Some(digest) = &e.digest else {
        let _ = std::fs::remove_file(&path);
        return Ok(());
    };
    let mtime = SystemTime::UNIX_EPOCH + Duration::from_nanos(e.mtime_ns);
    if let Ok(m) = std::fs::metadata(&path)
        && m.len() == e.size
        && m.modified().ok() == Some(mtime)
    {
        return Ok(());
    }
    let bytes = nats.get_object(&super::file_object(digest)).await?.ok_or_else(|| {
        OpError::lasting(format!("{}: its content {digest} is not in the object store", e.name))
    })?;
    if super::sha256_hex(&bytes) != *digest {
        return Err(OpError::lasting(format!(
            "{}: the object store's copy does not have its digest",
            e.name
        )));
    }
    crate::fsio::atomic_write(&path, &bytes).ctx(&e.name)?;
    let f = std::fs::File::options().write(true).open(&path).ctx(&e.name)?;
    f.set_modified(mtime).ctx(&e.name)?;
    Ok(())
}

/// Applies one listing entry to the session, as the folder's worker applies a job.
fn apply_entry(ctx: &Ctx, slot: &mut Slot, session: &str, e: &Entry) {
    let path = slot.dir.join(&e.name);
    let role = watch::role_of_stem(watch::stem(&e.name));
    if e.digest.is_none() {
        let file = FileId { name: e.name.clone(), size: 0, mtime: SystemTime::UNIX_EPOCH };
        folder::apply(ctx, slot, role, &file, &path, None);
    } else {
        match folder::load(ctx, &path, role) {
            Ok((file, image)) => folder::apply(ctx, slot, role, &file, &path, Some(&image)),
            Err(err) => {
                let reason = err.reason();
                tracing::warn!(file = %watch::shown(&e.name), %reason, "file skipped");
                let skipped = FileSkipped {
                    file: Some(e.name.clone()),
                    path: format!("{session}/{}", e.name),
                    reason,
                    retried: Some("when the file changes"),
                    symlink: false,
                };
                ctx.emitter.emit(Some(session), &Event::FileSkipped(skipped));
            }
        }
    }
    slot.save_state(ctx);
}

/// A session's lease held by this worker.
struct Lease {
    key: String,
    id: String,
    revision: Arc<AtomicU64>,
    lost: Arc<AtomicBool>,
}

impl Lease {
    /// Takes the session's lease if it is free (or already this worker's); `None` when
    /// another worker holds it.
    async fn take(nats: &Nats, tok: &str, id: &str) -> Result<Option<Self>, OpError> {
        let key = format!("lease.{tok}");
        let rev = match Nats::kv_get(&nats.leases, &key).await? {
            Some((holder, _)) if holder.as_slice() != id.as_bytes() => return Ok(None),
            Some((_, rev)) => rev,
            None => 0,
        };
        Ok(Nats::kv_swap(&nats.leases, &key, id.as_bytes().to_vec(), rev).await?.map(|r| Self {
            key,
            id: id.to_owned(),
            revision: Arc::new(AtomicU64::new(r)),
            lost: Arc::default(),
        }))
    }

    /// Renews the lease and tells the server the message is in progress, every third of
    /// the shorter of the lease's time to live and the ack wait, until aborted.
    fn keep(&self, nats: &Nats, acker: Arc<jetstream::message::Acker>) -> tokio::task::JoinHandle<()> {
        let period = nats.config.lease_ttl.min(nats.config.ack_wait) / 3;
        let (store, key, id) = (nats.leases.clone(), self.key.clone(), self.id.clone());
        let (revision, lost) = (self.revision.clone(), self.lost.clone());
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(period).await;
                let _ = acker.ack_with(AckKind::Progress).await;
                let rev = revision.load(Ordering::Relaxed);
                match Nats::kv_swap(&store, &key, id.clone().into_bytes(), rev).await {
                    Ok(Some(r)) => revision.store(r, Ordering::Relaxed),
                    Ok(None) => {
                        tracing::warn!("the session's lease was taken by another worker");
                        lost.store(true, Ordering::Relaxed);
                        return;
                    }
                    Err(e) => tracing::warn!(error = %e, "cannot renew the lease: trying again"),
                }
            }
        })
    }

    /// Frees the lease (if it is still this worker's).
    async fn release(self, nats: &Nats) {
        let rev = self.revision.load(Ordering::Relaxed);
        if let Err(e) = nats.leases.delete_expect_revision(&self.key, Some(rev)).await {
            tracing::debug!(error = %e, "lease not released (it lapses)");
        }
    }
}

/// Keeps the queue-lag gauges of `/metrics` current (every 2 s).
async fn watch_lag(mut consumer: jetstream::consumer::Consumer<pull::Config>, metrics: Arc<Metrics>) {
    loop {
        if let Ok(info) = consumer.info().await {
            metrics.pending.store(info.num_pending, Ordering::Relaxed);
            metrics.ack_pending.store(info.num_ack_pending as u64, Ordering::Relaxed);
        }
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
}

/// A tiny HTTP endpoint: `GET /metrics` (Prometheus text), 404 otherwise; one request per
/// connection, a 5 s limit to send it.
async fn serve_metrics(listener: tokio::net::TcpListener, metrics: Arc<Metrics>, id: String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    loop {
        let Ok((mut sock, _)) = listener.accept().await else { continue };
        let (metrics, id) = (metrics.clone(), id.clone());
        tokio::spawn(async move {
            let mut buf = vec![0u8; 4096];
            let mut len = 0;
            let read = tokio::time::timeout(Duration::from_secs(5), async {
                while len < buf.len() {
                    let n = sock.read(&mut buf[len..]).await.ok()?;
                    if n == 0 {
                        return None;
                    }
                    len += n;
                    if buf[..len].windows(4).any(|w| w == b"\r\n\r\n") {
                        return Some(());
                    }
                }
                None
            })
            .await;
            if !matches!(read, Ok(Some(()))) {
                return;
            }
            let head = String::from_utf8_lossy(&buf[..len]);
            let (status, body) = if head.starts_with("GET /metrics ") || head.starts_with("GET /metrics?") {
                ("200 OK", metrics.render(&id))
            } else {
                ("404 Not Found", "not found\n".to_owned())
            };
            let reply = format!(
                "HTTP/1.1 {status}\r\ncontent-type: text/plain; version=0.0.4\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = sock.write_all(reply.as_bytes()).await;
        });
    }
}
