//! The session thread of one video source (shell layer): takes the frames the decoder
//! kept, aligns each against the keyframe (the prior: the camera's motion so far,
//! [`predict`]; a frame the keyframe cannot place is chained through the last accepted
//! frame, [`Runner::chain`]) and hands it to the session engine
//! ([`crate::daemon::engine::Slot`]), which admits, reports and fills exactly as for a
//! photo.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant, SystemTime};

use crossbeam_channel::{Receiver, RecvTimeoutError};
use image::{DynamicImage, RgbImage};
use tokio_util::sync::CancellationToken;

use super::{KEYFRAME_FILE, Msg, VideoStats};
use crate::align::{Frame, align_near_prior};
use crate::config::{VideoMask, VideoSource};
use crate::daemon::engine::{Admitted, Ctx, MaskOrigin, Offer, Slot, rgb8};
use crate::daemon::event::Event;
use crate::daemon::job::ViewId;
use crate::daemon::policy::KeySource;
use crate::daemon::state;
use crate::geometry::Homography;
use crate::imaging::convert::to_luminance;
use crate::imaging::{GrayF32, Mask, RgbF32};
use crate::inpaint::{Source, auto_mask};
use crate::session::{AlignRecord, Rgb8, Session, SessionParams};

/// Kept frames from before the keyframe that wait for it (the latest ones): four seconds
/// of a walk at the default kept rate (`SelectParams::max_kept_fps`, 5), so that with the
/// keyframe at frame 30 of a 10 fps walk the frames from its start, which saw what only
/// they saw, are still there. Bounded: a full frame each.
const PRE_KEY_FRAMES: usize = 20;

/// Frames buffered without calling for a fill after which a video refills anyway.
const REFILL_AFTER: usize = 4;

/// The latest accepted frames (the keyframe among them) against which a new frame's own
/// occluders are found ([`Runner::own_occluders`]).
const NEIGHBOURS: usize = 3;

/// An accepted frame waiting for the automatic mask: its id, index and time, alignment,
/// pixels and alignment time.
type Stashed = (ViewId, (u64, f64), AlignRecord, Rgb8, f64);

/// The session thread of one source.
pub(super) struct Runner {
    ctx: Ctx,
    src: VideoSource,
    stats: Arc<VideoStats>,
    slot: Slot,
    mask: Option<Mask>,
    /// Stream times and homographies of the last two accepted frames: the next frame's
    /// prior is their motion carried on ([`predict`]), or the last one's alone.
    track: VecDeque<(f64, Homography)>,
    /// Accepted frames waiting for the automatic mask.
    stash: Vec<Stashed>,
    /// The last frame accepted (the frames before the keyframe, aligned nearest first,
    /// chain among themselves; the frames after it from the first one accepted after it):
    /// its stream time, keyframe → frame map and grey pixels. A frame the keyframe alone
    /// cannot place is aligned to it and the two maps chained ([`Self::chain`]).
    last_accepted: Option<(f64, Homography, GrayF32)>,
    /// The latest accepted frames (at most [`NEIGHBOURS`], the keyframe first): their
    /// keyframe → frame maps and pixels, the evidence for a new frame's own occluders.
    neighbours: VecDeque<(Homography, RgbF32)>,
    /// Kept frames that arrived before the keyframe (at most [`PRE_KEY_FRAMES`], the
    /// latest): aligned once it is set, since they saw what the keyframe's occluders hide.
    pre_key: VecDeque<(u64, f64, DynamicImage, Instant)>,
    /// Frames buffered since the last fill (improving or not).
    buffered_since_fill: usize,
    /// Arrival time of the oldest frame admitted since the last fill.
    pending_since: Option<Instant>,
    run_id: u128,
}

