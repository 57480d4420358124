//! The NATS JetStream scale-out (shell layer): three roles beside `clearview run`, one
//! cluster in between, no shared file system.
//!
//! ```text
//!  camera folder ─► ingest ─► object store  file/<sha256>          ◄─ workers read files
//!                     │       KV sessions   files.<session>  (the listing, in ingest order)
//!                     └─────► stream IN     clearview.in.<session>  (one message per file)
//!                                              │ durable pull consumer, explicit ack
//!                                              ▼
//!                   KV leases lease.<session> ◄─ worker × N ─► KV sessions  state.<session>
//!                                                   │          object store result/<session>/<inputs>/<n>/…
//!                                                   ▼
//!                     stream OUT  clearview.out|events|dead.<session> ─► collect ─► out folder
//! ```
//!
//! - [`ingest`]: the folder intake of `run` as it is ([`super::intake`]: quiet period,
//!   partial uploads, links refused, bad files reported as events). Each complete file goes
//!   to the object store under its SHA-256 (`file/<hex>`), is appended to its session's
//!   **listing** in the key-value bucket (`files.<session>`, compare-and-set, in arrival
//!   order; a deletion is an entry too), and a message ([`FileMsg`]) goes to
//!   `clearview.in.<session>` with `Nats-Msg-Id` = the entry's place in the listing +
//!   digest + time + session + name, so a restarted or doubled ingest adds nothing twice (the
//!   stream's duplicate window; after it, the listing already has the entry and the worker
//!   finds nothing new), and a file put back after another of its name is a new message.
//! - [`worker`]: pulls one message at a time. The message only says "session S has a new
//!   file": the worker takes S's **lease** (key-value create, renewed by revision
//!   compare-and-set, lapsing after the bucket's max age), then applies every listing entry
//!   S's record has not applied yet, in listing order, and fills once. So a session's files
//!   are applied in the order they arrived whatever order the messages are delivered in, a
//!   duplicate or late message finds nothing to do, and several files that landed together
//!   make one fill (the batching of `run`). A message for a session leased by another worker
//!   is NAK'd with a delay. The listing and the record are read from their stream's leader
//!   (the buckets answer no direct gets, which a follower that has not caught up may
//!   answer), and a message whose file the listing as read does not have is put back, never
//!   acknowledged: ingest lists a file before it sends its message.
//!
//!   **Roles.** The message carries the file's role by name (keyframe `key.*`, mask, view:
//!   [`super::watch::role_of_stem`]); which image *is* the keyframe (the first, the one a mask
//!   names, the configured one) depends on the listing, so the worker decides it with
//!   [`super::policy`] over the session's listing as it stood when the file arrived, exactly
//!   as `run` does over the folder: the worker keeps a scratch copy of the session's folder,
//!   made from the object store entry by entry, and runs the folder source
//!   ([`super::folder`]) and the session engine ([`super::engine`]) on it unchanged.
//!
//!   **State and takeover.** A step ends by saving the session's **record**
//!   (`state.<session>`: how many listing entries are applied, the engine's saved state —
//!   keyframe, alignments by view id, the published result's input digest, score and
//!   number —, where that result is, and the step's events) with compare-and-set on its
//!   revision. The record is the step's commit: its result message and events are
//!   published after it is saved, each with a message id of its own, and any worker that
//!   finds a record it has not seen publishes them again (the stream drops what it already
//!   has), so a worker that dies between saving and publishing loses nothing, and one that
//!   dies before saving leaves nothing behind (its message is delivered again, its
//!   numbers are used again). A worker whose copy of a session is not at the record's
//!   revision (another worker touched it since, or it never saw it) rebuilds it: the result
//!   files of the record from the object store, then the applied entries replayed with
//!   their saved alignments (nothing aligned again, nothing said again); the fill then
//!   finds the inputs unchanged and writes nothing. Files are materialised with the
//!   modification time ingest saw, so view ids — and the alignments keyed by them — are the
//!   same on every worker.
//!
//!   **Results** are keyed by the digest of their inputs (the session's inputs digest) and
//!   their number: `result/<session>/<inputs>/<number>/{result.<ext>, result.json, history/…,
//!   confidence.png, surfaces.png, provenance.png, mask.png}` (not uploaded again when there),
//!   and a [`ResultMsg`] on `clearview.out.<session>` with `Nats-Msg-Id` = session + inputs +
//!   number. A step done again after a worker died has the same of both; the same inputs
//!   can come back later under a new number (a mask put back), and that is a new result.
//!
//!   **Events** are the service's own ([`super::event::Event`]) on
//!   `clearview.events.<session>`, with ids session + record revision + place: exactly
//!   once within the stream's duplicate window.
//!
//!   **Poison.** A file that does not decode is not poison: it is a `file_skipped` event, as
//!   in `run`. A message whose step fails `max_deliver` times the same lasting way (the
//!   object store lost a file, a malformed message: [`OpError::lasting`]) goes to
//!   `clearview.dead.<session>` with the reason and an event `message_dead_lettered`, and
//!   is terminated. A failure of the cluster (a server died, a stream without a leader for
//!   a while) is never poison: the message comes again, up to 30 s later each time.
//! - [`collect`]: a durable consumer of the OUT stream that writes `DIR/<session>/result.*`,
//!   `result.json`, `history/`, the maps, and `DIR/events.jsonl`, with `run`'s layout, each
//!   file atomically; a result whose number is not newer than the one on disk is skipped,
//!   so replays write nothing.
//!
//! Every stream and bucket is created with `[nats].replicas` replicas by whichever role
//! starts first (creation is idempotent); with 3 replicas on 3 servers one server may die.

