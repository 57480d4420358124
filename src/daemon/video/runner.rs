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
use crate::inpaint::follow::{FollowParams, follow_occluders};
use crate::inpaint::{AutoMask, AutoMaskParams, CONFIDENT, FAINT_MARK, Source, auto_mask_report};
use crate::session::{AlignRecord, Rgb8, Session, SessionParams};

/// Kept frames from before the keyframe that wait for it (the latest ones): four seconds
/// of a walk at the default kept rate (`SelectParams::max_kept_fps`, 5), so that with the
/// keyframe at frame 30 of a 10 fps walk the frames from its start, which saw what only
/// they saw, are still there. Bounded: a full frame each.
const PRE_KEY_FRAMES: usize = 20;

/// Frames buffered without calling for a fill after which a video refills anyway.
const REFILL_AFTER: usize = 4;

/// A new frame's own occluders are first found against the keyframe and this many
/// accepted frames before it ([`Runner::own_occluders`])...
const LOOK_BACK: usize = 2;
/// ...and found again once this many more have arrived, against those too.
const LOOK_AHEAD: usize = 2;

/// An accepted frame that a later frame's own occluders are judged against: its id (`None`
/// for the keyframe), keyframe → frame map, pixels, the marks it was given first and the
/// keyframe's occluders followed into it ([`follow_occluders`]).
struct Neighbour {
    id: Option<String>,
    h: Homography,
    pixels: Rgb8,
    marks: Option<Mask>,
    followed: Option<Mask>,
}

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
    /// The keyframe, then the latest accepted frames (at most [`LOOK_BACK`] + 1 +
    /// [`LOOK_AHEAD`]): the evidence for a frame's own occluders.
    neighbours: VecDeque<Neighbour>,
    /// Kept frames that arrived before the keyframe (at most [`PRE_KEY_FRAMES`], the
    /// latest): aligned once it is set, since they saw what the keyframe's occluders hide.
    pre_key: VecDeque<(u64, f64, DynamicImage, Instant)>,
    /// Per part of the keyframe's mask, the stream times and shifts at which the frames
    /// showed it ([`follow_occluders`]), the keyframe's own first: what a frame that does not
    /// show a part clearly is marked by ([`predict_shift`]).
    followed: Vec<Vec<(f64, [f64; 2])>>,
    /// The keyframe's stream time.
    key_time: f64,
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
            followed: Vec::new(),
            key_time: 0.0,
            buffered_since_fill: 0,
            pending_since: None,
            run_id,
        }
    }

    /// Runs the session until its stream ends (then the reason it ended with an error, if
    /// it did) or the service stops.
    pub(super) fn run(mut self, rx: &Receiver<Msg>, cancel: &CancellationToken) -> Option<String> {
        let span = tracing::info_span!("session", session = %self.src.session);
        let _enter = span.enter();
        let heart = self.ctx.stats.heartbeats.register(format!("video {}", self.src.session));
        let mut failed = None;
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
                        reason: reason.clone(),
                        results: self.slot.state.last_number,
                    };
                    self.ctx.emitter.emit(Some(&self.src.session), &e);
                    failed = reason;
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
        failed
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
        self.followed.clear();
        self.key_time = t;
        self.neighbours.push_back(Neighbour {
            id: None,
            h: Homography::identity(),
            pixels: rgb8(image),
            marks: None,
            followed: None,
        });
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
            self.own_occluders(&key, t, h, px);
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

    /// Finds the occluders of buffered frame `id` (keyframe → frame map `h`, pixels `px`)
    /// against the keyframe and the [`LOOK_BACK`] frames accepted before it, as the
    /// automatic mask finds a keyframe's ([`crate::inpaint::auto_mask`], the frame in the
    /// keyframe's place), and has the fill never copy them; then the frame joins those
    /// neighbours, and the frame [`LOOK_AHEAD`] before it is judged again
    /// ([`Self::judge_again`]). A walk's near trees, cars and people move against the
    /// facade from one frame to the next, so each frame's own occluders disagree with the
    /// facade its neighbours show there; the occlusion model, judging every frame's pixel
    /// against the others, doubts them but not always enough when several frames carry
    /// pieces of occluders over one pixel (BENCHMARKS.md, "Video target, tenth pass").
    fn own_occluders(&mut self, id: &str, t: f64, h: Homography, px: Rgb8) {
        let n = self.neighbours.len();
        let before: Vec<usize> = std::iter::once(0).chain(n.saturating_sub(LOOK_BACK).max(1)..n).collect();
        let marks = self.judge(id, &h, &px, &before).map(|found| with_faint_rim(&found.mask, FAINT_RIM));
        let followed = self.follow(id, t, &h, &px);
        if let Some(marks) = with_followed(marks.as_ref(), followed.as_ref()) {
            self.slot.session.set_view_occluders(id, &marks);
        }
        self.neighbours.push_back(Neighbour { id: Some(id.to_owned()), h, pixels: px, marks, followed });
        if let Some(g) = self.neighbours.len().checked_sub(1 + LOOK_AHEAD).filter(|&g| g >= 1) {
            self.judge_again(g);
        }
        while self.neighbours.len() > 1 + LOOK_BACK + 1 + LOOK_AHEAD {
            // The keyframe stays: it is the one every frame overlaps most with the mask.
            self.neighbours.remove(1);
        }
    }

    /// Neighbour `g`'s occluders judged again, now that [`LOOK_AHEAD`] frames came after it:
    /// against the keyframe, the [`LOOK_BACK`] frames before it and those after it. Where
    /// two of these frames agree with each other (the pixel is judged), their verdict
    /// replaces the first one; elsewhere the first stands. Judged against the past alone, a
    /// frame is marked wherever the frames before it showed their own trees: a near tree
    /// drifts across the facade from frame to frame, so the frames just before a frame
    /// cover, with their trees, much of what it sees clear beside its own, and the first
    /// marks reach 30–60 px past its crown (BENCHMARKS.md, "Video target, fifteenth
    /// session"). The frames after it have moved on and show that facade; where they and
    /// the others cannot judge a pixel (it leaves the picture, or all of them show
    /// occluders), the first verdict is all there is.
    fn judge_again(&mut self, g: usize) {
        let Neighbour { id: Some(id), h, pixels, marks: Some(first), followed } = &self.neighbours[g] else {
            return;
        };
        let around: Vec<usize> = std::iter::once(0)
            .chain((g.saturating_sub(LOOK_BACK).max(1)..self.neighbours.len()).filter(|&i| i != g))
            .collect();
        let Some(again) = self.judge(id, h, pixels, &around) else { return };
        // The way the facade moves in this frame between the first and the last of the
        // frames around it: the way their occluders are displaced against it.
        let centre = nalgebra::Point2::new(pixels.width() as f64 / 2.0, pixels.height() as f64 / 2.0);
        let at = |i: usize| {
            let n = &self.neighbours[i];
            n.h.inverse().and_then(|back| h.apply(back.apply(centre)?))
        };
        let motion = match (at(around[1]), at(*around.last().expect("the keyframe and more"))) {
            (Some(a), Some(b)) => [(b.x - a.x) as f32, (b.y - a.y) as f32],
            _ => [1.0, 0.0],
        };
        let marks = judged_again(first, &again, pixels, motion);
        let marks = with_followed(Some(&marks), followed.as_ref()).expect("marks given");
        let id = id.clone();
        self.slot.session.set_view_occluders(&id, &marks);
    }

    /// The keyframe's occluders followed into a frame (keyframe → frame map `h`, pixels
    /// `px`) by their motion against the facade ([`follow_occluders`]): the frame's pixels
    /// they cover. `None` without a mask, or where no part of it was followed.
    fn follow(&mut self, id: &str, t: f64, h: &Homography, px: &Rgb8) -> Option<Mask> {
        let mask = self.slot.session.mask()?;
        let key = &self.neighbours.front()?.pixels;
        let predicted: Vec<Option<[f64; 2]>> =
            self.followed.iter().map(|track| predict_shift(track, t)).collect();
        let found = follow_occluders(key, mask, px, h, &predicted, &FollowParams::default());
        tracing::debug!(view = id, shifts = ?found.shifts, ?predicted, "the keyframe's occluders followed into a frame");
        if self.followed.len() < found.shifts.len() {
            self.followed.resize(found.shifts.len(), vec![(self.key_time, [0.0; 2])]);
        }
        for (track, &d) in self.followed.iter_mut().zip(&found.shifts) {
            carry_shift(track, t, d);
        }
        (found.marks.as_slice().iter().any(|&v| v > 0)).then_some(found.marks)
    }

    /// The automatic mask of buffered frame `id` (keyframe → frame map `h`, pixels `px`)
    /// against the neighbours `refs`; `None` when the frame is no longer buffered.
    fn judge(&self, id: &str, h: &Homography, px: &Rgb8, refs: &[usize]) -> Option<AutoMask> {
        let buffered = self.slot.session.buffered().iter().any(|b| b.id == id && b.has_pixels());
        let back = h.inverse().filter(|_| buffered)?;
        let sources: Vec<Source<'_, [u8; 3]>> = refs
            .iter()
            .map(|&i| {
                let n = &self.neighbours[i];
                Source { image: &n.pixels, homography: n.h.after(&back) }
            })
            .collect();
        let params = frame_judgement(&self.slot.session.params().auto_mask, sources.len());
        let found = auto_mask_report(&rgb8_to_f32(px), &sources, &params);
        let share = found.mask.as_slice().iter().filter(|&&v| v > 127).count() as f64
            / found.mask.as_slice().len().max(1) as f64;
        tracing::debug!(view = id, share, refs = refs.len(), "a frame's own occluders");
        Some(found)
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

/// A frame's marks `first`, revised by a second judgement `again` of the same frame (pixels
/// `px`) against more frames ([`Runner::judge_again`]): where those frames judged the pixel
/// (two of them agree there) and find no occluder, and the frame shows detail across
/// `motion`, the way the frames' occluders move against the facade ([`MIN_DETAIL`]), the
/// mark becomes soft ([`SOFT_MARK`]). Elsewhere the first verdict stands; the second adds
/// no mark.
///
/// Frames that agree with each other and with this frame show the facade, unless what they
/// show looks the same when displaced: a car's flat body, the sky around a crown, or a
/// roof line along the walk, which the frames around show as this frame does although
/// each has its car at another place. Such pixels are left as the first judgement had
/// them; where they are marked, the fallback makes them, and it makes flat regions well.
/// A soft mark is still a doubt: the fill copies such a pixel only where every frame that
/// sees it is marked (the fallback's alternative), not where it looks like the keyframe's
/// own occluder, and never reports it sure (BENCHMARKS.md, "Video target, eighteenth
/// session").
fn judged_again(first: &Mask, again: &AutoMask, px: &Rgb8, motion: [f32; 2]) -> Mask {
    let detail = detail_along(px, motion, DETAIL_RADIUS);
    let mut marks = first.clone();
    for (((m, &a), &judged), &t) in marks
        .as_mut_slice()
        .iter_mut()
        .zip(again.mask.as_slice())
        .zip(again.judged.as_slice())
        .zip(detail.as_slice())
    {
        if judged > 127 && *m > 127 && a <= 127 && t >= MIN_DETAIL {
            // A faint rim stays faint.
            *m = (*m).min(SOFT_MARK);
        }
    }
    marks
}

/// The automatic mask's parameters for judging a frame against `sources` others, from the
/// session's (`base`).
fn frame_judgement(base: &AutoMaskParams, sources: usize) -> AutoMaskParams {
    let mut params = base.clone();
    params.min_views = params.min_views.min(sources);
    // The walk's marks were measured without the regrowth (BENCHMARKS.md, "Video
    // target, tenth pass"), and they already cover too much on some walks. Neighbouring
    // frames' own objects explaining their disagreement cost two walks 3 and 4 dB
    // (BENCHMARKS.md, "--mask auto: the views' own objects").
    params.regrowth_passes = 0;
    params.own_objects = false;
    // Nor the clouds joined to the sky: in a walk's soft frames the sky ran on into the
    // glass reflecting it, and one walk lost 3.3 dB (BENCHMARKS.md, "Bands of cloud").
    params.sky_cloud_gradient = 0.0;
    // Nor faces shaded otherwise (`shading_ncc`): the walks were not
    // measured with it (sixty-eighth session).
    params.shading_ncc = 0.0;
    params
}

/// A frame's `marks` with the keyframe's occluders `followed` into it: the stronger of the
/// two per pixel. `None` when there is neither.
fn with_followed(marks: Option<&Mask>, followed: Option<&Mask>) -> Option<Mask> {
    match (marks, followed) {
        (Some(m), Some(f)) => {
            let mut out = m.clone();
            out.as_mut_slice().iter_mut().zip(f.as_slice()).for_each(|(o, &v)| *o = (*o).max(v));
            Some(out)
        }
        (m, f) => m.or(f).cloned(),
    }
}

/// `marks` with the pixels within `r` of a mark (a `(2r + 1)²` square), and not on one,
/// marked faintly ([`FAINT_MARK`]: near an occluder, not judged one).
fn with_faint_rim(marks: &Mask, r: usize) -> Mask {
    let (w, h) = (marks.width(), marks.height());
    let hard = crate::imaging::Plane::from_fn(w, h, |x, y| marks.get(x, y) > 127);
    let near = crate::inpaint::automask::dilate(&hard, r);
    Mask::from_fn(w, h, |x, y| match (hard.get(x, y), near.get(x, y)) {
        (true, _) => marks.get(x, y),
        (false, true) => FAINT_MARK,
        (false, false) => 0,
    })
}

/// How far past what the automatic mask found a frame's marks go on, faint ([`FAINT_MARK`]):
/// the fill copies such a pixel only where every frame that sees it is marked. The mask ends
/// about where a person paints, a pixel past the outline
/// ([`crate::inpaint::AutoMaskParams::dilate_radius`]); since it ended there (it was 3 px),
/// seed 13's walk with keyframe 30 had a car's body pasted back (26.52 dB, under the
/// target). On 24 rendered walk cases a 2 px soft rim gained on 10 of the 12 keyframe-30
/// cases (up to +2.95 dB, the car gone) and lost on 8 of the 12 first-frame ones (up to
/// −4.4 dB, where the fallback fills more): 21 targets met against 20, the mean the same.
/// Grown hard by 3 px instead, the mean fell 0.33 dB on 16 of them (BENCHMARKS.md, "A
/// frame's marks go on softly past what was found"). Marked faint rather than soft, the
/// first-frame cases no longer lose (the mean 33.39 → 33.53 dB; BENCHMARKS.md, "A frame's
/// rim is faint").
const FAINT_RIM: usize = 2;

/// A mark the second judgement lifted: the fill copies the pixel only where every frame
/// that sees it is marked there ([`crate::inpaint::FillExtras::occluders`]).
const SOFT_MARK: u8 = 160;

/// Radius of the window over which a frame's detail across the motion is measured.
const DETAIL_RADIUS: usize = 4;
/// The mean absolute luma derivative across the motion (per pixel, luma 0..=1) from which a
/// second judgement may lift a mark. Measured on the rendered walks (BENCHMARKS.md, "Video
/// target, fifteenth session"): with none, a car's roof line was copied (seed 34 key 30,
/// 38.41 → 25.16 dB); at 0.012 still part of it (32.72); at 0.025 the mullions of a glass
/// wall and the joints of brick pass, the panes and flat bodies do not.
const MIN_DETAIL: f32 = 0.025;

/// The mean absolute derivative of the luma of `px` along `motion` (any length; the x axis
/// when it is nil) over the `(2r + 1)²` window around each pixel.
fn detail_along(px: &Rgb8, motion: [f32; 2], r: usize) -> crate::imaging::Plane<f32> {
    let (w, h) = (px.width(), px.height());
    let norm = (motion[0] * motion[0] + motion[1] * motion[1]).sqrt();
    let d = if norm > 1e-3 { [motion[0] / norm, motion[1] / norm] } else { [1.0, 0.0] };
    let luma = |x: usize, y: usize| {
        let p = px.get(x, y);
        (0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32) / 255.0
    };
    let deriv: Vec<f64> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let gx = (luma((x + 1).min(w - 1), y) - luma(x.saturating_sub(1), y)) / 2.0;
            let gy = (luma(x, (y + 1).min(h - 1)) - luma(x, y.saturating_sub(1))) / 2.0;
            f64::from((d[0] * gx + d[1] * gy).abs())
        })
        .collect();
    let mut sat = vec![0.0f64; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0.0;
        for x in 0..w {
            row += deriv[y * w + x];
            sat[(y + 1) * (w + 1) + x + 1] = sat[y * (w + 1) + x + 1] + row;
        }
    }
    crate::imaging::Plane::from_fn(w, h, |x, y| {
        let (x0, y0, x1, y1) =
            (x.saturating_sub(r), y.saturating_sub(r), (x + r + 1).min(w), (y + r + 1).min(h));
        let sum =
            sat[y1 * (w + 1) + x1] + sat[y0 * (w + 1) + x0] - sat[y0 * (w + 1) + x1] - sat[y1 * (w + 1) + x0];
        (sum / ((x1 - x0) * (y1 - y0)) as f64) as f32
    })
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
/// It takes only the frame pixels the fill is sure of (`CONFIDENT`), not the fairly sure
/// ones the service takes: beside what no frame saw they are the rim of the near crown
/// that every frame showed there, wrong one time in two, and they guided glass and brick
/// into the sky (seed 65's first frame 20.06 → 26.34 dB, seed 20's 28.16 → 31.59; no walk
/// of 36 lost 0.3 dB; BENCHMARKS.md "A walk's fallback: guided by what the fill is sure
/// of"). The service and the command keep theirs: there it flipped the judgement of a
/// facade's surfaces (parallax-13 −6 dB).
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
///
/// The frames are averaged into the copies as elsewhere (`FillParams::fuse`): on the walks
/// of seeds 13–20 the mean went 34.61 → 34.79 dB, four cases gained 0.37–0.85 dB, none
/// lost 0.3 (BENCHMARKS.md, "Averaging the views").
///
/// The fill does not look for the frames' own occluders itself (`FillParams::own`): the
/// runner marks them, against more frames and with what came after
/// ([`Runner::own_occluders`]), and the fill's own judgement runs only where a caller has
/// none.
///
/// Nor does it sweep the surfaces off the wall (`SessionParams::sweep`): a walk fills with
/// up to the whole buffer of frames, each a view for the sweep to tie, and the sweep was
/// neither measured on walks nor timed against a stream's pace.
fn walk_params(mut params: SessionParams) -> SessionParams {
    let fill = &mut params.fill;
    fill.occlusion_model.sure = fill.occlusion_model.cut;
    fill.select_views = false;
    fill.local_shift = None;
    fill.own = None;
    fill.fallback_guide_from = Some(CONFIDENT);
    params.sweep = None;
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

/// The shift at time `t` of a part of the keyframe's mask that the frames of `track`
/// (stream times and shifts, the keyframe at shift nil among them) showed: carried on from the
/// two frames nearest in time, when they are within [`PREDICT_SPAN`] of `t`.
fn predict_shift(track: &[(f64, [f64; 2])], t: f64) -> Option<[f64; 2]> {
    let mut near: Vec<&(f64, [f64; 2])> =
        track.iter().filter(|(ti, _)| (ti - t).abs() <= PREDICT_SPAN).collect();
    near.sort_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()));
    let (&(t1, d1), &(t2, d2)) = (near.first()?, near.get(1)?);
    if (t2 - t1).abs() < 1e-6 {
        return None;
    }
    let k = (t - t1) / (t2 - t1);
    Some([d1[0] + k * (d2[0] - d1[0]), d1[1] + k * (d2[1] - d1[1])])
}