impl Runner {
    pub(super) fn new(ctx: Ctx, src: VideoSource, stats: Arc<VideoStats>, mask: Option<Mask>) -> Self {
        let mut slot = Slot::new(&ctx, &src.session, PathBuf::new());
        slot.session = Session::new(walk_params(slot.session.params().clone()));
        let run_id = SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        Self {
            ctx,
            src,
            stats,
            slot,
            mask,
            track: VecDeque::new(),
            stash: Vec::new(),
            pre_key: VecDeque::new(),
            last_accepted: None,
            neighbours: VecDeque::new(),
            buffered_since_fill: 0,
            pending_since: None,
            run_id,
        }
    }

    pub(super) fn run(mut self, rx: &Receiver<Msg>, cancel: &CancellationToken) {
        let span = tracing::info_span!("session", session = %self.src.session);
        let _enter = span.enter();
        let heart = self.ctx.stats.heartbeats.register(format!("video {}", self.src.session));
        loop {
            heart.beat();
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(Msg::Frame { index, t, key, width, height, rgb, arrived }) => {
                    if cancel.is_cancelled() {
                        break;
                    }
                    let Some(image) = RgbImage::from_raw(width as u32, height as u32, rgb) else { continue };
                    let image = DynamicImage::ImageRgb8(image);
                    if key {
                        self.take_key(index, t, &image);
                        self.take_pre_key();
                    } else if self.slot.session.key_id().is_none() {
                        if self.pre_key.len() == PRE_KEY_FRAMES {
                            self.pre_key.pop_front();
                        }
                        self.pre_key.push_back((index, t, image, arrived));
                        continue;
                    } else {
                        self.take_frame(index, t, &image, arrived);
                    }
                    let batch = self.ctx.config.batch_max.get();
                    // A file read at the service's pace fills after every frame that calls
                    // for it (results follow the camera); a stream fills when it has caught
                    // up, or after `batch_max` frames.
                    if !self.src.realtime || rx.is_empty() || self.slot.session.admitted_since_fill() >= batch
                    {
                        self.fill();
                    }
                }
                Ok(Msg::End { reason }) => {
                    // The final result: with every witness buffered since the last fill.
                    if self.buffered_since_fill > 0 {
                        self.slot.session.request_fill();
                    }
                    self.fill();
                    match &reason {
                        Some(r) => tracing::error!(reason = %r, "video ended with an error"),
                        None => tracing::info!("video ended"),
                    }
                    let e = Event::VideoEnded {
                        counters: self.stats.counters(),
                        input: self.src.input.clone(),
                        reason,
                        results: self.slot.state.last_number,
                    };
                    self.ctx.emitter.emit(Some(&self.src.session), &e);
                    break;
                }
                Err(RecvTimeoutError::Timeout) => {
                    if cancel.is_cancelled() {
                        break;
                    }
                    self.fill();
                }
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        if self.slot.state_dirty {
            state::save(&self.ctx.config.state_dir, &self.slot.name, &self.slot.state);
        }
    }

    /// Writes the keyframe beside the results (`keyframe.png`), so that a mask can be
    /// painted on exactly that frame.
    fn write_keyframe(&self, image: &DynamicImage) {
        let dir = self.ctx.config.out_dir.join(&self.slot.name);
        let mut png = Vec::new();
        let written = std::fs::create_dir_all(&dir)
            .and_then(|()| {
                image
                    .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                    .map_err(std::io::Error::other)
            })
            .and_then(|()| crate::fsio::atomic_write(&dir.join(KEYFRAME_FILE), &png));
        if let Err(e) = written {
            tracing::error!(error = %e, dir = %dir.display(), "cannot write {KEYFRAME_FILE}");
        }
    }

    fn frame_name(index: u64) -> String {
        format!("frame-{index:06}")
    }

    fn take_key(&mut self, index: u64, t: f64, image: &DynamicImage) {
        let name = Self::frame_name(index);
        let id = ViewId::frame(&name, self.run_id);
        self.track.clear();
        self.track.push_back((t, Homography::identity()));
        self.last_accepted = None;
        self.neighbours.clear();
        self.neighbours.push_back((Homography::identity(), rgb8_to_f32(&rgb8(image))));
        let (w, h) = (image.width(), image.height());
        tracing::info!(key = %name, t, width = w, height = h, "keyframe set");
        self.write_keyframe(image);
        let frame = Some((index, t, self.src.input.as_str()));
        self.slot.set_key(&self.ctx, id, PathBuf::from(&name), image, KeySource::Video, frame);
        if let Some(mask) = self.mask.clone() {
            let file = match &self.src.mask {
                VideoMask::File(p) => p.display().to_string(),
                VideoMask::Auto { .. } => String::new(),
            };
            let id = format!("file|{}", self.run_id);
            if let Err(reason) = self.slot.set_mask(&self.ctx, id, mask, MaskOrigin::File(&file)) {
                tracing::error!(error = %reason, "the mask does not fit the video");
                self.ctx.emitter.emit(Some(&self.slot.name), &Event::MaskRejected { reason });
            }
        }
    }

    /// Aligns the frames kept before the keyframe, nearest first (each one's homography
    /// is the next one's prior), then restarts the track from the keyframe. The nearest
    /// of them, when accepted, stays in the track before the keyframe: it gives the
    /// frames after the keyframe the camera's speed, where the keyframe alone predicts no
    /// motion at all (a walk moves 30 px between kept frames, far outside guided
    /// matching's window).
    fn take_pre_key(&mut self) {
        let Some(&(t_key, _)) = self.track.back() else { return };
        let mut nearest = None;
        while let Some((index, t, image, arrived)) = self.pre_key.pop_back() {
            self.take_frame(index, t, &image, arrived);
            if nearest.is_none() {
                nearest = Some(self.track.back().copied().filter(|&(tn, _)| tn != t_key));
            }
        }
        self.track.clear();
        self.track.extend(nearest.flatten());
        self.track.push_back((t_key, Homography::identity()));
        // The frames after the keyframe chain from those after it, never across it.
        self.last_accepted = None;
        // Their own occluders are judged against the keyframe and the frames after it.
        self.neighbours.truncate(1);
    }

    fn take_frame(&mut self, index: u64, t: f64, image: &DynamicImage, arrived: Instant) {
        if self.slot.session.key_id().is_none() {
            return;
        }
        self.ctx.registry.metrics.views_received.fetch_add(1, Ordering::Relaxed);
        let id = ViewId::frame(&Self::frame_name(index), self.run_id);
        let start = Instant::now();
        let prior = predict(&self.track, t);
        let gray = to_luminance(image);
        let mut record = match self.slot.session.align_with_prior(gray.clone(), prior) {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!(frame = index, error = %e, "frame skipped");
                return;
            }
        };
        // Refused, or placed by the descriptors away from the camera's predicted motion:
        // the last accepted frame has most of the picture in common with this one.
        if (!record.accepted || (prior.is_some() && !record.from_prior))
            && let Some(chained) = self.chain(&gray, prior)
            && (!record.accepted || disagree(&record, &chained))
        {
            tracing::info!(
                frame = index,
                direct = record.reason.as_deref().unwrap_or("accepted elsewhere"),
                inliers = chained.inliers,
                "aligned through the last accepted frame"
            );
            record = chained;
        }
        let align_ms = start.elapsed().as_secs_f64() * 1e3;
        self.stats.aligned.fetch_add(1, Ordering::Relaxed);
        if record.accepted
            && let Some(h) = record.homography()
        {
            if self.track.len() == 2 {
                self.track.pop_front();
            }
            self.track.push_back((t, h));
            self.last_accepted = Some((t, h, gray));
        }
        if self.slot.session.mask_id().is_none()
            && let VideoMask::Auto { views } = self.src.mask
        {
            if !record.accepted {
                self.admit(id, (index, t), record, None, align_ms, arrived);
                return;
            }
            self.stash.push((id, (index, t), record, rgb8(image), align_ms));
            if self.stash.len() >= views {
                self.auto_mask();
            }
            return;
        }
        let pixels = record.accepted.then(|| rgb8(image));
        let h = record.homography().filter(|_| record.accepted);
        let before = self.slot.session.inputs_digest();
        let key = id.as_str().to_owned();
        if self.admit(id, (index, t), record, pixels.as_ref(), align_ms, arrived) {
            self.pending_since.get_or_insert(arrived);
        }
        if let (Some(h), Some(px)) = (h, pixels) {
            self.own_occluders(&key, h, rgb8_to_f32(&px));
        }
        if self.slot.session.inputs_digest() != before {
            self.buffered_since_fill += 1;
            // Frames that see only well-witnessed pixels do not call for a fill by the
            // improvement rule, but a few of them can outvote views that saw the
            // occluder there: refill after REFILL_AFTER of them.
            if self.buffered_since_fill >= REFILL_AFTER {
                self.slot.session.request_fill();
                self.pending_since.get_or_insert(arrived);
            }
        }
    }