pub mod collect;
pub mod ingest;
pub mod worker;

use std::collections::BTreeMap;
use std::time::Duration;

use async_nats::jetstream::{self, kv, object_store, stream};
use serde::{Deserialize, Serialize};
use sha2::Digest as _;
use thiserror::Error;

use super::registry::SessionSnapshot;
use super::watch::Role;
use crate::config::NatsConfig;

/// Why a role could not start or go on. Per-file and per-message problems are events.
#[derive(Debug, Error)]
pub enum ClusterError {
    #[error("no NATS server: give --nats URL[,URL...] or [nats].servers")]
    NoServers,
    #[error("cannot connect to NATS ({servers}): {reason}")]
    Connect { servers: String, reason: String },
    #[error("cannot set up {what}: {reason}")]
    Setup { what: String, reason: String },
    #[error("{path}: {source}")]
    Io { path: std::path::PathBuf, source: std::io::Error },
    #[error(transparent)]
    Daemon(#[from] super::DaemonError),
}

/// A failure of one operation, in words (for a NAK, a retry, a dead letter), and whether
/// doing it again can go differently.
#[derive(Debug, Error)]
#[error("{reason}")]
pub struct OpError {
    pub reason: String,
    /// It fails the same way every time: a file the object store does not have, a copy
    /// without its digest, a malformed message or record. Only such a failure makes a
    /// message poison. Anything else (a timeout, no leader for a moment, a lost
    /// connection, a full disk) is the cluster or the machine not doing it *now*.
    pub lasting: bool,
}

impl OpError {
    /// A failure that may not happen again (the default: see [`OpError::lasting`]).
    pub fn passing(reason: impl Into<String>) -> Self {
        Self { reason: reason.into(), lasting: false }
    }

    /// A failure that will happen every time.
    pub fn lasting(reason: impl Into<String>) -> Self {
        Self { reason: reason.into(), lasting: true }
    }
}

/// `?` on any error, with what was being done.
pub(crate) trait Context<T> {
    /// A failure that may not happen again (a NATS request, a file written).
    fn ctx(self, what: &str) -> Result<T, OpError>;
    /// A failure that will happen every time (bytes that do not parse).
    fn lasting(self, what: &str) -> Result<T, OpError>;
}

impl<T, E: std::fmt::Display> Context<T> for Result<T, E> {
    fn ctx(self, what: &str) -> Result<T, OpError> {
        self.map_err(|e| OpError::passing(format!("{what}: {e}")))
    }

