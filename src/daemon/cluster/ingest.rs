//! `clearview ingest` (shell layer): the folder intake of `run` ([`super::super::intake`],
//! unchanged) feeding the cluster instead of worker threads. Each complete file goes to
//! the object store under its SHA-256, into its session's listing, and as a message to
//! the work-queue stream (see [`super`]). It never changes or deletes the user's files.
//! Events (bad files, links refused) go to the local `events.jsonl` of `--state` and to
//! `clearview.events.<session>`.

use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use crossbeam_channel::{RecvTimeoutError, bounded};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::{ClusterError, Context, EVENTS_PREFIX, Entry, FileMsg, IN_PREFIX, NO_SESSION, Nats, OpError};
use crate::config::Config;
use crate::daemon::job::Job;
use crate::daemon::paths::Inbox;
use crate::daemon::{Backlog, Stats, emit, intake, watch};

/// Runs the ingest on `config.watch_dir` until `shutdown`. The local event log is
/// `config.out_dir/events.jsonl`.
pub async fn run(mut config: Config, shutdown: impl Future<Output = ()>) -> Result<(), ClusterError> {
    for dir in [&mut config.watch_dir, &mut config.out_dir] {
        std::fs::create_dir_all(&*dir).map_err(|source| ClusterError::Io { path: dir.clone(), source })?;
        if let Ok(abs) = std::fs::canonicalize(&*dir) {
            *dir = abs;
        }
    }
    let nats = Arc::new(Nats::connect(&config.nats, "clearview-ingest").await?);
    let config = Arc::new(config);
    let cancel = CancellationToken::new();
    let tracker = TaskTracker::new();

    // Events: to the local log, and through a bounded queue to the stream (when it is full
    // an event is only in the local log, and that is logged).
    let (ev_tx, mut ev_rx) = tokio::sync::mpsc::channel::<(Option<String>, String)>(1024);
    let tee: emit::Tee = Arc::new(move |session: Option<&str>, line: &str| {
        if ev_tx.try_send((session.map(str::to_owned), line.to_owned())).is_err() {
            tracing::warn!("event queue full: the event is only in the local log");
        }
    });
    let emitter = Arc::new(emit::Emitter::open(&config)?.with_tee(tee));
    {
        let nats = nats.clone();
        tracker.spawn(async move {
            while let Some((session, line)) = ev_rx.recv().await {
                let tok = session.as_deref().map_or_else(|| NO_SESSION.to_owned(), super::token);
                let subject = format!("{EVENTS_PREFIX}.{tok}");
                if let Err(e) = retry(&CancellationToken::new(), 5, || {
                    nats.publish(subject.clone(), None, line.clone().into_bytes())
                })
                .await
                {
                    tracing::warn!(error = %e, "event not published");
                }
            }
        });
    }

    let backlog = Arc::new(Backlog::default());
    let stats = Arc::new(Stats::default());
    let (job_tx, job_rx) = bounded::<Job>(config.queue.get());
    let publisher = {
        let (nats, config, backlog, cancel) = (nats.clone(), config.clone(), backlog.clone(), cancel.clone());
        let handle = tokio::runtime::Handle::current();
        std::thread::Builder::new()
            .name("clearview-ingest".into())
            .spawn(move || {
                loop {
                    match job_rx.recv_timeout(Duration::from_millis(100)) {
                        Ok(job) => {
                            let session = job.session.clone();
                            let counted = job.image.is_some();
                            let name = job.file.name.clone();
                            match handle.block_on(ingest(&nats, &config, job, &cancel)) {
                                Ok(()) => {}
                                Err(e) => {
                                    tracing::error!(session = %watch::shown(&session), file = %watch::shown(&name), error = %e, "file not ingested");
                                }
                            }
                            if counted {
                                backlog.done(&session);
                            }
                        }
                        Err(RecvTimeoutError::Timeout) if cancel.is_cancelled() => break,
                        Err(RecvTimeoutError::Timeout) => {}
                        Err(RecvTimeoutError::Disconnected) => break,
                    }
                }
            })
            .map_err(|e| ClusterError::Daemon(crate::daemon::DaemonError::Thread(e)))?
    };

    let (hint_tx, hint_rx) = tokio::sync::mpsc::channel(watch::HINT_QUEUE);
    let overflow = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watcher = match config.watch_mode {
        crate::config::WatchMode::Notify => Some(
            watch::start_notify(&config.watch_dir, config.follow_symlinks, hint_tx.clone(), overflow.clone())
                .map_err(|source| crate::daemon::DaemonError::Watch {
                    path: config.watch_dir.clone(),
                    source,
                })?,
        ),
        crate::config::WatchMode::Poll { .. } => None,
    };
    drop(hint_tx);
    let intake = intake::Intake::new(config.clone(), vec![job_tx], backlog, emitter.clone(), stats);
    tracker.spawn(intake.run(hint_rx, overflow, cancel.clone(), watcher));
    tracing::info!(watch = %config.watch_dir.display(), servers = %config.nats.servers.join(","), "ingest started");
    crate::daemon::systemd::ready();
    tracker.close();

    shutdown.await;
    tracing::info!("shutdown requested: finishing the file in hand");
    crate::daemon::systemd::stopping();
    cancel.cancel();
    let _ = tokio::task::spawn_blocking(move || publisher.join()).await;
    drop(emitter);
    let grace = config.grace_period;
    if tokio::time::timeout(grace, tracker.wait()).await.is_err() {
        tracing::warn!("grace period over: events may be left unpublished");
    }
    tracing::info!("ingest stopped");
    Ok(())
}

