//! The alignment pipeline: a keyframe and a view in, the homography between them and an
//! honest verdict out (pure layer).
//!
//! 1. Harris corners on a half-octave pyramid of a reduced image (about 1 MP), described
//!    by oriented, normalised patches (scale and rotation invariant);
//! 2. putative matches by SSD with ratio test and mutual check;
//! 3. a coarse homography by MSAC (tolerates the > 50 % outliers of hard pairs);
//! 4. the paper's steps 2–3 proper: SSD (as normalised correlation) within a small region
//!    around each predicted position, then LMedS with bucketing and a least-squares
//!    refinement, octave by octave from the detection resolution towards full resolution;
//! 5. a verdict: enough inliers, matches that agree on one geometry, inliers spread over a
//!    real part of the frame, a well-conditioned map. Rejecting is always better than
//!    guessing.
//!
//! # What was added to the paper's Harris + SSD + LMedS, and why (issue 13)
//!
//! - **A pyramid level chosen per view.** Guided matching walks down one octave at a time
//!   (an error of one sample at an octave is two at the next, inside the search window)
//!   and stops at the finest octave whose estimate keeps its support ([`AlignParams::keep_finer`]). A
//!   12 MP frame is rarely sharp at the pixel: its full-resolution patches are smooth and
//!   match ambiguously, and jumping there from the detection octave starved the matching
//!   (hunt3→hunt4: 170 inliers at native size, 57 and a rejection at 12 MP). Now a sharper
//!   or larger image never does worse than the octave that suits it. The model is chosen
//!   once, by LMedS at the detection octave; the finer octaves settle it
//!   ([`crate::geometry::robust::settle`]) rather than choose again: on a scene that is not
//!   one plane LMedS re-run on the finer matches fitted a narrower plane (ece5→ece6 at
//!   12 MP: 1.7 px from the reference at the detection octave, 4.9 px after the finer ones),
//!   and they settle it at the detection octave's tolerance (in full-resolution pixels),
//!   not at a threshold halved per octave that kept ever fewer of the plane's points.
//! - **1500 corners instead of 500, and guided points that are both spread and strong.**
//!   Pasted trees and cars took most of a 500-corner budget (bark 1→5/1→6, boat 1→6
//!   refused: "of 27 details that look alike, only 6 agree"). The guided points are the
//!   grid-spread ones (so an occluder cannot take them all) plus the 600 strongest
//!   corners (`guided_strongest`): on a scene with depth (a lawn in front of distant
//!   buildings) the grid alone gave the textured foreground as many votes as the
//!   facades, and LMedS fitted the lawn (hunt3→hunt4 at 12 MP 27 px off the facade).
//! - **A race of hypotheses before a weak model is judged** ([`align_from_matches`]). A
//!   model that matches under 30 % of the checked points may be weak because the view is
//!   blurred, occluded or partly seen, or because it is wrong: on a repeating facade a
//!   model shifted by one window period matches 20 % (`tests/align_synthetic.rs` seed
//!   178, 196 px off). The counts alone cannot tell these apart, so the next hypotheses
//!   the descriptor matches hold (sequential MSAC on what no earlier model explains) are
//!   refined too: a rival that sends the *same* keyframe points elsewhere with half the
//!   support or more means a repeating pattern and nothing is accepted ("a repeating
//!   pattern: two different viewpoints each explain the details"); a rival supported by
//!   other points is another plane of a scene with depth (roofs1→roofs2's near roofs
//!   and far facades) and does not count against the winner. A clear winner that the
//!   descriptor matches also agree with (≥ 35 % of them) is accepted on 5 % of the
//!   checked points instead of 20 %: blurred views (bikes and trees 1→5/1→6) and the
//!   partly seen roofs1→roofs2 are accepted, an aliased model (10–15 % agreement) is not.
//! - **Two settling passes at full resolution for small images**, so the larger guided set
//!   does not cost accuracy (trees 1→2 corner error 1.00 → 0.45 px).
//! - **Oriented, scale-normalised patches** for the putative matches (`features::descriptor`,
//!   unchanged): SSD of patches sampled at the corner's pyramid scale and in its dominant
//!   gradient orientation, so zoom and roll compare like with like.
//! - **A verdict that says what it saw** ([`Acceptance`]): a keyframe point outside the
//!   view's footprint is never counted; the matched points must agree on one geometry
//!   (another scene scatters), and each reason says "another scene", "the same scene,
//!   partly seen", "too few details" or "a repeating pattern", in a photographer's words.
//!   The lower floor is reached only through the race above: a lone 5 % floor accepted
//!   aliased models (BENCHMARKS.md). "Another scene" is said only by the verdict on guided
//!   matches; the descriptor stage's refusal says it cannot tell.
//! - **The keyframe's mask** ([`Frame::set_mask`]): corners whose support touches it are
//!   neither matched nor checked; they belong to what is to be removed.
//! - **A prior must win against the descriptors unless strongly confirmed** ([`align`]):
//!   a video's prior whole window periods off was confirmed unmoved on aliased matches and
//!   accepted 10–89 px off in rendered walks (all 28 false accepts of 52 walk cases); only
//!   a confirmed prior matching half the points looked for ([`PRIOR_TRUSTED_SHARE`]) now
//!   skips the descriptor path.
//! - **A scale and roll search when the plain path refuses** (`search`, [`SearchParams`]):
//!   both images resampled to one scale of the scene for each of 9 scales (×0.25..×4) and
//!   patches sampled at each of 16 rolls, scored by matches agreeing on one similarity;
//!   the best candidates' matches (or similarities) go through the steps above unchanged.
//!   bark 1→6 with occluders (×4 zoom, 150° roll) was refused and is now within 0.06 px.

use nalgebra::Point2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::fmt;

use crate::features::{
    DescriptorParams, GuidedParams, HarrisParams, Keypoint, MatchParams, descriptor, guided_match, harris,
    match_descriptors,
};
use crate::geometry::robust::{Consensus, settle};
use crate::geometry::{Correspondence, Homography, Method, NoModel, RobustParams, homography::image_corners};
use crate::imaging::pyramid::{Pyramid, half};
use crate::imaging::{GrayF32, Mask};

mod search;
pub use search::{SearchParams, Searched};

/// Parameters of the whole pipeline; `Default` is tuned on the Oxford sequences.
#[derive(Debug, Clone, PartialEq)]
pub struct AlignParams {
    /// Features are detected on the largest octave (image halved n times) with at most
    /// this many pixels.
    pub detect_max_pixels: usize,
    /// Half-octave levels in the detection pyramid (the top two only feed descriptors).
    pub pyramid_levels: usize,
    pub harris: HarrisParams,
    /// Corners kept on the finest detection level; coarser levels keep fewer.
    pub corners: usize,
    pub descriptor: DescriptorParams,
    pub matching: MatchParams,
    /// The coarse estimate from putative matches (threshold in detection-level pixels).
    pub coarse: RobustParams,
    pub guided: GuidedParams,
    /// The estimate from guided matches (threshold in pixels of the detection octave, the
    /// same tolerance at every finer octave).
    pub fine: RobustParams,
    /// At most this many keyframe points are matched by guided search.
    pub guided_points: usize,
    /// Guided points are spread by a `guided_grid × guided_grid` grid over the keyframe.
    pub guided_grid: usize,
    /// This many of the strongest corners (finest level first, no grid) are added to the
    /// guided points.
    pub guided_strongest: usize,
    /// See [`AlignParams::keep_finer`]: a finer octave's estimate replaces the coarser one
    /// only if it keeps at least this share of its inliers.
    pub keep_finer: f64,
    /// Coarse hypotheses raced when the first one's support is weak (see
    /// [`align_from_matches`]).
    pub hypotheses: usize,
    pub acceptance: Acceptance,
    /// The scale and roll search tried when the plain path refuses a view ([`align`]).
    pub search: SearchParams,
    /// Seed for every random choice (the same inputs and seed give the same answer).
    pub seed: u64,
}