    /// A frame the keyframe alone could not place, aligned to the last accepted frame
    /// instead (guided from the prior carried into that frame's coordinates, no
    /// descriptor race: [`align_near_prior`]) and the two maps chained: keyframe → last
    /// accepted → this frame. When near occluders hide much of the keyframe, the frames
    /// further along the walk share only a sliver of it clear (too few details to
    /// recognise, or an alias of a repeating facade), while consecutive kept frames share
    /// most of the picture; and those are the frames that see what the keyframe's
    /// occluders hide (BENCHMARKS.md, "Video target, eighth pass"). The caller asks for it
    /// when the keyframe refused the frame or placed it from descriptors rather than the
    /// prior, and takes it over an accepted direct alignment only when the two
    /// [`disagree`]. `None` without an earlier accepted frame or a prior, or when that
    /// alignment is refused too.
    fn chain(&self, gray: &GrayF32, prior: Option<Homography>) -> Option<AlignRecord> {
        let (_, to_last, last) = self.last_accepted.as_ref()?;
        let prior = prior?.after(&to_last.inverse()?);
        let params = &self.slot.session.params().align;
        let a = align_near_prior(
            &Frame::new(last.clone(), params),
            &Frame::new(gray.clone(), params),
            params,
            &prior,
        );
        let mut record = AlignRecord::from_alignment(&a, (gray.width(), gray.height()));
        let Some(h) = a.homography.filter(|_| a.accepted()) else {
            tracing::debug!(
                reason = record.reason.as_deref().unwrap_or(""),
                "not aligned to the last accepted frame either"
            );
            return None;
        };
        record.homography = Some(h.after(to_last).rows());
        Some(record)
    }

