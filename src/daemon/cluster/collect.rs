//! `clearview collect` (shell layer): mirrors the cluster's results and events into a
//! folder with `clearview run`'s layout — `DIR/<session>/result.<ext>`, `result.json`,
//! `history/`, `confidence.png`, `surfaces.png`, `provenance.png`, `mask.png`, and
//! `DIR/events.jsonl` — so the preview page and the user's scripts work on it unchanged.
//!
//! A durable consumer of the OUT stream, in stream order, acknowledged after each write:
//! a collector that restarts goes on where it stopped. Each file is written atomically
//! (temporary name, fsync, rename), `result.json` after the image it describes, so a
//! reader never sees a result.json naming an image that is not there. A result whose
//! number is not newer than the one on disk is skipped: a replay writes nothing.
//!
//! The preview page (`--http`, read-only): `run`'s page is fed by its in-memory registry of
//! session snapshots and by the inbox (keyframe, view thumbnails), neither of which exists
//! here. So each worker step also publishes the session's snapshot and the object of each
//! file it names ([`SessionMsg`], after the result it shows); the collector keeps the
//! latest per session in its own folder (`<state>/sessions/`, read back at start) and,
//! with `--http`, copies the keyframes and views from the object store to
//! `<state>/inputs/<digest>.<ext>` (content-addressed: once each), which it serves as
//! `run` serves its inbox. The page's result, mask and provenance come from the collected
//! folder itself. Painting a mask and choosing a keyframe are refused (405): the session's
//! files are in the folder ingest watches.

use std::collections::HashSet;
use std::future::Future;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use async_nats::jetstream::{self, consumer::pull};
use tokio_stream::StreamExt;
use tokio_util::sync::CancellationToken;

use super::{
    ClusterError, Context, DEAD_PREFIX, DeadLetter, EVENTS_PREFIX, Nats, OUT_PREFIX, OpError, ResultMsg,
    SessionMsg,
};
use crate::config::Config;
use crate::daemon::registry::{Registry, SessionSnapshot};
use crate::daemon::{http, paths, watch};

/// What `clearview collect` is told beyond the configuration (`config.http`: serve the
/// preview page).
#[derive(Debug, Clone)]
pub struct CollectOptions {
    /// Its durable consumer's name (one per collected folder).
    pub consumer: String,
    /// Its own folder: the sessions' snapshots and the copies of their inputs.
    pub state: PathBuf,
}

/// Why the preview page of a collector refuses changes.
const READ_ONLY: &str = "this page is served by clearview collect: it shows results only. Paint the mask or choose the keyframe where the session's files are uploaded (the folder clearview ingest watches)";