impl Default for AlignParams {
    fn default() -> Self {
        Self {
            detect_max_pixels: 800_000,
            pyramid_levels: 8,
            harris: HarrisParams { border: 12, ..HarrisParams::default() },
            corners: 1500,
            descriptor: DescriptorParams::default(),
            matching: MatchParams::default(),
            coarse: RobustParams {
                method: Method::Msac,
                sample_size: 4,
                threshold_px: 3.0,
                max_iterations: 5000,
                ..RobustParams::default()
            },
            guided: GuidedParams::default(),
            fine: RobustParams { threshold_px: 1.5, ..RobustParams::paper() },
            guided_points: 600,
            guided_grid: 12,
            guided_strongest: 600,
            keep_finer: 0.7,
            hypotheses: 3,
            acceptance: Acceptance::default(),
            search: SearchParams::default(),
            seed: crate::DEFAULT_SEED,
        }
    }
}

/// What a view must show to be accepted.
///
/// Judged on what the view can see: keyframe points outside the view's footprint are
/// never counted. What separates another scene from the same scene partly seen is
/// whether the points that did match agree on one geometry
/// ([`Acceptance::min_consistency`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Acceptance {
    pub min_inliers: usize,
    /// Inliers as a share of the guided matches (points that found a confident match in
    /// the view). Matches of the same scene agree on one homography; matches forced onto
    /// another scene by a wrong model scatter over the search window and few agree.
    pub min_consistency: f64,
    /// Inliers as a share of the keyframe points checked inside the view's footprint. Not
    /// lower: on a repetitive facade a wrong model matches a consistent few (two of
    /// `tests/align_synthetic.rs`'s hard scenes, 85 of 85 matches agreeing, 20 % of those
    /// checked, 196 px off), and roofs1→roofs2 at 12 MP was accepted 40 px off at 15 %.
    pub min_inlier_share: f64,
    /// The floor on that share for a model that clearly beat every other hypothesis the
    /// putative matches hold (see [`align_from_matches`]): a blurred, occluded or partly
    /// seen view matches few of the points looked for, yet no other viewpoint explains
    /// them.
    pub min_inlier_share_unrivalled: f64,
    /// A rival hypothesis with at least this share of the winner's inliers, that places
    /// the keyframe elsewhere, makes the view ambiguous.
    pub max_rival: f64,
    /// The lower floor also needs the descriptor matches (global, ratio-tested) to agree
    /// with the model: at least this share of those whose keyframe point the model sends
    /// inside the view, within the coarse threshold. A blurred
    /// or occluded view of the same scene keeps most of its few descriptor matches
    /// consistent (55–80 % on the Oxford and 12 MP sets); a model aliased by a repeating
    /// pattern explains 10–15 % of them (`tests/align_synthetic.rs` seeds 4 and 178).
    pub min_putative_agreement: f64,
    /// A model matching at least this share of the checked points is accepted without
    /// racing other hypotheses; below it, a repeating pattern could explain the matches
    /// (a model aliased by one window period matched 20 % in `tests/align_synthetic.rs`).
    pub unchallenged_share: f64,
    /// Area of the inliers' convex hull as a share of the keyframe, for a view that sees
    /// at least [`PARTLY_SEEN`] of it; a view that sees less needs as much of what it sees
    /// (the share scaled by `seen / PARTLY_SEEN`), and never less than a quarter of this.
    /// A view from far along a facade that sees its last 13 % (hunt5 for hunt2,
    /// `parapano_hunt`) has its details over 1.6 % of the frame: 12 % of what it sees,
    /// and its homography lies within 0.5 px of SIFT + MAGSAC's over it; it was refused as
    /// though it had to place the whole frame.
    pub min_coverage: f64,
    /// Largest zoom between keyframe and view (either way), measured as the square root
    /// of the local area scale over the inliers' hull.
    pub max_zoom: f64,
}

impl Default for Acceptance {
    fn default() -> Self {
        Self {
            min_inliers: 20,
            min_consistency: 0.35,
            min_inlier_share: 0.2,
            min_inlier_share_unrivalled: 0.05,
            max_rival: 0.5,
            min_putative_agreement: 0.35,
            unchallenged_share: 0.3,
            min_coverage: 0.02,
            max_zoom: 8.0,
        }
    }
}

/// A prior that guided matching confirms unmoved and that matches at least this share of
/// the points looked for is accepted without the descriptor path (see [`align`]); the
/// aliased priors of a repeating facade matched up to 32 % (37 % where the fit moved them),
/// true ones 13–90 %.
pub const PRIOR_TRUSTED_SHARE: f64 = 0.5;

/// A view that sees less than this share of the keyframe sees it "partly".
pub const PARTLY_SEEN: f64 = 0.6;

/// What the final stage of an alignment found, for the verdict and its reasons.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Evidence {
    inliers: usize,
    matches: usize,
    /// Keyframe points searched for inside the view's footprint.
    checked: usize,
    coverage: f64,
    /// Share of the keyframe the view sees through the estimate.
    seen: f64,
}

/// Why a view was not accepted, in words a photographer can act on.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    TooFewMatches {
        matches: usize,
    },
    NoModel(NoModel),
    /// The descriptor matches do not agree on one viewpoint (before guided matching): the
    /// evidence cannot tell another scene from this one zoomed, turned or hidden too far.
    TooFewInliers {
        inliers: usize,
        matches: usize,
    },
    /// The points that matched do not agree on one geometry: another scene.
    AnotherScene {
        inliers: usize,
        matches: usize,
    },
    /// The same scene, but too little of it was matched in the part the view sees.
    PartlySeen {
        inliers: usize,
        needed: usize,
        seen: f64,
    },
    /// Most of the keyframe is in view, yet too few details match: blur, darkness,
    /// glare or an extreme angle.
    TooFewDetails {
        inliers: usize,
        needed: usize,
        checked: usize,
    },
    /// Two hypotheses that place the keyframe differently are about equally supported:
    /// a repeating pattern.
    Ambiguous {
        inliers: usize,
        rival: usize,
    },
    /// The inliers' hull covers too little of what the view sees of the keyframe
    /// (`coverage` of the keyframe, where the view sees `seen` of it).
    PoorSpread {
        coverage: f64,
        seen: f64,
    },
    IllConditioned {
        zoom: f64,
    },
    FoldsOver,
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::TooFewMatches { matches } => write!(
                f,
                "another scene, or too little of this one: only {matches} details look alike in the keyframe and the view"
            ),
            Self::NoModel(e) => write!(f, "no single viewpoint explains the details the two share: {e}"),
            // The descriptor stage alone cannot tell another scene from this one zoomed,
            // turned, blurred or hidden too far: "another scene" is said only by the
            // verdict on guided matches ([`Rejection::AnotherScene`]).
            Self::TooFewInliers { inliers, matches } => write!(
                f,
                "no common viewpoint found: of {matches} details that look alike, only {inliers} agree on one; \
                 another scene, or this one zoomed, turned, blurred or hidden too far to recognise"
            ),
            Self::AnotherScene { inliers, matches } => write!(
                f,
                "probably another scene: of {matches} points matched, only {inliers} agree on one viewpoint ({:.0} %)",
                100.0 * *inliers as f64 / (*matches).max(1) as f64
            ),
            Self::PartlySeen { inliers, needed, seen } => write!(
                f,
                "the same scene, partly seen: the view shows {:.0} % of the keyframe and only {inliers} points there \
                 could be matched ({needed} needed); a view with more of the keyframe in frame would help",
                100.0 * seen
            ),
            Self::TooFewDetails { inliers, needed, checked } => write!(
                f,
                "too few details match ({inliers} of {checked} points looked for, {needed} needed): the view may be \
                 blurred, too dark, or taken from too steep an angle"
            ),
            Self::Ambiguous { inliers, rival } => write!(
                f,
                "a repeating pattern: two different viewpoints each explain the details ({inliers} and {rival} points), \
                 so which windows or tiles match which cannot be told"
            ),
            Self::PoorSpread { coverage, seen } if *seen < PARTLY_SEEN => write!(
                f,
                "the matching details cluster in {:.1} % of the frame, of the {:.0} % the view sees: too little to place it",
                100.0 * coverage,
                100.0 * seen
            ),
            Self::PoorSpread { coverage, .. } => write!(
                f,
                "the matching details cluster in {:.1} % of the frame: too little to place the whole view",
                100.0 * coverage
            ),
            Self::IllConditioned { zoom } => {
                write!(f, "the homography zooms by {zoom:.1}x: too extreme to be a view of the same facade")
            }
            Self::FoldsOver => {
                write!(f, "the homography folds the keyframe over (part of it maps behind the camera)")
            }
        }
    }
}

