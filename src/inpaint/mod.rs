//! The fill: the keyframe's masked region re-inpainted from what the aligned views saw
//! there (the paper's section 4, steps 3–7), with a single-image fallback for what no view
//! saw (pure layer).
//!
//! [`fill`] is the whole of it; the submodules are its stages. Nothing here reads a file
//! or a clock: stage changes and progress are reported to an [`Observer`] that the edge
//! (CLI progress bar, daemon timings) supplies.

pub mod automask;
pub mod blend;
pub mod exemplar;
pub mod follow;
pub mod fuse;
pub mod multiview;
pub mod occlusion;
pub mod parallax;
pub mod priority;
pub mod reduced;
pub mod region;
pub mod shift;
pub mod swept;

use nalgebra::Point2;
use rayon::prelude::*;

use crate::geometry::Homography;
use crate::imaging::convert::{luma, monochrome};
use crate::imaging::photometric::{Gain, GainParams, ToneCurve, ToneParams, fit_gain, fit_tone};
use crate::imaging::warp::{Interpolation, Rect, Warped, warp};
use crate::imaging::{Mask, Plane, RgbF32, RgbPixel, bilinear_rgb};
use automask::dilate;
use blend::{BlendParams, guidance_rhs, poisson_blend, solve_membrane};
use fuse::{FuseParams, Mix};
use multiview::{MultiviewParams, NO_VIEW, Pick, Region, ViewData, fill_region};
use occlusion::{KeyRegion, OcclusionMap, OcclusionParams, RegionInput, occlusion_map};
use parallax::{ParallaxParams, PlaneInput, SurfacePlane, WarpedView, choose_planes};
use shift::{Shift, ShiftBand, ShiftParams, local_shift};

pub use automask::{
    AutoMask, AutoMaskParams, OwnMarks, OwnParams, auto_mask, auto_mask_report, own_occluders,
    own_occluders_memo, own_occluders_off_surfaces,
};
pub use exemplar::{ExemplarParams, exemplar_fill, exemplar_fill_guided, exemplar_fill_until};
pub use swept::{SurfaceReport, SurfacesReport, Swept, fill_swept, judged_with_marks, sweep_surfaces};

/// Where each pixel of a result came from: [`KEYFRAME`] outside the mask, [`FALLBACK`]
/// for the single-image fallback, otherwise `1 + i` for `sources[i]`.
pub type Provenance = Plane<u16>;
/// A pixel the keyframe itself provides (outside the mask).
pub const KEYFRAME: u16 = 0;
/// A masked pixel no view could fill: the single-image fallback made it.
pub const FALLBACK: u16 = u16::MAX;

/// Per-pixel confidence of a result (see [`Filled::confidence`]): 0 outside the mask,
/// 0..=255 inside, at least [`CONFIDENT`] where the fill is sure the pixel shows the
/// building.
pub type Confidence = Plane<u8>;

/// The confidence from which a filled pixel counts as sure.
pub const CONFIDENT: u8 = 128;

/// The most the fill may trust a pixel copied under a soft mark of its view
/// ([`FillExtras::occluders`]): below [`CONFIDENT`], since the view's own judgement took it
/// for an occluder.
const LIFTED_CONFIDENCE: f32 = 0.45;

/// A soft-marked pixel inside the mask whose 3 × 3 mean is within this of the keyframe's
/// (RGB distance, 0..=√3) is not copied: inside the mask the keyframe shows its occluder,
/// and a view like it there shows the same one. On the rendered walks these were the edges
/// of a crown over the sky, which the frames around had agreed with (BENCHMARKS.md,
/// "Video target, eighteenth session").
const LIFTED_RESEMBLES: f32 = 0.08;
/// A soft mark of at most this level ([`FillExtras::occluders`]) is faint: its view did not
/// judge the pixel an occluder, it only lies near one (the rim a walk's frame is marked
/// with past what was found). [`LIFTED_RESEMBLES`] is not asked of it: inside a generous
/// mask's margin the keyframe shows the wall, and a view like it there shows the wall
/// too. On the rendered walks the rule had dropped the wall every frame saw in the margin,
/// and the fallback invented it (BENCHMARKS.md, "A frame's rim is faint").
pub const FAINT_MARK: u8 = 144;
/// Nor is a soft-marked pixel whose 3 × 3 mean is at least this foreign to the colours of
/// the building around the mask (the keyframe outside the mask near the part,
/// [`LIFTED_FOREIGN_REACH`]; [`occlusion::Histogram::foreign`], 0 common .. 1 never seen):
/// where every view has its own occluder over a spot, the one marked least may show the
/// building, or a van of a colour the facade has nowhere; the van is left to the fallback.
/// On the shared-occluder service cases the third view's van was copied over the
/// keyframe's tree (BENCHMARKS.md, "A mark over a foreign colour stays", fifty-eighth
/// session).
const LIFTED_FOREIGN: f32 = 0.7;
/// The building's colours for [`LIFTED_FOREIGN`] are the keyframe's outside the mask within
/// this many pixels of the part's rectangle (the hole grown by the fill's margin, 11 px):
/// a window wholly inside a large hole has its like further along the facade. The part
/// grown by this much stays inside the service's crop ([`crate::session::SessionParams`]'s
/// 48 px margin), so that the service's fill and `clearview fill` hear the same colours.
const LIFTED_FOREIGN_REACH: usize = 32;
/// The confidence of a pixel the single-image fallback invented.
const INVENTED: f32 = 0.2;
/// The most the fill may trust a pixel the blend moved by more than a gross difference
/// ([`GROSS`]) beyond its part's common correction: below [`CONFIDENT`], since what it
/// shows is no longer what a view saw. The blend's correction is smooth, and nearly
/// constant wherever the copies meet the keyframe (exposure); it moves a pixel that far
/// from the rest only where they disagree across the mask's edge (a mullion the fill cut at
/// the border, spread inwards as a glow). On a six-view facade with surfaces off the wall
/// nine in ten of the pixels this caps were grossly wrong (BENCHMARKS.md, "What the
/// confidence does not see through the surfaces").
const MOVED_CONFIDENCE: f32 = 0.45;
/// The most the fill may trust a pixel copied from a view that contradicts the keyframe on
/// the ring nearest to it ([`contradicted_by_ring`]): below [`CONFIDENT`]. With one view of
/// a six-view facade missing, the walls' fill called the bricks behind a masked pipe sure
/// (confident error rate 41.7 %, 25.4 % with this); over 16 facades with slabs the pixels it
/// doubts are wrong 15–43 times in a hundred, three to eight times the rate among the sure
/// (BENCHMARKS.md, "What the confidence does not see through the surfaces").
const CONTRADICTED_CONFIDENCE: f32 = 0.45;

/// One aligned view, as the fill sees it. Its pixels are [`RgbF32`] by default, or 8-bit
/// ([`crate::imaging::Rgb8`], a quarter of the memory; the result is the same as with their
/// `f32` copy).
#[derive(Debug, Clone, Copy)]
pub struct Source<'a, P: RgbPixel = [f32; 3]> {
    /// The view's pixels (RGB, 0..=1 once read as `f32`).
    pub image: &'a Plane<P>,
    /// Maps keyframe pixel coordinates to this view's (ARCHITECTURE.md convention).
    pub homography: Homography,
}

/// The stages of [`fill`], in the order they run (for timings and progress).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stage {
    /// The surfaces off the wall swept from the views ([`swept::sweep_surfaces`]).
    Sweep,
    /// The fill through the surfaces judged against the walls' ([`swept::fill_swept`]: the
    /// walls' fill and two judging fills).
    Judge,
    /// Each view's own occluders, judged against the keyframe and the other views
    /// ([`FillParams::own`]).
    Own,
    Warp,
    Photometric,
    Planes,
    Occlusion,
    Fill,
    Fallback,
    Blend,
    /// Views chosen by trial fills (each a fill, fallback and blend of its own).
    Select,
    /// The chosen views averaged into the copies ([`FillParams::fuse`]).
    Fuse,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Self::Sweep => "plane sweep",
            Self::Judge => "judge planes",
            Self::Own => "own occluders",
            Self::Warp => "warp",
            Self::Photometric => "photometric",
            Self::Planes => "planes",
            Self::Occlusion => "occlusion",
            Self::Fill => "fill",
            Self::Fallback => "fallback",
            Self::Blend => "blend",
            Self::Select => "select",
            Self::Fuse => "fuse",
        }
    }
}

/// Told what [`fill`] is doing; the edge times stages and draws progress with it.
pub trait Observer {
    /// A stage begins (the previous one, if any, has ended).
    fn stage(&mut self, _stage: Stage) {}
    /// `done` of `total` units of the current stage are finished.
    fn progress(&mut self, _done: usize, _total: usize) {}
    /// Whether the work is no longer wanted (the service is stopping). The fill asks
    /// between stages and inside its long loops and, when told so, returns at once with an
    /// unfinished image, which the caller (that said so) throws away.
    fn cancelled(&self) -> bool {
        false
    }
}

/// An observer that ignores everything.
impl Observer for () {}

/// How much less than the current result (a share of the mask, [`FillReport::witnessed_quality`])
/// a fill with a new view may be judged and still win. The judge cannot see the blur and
/// sub-pixel placement that separate two good fills, and the new fill has the evidence as it
/// now is: on a near tie it wins, so that where views arrive one by one or in batches a
/// session ends with the result `clearview fill` makes of them.
pub const KEEP_MARGIN: f64 = 0.005;

/// Per-source figures of a result.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SourceReport {
    /// Masked pixels this view sees (lands inside it).
    pub covered: usize,
    /// Masked pixels the result took from this view.
    pub filled: usize,
    /// Photometric compensation applied: `key ≈ gain · view + offset`, per channel.
    pub gain: [f32; 3],
    pub offset: [f32; 3],
    /// Whether a tone curve ([`FillParams::tone`]) was applied before the gain.
    pub tone: bool,
    /// Whether the result was made from this source; one the choice kept out is still a
    /// witness ([`FillParams::select_views`]).
    pub joined: bool,
    /// The most the local shift ([`FillParams::local_shift`], refined) moved a point of a
    /// hole's part of this source, in keyframe pixels (0: none).
    pub shift_px: f64,
}

/// What a result is made of. The default is an empty mask's: nothing to fill, and what
/// there is backed everywhere.
#[derive(Debug, Clone, PartialEq)]
pub struct FillReport {
    /// Pixels the mask asked to fill.
    pub masked: usize,
    /// One entry per source, in the order given.
    pub sources: Vec<SourceReport>,
    /// Masked pixels the single-image fallback filled.
    pub fallback: usize,
    /// Masked pixels whose confidence is at least [`CONFIDENT`].
    pub confident: usize,
    /// Sum of the masked pixels' confidences (0..=1 each): with `masked`, the result's
    /// expected share of pixels that show the building.
    pub confidence_sum: f64,
    /// Mean over the mask of how well the result's pixels agree with what the views show
    /// there ([`witnessed_by`]): the measure on which two results of the same keyframe and
    /// mask are compared with the same views as witnesses (1 for an empty mask).
    pub witnessed_quality: f64,
    /// Masked pixels whose copy took in other views' colours ([`FillParams::fuse`]).
    pub fused: usize,
}

impl Default for FillReport {
    fn default() -> Self {
        Self {
            masked: 0,
            sources: Vec::new(),
            fallback: 0,
            confident: 0,
            confidence_sum: 0.0,
            witnessed_quality: 1.0,
            fused: 0,
        }
    }
}

impl FillReport {
    /// Share of the mask filled from real views (0..=1; 1 for an empty mask).
    pub fn from_views(&self) -> f64 {
        if self.masked == 0 {
            return 1.0;
        }
        self.sources.iter().map(|s| s.filled).sum::<usize>() as f64 / self.masked as f64
    }

    /// Share of the mask the fill is sure of (confidence at least [`CONFIDENT`]; 1 for an
    /// empty mask).
    pub fn confident_share(&self) -> f64 {
        if self.masked == 0 { 1.0 } else { self.confident as f64 / self.masked as f64 }
    }

    /// Share of the mask that was invented (fallback) or filled from views without
    /// confidence: what a person should look at.
    pub fn doubtful_share(&self) -> f64 {
        1.0 - self.confident_share()
    }

    /// Mean confidence over the mask (1 for an empty mask): the result's expected quality,
    /// what a new result must beat to be published.
    pub fn expected_quality(&self) -> f64 {
        if self.masked == 0 { 1.0 } else { self.confidence_sum / self.masked as f64 }
    }
}