    fn lasting(self, what: &str) -> Result<T, OpError> {
        self.map_err(|e| OpError::lasting(format!("{what}: {e}")))
    }
}

/// Subjects of the two streams.
pub const IN_PREFIX: &str = "clearview.in";
pub const OUT_PREFIX: &str = "clearview.out";
pub const EVENTS_PREFIX: &str = "clearview.events";
pub const DEAD_PREFIX: &str = "clearview.dead";

/// The token of the events that belong to no session.
pub const NO_SESSION: &str = "_";

/// A session's name as one subject token and key-value key part: itself when it is made
/// of letters, digits, `-` and `_` (at most 64), else `=` and its UTF-8 in hex (`=` never
/// appears in a plain token, so the two never meet).
pub fn token(session: &str) -> String {
    if !session.is_empty()
        && session.len() <= 64
        && session.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
    {
        session.to_owned()
    } else {
        format!("={}", hex(session.as_bytes()))
    }
}

/// The session a [`token`] stands for.
pub fn untoken(tok: &str) -> String {
    let Some(h) = tok.strip_prefix('=') else { return tok.to_owned() };
    let bytes: Vec<u8> =
        (0..h.len() / 2).filter_map(|i| u8::from_str_radix(h.get(2 * i..2 * i + 2)?, 16).ok()).collect();
    String::from_utf8_lossy(&bytes).into_owned()
}

pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of `bytes`, 64 hex digits.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&sha2::Sha256::digest(bytes))
}

/// The object of a file's content.
pub fn file_object(digest: &str) -> String {
    format!("file/{digest}")
}

/// The object of one file of a result (`rel`: `result.png`, `history/result-0003.png`…),
/// under the digest of the result's inputs and its number. A step done again after a worker
/// died has both the same and uploads nothing. The same inputs can come back under a later
/// number (a mask swapped and put back from a copy that keeps its time), and that is another
/// result: its own `result.json`, its own history file. Under the inputs alone, the later
/// result found the earlier one's objects, uploaded nothing, and named a history file the
/// store never had.
pub fn result_object(session_token: &str, inputs: &str, number: u64, rel: &str) -> String {
    format!("result/{session_token}/{inputs}/{number}/{rel}")
}

/// Where a version before the results' numbers kept [`result_object`]: under the inputs
/// alone. Read only (a result an earlier worker stored), never written.
fn legacy_result_object(session_token: &str, inputs: &str, rel: &str) -> String {
    format!("result/{session_token}/{inputs}/{rel}")
}

/// A file's role by its name, as messages carry it.
pub fn role_name(role: Role) -> &'static str {
    match role {
        Role::Key => "keyframe",
        Role::Mask => "mask",
        Role::View => "view",
    }
}

/// One entry of a session's listing (`files.<session>`): a file as ingest took it, or its
/// deletion (`digest` `None`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Entry {
    pub name: String,
    /// `keyframe`, `mask` or `view` ([`role_name`]).
    pub role: String,
    pub size: u64,
    /// Modification time (ns since the epoch) ingest saw; the worker's copy gets it too.
    pub mtime_ns: u64,
    /// SHA-256 of the content (hex); `None`: the file was deleted.
    pub digest: Option<String>,
}

/// A session's listing: every file in the order ingest took it.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Listing {
    pub entries: Vec<Entry>,
}

/// The work message on `clearview.in.<session>`: a file (or a deletion) of a session.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FileMsg {
    pub session: String,
    #[serde(flatten)]
    pub entry: Entry,
}

/// Where a published result's files are.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ResultRef {
    pub number: u64,
    /// The digest of the result's inputs (16 hex digits): its objects' folder.
    pub inputs: String,
    /// The files, relative to the session's folder (`result.json` last).
    pub files: Vec<String>,
}

/// A session's record (`state.<session>`): what a worker that takes the session over
/// needs.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Record {
    /// Listing entries applied (a prefix of the listing).
    pub applied: usize,
    /// The engine's saved state file ([`super::state`]), as it is on disk.
    pub state: Option<String>,
    /// The latest result published.
    pub result: Option<ResultRef>,
    /// The events of the step that saved it (event log lines), published after it.
    #[serde(default)]
    pub events: Vec<Said>,
    /// The worker that saved it.
    pub worker: String,
    /// The session as the status API shows it after the step, published after the result.
    #[serde(default)]
    pub session: Option<SessionMsg>,
}