/// The outcome of aligning one view to the keyframe.
#[derive(Debug, Clone)]
pub struct Alignment {
    /// The best estimate, also when rejected (for the report), `None` if there was none.
    pub homography: Option<Homography>,
    /// `None` when accepted.
    pub rejection: Option<Rejection>,
    /// Putative matches from descriptors (0 when a prior made them unnecessary).
    pub putative: usize,
    /// Correspondences the final estimate was fitted on (from guided matching).
    pub matches: usize,
    /// Those of `matches` that the final estimate explains.
    pub inliers: usize,
    /// Keyframe points checked by the final guided search.
    pub checked: usize,
    /// Median transfer distance of the final inliers, in full-resolution pixels.
    pub median_residual_px: f64,
    /// Area of the inliers' convex hull as a share of the keyframe.
    pub coverage: f64,
    /// Whether the estimate started from a given prior homography.
    pub from_prior: bool,
    /// The pyramid octave of the final estimate (0 = full resolution).
    pub octave: usize,
    /// Set when the plain path refused the view and the scale and roll search found it.
    pub searched: Option<Searched>,
}

impl Alignment {
    pub fn accepted(&self) -> bool {
        self.rejection.is_none() && self.homography.is_some()
    }

    fn rejected(rejection: Rejection, putative: usize) -> Self {
        Self {
            homography: None,
            rejection: Some(rejection),
            putative,
            matches: 0,
            inliers: 0,
            checked: 0,
            median_residual_px: f64::NAN,
            coverage: 0.0,
            from_prior: false,
            octave: 0,
            searched: None,
        }
    }
}

/// An image prepared for alignment: its octaves and its described corners. Building one
/// is most of the cost of aligning, so a keyframe's is built once and reused.
pub struct Frame {
    width: usize,
    height: usize,
    /// `octaves[o]` is the image halved `o` times; `octaves[0]` is full resolution.
    octaves: Vec<GrayF32>,
    detect_octave: usize,
    /// The corners used for matching: those detected, less any the keyframe's mask covers
    /// ([`Frame::set_mask`]).
    keypoints: Vec<Keypoint>,
    descriptors: Vec<descriptor::Descriptor>,
    /// Every corner detected, with its descriptor, so that a new mask starts from them.
    detected: Vec<(Keypoint, descriptor::Descriptor)>,
    /// σ of the Harris window, in pixels of a corner's level (its support is 3σ).
    harris_sigma: f32,
    /// The keyframe's mask, when one is set ([`Frame::set_mask`]).
    mask: Option<Mask>,
}

impl fmt::Debug for Frame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Frame({}x{}, {} keypoints)", self.width, self.height, self.keypoints.len())
    }
}

impl Frame {
    /// Builds the octaves and detects and describes corners.
    pub fn new(gray: GrayF32, params: &AlignParams) -> Self {
        let (width, height) = (gray.width(), gray.height());
        let mut octaves = vec![gray];
        loop {
            let last = octaves.last().expect("at least the base");
            if last.width().min(last.height()) < 64 {
                break;
            }
            octaves.push(half(last));
        }
        let detect_octave =
            octaves.iter().position(|o| o.len() <= params.detect_max_pixels).unwrap_or(octaves.len() - 1);
        let detect = octaves[detect_octave].clone();
        let octave_scale = (1u32 << detect_octave) as f32;
        let pyramid = Pyramid::half_octaves(detect, params.pyramid_levels, 24);
        let mut keypoints = Vec::new();
        let mut descriptors = Vec::new();
        for level in 0..pyramid.levels.len().saturating_sub(2) {
            let budget = (params.corners as f32 / pyramid.scales[level]).round() as usize;
            let hp = HarrisParams { max_corners: budget.max(16), ..params.harris.clone() };
            let corners = harris(&pyramid.levels[level], &hp);
            for (mut kp, d) in descriptor::describe(&pyramid, level, &corners, &params.descriptor) {
                kp.x *= octave_scale;
                kp.y *= octave_scale;
                kp.scale *= octave_scale;
                keypoints.push(kp);
                descriptors.push(d);
            }
        }
        let detected = keypoints.iter().copied().zip(descriptors.iter().copied()).collect();
        let harris_sigma = params.harris.sigma_i;
        Self {
            width,
            height,
            octaves,
            detect_octave,
            keypoints,
            descriptors,
            detected,
            harris_sigma,
            mask: None,
        }
    }

