//! Image pyramids: half-octave levels for scale-aware features, and fast 2× reduction
//! for coarse-to-fine alignment (pure layer).

use rayon::prelude::*;

use super::{GrayF32, bilinear_clamped, filter};

/// Halves an image with the 5-tap binomial filter (1 4 6 4 1)/16 in each direction.
pub fn half(src: &GrayF32) -> GrayF32 {
    let (w, h) = (src.width(), src.height());
    let (nw, nh) = (w.div_ceil(2).max(1), h.div_ceil(2).max(1));
    const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    // Vertical pass on the rows we keep, then horizontal decimation.
    let mut out = GrayF32::new(nw, nh, 0.0);
    out.as_mut_slice().par_chunks_mut(nw).enumerate().for_each_init(
        || vec![0.0f32; w],
        |col, (ny, dst)| {
            col.iter_mut().for_each(|v| *v = 0.0);
            let y = 2 * ny;
            for (i, k) in K.iter().enumerate() {
                let yy = (y as isize + i as isize - 2).clamp(0, h as isize - 1) as usize;
                for (c, s) in col.iter_mut().zip(src.row(yy)) {
                    *c += k * s;
                }
            }
            // Interior without index clamping (the taps of output nx are 2nx−2..=2nx+2),
            // then the few border outputs with it.
            let clamped = |nx: usize| {
                let x = 2 * nx as isize;
                K.iter()
                    .enumerate()
                    .map(|(i, k)| k * col[(x + i as isize - 2).clamp(0, w as isize - 1) as usize])
                    .sum::<f32>()
            };
            let inner = if w >= 5 { 1..(w - 3) / 2 + 1 } else { 0..0 };
            for (nx, d) in dst.iter_mut().enumerate() {
                *d = if inner.contains(&nx) {
                    let c = &col[2 * nx - 2..2 * nx + 3];
                    K[0] * c[0] + K[1] * c[1] + K[2] * c[2] + K[3] * c[3] + K[4] * c[4]
                } else {
                    clamped(nx)
                };
            }
        },
    );
    out
}

/// Resamples by `factor` (< 1 shrinks) with a Gaussian pre-filter against aliasing.
/// Pixel centres map as `x_out = x_in · factor`.
pub fn scale(src: &GrayF32, factor: f32) -> GrayF32 {
    let nw = ((src.width() as f32 * factor).round() as usize).max(1);
    let nh = ((src.height() as f32 * factor).round() as usize).max(1);
    let blurred;
    let from = if factor < 1.0 {
        // σ chosen so the blur roughly matches the new sampling rate.
        let sigma = 0.5 * (1.0 / (factor * factor) - 1.0).sqrt();
        blurred = filter::gaussian_blur(src, sigma.max(0.3));
        &blurred
    } else {
        src
    };
    let inv = 1.0 / factor;
    let mut out = GrayF32::new(nw, nh, 0.0);
    out.as_mut_slice().par_chunks_mut(nw).enumerate().for_each(|(y, row)| {
        for (x, d) in row.iter_mut().enumerate() {
            *d = bilinear_clamped(from, x as f32 * inv, y as f32 * inv);
        }
    });
    out
}

/// A scale pyramid: `levels[i]` is the image shrunk by `scales[i]` (1, √2, 2, 2√2, …).
#[derive(Debug, Clone)]
pub struct Pyramid {
    pub levels: Vec<GrayF32>,
    /// How many base-image pixels one pixel of each level spans.
    pub scales: Vec<f32>,
}

impl Pyramid {
    /// Half-octave pyramid until the shorter side would drop below `min_side` pixels or
    /// `max_levels` levels exist.
    pub fn half_octaves(base: GrayF32, max_levels: usize, min_side: usize) -> Self {
        let mut levels = Vec::new();
        let mut scales = Vec::new();
        let odd = if max_levels > 1 { Some(scale(&base, std::f32::consts::FRAC_1_SQRT_2)) } else { None };
        let mut even = Some(base);
        let mut odd = odd;
        let mut s = 1.0f32;
        while levels.len() < max_levels {
            let Some(e) = even.take() else { break };
            if e.width().min(e.height()) < min_side {
                break;
            }
            let next_even = half(&e);
            levels.push(e);
            scales.push(s);
            if levels.len() >= max_levels {
                break;
            }
            if let Some(o) = odd.take() {
                if o.width().min(o.height()) < min_side {
                    break;
                }
                let next_odd = half(&o);
                levels.push(o);
                scales.push(s * std::f32::consts::SQRT_2);
                odd = Some(next_odd);
            }
            even = Some(next_even);
            s *= 2.0;
        }
        Self { levels, scales }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_keeps_a_ramp_aligned() {
        let ramp = GrayF32::from_fn(64, 32, |x, _| x as f32);
        let h = half(&ramp);
        assert_eq!((h.width(), h.height()), (32, 16));
        // Pixel n of the half image sits on pixel 2n of the source.
        assert!((h.get(10, 5) - 20.0).abs() < 1e-4);
    }

    #[test]
    fn half_octave_scales() {
        let img = GrayF32::from_fn(256, 200, |x, y| ((x ^ y) & 15) as f32);
        let p = Pyramid::half_octaves(img, 5, 16);
        assert_eq!(p.levels.len(), 5);
        for (l, s) in p.levels.iter().zip(&p.scales) {
            assert!((l.width() as f32 * s - 256.0).abs() < 2.0 * s, "{} {}", l.width(), s);
        }
    }
}
