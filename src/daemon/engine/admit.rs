//! Admission (shell layer, part of the engine): an aligned view offered to the session's
//! buffer, and everything said of it — the event (`view_accepted`, `view_rejected`,
//! `view_dropped` for the views it pushed out), the `/metrics` counters, the report's
//! listing. Folder views and video frames go through the same code.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::Instant;

use super::{Ctx, MAX_LISTED, Slot, ViewEntry, ViewStatus};
use crate::daemon::event::{Event, ViewAccepted, ViewAligned, ViewRejected};
use crate::daemon::job::{ViewId, name_of};
use crate::daemon::watch;
use crate::session::{Admission, AlignRecord, Rgb8};

/// An aligned view, as a source offers it.
pub(crate) struct Offer {
    pub(crate) id: ViewId,
    /// A video frame's index and stream time (s).
    pub(crate) frame: Option<(u64, f64)>,
    pub(crate) record: AlignRecord,
    /// The alignment was read from the saved state, not computed.
    pub(crate) from_state: bool,
    pub(crate) align_ms: f64,
    /// When the view reached the service (the update latency runs from there).
    pub(crate) since: Instant,
    /// Its file, to read it again after a keyframe or mask change (none for a frame).
    pub(crate) path: Option<PathBuf>,
}

/// What became of an offered view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Admitted {
    Rejected,
    /// Aligned, but it sees none of the mask.
    OutsideMask,
    /// In the buffer; `improves`: it calls for a fill.
    Buffered {
        improves: bool,
    },
}

impl Slot {
    /// Offers an aligned view (with its pixels when it is accepted and there is a mask)
    /// and reports what became of it. `Err`: the core refused it (its reason).
    pub(crate) fn admit(
        &mut self,
        ctx: &Ctx,
        offer: Offer,
        pixels: Option<&Rgb8>,
    ) -> Result<Admitted, String> {
        let Offer { id, frame, record, from_state, align_ms, since, path } = offer;
        let admission = if frame.is_some() {
            self.session.admit_frame(id.as_str().to_owned(), record.clone(), pixels)
        } else {
            self.session.admit(id.as_str().to_owned(), record.clone(), pixels)
        }
        .map_err(|e| e.to_string())?;
        ctx.stats.views.fetch_add(1, Ordering::Relaxed);
        let name = id.name().to_owned();
        if let Some(p) = path {
            self.paths.insert(id.as_str().to_owned(), p);
        }
        self.seq += 1;
        let view = ViewAligned {
            file: name.clone(),
            frame: frame.map(|f| f.0),
            t: frame.map(|f| (f.1 * 1000.0).round() / 1000.0),
            from_state,
            from_prior: record.from_prior,
            inliers: record.inliers,
            matches: record.matches,
            median_residual_px: record.median_residual_px,
            homography: record.homography,
            align_ms: (align_ms * 10.0).round() / 10.0,
        };
        let m = &ctx.registry.metrics;
        let duplicate = matches!(admission, Admission::Duplicate { .. });
        let (status, reason, admitted) = match admission {
            Admission::Rejected { reason } | Admission::Duplicate { of: reason } => {
                // A copy of a buffered view is turned down as any other view is, naming it.
                let reason = if duplicate {
                    format!(
                        "the same picture as a view already buffered: {} (the same pixels, or the same shot saved again); it adds nothing",
                        name_of(&reason)
                    )
                } else {
                    reason
                };
                m.rejected(&reason);
                tracing::info!(%reason, from_state, "view rejected");
                let e = ViewRejected { view, reason: reason.clone() };
                ctx.emitter.emit(Some(&self.name), &Event::ViewRejected(e));
                (ViewStatus::Rejected, Some(reason), Admitted::Rejected)
            }
            Admission::OutsideMask => {
                m.views_accepted.fetch_add(1, Ordering::Relaxed);
                tracing::info!(from_state, "view accepted, but it sees none of the mask");
                let reason = "sees none of the mask".to_owned();
                let e = ViewAccepted {
                    view,
                    buffered: false,
                    reason: Some(reason.clone()),
                    improves: None,
                    fallback_px: None,
                    weakly_witnessed_px: None,
                    doubtful_px: None,
                };
                ctx.emitter.emit(Some(&self.name), &Event::ViewAccepted(e));
                (ViewStatus::OutsideMask, Some(reason), Admitted::OutsideMask)
            }
            Admission::Accepted { improves, fallback_px, weak_px, doubtful_px, dropped } => {
                tracing::info!(inliers = record.inliers, from_state, improves, "view accepted");
                m.views_accepted.fetch_add(1, Ordering::Relaxed);
                self.pending_since.get_or_insert(since);
                let e = ViewAccepted {
                    view,
                    buffered: true,
                    reason: None,
                    improves: Some(improves),
                    fallback_px: Some(fallback_px),
                    weakly_witnessed_px: Some(weak_px),
                    doubtful_px: Some(doubtful_px),
                };
                ctx.emitter.emit(Some(&self.name), &Event::ViewAccepted(e));
                for d in &dropped {
                    self.dropped_from_buffer(ctx, d);
                }
                (ViewStatus::Buffered, None, Admitted::Buffered { improves })
            }
        };
        self.decided.insert(id.as_str().to_owned());
        let entry = ViewEntry { id, status, reason, record: Some(record), from_state, seq: self.seq };
        self.views.insert(name, entry);
        if self.views.len() > MAX_LISTED
            && let Some(oldest) = self.views.iter().min_by_key(|(_, v)| v.seq).map(|(k, _)| k.clone())
        {
            self.views.remove(&oldest);
        }
        let buffered: std::collections::HashSet<&str> =
            self.session.buffered().iter().map(|b| b.id.as_str()).collect();
        self.paths.retain(|id, _| buffered.contains(id.as_str()));
        Ok(admitted)
    }