    /// Leaves out of matching every corner whose support touches the mask's holes (a
    /// keyframe's mask: what is there is to be removed, so a corner on it, or on its edge,
    /// belongs to the occluder and would spend the matching budget and votes on it). The
    /// support is the Harris window, 3σ at the corner's level. `None` restores every
    /// corner detected. Guided points and the verdict's count of checked points follow, so
    /// points under the mask never count against a view.
    ///
    /// # Panics
    /// If the mask is not the frame's size (callers check it, as [`crate::session`] does).
    pub fn set_mask(&mut self, mask: Option<&Mask>) {
        let kept: Vec<(Keypoint, descriptor::Descriptor)> = match mask {
            None => self.detected.clone(),
            Some(m) => {
                assert_eq!((m.width(), m.height()), (self.width, self.height), "mask and frame sizes differ");
                self.detected
                    .iter()
                    .filter(|(kp, _)| !touches_hole(m, kp, 3.0 * self.harris_sigma * kp.scale))
                    .copied()
                    .collect()
            }
        };
        (self.keypoints, self.descriptors) = kept.into_iter().unzip();
        self.mask = mask.cloned();
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    pub fn keypoints(&self) -> &[Keypoint] {
        &self.keypoints
    }

    /// The descriptors, in the order of [`Frame::keypoints`] (benchmarks and diagnostics).
    pub fn descriptors_for_bench(&self) -> &[descriptor::Descriptor] {
        &self.descriptors
    }

    /// The full-resolution grey image.
    pub fn image(&self) -> &GrayF32 {
        &self.octaves[0]
    }

    /// Keyframe points for guided matching: the strongest corners, spread over the frame
    /// by a grid, finest level first.
    fn guided_points(&self, limit: usize, grid: usize) -> Vec<Point2<f64>> {
        let grid = grid.max(1);
        let mut cells: Vec<Vec<&Keypoint>> = vec![Vec::new(); grid * grid];
        for kp in &self.keypoints {
            let cx = ((kp.x as usize * grid) / self.width).min(grid - 1);
            let cy = ((kp.y as usize * grid) / self.height).min(grid - 1);
            cells[cy * grid + cx].push(kp);
        }
        for c in &mut cells {
            c.sort_by(|a, b| a.level.cmp(&b.level).then(b.response.total_cmp(&a.response)));
        }
        // Round-robin over the cells so every part of the frame is represented.
        let mut out = Vec::with_capacity(limit);
        let mut rank = 0;
        while out.len() < limit {
            let mut any = false;
            for c in &cells {
                if let Some(kp) = c.get(rank) {
                    any = true;
                    out.push(Point2::new(kp.x as f64, kp.y as f64));
                    if out.len() == limit {
                        break;
                    }
                }
            }
            if !any {
                break;
            }
            rank += 1;
        }
        out
    }
}

/// Whether any hole of `mask` lies within `radius` of the keypoint, sampled on a grid over
/// the disc: a pixel apart for small radii, at most 9 × 9 points (a step of radius / 4)
/// for large ones, enough for a painted mask's blobs.
fn touches_hole(mask: &Mask, kp: &Keypoint, radius: f32) -> bool {
    let steps = (radius.ceil() as isize).clamp(1, 4);
    let step = radius / steps as f32;
    for j in -steps..=steps {
        for i in -steps..=steps {
            let (dx, dy) = (i as f32 * step, j as f32 * step);
            if dx * dx + dy * dy > radius * radius + 1e-3 {
                continue;
            }
            let (x, y) = ((kp.x + dx).round() as isize, (kp.y + dy).round() as isize);
            if mask.get_checked(x, y).is_some_and(|v| v > 127) {
                return true;
            }
        }
    }
    false
}

/// Aligns `view` to `key`: the homography mapping keyframe pixels to view pixels, and
/// whether it can be trusted. With a `prior` (say, the previous view's homography in a
/// sequence), guided matching starts from it and the descriptor stage is skipped when
/// that succeeds.
///
/// A prior is trusted without the descriptors only when guided matching confirms it
/// unmoved *and* it matches at least half the points looked for ([`PRIOR_TRUSTED_SHARE`]).
/// A prior off by whole window periods of a facade (a walk's first frame after the
/// keyframe, predicted unmoved while the camera moved 30 or 60 px) is confirmed unmoved
/// by a consistent set of aliased matches: 5–32 % of the points looked for, 26–62 px from
/// the truth, in the generated walks of `a_prior_whole_periods_off_loses_to_the_descriptors`
/// (and 19 px off in a rendered walk, `bench/align_video.py` seed 16). So a prior with
/// less support, or one the fit moved, races the descriptor path: the accepted model with
/// more inliers wins; where the descriptors find nothing (a view that shares a sliver
/// with the keyframe), a confirmed prior stands, and a moved one only if the descriptor
/// matches agree with it.
pub fn align(key: &Frame, view: &Frame, params: &AlignParams, prior: Option<&Homography>) -> Alignment {
    let mut challenged = None;
    if let Some(h) = prior {
        let (mut out, confirmed) = refine(key, view, params, *h, 0);
        out.from_prior = true;
        if out.accepted() {
            let share = out.inliers as f64 / out.checked.max(1) as f64;
            if confirmed && share >= PRIOR_TRUSTED_SHARE {
                return out;
            }
            challenged = Some((out, confirmed));
        }
    }
    let putative = putative_matches(key, view, params);
    let plain = align_from_matches(key, view, params, &putative);
    if let Some((p, confirmed)) = challenged {
        if plain.accepted() {
            return if p.inliers > plain.inliers { p } else { plain };
        }
        let h = p.homography.expect("an accepted alignment has a homography");
        if confirmed
            || putative_agreement(&putative, &h, params, key, view)
                >= params.acceptance.min_putative_agreement
        {
            return p;
        }
    }
    if search::worth_searching(&plain)
        && let Some(found) = search::rescue(key, view, params)
        && !rivalled_by(&found, &plain, params, key, view)
    {
        return found;
    }
    plain
}

/// Guided matching and re-estimation from `prior` alone, with no race against the
/// descriptors: for a prior known to be near, the camera's own motion between two
/// consecutive kept frames of a video (the session thread's chaining,
/// `daemon::video::runner`). There a near occluder that fills much of both frames moves
/// several times faster than the facade, and the descriptors' larger consensus is its
/// motion (a walk with a tree over 47 % of the picture: 566 inliers 62 px off the facade's
/// motion), which guided matching within a few pixels of the prior never sees.
pub fn align_near_prior(key: &Frame, view: &Frame, params: &AlignParams, prior: &Homography) -> Alignment {
    let (mut out, _) = refine(key, view, params, *prior, 0);
    out.from_prior = true;
    out
}

/// Whether the plain path's own guided model, refused on its share, rivals what the search
/// found: a different place for the keyframe with at least [`Acceptance::max_rival`] of its
/// inliers is the race's ambiguity, and a repeating facade gives just that (a search
/// candidate ×1.4 away matched 47 points of a one-period alias where the plain model
/// matched 80, `tests/align_synthetic.rs`'s scene 4).
fn rivalled_by(
    found: &Alignment,
    plain: &Alignment,
    params: &AlignParams,
    key: &Frame,
    view: &Frame,
) -> bool {
    let (Some(a), Some(b)) = (&found.homography, &plain.homography) else { return false };
    plain.inliers > 0
        && plain.inliers as f64 >= params.acceptance.max_rival * found.inliers as f64
        && maps_differ(a, b, found.octave.max(plain.octave), key, view)
}

/// Step 2: putative correspondences from descriptor matches (SSD of oriented, normalised
/// patches with ratio test and mutual check), keyframe → view.
pub fn putative_matches(key: &Frame, view: &Frame, params: &AlignParams) -> Vec<Correspondence> {
    let matches = match_descriptors(&key.descriptors, &view.descriptors, &params.matching);
    matches
        .iter()
        .map(|m| {
            let (a, b) = (key.keypoints[m.key], view.keypoints[m.view]);
            Correspondence::new(Point2::new(a.x as f64, a.y as f64), Point2::new(b.x as f64, b.y as f64))
        })
        .collect()
}

/// Steps 3–5 from given putative correspondences: the coarse model, guided refinement
/// coarse to fine, and the verdict. [`align`] is this after [`putative_matches`]; tests
/// use it to feed in correspondences with a known share of outliers.
pub fn align_from_matches(
    key: &Frame,
    view: &Frame,
    params: &AlignParams,
    putative: &[Correspondence],
) -> Alignment {
    if putative.len() < 8 {
        return Alignment::rejected(Rejection::TooFewMatches { matches: putative.len() }, putative.len());
    }
    // Coarse model; its threshold is in detection-level pixels.
    let scale = (1u32 << key.detect_octave) as f64;
    let coarse_params =
        RobustParams { threshold_px: params.coarse.threshold_px * scale, ..params.coarse.clone() };
    let rng = ChaCha8Rng::seed_from_u64(params.seed);
    let coarse = match Consensus::new(coarse_params, rng).estimate(putative) {
        Ok(e) => e,
        Err(e) => return Alignment::rejected(Rejection::NoModel(e), putative.len()),
    };
    if coarse.inliers.len() < params.acceptance.min_inliers.min(12) {
        let mut out = Alignment::rejected(
            Rejection::TooFewInliers { inliers: coarse.inliers.len(), matches: putative.len() },
            putative.len(),
        );
        out.homography = Some(coarse.homography);
        return out;
    }
    let first = match fit(key, view, params, coarse.homography) {
        Ok(f) => f,
        Err((e, h)) => {
            let mut out = Alignment::rejected(Rejection::NoModel(e), putative.len());
            out.homography = Some(h);
            return out;
        }
    };
    let share = first.evidence.inliers as f64 / first.evidence.checked.max(1) as f64;
    if share >= params.acceptance.unchallenged_share
        && verdict(&params.acceptance, &first, Floor::Strict).is_none()
    {
        return first.into_alignment(None, putative.len());
    }
    // Weak support: is it weak because the view is blurred, occluded or partly seen, or
    // because the model is wrong (a repetitive facade aliased by one period)? Race the
    // next hypotheses the putative matches hold (sequential MSAC: each on the matches no
    // earlier coarse model explains) and keep the best supported. A clear winner may be
    // accepted on a lower share of the checked points; a close rival that disagrees means
    // the details fit two viewpoints and nothing is accepted.
    let tol = coarse_threshold_sq(params, key);
    let mut fitted = vec![first];
    let mut remaining: Vec<Correspondence> = putative.to_vec();
    let mut model = coarse.homography;
    for k in 1..params.hypotheses {
        remaining.retain(|c| c.residual_sq(&model) > tol);
        if remaining.len() < 8 {
            break;
        }
        let coarse_params =
            RobustParams { threshold_px: params.coarse.threshold_px * scale, ..params.coarse.clone() };
        let rng = ChaCha8Rng::seed_from_u64(params.seed.wrapping_add(0x100 * k as u64));
        let Ok(est) = Consensus::new(coarse_params, rng).estimate(&remaining) else { break };
        if est.inliers.len() < params.acceptance.min_inliers.min(12) {
            break;
        }
        model = est.homography;
        if let Ok(f) = fit(key, view, params, est.homography) {
            fitted.push(f);
        }
    }
    let best = (0..fitted.len())
        .max_by_key(|&i| (fitted[i].inliers.len(), std::cmp::Reverse(i)))
        .expect("the first hypothesis");
    let rival = fitted
        .iter()
        .enumerate()
        .filter(|&(i, f)| {
            i != best && models_differ(&fitted[best], f, key, view) && claim_same_points(&fitted[best], f)
        })
        .map(|(_, f)| f.inliers.len())
        .max()
        .unwrap_or(0);
    let best = fitted.swap_remove(best);
    // Judged on what the view can see: a descriptor match whose keyframe point the model
    // sends outside the view cannot be right under any model, so it does not count against
    // this one (a walk's frame that sees 41 % of the keyframe: 15 of its 61 matches agree,
    // and 15 others are of keyframe points it does not show).
    let agreement = putative_agreement(putative, &best.h, params, key, view);
    best.into_alignment_with_rival(params, rival, agreement, putative.len())
}

/// The share of the descriptor matches whose keyframe point `h` sends inside the view that
/// `h` explains within the coarse threshold (0 when none lands inside).
fn putative_agreement(
    putative: &[Correspondence],
    h: &Homography,
    params: &AlignParams,
    key: &Frame,
    view: &Frame,
) -> f64 {
    let tol = coarse_threshold_sq(params, key);
    let in_view: Vec<&Correspondence> = putative.iter().filter(|c| lands_inside(h, c.key, view)).collect();
    in_view.iter().filter(|c| c.residual_sq(h) <= tol).count() as f64 / in_view.len().max(1) as f64
}

/// Squared threshold of the coarse estimate, in full-resolution pixels.
fn coarse_threshold_sq(params: &AlignParams, key: &Frame) -> f64 {
    let t = params.coarse.threshold_px * (1u32 << key.detect_octave) as f64;
    t * t
}

/// Whether two fitted models send the keyframe to different places (more than a few
/// samples of the coarser one's octave, median over the keyframe points the first sees).
fn models_differ(a: &Fitted, b: &Fitted, key: &Frame, view: &Frame) -> bool {
    maps_differ(&a.h, &b.h, a.octave.max(b.octave), key, view)
}

/// Whether `a` and `b` send the keyframe to different places: more than 4 samples of
/// `octave`, median over a grid of the keyframe points `a` sends inside the view.
fn maps_differ(a: &Homography, b: &Homography, octave: usize, key: &Frame, view: &Frame) -> bool {
    let tol = 4.0 * (1u32 << octave) as f64;
    a.median_grid_gap(b, key.width as f64, key.height as f64, |p| lands_inside(a, p, view))
        .is_none_or(|gap| gap > tol)
}

/// Whether a rival model's inliers are largely the winner's keyframe points, sent
/// elsewhere: two viewpoints for the same details, which is what a repeating pattern
/// gives. A rival supported by other points (the far buildings behind near roofs: another
/// plane of the same scene, with parallax) does not make the winner ambiguous.
///
/// A shared point counts only where the two models send it apart (by the tolerance of
/// [`maps_differ`]). Two planes of one scene meet along a line that both map alike, and
/// the points near it are inliers of both, at the same place in the view: on parapano_ece
/// (ece4 with pasted occluders, against ece3, no mask) the second model shared 41 of its
/// 103 inliers with the winner's 177, 36 of them sent within 3 px of where the winner
/// sends them, and the building's best view was refused as a repeating pattern. A
/// pattern aliased by one period sends its shared points a period apart.
fn claim_same_points(winner: &Fitted, rival: &Fitted) -> bool {
    let tol = 4.0 * (1u32 << winner.octave.max(rival.octave)) as f64;
    let mine: std::collections::HashSet<(u64, u64)> =
        winner.inlier_keys.iter().map(|p| (p.x.to_bits(), p.y.to_bits())).collect();
    let shared = rival
        .inlier_keys
        .iter()
        .filter(|p| mine.contains(&(p.x.to_bits(), p.y.to_bits())))
        .filter(|&&p| match (winner.h.apply(p), rival.h.apply(p)) {
            (Some(a), Some(b)) => (a - b).norm() > tol,
            _ => true,
        })
        .count();
    shared as f64 >= 0.3 * rival.inlier_keys.len() as f64
}

/// One stage of the coarse-to-fine refinement: the estimate at one octave.
struct Stage {
    octave: usize,
    h: Homography,
    found: Vec<Correspondence>,
    inliers: Vec<usize>,
    checked: usize,
}

/// A model fitted by guided matching, with what the verdict weighs.
struct Fitted {
    octave: usize,
    h: Homography,
    inliers: Vec<usize>,
    /// The keyframe points of the inliers.
    inlier_keys: Vec<Point2<f64>>,
    evidence: Evidence,
    hull: Vec<Point2<f64>>,
    median_residual_px: f64,
}

impl Fitted {
    fn into_alignment(self, rejection: Option<Rejection>, putative: usize) -> Alignment {
        Alignment {
            homography: Some(self.h),
            rejection,
            putative,
            matches: self.evidence.matches,
            inliers: self.evidence.inliers,
            checked: self.evidence.checked,
            median_residual_px: self.median_residual_px,
            coverage: self.evidence.coverage,
            from_prior: false,
            octave: self.octave,
            searched: None,
        }
    }