/// Runs the collector into `config.out_dir` until `shutdown`.
pub async fn run(
    mut config: Config,
    opts: CollectOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ClusterError> {
    let consumer = opts.consumer.as_str();
    let sessions = opts.state.join("sessions");
    let inputs = opts.state.join("inputs");
    for dir in [&config.out_dir, &sessions, &inputs] {
        std::fs::create_dir_all(dir).map_err(|source| ClusterError::Io { path: dir.clone(), source })?;
        crate::daemon::emit::remove_stale_temporaries(dir);
    }
    config.out_dir = std::fs::canonicalize(&config.out_dir).unwrap_or(config.out_dir);
    let inputs = std::fs::canonicalize(&inputs).unwrap_or(inputs);
    let nats = Arc::new(Nats::connect(&config.nats, "clearview-collect").await?);
    let c = &nats.config;
    let setup = |e: &dyn std::fmt::Display| ClusterError::Setup {
        what: format!("consumer {consumer} on {}", c.results_stream),
        reason: e.to_string(),
    };
    let consumer = super::settled("the collector's consumer", || async {
        let stream = nats.js.get_stream(&c.results_stream).await.map_err(|e| setup(&e))?;
        stream
            .get_or_create_consumer(
                consumer,
                pull::Config {
                    durable_name: Some(consumer.to_owned()),
                    ack_policy: jetstream::consumer::AckPolicy::Explicit,
                    ack_wait: c.ack_wait,
                    num_replicas: c.replicas,
                    ..Default::default()
                },
            )
            .await
            .map_err(|e| setup(&e))
    })
    .await?;
    let cancel = CancellationToken::new();
    {
        let cancel = cancel.clone();
        tokio::spawn(async move {
            shutdown.await;
            tracing::info!("shutdown requested: finishing the write in hand");
            cancel.cancel();
        });
    }
    let pages = match &config.http {
        Some(_) => Some(Pages::start(&config, &sessions, inputs, &cancel).await?),
        None => None,
    };
    let out = Collector {
        nats: nats.clone(),
        out: config.out_dir.clone(),
        events: EventLog::open(config.out_dir.join("events.jsonl"))?,
        history: config.history,
        sessions,
        pages,
    };
    if let Some(p) = &out.pages {
        // Inputs a page needs that an earlier run (or one without --http) did not copy.
        let (pages, nats, cancel) = (p.clone(), nats.clone(), cancel.clone());
        tokio::spawn(async move {
            for m in pages.registry_messages() {
                if cancel.is_cancelled() {
                    return;
                }
                if let Err(e) = pages.mirror(&nats, &m).await {
                    tracing::warn!(session = %watch::shown(&m.session), error = %e, "inputs not copied for the page (they come with its next step)");
                }
            }
        });
    }
    tracing::info!(out = %config.out_dir.display(), "collect started");
    crate::daemon::systemd::ready();
    while !cancel.is_cancelled() {
        let fetched = tokio::select! {
            () = cancel.cancelled() => break,
            f = consumer.fetch().max_messages(64).expires(Duration::from_secs(1)).messages() => f,
        };
        let mut batch = match fetched {
            Ok(b) => b,
            Err(e) => {
                tracing::warn!(error = %e, "cannot fetch: trying again");
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
        };
        while let Some(next) = batch.next().await {
            let Ok(msg) = next else { continue };
            match out.take(&msg).await {
                Ok(()) => {
                    let _ = msg.ack().await;
                }
                Err(e) => {
                    tracing::warn!(subject = %msg.subject, error = %e, "not written: the message comes again");
                    let _ = msg.ack_with(jetstream::AckKind::Nak(Some(Duration::from_secs(1)))).await;
                    // Later messages wait for this one (stream order is result order).
                    break;
                }
            }
        }
    }
    crate::daemon::systemd::stopping();
    tracing::info!("collect stopped");
    Ok(())
}

struct Collector {
    nats: Arc<Nats>,
    out: PathBuf,
    events: EventLog,
    history: usize,
    /// Where the latest [`SessionMsg`] of each session is kept.
    sessions: PathBuf,
    pages: Option<Pages>,
}

impl Collector {
    async fn take(&self, msg: &jetstream::Message) -> Result<(), OpError> {
        let subject = msg.subject.as_str();
        let session_msg = subject
            .strip_prefix(&format!("{OUT_PREFIX}."))
            .is_some_and(|rest| super::session_subject(rest.split('.').next().unwrap_or("")) == subject);
        if subject.starts_with(&format!("{EVENTS_PREFIX}.")) {
            self.event(&msg.payload)
        } else if session_msg {
            match serde_json::from_slice::<SessionMsg>(&msg.payload) {
                Ok(m) => self.session(m).await,
                Err(e) => {
                    tracing::error!(%subject, error = %e, "malformed session message: skipped");
                    Ok(())
                }
            }
        } else if subject.starts_with(&format!("{OUT_PREFIX}.")) {
            let r: ResultMsg = match serde_json::from_slice(&msg.payload) {
                Ok(r) => r,
                Err(e) => {
                    tracing::error!(%subject, error = %e, "malformed result message: skipped");
                    return Ok(());
                }
            };
            self.result(r).await
        } else if subject.starts_with(&format!("{DEAD_PREFIX}.")) {
            if let Ok(d) = serde_json::from_slice::<DeadLetter>(&msg.payload) {
                tracing::error!(subject = %d.subject, reason = %d.reason, deliveries = d.deliveries, "a work message was dead-lettered");
            }
            Ok(())
        } else {
            Ok(())
        }
    }

    /// Appends one event line to `events.jsonl` (one write per line, as `run` does), once.
    fn event(&self, line: &[u8]) -> Result<(), OpError> {
        let Ok(mut event) = serde_json::from_slice::<serde_json::Value>(line) else {
            tracing::warn!("an event that is not JSON: skipped");
            return Ok(());
        };
        // A result's path is where this folder has it, not where the worker made it.
        let line = if event["event"] == "result_updated"
            && let (Some(session), Some(file)) = (event["session"].as_str(), event["result"].as_str())
        {
            let path = self.out.join(paths::session_dir_name(session)).join(file);
            event["path"] = path.to_string_lossy().into_owned().into();
            event.to_string().into_bytes()
        } else {
            line.to_vec()
        };
        if !self.events.append(&line)? {
            tracing::debug!("an event already in events.jsonl: skipped");
        }
        Ok(())
    }

    /// Writes a result's files into the session's folder, `result.json` last; nothing when
    /// the folder already has this result or a newer one.
    async fn result(&self, r: ResultMsg) -> Result<(), OpError> {
        if !folder_name(&r.session) {
            tracing::error!(session = %watch::shown(&r.session), "a result for a session that cannot be a folder: skipped");
            return Ok(());
        }
        let dir = self.out.join(paths::session_dir_name(&r.session));
        if let Some(have) = number_on_disk(&dir)
            && have >= r.result.number
        {
            tracing::debug!(session = %watch::shown(&r.session), number = r.result.number, have, "already collected");
            return Ok(());
        }
        let tok = super::token(&r.session);
        for rel in &r.result.files {
            let ok = !rel.starts_with('.')
                && !rel.contains("..")
                && (!rel.contains('/') || rel.strip_prefix("history/").is_some_and(|f| !f.contains('/')));
            if !ok {
                tracing::error!(file = %rel, "a result file outside the session's folder: skipped");
                continue;
            }
            let bytes = self.nats.result_file(&tok, &r.result, rel).await?.ok_or_else(|| {
                let name = super::result_object(&tok, &r.result.inputs, r.result.number, rel);
                OpError::lasting(format!("{name} is not in the object store"))
            })?;
            if rel == "result.json" {
                // A map an earlier result left, which this one has not: it goes before the
                // result.json that does not name it.
                for map in
                    crate::daemon::emit::MAPS.iter().filter(|m| !r.result.files.iter().any(|f| f == *m))
                {
                    match std::fs::remove_file(dir.join(map)) {
                        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                            return Err::<(), _>(e).ctx(map);
                        }
                        _ => {}
                    }
                }
            }
            let path = dir.join(rel);
            if let Some(parent) = path.parent() {
                std::fs::create_dir_all(parent).ctx("create folder")?;
            }
            crate::fsio::atomic_write(&path, &bytes).ctx(rel)?;
        }
        if self.history > 0 {
            crate::daemon::emit::prune_history(&dir.join("history"), self.history);
        }
        tracing::info!(session = %watch::shown(&r.session), number = r.result.number, inputs = %r.result.inputs, "result collected");
        Ok(())
    }

    /// Keeps a session's latest snapshot (one older than the kept one, by its record's
    /// revision, is skipped: a message put back comes after later ones) and, with the
    /// page, copies its inputs and shows it.
    async fn session(&self, m: SessionMsg) -> Result<(), OpError> {
        if !folder_name(&m.session) || m.snapshot.id != m.session {
            tracing::error!(session = %watch::shown(&m.session), "a snapshot for a session that cannot be a folder: skipped");
            return Ok(());
        }
        let path = snapshot_path(&self.sessions, &m.session);
        let kept = std::fs::read(&path).ok().and_then(|b| serde_json::from_slice::<SessionMsg>(&b).ok());
        if kept.is_some_and(|k| k.record > m.record) {
            tracing::debug!(session = %watch::shown(&m.session), record = m.record, "an older snapshot: skipped");
            return Ok(());
        }
        let bytes = serde_json::to_vec(&m).ctx("snapshot")?;
        crate::fsio::atomic_write(&path, &bytes).ctx("snapshot")?;
        if let Some(p) = &self.pages {
            p.mirror(&self.nats, &m).await?;
            p.show(m);
        }
        Ok(())
    }
}

/// A session name that is one plain folder name.
/// `DIR/events.jsonl` as the collector writes it: each event line once.
///
/// The OUT stream delivers at least once: a collector that dies between its write and its
/// acknowledgement, or whose acknowledgement is lost with a server, is given the event
/// again, and message ids guard a stream only while it keeps its duplicate window (seen
/// with a server killed while a worker published: four `result_updated` lines twice, the
/// same bytes). A user's script reads a line twice as two events, so the
/// digest of every line in the file is kept, read back at start, and a line already there is
/// not appended again. Two events never make the same line: each carries its time to the
/// millisecond, its session and its step's numbers.
struct EventLog {
    path: PathBuf,
    written: std::sync::Mutex<HashSet<[u8; 16]>>,
}

impl EventLog {
    /// Reads the digests of the lines `path` has. A last line without its newline (a
    /// collector killed in its write) is cut off: its event was not acknowledged and comes
    /// again.
    fn open(path: PathBuf) -> Result<Self, ClusterError> {
        let io = |source| ClusterError::Io { path: path.clone(), source };
        let mut text = match std::fs::read(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
            Err(e) => return Err(io(e)),
        };
        let whole = text.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
        if whole < text.len() {
            tracing::warn!(path = %path.display(), bytes = text.len() - whole, "a torn last event line: cut off (it comes again)");
            let f = std::fs::OpenOptions::new().write(true).open(&path).map_err(io)?;
            f.set_len(whole as u64).map_err(io)?;
            f.sync_all().map_err(io)?;
            text.truncate(whole);
        }
        let written = text.split(|&b| b == b'\n').filter(|l| !l.is_empty()).map(digest).collect();
        Ok(Self { path, written: std::sync::Mutex::new(written) })
    }

    /// Appends `line` (without its newline) unless the file has it; whether it did.
    fn append(&self, line: &[u8]) -> Result<bool, OpError> {
        let line = line.strip_suffix(b"\n").unwrap_or(line);
        let mut written = self.written.lock().expect("event log lock");
        let d = digest(line);
        if written.contains(&d) {
            return Ok(false);
        }
        let mut bytes = Vec::with_capacity(line.len() + 1);
        bytes.extend_from_slice(line);
        bytes.push(b'\n');
        let mut f =
            std::fs::OpenOptions::new().create(true).append(true).open(&self.path).ctx("events.jsonl")?;
        f.write_all(&bytes).ctx("events.jsonl")?;
        written.insert(d);
        Ok(true)
    }
}

/// The first 128 bits of a line's SHA-256.
fn digest(line: &[u8]) -> [u8; 16] {
    use sha2::Digest as _;
    let full = sha2::Sha256::digest(line);
    let mut d = [0; 16];
    d.copy_from_slice(&full[..16]);
    d
}

fn folder_name(session: &str) -> bool {
    !session.contains(['/', '\\']) && !session.starts_with('.')
}

fn snapshot_path(dir: &Path, session: &str) -> PathBuf {
    dir.join(format!("{}.json", paths::session_dir_name(session)))
}

/// The preview page of a collector: its registry, fed by the sessions' snapshots, and the
/// copies of their inputs.
#[derive(Clone)]
struct Pages {
    registry: Arc<Registry>,
    /// Kept sessions' messages, for the copies made at start.
    loaded: Arc<std::sync::Mutex<Vec<SessionMsg>>>,
    inputs: PathBuf,
}

impl Pages {
    /// Reads the snapshots kept by earlier runs and starts the server (`config.http`).
    async fn start(
        config: &Config,
        sessions: &Path,
        inputs: PathBuf,
        cancel: &CancellationToken,
    ) -> Result<Self, ClusterError> {
        let h = config.http.as_ref().expect("only with [http]");
        let mut served = config.clone();
        // The page reads keyframes and views from the copies, as `run` reads its inbox.
        served.watch_dir = inputs.clone();
        let pages = Self { registry: Arc::default(), loaded: Arc::default(), inputs };
        let mut loaded = Vec::new();
        for entry in std::fs::read_dir(sessions)
            .map_err(|source| ClusterError::Io { path: sessions.to_owned(), source })?
            .flatten()
        {
            let path = entry.path();
            if path.extension().is_none_or(|e| e != "json") {
                continue;
            }
            match std::fs::read(&path)
                .map_err(|e| e.to_string())
                .and_then(|b| serde_json::from_slice::<SessionMsg>(&b).map_err(|e| e.to_string()))
            {
                Ok(m) => {
                    pages.show(m.clone());
                    loaded.push(m);
                }
                Err(e) => {
                    tracing::warn!(file = %path.display(), error = %e, "a kept snapshot that cannot be read: skipped")
                }
            }
        }
        *pages.loaded.lock().expect("pages lock") = loaded;
        let token = h.token.clone().unwrap_or_else(http::generate_token);
        let server = http::bind(h, &token)
            .await
            .map_err(|source| crate::daemon::DaemonError::Http { addr: h.listen, source })?;
        tracing::info!(addr = %server.addr, "HTTP server listening (read-only)");
        http::announce(&server);
        let shared = Arc::new(http::Shared {
            emitter: Arc::new(crate::daemon::emit::Emitter::open(&served)?),
            config: Arc::new(served),
            registry: pages.registry.clone(),
            stats: Arc::default(),
            backlog: Arc::default(),
            queues: Vec::new(),
            token,
            loopback: server.addr.ip().is_loopback(),
            started: std::time::Instant::now(),
            cancel: cancel.clone(),
            limits: http::limits::Limits::default(),
            read_only: Some(READ_ONLY),
        });
        tokio::spawn(http::serve(server, shared, h.max_body_bytes));
        Ok(pages)
    }

    /// The messages read at start (once).
    fn registry_messages(&self) -> Vec<SessionMsg> {
        std::mem::take(&mut *self.loaded.lock().expect("pages lock"))
    }

    /// Where the copy of a file with content `digest` and name `name` is.
    fn input_path(&self, name: &str, digest: &str) -> PathBuf {
        let ext = name.rsplit_once('.').map(|(_, e)| e.to_ascii_lowercase());
        let ext =
            ext.filter(|e| !e.is_empty() && e.len() <= 8 && e.bytes().all(|b| b.is_ascii_alphanumeric()));
        self.inputs.join(format!("{digest}.{}", ext.as_deref().unwrap_or("bin")))
    }

    /// Copies the files `m` names from the object store (those not copied yet). A file the
    /// store no longer has is said and left out (the page answers 404 for it); a store that
    /// does not answer is an error (the message comes again).
    async fn mirror(&self, nats: &Nats, m: &SessionMsg) -> Result<(), OpError> {
        for (name, digest) in &m.files {
            if digest.len() != 64 || !digest.bytes().all(|b| b.is_ascii_hexdigit()) {
                continue;
            }
            let path = self.input_path(name, digest);
            if path.is_file() {
                continue;
            }
            let Some(bytes) = nats.get_object(&super::file_object(digest)).await? else {
                tracing::warn!(session = %watch::shown(&m.session), file = %watch::shown(name), "not in the object store: the page cannot show it");
                continue;
            };
            if super::sha256_hex(&bytes) != *digest {
                tracing::warn!(file = %watch::shown(name), "the object store's copy does not have its digest: not shown");
                continue;
            }
            crate::fsio::atomic_write(&path, &bytes).ctx(name)?;
        }
        Ok(())
    }

    /// Shows a snapshot: its files are the copies; a `result` update when its result is new.
    fn show(&self, m: SessionMsg) {
        let SessionMsg { mut snapshot, files, .. } = m;
        let at = |name: &str| files.get(name).map(|d| self.input_path(name, d));
        snapshot.key_path = snapshot.keyframe.as_deref().and_then(at);
        for v in &mut snapshot.views {
            v.path = at(&v.file).unwrap_or_default();
        }
        snapshot.inbox_dir = self.inputs.clone();
        let number = |s: &SessionSnapshot| s.result.as_ref().and_then(|r| r["number"].as_u64());
        let new = number(&snapshot)
            .filter(|&n| self.registry.get(&snapshot.id).and_then(|o| number(&o)) != Some(n));
        self.registry.publish(snapshot, new);
    }
}

/// The number of the result in a session's folder, if it has one.
fn number_on_disk(dir: &Path) -> Option<u64> {
    let bytes = std::fs::read(dir.join("result.json")).ok()?;
    serde_json::from_slice::<serde_json::Value>(&bytes).ok()?["number"].as_u64()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lines(path: &Path) -> Vec<String> {
        std::fs::read_to_string(path).unwrap().lines().map(str::to_owned).collect()
    }

    #[test]
    fn an_event_delivered_again_is_written_once_even_by_a_restarted_collector() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("events.jsonl");
        let a = br#"{"event":"result_updated","number":1,"session":"s","time":"2026-11-25T00:16:32.005Z"}"#;
        let b =
            br#"{"event":"view_accepted","file":"v.png","session":"s","time":"2026-11-25T00:16:32.006Z"}"#;
        let log = EventLog::open(path.clone()).unwrap();
        assert!(log.append(a).unwrap());
        assert!(!log.append(a).unwrap(), "a redelivery is not appended");
        assert!(log.append(b).unwrap());
        drop(log);
        // A collector killed in its next write left a torn line; the restarted one cuts it
        // off, knows what the file has, and writes the torn event whole when it comes again.
        let mut f = std::fs::OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(br#"{"event":"view_acc"#).unwrap();
        drop(f);
        let log = EventLog::open(path.clone()).unwrap();
        assert!(!log.append(a).unwrap() && !log.append(b).unwrap());
        let c =
            br#"{"event":"view_accepted","file":"w.png","session":"s","time":"2026-11-25T00:16:33.000Z"}"#;
        assert!(log.append(&[&c[..], b"\n"].concat()).unwrap());
        let want: Vec<String> =
            [&a[..], &b[..], &c[..]].iter().map(|l| String::from_utf8(l.to_vec()).unwrap()).collect();
        assert_eq!(lines(&path), want);
    }
}
