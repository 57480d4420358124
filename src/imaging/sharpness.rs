//! Frame selection for video input: sharpness (variance of the Laplacian) against a
//! running level, motion since the last kept frame, and a cap on the kept rate (pure
//! layer: the caller passes each frame's time; no clock here).
//!
//! A 30 fps stream offers far more frames than alignment and fill can take, and most of
//! them add nothing: neighbours see the same thing, and a frame shot while the camera
//! shook is blurred. [`FrameSelector::offer`] keeps a frame only when
//! 1. it is sharp: its [`sharpness`] (the Laplacian variance at the frame's scale over the
//!    same at half that scale) is at least [`SelectParams::min_sharpness`] times the
//!    running level (a maximum that decays with half-life [`SelectParams::level_half_life_s`],
//!    so a change of scene lowers it in seconds);
//! 2. it moved: the mean absolute difference of its thumbnail from the last kept frame's
//!    is at least [`SelectParams::min_motion`];
//! 3. it is at least `1 / max_kept_fps` seconds after the last kept frame.
//!
//! The first [`SelectParams::warmup_frames`] frames set the level before anything is judged
//! ([`FrameSelector::observe`]: nothing is judged before the selector knows what sharp looks
//! like in this stream). The caller holds them and judges them once the level is known
//! ([`FrameSelector::judge`]) rather than lose them: with the keyframe named at frame 30,
//! the first frames are the ones that saw most of what its occluders hide (measured on the
//! rendered walks of `bench/align_video.py`; BENCHMARKS.md, "Video target, sixth pass").

use super::GrayF32;
use super::convert::luma;

/// Parameters of the frame selection.
#[derive(Debug, Clone, PartialEq)]
pub struct SelectParams {
    /// A frame is blurred when its Laplacian variance is below this share of the running
    /// level (0: keep every frame, however blurred).
    pub min_sharpness: f32,
    /// Half-life of the running level, in seconds of stream time.
    pub level_half_life_s: f32,
    /// Mean absolute difference (0..=1 grey levels) of the frame's thumbnail from the last
    /// kept frame's below which the frame adds nothing (0: no motion test).
    pub min_motion: f32,
    /// Frames kept per second of stream time at most (0: no cap). The default, 5, keeps
    /// every other frame of a 10 fps walk: each frame's own occluders are marked
    /// (`daemon::video::runner`), so frames close together no longer vote a near occluder
    /// in as one, and the denser frames see the pixels each occluder hides only briefly
    /// (BENCHMARKS.md, "Video target, eleventh pass"; 2 before).
    pub max_kept_fps: f32,
    /// Frames that set the running level before any is judged (see [`FrameSelector::observe`]).
    pub warmup_frames: usize,
    /// Width of the motion thumbnail, in pixels.
    pub thumb_width: usize,
}

impl Default for SelectParams {
    fn default() -> Self {
        Self {
            min_sharpness: 0.5,
            level_half_life_s: 2.0,
            min_motion: 0.02,
            max_kept_fps: 5.0,
            warmup_frames: 5,
            thumb_width: 64,
        }
    }
}

/// What the selector made of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Keep,
    /// Still setting the running level.
    Warmup,
    /// Below the running sharpness level.
    Blurred,
    /// Too close to the last kept frame.
    Still,
    /// Too soon after the last kept frame.
    RateCapped,
}

impl Verdict {
    pub fn name(self) -> &'static str {
        match self {
            Self::Keep => "kept",
            Self::Warmup => "warmup",
            Self::Blurred => "blurred",
            Self::Still => "still",
            Self::RateCapped => "rate_capped",
        }
    }
}

/// The measures of one frame: its sharpness and motion thumbnail.
#[derive(Debug, Clone)]
pub struct FrameMeasure {
    /// [`sharpness`] of the grey frame.
    pub sharpness: f32,
    pub thumb: GrayF32,
}

impl FrameMeasure {
    /// Measures an RGB24 frame (`width * height * 3` bytes), on a grey copy box-averaged
    /// down to at most about 640 pixels wide (sharpness) and `thumb_width` (motion).
    pub fn of_rgb24(bytes: &[u8], width: usize, height: usize, thumb_width: usize) -> Self {
        let factor = width.div_ceil(640).max(1);
        let gray = gray_reduced(bytes, width, height, factor);
        let sharpness = sharpness(&gray);
        let t = (gray.width() / thumb_width.max(8)).max(1);
        let thumb = box_reduce(&gray, t);
        Self { sharpness, thumb }
    }
}