    /// Finds the occluders of buffered frame `id` (keyframe → frame map `h`, pixels `rgb`)
    /// against the latest accepted frames, as the automatic mask finds a keyframe's
    /// ([`crate::inpaint::auto_mask`], the frame in the keyframe's place), and has the
    /// fill never copy them; then the frame joins those neighbours. A walk's near trees,
    /// cars and people move against the facade from one frame to the next, so each frame's
    /// own occluders disagree with the facade its neighbours show there; the occlusion
    /// model, judging every frame's pixel against the others, doubts them but not always
    /// enough when several frames carry pieces of occluders over one pixel (BENCHMARKS.md,
    /// "Video target, tenth pass").
    fn own_occluders(&mut self, id: &str, h: Homography, rgb: RgbF32) {
        let buffered = self.slot.session.buffered().iter().any(|b| b.id == id && b.has_pixels());
        if buffered && let Some(back) = h.inverse() {
            let sources: Vec<Source<'_>> = self
                .neighbours
                .iter()
                .map(|(g, image)| Source { image, homography: g.after(&back) })
                .collect();
            let mut params = self.slot.session.params().auto_mask.clone();
            params.min_views = params.min_views.min(sources.len());
            // The walk's marks were measured without the regrowth (BENCHMARKS.md, "Video
            // target, tenth pass"), and they already cover too much on some walks. Neighbouring
            // frames' own objects explaining their disagreement cost two walks 3 and 4 dB
            // (BENCHMARKS.md, "--mask auto: the views' own objects").
            params.regrowth_passes = 0;
            params.own_objects = false;
            let mask = auto_mask(&rgb, &sources, &params);
            drop(sources);
            let share = mask.as_slice().iter().filter(|&&v| v > 127).count() as f64
                / mask.as_slice().len().max(1) as f64;
            tracing::debug!(view = id, share, "a frame's own occluders");
            self.slot.session.set_view_occluders(id, &mask);
        }
        if self.neighbours.len() >= NEIGHBOURS {
            // The keyframe stays: it is the one every frame overlaps most with the mask.
            self.neighbours.remove(1);
        }
        self.neighbours.push_back((h, rgb));
    }