/// Parameters of [`fill`]. The switches (`occlusion`, `photometric`, `blend`) exist so that
/// each piece can be shown to matter; all are on by default.
#[derive(Debug, Clone, PartialEq)]
pub struct FillParams {
    /// Patches are `(2·r + 1)²` pixels (the paper's window; 4 gives 9×9).
    pub patch_radius: usize,
    /// Each front step copies the chosen view's pixels within this radius (see
    /// [`multiview::MultiviewParams::copy_radius`]); larger is faster.
    pub copy_radius: usize,
    /// Candidate patches are searched up to this many pixels around the homography's
    /// prediction (misregistration, parallax); 0 trusts the homography exactly.
    pub search_radius: usize,
    /// Occlusion reasoning ([`occlusion`]): a candidate the model thinks shows an occluder
    /// is penalised by `occlusion_weight`, and a pixel it is fairly sure of is not copied at
    /// all. Off, every view is taken at its word (and the confidence believes it too).
    pub occlusion: bool,
    /// Cost of a candidate per unit of occlusion probability, in the SSD's units (squared
    /// RGB per pixel, see [`multiview::MultiviewParams::occlusion_weight`]).
    pub occlusion_weight: f32,
    /// The model of who sees what.
    pub occlusion_model: OcclusionParams,
    /// Per-view gain and offset fitted on a ring of keyframe pixels around the hole.
    pub photometric: bool,
    /// The ring starts this many pixels away from the hole (skips the occluder's halo)...
    pub ring_gap: usize,
    /// ...and is this many pixels wide.
    pub ring_width: usize,
    /// The robust gain fit.
    pub gain: GainParams,
    /// Before the ring's gain, a monotone tone curve per view fitted on the whole overlap
    /// of the view and the keyframe (outside the mask, where neither has a strong edge),
    /// applied only where it explains that overlap clearly better than a line
    /// ([`ToneParams`]); the ring's gain then corrects the local level on top of it.
    pub tone: bool,
    pub tone_params: ToneParams,
    /// Gradient-domain (Poisson) blending of the filled region into the keyframe.
    pub blend: bool,
    pub blend_params: BlendParams,
    /// How views are sampled between pixel centres.
    pub interpolation: Interpolation,
    /// Weight of a view's expected error ([`view_errors`]) in the choice between views
    /// (0: every view is as good as its patch's SSD says).
    pub view_error_weight: f32,
    /// The single-image fallback for pixels no view saw.
    pub exemplar: ExemplarParams,
    /// The fallback sees this many pixels of context around what it fills (plus half the
    /// unseen area's extent).
    pub fallback_margin: usize,
    /// The fallback's guide (the membrane of its region's border, `fallback_guide`)
    /// interpolates from the keyframe, from what the fallback made already and from the
    /// view pixels the fill gives at least this confidence (with edges counted as
    /// [`occlusion::GUIDE_EDGE_SHARE`] says); `None`: from no view pixel.
    /// The views' pixels next to what no view saw clear are the ones most likely to show
    /// a piece of an occluder; with few views they are mostly right, so the default keeps
    /// the fairly sure ones (half of [`CONFIDENT`]). A video walk takes only those it is
    /// sure of: beside a walk's unseen sky the fairly sure ones were the rim of a crown
    /// every frame showed, wrong one time in two, and the guide they gave grew glass into
    /// that sky (BENCHMARKS.md, "A walk's fallback: guided by what the fill is sure of").
    pub fallback_guide_from: Option<u8>,
    /// Which surface each pixel shows, where [`FillExtras::planes`] gives surfaces off the
    /// wall: given for a 640 × 480 keyframe, and scaled to the keyframe's size
    /// ([`ParallaxParams::at_diagonal`]).
    pub parallax: ParallaxParams,
    /// Views join the fill one by one, in the order given, each only when the fill with it
    /// agrees with what all the views show ([`FillReport::witnessed_quality`]) at least as
    /// well as the fill without it, less `select_margin`. Off, every view is used.
    pub select_views: bool,
    /// How much of the judge's agreement (a share of the mask) a view may cost and still
    /// join ([`KEEP_MARGIN`]; the service's publish rule uses the same), below which the judge does
    /// not tell two good fills apart (at 0.001 a view worth 3.7 dB was kept out).
    pub select_margin: f64,
    /// The choice costs one trial fill per view after the first; it is made only while
    /// masked pixels × those views stay within this budget (beyond it every view is used):
    /// a 12 MP photograph with 15 % masked and 6 views (9 M) took 2.8× as long and 1.65 GB.
    pub select_budget: usize,
    /// The fill through the surfaces off the wall is judged against the walls' alone
    /// ([`swept::fill_swept`]) on the inputs halved until the keyframe has at most this many
    /// pixels (then only the fill chosen is made at full resolution): the judge needs
    /// shares of the mask, and four fills of a 12 MP keyframe cost seconds. At 600 000 a larger
    /// keyframe is judged at 150 000–600 000 pixels, about the size of the evaluations'
    /// (640 × 480, judged as they are); a 12 MP one at 500 × 375, where at 1.3 MP it was
    /// judged at 1000 × 750 for 2.5 s more and no better (BENCHMARKS.md, "The judge at a
    /// third of a megapixel").
    pub judge_max_pixels: usize,
    /// Around each hole, each view moved by the shift, then the small homography, that best
    /// brings it onto the keyframe's own pixels there, when that makes them clearly more
    /// alike ([`shift::local_shift`]): one homography cannot hold a curved or stepped facade.
    pub local_shift: Option<ShiftParams>,
    /// After the views are chosen, each pixel copied from a view takes in the other views'
    /// colours there as far as the ring around its hole shows that their errors are
    /// independent ([`fuse`]): noise, reflections and a curved facade's small
    /// misregistrations average out. The views are chosen on the copies (the judge would
    /// otherwise favour any view an average agrees with). `None`: copies only.
    pub fuse: Option<FuseParams>,
    /// Each view's own occluders found before the fill ([`own_occluders`]) and never
    /// copied with certainty, when the caller gives none of its own
    /// ([`FillExtras::occluders`]). `None`: views are judged only by the occlusion model.
    pub own: Option<OwnParams>,
}

impl Default for FillParams {
    fn default() -> Self {
        Self {
            patch_radius: 4,
            copy_radius: 8,
            search_radius: 2,
            occlusion: true,
            occlusion_weight: 0.1,
            occlusion_model: OcclusionParams::default(),
            photometric: true,
            ring_gap: 2,
            ring_width: 6,
            gain: GainParams::default(),
            tone: true,
            tone_params: ToneParams::default(),
            blend: true,
            blend_params: BlendParams::default(),
            interpolation: Interpolation::Bilinear,
            view_error_weight: 30.0,
            exemplar: ExemplarParams::default(),
            fallback_margin: 32,
            fallback_guide_from: Some(CONFIDENT / 2),
            parallax: ParallaxParams::default(),
            select_views: true,
            select_margin: KEEP_MARGIN,
            select_budget: 4_000_000,
            judge_max_pixels: 600_000,
            local_shift: Some(ShiftParams::default()),
            fuse: Some(FuseParams::default()),
            own: Some(OwnParams::default()),
        }
    }
}

impl FillParams {
    fn multiview(&self) -> MultiviewParams {
        MultiviewParams {
            patch_radius: self.patch_radius,
            copy_radius: self.copy_radius,
            search_radius: self.search_radius,
            occlusion_weight: if self.occlusion { self.occlusion_weight } else { 0.0 },
            ..MultiviewParams::default()
        }
    }

    /// How far around the hole the views are needed.
    fn margin(&self) -> usize {
        (self.patch_radius.max(self.copy_radius) + self.search_radius + 1)
            .max(self.ring_gap + self.ring_width)
    }
}

/// What [`fill_with`] knows besides the views' wall homographies.
#[derive(Debug, Clone, Copy, Default)]
pub struct FillExtras<'a> {
    /// Surfaces off the wall (balconies, pilasters, signs): each masked pixel takes the
    /// plane, the wall included, under which the views agree ([`parallax`]).
    pub planes: &'a [SurfacePlane],
    /// Per source (or empty): view-sized masks of pixels known to show something other
    /// than the building (an occluder found by other means); they are never copied. A
    /// soft mark (128..255, exclusive) is a doubt, not a verdict: such a pixel may be
    /// copied where every source that sees it is marked there, and is then never
    /// reported sure ([`LIFTED_CONFIDENCE`], [`LIFTED_RESEMBLES`], [`LIFTED_FOREIGN`]); a
    /// faint one ([`FAINT_MARK`] or below) says only that an occluder is near.
    pub occluders: &'a [Option<&'a Mask>],
    /// Another result of the same keyframe and mask (keyframe-sized), to be judged on the
    /// same evidence as this fill ([`Filled::rival_quality`]).
    pub rival: Option<&'a RgbF32>,
    /// Per source (or empty: every source is a candidate), with
    /// [`FillParams::select_views`]: `Some(true)` a source already in the result, `None` a
    /// candidate, tried in the order given, `Some(false)` a source kept out (a witness
    /// only: the model and the judge still hear it). Without the choice, every source but
    /// those kept out makes the fill.
    pub choice: &'a [Option<bool>],
    /// The whole keyframe's size when `key` is a part of it (the service fills the mask's
    /// neighbourhood only): what scales with the keyframe (parallax, misregistration) is
    /// measured on the whole, so that the part is filled as the whole would be.
    pub whole: Option<(usize, usize)>,
    /// Each view's own occluders as [`own_occluders`] finds them for this keyframe, mask
    /// and these sources, found already ([`own_occluders_memo`]: a session keeps them from
    /// one fill to the next): used where [`FillParams::own`] would find them.
    pub own: Option<&'a [Option<&'a Mask>]>,
    /// `rival` was filled through surfaces off the wall ([`fill_swept`]): the surfaces then
    /// stay unless the walls' fill is clearly better, so that a near tie does not flip a
    /// session's result between the two from one view to the next.
    pub rival_swept: bool,
    /// The views' own occluders ([`FillExtras::own`], else as [`FillParams::own`] finds
    /// them) are marked through `planes` too, less what the surfaces explain
    /// ([`own_occluders_off_surfaces`]). For a judgement ([`judged_with_marks`]), not for a
    /// fill: the marks left on the slabs still take pixels the surfaces fill from (a fill
    /// through the surfaces with them: 18.55 → 17.15 dB on the 40 depth facades;
    /// BENCHMARKS.md, eighty-sixth session).
    pub marks_through_planes: bool,
}

/// A filled keyframe: the image, where each pixel came from, how sure the fill is of it,
/// and the figures.
#[derive(Debug, Clone)]
pub struct Filled {
    pub image: RgbF32,
    pub provenance: Provenance,
    /// Keyframe-sized: the surface each pixel was filled through (0 the wall, `1 + p` for
    /// [`FillExtras::planes`]`[p]`; 0 outside the mask).
    pub surface: Plane<u16>,
    /// Keyframe-sized: 0 outside the mask; inside, how sure the fill is that the pixel
    /// shows the building (255 · probability; see [`CONFIDENT`]).
    pub confidence: Confidence,
    /// As `confidence`, but with a sharp edge counted as the fill decides with it
    /// ([`occlusion::GUIDE_EDGE_SHARE`] of its step, not [`occlusion::EDGE_SHARE`]): the
    /// doubt that another view could settle. An edge a fraction of a pixel off stays
    /// doubtful in the reported map however many views agree, so a rule that asks whether
    /// a new view can help (the session's improvement rule) reads this one.
    pub deciding: Confidence,
    pub report: FillReport,
    /// How well [`FillExtras::rival`] agrees with these views, as
    /// [`FillReport::witnessed_quality`] says of this fill.
    pub rival_quality: Option<f64>,
    /// The pixels of `image` the fusion changed ([`FillParams::fuse`]), with the colours
    /// the fill was judged on (index into `image`, row-major). A later fill's rival is the
    /// judged image ([`Filled::judged_image`]), so that copies are compared with copies.
    pub unfused: Vec<(usize, [f32; 3])>,
}

impl Filled {
    /// `image` as the judge saw it: before the fusion.
    pub fn judged_image(&self) -> RgbF32 {
        let mut out = self.image.clone();
        let px = out.as_mut_slice();
        for &(i, c) in &self.unfused {
            px[i] = c;
        }
        out
    }
}

/// Fills the pixels of `key` that `mask` marks from `sources`, then what they could not
/// see by the single-image fallback. An empty mask returns `key` unchanged.
///
/// The hole is cut into regions (connected parts, with the margin the patches need); each
/// view is warped only over those, compensated, and the regions are filled independently
/// (in parallel), then blended. With several views, each joins the fill only when the fill
/// with it agrees with what the views show no worse ([`FillParams::select_views`]).
///
/// # Panics
/// If `mask` is not the size of `key` (the edge checks and reports that).
pub fn fill<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    params: &FillParams,
    seed: u64,
    observer: &mut dyn Observer,
) -> Filled {
    fill_with(key, mask, sources, &FillExtras::default(), params, seed, observer)
}

/// [`fill`] with surfaces off the wall and known occluders (see [`FillExtras`]).
///
/// # Panics
/// As [`fill`]; and if `extras` does not give one entry per source.
pub fn fill_with<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    seed: u64,
    observer: &mut dyn Observer,
) -> Filled {
    fill_gathered(key, mask, sources, extras, params, seed, observer).0
}

/// Panics unless `extras` gives one entry per source and `mask` is the keyframe's size.
fn check_inputs<P: RgbPixel>(key: &RgbF32, mask: &Mask, sources: &[Source<'_, P>], extras: &FillExtras<'_>) {
    assert!(extras.occluders.is_empty() || extras.occluders.len() == sources.len(), "occluders per source");
    assert!(extras.own.is_none_or(|o| o.is_empty() || o.len() == sources.len()), "own occluders per source");
    assert!(extras.planes.iter().all(|p| p.views.len() == sources.len()), "plane homographies per source");
    assert_eq!((mask.width(), mask.height()), (key.width(), key.height()), "mask size");
}

/// [`fill_with`], and the evidence the fill was made from, to judge other results of the
/// same inputs on ([`Gathered::judge`]); `None` where no fill was made (an empty mask, a
/// cancelled fill).
fn fill_gathered<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    seed: u64,
    observer: &mut dyn Observer,
) -> (Filled, Option<Gathered>) {
    let (w, h) = (key.width(), key.height());
    check_inputs(key, mask, sources, extras);
    let nv = sources.len();
    let masked = mask.hole_count();
    let mut report = FillReport {
        masked,
        sources: vec![SourceReport { gain: [1.0; 3], ..SourceReport::default() }; nv],
        ..FillReport::default()
    };
    // What is returned before the fill is made (an empty mask, or a cancelled fill): the
    // keyframe as it is.
    let unfinished = |surface, report| Filled {
        image: key.clone(),
        provenance: Provenance::new(w, h, KEYFRAME),
        surface,
        confidence: Confidence::new(w, h, 0),
        deciding: Confidence::new(w, h, 0),
        report,
        rival_quality: None,
        unfused: Vec::new(),
    };
    let mut surface = Plane::new(w, h, 0u16);
    if masked == 0 {
        return (unfinished(surface, report), None);
    }
    let Some(evidence) =
        Gathered::gather(key, mask, sources, extras, params, observer, &mut report, &mut surface)
    else {
        return (unfinished(surface, report), None);
    };
    let Gathered { parts, warps, lifted, maps, errors, edge_shares, reach, diagonal } = &evidence;
    let diagonal = *diagonal;
    let judge = |img: &RgbF32| evidence.judge(key, mask, img);
    let stage =
        Staged { key, mask, parts, warps, lifted, maps, errors, edge_shares, reach, diagonal, params, seed };
    if observer.cancelled() {
        return (unfinished(surface, report), None);
    }
    // Which sources may make the fill: those already in it, then the candidates (in the
    // order given); a source kept out is a witness only.
    let choice = |v: usize| extras.choice.get(v).copied().flatten();
    let fixed: Vec<usize> = (0..nv).filter(|&v| choice(v) == Some(true)).collect();
    let candidates: Vec<usize> =
        (0..nv).filter(|&v| extras.choice.get(v).is_none_or(Option::is_none)).collect();
    let rival_quality = extras.rival.filter(|r| (r.width(), r.height()) == (w, h)).map(judge);
    // The bar a candidate must clear: the current result's, else the fill of the sources
    // already in it, else none (the first candidate joins).
    let base_trial = rival_quality.is_none() && !fixed.is_empty();
    let trials = candidates.len() + usize::from(base_trial);
    let choose = params.select_views
        && !candidates.is_empty()
        && (trials >= 2 || rival_quality.is_some())
        && masked * trials <= params.select_budget;
    let (made, quality) = if choose {
        // Candidates join one by one, each only when the fill it makes with the sources in
        // so far agrees with the evidence at least as well as the best result so far
        // (the current one included), less the margin. Each trial is blended before it is
        // judged: unblended, a view's exposure residue along the seams crossed the judge's
        // gross difference and kept a good view out (hpatches-wormhole-3: 1.7 dB lost).
        observer.stage(Stage::Select);
        let trial = |views: &[usize], observer: &dyn Observer| {
            let made = stage.compose(views, &mut Quiet(observer));
            stage.blend(made, &mut Quiet(observer))
        };
        let mut kept = fixed.clone();
        let mut best: Option<(Made, f64)> = None;
        let mut bar = rival_quality;
        if base_trial {
            let made = trial(&kept, &*observer);
            let q = judge(&made.image);
            bar = Some(q);
            best = Some((made, q));
        }
        // With nothing joining, the best of the refused trials is returned: judged below
        // the current result, it is not published.
        let mut refused: Option<(Made, f64)> = None;
        for (k, &v) in candidates.iter().enumerate() {
            if observer.cancelled() {
                break;
            }
            let mut tried = kept.clone();
            tried.push(v);
            tried.sort_unstable();
            let made = trial(&tried, &*observer);
            let q = judge(&made.image);
            if bar.is_none_or(|b| q >= b - params.select_margin) {
                kept = tried;
                bar = Some(bar.map_or(q, |b| b.max(q)));
                best = Some((made, q));
            } else if refused.as_ref().is_none_or(|(_, r)| q > *r) {
                refused = Some((made, q));
            }
            observer.progress(k + 1, candidates.len());
        }
        match best.or(refused) {
            Some(b) => b,
            None => return (unfinished(surface, report), None),
        }
    } else {
        let mut views = fixed.clone();
        views.extend(&candidates);
        views.sort_unstable();
        let made = stage.compose(&views, observer);
        let made = stage.blend(made, observer);
        let q = if observer.cancelled() { 0.0 } else { judge(&made.image) };
        (made, q)
    };
    if observer.cancelled() {
        return (unfinished(surface, report), None);
    }
    // The views were chosen on their copies; the chosen fill now averages them where the
    // rings say their errors are independent.
    let mut made = made;
    let unfused = match &params.fuse {
        Some(f) if made.views.len() >= 2 => {
            observer.stage(Stage::Fuse);
            stage.fuse(&mut made, f, &*observer)
        }
        _ => Vec::new(),
    };
    if observer.cancelled() {
        return (unfinished(surface, report), None);
    }
    report.fused = unfused.len();
    for (s, &f) in report.sources.iter_mut().zip(&made.filled) {
        s.filled = f;
    }
    for &v in &made.views {
        report.sources[v].joined = true;
    }
    report.fallback = made.fallback;
    for (&m, &c) in mask.as_slice().iter().zip(made.confidence.as_slice()) {
        if m > 127 {
            report.confident += usize::from(c >= CONFIDENT);
            report.confidence_sum += f64::from(c) / 255.0;
        }
    }
    report.witnessed_quality = quality;
    // A black-and-white keyframe stays black and white: the views' colour (each channel
    // brought to the keyframe's grey by its own gain) is taken out of what they filled.
    let (mut image, mut unfused) = (made.image, unfused);
    if monochrome(key) {
        let grey = |c: &mut [f32; 3]| *c = [luma(*c); 3];
        for (p, &m) in image.as_mut_slice().iter_mut().zip(mask.as_slice()) {
            if m > 127 {
                grey(p);
            }
        }
        unfused.iter_mut().for_each(|(_, c)| grey(c));
    }
    let filled = Filled {
        image,
        provenance: made.provenance,
        surface,
        confidence: made.confidence,
        deciding: made.guiding,
        report,
        rival_quality,
        unfused,
    };
    (filled, Some(evidence))
}

