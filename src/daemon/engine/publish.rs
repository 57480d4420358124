//! A session's results (shell layer, part of the engine): the fill, the publish rule's
//! outcome, writing a result ([`write_result`], the one place result files are written),
//! retrying one that could not be written, and the snapshot the HTTP server shows.

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::{Instant, SystemTime};

use serde_json::json;
use tokio_util::sync::CancellationToken;

use super::{Backoff, Ctx, Slot, ViewEntry, ViewStatus};
use crate::daemon::emit::rfc3339;
use crate::daemon::event::{Event, ResultUpdated};
use crate::daemon::paths::Inbox;
use crate::daemon::registry::{SessionSnapshot, ViewSnapshot};
use crate::daemon::state::SavedResult;
use crate::daemon::watch;
use crate::inpaint::{Observer, Stage};

/// What a fill step came to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FillStep {
    /// Nothing to fill with (no keyframe, mask or view yet).
    Idle,
    /// Same inputs as the result already on disk (from before a restart): not rewritten.
    Unchanged(u64),
    /// The new fill scores lower: the result is kept.
    NotBetter,
    /// The service is stopping: the fill was given up, nothing written.
    Cancelled,
    /// Result `n` written.
    Written(u64),
    /// Result `n` could not be written: kept, tried again later.
    Failed(u64),
}