/// The shift `d` at which the frame at time `t` showed a part of the keyframe's mask (if it
/// did) added to the part's `track`, and what can no longer predict a frame dropped: after the
/// keyframe the frames come on in time, and nothing further back than [`PREDICT_SPAN`]
/// predicts any of them ([`predict_shift`]), so an hours-long stream keeps a bounded track.
/// (Before the keyframe they come nearest first, back in time: nothing is older than the
/// frame.)
fn carry_shift(track: &mut Vec<(f64, [f64; 2])>, t: f64, d: Option<[f64; 2]>) {
    track.extend(d.map(|d| (t, d)));
    track.retain(|&(ti, _)| ti >= t - PREDICT_SPAN);
}

/// How far in time (seconds) the shift of a keyframe's occluder is carried on.
const PREDICT_SPAN: f64 = 1.5;

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

    /// A generated walk past a near tree: the facade stands still (every map the identity)
    /// and the tree drifts 24 px a frame across it. Judged against the keyframe and the two
    /// frames before it, frame 3 is marked over much of the facade it sees clear where
    /// their trees stand; judged again with the two frames after it as well, a third of
    /// those marks go soft, and its own tree stays marked whole.
    #[test]
    fn a_frame_judged_again_with_the_frames_after_it_keeps_its_tree_and_softens_the_others() {
        use crate::synth::{Occluder, facade, paint_occluder};
        let (w, h) = (320, 240);
        let wall = facade(w, h, 5);
        let frame = |k: usize| {
            let mut img = wall.clone();
            let mut tree = Mask::new(w, h, 0);
            paint_occluder(
                &mut img,
                Some(&mut tree),
                Occluder::Tree,
                90.0 + 24.0 * k as f32,
                120.0,
                150.0,
                11,
            );
            (img, tree)
        };
        let frames: Vec<(RgbF32, Mask)> = (0..6).map(frame).collect();
        let pixels: Vec<Rgb8> =
            frames.iter().map(|(img, _)| img.map(|p| p.map(|v| (v * 255.0).round() as u8))).collect();
        let sources = |of: &[usize]| -> Vec<Source<'_, [u8; 3]>> {
            of.iter().map(|&k| Source { image: &pixels[k], homography: Homography::identity() }).collect()
        };
        let params = frame_judgement(&SessionParams::default().auto_mask, 3);
        let (img, tree) = &frames[3];
        let first = auto_mask_report(img, &sources(&[0, 1, 2]), &params).mask;
        let again = auto_mask_report(img, &sources(&[0, 1, 2, 4, 5]), &params);
        let marks = judged_again(&first, &again, &pixels[3], [24.0, 0.0]);
        // Shares of the frame's tree, and of the facade it shows where the trees of the
        // keyframe and the frames before it stand, that are marked whole (not soft).
        let covered = |i: usize| frames[..3].iter().any(|(_, t)| t.as_slice()[i] > 127);
        let share = |m: &Mask, of: &dyn Fn(usize) -> bool| {
            let (mut hit, mut n) = (0usize, 0usize);
            for i in (0..w * h).filter(|&i| of(i)) {
                n += 1;
                hit += usize::from(m.as_slice()[i] == 255);
            }
            hit as f64 / n.max(1) as f64
        };
        let in_tree = |i: usize| tree.as_slice()[i] > 127;
        let beside = |i: usize| tree.as_slice()[i] <= 127 && covered(i);
        let (tree_first, beside_first) = (share(&first, &in_tree), share(&first, &beside));
        let (tree_again, beside_again) = (share(&marks, &in_tree), share(&marks, &beside));
        // Measured: 0.61 -> 0.40 (0.32 without the detail rule: the brick's courses run
        // along the motion), the tree wholly marked before and after.
        assert!(
            beside_first > 0.4,
            "the first marks cover {beside_first:.2} of the facade the others' trees hide"
        );
        assert!(
            beside_again < 0.7 * beside_first,
            "where the others' trees stand: {beside_first:.2} -> {beside_again:.2}"
        );
        assert!(tree_again > 0.97, "its own tree: {tree_first:.3} -> {tree_again:.3} marked");
    }

    /// A frame's marks go on faintly for `r` pixels past what was found (a square's reach),
    /// and no further; what was found keeps its mark.
    #[test]
    fn a_frames_marks_go_on_faintly_past_what_was_found() {
        let found = Mask::from_fn(40, 30, |x, y| match (x, y) {
            (10..20, 10..15) => 255,
            (30, 20) => SOFT_MARK,
            _ => 0,
        });
        let marks = with_faint_rim(&found, 2);
        for y in 0..30usize {
            for x in 0..40usize {
                // The distance (a square's) to the nearest pixel found.
                let d = (0..30)
                    .flat_map(|v| (0..40).map(move |u| (u, v)))
                    .filter(|&(u, v)| found.get(u, v) > 127)
                    .map(|(u, v)| x.abs_diff(u).max(y.abs_diff(v)))
                    .min()
                    .expect("found");
                let want = match d {
                    0 => found.get(x, y),
                    1 | 2 => FAINT_MARK,
                    _ => 0,
                };
                assert_eq!(marks.get(x, y), want, "({x}, {y}), {d} from what was found");
            }
        }
    }

    /// The second judgement softens a mark only where the frame shows detail across the way
    /// the occluders move: vertical stripes' marks go soft when the walk moves sideways,
    /// not when it moves up; a flat half keeps them either way; it adds no mark.
    #[test]
    fn a_mark_is_lifted_only_where_the_frame_has_detail_across_the_motion() {
        let (w, h) = (64, 32);
        let px: Rgb8 =
            Rgb8::from_fn(
                w,
                h,
                |x, _| if x < 32 || (x / 3) % 2 == 0 { [90, 90, 90] } else { [200, 200, 200] },
            );
        let first = Mask::from_fn(w, h, |_, y| if y < 28 { 255 } else { 0 });
        let again = AutoMask {
            mask: Mask::from_fn(w, h, |_, y| if y >= 28 { 255 } else { 0 }),
            objects: 1,
            certain_share: 1.0,
            judged_share: 1.0,
            judged: Mask::new(w, h, 255),
        };
        let marked = |m: &Mask, x0: usize, x1: usize| (0..28).all(|y| (x0..x1).all(|x| m.get(x, y) > 127));
        let sideways = judged_again(&first, &again, &px, [30.0, 0.0]);
        assert!(marked(&sideways, 0, 26), "the flat half keeps its marks");
        assert!((38..64).all(|x| (0..28).all(|y| sideways.get(x, y) == SOFT_MARK)), "the stripes' go soft");
        assert!((0..w).all(|x| (28..h).all(|y| sideways.get(x, y) == 0)), "no mark added");
        let upwards = judged_again(&first, &again, &px, [0.0, -30.0]);
        assert!(
            (0..64).all(|x| (0..28).all(|y| upwards.get(x, y) == 255)),
            "no detail across the motion: every mark stays whole"
        );
    }

    #[test]
    fn a_walk_leaves_what_every_frame_doubts_to_the_fallback() {
        let base = SessionParams::default();
        let walk = walk_params(base.clone());
        let (model, fill) = (&walk.fill.occlusion_model, &walk.fill);
        assert_eq!(model.sure, model.cut, "a pixel every frame doubts is not copied");
        assert!(!fill.select_views, "a walk's fill chooses no frames");
        assert!(fill.local_shift.is_none(), "a walk's frames are not moved around the hole");
        assert!(fill.own.is_none(), "the runner marks the frames' own occluders, not the fill");
        assert!(walk.sweep.is_none(), "a walk is not swept for surfaces off the wall");
        assert_eq!(fill.fallback_guide_from, Some(CONFIDENT), "the guide takes the sure pixels only");
        // The rest is the service's.
        let mut back = walk.clone();
        back.fill.fallback_guide_from = base.fill.fallback_guide_from;
        back.sweep = base.sweep.clone();
        back.fill.occlusion_model.sure = base.fill.occlusion_model.sure;
        back.fill.select_views = base.fill.select_views;
        back.fill.local_shift = base.fill.local_shift.clone();
        back.fill.own = base.fill.own.clone();
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

    #[test]
    fn an_occluders_shift_is_carried_on_from_the_frames_nearest_in_time() {
        // The keyframe at t = 3 (shift nil); the frames before it, aligned nearest first,
        // then those after it.
        let track = vec![(3.0, [0.0, 0.0]), (2.75, [30.0, 2.0]), (2.5, [60.0, 4.0])];
        let d = predict_shift(&track, 2.25).unwrap();
        assert!((d[0] - 90.0).abs() < 1e-9 && (d[1] - 6.0).abs() < 1e-9, "{d:?}");
        // After the keyframe, from it and the frame nearest it: the same speed, onwards.
        let d = predict_shift(&track, 3.25).unwrap();
        assert!((d[0] + 30.0).abs() < 1e-9, "{d:?}");
        // Not from a single frame, nor further than PREDICT_SPAN from any two.
        assert_eq!(predict_shift(&track[..1], 3.25), None);
        assert_eq!(predict_shift(&track, 3.0 + PREDICT_SPAN + 0.5), None);
    }

    #[test]
    fn an_hour_of_frames_keeps_a_short_track_that_predicts_as_the_whole_one() {
        // The keyframe at t = 30; 20 frames before it at 5 fps, nearest first; then an hour
        // at 5 fps, the part seen in two frames of every three.
        let shift = |t: f64| [12.0 * (t - 30.0), 0.5 * (t - 30.0)];
        let times = (1..=20)
            .map(|i| 30.0 - 0.2 * f64::from(i))
            .chain((1..=18_000).map(|i| 30.0 + 0.2 * f64::from(i)));
        let (mut short, mut whole) = (vec![(30.0, [0.0; 2])], vec![(30.0, [0.0; 2])]);
        let mut longest = 0;
        for (i, t) in times.enumerate() {
            assert_eq!(predict_shift(&short, t), predict_shift(&whole, t), "at {t}");
            let d = (i % 3 != 0).then(|| shift(t));
            carry_shift(&mut short, t, d);
            whole.extend(d.map(|d| (t, d)));
            longest = longest.max(short.len());
        }
        assert!(whole.len() > 10_000);
        // The 20 frames before the keyframe wait for the first frames after it.
        assert!(longest <= 20 + 8, "{longest}");
        assert!(short.len() <= 8, "{}", short.len());
    }
}