/// What a fill is made from and judged on: every view warped over the mask's parts (and
/// through the surfaces off the wall, composed where they show), compensated, and the
/// occlusion model fitted on all of them. [`fill_with`] makes its fill from it;
/// [`backed_by`] only judges results with it.
struct Gathered {
    parts: Vec<Part>,
    /// Per part, per source.
    warps: Vec<Vec<Warped>>,
    /// Per part, per source: where the source's pixel is there only under a soft mark.
    lifted: Vec<Vec<Option<Plane<bool>>>>,
    /// Per part, the occlusion model fitted on every source.
    maps: Vec<OcclusionMap>,
    /// Per part, per source ([`view_errors`]).
    errors: Vec<Vec<f32>>,
    /// Per part, per source ([`view_edge_shares`]).
    edge_shares: Vec<Vec<f32>>,
    /// Per part, per source ([`view_reach`]).
    reach: Vec<Vec<usize>>,
    /// The whole keyframe's diagonal ([`FillExtras::whole`]).
    diagonal: f32,
}

impl Gathered {
    /// The evidence of `sources` for a fill of `key`'s `mask`, as [`fill_with`] gathers it
    /// (each source's coverage and compensation written into `report`, the surface each
    /// masked pixel shows into `surface`); `None` for an empty mask or when `observer` is
    /// cancelled.
    #[allow(clippy::too_many_arguments)]
    fn gather<P: RgbPixel>(
        key: &RgbF32,
        mask: &Mask,
        sources: &[Source<'_, P>],
        extras: &FillExtras<'_>,
        params: &FillParams,
        observer: &mut dyn Observer,
        report: &mut FillReport,
        surface: &mut Plane<u16>,
    ) -> Option<Self> {
        let (w, h) = (key.width(), key.height());
        let nv = sources.len();
        if mask.hole_count() == 0 {
            return None;
        }
        let parts = regions(mask, params.margin(), params.ring_gap, params.ring_width);
        // Each view's own occluders, where the caller found none by other means. Not with
        // surfaces off the wall: a slab seen through the wall's homography disagrees like an
        // occluder, and its marks took the pixels the surfaces fill from (the swept fill and
        // its judgement were measured without them); unless a judgement asks for them
        // ([`FillExtras::marks_through_planes`]), and then less what the surfaces explain.
        let found: Vec<Option<Mask>>;
        let off: Vec<Option<Mask>>;
        let own: Vec<Option<&Mask>> = match (&params.own, extras.own) {
            (Some(p), given)
                if extras.occluders.is_empty()
                    && (extras.planes.is_empty() || extras.marks_through_planes)
                    && sources.len() >= p.min_views =>
            {
                let through_walls: Vec<Option<&Mask>> = match given {
                    Some(given) => given.to_vec(),
                    None => {
                        observer.stage(Stage::Own);
                        found = own_occluders(key, mask, sources, p, &AutoMaskParams::default());
                        found.iter().map(Option::as_ref).collect()
                    }
                };
                if extras.planes.is_empty() || through_walls.is_empty() {
                    through_walls
                } else {
                    // Found through the walls, a slab is marked as an occluder: judged
                    // again through the surfaces, what one explains is not.
                    observer.stage(Stage::Own);
                    off = own_occluders_off_surfaces(
                        key,
                        mask,
                        sources,
                        &through_walls,
                        extras.planes,
                        p,
                        &AutoMaskParams::default(),
                    );
                    off.iter().map(Option::as_ref).collect()
                }
            }
            _ => Vec::new(),
        };
        if observer.cancelled() {
            return None;
        }
        let occluders: &[Option<&Mask>] = if own.is_empty() { extras.occluders } else { &own };

        // Warp: every view over every region's needed pixels.
        observer.stage(Stage::Warp);
        let mut warps: Vec<Vec<Warped>> = Vec::with_capacity(parts.len());
        // Per part, per plane off the wall, per source (empty where the plane is not near).
        let mut plane_warps: Vec<Vec<Vec<Option<Warped>>>> = Vec::with_capacity(parts.len());
        // Per part, per source: the pixels copied only under a soft mark ([`exclude_marked`]).
        let mut lifted: Vec<Vec<Option<Plane<bool>>>> = Vec::with_capacity(parts.len());
        let mut reach: Vec<Vec<usize>> = Vec::with_capacity(parts.len());
        for (k, part) in parts.iter().enumerate() {
            // Each view's homography here: its own, or moved onto the keyframe around this hole.
            let shifts: Vec<Option<Shift>> = match &params.local_shift {
                Some(p) => {
                    let band = ShiftBand::new(key, mask, &part.hole, part.rect, p);
                    sources
                        .par_iter()
                        .enumerate()
                        .map(|(v, s)| local_shift(&band, s, occluders.get(v).copied().flatten(), p))
                        .collect()
                }
                None => vec![None; nv],
            };
            let hs: Vec<Homography> = sources
                .iter()
                .zip(&shifts)
                .zip(&mut report.sources)
                .map(|((s, shift), r)| match shift {
                    Some(sh) => {
                        r.shift_px = r.shift_px.max(sh.moved_px);
                        sh.apply(&s.homography)
                    }
                    None => s.homography,
                })
                .collect();
            reach.push(hs.iter().map(|hv| view_reach(hv, part.rect)).collect());
            let mut ws: Vec<Warped> = sources
                .par_iter()
                .zip(&hs)
                .map(|(s, hv)| warp(s.image, hv, part.rect, Some(&part.need), params.interpolation))
                .collect();
            let levels: Vec<Option<Plane<u8>>> = ws
                .par_iter()
                .zip(hs.par_iter())
                .enumerate()
                .map(|(v, (wv, hv))| mark_levels(wv, hv, occluders.get(v).copied().flatten()))
                .collect();
            lifted.push(exclude_marked(&mut ws, &levels, key, mask));
            for (v, wv) in ws.iter().enumerate() {
                report.sources[v].covered += part
                    .hole
                    .as_slice()
                    .iter()
                    .zip(wv.valid.as_slice())
                    .filter(|&(&hh, &ok)| hh && ok)
                    .count();
            }
            warps.push(ws);
            // The same views through each surface off the wall that may show in this part.
            plane_warps.push(
                extras
                    .planes
                    .iter()
                    .map(|pl| {
                        if !overlap(pl.region, part.rect) {
                            return Vec::new();
                        }
                        sources
                            .par_iter()
                            .zip(&pl.views)
                            .enumerate()
                            .map(|(v, (s, hp))| {
                                hp.map(|hp| {
                                    let mut wv =
                                        warp(s.image, &hp, part.rect, Some(&part.need), params.interpolation);
                                    exclude(&mut wv, &hp, occluders.get(v).copied().flatten());
                                    wv
                                })
                            })
                            .collect()
                    })
                    .collect(),
            );
            observer.progress(k + 1, parts.len());
        }

        // Photometric: one gain per view from the rings around all regions.
        if observer.cancelled() {
            return None;
        }
        observer.stage(Stage::Photometric);
        if params.photometric {
            // Per view (each on its own, in parallel): the tone curve from the whole overlap,
            // then the gain from the rings around the regions as the curve leaves them.
            let fits: Vec<(Option<ToneCurve>, Gain)> = (0..nv)
                .into_par_iter()
                .map(|v| {
                    let tone = if params.tone {
                        let occluders = occluders.get(v).copied().flatten();
                        let overlap = overlap_pairs(key, mask, &sources[v], occluders);
                        fit_tone(&overlap, &params.tone_params).curve
                    } else {
                        None
                    };
                    let mut pairs = Vec::new();
                    for (part, ws) in parts.iter().zip(&warps) {
                        let rw = part.rect.width;
                        for (i, &ring) in part.ring.as_slice().iter().enumerate() {
                            if ring && ws[v].valid.as_slice()[i] {
                                let (x, y) = (part.rect.x + i % rw, part.rect.y + i / rw);
                                let p = ws[v].image.as_slice()[i];
                                pairs.push((tone.as_ref().map_or(p, |c| c.apply(p)), key.get(x, y)));
                            }
                        }
                    }
                    let step = (pairs.len() / GAIN_SAMPLES).max(1);
                    let sample: Vec<_> = pairs.into_iter().step_by(step).collect();
                    (tone, fit_gain(&sample, &params.gain))
                })
                .collect();
            for (v, (tone, gain)) in fits.into_iter().enumerate() {
                report.sources[v].tone = tone.is_some();
                report.sources[v].gain = gain.gain;
                report.sources[v].offset = gain.offset;
                match tone {
                    Some(curve) => map_view(&mut warps, &mut plane_warps, v, |p| gain.apply(curve.apply(p))),
                    None => map_view(&mut warps, &mut plane_warps, v, |p| gain.apply(p)),
                }
                observer.progress(v + 1, nv);
            }
        }

        // Planes: which surface each pixel shows; each view's warp composed accordingly.
        if observer.cancelled() {
            return None;
        }
        let (ww, wh) = extras.whole.unwrap_or((w, h));
        let diagonal = (ww as f32).hypot(wh as f32);
        if !extras.planes.is_empty() {
            observer.stage(Stage::Planes);
            let choice = params.parallax.at_diagonal(diagonal);
            let labels: Vec<Vec<u16>> = parts
                .par_iter()
                .zip(warps.par_iter_mut())
                .zip(plane_warps.par_iter())
                .map(|((part, ws), pw)| compose_planes(key, part, ws, pw, extras.planes, &choice))
                .collect();
            for (part, l) in parts.iter().zip(&labels) {
                let rw = part.rect.width;
                for (i, &hh) in part.hole.as_slice().iter().enumerate() {
                    if hh {
                        surface.set(part.rect.x + i % rw, part.rect.y + i / rw, l[i]);
                    }
                }
            }
        }
        drop(plane_warps);

        // Occlusion: who sees what, per region, view and pixel, with every view as evidence.
        if observer.cancelled() {
            return None;
        }
        observer.stage(Stage::Occlusion);
        let all: Vec<usize> = (0..nv).collect();
        let maps: Vec<OcclusionMap> = parts
            .par_iter()
            .zip(warps.par_iter())
            .map(|(part, ws)| region_model(key, part, &pick_views(ws, &all), diagonal, params))
            .collect();

        let errors: Vec<Vec<f32>> =
            parts.par_iter().zip(warps.par_iter()).map(|(part, ws)| view_errors(key, part, ws)).collect();
        let edge_shares: Vec<Vec<f32>> = parts
            .par_iter()
            .zip(warps.par_iter())
            .zip(maps.par_iter())
            .zip(reach.par_iter())
            .map(|(((part, ws), map), reach)| view_edge_shares(key, part, ws, map, reach))
            .collect();
        Some(Gathered { parts, warps, lifted, maps, errors, edge_shares, reach, diagonal })
    }

    /// A result against what every view shows, each view a witness as far as the model
    /// (fitted on all of them) trusts it: the share of the mask they back
    /// ([`FillReport::witnessed_quality`]).
    fn judge(&self, key: &RgbF32, mask: &Mask, img: &RgbF32) -> f64 {
        self.judge_by(key, mask, img, &|_, _| 0, 1)[0]
    }

    /// [`Self::judge`] apart for each of `bins` classes of masked pixel (`bin(x, y)` says
    /// which): each class's share of the mask the views back, the classes adding up to it.
    fn judge_by(
        &self,
        key: &RgbF32,
        mask: &Mask,
        img: &RgbF32,
        bin: &(dyn Fn(usize, usize) -> usize + Sync),
        bins: usize,
    ) -> Vec<f64> {
        debug_assert_eq!((img.width(), img.height()), (key.width(), key.height()));
        // Each part in parallel, added in order: a parallel sum's order follows the work
        // stealing, and a judge must give the same figure for the same result every time.
        let parts: Vec<Vec<f64>> = self
            .parts
            .par_iter()
            .zip(self.warps.par_iter())
            .zip(self.maps.par_iter())
            .zip(self.errors.par_iter())
            .map(|(((part, ws), map), errs)| witnessed_by(img, part, ws, map, errs, bin, bins))
            .collect();
        let masked = mask.hole_count() as f64;
        (0..bins).map(|k| parts.iter().map(|p| p[k]).sum::<f64>() / masked).collect()
    }
}

/// How well the views back each of `images` (results of `key`'s `mask`, keyframe-sized) on
/// the evidence `sources`, `extras` and `params` give: the share of the mask the views
/// that show the building back, as [`Filled::rival_quality`] says of a rival. The
/// evidence is gathered once, as [`fill_with`] gathers it, and no fill is made from it.
/// 0 for an image of another size, and for every image when the mask is empty or
/// `observer` is cancelled.
///
/// # Panics
/// As [`fill_with`].
pub fn backed_by<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    images: &[&RgbF32],
    observer: &mut dyn Observer,
) -> Vec<f64> {
    backed_by_in(key, mask, sources, extras, params, images, &|_, _| 0, 1, observer)
        .into_iter()
        .map(|b| b[0])
        .collect()
}

