//! The automatic mask: pixels where the keyframe disagrees with the consensus of the
//! aligned views are transient occluders (pure layer).

use super::Source;
use crate::imaging::{Mask, RgbF32};

/// Parameters of [`auto_mask`].
#[derive(Debug, Clone, PartialEq)]
pub struct AutoMaskParams {
    /// At least this many views must see a pixel (and agree) to judge it.
    pub min_views: usize,
}

impl Default for AutoMaskParams {
    fn default() -> Self {
        Self { min_views: 2 }
    }
}

/// The mask of transient objects in `key` (255 = fill), judged against `sources`.
pub fn auto_mask(key: &RgbF32, sources: &[Source<'_>], params: &AutoMaskParams) -> Mask {
    // Placeholder: nothing is masked. Replaced by the consensus test.
    let _ = (sources, params);
    Mask::new(key.width(), key.height(), 0)
}