/// An event line of a step and the session it is of.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Said {
    pub session: Option<String>,
    pub line: String,
}

/// The message on `clearview.out.<session>`: a result's files are in the object store.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ResultMsg {
    pub session: String,
    #[serde(flatten)]
    pub result: ResultRef,
}

/// The message on `clearview.out.<session>.session` ([`session_subject`]): the session as
/// `run`'s status API shows it after a step, for `clearview collect --http`, and where the
/// files it names (keyframe, views) are in the object store.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SessionMsg {
    pub session: String,
    pub snapshot: SessionSnapshot,
    /// The revision of the session's record that published it: a later step's snapshot
    /// has a higher one.
    #[serde(default)]
    pub record: u64,
    /// File name → SHA-256 of its content (the `file/<digest>` object), for the keyframe
    /// and the views the snapshot names.
    pub files: BTreeMap<String, String>,
}

/// The subject of a session's [`SessionMsg`]: under `clearview.out.>` (so the results
/// stream takes it as it is), one token deeper than its results.
pub fn session_subject(session_token: &str) -> String {
    format!("{OUT_PREFIX}.{session_token}.session")
}

/// The message on `clearview.dead.<session>`: a poison message and why.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DeadLetter {
    pub session: Option<String>,
    pub subject: String,
    pub stream_sequence: u64,
    pub deliveries: i64,
    pub reason: String,
    pub payload: String,
}

/// The cluster as a role sees it: the connection and the streams and buckets, made if
/// missing.
pub struct Nats {
    pub client: async_nats::Client,
    pub js: jetstream::Context,
    pub objects: object_store::ObjectStore,
    /// The object store's stream (its chunks are read from it directly).
    pub object_stream: stream::Stream,
    pub sessions: kv::Store,
    pub leases: kv::Store,
    pub config: NatsConfig,
}

impl Nats {
    /// Connects (`name` is the connection's name on the servers' monitoring) and makes the
    /// streams and buckets that are missing.
    pub async fn connect(config: &NatsConfig, name: &str) -> Result<Self, ClusterError> {
        if config.servers.is_empty() {
            return Err(ClusterError::NoServers);
        }
        let servers = config.servers.join(",");
        let fail = |reason: String| ClusterError::Connect { servers: servers.clone(), reason };
        let mut opts = async_nats::ConnectOptions::new()
            .name(name)
            .retry_on_initial_connect()
            .connection_timeout(Duration::from_secs(5))
            .request_timeout(Some(Duration::from_secs(10)));
        if let Some(creds) = &config.credentials {
            opts =
                opts.credentials_file(creds).await.map_err(|e| fail(format!("{}: {e}", creds.display())))?;
        }
        if let Some(ca) = &config.tls_ca {
            opts = opts.add_root_certificates(ca.clone()).require_tls(true);
        }
        if let Some((cert, key)) = &config.tls_client {
            opts = opts.add_client_certificate(cert.clone(), key.clone()).require_tls(true);
        }
        let addrs: Vec<async_nats::ServerAddr> = config
            .servers
            .iter()
            .map(|s| s.parse::<async_nats::ServerAddr>().map_err(|e| fail(format!("{s}: {e}"))))
            .collect::<Result<_, _>>()?;
        let client = tokio::time::timeout(Duration::from_secs(30), opts.connect(addrs))
            .await
            .map_err(|_| fail("no server answered within 30 s".into()))?
            .map_err(|e| fail(e.to_string()))?;
        let js = jetstream::new(client.clone());
        let (objects, sessions, leases) = settled("streams", || ensure(&js, config)).await?;
        let object_stream = js.get_stream(format!("OBJ_{}", config.objects)).await.map_err(|e| {
            ClusterError::Setup { what: format!("object store {}", config.objects), reason: e.to_string() }
        })?;
        Ok(Self { client, js, objects, object_stream, sessions, leases, config: config.clone() })
    }