/// [`backed_by`] apart for each of `bins` classes of masked pixel (`bin(x, y)` says which):
/// per image, each class's share of the mask the views back.
#[allow(clippy::too_many_arguments)]
pub(crate) fn backed_by_in<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    images: &[&RgbF32],
    bin: &(dyn Fn(usize, usize) -> usize + Sync),
    bins: usize,
    observer: &mut dyn Observer,
) -> Vec<Vec<f64>> {
    check_inputs(key, mask, sources, extras);
    let (w, h) = (key.width(), key.height());
    let mut report = FillReport {
        sources: vec![SourceReport { gain: [1.0; 3], ..SourceReport::default() }; sources.len()],
        ..FillReport::default()
    };
    let mut surface = Plane::new(w, h, 0u16);
    let gathered = Gathered::gather(key, mask, sources, extras, params, observer, &mut report, &mut surface);
    images
        .iter()
        .map(|image| match &gathered {
            Some(g) if (image.width(), image.height()) == (w, h) => g.judge_by(key, mask, image, bin, bins),
            _ => vec![0.0; bins],
        })
        .collect()
}

/// An observer for a trial fill: it is told nothing, but a cancellation still stops it.
struct Quiet<'a>(&'a dyn Observer);

impl Observer for Quiet<'_> {
    fn cancelled(&self) -> bool {
        self.0.cancelled()
    }
}

/// `0..n`: every view.
fn all_views(n: usize) -> Vec<usize> {
    (0..n).collect()
}

/// `ws[v]` for the views `views`, in that order.
fn pick_views<'a>(ws: &'a [Warped], views: &[usize]) -> Vec<&'a Warped> {
    views.iter().map(|&v| &ws[v]).collect()
}

/// What the fill of a set of views needs once the views are warped and compensated.
struct Staged<'a> {
    key: &'a RgbF32,
    mask: &'a Mask,
    parts: &'a [Part],
    /// Per part, per source.
    warps: &'a [Vec<Warped>],
    /// Per part, per source: where the source's pixel is there only under a soft mark.
    lifted: &'a [Vec<Option<Plane<bool>>>],
    /// Per part, the occlusion model fitted on every source.
    maps: &'a [OcclusionMap],
    /// Per part, per source ([`view_errors`]: each view's own, whatever the others).
    errors: &'a [Vec<f32>],
    /// Per part, per source ([`view_edge_shares`]).
    edge_shares: &'a [Vec<f32>],
    /// Per part, per source ([`view_reach`]).
    reach: &'a [Vec<usize>],
    /// The whole keyframe's diagonal ([`FillExtras::whole`]).
    diagonal: f32,
    params: &'a FillParams,
    seed: u64,
}

/// A result made from some of the views.
struct Made {
    /// The sources it was made from (indices, in order).
    views: Vec<usize>,
    /// Per part: the multi-view fill (picks in `views`' numbering), for the blend.
    results: Vec<RegionFill>,
    image: RgbF32,
    provenance: Provenance,
    confidence: Confidence,
    /// The confidence as the fill decides with it ([`Filled::deciding`]).
    guiding: Confidence,
    /// Masked pixels taken from each source (all of them, by index).
    filled: Vec<usize>,
    fallback: usize,
}

impl Staged<'_> {
    /// The fill and fallback from the sources `views` (indices, in order) alone, with the
    /// occlusion model fitted on them (`maps` when it is already known, per part); not yet
    /// blended ([`Staged::blend`]).
    fn compose(&self, views: &[usize], observer: &mut dyn Observer) -> Made {
        let (key, mask, parts, params) = (self.key, self.mask, self.parts, self.params);
        let (w, h) = (key.width(), key.height());
        let masked = mask.hole_count();
        let mut image = key.clone();
        let mut provenance = Provenance::new(w, h, KEYFRAME);
        let mut confidence = Confidence::new(w, h, 0);
        let mut guiding = Confidence::new(w, h, 0);
        let mut filled = vec![0; self.warps.first().map_or(0, Vec::len)];
        let mut fallback_count = 0;
        let warps: Vec<Vec<&Warped>> = self.warps.iter().map(|ws| pick_views(ws, views)).collect();
        let errors: Vec<Vec<f32>> =
            self.errors.iter().map(|e| views.iter().map(|&v| e[v]).collect()).collect();
        let own: Vec<OcclusionMap>;
        let maps = if views.len() == self.maps.first().map_or(0, |m| m.occluded.len()) {
            self.maps
        } else {
            own = parts
                .par_iter()
                .zip(warps.par_iter())
                .map(|(part, ws)| region_model(key, part, ws, self.diagonal, params))
                .collect();
            &own
        };
        let done = |results, image, provenance, confidence, guiding, filled, fallback| Made {
            views: views.to_vec(),
            results,
            image,
            provenance,
            confidence,
            guiding,
            filled,
            fallback,
        };

        // Fill: regions in parallel, in batches so that progress can be told.
        if observer.cancelled() {
            return done(Vec::new(), image, provenance, confidence, guiding, filled, fallback_count);
        }
        observer.stage(Stage::Fill);
        let mparams = params.multiview();
        let mut results: Vec<RegionFill> = Vec::with_capacity(parts.len());
        let batch = rayon::current_num_threads().max(1);
        let mut count = 0;
        for start in (0..parts.len()).step_by(batch) {
            if observer.cancelled() {
                break;
            }
            let out: Vec<RegionFill> = (start..(start + batch).min(parts.len()))
                .into_par_iter()
                .map(|k| {
                    let evidence = Evidence {
                        warps: pick_views(&self.warps[k], &all_views(self.warps[k].len())),
                        map: &self.maps[k],
                        errors: &self.errors[k],
                        edge_shares: &self.edge_shares[k],
                        reach: &self.reach[k],
                        views,
                    };
                    let lifted: Vec<Option<&Plane<bool>>> =
                        views.iter().map(|&v| self.lifted[k].get(v).and_then(Option::as_ref)).collect();
                    fill_one(
                        key, &parts[k], &warps[k], &lifted, &maps[k], &errors[k], &evidence, &mparams, params,
                    )
                })
                .collect();
            count += parts[start..(start + batch).min(parts.len())].iter().map(|p| p.holes).sum::<usize>();
            results.extend(out);
            observer.progress(count, masked);
        }
        for (part, res) in parts.iter().zip(&results) {
            let rw = part.rect.width;
            for (i, (&st, pk)) in res.state.iter().zip(&res.pick).enumerate() {
                if st == multiview::FILLED {
                    let (x, y) = (part.rect.x + i % rw, part.rect.y + i / rw);
                    let source = views[pk.view as usize];
                    image.set(x, y, res.pixels[i]);
                    provenance.set(x, y, 1 + source as u16);
                    confidence.set(x, y, to_byte(res.confidence[i]));
                    guiding.set(x, y, to_byte(res.guiding[i]));
                    filled[source] += 1;
                }
            }
        }

        // Fallback: what no view saw, from the image itself (with the views' fill as context).
        if observer.cancelled() {
            return done(results, image, provenance, confidence, guiding, filled, fallback_count);
        }
        observer.stage(Stage::Fallback);
        let mut pending = Mask::new(w, h, 0);
        let mut any_pending = false;
        for (part, res) in parts.iter().zip(&results) {
            let rw = part.rect.width;
            for (i, &st) in res.state.iter().enumerate() {
                if part.hole.as_slice()[i] && st != multiview::FILLED {
                    pending.set(part.rect.x + i % rw, part.rect.y + i / rw, 255);
                    any_pending = true;
                }
            }
        }
        if any_pending {
            for (k, part) in parts.iter().enumerate() {
                let stop = || observer.cancelled();
                fallback_count += fallback(
                    &mut image,
                    &mut pending,
                    &mut provenance,
                    &guiding,
                    part.rect,
                    params,
                    self.seed ^ k as u64,
                    &stop,
                );
                observer.progress(k + 1, parts.len());
            }
        }
        for y in 0..h {
            for (x, &p) in provenance.row(y).iter().enumerate() {
                if p == FALLBACK {
                    confidence.set(x, y, to_byte(INVENTED));
                    guiding.set(x, y, to_byte(INVENTED));
                }
            }
        }

        done(results, image, provenance, confidence, guiding, filled, fallback_count)
    }

    /// Averages into each pixel of `made` copied from a view the other views of the fill
    /// there ([`fuse`]), per part as far as its ring says the views' errors are independent.
    /// The blend's correction is kept: what changes is the copy under it. Returns the
    /// changed pixels with their colours before (see [`Filled::unfused`]). Stops when
    /// `observer` cancels (asked every [`FUSE_BAND_PIXELS`]; the caller then throws the fill
    /// away).
    fn fuse(&self, made: &mut Made, params: &FuseParams, observer: &dyn Observer) -> Vec<(usize, [f32; 3])> {
        let w = made.image.width();
        let mut changed = Vec::new();
        if made.results.len() != self.parts.len() {
            return changed;
        }
        for (k, part) in self.parts.iter().enumerate() {
            let (res, ws, map) = (&made.results[k], &self.warps[k], &self.maps[k]);
            let Some(mix) = ring_mix(self.key, part, ws, &made.views, params) else { continue };
            let r = part.rect;
            // In bands of the box's pixels, asking between them: one hole can be most of a
            // 12 MP frame.
            let mut deltas: Vec<(usize, [f32; 3])> = Vec::new();
            for start in (0..r.area()).step_by(FUSE_BAND_PIXELS) {
                if observer.cancelled() {
                    return changed;
                }
                let band = start..(start + FUSE_BAND_PIXELS).min(r.area());
                deltas.par_extend(band.into_par_iter().filter_map(|i| {
                    let p = res.pick[i];
                    if res.state[i] != multiview::FILLED || p.view == NO_VIEW {
                        return None;
                    }
                    let others = made
                        .views
                        .iter()
                        .enumerate()
                        .filter(|&(_, &u)| ws[u].valid.as_slice()[i])
                        .map(|(j, &u)| (j, ws[u].image.as_slice()[i], map.occluded[u][i]));
                    let a = res.pixels[i];
                    let f = fuse::fuse_pixel(a, p.view as usize, others, &mix, params)?;
                    Some((i, [f[0] - a[0], f[1] - a[1], f[2] - a[2]]))
                }));
            }
            for (i, d) in deltas {
                let (x, y) = (r.x + i % r.width, r.y + i / r.width);
                let before = made.image.get(x, y);
                made.image.set(x, y, [0, 1, 2].map(|c| (before[c] + d[c]).clamp(0.0, 1.0)));
                changed.push((y * w + x, before));
            }
        }
        changed
    }

    /// Blends `made` into the keyframe: each region's fill, guided by its views' own
    /// gradients; the result's pixels clamped to 0..=1.
    fn blend(&self, mut made: Made, observer: &mut dyn Observer) -> Made {
        let (parts, params) = (self.parts, self.params);
        if observer.cancelled() {
            return made;
        }
        observer.stage(Stage::Blend);
        let warps: Vec<Vec<&Warped>> = self.warps.iter().map(|ws| pick_views(ws, &made.views)).collect();
        let image = &mut made.image;
        if params.blend {
            let batch = rayon::current_num_threads().max(1);
            let mut count = 0;
            for ((pb, wb), rb) in parts.chunks(batch).zip(warps.chunks(batch)).zip(made.results.chunks(batch))
            {
                if observer.cancelled() {
                    break;
                }
                let blended: Vec<(Vec<[f32; 3]>, Vec<bool>)> = pb
                    .par_iter()
                    .zip(wb.par_iter())
                    .zip(rb.par_iter())
                    .map(|((part, ws), res)| blend_one(image, part, ws, res, &params.blend_params))
                    .collect();
                for (part, (u, moved)) in pb.iter().zip(&blended) {
                    let r = part.rect;
                    for y in 0..r.height {
                        let row = &mut image.row_mut(r.y + y)[r.x..r.x + r.width];
                        for (x, px) in row.iter_mut().enumerate() {
                            let i = y * r.width + x;
                            if part.hole.as_slice()[i] {
                                *px = u[i];
                            }
                            if moved[i] {
                                let c = made.confidence.get(r.x + x, r.y + y);
                                made.confidence.set(r.x + x, r.y + y, c.min(to_byte(MOVED_CONFIDENCE)));
                            }
                        }
                    }
                }
                count += pb.len();
                observer.progress(count, parts.len());
            }
        }
        for part in parts {
            let rw = part.rect.width;
            for (i, &hh) in part.hole.as_slice().iter().enumerate() {
                if hh {
                    let (x, y) = (part.rect.x + i % rw, part.rect.y + i / rw);
                    image.set(x, y, image.get(x, y).map(|v| v.clamp(0.0, 1.0)));
                }
            }
        }
        made
    }
}

/// Sums, over a part's hole, how well `img`'s pixels agree with the views there (0..=1
/// each): each view a witness as far as the model thinks it shows the building, weighted by
/// its precision (the inverse of its expected error, [`view_errors`]: a blurred or shifted
/// view is a poor judge of a sharp edge), and a witness backs the pixel or not ([`backs`]:
/// the step is at a gross difference); where the witnesses are weak (every view occluded there) the rest of
/// the pixel counts as invented, and a pixel no view sees is invented.
///
/// Agreement is (nearly) all or nothing on purpose: two fills of the same wall from different views
/// differ by resampling blur and sub-pixel shifts along every edge, which a graded
/// closeness counts over thousands of pixels and which says nothing of which fill is right;
/// what decides is where a fill shows what the views do not (an occluder copied, a wrong
/// surface), and that is a gross error.
///
/// The sums are kept apart for each of `bins` classes of pixel: `bin(x, y)` (keyframe
/// coordinates, below `bins`) says which class a masked pixel adds to.
fn witnessed_by(
    img: &RgbF32,
    part: &Part,
    ws: &[Warped],
    map: &OcclusionMap,
    errors: &[f32],
    bin: &(dyn Fn(usize, usize) -> usize + Sync),
    bins: usize,
) -> Vec<f64> {
    let r = part.rect;
    let holes = part.hole.as_slice();
    // In blocks of a fixed size on every core, their sums added in order: the same figure
    // for the same result, whatever the threads (a hole is often one part: serial, it held
    // one core through every judgement).
    let blocks: Vec<Vec<f64>> = holes
        .par_chunks(WITNESS_BLOCK)
        .enumerate()
        .map(|(b, block)| {
            let mut sums = vec![0.0f64; bins];
            for (j, &hole) in block.iter().enumerate() {
                if !hole {
                    continue;
                }
                let i = b * WITNESS_BLOCK + j;
                let (x, y) = (r.x + i % r.width, r.y + i / r.width);
                let value = img.get(x, y);
                let (mut trust, mut wsum, mut agree) = (0.0f32, 0.0f32, 0.0f32);
                for (v, wv) in ws.iter().enumerate() {
                    if !wv.valid.as_slice()[i] {
                        continue;
                    }
                    let t = map.independence[v] * (1.0 - map.occluded[v][i]);
                    let precision = 1.0 / (errors[v].min(1.0) + ERROR_FLOOR);
                    trust += t;
                    wsum += t * precision;
                    agree += t * precision * backs(occlusion::max_channel(wv.image.as_slice()[i], value));
                }
                let sure = (trust / WITNESS_TRUST).min(1.0);
                let q = if wsum > 0.0 { sure * agree / wsum } else { 0.0 };
                sums[bin(x, y)] += f64::from(q + (1.0 - sure) * INVENTED);
            }
            sums
        })
        .collect();
    (0..bins).map(|k| blocks.iter().map(|b| b[k]).sum()).collect()
}