    /// The verdict on the winner of a race of hypotheses: the lower floor when no other
    /// hypothesis came close and the descriptor matches agree with it (`agreement`: the
    /// share of the putative matches it explains), a refusal naming the ambiguity when a
    /// rival came close.
    fn into_alignment_with_rival(
        self,
        params: &AlignParams,
        rival: usize,
        agreement: f64,
        putative: usize,
    ) -> Alignment {
        let acc = &params.acceptance;
        let inliers = self.inliers.len();
        let strict = verdict(acc, &self, Floor::Strict);
        let rejection = if rival as f64 >= acc.max_rival * inliers as f64 && rival >= acc.min_inliers {
            Some(Rejection::Ambiguous { inliers, rival })
        } else if strict.is_none() {
            None
        } else if agreement >= acc.min_putative_agreement {
            verdict(acc, &self, Floor::Unrivalled)
        } else {
            strict
        };
        self.into_alignment(rejection, putative)
    }
}

/// Which floor on the share of checked points applies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Floor {
    Strict,
    /// The model beat every other hypothesis clearly.
    Unrivalled,
}

/// Guided matching and re-estimation from an initial `h`, coarse to fine, then the
/// strict verdict (used for a prior: on failure the descriptors are tried).
///
/// A prior is a hypothesis that came from elsewhere (the previous frame's accepted
/// homography, carried on): a model that guided matching refines *without moving it* is
/// confirmed by two independent sources, as a race's clear winner is, and is judged on the
/// lower floor ([`Acceptance::min_inlier_share_unrivalled`]). A repeating pattern cannot
/// alias it: that needs a jump of one period, far outside the search window. A walk's
/// frame that sees 41 % of the keyframe past near trees matched 55 of 404 points looked
/// for, 55 of 70 found agreeing at 0.05 px, and was refused on the strict floor.
///
/// Also says whether the prior was confirmed (the fit did not move it); [`align`] does not
/// trust a moved one on its own.
fn refine(
    key: &Frame,
    view: &Frame,
    params: &AlignParams,
    h: Homography,
    putative: usize,
) -> (Alignment, bool) {
    match fit(key, view, params, h) {
        Ok(f) => {
            let confirmed = !maps_differ(&f.h, &h, f.octave, key, view);
            let mut rejection = verdict(&params.acceptance, &f, Floor::Strict);
            if matches!(rejection, Some(Rejection::PartlySeen { .. } | Rejection::TooFewDetails { .. }))
                && confirmed
            {
                rejection = verdict(&params.acceptance, &f, Floor::Unrivalled);
            }
            (f.into_alignment(rejection, putative), confirmed)
        }
        Err((e, h)) => {
            let mut out = Alignment::rejected(Rejection::NoModel(e), putative);
            out.homography = Some(h);
            (out, false)
        }
    }
}