    /// Whether object `name` is in the store.
    pub async fn has_object(&self, name: &str) -> Result<bool, OpError> {
        match self.objects.info(name).await {
            Ok(_) => Ok(true),
            Err(e) if e.kind() == object_store::InfoErrorKind::NotFound => Ok(false),
            Err(e) => Err(OpError::passing(format!("object {name}: {e}"))),
        }
    }

    /// Puts `bytes` as object `name` unless it is there already (content-addressed
    /// names: same name, same bytes). Returns whether it was put.
    pub async fn put_object(&self, name: &str, bytes: &[u8]) -> Result<bool, OpError> {
        if self.has_object(name).await? {
            return Ok(false);
        }
        // On a task of its own: a panic of the client (see `get_object`) is an error here.
        let (objects, owned, data) = (self.objects.clone(), name.to_owned(), bytes.to_vec());
        let put = tokio::spawn(async move {
            let mut reader = data.as_slice();
            objects.put(owned.as_str(), &mut reader).await.map(|_| ()).ctx(&format!("put {owned}"))
        });
        put.await.map_err(|e| OpError::passing(format!("put {name}: the client failed ({e})")))??;
        Ok(true)
    }

    /// The bytes of object `name`; `Ok(None)` when it is not in the store.
    ///
    /// Its chunks are read with direct gets (any replica answers), not with the client's
    /// object reader: that one makes an ordered consumer per object, whose creation kept
    /// timing out for a minute after a server of the cluster died (and `async_nats` 0.50
    /// unwraps that error, a panic).
    pub async fn get_object(&self, name: &str) -> Result<Option<Vec<u8>>, OpError> {
        let info = match self.objects.info(name).await {
            Ok(i) if !i.deleted => i,
            Ok(_) => return Ok(None),
            Err(e) if e.kind() == object_store::InfoErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(OpError::passing(format!("object {name}: {e}"))),
        };
        let subject = format!("$O.{}.C.{}", self.config.objects, info.nuid);
        let mut bytes = Vec::with_capacity(info.size);
        let mut seq = 1;
        for _ in 0..info.chunks {
            let m = self
                .object_stream
                .direct_get_next_for_subject(subject.as_str(), Some(seq))
                .await
                .ctx(&format!("read {name}"))?;
            bytes.extend_from_slice(&m.payload);
            seq = m.sequence + 1;
        }
        if bytes.len() != info.size {
            return Err(OpError::passing(format!("read {name}: {} bytes of {}", bytes.len(), info.size)));
        }
        Ok(Some(bytes))
    }

    /// The file `rel` of result `r` of the session `tok`; where an earlier version kept it
    /// (under the inputs alone) when it is not under the result's number.
    pub async fn result_file(&self, tok: &str, r: &ResultRef, rel: &str) -> Result<Option<Vec<u8>>, OpError> {
        match self.get_object(&result_object(tok, &r.inputs, r.number, rel)).await? {
            Some(bytes) => Ok(Some(bytes)),
            None => self.get_object(&legacy_result_object(tok, &r.inputs, rel)).await,
        }
    }

    /// Publishes `payload` to `subject` (with a message id for the stream's duplicate
    /// window) and waits for the stream's acknowledgement.
    pub async fn publish(&self, subject: String, id: Option<&str>, payload: Vec<u8>) -> Result<(), OpError> {
        let mut msg = jetstream::message::PublishMessage::build().payload(payload.into());
        if let Some(id) = id {
            msg = msg.message_id(id);
        }
        let ack = self.js.send_publish(subject.clone(), msg).await.ctx(&format!("publish to {subject}"))?;
        ack.await.ctx(&format!("publish to {subject}"))?;
        Ok(())
    }

    /// A key's value and revision; `None` when absent (never written, deleted, expired).
    pub async fn kv_get(store: &kv::Store, key: &str) -> Result<Option<(Vec<u8>, u64)>, OpError> {
        match store.entry(key).await.ctx(&format!("read {key}"))? {
            Some(e) if e.operation == kv::Operation::Put => Ok(Some((e.value.to_vec(), e.revision))),
            _ => Ok(None),
        }
    }