    /// The automatic mask from the stashed frames, then their admission with pixels.
    fn auto_mask(&mut self) {
        let views: Vec<(RgbF32, Homography)> = self
            .stash
            .iter()
            .filter_map(|(_, _, r, px, _)| Some((rgb8_to_f32(px), r.homography()?)))
            .collect();
        let mask = match self.slot.session.auto_mask(&views) {
            Ok(m) => m,
            Err(e) => {
                tracing::warn!(error = %e, "automatic mask failed; trying with later frames");
                self.stash.remove(0);
                return;
            }
        };
        drop(views);
        let id = format!("auto|{}", self.stash.iter().map(|s| s.0.name()).collect::<Vec<_>>().join("|"));
        if self.slot.set_mask(&self.ctx, id, mask, MaskOrigin::Auto(self.stash.len())).is_err() {
            return;
        }
        for (id, frame, record, px, align_ms) in std::mem::take(&mut self.stash) {
            let now = Instant::now();
            if self.admit(id, frame, record, Some(&px), align_ms, now) {
                self.pending_since.get_or_insert(now);
            }
        }
    }

    /// Offers an aligned frame to the session (which reports it); `true` when it calls for
    /// a fill.
    fn admit(
        &mut self,
        id: ViewId,
        frame: (u64, f64),
        record: AlignRecord,
        pixels: Option<&Rgb8>,
        align_ms: f64,
        since: Instant,
    ) -> bool {
        let index = frame.0;
        let offer = Offer { id, frame: Some(frame), record, from_state: false, align_ms, since, path: None };
        match self.slot.admit(&self.ctx, offer, pixels) {
            Ok(admitted) => admitted == Admitted::Buffered { improves: true },
            Err(e) => {
                tracing::warn!(frame = index, error = %e, "frame skipped");
                false
            }
        }
    }

    fn fill(&mut self) {
        self.slot.retry_pending(&self.ctx);
        if !self.slot.session.needs_fill() {
            self.slot.save_state(&self.ctx);
            return;
        }
        self.buffered_since_fill = 0;
        let step = self.slot.fill(&self.ctx);
        if let Some(since) = self.pending_since.take()
            && step.written().is_some()
        {
            self.stats.latency_ms_sum.fetch_add(since.elapsed().as_millis() as u64, Ordering::Relaxed);
            self.stats.latency_n.fetch_add(1, Ordering::Relaxed);
        }
        self.slot.save_state(&self.ctx);
    }
}