/// Refits of a finer octave's model on its inliers (see [`settle`]).
const SETTLE_ROUNDS: usize = 4;

/// Guided matching and re-estimation from an initial `h`, coarse to fine.
///
/// The octave schedule walks from the detection octave down to full resolution one
/// octave at a time (an error of one sample at one octave is two at the next, well
/// inside the search window), and stops at the finest octave whose estimate is still
/// supported (a finer octave's estimate replaces the coarser one only if it keeps
/// [`AlignParams::keep_finer`] of its inliers): the pyramid level is chosen per view. On a
/// soft image (a 12 MP frame is rarely sharp at the pixel level) the full-resolution
/// patches are smooth and match ambiguously; there the coarser octave's estimate is the
/// better one, and alignment must not get worse as the resolution rises.
fn fit(
    key: &Frame,
    view: &Frame,
    params: &AlignParams,
    h: Homography,
) -> Result<Fitted, (NoModel, Homography)> {
    let mut points = key.guided_points(params.guided_points, params.guided_grid);
    if params.guided_strongest > 0 {
        let have: std::collections::HashSet<(u64, u64)> =
            points.iter().map(|p| (p.x.to_bits(), p.y.to_bits())).collect();
        let extra = key.guided_points(params.guided_strongest, 1);
        points.extend(extra.into_iter().filter(|p| !have.contains(&(p.x.to_bits(), p.y.to_bits()))));
    }
    let mut stages: Vec<(usize, usize)> = vec![(key.detect_octave, params.guided.search)];
    for octave in (0..key.detect_octave).rev() {
        stages.push((octave, params.guided.search.min(3)));
    }
    if key.detect_octave == 0 {
        // A small image: two more passes with the better model and a tighter search (the
        // second settles what the first moved: trees 1->2's corner error 1.00 -> 0.45 px
        // with the larger guided set).
        stages.push((0, 2));
        stages.push((0, 2));
    }
    // One tolerance for every stage, in full-resolution pixels: the detection octave's.
    // The finer octaves place the matches more precisely but do not redefine which of them
    // lie on the plane: at a threshold halved with each octave, a scene that is not one
    // plane kept ever fewer of the chosen plane's points, and the settled fit narrowed to
    // a part of it (building1→building2 at 12 MP: 192 of 195 octave-1 matches within the
    // detection tolerance of the finer fit, 82 within its own threshold, and the octave
    // refused; ece1→ece2 5.2 px from the reference after the finer octaves, 3.2 px now).
    let fine = RobustParams {
        threshold_px: params.fine.threshold_px * (1u32 << key.detect_octave) as f64,
        ..params.fine.clone()
    };
    let mut best: Option<Stage> = None;
    let mut h = h;
    for (i, &(octave, search)) in stages.iter().enumerate() {
        let gp = GuidedParams { search, ..params.guided.clone() };
        let found = guided_match(&key.octaves, &view.octaves, &points, &h, octave, &gp);
        let checked = points.iter().filter(|&&p| lands_inside(&h, p, view)).count();
        // The detection octave chooses the model (LMedS with bucketing on every guided
        // match); the finer octaves and settling passes only sharpen it. Run again there,
        // LMedS chose afresh which plane of a scene with depth wins, and on the finer
        // matches it often fitted a narrower one: ece5→ece6 at 12 MP was 1.7 px from the
        // reference at the detection octave and 4.9 px after the finer ones.
        let est = if best.is_some() {
            match settle(&found, &h, fine.threshold_px, SETTLE_ROUNDS) {
                Some(e) => e,
                None => break,
            }
        } else {
            let rng = ChaCha8Rng::seed_from_u64(params.seed.wrapping_add(1 + i as u64));
            match Consensus::new(fine.clone(), rng).estimate(&found) {
                Ok(e) => e,
                Err(e) => return Err((e, h)),
            }
        };
        if let Some(prev) = &best
            && (est.inliers.len() as f64) < params.keep_finer * prev.inliers.len() as f64
        {
            break;
        }
        h = est.homography;
        // Every stage searches all points again: where the previous model was off by more
        // than the search window, the better one now finds them.
        best = Some(Stage { octave, h, found, inliers: est.inliers, checked });
    }
    let Stage { octave, h, found, inliers, checked } = best.expect("at least one stage");
    let inlier_keys: Vec<Point2<f64>> = inliers.iter().map(|&k| found[k].key).collect();
    let mut residuals: Vec<f64> = inliers.iter().map(|&k| found[k].residual(&h)).collect();
    residuals.sort_by(f64::total_cmp);
    let median_residual_px = residuals.get(residuals.len() / 2).copied().unwrap_or(f64::NAN);
    let hull = convex_hull(&inlier_keys);
    let coverage = polygon_area(&hull) / ((key.width - 1) * (key.height - 1)).max(1) as f64;
    let evidence = Evidence {
        inliers: inliers.len(),
        matches: found.len(),
        checked,
        coverage,
        seen: seen_share(&h, key, view),
    };
    Ok(Fitted { octave, h, inliers, inlier_keys, evidence, hull, median_residual_px })
}

fn verdict(acc: &Acceptance, f: &Fitted, floor: Floor) -> Option<Rejection> {
    let (h, hull, e) = (&f.h, &f.hull, &f.evidence);
    let consistency = e.inliers as f64 / e.matches.max(1) as f64;
    if consistency < acc.min_consistency {
        return Some(Rejection::AnotherScene { inliers: e.inliers, matches: e.matches });
    }
    let share = match floor {
        Floor::Strict => acc.min_inlier_share,
        Floor::Unrivalled => acc.min_inlier_share_unrivalled,
    };
    if e.inliers < acc.min_inliers || (e.inliers as f64) < share * e.checked as f64 {
        let needed = acc.min_inliers.max((share * e.checked as f64).ceil() as usize);
        return Some(if e.seen < PARTLY_SEEN {
            Rejection::PartlySeen { inliers: e.inliers, needed, seen: e.seen }
        } else {
            Rejection::TooFewDetails { inliers: e.inliers, needed, checked: e.checked }
        });
    }
    let needed = acc.min_coverage * (e.seen / PARTLY_SEEN).clamp(0.25, 1.0);
    if e.coverage < needed {
        return Some(Rejection::PoorSpread { coverage: e.coverage, seen: e.seen });
    }
    if hull.iter().any(|&p| h.w(p) <= 0.0 || h.area_scale(p) <= 0.0) {
        return Some(Rejection::FoldsOver);
    }
    let max_area = acc.max_zoom * acc.max_zoom;
    for &p in hull {
        let a = h.area_scale(p);
        if a > max_area || a < 1.0 / max_area {
            let zoom = if a > 1.0 { a.sqrt() } else { 1.0 / a.sqrt() };
            return Some(Rejection::IllConditioned { zoom });
        }
    }
    None
}