/// Grey (Rec. 601 weights, 0..=1) of an RGB24 buffer, box-averaged by `factor`.
pub fn gray_reduced(bytes: &[u8], width: usize, height: usize, factor: usize) -> GrayF32 {
    assert_eq!(bytes.len(), width * height * 3, "an RGB24 frame of {width}x{height}");
    let f = factor.max(1);
    let (w, h) = ((width / f).max(1), (height / f).max(1));
    let norm = 1.0 / (255.0 * (f * f) as f32);
    let mut out = GrayF32::new(w, h, 0.0);
    for y in 0..h {
        let row = out.row_mut(y);
        for sy in y * f..((y + 1) * f).min(height) {
            let src = &bytes[sy * width * 3..(sy + 1) * width * 3];
            for (x, o) in row.iter_mut().enumerate() {
                let mut acc = 0.0;
                for sx in x * f..((x + 1) * f).min(width) {
                    let p = &src[sx * 3..sx * 3 + 3];
                    acc += luma([p[0] as f32, p[1] as f32, p[2] as f32]);
                }
                *o += acc * norm;
            }
        }
    }
    out
}

/// Box average by `factor` of a grey image.
pub fn box_reduce(src: &GrayF32, factor: usize) -> GrayF32 {
    let f = factor.max(1);
    let (w, h) = ((src.width() / f).max(1), (src.height() / f).max(1));
    GrayF32::from_fn(w, h, |x, y| {
        let mut acc = 0.0;
        let mut n = 0.0;
        for sy in y * f..((y + 1) * f).min(src.height()) {
            for sx in x * f..((x + 1) * f).min(src.width()) {
                acc += src.get(sx, sy);
                n += 1.0;
            }
        }
        acc / n
    })
}

/// Variance of the 4-neighbour Laplacian over the interior of `img`: high for a sharp
/// image, low for a blurred one of the same scene.
pub fn laplacian_variance(img: &GrayF32) -> f32 {
    let (w, h) = (img.width(), img.height());
    if w < 3 || h < 3 {
        return 0.0;
    }
    let (mut sum, mut sum2) = (0.0f64, 0.0f64);
    for y in 1..h - 1 {
        let (up, row, down) = (img.row(y - 1), img.row(y), img.row(y + 1));
        for x in 1..w - 1 {
            let l = (up[x] + down[x] + row[x - 1] + row[x + 1] - 4.0 * row[x]) as f64;
            sum += l;
            sum2 += l * l;
        }
    }
    let n = ((w - 2) * (h - 2)) as f64;
    let mean = sum / n;
    (sum2 / n - mean * mean).max(0.0) as f32
}

/// How sharp `img` is, whatever it shows: the Laplacian variance of the image over that of
/// the image box-averaged by 2 (0 for a flat image). Blur takes the finest scale's detail
/// first, so the ratio falls (σ 1.5 px: about a quarter of a sharp frame's), while a scene
/// that loses its detail altogether keeps it: the raw variance of a sharp walk's frames
/// fell tenfold as a near tree with fine leaves left the picture (`bench/align_video.py`
/// seed 16), and seventeen sharp frames in a row were refused as blurred against the level
/// the tree had set; their ratios stayed within 0.29–0.43 (blurred by σ 1.5: 0.07–0.09).
pub fn sharpness(img: &GrayF32) -> f32 {
    let coarse = laplacian_variance(&box_reduce(img, 2));
    if coarse <= 1e-12 { 0.0 } else { laplacian_variance(img) / coarse }
}

/// Mean absolute difference of two thumbnails (1 when their sizes differ).
pub fn motion(a: &GrayF32, b: &GrayF32) -> f32 {
    if (a.width(), a.height()) != (b.width(), b.height()) || a.is_empty() {
        return 1.0;
    }
    let s: f32 = a.as_slice().iter().zip(b.as_slice()).map(|(p, q)| (p - q).abs()).sum();
    s / a.len() as f32
}

/// The selection state of one stream.
#[derive(Debug, Clone)]
pub struct FrameSelector {
    params: SelectParams,
    seen: usize,
    level: f32,
    level_t: f64,
    last_kept: Option<(f64, GrayF32)>,
}

impl FrameSelector {
    pub fn new(params: SelectParams) -> Self {
        Self { params, seen: 0, level: 0.0, level_t: 0.0, last_kept: None }
    }

    pub fn params(&self) -> &SelectParams {
        &self.params
    }

    /// The running sharpness level.
    pub fn level(&self) -> f32 {
        self.level
    }

    /// Judges the frame at stream time `t` (seconds, non-decreasing): [`Self::observe`],
    /// then [`Self::judge`] once the warm-up is over.
    pub fn offer(&mut self, t: f64, m: &FrameMeasure, force_keep: bool) -> Verdict {
        if !self.observe(t, m) {
            return Verdict::Warmup;
        }
        self.judge(t, m, force_keep)
    }