/// The session's parameters for a walk: where every view doubts a pixel, the fill leaves
/// it to the fallback rather than copying the least doubtful view (`sure` down to `cut`).
/// A walk's frames come from one camera along one path, so a pixel all of them doubt is a
/// near occluder they all passed, not a view's light (the folder service keeps copying it:
/// a darker view is doubted over a ledge there and was right, BENCHMARKS.md "Does every
/// view make the one-shot fill better?"). So is a pixel every frame that sees it marks as
/// its own occluder ([`Runner::own_occluders`]): it goes to the fallback too, however many
/// frames see it.
///
/// The fallback's guide takes the confident view pixels around what it fills, as in the
/// service. Before the frames' own occluders were marked, the view pixels next to what no
/// frame saw clear were mostly the fringe of those occluders, and a guide from the
/// keyframe alone did better (BENCHMARKS.md, "Video target, ninth pass"); with the marks,
/// and with the marked pixels left to the fallback, the fallback has large pieces of sky
/// and wall to invent beside frames that saw their surroundings, and the views' guide wins
/// (seed 16 `--keyframe-frame 30`: 16.81 → 27.85 dB; 17 of 24 cases gain, 5 lose up to
/// 1.8 dB, none below the target; BENCHMARKS.md "Video target, thirteenth session"). The
/// guide alone loses (seed 16 stays at 16.8 dB, seed 14's first frame falls below 27).
///
/// A walk's fill uses every buffered frame (no choice of views, `FillParams::select_views`):
/// frames come in batches between fills, and each candidate would cost a trial fill; the
/// choice was measured on the folder service's cases, not yet on walks.
///
/// Nor is a frame moved onto the keyframe around the hole (`FillParams::local_shift`): a
/// walk's frames are chained from their neighbours and land where they should, while their
/// bands hold the near trees' edges their own marks miss. On the 48 walk cases the shift
/// met the target on as many (43) but lowered the mean 34.72 → 34.56 dB: two gains of
/// 1.3–1.8 dB, five losses of 0.3–7.9 dB (seed 17 `--keyframe-frame 30`: 41.09 → 33.16).
fn walk_params(mut params: SessionParams) -> SessionParams {
    let fill = &mut params.fill;
    fill.occlusion_model.sure = fill.occlusion_model.cut;
    fill.select_views = false;
    fill.local_shift = None;
    params
}

/// Whether two alignments of one frame place the keyframe differently: a grid of the
/// frame's points, taken back to the keyframe by `b` and sent to the frame again by `a`,
/// lands more than [`DISAGREE_PX`] away from where it started (median). A direct alignment
/// accepted on an alias of a repeating facade lands a period or more away (233 px in
/// `tests/video.rs`).
fn disagree(a: &AlignRecord, b: &AlignRecord) -> bool {
    let (Some(ha), Some(hb)) = (a.homography(), b.homography()) else { return true };
    let Some(back) = hb.inverse() else { return true };
    let (w, h) = (b.view_size.0 as f64, b.view_size.1 as f64);
    // The frame's points, taken back to the keyframe by `b` and sent again by `a`.
    ha.after(&back)
        .median_grid_gap(&Homography::identity(), w, h, |_| true)
        .is_none_or(|gap| gap > DISAGREE_PX)
}

/// Median disagreement (frame pixels) beyond which two alignments of a frame differ.
const DISAGREE_PX: f64 = 4.0;

/// The prior for a frame at time `t` from the last accepted frames: the latest
/// homography, carried on at the speed of the last two (entries extrapolated linearly in
/// time, at most three intervals ahead). A camera panning steadily is predicted to within
/// a few pixels, so guided matching finds it without descriptors. The track may run
/// backwards in time (the frames before a keyframe, aligned nearest first): it is
/// extrapolated the same way.
fn predict(track: &VecDeque<(f64, Homography)>, t: f64) -> Option<Homography> {
    let (t2, h2) = *track.back()?;
    let Some(&(t1, h1)) = track.len().checked_sub(2).and_then(|i| track.get(i)) else { return Some(h2) };
    if (t2 - t1).abs() <= 1e-6 {
        return Some(h2);
    }
    let r = ((t - t2) / (t2 - t1)).clamp(0.0, 3.0);
    let (a, b) = (normalised(&h1), normalised(&h2));
    let mut rows = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            rows[i][j] = b[i][j] + (b[i][j] - a[i][j]) * r;
        }
    }
    Homography::from_rows(rows).or(Some(h2))
}

fn normalised(h: &Homography) -> [[f64; 3]; 3] {
    let r = h.rows();
    let s = if r[2][2].abs() > 1e-12 { 1.0 / r[2][2] } else { 1.0 };
    r.map(|row| row.map(|v| v * s))
}