    /// View `id` left the buffer to make room for a better one.
    fn dropped_from_buffer(&mut self, ctx: &Ctx, id: &str) {
        const WHY: &str = "contributed least when the buffer was full";
        ctx.registry.metrics.views_dropped.fetch_add(1, Ordering::Relaxed);
        if let Some(v) = self.views.values_mut().find(|v| v.id.as_str() == id) {
            v.status = ViewStatus::Dropped;
            v.reason = Some(WHY.into());
        }
        let name = name_of(id);
        tracing::info!(dropped = %watch::shown(name), "view dropped from the buffer");
        ctx.emitter.emit(Some(&self.name), &Event::ViewDropped { file: name.to_owned(), reason: WHY.into() });
    }

    /// The file `name` now holds content `id` (`None`: nothing usable, `why` says): the
    /// pixels buffered from what it held before leave the buffer, whatever becomes of the
    /// new content (accepted, rejected, unreadable, deleted). A result must never be made
    /// of pixels that no file holds any more.
    pub(crate) fn forget_old_content(&mut self, ctx: &Ctx, name: &str, id: Option<&ViewId>, why: &str) {
        let Some(old) = self.views.get(name).map(|v| v.id.clone()).filter(|old| Some(old) != id) else {
            return;
        };
        self.paths.remove(old.as_str());
        self.decided.remove(old.as_str());
        if self.session.forget_view(old.as_str()) {
            tracing::info!(file = %watch::shown(name), reason = why, "the view's old pixels leave the buffer");
            let reason = format!("{why}: its old pixels are no longer used");
            ctx.emitter.emit(Some(&self.name), &Event::ViewDropped { file: name.to_owned(), reason });
        }
        if let Some(v) = self.views.get_mut(name) {
            v.status = ViewStatus::Dropped;
            v.reason = Some(why.to_owned());
        }
    }
}

#[cfg(test)]
mod tests {

    use image::DynamicImage;

    use super::*;
    use crate::config::Config;
    use crate::daemon::engine::{MaskOrigin, rgb8};
    use crate::daemon::policy::KeySource;
    use crate::geometry::Homography;
    use crate::imaging::Mask;
    use crate::imaging::convert::to_rgb8;