    /// Takes the frame at stream time `t` (non-decreasing) into the running level; whether
    /// the warm-up is over (frames can be judged).
    pub fn observe(&mut self, t: f64, m: &FrameMeasure) -> bool {
        let p = &self.params;
        let dt = (t - self.level_t).max(0.0);
        let decay =
            if p.level_half_life_s > 0.0 { 0.5f64.powf(dt / p.level_half_life_s as f64) } else { 0.0 };
        self.level = (self.level * decay as f32).max(m.sharpness);
        self.level_t = t;
        self.seen += 1;
        self.seen > p.warmup_frames
    }

    /// Whether the frame at `t` (not before the last frame judged) is kept against the
    /// current level; when it is, it becomes the last kept frame. `force_keep` keeps a
    /// sharp frame whatever its motion and time (the keyframe). A frame held through the
    /// warm-up is judged here once [`Self::observe`] says the level is known.
    pub fn judge(&mut self, t: f64, m: &FrameMeasure, force_keep: bool) -> Verdict {
        let p = &self.params;
        if m.sharpness < p.min_sharpness * self.level {
            return Verdict::Blurred;
        }
        if !force_keep && let Some((last_t, last)) = &self.last_kept {
            if p.max_kept_fps > 0.0 && t - last_t < 1.0 / p.max_kept_fps as f64 {
                return Verdict::RateCapped;
            }
            if motion(&m.thumb, last) < p.min_motion {
                return Verdict::Still;
            }
        }
        self.last_kept = Some((t, m.thumb.clone()));
        Verdict::Keep
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::imaging::filter::gaussian_blur;

    /// A checkerboard-ish texture shifted by `dx`, as RGB24.
    /// A textured facade (rectangles of two greys, the darker ones speckled) moved `dx`
    /// pixels to the left: the frames of a pan.
    pub(crate) fn texture(w: usize, h: usize, dx: usize) -> GrayF32 {
        GrayF32::from_fn(w, h, |x, y| {
            let (u, v) = (x + dx, y);
            if ((u / 5) + (v / 7)) % 2 == 0 { 0.8 } else { 0.2 + ((u * 13 + v * 7) % 11) as f32 * 0.02 }
        })
    }

    fn rgb24(g: &GrayF32) -> Vec<u8> {
        g.as_slice().iter().flat_map(|v| [(v * 255.0).round() as u8; 3]).collect()
    }

    pub(crate) fn measure(g: &GrayF32) -> FrameMeasure {
        FrameMeasure::of_rgb24(&rgb24(g), g.width(), g.height(), 16)
    }

    #[test]
    fn blur_lowers_the_laplacian_variance() {
        let sharp = texture(80, 60, 0);
        let blurred = gaussian_blur(&sharp, 2.0);
        let (s, b) = (laplacian_variance(&sharp), laplacian_variance(&blurred));
        assert!(b < 0.2 * s, "sharp {s}, blurred {b}");
        assert_eq!(laplacian_variance(&GrayF32::new(10, 10, 0.5)), 0.0);
    }

    /// A sharp scene that shows less detail (less contrast: a textured tree left the
    /// picture) is not a blurred one. With the raw Laplacian variance as the measure, the
    /// dull frame was refused as blurred.
    #[test]
    fn a_sharp_frame_with_less_detail_is_not_blurred() {
        let params =
            SelectParams { warmup_frames: 0, max_kept_fps: 0.0, min_motion: 0.0, ..Default::default() };
        let mut s = FrameSelector::new(params);
        let busy = measure(&texture(80, 60, 0));
        let dull = measure(&texture(80, 60, 3).map(|v| 0.45 + 0.15 * v));
        let blurred = measure(&gaussian_blur(&texture(80, 60, 3).map(|v| 0.45 + 0.15 * v), 1.5));
        assert_eq!(s.offer(0.0, &busy, false), Verdict::Keep);
        assert_eq!(s.offer(0.1, &dull, false), Verdict::Keep, "busy {busy:?}, dull {dull:?}");
        assert_eq!(s.offer(0.2, &blurred, false), Verdict::Blurred);
        assert_eq!(sharpness(&GrayF32::new(10, 10, 0.5)), 0.0);
    }

    #[test]
    fn grey_of_rgb24_averages_boxes() {
        let bytes = [255u8, 255, 255, 0, 0, 0, 255, 255, 255, 0, 0, 0];
        let g = gray_reduced(&bytes, 2, 2, 2);
        assert_eq!((g.width(), g.height()), (1, 1));
        assert!((g.get(0, 0) - 0.5).abs() < 1e-3);
        let g = gray_reduced(&bytes, 2, 2, 1);
        assert!((g.get(0, 0) - 1.0).abs() < 1e-3 && g.get(1, 0).abs() < 1e-3);
    }

    #[test]
    fn selector_skips_blurred_still_and_too_frequent_frames() {
        let params =
            SelectParams { warmup_frames: 2, max_kept_fps: 5.0, min_motion: 0.02, ..Default::default() };
        let mut s = FrameSelector::new(params);
        let f = |dx| measure(&texture(80, 60, dx));
        assert_eq!(s.offer(0.0, &f(0), false), Verdict::Warmup);
        assert_eq!(s.offer(0.1, &f(1), false), Verdict::Warmup);
        assert_eq!(s.offer(0.2, &f(2), false), Verdict::Keep);
        // Blurred: same place, far less detail.
        let blurred = measure(&gaussian_blur(&texture(80, 60, 9), 2.5));
        assert_eq!(s.offer(0.5, &blurred, false), Verdict::Blurred);
        // Too soon (5 fps cap: 0.2 s), then the same picture (no motion), then moved.
        assert_eq!(s.offer(0.3, &f(9), false), Verdict::RateCapped);
        assert_eq!(s.offer(0.6, &f(2), false), Verdict::Still);
        assert_eq!(s.offer(0.7, &f(9), false), Verdict::Keep);
        // The keyframe is kept whatever its motion, but never blurred.
        assert_eq!(s.offer(0.75, &f(9), true), Verdict::Keep);
        assert_eq!(s.offer(0.8, &blurred, true), Verdict::Blurred);
    }

    /// A 10 fps walk gives its frames a few tenths of a second apart: by default at
    /// least one in three is kept (one in five with the former cap of 2 per second, which
    /// left the pixels a near occluder hides only briefly to the fallback; BENCHMARKS.md,
    /// "Video target, eleventh pass").
    #[test]
    fn a_ten_fps_walk_keeps_at_least_one_frame_in_three_by_default() {
        let mut s = FrameSelector::new(SelectParams::default());
        let mut judged = 0;
        let mut kept = 0;
        for i in 0..40 {
            let v = s.offer(i as f64 / 10.0, &measure(&texture(80, 60, 4 * i)), false);
            if v != Verdict::Warmup {
                judged += 1;
                kept += usize::from(v == Verdict::Keep);
            }
        }
        assert!(judged >= 30, "{judged} judged");
        assert!(3 * kept >= judged, "{kept} of {judged} kept");
    }

    #[test]
    fn frames_held_through_the_warm_up_are_judged_once_the_level_is_known() {
        let params =
            SelectParams { warmup_frames: 3, max_kept_fps: 5.0, min_motion: 0.02, ..Default::default() };
        let mut s = FrameSelector::new(params);
        let f = |dx| measure(&texture(80, 60, dx));
        let blurred = measure(&gaussian_blur(&texture(80, 60, 4), 2.5));
        // A blurred first frame sets a low level; the sharp ones after it raise it.
        assert!(!s.observe(0.0, &blurred));
        assert!(!s.observe(0.1, &f(1)));
        assert!(!s.observe(0.35, &f(3)));
        assert!(s.observe(0.4, &f(4)));
        // Held frames, in order, against the level the warm-up set: the blurred one is
        // refused although it was the sharpest when it came, then the cap and the motion test.
        assert_eq!(s.judge(0.0, &blurred, false), Verdict::Blurred);
        assert_eq!(s.judge(0.1, &f(1), false), Verdict::Keep);
        assert_eq!(s.judge(0.35, &f(3), false), Verdict::Keep);
        assert_eq!(s.judge(0.4, &f(4), false), Verdict::RateCapped);
    }

    #[test]
    fn the_level_decays_so_a_duller_scene_is_kept_again() {
        let params =
            SelectParams { warmup_frames: 0, max_kept_fps: 0.0, min_motion: 0.0, ..Default::default() };
        let mut s = FrameSelector::new(params);
        let sharp = measure(&texture(80, 60, 0));
        let dull = measure(&gaussian_blur(&texture(80, 60, 0), 1.5));
        assert_eq!(s.offer(0.0, &sharp, false), Verdict::Keep);
        assert_eq!(s.offer(0.1, &dull, false), Verdict::Blurred);
        // After many half-lives of only dull frames, dull is the scene's normal.
        assert_eq!(s.offer(30.0, &dull, false), Verdict::Keep);
    }
}
