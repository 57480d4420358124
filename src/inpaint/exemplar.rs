//! The single-image fallback: exemplar-based inpainting (Criminisi et al. 2004) for the
//! pixels that no view saw (pure layer).

use crate::imaging::{Mask, RgbF32};

/// Parameters of [`exemplar_fill`].
#[derive(Debug, Clone, PartialEq)]
pub struct ExemplarParams {
    /// Patches are `(2·r + 1)²` pixels.
    pub patch_radius: usize,
}

impl Default for ExemplarParams {
    fn default() -> Self {
        Self { patch_radius: 4 }
    }
}

/// Fills the pixels of `image` that `hole` marks (> 127) from the image's own known
/// pixels; returns how many it filled. Pixels outside `hole` are never changed.
pub fn exemplar_fill(image: &mut RgbF32, hole: &Mask, params: &ExemplarParams, seed: u64) -> usize {
    // Placeholder: the mean of the known pixels. Replaced by Criminisi + PatchMatch.
    let _ = (params, seed);
    let (mut sum, mut n) = ([0.0f64; 3], 0usize);
    for (p, &m) in image.as_slice().iter().zip(hole.as_slice()) {
        if m <= 127 {
            for c in 0..3 {
                sum[c] += p[c] as f64;
            }
            n += 1;
        }
    }
    let mean = sum.map(|s| (s / n.max(1) as f64) as f32);
    let mut filled = 0;
    for (p, &m) in image.as_mut_slice().iter_mut().zip(hole.as_slice()) {
        if m > 127 {
            *p = mean;
            filled += 1;
        }
    }
    filled
}