/// The pixels of a part [`witnessed_by`] sums on one core before the blocks' sums are added.
const WITNESS_BLOCK: usize = 1 << 16;

/// Whether a witness backs a pixel it differs from by `d` (the largest channel difference):
/// fully below [`GROSS`] less [`GROSS_STEP`], not at all from [`GROSS`] plus it, linearly
/// between (a step, not a cliff: two fills that agree to the level do not part on a pixel
/// that rounding moves across the line).
#[inline]
fn backs(d: f32) -> f32 {
    ((GROSS + GROSS_STEP - d) / (2.0 * GROSS_STEP)).clamp(0.0, 1.0)
}

/// A gross difference: 30 levels of 255, past noise, exposure residue and the blur of
/// resampling on brick and render, short of another material (a strong edge moved by a
/// pixel still counts against, on the edge's few pixels rather than as a graded penalty on
/// every joint).
const GROSS: f32 = 30.0 / 255.0;
/// Half the width of the step around [`GROSS`].
const GROSS_STEP: f32 = 6.0 / 255.0;

/// The expected error (squared RGB per pixel) below which views are equally precise
/// witnesses: noise and the resampling every view shares.
const ERROR_FLOOR: f32 = 1e-4;
/// Witness trust (views' sum of `1 - occlusion probability`) from which a pixel is fully
/// judged by its witnesses.
const WITNESS_TRUST: f32 = 0.5;