fn rgb8_to_f32(px: &Rgb8) -> RgbF32 {
    px.map(|p| p.map(|v| v as f32 / 255.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_walk_leaves_what_every_frame_doubts_to_the_fallback() {
        let base = SessionParams::default();
        let walk = walk_params(base.clone());
        let (model, fill) = (&walk.fill.occlusion_model, &walk.fill);
        assert_eq!(model.sure, model.cut, "a pixel every frame doubts is not copied");
        assert!(!fill.select_views, "a walk's fill chooses no frames");
        assert!(fill.local_shift.is_none(), "a walk's frames are not moved around the hole");
        // The rest is the service's: the fallback's guide among it.
        let mut back = walk.clone();
        back.fill.occlusion_model.sure = base.fill.occlusion_model.sure;
        back.fill.select_views = base.fill.select_views;
        back.fill.local_shift = base.fill.local_shift.clone();
        assert_eq!(back, base);
    }

    /// With the keyframe named at frame 30 of a 10 fps walk (three seconds in), the
    /// default selection keeps many of the frames before it (the pixels a near occluder
    /// hides only briefly are seen by few frames), and every one it keeps (the warm-up's
    /// included) waits for the keyframe: the first ones saw what only they saw. At 2 kept
    /// frames a second and a bound of 8, 5 frames were kept after the warm-up.
    #[test]
    fn the_frames_of_a_walks_first_three_seconds_wait_for_its_keyframe() {
        use crate::imaging::sharpness::tests::{measure, texture};
        use crate::imaging::sharpness::{FrameSelector, SelectParams, Verdict};
        let params = SelectParams::default();
        let warmup = params.warmup_frames;
        let mut selector = FrameSelector::new(params);
        let mut kept = 0;
        for i in 0..30 {
            // A textured facade panning 4 px a frame.
            let m = measure(&texture(80, 60, 4 * i));
            kept += usize::from(selector.offer(i as f64 / 10.0, &m, false) == Verdict::Keep);
        }
        assert!(kept >= 8, "{kept} frames kept after the warm-up");
        assert!(kept + warmup <= PRE_KEY_FRAMES, "{kept} + {warmup} frames for {PRE_KEY_FRAMES}");
    }

    #[test]
    fn a_steady_pan_is_predicted() {
        let mut track = VecDeque::new();
        assert!(predict(&track, 1.0).is_none());
        track.push_back((0.0, Homography::translation(-10.0, 0.0)));
        let h = predict(&track, 1.0).unwrap();
        assert!((h.rows()[0][2] + 10.0).abs() < 1e-9, "one frame: its homography");
        track.push_back((0.5, Homography::translation(-30.0, 2.0)));
        let h = predict(&track, 1.0).unwrap().rows();
        assert!((h[0][2] + 50.0).abs() < 1e-9 && (h[1][2] - 4.0).abs() < 1e-9, "{h:?}");
        // Far ahead: at most three intervals.
        let h = predict(&track, 10.0).unwrap().rows();
        assert!((h[0][2] + 90.0).abs() < 1e-9, "{h:?}");
    }

    #[test]
    fn a_track_running_backwards_is_predicted_too() {
        // The frames before a keyframe at t = 3, aligned nearest first.
        let mut track = VecDeque::new();
        track.push_back((3.0, Homography::identity()));
        track.push_back((2.5, Homography::translation(30.0, -1.0)));
        let h = predict(&track, 2.0).unwrap().rows();
        assert!((h[0][2] - 60.0).abs() < 1e-9 && (h[1][2] + 2.0).abs() < 1e-9, "{h:?}");
        // Past the keyframe, from the nearest earlier frame: the same speed, onwards.
        let mut track = VecDeque::new();
        track.push_back((2.5, Homography::translation(30.0, 0.0)));
        track.push_back((3.0, Homography::identity()));
        let h = predict(&track, 3.5).unwrap().rows();
        assert!((h[0][2] + 30.0).abs() < 1e-9, "{h:?}");
    }
}