/// Tries `op` up to `tries` times (or until `cancel`, or a lasting failure), waiting
/// 0.5 s, 1 s, 2 s… between.
pub(crate) async fn retry<T, F, Fut>(cancel: &CancellationToken, tries: u32, mut op: F) -> Result<T, OpError>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<T, OpError>>,
{
    let mut delay = Duration::from_millis(500);
    let mut n = 0;
    loop {
        match op().await {
            Ok(v) => return Ok(v),
            Err(e) if e.lasting || n + 1 >= tries || cancel.is_cancelled() => return Err(e),
            Err(e) => {
                tracing::warn!(error = %e, retry_in_ms = delay.as_millis() as u64, "NATS operation failed: trying again");
                tokio::time::sleep(delay).await;
                delay = (delay * 2).min(Duration::from_secs(10));
                n += 1;
            }
        }
    }
}

/// One file (or deletion) to the cluster: object, listing entry, message. Tried again
/// while the cluster cannot take it (a server down, no leader for a moment), until the
/// service stops.
async fn ingest(nats: &Nats, config: &Config, job: Job, cancel: &CancellationToken) -> Result<(), OpError> {
    let Job { session, path, role, file, image } = job;
    let entry = match image {
        None => Entry {
            name: file.name.clone(),
            role: super::role_name(role).into(),
            size: 0,
            mtime_ns: 0,
            digest: None,
        },
        Some(image) => {
            drop(image);
            // The bytes that were decoded: the same size and time, read through the inbox
            // (no link followed); a file that changed since is brought again by the intake.
            let bytes = {
                use std::io::Read;
                let mut f = Inbox::of(config).open(&path).ctx("open")?;
                let mut b = Vec::new();
                f.read_to_end(&mut b).ctx("read")?;
                let meta = f.metadata().ctx("read")?;
                if meta.len() != file.size
                    || meta.modified().ok() != Some(file.mtime)
                    || b.len() as u64 != file.size
                {
                    tracing::info!(file = %watch::shown_path(&path), "changed since it was decoded: left to the next look");
                    return Ok(());
                }
                b
            };
            let digest = super::sha256_hex(&bytes);
            let mtime_ns =
                file.mtime.duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64);
            let object = super::file_object(&digest);
            retry(cancel, u32::MAX, || nats.put_object(&object, &bytes)).await?;
            Entry {
                name: file.name.clone(),
                role: super::role_name(role).into(),
                size: file.size,
                mtime_ns,
                digest: Some(digest),
            }
        }
    };
    let tok = super::token(&session);
    let (place, added) = retry(cancel, u32::MAX, || append(nats, &tok, &entry)).await?;
    // A file's id is its place in the listing, its content, session, name and time: the
    // same file ingested again (a restart, a second ingest) is dropped by the stream, and a
    // file put back after another of its name (a mask restored from a copy that keeps its
    // time) is a new entry and a new message. A deletion's id is its moment.
    let when = match &entry.digest {
        Some(d) => format!("{d}:{}", entry.mtime_ns),
        None => format!(
            "deleted:{}",
            SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_nanos())
        ),
    };
    let id = format!("{place}:{when}:{tok}:{}", super::sha256_hex(entry.name.as_bytes()));
    let msg =
        serde_json::to_vec(&FileMsg { session: session.clone(), entry: entry.clone() }).ctx("message")?;
    retry(cancel, u32::MAX, || nats.publish(format!("{IN_PREFIX}.{tok}"), Some(&id), msg.clone())).await?;
    tracing::info!(
        session = %watch::shown(&session),
        file = %watch::shown(&entry.name),
        digest = entry.digest.as_deref().unwrap_or("deleted"),
        new = added,
        "file ingested"
    );
    Ok(())
}

/// Appends `entry` to the session's listing (compare-and-set), unless the listing's last
/// entry for that name is the same; returns the entry's place in the listing and whether
/// it was appended.
async fn append(nats: &Nats, tok: &str, entry: &Entry) -> Result<(usize, bool), OpError> {
    let key = format!("files.{tok}");
    loop {
        let (mut listing, rev) = nats.listing(tok).await?;
        if let Some(i) = listing.entries.iter().rposition(|e| e.name == entry.name)
            && listing.entries[i] == *entry
        {
            return Ok((i, false));
        }
        listing.entries.push(entry.clone());
        let place = listing.entries.len() - 1;
        let bytes = serde_json::to_vec(&listing).ctx("listing")?;
        if Nats::kv_swap(&nats.sessions, &key, bytes, rev).await?.is_some() {
            return Ok((place, true));
        }
        // Another ingest appended meanwhile: read again.
    }
}