    /// Reads a session's listing.
    pub async fn listing(&self, tok: &str) -> Result<(Listing, u64), OpError> {
        match Self::kv_get(&self.sessions, &format!("files.{tok}")).await? {
            Some((v, rev)) => Ok((serde_json::from_slice(&v).lasting("listing")?, rev)),
            None => Ok((Listing::default(), 0)),
        }
    }

    /// Reads a session's record and its revision (0: none yet).
    pub async fn record(&self, tok: &str) -> Result<(Record, u64), OpError> {
        match Self::kv_get(&self.sessions, &format!("state.{tok}")).await? {
            Some((v, rev)) => Ok((serde_json::from_slice(&v).lasting("record")?, rev)),
            None => Ok((Record::default(), 0)),
        }
    }

    /// Writes `value` at `key` if its revision is still `rev` (0: if it has none);
    /// `Ok(None)` when someone wrote it since.
    pub async fn kv_swap(
        store: &kv::Store,
        key: &str,
        value: Vec<u8>,
        rev: u64,
    ) -> Result<Option<u64>, OpError> {
        if rev == 0 {
            return match store.create(key, value.into()).await {
                Ok(r) => Ok(Some(r)),
                Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => Ok(None),
                Err(e) => Err(OpError::passing(format!("create {key}: {e}"))),
            };
        }
        match store.update(key, value.into(), rev).await {
            Ok(r) => Ok(Some(r)),
            Err(e) if e.kind() == kv::UpdateErrorKind::WrongLastRevision => Ok(None),
            Err(e) => Err(OpError::passing(format!("update {key}: {e}"))),
        }
    }
}

type Buckets = (object_store::ObjectStore, kv::Store, kv::Store);

/// Tries after the first that [`settled`] makes before it gives up.
const SETUP_RETRIES: u32 = 10;