    const W: usize = 96;
    const H: usize = 72;

    fn record() -> AlignRecord {
        AlignRecord {
            accepted: true,
            reason: None,
            homography: Some(Homography::identity().rows()),
            inliers: 50,
            matches: 60,
            checked: 60,
            median_residual_px: Some(0.3),
            coverage: 1.0,
            from_prior: true,
            view_size: (W, H),
        }
    }

    /// A video frame goes through the same admission as a file: the `/metrics` counters
    /// move and a frame pushed out of the full buffer is said (`view_dropped`), with the
    /// same fields as a file's events plus the frame's index and time.
    #[test]
    fn a_video_frame_is_counted_and_reported_like_a_file() {
        let tmp = tempfile::tempdir().unwrap();
        let mut config = Config {
            out_dir: tmp.path().join("out"),
            state_dir: tmp.path().join("state"),
            ..Config::default()
        };
        config.session.buffer = 1;
        let ctx = Ctx::for_test(config);
        let mut slot = Slot::new(&ctx, "video", PathBuf::new());
        let key = DynamicImage::ImageRgb8(to_rgb8(&crate::synth::facade(W, H, 1)));
        let input = Some((0, 0.0, "walk.mp4"));
        slot.set_key(
            &ctx,
            ViewId::frame("frame-000000", 7),
            "frame-000000".into(),
            &key,
            KeySource::Video,
            input,
        );
        let mut mask = Mask::new(W, H, 0);
        for y in 20..40 {
            for x in 30..60 {
                mask.set(x, y, 255);
            }
        }
        slot.set_mask(&ctx, "file|7".into(), mask, MaskOrigin::File("mask.png")).unwrap();
        // Another picture than the keyframe where the mask is (the same one adds nothing).
        let view = rgb8(&DynamicImage::ImageRgb8(to_rgb8(&crate::synth::facade(W, H, 9))));
        for i in 1..=3u64 {
            let name = format!("frame-{i:06}");
            let offer = Offer {
                id: ViewId::frame(&name, 7),
                frame: Some((i, i as f64 / 10.0)),
                record: record(),
                from_state: false,
                align_ms: 2.0,
                since: Instant::now(),
                path: None,
            };
            // Each frame a little different: a copy of a frame is not buffered again.
            let mut frame = view.clone();
            frame.set(0, 0, [i as u8, 0, 0]);
            assert!(matches!(slot.admit(&ctx, offer, Some(&frame)), Ok(Admitted::Buffered { .. })));
        }
        let m = &ctx.registry.metrics;
        assert_eq!(m.views_accepted.load(Ordering::Relaxed), 3);
        assert_eq!(m.views_dropped.load(Ordering::Relaxed), 2, "a buffer of one keeps one");
        let log = std::fs::read_to_string(ctx.config.out_dir.join("events.jsonl")).unwrap();
        let events: Vec<serde_json::Value> = log.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        let kind = |k: &str| events.iter().filter(|e| e["event"] == k).collect::<Vec<_>>();
        let started = kind("session_started");
        assert_eq!(started.len(), 1);
        assert_eq!(
            (started[0]["key_source"].as_str(), started[0]["frame"].as_u64()),
            (Some("video"), Some(0))
        );
        assert_eq!(kind("mask_set")[0]["file"], "mask.png");
        let accepted = kind("view_accepted");
        assert_eq!(accepted.len(), 3);
        assert_eq!(
            (accepted[2]["file"].as_str(), accepted[2]["frame"].as_u64()),
            (Some("frame-000003"), Some(3))
        );
        assert_eq!(accepted[2]["buffered"], true);
        assert!(accepted[2].as_object().unwrap().contains_key("from_state"), "{}", accepted[2]);
        let dropped = kind("view_dropped");
        assert_eq!(dropped.len(), 2, "{log}");
        assert!(dropped.iter().all(|d| d["file"].as_str().unwrap().starts_with("frame-")), "{log}");
    }
}
