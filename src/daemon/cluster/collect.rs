//! `clearview collect` (shell layer): mirrors the cluster's results and events into a
//! folder with `clearview run`'s layout — `DIR/<session>/result.<ext>`, `result.json`,
//! `history/`, `confidence.png`, `provenance.png`, `mask.png`, and `DIR/events.jsonl` —
//! so the preview page and the user's scripts work on it unchanged.
//!
//! A durable consumer of the OUT stream, in stream order, acknowledged after each write:
//! a collector that restarts goes on where it stopped. Each file is written atomically
//! (temporary name, fsync, rename), `result.json` after the image it describes, so a
//! reader never sees a result.json naming an image that is not there. A result whose
//! number is not newer than the one on disk is skipped: a replay writes nothing.

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
};
use crate::config::Config;
use crate::daemon::{paths, watch};

/// Runs the collector into `config.out_dir` until `shutdown`; `consumer` is its durable
/// consumer's name (one per collected folder).
pub async fn run(
    mut config: Config,
    consumer: &str,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ClusterError> {
    std::fs::create_dir_all(&config.out_dir)
        .map_err(|source| ClusterError::Io { path: config.out_dir.clone(), source })?;
    config.out_dir = std::fs::canonicalize(&config.out_dir).unwrap_or(config.out_dir);
    crate::daemon::emit::remove_stale_temporaries(&config.out_dir);
    let nats = Arc::new(Nats::connect(&config.nats, "clearview-collect").await?);
    let c = &nats.config;
    let setup = |e: &dyn std::fmt::Display| ClusterError::Setup {
        what: format!("consumer {consumer} on {}", c.results_stream),
        reason: e.to_string(),
    };
    let stream = nats.js.get_stream(&c.results_stream).await.map_err(|e| setup(&e))?;
    let consumer = stream
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
        .map_err(|e| setup(&e))?;
    let cancel = CancellationToken::new();
    {
        let cancel = cancel.clone();
        tokio::spawn(async move {
            shutdown.await;
            tracing::info!("shutdown requested: finishing the write in hand");
            cancel.cancel();
        });
    }
    tracing::info!(out = %config.out_dir.display(), "collect started");
    crate::daemon::systemd::ready();
    let out = Collector { nats: nats.clone(), out: config.out_dir.clone(), history: config.history };
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
    history: usize,
}

impl Collector {
    async fn take(&self, msg: &jetstream::Message) -> Result<(), OpError> {
        let subject = msg.subject.as_str();
        if subject.starts_with(&format!("{EVENTS_PREFIX}.")) {
            self.event(&msg.payload)
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

    /// Appends one event line to `events.jsonl` (one write per line, as `run` does).
    fn event(&self, line: &[u8]) -> Result<(), OpError> {
        let Ok(mut event) = serde_json::from_slice::<serde_json::Value>(line) else {
            tracing::warn!("an event that is not JSON: skipped");
            return Ok(());
        };
        // A result's path is where this folder has it, not where the worker made it.
        let mut line = if event["event"] == "result_updated"
            && let (Some(session), Some(file)) = (event["session"].as_str(), event["result"].as_str())
        {
            let path = self.out.join(paths::session_dir_name(session)).join(file);
            event["path"] = path.to_string_lossy().into_owned().into();
            event.to_string().into_bytes()
        } else {
            line.to_vec()
        };
        if line.last() != Some(&b'\n') {
            line.push(b'\n');
        }
        let path = self.out.join("events.jsonl");
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(&path).ctx("events.jsonl")?;
        f.write_all(&line).ctx("events.jsonl")
    }

    /// Writes a result's files into the session's folder, `result.json` last; nothing when
    /// the folder already has this result or a newer one.
    async fn result(&self, r: ResultMsg) -> Result<(), OpError> {
        if r.session.contains(['/', '\\']) || r.session.starts_with('.') {
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
            let name = super::result_object(&tok, &r.result.inputs, rel);
            let bytes = self
                .nats
                .get_object(&name)
                .await?
                .ok_or_else(|| OpError(format!("{name} is not in the object store")))?;
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
}

/// The number of the result in a session's folder, if it has one.
fn number_on_disk(dir: &Path) -> Option<u64> {
    let bytes = std::fs::read(dir.join("result.json")).ok()?;
    serde_json::from_slice::<serde_json::Value>(&bytes).ok()?["number"].as_u64()
}