/// Share of the keyframe whose image through `h` lands inside the view (a 32 × 32 grid).
fn seen_share(h: &Homography, key: &Frame, view: &Frame) -> f64 {
    const N: usize = 32;
    let (vw, vh) = ((view.width - 1) as f64, (view.height - 1) as f64);
    let mut inside = 0;
    for j in 0..N {
        for i in 0..N {
            let p = Point2::new(
                (i as f64 + 0.5) * key.width as f64 / N as f64,
                (j as f64 + 0.5) * key.height as f64 / N as f64,
            );
            let q = if h.w(p) > 0.0 { h.apply(p) } else { None };
            if q.is_some_and(|q| q.x >= 0.0 && q.y >= 0.0 && q.x <= vw && q.y <= vh) {
                inside += 1;
            }
        }
    }
    inside as f64 / (N * N) as f64
}

fn lands_inside(h: &Homography, p: Point2<f64>, view: &Frame) -> bool {
    h.w(p) > 0.0
        && h.apply(p).is_some_and(|q| {
            q.x >= 8.0 && q.y >= 8.0 && q.x <= view.width as f64 - 9.0 && q.y <= view.height as f64 - 9.0
        })
}

/// Convex hull (Andrew's monotone chain), counter-clockwise in a y-up frame.
fn convex_hull(points: &[Point2<f64>]) -> Vec<Point2<f64>> {
    let mut pts: Vec<Point2<f64>> = points.to_vec();
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let cross = crate::geometry::homography::cross;
    let mut hull: Vec<Point2<f64>> = Vec::with_capacity(2 * pts.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Point2<f64>>> =
            if pass == 0 { Box::new(pts.iter()) } else { Box::new(pts.iter().rev()) };
        for &p in iter {
            while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

fn polygon_area(poly: &[Point2<f64>]) -> f64 {
    if poly.len() < 3 {
        return 0.0;
    }
    let mut a = 0.0;
    for i in 0..poly.len() {
        let (p, q) = (poly[i], poly[(i + 1) % poly.len()]);
        a += p.x * q.y - q.x * p.y;
    }
    a.abs() / 2.0
}

/// The corners of a `width × height` frame (re-exported for reports).
pub fn frame_corners(width: usize, height: usize) -> [Point2<f64>; 4] {
    image_corners(width, height)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::RgbF32;
    use crate::imaging::convert::luminance;
    use crate::synth;

    #[test]
    fn hull_and_area_of_a_square_with_inner_points() {
        let pts: Vec<_> = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0), (1.0, 1.0), (0.5, 1.5)]
            .iter()
            .map(|&(x, y)| Point2::new(x, y))
            .collect();
        let hull = convex_hull(&pts);
        assert_eq!(hull.len(), 4);
        assert!((polygon_area(&hull) - 4.0).abs() < 1e-12);
    }

    #[test]
    fn aligns_a_rendered_view_and_rejects_an_unrelated_one() {
        let scene = synth::facade(640, 480, 11);
        let truth =
            Homography::from_rows([[0.95, 0.08, 12.0], [-0.06, 0.97, 9.0], [1e-4, -5e-5, 1.0]]).unwrap();
        let view = synth::render_view(&scene, &truth.inverse().unwrap(), 640, 480, [0.0; 3]);
        let params = AlignParams::default();
        let kf = Frame::new(luminance(&scene), &params);
        let vf = Frame::new(luminance(&view), &params);
        let a = align(&kf, &vf, &params, None);
        assert!(a.accepted(), "{:?}", a.rejection);
        let err = a.homography.unwrap().mean_corner_error(&truth, 640, 480);
        assert!(err < 0.3, "corner error {err}");

        let other = synth::facade(640, 480, 12345);
        let of = Frame::new(luminance(&other), &params);
        let b = align(&kf, &of, &params, None);
        assert!(!b.accepted(), "an unrelated facade was accepted: {b:?}");
    }

    #[test]
    fn corners_under_the_keyframes_mask_are_not_matched() {
        let scene = synth::facade(640, 480, 21);
        let truth = Homography::from_rows([[0.97, 0.05, 9.0], [-0.04, 0.99, 6.0], [5e-5, 0.0, 1.0]]).unwrap();
        let view = synth::render_view(&scene, &truth.inverse().unwrap(), 640, 480, [0.0; 3]);
        let params = AlignParams::default();
        let mut kf = Frame::new(luminance(&scene), &params);
        let all = kf.keypoints().len();
        // A tree-sized hole over the left third.
        let mask =
            Mask::from_fn(
                640,
                480,
                |x, y| if (40..240).contains(&x) && (60..420).contains(&y) { 255 } else { 0 },
            );
        kf.set_mask(Some(&mask));
        let kept = kf.keypoints().len();
        assert!(kept < all * 9 / 10 && kept > all / 3, "{kept} of {all} kept");
        assert_eq!(kf.descriptors.len(), kept);
        // None within the Harris support (3σ at its level) of a hole.
        for kp in kf.keypoints() {
            let r = 3.0 * params.harris.sigma_i * kp.scale;
            // Distance to the hole's pixels (x 40..=239, y 60..=419), less the rounding to
            // pixels of the samples.
            let (dx, dy) =
                ((40.0 - kp.x).max(kp.x - 239.0).max(0.0), (60.0 - kp.y).max(kp.y - 419.0).max(0.0));
            assert!((dx * dx + dy * dy).sqrt() > r - 1.0, "{kp:?} on the mask");
        }
        let vf = Frame::new(luminance(&view), &params);
        let a = align(&kf, &vf, &params, None);
        assert!(a.accepted(), "{:?}", a.rejection);
        assert!(a.homography.unwrap().mean_corner_error(&truth, 640, 480) < 0.5);
        // The unmasked points alone were checked: none under the hole counts against it.
        assert!(a.checked <= kept, "{} checked of {kept}", a.checked);
        kf.set_mask(None);
        assert_eq!(kf.keypoints().len(), all);
    }

    #[test]
    fn only_the_guided_verdict_says_another_scene() {
        // The descriptor stage cannot tell another scene from a zoomed, turned or hidden
        // view of this one; only guided matches that scatter can (README quotes these).
        let reasons = [
            Rejection::TooFewMatches { matches: 5 },
            Rejection::TooFewInliers { inliers: 5, matches: 41 },
            Rejection::PartlySeen { inliers: 10, needed: 20, seen: 0.4 },
            Rejection::TooFewDetails { inliers: 10, needed: 20, checked: 100 },
            Rejection::Ambiguous { inliers: 40, rival: 30 },
            Rejection::PoorSpread { coverage: 0.01, seen: 0.9 },
            Rejection::PoorSpread { coverage: 0.004, seen: 0.1 },
            Rejection::IllConditioned { zoom: 9.0 },
            Rejection::FoldsOver,
        ];
        for r in &reasons {
            assert!(!r.to_string().contains("probably another scene"), "{r:?}: {r}");
        }
        let scattered = Rejection::AnotherScene { inliers: 10, matches: 100 }.to_string();
        assert!(scattered.starts_with("probably another scene"), "{scattered}");
    }

    #[test]
    fn a_prior_the_guided_fit_confirms_is_judged_on_the_lower_floor() {
        // A blurred view that sees the keyframe's right half: few of the points looked for
        // match, all of them on one viewpoint.
        let scene = synth::facade(640, 480, 31);
        let truth = Homography::from_rows([[1.0, 0.02, -300.0], [-0.01, 1.0, 5.0], [0.0, 0.0, 1.0]]).unwrap();
        let view = synth::render_view(&scene, &truth.inverse().unwrap(), 640, 480, [0.5; 3]);
        let view = crate::imaging::filter::gaussian_blur(&luminance(&view), BLUR);
        let params = AlignParams::default();
        let kf = Frame::new(luminance(&scene), &params);
        let vf = Frame::new(view, &params);
        let strict = refine_strict(&kf, &vf, &params, truth);
        assert!(
            matches!(strict.rejection, Some(Rejection::PartlySeen { .. })),
            "the strict floor alone decides: not the case tested ({:?}, {} of {})",
            strict.rejection,
            strict.inliers,
            strict.checked
        );
        let prior = Homography::translation(1.5, -1.0).after(&truth);
        let (a, confirmed) = refine(&kf, &vf, &params, prior, 0);
        assert!(a.accepted() && confirmed, "{a:?}");
        // Its support is too weak to skip the descriptors (a prior whole periods off has
        // as much): they race, and either way the answer is right.
        let b = align(&kf, &vf, &params, Some(&prior));
        assert!(b.accepted(), "{b:?}");
        // Over the half the view sees (blurred by σ = 4.5 px): within a pixel, nowhere 2 px off.
        for h in [a.homography.unwrap(), b.homography.unwrap()] {
            let errors = sorted_errors(&h, &truth, (20..460).step_by(40), (340..620).step_by(40));
            assert!(errors[errors.len() / 2] < 1.0 && errors[errors.len() - 1] < 2.0, "{errors:?}");
        }
    }

    /// A view from far along a facade sees only its last strip, where the details lie in
    /// one band (sky above, a lawn below: plain): they cover 1.1 % of the frame, where the
    /// view sees 16 % of it. Judged by what it sees, not by the whole frame, it is accepted,
    /// and right over the strip (hunt5 for hunt2 in `parapano_hunt` was refused so).
    #[test]
    fn a_view_that_sees_a_strip_is_judged_by_the_strip() {
        let (w, h) = (640usize, 480usize);
        let bricks = synth::facade(w, h, 12);
        let band = 200..264;
        let scene = RgbF32::from_fn(w, h, |x, y| {
            if band.contains(&y) {
                bricks.get(x, y)
            } else {
                let t = y as f32 / h as f32;
                [0.6 + 0.1 * t, 0.65 + 0.1 * t, 0.7]
            }
        });
        let truth =
            Homography::from_rows([[1.02, 0.01, -560.0], [0.005, 1.0, 4.0], [0.00002, 0.0, 1.0]]).unwrap();
        let view = synth::render_view(&scene, &truth.inverse().unwrap(), w, h, [0.65; 3]);
        let params = AlignParams::default();
        let kf = Frame::new(luminance(&scene), &params);
        let vf = Frame::new(luminance(&view), &params);
        let a = align(&kf, &vf, &params, None);
        assert!(a.accepted(), "{a:?}");
        assert!(a.coverage < params.acceptance.min_coverage, "not the case tested: {a:?}");
        let errors = sorted_errors(&a.homography.unwrap(), &truth, band.step_by(8), (566..636).step_by(10));
        assert!(errors[errors.len() / 2] < 0.5 && errors[errors.len() - 1] < 1.5, "{errors:?}");
    }

    /// The distances between where `h` and `truth` send the grid of `ys` × `xs`, ascending.
    fn sorted_errors(
        h: &Homography,
        truth: &Homography,
        ys: impl Iterator<Item = usize>,
        xs: impl Iterator<Item = usize> + Clone,
    ) -> Vec<f64> {
        let mut errors: Vec<f64> = ys
            .flat_map(|y| xs.clone().map(move |x| Point2::new(x as f64, y as f64)))
            .map(|p| (h.apply(p).unwrap() - truth.apply(p).unwrap()).norm())
            .collect();
        errors.sort_by(f64::total_cmp);
        errors
    }

    const BLUR: f32 = 4.5;

    fn refine_strict(key: &Frame, view: &Frame, params: &AlignParams, h: Homography) -> Alignment {
        let f = fit(key, view, params, h).expect("a model");
        let r = verdict(&params.acceptance, &f, Floor::Strict);
        f.into_alignment(r, 0)
    }

    /// A walk along a facade: a tree masked over 45–60 % of the keyframe, the view
    /// 30 or 60 px further (one or two window periods) with its own tree elsewhere, and the
    /// prior a video gives the first frame after its keyframe: no motion at all.
    #[test]
    fn a_prior_whole_periods_off_loses_to_the_descriptors() {
        let params = AlignParams::default();
        // (facade seed, camera shift, tree size, tree centre, the view's tree offset)
        for (seed, shift, size, cx, vdx) in [(3, 60.0, 800.0, 420.0, 250.0), (8, 30.0, 520.0, 400.0, -90.0)] {
            let world = synth::facade(1400, 480, seed);
            let key_to_world = Homography::translation(200.0, 0.0);
            let zoom = Homography::from_rows([[0.99, 0.0, 0.0], [0.0, 0.99, 0.0], [0.0, 0.0, 1.0]]).unwrap();
            let view_to_world = Homography::translation(200.0 + shift, 0.0).after(&zoom);
            let mut key = synth::render_view(&world, &key_to_world, 640, 480, [0.0; 3]);
            let mut view = synth::render_view(&world, &view_to_world, 640, 480, [0.0; 3]);
            let mut mask = Mask::new(640, 480, 0);
            synth::paint_occluder(
                &mut key,
                Some(&mut mask),
                synth::Occluder::Tree,
                cx,
                260.0,
                size,
                seed + 7,
            );
            synth::paint_occluder(&mut view, None, synth::Occluder::Tree, cx + vdx, 260.0, size, seed + 7);
            let mask = synth::dilate_mask(&mask, 6);
            let mut kf = Frame::new(luminance(&key), &params);
            kf.set_mask(Some(&mask));
            let vf = Frame::new(luminance(&view), &params);
            let truth = view_to_world.inverse().unwrap().after(&key_to_world);
            // The case tested: guided matching confirms the prior on aliased matches.
            let (aliased, confirmed) = refine(&kf, &vf, &params, Homography::identity(), 0);
            let off = aliased.homography.unwrap().mean_corner_error(&truth, 640, 480);
            assert!(
                aliased.accepted() && confirmed && off > 20.0,
                "seed {seed}: not the case tested: {aliased:?}"
            );
            let a = align(&kf, &vf, &params, Some(&Homography::identity()));
            assert!(a.accepted(), "seed {seed}: {:?}", a.rejection);
            let err = a.homography.unwrap().mean_corner_error(&truth, 640, 480);
            assert!(err < 0.5 && !a.from_prior, "seed {seed}: {err} px off ({a:?})");
        }
    }

    #[test]
    fn a_good_prior_skips_the_descriptors() {
        let scene = synth::facade(480, 360, 2);
        let truth = Homography::from_rows([[1.02, 0.03, -7.0], [-0.02, 1.01, 4.0], [0.0, 0.0, 1.0]]).unwrap();
        let view = synth::render_view(&scene, &truth.inverse().unwrap(), 480, 360, [0.0; 3]);
        let params = AlignParams::default();
        let kf = Frame::new(luminance(&scene), &params);
        let vf = Frame::new(luminance(&view), &params);
        // A prior off by a few pixels.
        let prior = Homography::translation(2.0, -1.5).after(&truth);
        let a = align(&kf, &vf, &params, Some(&prior));
        assert!(a.accepted() && a.from_prior && a.putative == 0, "{a:?}");
        assert!(a.homography.unwrap().mean_corner_error(&truth, 480, 360) < 0.3);
    }
}