/// `op`, a set-up request to JetStream (streams, buckets, a durable consumer), tried until
/// it succeeds: each try bounded, since a request can wait on a cluster without a leader,
/// and [`SETUP_RETRIES`] more a second apart. Servers started together elect their leaders
/// within seconds, and a role started among them must wait for that, not die: a worker
/// whose streams were made while its consumer's request timed out exited (`what`: what is
/// set up, for the error and the log).
pub(crate) async fn settled<T, F, Fut>(what: &str, mut op: F) -> Result<T, ClusterError>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<T, ClusterError>>,
{
    let mut tries = 0;
    loop {
        match tokio::time::timeout(Duration::from_secs(20), op()).await {
            Ok(Ok(v)) => return Ok(v),
            Ok(Err(e)) if tries >= SETUP_RETRIES => return Err(e),
            Err(_) if tries >= SETUP_RETRIES => {
                return Err(ClusterError::Setup { what: what.into(), reason: "timed out".into() });
            }
            other => {
                let reason = match other {
                    Ok(Err(e)) => e.to_string(),
                    _ => "timed out".into(),
                };
                tracing::warn!(%reason, tries, what, "JetStream not ready: trying again");
                tries += 1;
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }
}

/// Makes the streams and buckets that are missing (creation is idempotent, so roles that
/// start together do not fight).
async fn ensure(js: &jetstream::Context, config: &NatsConfig) -> Result<Buckets, ClusterError> {
    let setup = |what: String, e: &dyn std::fmt::Display| ClusterError::Setup { what, reason: e.to_string() };
    let replicas = config.replicas;
    let work = stream::Config {
        name: config.stream.clone(),
        subjects: vec![format!("{IN_PREFIX}.>")],
        retention: stream::RetentionPolicy::WorkQueue,
        duplicate_window: config.duplicate_window,
        num_replicas: replicas,
        ..Default::default()
    };
    js.get_or_create_stream(work).await.map_err(|e| setup(format!("stream {}", config.stream), &e))?;
    let out = stream::Config {
        name: config.results_stream.clone(),
        subjects: vec![format!("{OUT_PREFIX}.>"), format!("{EVENTS_PREFIX}.>"), format!("{DEAD_PREFIX}.>")],
        retention: stream::RetentionPolicy::Limits,
        duplicate_window: config.duplicate_window,
        num_replicas: replicas,
        ..Default::default()
    };
    js.get_or_create_stream(out).await.map_err(|e| setup(format!("stream {}", config.results_stream), &e))?;
    let objects = match js.get_object_store(&config.objects).await {
        Ok(o) => o,
        Err(_) => js
            .create_object_store(object_store::Config {
                bucket: config.objects.clone(),
                num_replicas: replicas,
                ..Default::default()
            })
            .await
            .map_err(|e| setup(format!("object store {}", config.objects), &e))?,
    };
    let sessions = kv_bucket(js, &config.sessions, Duration::ZERO, replicas)
        .await
        .map_err(|e| setup(format!("key-value bucket {}", config.sessions), &e))?;
    let leases = kv_bucket(js, &config.leases, config.lease_ttl, replicas)
        .await
        .map_err(|e| setup(format!("key-value bucket {}", config.leases), &e))?;
    Ok((objects, sessions, leases))
}

/// A key-value bucket, made if missing. Its stream is made here with the configuration
/// `async_nats`' `create_key_value` would send (that call first reads the account's
/// JetStream info, whose reply from a 2.9 server the client cannot parse), but for
/// direct gets: with them any replica answers a read, one that has not caught up too,
/// and a worker that read a listing from behind would find a new file's entry missing.
/// Without them the stream's leader answers. A bucket an earlier version made with
/// direct gets is changed.
async fn kv_bucket(
    js: &jetstream::Context,
    bucket: &str,
    max_age: Duration,
    replicas: usize,
) -> Result<kv::Store, String> {
    if let Ok(s) = js.get_key_value(bucket).await {
        let mut config = s.stream.cached_info().config.clone();
        if !config.allow_direct {
            return Ok(s);
        }
        config.allow_direct = false;
        js.update_stream(&config).await.map_err(|e| e.to_string())?;
        return js.get_key_value(bucket).await.map_err(|e| e.to_string());
    }
    let config = stream::Config {
        name: format!("KV_{bucket}"),
        subjects: vec![format!("$KV.{bucket}.>")],
        max_messages_per_subject: 1,
        max_bytes: -1,
        max_messages: -1,
        max_message_size: -1,
        max_age,
        allow_rollup: true,
        deny_delete: true,
        allow_direct: false,
        discard: stream::DiscardPolicy::New,
        num_replicas: replicas,
        ..Default::default()
    };
    js.get_or_create_stream(config).await.map_err(|e| e.to_string())?;
    js.get_key_value(bucket).await.map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A set-up request that fails while the servers elect their leaders is tried again, and
    /// the role goes on once it succeeds (a worker used to exit when its consumer's request
    /// timed out after its streams were made).
    #[test]
    fn a_set_up_request_is_tried_again_until_jetstream_answers() {
        let rt = tokio::runtime::Builder::new_current_thread().enable_time().build().unwrap();
        let calls = std::sync::atomic::AtomicU32::new(0);
        let got = rt.block_on(settled("a consumer", || async {
            match calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed) {
                0 | 1 => Err(ClusterError::Setup { what: "a consumer".into(), reason: "timed out".into() }),
                n => Ok(n),
            }
        }));
        assert_eq!(got.unwrap(), 2, "answered at the third try");
    }

    #[test]
    fn session_tokens_are_plain_names_or_marked_hex_and_never_meet() {
        assert_eq!(token("facade_12-b"), "facade_12-b");
        assert_eq!(token("rue de la paix"), format!("={}", hex(b"rue de la paix")));
        assert_eq!(token("a.b"), "=612e62");
        assert_eq!(token(""), "=");
        for s in ["rue de la paix", "façade", "a.b", "plain_1"] {
            assert_eq!(untoken(&token(s)), s);
        }
        let long = "x".repeat(65);
        assert!(token(&long).starts_with('='));
        // Every token is one subject token and a valid key part.
        for s in ["a.b", "*", ">", "é", "a b", "_root"] {
            let t = token(s);
            assert!(t.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_=".contains(&b)), "{t}");
        }
    }

    #[test]
    fn digests_are_sha256() {
        assert_eq!(sha256_hex(b"abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    }
}