impl FillStep {
    /// The number of the result written, if one was.
    pub(crate) fn written(self) -> Option<u64> {
        match self {
            Self::Written(n) => Some(n),
            _ => None,
        }
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

impl Slot {
    /// Fills (whether or not the session calls for it: see `Session::needs_fill`) and
    /// writes a better result.
    pub(crate) fn fill(&mut self, ctx: &Ctx) -> FillStep {
        fill(ctx, self)
    }

    /// Writes the result waiting to be written, when its next try is due; returns its
    /// number when it was written.
    pub(crate) fn retry_pending(&mut self, ctx: &Ctx) -> Option<u64> {
        if !self.pending.as_ref()?.retry.due() {
            return None;
        }
        let p = self.pending.take()?;
        let span = tracing::info_span!("session", session = %watch::shown(&self.name));
        let _enter = span.enter();
        tracing::info!(number = p.number, tries = p.retry.failures() + 1, "writing the result again");
        write_result(ctx, self, p).written()
    }

    /// Publishes the session's snapshot for the HTTP server.
    pub(crate) fn publish(&self, ctx: &Ctx, new_result: Option<u64>) {
        publish(ctx, self, new_result);
    }
}

/// Fills and writes a better result.
fn fill(ctx: &Ctx, slot: &mut Slot) -> FillStep {
    let digest = slot.session.inputs_digest();
    if slot.session.best_score().is_none()
        && let Some(saved) = &slot.state.result
        && saved.digest == digest
    {
        // Same inputs as the result already on disk (from before a restart).
        slot.session.assume_result(saved.score);
        tracing::info!(number = saved.number, "result unchanged since the last run: not rewritten");
        let (number, score) = (saved.number, saved.score);
        ctx.emitter.emit(Some(&slot.name), &Event::ResultUnchanged { number, score });
        return FillStep::Unchanged(number);
    }
    if ctx.cancel.is_cancelled() {
        return FillStep::Cancelled;
    }
    let start = Instant::now();
    tracing::debug!("fill started");
    let mut timings = Timings { current: None, done: Vec::new(), cancel: ctx.cancel.clone() };
    let Some(outcome) = slot.session.fill(&mut timings) else {
        if ctx.cancel.is_cancelled() {
            tracing::info!(
                fill_ms = start.elapsed().as_millis() as u64,
                "stopping: the fill in hand is given up, nothing written"
            );
            return FillStep::Cancelled;
        }
        return FillStep::Idle;
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
        let e = Event::ResultNotBetter {
            score: outcome.score,
            best: outcome.previous,
            backed: outcome.report.witnessed_quality,
            current_backed: outcome.current_backed,
            fill_ms: fill_ms.round(),
        };
        ctx.emitter.emit(Some(&slot.name), &e);
        ctx.registry.metrics.results_not_better.fetch_add(1, Ordering::Relaxed);
        slot.pending_since = None;
        return FillStep::NotBetter;
    };
    let number = slot.state.last_number + 1;
    let report = result_json(ctx, slot, &outcome, number, fallback_share);
    if slot.pending.take().is_some() {
        tracing::info!(number, "a newer result replaces the one waiting to be written");
    }
    write_result(
        ctx,
        slot,
        Pending { outcome, report, number, digest, fill_ms, stages, retry: Backoff::default() },
    )
}

/// A result that could not be written (full disk, read-only folder): kept in memory and
/// written again with a growing delay until it is, or until a newer result replaces it.
/// The files already on disk stay as they were meanwhile.
pub(super) struct Pending {
    outcome: crate::session::FillOutcome,
    report: serde_json::Value,
    pub(super) number: u64,
    digest: u64,
    fill_ms: f64,
    stages: serde_json::Map<String, serde_json::Value>,
    retry: Backoff,
}

/// Writes a result (its maps, image, history, then `result.json`);
/// on failure keeps it as the slot's pending result. The only place result files are
/// written.
fn write_result(ctx: &Ctx, slot: &mut Slot, mut p: Pending) -> FillStep {
    let number = p.number;
    let ext = ctx.emitter.result_name();
    let write_start = Instant::now();
    let image = p.outcome.image.as_ref().expect("a pending result has an image");
    let (key, full) = key_metadata(ctx, slot).unzip();
    // The keyframe's own pixels at its precision (16-bit, or another colour space).
    let precise = full.flatten().and_then(|k| slot.session.with_key_pixels(image, &k));
    let image = precise.as_ref().unwrap_or(image);
    let (maps, legend) = crate::daemon::provenance::result_maps(&slot.session, &p.outcome);
    match ctx.emitter.write_result(&slot.name, number, image, key.as_ref(), &mut p.report, &maps) {
        Ok(path) => {
            slot.legend = legend;
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
            let e = ResultUpdated {
                number,
                path,
                result: ext,
                views,
                masked,
                from_views: r.from_views(),
                from_fallback: fallback_share,
                confident: r.confident_share(),
                doubtful: r.doubtful_share(),
                score,
                previous_score: previous,
                backed: outcome.report.witnessed_quality,
                current_backed: outcome.current_backed,
                fill_ms: fill_ms.round(),
                write_ms: write_ms.round(),
                stages_ms: stages,
                tries: retry.failures() + 1,
            };
            ctx.emitter.emit(Some(&slot.name), &Event::ResultUpdated(e));
            FillStep::Written(number)
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
            let ev = Event::ResultFailed {
                number,
                file: e.path,
                reason: e.source.to_string(),
                tries: p.retry.failures(),
                retry_in_ms: delay.as_millis() as u64,
            };
            ctx.emitter.emit(Some(&slot.name), &ev);
            slot.pending = Some(p);
            FillStep::Failed(number)
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
    let views: Vec<serde_json::Value> = listed(slot)
        .into_iter()
        .map(|v| {
            let used = by_id.get(v.id.as_str());
            json!({
                "file": v.id.name(),
                "status": if used.is_some() { ViewStatus::Used } else { v.status },
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
    let mut report = json!({
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
        "score_rule": "expected quality: the mean over the mask of the confidence that each pixel shows the building (confidence.png); a result is replaced by a new fill only when, with every view so far as witnesses, the new fill agrees with the views at least as well as the result does",
        "views": views,
    });
    // As `clearview fill --report` has it: the surfaces off the wall the sweep found,
    // whether the result was filled through them, and the masked pixels each filled.
    if let Some(surfaces) = &outcome.surfaces {
        report["planes"] = json!(surfaces);
    }
    if outcome.surface_map.is_some() {
        report["surfaces"] = json!(crate::daemon::provenance::SURFACES);
    }
    report
}

/// The numbers of the results in a session's `history/` folder, oldest first.
/// The views a report lists: those aligned against the current keyframe, oldest first.
fn listed(slot: &Slot) -> Vec<&ViewEntry> {
    let mut views: Vec<&ViewEntry> =
        slot.views.values().filter(|v| v.status != ViewStatus::Superseded).collect();
    views.sort_by_key(|v| v.seq);
    views
}

pub(super) fn saved_history(dir: &Path) -> Vec<u64> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut n: Vec<u64> = entries
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.strip_prefix("result-")?.split('.').next()?.parse().ok())
        .collect();
    n.sort_unstable();
    n
}

/// The current mask as `mask.png` beside the results (for the status API and the page).
pub(super) fn write_mask(ctx: &Ctx, slot: &Slot) {
    let Some(mask) = slot.session.mask() else { return };
    let dir = ctx.emitter.session_dir(&slot.name);
    let mut png = std::io::Cursor::new(Vec::new());
    let r = std::fs::create_dir_all(&dir)
        .and_then(|()| {
            crate::imaging::convert::mask_to_luma8(mask)
                .write_to(&mut png, image::ImageFormat::Png)
                .map_err(std::io::Error::other)
        })
        .and_then(|()| crate::fsio::atomic_write(&dir.join("mask.png"), png.get_ref()));
    if let Err(e) = r {
        tracing::warn!(error = %e, "cannot write mask.png");
    }
}

/// After result `number` is written: the bookkeeping of the status API, and the update
/// latency.
fn after_result(
    ctx: &Ctx,
    slot: &mut Slot,
    outcome: &crate::session::FillOutcome,
    number: u64,
    report: serde_json::Value,
) {
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
    let views = listed(slot)
        .into_iter()
        .map(|v| {
            let file = v.id.name().to_owned();
            let filled = slot.filled_by.get(v.id.as_str()).copied();
            let r = v.record.as_ref();
            ViewSnapshot {
                path: slot.dir.join(&file),
                file,
                status: if filled.is_some() && v.status == ViewStatus::Buffered {
                    ViewStatus::Used
                } else {
                    v.status
                }
                .as_str()
                .to_owned(),
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

/// The keyframe's metadata (EXIF, XMP, profile) its result carries, and its pixels at full
/// precision when the session's 8-bit copy lacks some ([`crate::imaging::decode::read_key`]),
/// read again from its file; none when it cannot be read.
fn key_metadata(
    ctx: &Ctx,
    slot: &Slot,
) -> Option<(crate::imaging::meta::Metadata, Option<crate::imaging::RgbF32>)> {
    use std::io::Read;
    let mut bytes = Vec::new();
    Inbox::of(&ctx.config).open(slot.key_path.as_ref()?).ok()?.read_to_end(&mut bytes).ok()?;
    let limits = crate::imaging::decode::DecodeLimits { max_pixels: ctx.config.max_pixels };
    crate::imaging::decode::read_key(&bytes, &limits).ok()
}
