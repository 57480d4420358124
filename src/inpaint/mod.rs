//! The fill: the keyframe's masked region re-inpainted from what the aligned views saw
//! there (the paper's section 4, steps 3–7), with a single-image fallback for what no view
//! saw (pure layer).
//!
//! [`fill`] is the whole of it; the submodules are its stages. Nothing here reads a file
//! or a clock: stage changes and progress are reported to an [`Observer`] that the edge
//! (CLI progress bar, daemon timings) supplies.

pub mod automask;
pub mod exemplar;
pub mod region;

use crate::geometry::Homography;
use crate::imaging::{Mask, Plane, RgbF32};

pub use automask::{AutoMaskParams, auto_mask};
pub use exemplar::{ExemplarParams, exemplar_fill};

/// Where each pixel of a result came from: [`KEYFRAME`] outside the mask, [`FALLBACK`]
/// for the single-image fallback, otherwise `1 + i` for `sources[i]`.
pub type Provenance = Plane<u16>;
/// A pixel the keyframe itself provides (outside the mask).
pub const KEYFRAME: u16 = 0;
/// A masked pixel no view could fill: the single-image fallback made it.
pub const FALLBACK: u16 = u16::MAX;

/// One aligned view, as the fill sees it.
#[derive(Debug, Clone, Copy)]
pub struct Source<'a> {
    /// The view's pixels (RGB, 0..=1).
    pub image: &'a RgbF32,
    /// Maps keyframe pixel coordinates to this view's (ARCHITECTURE.md convention).
    pub homography: Homography,
}

/// The stages of [`fill`], in the order they run (for timings and progress).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stage {
    Warp,
    Photometric,
    Fill,
    Fallback,
    Blend,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Self::Warp => "warp",
            Self::Photometric => "photometric",
            Self::Fill => "fill",
            Self::Fallback => "fallback",
            Self::Blend => "blend",
        }
    }
}

/// Told what [`fill`] is doing; the edge times stages and draws progress with it.
pub trait Observer {
    /// A stage begins (the previous one, if any, has ended).
    fn stage(&mut self, _stage: Stage) {}
    /// `done` of `total` units of the current stage are finished.
    fn progress(&mut self, _done: usize, _total: usize) {}
}

/// An observer that ignores everything.
impl Observer for () {}

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
}

/// What a result is made of.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FillReport {
    /// Pixels the mask asked to fill.
    pub masked: usize,
    /// One entry per source, in the order given.
    pub sources: Vec<SourceReport>,
    /// Masked pixels the single-image fallback filled.
    pub fallback: usize,
}

impl FillReport {
    /// Share of the mask filled from real views (0..=1; 1 for an empty mask).
    pub fn from_views(&self) -> f64 {
        if self.masked == 0 {
            return 1.0;
        }
        self.sources.iter().map(|s| s.filled).sum::<usize>() as f64 / self.masked as f64
    }
}

/// Parameters of [`fill`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FillParams {
    pub exemplar: ExemplarParams,
}

/// A filled keyframe: the image, where each pixel came from, and the figures.
#[derive(Debug, Clone)]
pub struct Filled {
    pub image: RgbF32,
    pub provenance: Provenance,
    pub report: FillReport,
}

/// Fills the pixels of `key` that `mask` marks from `sources`, then what they could not
/// see by the single-image fallback. An empty mask returns `key` unchanged.
///
/// # Panics
/// If `mask` is not the size of `key` (the edge checks and reports that).
pub fn fill(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_>],
    params: &FillParams,
    seed: u64,
    observer: &mut dyn Observer,
) -> Filled {
    // Placeholder until the multi-view fill lands: everything from the fallback.
    assert_eq!((mask.width(), mask.height()), (key.width(), key.height()), "mask size");
    let _ = sources;
    observer.stage(Stage::Fallback);
    let mut image = key.clone();
    let masked = exemplar_fill(&mut image, mask, &params.exemplar, seed);
    let provenance = mask.map(|&m| if m > 127 { FALLBACK } else { KEYFRAME });
    let report =
        FillReport { masked, sources: vec![SourceReport::default(); sources.len()], fallback: masked };
    Filled { image, provenance, report }
}