fn to_byte(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// The value of `occluders` (view coordinates, nearest pixel) under each valid pixel of
/// `wv` (warped through `h`); `None` without occluders.
fn mark_levels(wv: &Warped, h: &Homography, occluders: Option<&Mask>) -> Option<Plane<u8>> {
    let m = occluders?;
    let r = wv.rect;
    Some(Plane::from_fn(r.width, r.height, |x, y| {
        if !wv.valid.get(x, y) {
            return 0;
        }
        h.apply(nalgebra::Point2::new((r.x + x) as f64, (r.y + y) as f64))
            .and_then(|p| {
                let (u, v) = (p.x.round(), p.y.round());
                if u >= 0.0 && v >= 0.0 { m.get_checked(u as isize, v as isize) } else { None }
            })
            .unwrap_or(0)
    }))
}

/// Marks invalid the views' pixels on their occluders (`levels` > 127), but where every
/// view that sees a pixel is marked there, those whose mark is soft (below 255) stay,
/// unless, inside the mask, they look like the keyframe ([`LIFTED_RESEMBLES`]; not asked of
/// a faint mark, [`FAINT_MARK`]), or their
/// colour is foreign to the building around the mask ([`LIFTED_FOREIGN`]). Returns,
/// per view, the pixels that stayed under a soft mark (`None`: none did).
fn exclude_marked(
    ws: &mut [Warped],
    levels: &[Option<Plane<u8>>],
    key: &RgbF32,
    mask: &Mask,
) -> Vec<Option<Plane<bool>>> {
    let mut lifted: Vec<Option<Plane<bool>>> = vec![None; ws.len()];
    let Some(first) = ws.first() else { return lifted };
    if levels.iter().all(Option::is_none) {
        // No source has marks (no caller's marks, and no own occluders found: fewer views
        // than [`OwnParams::min_views`], or `FillParams::own` off): nothing to do.
        return lifted;
    }
    let (w, h, r) = (first.rect.width, first.rect.height, first.rect);
    let level = |v: usize, x: usize, y: usize| levels[v].as_ref().map_or(0, |l| l.get(x, y));
    // The 3 × 3 mean at a pixel of the part of what `at` gives there.
    let mean = |x: usize, y: usize, at: &dyn Fn(usize, usize) -> Option<[f32; 3]>| {
        let (mut s, mut n) = ([0.0f32; 3], 0.0f32);
        for yy in y.saturating_sub(1)..(y + 2).min(h) {
            for xx in x.saturating_sub(1)..(x + 2).min(w) {
                if let Some(k) = at(xx, yy) {
                    (0..3).for_each(|c| s[c] += k[c]);
                    n += 1.0;
                }
            }
        }
        s.map(|c| c / n.max(1.0))
    };
    let key_mean = |x: usize, y: usize| mean(x, y, &|xx, yy| Some(key.get(r.x + xx, r.y + yy)));
    let view_mean = |wv: &Warped, x: usize, y: usize| {
        mean(x, y, &|xx, yy| wv.valid.get(xx, yy).then(|| wv.image.get(xx, yy)))
    };
    // Row by row on every core: a mark drops its pixel, except where every view that sees
    // the pixel is marked and this mark is not sure; those are judged after.
    // (view, x, y) of a part's pixel.
    type At = (usize, usize, usize);
    let rows: Vec<(Vec<At>, Vec<At>)> = (0..h)
        .into_par_iter()
        .map(|y| {
            let (mut drop, mut judge) = (Vec::new(), Vec::new());
            for x in 0..w {
                let mut seen = (0..ws.len()).filter(|&v| ws[v].valid.get(x, y)).peekable();
                let all_marked = seen.peek().is_some() && seen.clone().all(|v| level(v, x, y) > 127);
                for v in seen {
                    let l = level(v, x, y);
                    if l > 127 && !(all_marked && l < 255) {
                        drop.push((v, x, y));
                    } else if l > 127 {
                        judge.push((v, x, y));
                    }
                }
            }
            (drop, judge)
        })
        .collect();
    let judged: Vec<At> = rows.iter().flat_map(|r| r.1.iter().copied()).collect();
    let mut drop: Vec<At> = rows.into_iter().flat_map(|r| r.0).collect();
    if !judged.is_empty() {
        // The building's colours: the keyframe around the part, outside the mask.
        let around = r.grown(LIFTED_FOREIGN_REACH, key.width(), key.height());
        let building = occlusion::Histogram::new(
            (around.y..around.y1())
                .flat_map(|y| (around.x..around.x1()).map(move |x| (x, y)))
                .filter(|&(x, y)| !mask.is_hole(x, y))
                .map(|(x, y)| key.get(x, y)),
        );
        for (v, x, y) in judged {
            let l = level(v, x, y);
            // Inside the mask the keyframe shows its occluder: a lifted pixel like it shows
            // the same one. And a mark over a colour the building does not have is right,
            // whatever the other views' marks.
            let inside = mask.is_hole(r.x + x, r.y + y);
            let (a, b) = (view_mean(&ws[v], x, y), key_mean(x, y));
            let d = (0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f32>().sqrt();
            let like_keys_occluder = inside && d < LIFTED_RESEMBLES && l > FAINT_MARK;
            if like_keys_occluder || building.foreign(a) >= LIFTED_FOREIGN {
                drop.push((v, x, y));
            } else {
                lifted[v].get_or_insert_with(|| Plane::new(w, h, false)).set(x, y, true);
            }
        }
    }
    for (v, x, y) in drop {
        ws[v].valid.set(x, y, false);
    }
    lifted
}

/// Marks invalid the pixels of `wv` (warped through `h`) that fall on `occluders` (view
/// coordinates, nearest pixel).
fn exclude(wv: &mut Warped, h: &Homography, occluders: Option<&Mask>) {
    let Some(levels) = mark_levels(wv, h, occluders) else { return };
    for (ok, &l) in wv.valid.as_mut_slice().iter_mut().zip(levels.as_slice()) {
        if l > 127 {
            *ok = false;
        }
    }
}

/// The tone curve sees about this many pairs of the whole overlap per view (a grid).
const TONE_SAMPLES: usize = 40_000;
/// No pair where the keyframe or the view changes by more than this (0..=1, per channel,
/// over two pixels) on a step of one pixel: there a misregistration of a pixel moves the
/// value more than exposure does.
const TONE_MAX_GRADIENT: f32 = 24.0 / 255.0;
/// No pair within this many pixels of the keyframe's mask (the occluder's halo).
const TONE_MASK_GAP: isize = 6;

/// Maps view `v`'s valid warped pixels through `f`, in every part's warps and in its
/// surfaces' (`plane_warps`), so that all of them are compensated alike.
fn map_view(
    warps: &mut [Vec<Warped>],
    plane_warps: &mut [Vec<Vec<Option<Warped>>>],
    v: usize,
    f: impl Fn([f32; 3]) -> [f32; 3] + Sync,
) {
    let apply = |wv: &mut Warped| {
        wv.image.as_mut_slice().par_iter_mut().zip(wv.valid.as_slice().par_iter()).for_each(|(p, &ok)| {
            if ok {
                *p = f(*p);
            }
        });
    };
    for ws in warps.iter_mut() {
        apply(&mut ws[v]);
    }
    for pw in plane_warps.iter_mut() {
        for wv in pw.iter_mut().filter_map(|p| p.get_mut(v)).flatten() {
            apply(wv);
        }
    }
}

/// `(view, keyframe)` colour pairs over the whole overlap of `source` and `key`, on a grid
/// of about [`TONE_SAMPLES`] points: outside the mask and its halo, off the view's known
/// occluders, and only where neither image has a strong local gradient.
fn overlap_pairs<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    source: &Source<'_, P>,
    occluders: Option<&Mask>,
) -> Vec<([f32; 3], [f32; 3])> {
    let (w, h) = (key.width(), key.height());
    let step = (((w * h) as f64 / TONE_SAMPLES as f64).sqrt().floor() as usize).max(1);
    let steep = |a: [f32; 3], b: [f32; 3], c: [f32; 3], d: [f32; 3]| {
        (0..3).any(|i| (a[i] - b[i]).abs() + (c[i] - d[i]).abs() > TONE_MAX_GRADIENT)
    };
    let near_hole = |x: usize, y: usize| {
        let g = TONE_MASK_GAP;
        [(0, 0), (-g, 0), (g, 0), (0, -g), (0, g), (-g, -g), (g, -g), (-g, g), (g, g)]
            .iter()
            .any(|&(dx, dy)| mask.get_checked(x as isize + dx, y as isize + dy).is_some_and(|m| m > 127))
    };
    let rows: Vec<usize> = (1..h.saturating_sub(1)).step_by(step).collect();
    rows.par_iter()
        .flat_map_iter(|&y| {
            let mut out = Vec::new();
            for x in (1..w.saturating_sub(1)).step_by(step) {
                if near_hole(x, y) {
                    continue;
                }
                let k = key.get(x, y);
                if steep(key.get(x + 1, y), key.get(x - 1, y), key.get(x, y + 1), key.get(x, y - 1)) {
                    continue;
                }
                let Some(p) = source.homography.apply(nalgebra::Point2::new(x as f64, y as f64)) else {
                    continue;
                };
                let (u, v) = (p.x as f32, p.y as f32);
                if occluders.is_some_and(|m| {
                    m.get_checked(u.round() as isize, v.round() as isize).is_some_and(|o| o > 127)
                }) {
                    continue;
                }
                let at = |du: f32, dv: f32| bilinear_rgb(source.image, u + du, v + dv);
                let (Some(c), Some(r), Some(l), Some(d), Some(t)) =
                    (at(0.0, 0.0), at(1.0, 0.0), at(-1.0, 0.0), at(0.0, 1.0), at(0.0, -1.0))
                else {
                    continue;
                };
                if steep(r, l, d, t) {
                    continue;
                }
                out.push((c, k));
            }
            out
        })
        .collect()
}

/// Whether two rectangles share a pixel.
fn overlap(a: Rect, b: Rect) -> bool {
    a.x < b.x1() && b.x < a.x1() && a.y < b.y1() && b.y < a.y1()
}

/// Chooses the surface of each pixel of a part and rewrites each view's warp `ws[v]` from
/// its plane warps accordingly (a view without the chosen plane is invalid there). Returns
/// the part's labels (0 the wall, `1 + p` plane `p`).
fn compose_planes(
    key: &RgbF32,
    part: &Part,
    ws: &mut [Warped],
    pw: &[Vec<Option<Warped>>],
    planes: &[SurfacePlane],
    params: &ParallaxParams,
) -> Vec<u16> {
    let r = part.rect;
    let n = r.area();
    let near: Vec<usize> = (0..pw.len()).filter(|&p| !pw[p].is_empty()).collect();
    if near.is_empty() {
        return vec![0; n];
    }
    let pixels = key.crop(r).into_vec();
    let mut hyps: Vec<Vec<Option<WarpedView<'_>>>> =
        vec![ws.iter().map(|wv| Some((wv.image.as_slice(), wv.valid.as_slice()))).collect()];
    let mut allowed = vec![vec![true; n]];
    for &p in &near {
        hyps.push(
            pw[p].iter().map(|o| o.as_ref().map(|wv| (wv.image.as_slice(), wv.valid.as_slice()))).collect(),
        );
        let g = planes[p].region;
        allowed.push((0..n).map(|i| g.contains(r.x + i % r.width, r.y + i / r.width)).collect());
    }
    let input = PlaneInput { region: part.region(&pixels), planes: &hyps, allowed: &allowed };
    let chosen = choose_planes(&input, params);
    drop(hyps);
    for (v, wv) in ws.iter_mut().enumerate() {
        let (img, ok) = (wv.image.as_mut_slice(), wv.valid.as_mut_slice());
        for (i, &l) in chosen.iter().enumerate() {
            if l == 0 {
                continue;
            }
            match &pw[near[l as usize - 1]][v] {
                Some(src) => {
                    img[i] = src.image.as_slice()[i];
                    ok[i] = src.valid.as_slice()[i];
                }
                None => ok[i] = false,
            }
        }
    }
    chosen.iter().map(|&l| if l == 0 { 0 } else { 1 + near[l as usize - 1] as u16 }).collect()
}

/// One connected part of the hole with the margin around it that the fill reads.
struct Part {
    /// Keyframe pixels of the part (the margin included, clipped to the image).
    rect: Rect,
    /// `rect`-sized: this part's hole pixels.
    hole: Plane<bool>,
    /// `rect`-sized: the hole grown by the margin (where the views are warped).
    need: Plane<bool>,
    /// `rect`-sized: the keyframe ring the photometric fit uses.
    ring: Plane<bool>,
    /// `rect`-sized: hole pixels of other parts inside `rect`.
    blocked: Plane<bool>,
    holes: usize,
}

impl Part {
    /// The part as the occlusion model and the plane choice read it, over `pixels` (the
    /// keyframe cropped to `rect`).
    fn region<'a>(&'a self, pixels: &'a [[f32; 3]]) -> KeyRegion<'a> {
        KeyRegion {
            width: self.rect.width,
            height: self.rect.height,
            key: pixels,
            hole: self.hole.as_slice(),
            need: self.need.as_slice(),
            blocked: self.blocked.as_slice(),
        }
    }
}

/// Cuts the mask into parts: 8-connected components of the hole grown by `margin`.
fn regions(mask: &Mask, margin: usize, ring_gap: usize, ring_width: usize) -> Vec<Part> {
    let (w, h) = (mask.width(), mask.height());
    let Some(bounds) = mask.hole_bounds() else { return Vec::new() };
    let work = bounds.grown(margin + 1, w, h);
    let hole = Plane::from_fn(work.width, work.height, |x, y| mask.is_hole(work.x + x, work.y + y));
    let need = dilate(&hole, margin);
    let (ww, wh) = (work.width, work.height);
    let mut label = vec![u32::MAX; ww * wh];
    let mut parts = Vec::new();
    let mut stack = Vec::new();
    let mut members: Vec<usize> = Vec::new();
    for start in 0..ww * wh {
        if !need.as_slice()[start] || label[start] != u32::MAX {
            continue;
        }
        let id = parts.len() as u32;
        label[start] = id;
        stack.push(start);
        members.clear();
        let (mut bx0, mut by0, mut bx1, mut by1) = (ww, wh, 0, 0);
        while let Some(i) = stack.pop() {
            members.push(i);
            let (x, y) = (i % ww, i / ww);
            bx0 = bx0.min(x);
            bx1 = bx1.max(x + 1);
            by0 = by0.min(y);
            by1 = by1.max(y + 1);
            for dy in -1isize..=1 {
                for dx in -1isize..=1 {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    if nx < 0 || ny < 0 || nx >= ww as isize || ny >= wh as isize {
                        continue;
                    }
                    let j = ny as usize * ww + nx as usize;
                    if need.as_slice()[j] && label[j] == u32::MAX {
                        label[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
        let rect = Rect { x: work.x + bx0, y: work.y + by0, width: bx1 - bx0, height: by1 - by0 };
        let mut p_need = Plane::new(rect.width, rect.height, false);
        let mut p_hole = Plane::new(rect.width, rect.height, false);
        for &i in &members {
            let (x, y) = (i % ww - bx0, i / ww - by0);
            p_need.set(x, y, true);
            p_hole.set(x, y, hole.as_slice()[i]);
        }
        parts.push(Part {
            rect,
            holes: p_hole.as_slice().iter().filter(|&&b| b).count(),
            hole: p_hole,
            need: p_need,
            ring: Plane::new(0, 0, false),
            blocked: Plane::new(0, 0, false),
        });
    }
    parts.par_iter_mut().for_each(|p| p.finish(mask, ring_gap, ring_width));
    parts
}

impl Part {
    fn finish(&mut self, mask: &Mask, gap: usize, width: usize) {
        let inner = dilate(&self.hole, gap);
        let outer = dilate(&self.hole, gap + width);
        let r = self.rect;
        self.blocked =
            Plane::from_fn(r.width, r.height, |x, y| mask.is_hole(r.x + x, r.y + y) && !self.hole.get(x, y));
        self.ring = Plane::from_fn(r.width, r.height, |x, y| {
            outer.get(x, y) && !inner.get(x, y) && self.need.get(x, y) && !mask.is_hole(r.x + x, r.y + y)
        });
    }
}

/// A region after the multi-view fill (region-sized buffers).
struct RegionFill {
    pixels: Vec<[f32; 3]>,
    state: Vec<u8>,
    pick: Vec<Pick>,
    /// How sure the fill is of each filled pixel (0..=1), as reported...
    confidence: Vec<f32>,
    /// ...and as the fallback's guide takes it ([`occlusion::GUIDE_EDGE_SHARE`]).
    guiding: Vec<f32>,
}

/// The occlusion model over one region (all zeros with the model switched off).
fn region_model(
    key: &RgbF32,
    part: &Part,
    warps: &[&Warped],
    diagonal: f32,
    params: &FillParams,
) -> OcclusionMap {
    let r = part.rect;
    let n = r.area();
    if !params.occlusion {
        return OcclusionMap {
            occluded: vec![vec![0.0; n]; warps.len()],
            independence: vec![1.0; warps.len()],
        };
    }
    let pixels = key.crop(r).into_vec();
    let refs: Vec<_> = warps.iter().map(|wv| (wv.image.as_slice(), wv.valid.as_slice())).collect();
    let input = RegionInput { region: part.region(&pixels), views: &refs, diagonal };
    occlusion_map(&input, &params.occlusion_model)
}

/// The evidence a fill's confidence is judged on: every view of a part, the model fitted on
/// all of them and their expected errors, and `views`, which of them the fill used (its
/// picks are numbered in that list).
struct Evidence<'a> {
    warps: Vec<&'a Warped>,
    map: &'a OcclusionMap,
    errors: &'a [f32],
    /// Per source ([`view_edge_shares`]).
    edge_shares: &'a [f32],
    /// Per source ([`view_reach`]).
    reach: &'a [usize],
    views: &'a [usize],
}

/// The multi-view fill of a part from `warps` (with their model `map` and expected errors),
/// each pixel's confidence taken on `evidence` (the views a fill leaves out still witness).
#[allow(clippy::too_many_arguments)]
fn fill_one(
    key: &RgbF32,
    part: &Part,
    warps: &[&Warped],
    lifted: &[Option<&Plane<bool>>],
    map: &OcclusionMap,
    errors: &[f32],
    evidence: &Evidence<'_>,
    params: &MultiviewParams,
    fill_params: &FillParams,
) -> RegionFill {
    let r = part.rect;
    let n = r.area();
    let mut pixels = Vec::with_capacity(n);
    let mut state = Vec::with_capacity(n);
    for y in 0..r.height {
        pixels.extend_from_slice(&key.row(r.y + y)[r.x..r.x + r.width]);
        for x in 0..r.width {
            state.push(if part.hole.get(x, y) {
                multiview::HOLE
            } else if part.blocked.get(x, y) {
                multiview::BLOCKED
            } else {
                multiview::KNOWN
            });
        }
    }
    let mut pick = vec![Pick::NONE; n];
    let refs: Vec<_> = evidence.warps.iter().map(|wv| (wv.image.as_slice(), wv.valid.as_slice())).collect();
    let model = &fill_params.occlusion_model;
    // A view's pixel the model thinks is an occluder is not there to copy, unless no view
    // does better there and the model is not sure (then it is copied, and flagged).
    let least: Vec<f32> = (0..n)
        .map(|i| {
            warps
                .iter()
                .zip(&map.occluded)
                .filter(|(wv, _)| wv.valid.as_slice()[i])
                .map(|(_, o)| o[i])
                .fold(f32::INFINITY, f32::min)
        })
        .collect();
    let seen: Vec<Vec<bool>> = warps
        .iter()
        .zip(&map.occluded)
        .map(|(wv, o)| {
            (0..n)
                .map(|i| {
                    let p = o[i];
                    wv.valid.as_slice()[i] && (p <= model.cut || (p <= model.sure && p <= least[i]))
                })
                .collect()
        })
        .collect();
    let best = errors.iter().copied().fold(f32::INFINITY, f32::min);
    let views: Vec<ViewData<'_>> = warps
        .iter()
        .zip(&map.occluded)
        .zip(&seen)
        .zip(errors)
        .map(|(((wv, o), s), &e)| ViewData {
            image: wv.image.as_slice(),
            valid: s,
            occlusion: o,
            expected_error: if e.is_finite() { fill_params.view_error_weight * (e - best) } else { 0.0 },
        })
        .collect();
    let mut region =
        Region { width: r.width, height: r.height, pixels: &mut pixels, state: &mut state, pick: &mut pick };
    fill_region(&mut region, &views, params);
    let (confidence, guiding): (Vec<f32>, Vec<f32>) = (0..n)
        .into_par_iter()
        .map(|i| {
            if state[i] != multiview::FILLED {
                return (0.0, 0.0);
            }
            let p = pick[i];
            let at = (i as isize + p.dy as isize * r.width as isize + p.dx as isize) as usize;
            // As sure as the view is of the keyframe around the hole: a view that reproduces
            // it with a gross error (parallax, misregistration) fills the hole the same way,
            // however well it agrees with itself or with views as far off.
            let view = evidence.views[p.view as usize];
            let fit = evidence
                .errors
                .get(view)
                .map_or(1.0, |&e| if e.is_finite() { occlusion::closeness(e.sqrt()) } else { 1.0 });
            let reach = evidence.reach.get(view).copied().unwrap_or(1);
            let c = occlusion::confidence(evidence.map, &refs, view, (at, reach), i, r.width, pixels[i]);
            let value =
                fit * c.reported(evidence.edge_shares.get(view).copied().unwrap_or(occlusion::EDGE_SHARE));
            // Its own frame took it for an occluder: never reported as sure.
            let lifted = lifted.get(p.view as usize).copied().flatten().is_some_and(|l| l.as_slice()[at]);
            let value = if lifted { value.min(LIFTED_CONFIDENCE) } else { value };
            (value, fit * c.value(occlusion::GUIDE_EDGE_SHARE))
        })
        .unzip();
    // A copy its view's ring contradicts nearby is not sure, however well the views agree.
    let contradicted = contradicted_by_ring(key, part, warps, &state, &pick);
    let confidence = confidence
        .into_iter()
        .zip(&contradicted)
        .map(|(c, &no)| if no { c.min(CONTRADICTED_CONFIDENCE) } else { c })
        .collect();
    RegionFill { pixels, state, pick, confidence, guiding }
}

/// Per pixel of a part, whether it was copied from a view that contradicts the keyframe on
/// the stretch of the ring nearest to it: more than [`RING_CONTRADICTION_SHARE`] of that
/// view's ring pixels within [`RING_CONTRADICTION_RADIUS`] of the ring pixel nearest to the
/// copied one are grossly unlike the keyframe's ([`GROSS`]). The ring is the nearest truth
/// there is, and what it shows continues into the hole: a pier or a pipe standing off the
/// wall that enters the mask, which every view sees past to the wall behind, is contradicted
/// where it crosses the ring, and the views' agreement inside says nothing about it. A
/// view's error over the whole ring ([`view_errors`]) keeps the best share of it, so that
/// its own occluders over part of the ring do not count: it cannot see this.
fn contradicted_by_ring(
    key: &RgbF32,
    part: &Part,
    warps: &[&Warped],
    state: &[u8],
    pick: &[Pick],
) -> Vec<bool> {
    let r = part.rect;
    let (w, h, n) = (r.width, r.height, r.area());
    let ring = part.ring.as_slice();
    // The nearest ring pixel of every pixel (4-connected steps), from all of them at once.
    let mut nearest = vec![u32::MAX; n];
    let mut queue: std::collections::VecDeque<usize> = (0..n).filter(|&j| ring[j]).collect();
    for &j in &queue {
        nearest[j] = j as u32;
    }
    while let Some(j) = queue.pop_front() {
        let (x, y) = (j % w, j / w);
        let steps = [
            (x > 0).then(|| j - 1),
            (x + 1 < w).then(|| j + 1),
            (y > 0).then(|| j - w),
            (y + 1 < h).then(|| j + w),
        ];
        for k in steps.into_iter().flatten() {
            if nearest[k] == u32::MAX {
                nearest[k] = nearest[j];
                queue.push_back(k);
            }
        }
    }
    // Per view that filled something: the share of its ring pixels around each ring pixel
    // that contradict the keyframe.
    let mut used: Vec<usize> =
        (0..n).filter(|&i| state[i] == multiview::FILLED).map(|i| pick[i].view as usize).collect();
    used.sort_unstable();
    used.dedup();
    let keyed: Vec<(usize, [f32; 3])> =
        (0..n).filter(|&j| ring[j]).map(|j| (j, key.get(r.x + j % w, r.y + j / w))).collect();
    let mut share: Vec<Option<Vec<f32>>> = vec![None; warps.len()];
    for v in used {
        let (img, ok) = (warps[v].image.as_slice(), warps[v].valid.as_slice());
        let mut unlike = vec![0.0f32; n];
        let mut seen = vec![0.0f32; n];
        for &(j, k) in keyed.iter().filter(|&&(j, _)| ok[j]) {
            seen[j] = 1.0;
            unlike[j] = f32::from(u8::from(occlusion::max_channel(img[j], k) > GROSS));
        }
        let (u, s) = (
            parallax::box_sum(&unlike, w, h, RING_CONTRADICTION_RADIUS),
            parallax::box_sum(&seen, w, h, RING_CONTRADICTION_RADIUS),
        );
        share[v] = Some(u.iter().zip(&s).map(|(&u, &s)| if s > 0.0 { u / s } else { 0.0 }).collect());
    }
    (0..n)
        .map(|i| {
            state[i] == multiview::FILLED
                && nearest[i] != u32::MAX
                && share[pick[i].view as usize]
                    .as_ref()
                    .is_some_and(|s| s[nearest[i] as usize] > RING_CONTRADICTION_SHARE)
        })
        .collect()
}

/// The ring pixels around the nearest one that [`contradicted_by_ring`] reads: within this
/// many pixels each way (a 9 × 9 box over the ring's band).
const RING_CONTRADICTION_RADIUS: usize = 4;
/// The share of them that must contradict the keyframe: most (a strong edge a pixel off
/// contradicts on its own few pixels only).
const RING_CONTRADICTION_SHARE: f32 = 0.5;

/// The averaging asks whether the fill is cancelled once per this many pixels of a hole's
/// box (about 15 ms of work).
const FUSE_BAND_PIXELS: usize = 1 << 18;

/// The combination of the fill's `views` (sources, in the fill's numbering) that comes
/// closest to the keyframe on the part's ring ([`fuse::mix`]).
fn ring_mix(key: &RgbF32, part: &Part, ws: &[Warped], views: &[usize], params: &FuseParams) -> Option<Mix> {
    let r = part.rect;
    let rows: Vec<Vec<Option<[f32; 3]>>> = part
        .ring
        .as_slice()
        .iter()
        .enumerate()
        .filter(|&(_, &on)| on)
        .map(|(i, _)| {
            let k = key.get(r.x + i % r.width, r.y + i / r.width);
            views
                .iter()
                .map(|&u| {
                    let p = ws[u].image.as_slice()[i];
                    ws[u].valid.as_slice()[i].then_some([p[0] - k[0], p[1] - k[1], p[2] - k[2]])
                })
                .collect()
        })
        .collect();
    fuse::mix(&rows, views.len(), params)
}

/// Per view, the error it is expected to make where it fills this part: how far its warped,
/// compensated pixels are from the keyframe's on the ring around the hole (squared RGB
/// distance per pixel, the mean of the best [`RING_TRUST`] of the ring, so that the view's
/// own occluders over part of the ring do not count). The ring is the nearest truth there is:
/// a view that reproduces it blurred (a warp that magnifies it) or shifted (misregistration)
/// will fill the hole the same way. Infinity for a view that sees too little of the ring.
fn view_errors(key: &RgbF32, part: &Part, warps: &[Warped]) -> Vec<f32> {
    let r = part.rect;
    let ring = part.ring.as_slice();
    warps
        .iter()
        .map(|wv| {
            let (img, ok) = (wv.image.as_slice(), wv.valid.as_slice());
            let mut d: Vec<f32> = ring
                .iter()
                .enumerate()
                .filter(|&(i, &on)| on && ok[i])
                .map(|(i, _)| {
                    let k = key.get(r.x + i % r.width, r.y + i / r.width);
                    let p = img[i];
                    (0..3).map(|c| (p[c] - k[c]).powi(2)).sum::<f32>()
                })
                .collect();
            if d.len() < RING_MIN {
                return f32::INFINITY;
            }
            let keep = ((d.len() as f32 * RING_TRUST) as usize).max(1);
            d.select_nth_unstable_by(keep - 1, f32::total_cmp);
            d[..keep].iter().sum::<f32>() / keep as f32
        })
        .collect()
}

/// Per view, the share of an edge's step by which its copies are expected to be wrong, as its
/// ring says: of the ring's edges (a step of at least [`EDGE_MIN_STEP`] across the view's
/// own pixel, as [`occlusion::PixelConfidence::reported`] measures it) where the model does
/// not take the view for an occluder, the [`EDGE_QUANTILE`] of their error against the
/// keyframe over their step; never below [`occlusion::EDGE_SHARE`], and that where the ring
/// has fewer than [`EDGE_MIN_SAMPLES`] such edges. A view a fraction of a pixel off, or
/// softer than the keyframe, or off the wall there (parallax) shows it along the ring's
/// edges first: the keyframe's thin lines (mortar, mullions) come out split or shifted in
/// it, wrong by most of the step the view shows, and so they will inside.
fn view_edge_shares(
    key: &RgbF32,
    part: &Part,
    warps: &[Warped],
    map: &OcclusionMap,
    reach: &[usize],
) -> Vec<f32> {
    let r = part.rect;
    let ring = part.ring.as_slice();
    warps
        .iter()
        .enumerate()
        .map(|(v, wv)| {
            let (img, ok) = (wv.image.as_slice(), wv.valid.as_slice());
            let reach = reach.get(v).copied().unwrap_or(1);
            let mut ratios: Vec<f32> = ring
                .iter()
                .enumerate()
                .filter(|&(i, &on)| on && ok[i] && map.occluded[v][i] <= 0.5)
                .filter_map(|(i, _)| {
                    let (_, step) = occlusion::steps(img, ok, i, r.width, reach);
                    (step >= EDGE_MIN_STEP).then(|| {
                        let k = key.get(r.x + i % r.width, r.y + i / r.width);
                        occlusion::max_channel(img[i], k) / step
                    })
                })
                .collect();
            if ratios.len() < EDGE_MIN_SAMPLES {
                return occlusion::EDGE_SHARE;
            }
            let at = ((ratios.len() as f32 * EDGE_QUANTILE) as usize).min(ratios.len() - 1);
            ratios.select_nth_unstable_by(at, f32::total_cmp);
            ratios[at].max(occlusion::EDGE_SHARE)
        })
        .collect()
}

/// The step (0..=1) from which a ring pixel is an edge for [`view_edge_shares`]: a gross
/// difference's worth. Across smaller steps the error is noise and light, not the edge.
const EDGE_MIN_STEP: f32 = 30.0 / 255.0;
/// The quantile of the ring edges' error over step that [`view_edge_shares`] takes. At 0.85
/// the keyframe's mortar lines split in a softer view stayed confident (planar-2: 40 % of
/// the gross errors flagged); at 0.95, 70 % (BENCHMARKS.md, "Confidence at edges, measured
/// on the ring").
const EDGE_QUANTILE: f32 = 0.95;
/// Ring edges a view must show for its own share to be measured.
const EDGE_MIN_SAMPLES: usize = 16;

/// The share of a view's ring pixels its expected error is taken over (the closest ones).
const RING_TRUST: f32 = 0.7;
/// Ring pixels a view must see for its expected error to be measured.
const RING_MIN: usize = 32;

/// The gain fit sees at most about this many ring pixels per view (evenly spread).
const GAIN_SAMPLES: usize = 12_000;

/// Radius of the median that smooths the border's demand along the border.
const BORDER_MEDIAN: usize = 5;
/// The largest step between two views' colours that blending removes at a seam inside.
const SEAM_STEP: f32 = 0.03;

/// The most keyframe pixels [`view_reach`] gives.
const MAX_REACH: usize = 4;

/// How many keyframe pixels one pixel of a view mapped by `h` (keyframe → view) spans at
/// the centre of `rect`, rounded, from 1 (the keyframe's resolution or finer) to
/// [`MAX_REACH`]: a view at a third of the keyframe's resolution spreads each of its edges
/// over three keyframe pixels, and where the edge lies within them its copy cannot say.
fn view_reach(h: &Homography, rect: Rect) -> usize {
    let c = Point2::new(rect.x as f64 + 0.5 * rect.width as f64, rect.y as f64 + 0.5 * rect.height as f64);
    let s = h.area_scale(c).abs().sqrt();
    if s.is_finite() && s > 0.0 { (1.0 / s).round().clamp(1.0, MAX_REACH as f64) as usize } else { 1 }
}

/// The single-image fallback for the pending pixels of `rect`, on a crop with context;
/// returns how many it filled.
#[allow(clippy::too_many_arguments)]
fn fallback(
    image: &mut RgbF32,
    pending: &mut Mask,
    provenance: &mut Provenance,
    confidence: &Confidence,
    rect: Rect,
    params: &FillParams,
    seed: u64,
    stop: &dyn Fn() -> bool,
) -> usize {
    let Some(bounds) = pending.hole_bounds_within(rect) else { return 0 };
    let extent = bounds.width.max(bounds.height);
    let crop = bounds.grown(params.fallback_margin + extent / 2, image.width(), image.height());
    let mut sub = RgbF32::from_fn(crop.width, crop.height, |x, y| image.get(crop.x + x, crop.y + y));
    let hole = Mask::from_fn(crop.width, crop.height, |x, y| pending.get(crop.x + x, crop.y + y));
    // The membrane over the hole is the exemplar fill's guide: it keeps the texture at the
    // front from growing across a part whose border says otherwise (brick into the sky).
    match fallback_guide(
        &sub,
        &hole,
        crop,
        provenance,
        confidence,
        params.fallback_guide_from,
        &params.blend_params,
    ) {
        Some(guide) => exemplar_fill_guided(&mut sub, &hole, &guide, &params.exemplar, seed, stop),
        None => exemplar_fill_until(&mut sub, &hole, &params.exemplar, seed, stop),
    };
    let mut count = 0;
    for y in 0..crop.height {
        for x in 0..crop.width {
            if hole.is_hole(x, y) {
                image.set(crop.x + x, crop.y + y, sub.get(x, y));
                provenance.set(crop.x + x, crop.y + y, FALLBACK);
                pending.set(crop.x + x, crop.y + y, 0);
                count += 1;
            }
        }
    }
    count
}

/// The fallback's guide on `crop` (`sub` and `hole` are its pixels and pending pixels): the
/// membrane from the pixels the fill is sure of. A view's pixel below `from` (by default
/// half of [`CONFIDENT`]: perhaps an occluder copied; every view pixel when `from` is
/// `None`) is context for the patches, not the border of the guide.
fn fallback_guide(
    sub: &RgbF32,
    hole: &Mask,
    crop: Rect,
    provenance: &Provenance,
    confidence: &Confidence,
    from: Option<u8>,
    params: &BlendParams,
) -> Option<RgbF32> {
    let unsure = Mask::from_fn(crop.width, crop.height, |x, y| {
        let (kx, ky) = (crop.x + x, crop.y + y);
        let p = provenance.get(kx, ky);
        let doubted = p != KEYFRAME && p != FALLBACK && from.is_none_or(|c| confidence.get(kx, ky) < c);
        if hole.is_hole(x, y) || doubted { 255 } else { 0 }
    });
    harmonic(sub, &unsure, params)
}

/// `image` with its `hole` pixels replaced by the membrane (harmonic) interpolation of the
/// known pixels around them: the smoothest fill their border allows. `None` when no known
/// pixel touches the hole (nothing to interpolate from).
fn harmonic(image: &RgbF32, hole: &Mask, params: &BlendParams) -> Option<RgbF32> {
    let (w, h) = (image.width(), image.height());
    let omega: Vec<bool> = hole.as_slice().iter().map(|&m| m > 127).collect();
    let known = |x: usize, y: usize| !omega[y * w + x];
    let bordered = (0..w * h).any(|i| {
        let (x, y) = (i % w, i / w);
        omega[i]
            && ((x > 0 && known(x - 1, y))
                || (x + 1 < w && known(x + 1, y))
                || (y > 0 && known(x, y - 1))
                || (y + 1 < h && known(x, y + 1)))
    });
    if !bordered {
        return None;
    }
    // With the hole at zero and no guidance, the blend's correction is the membrane itself.
    let mut out = image.clone();
    for (p, &inside) in out.as_mut_slice().iter_mut().zip(&omega) {
        if inside {
            *p = [0.0; 3];
        }
    }
    poisson_blend(w, h, &omega, out.as_mut_slice(), |_, _| [0.0; 3], params);
    Some(out)
}

/// The per-channel median of `values` (the upper one of an even count; 0 with none).
fn channel_median(values: impl Iterator<Item = [f32; 3]>) -> [f32; 3] {
    let mut chans: [Vec<f32>; 3] = Default::default();
    for v in values {
        chans.iter_mut().zip(v).for_each(|(c, x)| c.push(x));
    }
    chans.map(|mut c| {
        let k = c.len() / 2;
        if c.is_empty() { 0.0 } else { *c.select_nth_unstable_by(k, f32::total_cmp).1 }
    })
}

/// Poisson-blends one region of `image`. The guidance across an edge `p–q` is the gradient
/// of the view (at its chosen shift) that filled `p`, or else `q`; so seams between views
/// and the border with the keyframe are dissolved without flattening the views' detail.
/// Returns the region's pixels after blending (only the hole's are meant to be used), and
/// the hole pixels it moved by more than a gross difference beyond the correction common to
/// the part (exposure the photometric fit left): those the border's disagreement reached.
fn blend_one(
    image: &RgbF32,
    part: &Part,
    warps: &[&Warped],
    res: &RegionFill,
    params: &BlendParams,
) -> (Vec<[f32; 3]>, Vec<bool>) {
    let r = part.rect;
    let (w, h) = (r.width, r.height);
    let mut u: Vec<[f32; 3]> = Vec::with_capacity(r.area());
    for y in 0..h {
        u.extend_from_slice(&image.row(r.y + y)[r.x..r.x + w]);
    }
    let omega = part.hole.as_slice();
    let view_diff = |pick: Pick, p: usize, q: usize| -> Option<[f32; 3]> {
        if pick.view == NO_VIEW {
            return None;
        }
        let wv = &warps[pick.view as usize];
        let shift = |i: usize| -> Option<usize> {
            let (x, y) = ((i % w) as isize + pick.dx as isize, (i / w) as isize + pick.dy as isize);
            (x >= 0 && y >= 0 && x < w as isize && y < h as isize).then(|| y as usize * w + x as usize)
        };
        let (a, b) = (shift(p)?, shift(q)?);
        let valid = wv.valid.as_slice();
        if !(valid[a] && valid[b]) {
            return None;
        }
        let img = wv.image.as_slice();
        Some(std::array::from_fn(|c| img[a][c] - img[b][c]))
    };
    // What the border asks of the correction: the keyframe minus the view that filled the
    // neighbouring hole pixel, at each border pixel. Its fine detail is misregistration and
    // resampling, not exposure; a median along the border keeps only the exposure part, so
    // a dark mortar line that one side has and the other has not does not bleed inwards.
    let mut border: Vec<Option<[f32; 3]>> = vec![None; w * h];
    let neighbours = |i: usize| {
        let (x, y) = (i % w, i / w);
        [
            (x > 0).then(|| i - 1),
            (x + 1 < w).then(|| i + 1),
            (y > 0).then(|| i - w),
            (y + 1 < h).then(|| i + w),
        ]
    };
    let mut border_pixels = Vec::new();
    for q in 0..w * h {
        if omega[q] {
            continue;
        }
        let mut d = None;
        let mut touches = false;
        for p in neighbours(q).into_iter().flatten() {
            if omega[p] {
                touches = true;
                if d.is_none() {
                    d = view_diff(res.pick[p], p, q)
                        .map(|g| std::array::from_fn(|c| g[c] - (u[p][c] - u[q][c])));
                }
            }
        }
        if touches {
            border[q] = Some(d.unwrap_or([0.0; 3]));
            border_pixels.push(q);
        }
    }
    let seen = &border;
    let smooth: Vec<(usize, [f32; 3])> = border_pixels
        .par_iter()
        .map(|&q| {
            let (x, y) = (q % w, q / w);
            let window = (y.saturating_sub(BORDER_MEDIAN)..(y + BORDER_MEDIAN + 1).min(h)).flat_map(|yy| {
                (x.saturating_sub(BORDER_MEDIAN)..(x + BORDER_MEDIAN + 1).min(w))
                    .filter_map(move |xx| seen[yy * w + xx])
            });
            (q, channel_median(window))
        })
        .collect();
    for (q, m) in smooth {
        border[q] = Some(m);
    }
    let u_ref = &u;
    let border_ref = &border;
    let guide = |p: usize, q: usize| -> [f32; 3] {
        let own: [f32; 3] = std::array::from_fn(|c| u_ref[p][c] - u_ref[q][c]);
        if !omega[q] {
            let d = border_ref[q].unwrap_or([0.0; 3]);
            return std::array::from_fn(|c| own[c] + d[c]);
        }
        // Inside: across a seam, the mean of the two views' gradients (the same value seen
        // from either side, so the field has no spurious sources), and only as far as an
        // exposure step goes (a larger jump is detail the two views disagree on).
        let g = match (view_diff(res.pick[p], p, q), view_diff(res.pick[q], p, q)) {
            (Some(a), Some(b)) => std::array::from_fn(|c| 0.5 * (a[c] + b[c])),
            (Some(a), None) | (None, Some(a)) => a,
            (None, None) => return own,
        };
        std::array::from_fn(|c| own[c] + (g[c] - own[c]).clamp(-SEAM_STEP, SEAM_STEP))
    };
    let b = guidance_rhs(w, h, omega, &u, guide);
    let c = solve_membrane(w, h, omega, &b, params);
    // The correction common to the part is exposure the photometric fit left; a pixel
    // moved grossly beyond it is one the border's disagreement reached.
    let common = channel_median(c.iter().zip(omega).filter(|&(_, &o)| o).map(|(d, _)| *d));
    let moved = c.iter().zip(omega).map(|(d, &o)| o && occlusion::max_channel(*d, common) > GROSS).collect();
    (u.iter().zip(&c).map(|(p, d)| std::array::from_fn(|k| p[k] + d[k])).collect(), moved)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::Rgb8;
    use crate::synth::{Occluder, facade, paint_occluder, render_view};

    /// One pixel of a view at a third of the keyframe's size spans three keyframe pixels;
    /// a view at the keyframe's size or finer, one; never more than four.
    #[test]
    fn a_views_reach_is_how_many_keyframe_pixels_one_of_its_pixels_spans() {
        let rect = Rect { x: 100, y: 50, width: 40, height: 30 };
        let scaled =
            |s: f64| Homography::from_rows([[s, 0.0, 7.0], [0.0, s, -3.0], [0.0, 0.0, 1.0]]).unwrap();
        assert_eq!(view_reach(&scaled(1.0 / 3.0), rect), 3);
        assert_eq!(view_reach(&scaled(0.5), rect), 2);
        assert_eq!(view_reach(&scaled(0.8), rect), 1);
        assert_eq!(view_reach(&scaled(2.0), rect), 1);
        assert_eq!(view_reach(&scaled(0.05), rect), MAX_REACH);
    }

    /// A strip of view pixels beside an unseen region in the sky shows a trunk (a copied
    /// occluder). When the fill doubts them they are not the border the fallback's guide
    /// interpolates: the guide is sky. When it is sure of them they are the building, and
    /// the guide carries them in.
    #[test]
    fn the_fallback_guide_does_not_interpolate_from_doubted_view_pixels() {
        let (w, h) = (90, 70);
        let sky = [0.7, 0.8, 0.92];
        let strip = |x: usize, y: usize| (25..40).contains(&x) && (10..60).contains(&y);
        let region = |x: usize, y: usize| (40..70).contains(&x) && (10..60).contains(&y);
        let image = RgbF32::from_fn(w, h, |x, y| if strip(x, y) { [0.35, 0.25, 0.15] } else { sky });
        let hole = Mask::from_fn(w, h, |x, y| if region(x, y) { 255 } else { 0 });
        let provenance = Provenance::from_fn(w, h, |x, y| u16::from(strip(x, y)));
        let crop = Rect { x: 0, y: 0, width: w, height: h };
        // The guide's largest difference from the sky over the region.
        let off_sky_from = |sure: u8, from: Option<u8>| {
            let confidence = Confidence::from_fn(w, h, |x, y| if strip(x, y) { sure } else { 0 });
            let guide =
                fallback_guide(&image, &hole, crop, &provenance, &confidence, from, &BlendParams::default())
                    .expect("the region has a border");
            (0..w * h)
                .filter(|&i| region(i % w, i / w))
                .map(|i| (0..3).map(|c| (guide.as_slice()[i][c] - sky[c]).abs()).fold(0.0f32, f32::max))
                .fold(0.0f32, f32::max)
        };
        let off_sky = |sure: u8| off_sky_from(sure, FillParams::default().fallback_guide_from);
        let (doubted, sure) = (off_sky(20), off_sky(220));
        assert!(doubted < 0.01, "doubted strip: the guide is {doubted:.3} off the sky");
        // Fairly sure guides by default; from `CONFIDENT` (a walk's guide), it does not.
        let fairly = off_sky_from(CONFIDENT - 28, Some(CONFIDENT));
        assert!(
            fairly < 0.01,
            "a strip the fill is only fairly sure of: the guide is {fairly:.3} off the sky"
        );
        assert!(off_sky(CONFIDENT - 28) > 0.2, "by default a fairly sure strip guides");
        assert!(sure > 0.2, "a strip the fill is sure of should be carried in: {sure:.3}");
        // Told to take no view pixel, not even one the fill is sure of.
        let none = off_sky_from(220, None);
        assert!(none < 0.01, "with no view pixel on the border the guide is {none:.3} off the sky");
    }

    /// A 160 × 120 facade, and the keyframe of it with a person painted in and masked:
    /// (facade, keyframe, mask).
    fn person_before_facade() -> (RgbF32, RgbF32, Mask) {
        let scene = facade(160, 120, 5);
        let mut key = scene.clone();
        let mut mask = Mask::new(160, 120, 0);
        paint_occluder(&mut key, Some(&mut mask), Occluder::Person, 80.0, 65.0, 60.0, 2);
        (scene, key, mask)
    }

    /// Each of `images` (keyframe-sized) seen through its keyframe → view map in `hs`, at
    /// the keyframe's size.
    fn rendered_views(images: &[&RgbF32], hs: &[Homography]) -> Vec<RgbF32> {
        images
            .iter()
            .zip(hs)
            .map(|(img, hm)| render_view(img, &hm.inverse().unwrap(), img.width(), img.height(), [0.5; 3]))
            .collect()
    }

    /// Per view (keyframe → view a translation, `hs`), view-sized occluder marks: `level(v,
    /// x, y)` at keyframe pixel (x, y).
    fn marks_in_views(
        hs: &[Homography],
        w: usize,
        h: usize,
        level: impl Fn(usize, usize, usize) -> u8,
    ) -> Vec<Mask> {
        hs.iter()
            .enumerate()
            .map(|(v, hm)| {
                let t = hm.rows();
                Mask::from_fn(w, h, |x, y| {
                    let (kx, ky) =
                        ((x as f64 - t[0][2]).round() as usize, (y as f64 - t[1][2]).round() as usize);
                    level(v, kx, ky)
                })
            })
            .collect()
    }

    /// Two views of a facade, each with its own occluder marked (`FillExtras::occluders`)
    /// over part of the keyframe's hole: over the left block only the first is marked, over
    /// the right block both. A marked pixel is never copied where the other view sees it
    /// clear; where both are marked it goes to the fallback.
    #[test]
    fn a_pixel_every_view_marks_as_its_occluder_is_never_copied() {
        let (scene, key, mask) = person_before_facade();
        let (w, h) = (key.width(), key.height());
        let hs = [Homography::translation(4.0, -2.0), Homography::translation(-3.0, 1.0)];
        let views: Vec<RgbF32> =
            hs.iter().map(|hm| render_view(&scene, &hm.inverse().unwrap(), w, h, [0.5; 3])).collect();
        let sources: Vec<Source<'_>> =
            views.iter().zip(&hs).map(|(image, &homography)| Source { image, homography }).collect();
        // Keyframe blocks: left [60, 80), right [80, 100), rows [40, 90).
        let left = |x: usize, y: usize| (60..80).contains(&x) && (40..90).contains(&y);
        let right = |x: usize, y: usize| (80..100).contains(&x) && (40..90).contains(&y);
        let marks =
            marks_in_views(&hs, w, h, |v, x, y| if right(x, y) || (v == 0 && left(x, y)) { 255 } else { 0 });
        let occluders: Vec<Option<&Mask>> = marks.iter().map(Some).collect();
        let extras = FillExtras { occluders: &occluders, ..FillExtras::default() };
        let hole = mask.as_slice();
        let in_hole = |f: &dyn Fn(usize, usize) -> bool| {
            (0..w * h).filter(|&i| f(i % w, i / w) && hole[i] > 127).collect::<Vec<_>>()
        };
        let (left_px, right_px) = (in_hole(&left), in_hole(&right));
        assert!(left_px.len() > 300 && right_px.len() > 300, "the blocks are in the hole");
        let f = fill_with(&key, &mask, &sources, &extras, &FillParams::default(), 3, &mut ());
        let p = f.provenance.as_slice();
        let from = |v: u16, px: &[usize]| px.iter().filter(|&&i| p[i] == v).count() as f64 / px.len() as f64;
        // Sources are numbered from 1 in the provenance.
        assert!(from(1, &left_px) < 0.02, "the first view's marked pixels were copied");
        assert!(from(2, &left_px) > 0.95, "the second view sees the left block clear");
        let fallback = from(FALLBACK, &right_px);
        assert!(fallback > 0.95, "both marked: {fallback:.2} to the fallback");
    }

    /// A soft mark (a frame's own judgement revised, as a walk makes them) over a block of
    /// the hole both views mark: the softly marked view's pixels are copied rather than
    /// invented, but never reported sure. Where that view shows the keyframe's own occluder
    /// (the same person at the same place), or something of a colour the facade has
    /// nowhere (a magenta van), they are not copied even with the occlusion model off: the
    /// fallback makes them.
    #[test]
    fn a_soft_mark_is_copied_where_every_view_is_marked_unless_it_shows_an_occluder() {
        let (scene, key, mask) = person_before_facade();
        let (w, h) = (key.width(), key.height());
        let mut person = Mask::new(w, h, 0);
        let mut with_person = scene.clone();
        paint_occluder(&mut with_person, Some(&mut person), Occluder::Person, 80.0, 65.0, 60.0, 2);
        let block = |x: usize, y: usize| (70..90).contains(&x) && (45..85).contains(&y);
        let block_px: Vec<usize> = (0..w * h)
            .filter(|&i| block(i % w, i / w) && mask.as_slice()[i] > 127 && person.as_slice()[i] > 127)
            .collect();
        assert!(block_px.len() > 300, "the block is on the person, in the hole");
        let hs = [Homography::translation(4.0, -2.0), Homography::translation(-3.0, 1.0)];
        // View 0 softly marked over the block, view 1 wholly.
        let marks = marks_in_views(&hs, w, h, |v, x, y| match (block(x, y), v) {
            (false, _) => 0,
            (true, 0) => 160,
            (true, _) => 255,
        });
        let occluders: Vec<Option<&Mask>> = marks.iter().map(Some).collect();
        let extras = FillExtras { occluders: &occluders, ..FillExtras::default() };
        let fill = |first: &RgbF32, params: &FillParams| {
            let views = rendered_views(&[first, &scene], &hs);
            let sources: Vec<Source<'_>> =
                views.iter().zip(&hs).map(|(image, &homography)| Source { image, homography }).collect();
            fill_with(&key, &mask, &sources, &extras, params, 3, &mut ())
        };
        let share = |of: &dyn Fn(usize) -> bool| {
            block_px.iter().filter(|&&i| of(i)).count() as f64 / block_px.len() as f64
        };
        // View 0 shows the wall there: copied, and doubtful.
        let f = fill(&scene, &FillParams::default());
        let (p, c) = (f.provenance.as_slice(), f.confidence.as_slice());
        let copied = share(&|i| p[i] == 1);
        assert!(copied > 0.9, "the softly marked view's wall: {copied:.2} copied");
        let sure = share(&|i| p[i] == 1 && c[i] >= CONFIDENT);
        assert_eq!(sure, 0.0, "a softly marked pixel reported sure");
        // View 0 shows the keyframe's person there, or a van of its own: not copied, the
        // model off or on.
        let mut with_van = scene.clone();
        for y in 35..95 {
            for x in 60..100 {
                with_van.set(x, y, [0.75, 0.1, 0.65]);
            }
        }
        for (first, what) in [(&with_person, "the keyframe's own person"), (&with_van, "a magenta van")] {
            for occlusion in [false, true] {
                let params = FillParams { occlusion, ..FillParams::default() };
                let f = fill(first, &params);
                let p = f.provenance.as_slice();
                let copied = share(&|i| p[i] == 1);
                assert!(copied < 0.05, "{what}, model {occlusion}: {copied:.2} copied");
            }
        }
    }

    /// A generous mask (the person grown by 6 px, as a walk's masks are) that every view
    /// marks: the second view wholly, the first softly over the person and faintly on a rim
    /// past it (as a walk's frame is marked). The first view shows what the keyframe shows.
    /// On the rim it is the wall, copied (doubtful) rather than invented; on the person it
    /// is the keyframe's own occluder, refused. Marked softly on the rim too, the wall there
    /// is refused as the person is.
    #[test]
    fn a_faint_mark_like_the_keyframe_in_the_masks_margin_is_copied() {
        let scene = facade(160, 120, 5);
        let (w, h) = (scene.width(), scene.height());
        let mut key = scene.clone();
        let mut person = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut person), Occluder::Person, 80.0, 65.0, 60.0, 2);
        let mask = crate::synth::dilate_mask(&person, 6);
        let rim = crate::synth::dilate_mask(&person, 7);
        let (hole, on_person) = (mask.as_slice(), person.as_slice());
        let margin_px: Vec<usize> = (0..w * h).filter(|&i| hole[i] > 127 && on_person[i] <= 127).collect();
        let person_px: Vec<usize> = (0..w * h).filter(|&i| on_person[i] > 127).collect();
        assert!(margin_px.len() > 500 && person_px.len() > 500, "a margin and a person in the hole");
        let hs = [Homography::translation(4.0, -2.0), Homography::translation(-3.0, 1.0)];
        let views = rendered_views(&[&key, &scene], &hs);
        let sources: Vec<Source<'_>> =
            views.iter().zip(&hs).map(|(image, &homography)| Source { image, homography }).collect();
        let at =
            |m: &Mask, x: usize, y: usize| m.get_checked(x as isize, y as isize).is_some_and(|l| l > 127);
        let fill = |rim_level: u8| {
            let marks = marks_in_views(&hs, w, h, |v, x, y| match (v, at(&person, x, y), at(&rim, x, y)) {
                (_, false, false) => 0,
                (0, true, _) => 160,
                (0, false, true) => rim_level,
                _ => 255,
            });
            let occluders: Vec<Option<&Mask>> = marks.iter().map(Some).collect();
            let extras = FillExtras { occluders: &occluders, ..FillExtras::default() };
            fill_with(&key, &mask, &sources, &extras, &FillParams::default(), 3, &mut ())
        };
        let share = |px: &[usize], of: &dyn Fn(usize) -> bool| {
            px.iter().filter(|&&i| of(i)).count() as f64 / px.len() as f64
        };
        let f = fill(FAINT_MARK);
        let (p, c) = (f.provenance.as_slice(), f.confidence.as_slice());
        let copied = share(&margin_px, &|i| p[i] == 1);
        assert!(copied > 0.8, "the wall under a faint mark: {copied:.2} copied");
        let sure = share(&margin_px, &|i| p[i] == 1 && c[i] >= CONFIDENT);
        assert_eq!(sure, 0.0, "a lifted pixel reported sure");
        let person_copied = share(&person_px, &|i| p[i] == 1);
        assert!(person_copied < 0.05, "the keyframe's own person: {person_copied:.2} copied");
        let f = fill(160);
        let p = f.provenance.as_slice();
        let copied = share(&margin_px, &|i| p[i] == 1);
        assert!(copied < 0.3, "the wall under a soft mark: {copied:.2} copied");
    }

    /// The colours a lifted pixel is judged foreign to ([`LIFTED_FOREIGN_REACH`] around the
    /// part) lie inside the crop the service fills, so that the service and `clearview
    /// fill` hear the same ones.
    #[test]
    fn the_building_around_a_lifted_mark_lies_inside_the_services_crop() {
        let session = crate::session::SessionParams::default();
        let (part, crop) = (session.fill.margin() + 1, session.margin_px);
        assert!(part + LIFTED_FOREIGN_REACH <= crop, "{part} + {LIFTED_FOREIGN_REACH} > {crop}");
    }

    #[test]
    fn eight_bit_sources_fill_exactly_as_their_f32_copies() {
        let (w, h) = (160, 120);
        let scene = facade(w, h, 5);
        let mut key = scene.clone();
        let mut mask = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut mask), Occluder::Person, 80.0, 65.0, 60.0, 2);
        let hs = [
            Homography::translation(4.5, -2.0),
            Homography::from_rows([[1.02, 0.01, -3.0], [-0.01, 0.99, 2.5], [1e-5, 0.0, 1.0]]).unwrap(),
        ];
        let views8: Vec<Rgb8> = hs
            .iter()
            .map(|hm| {
                let v = render_view(&scene, &hm.inverse().unwrap(), w, h, [0.5; 3]);
                v.map(|p| p.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8))
            })
            .collect();
        let views: Vec<RgbF32> = views8.iter().map(|v| v.map(|p| p.map(|c| c as f32 / 255.0))).collect();
        let s8: Vec<Source<'_, [u8; 3]>> =
            views8.iter().zip(&hs).map(|(image, &homography)| Source { image, homography }).collect();
        let s32: Vec<Source<'_>> =
            views.iter().zip(&hs).map(|(image, &homography)| Source { image, homography }).collect();
        let params = FillParams::default();
        let (a, b) =
            (fill(&key, &mask, &s8, &params, 3, &mut ()), fill(&key, &mask, &s32, &params, 3, &mut ()));
        assert!(a.report.from_views() > 0.9, "{:?}", a.report);
        assert_eq!(a.report, b.report);
        assert!(a.provenance == b.provenance && a.image == b.image, "the 8-bit fill differs");
        let am = AutoMaskParams { min_views: 2, ..AutoMaskParams::default() };
        assert!(auto_mask(&key, &s8, &am) == auto_mask(&key, &s32, &am));
    }
}
