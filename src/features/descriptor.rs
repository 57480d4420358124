//! Oriented, scale-normalised patches around corners: what the paper's SSD compares,
//! sampled at the corner's pyramid scale and in its dominant gradient orientation so that
//! a rolled or zoomed view compares like with like (pure layer).

use rayon::prelude::*;

use super::harris::Corner;
use crate::imaging::pyramid::Pyramid;
use crate::imaging::{GrayF32, bilinear};

/// Samples per side of a descriptor patch.
pub const SIDE: usize = 8;
/// Length of a descriptor.
pub const LEN: usize = SIDE * SIDE;

/// A zero-mean, unit-norm patch: the SSD of two is `2 − 2·dot`, which is invariant to
/// gain and offset changes of the image (exposure).
pub type Descriptor = [f32; LEN];

/// Parameters of [`describe`].
#[derive(Debug, Clone, PartialEq)]
pub struct DescriptorParams {
    /// Distance between samples, in pixels of the corner's own level (the patch spans
    /// `SIDE × spacing` of them).
    pub spacing: f32,
    /// σ of the window over which the dominant orientation is measured, in pixels of the
    /// corner's level.
    pub orientation_sigma: f32,
    /// Skip orientation (all patches axis-aligned): faster, and more distinctive when the
    /// camera is known not to roll.
    pub upright: bool,
    /// With `upright`, every patch is sampled turned by this angle (radians) instead: the
    /// roll of the whole image, when it is known or being tried (the scale and roll search
    /// of [`crate::align`]).
    pub roll: f32,
}

impl Default for DescriptorParams {
    fn default() -> Self {
        Self { spacing: 4.0, orientation_sigma: 4.5, upright: false, roll: 0.0 }
    }
}

/// A described corner, in base-image coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    pub x: f32,
    pub y: f32,
    /// Base pixels per pixel of the level the corner was found in.
    pub scale: f32,
    /// Dominant gradient orientation, radians.
    pub angle: f32,
    pub response: f32,
    pub level: u8,
}

/// Describes the `corners` found in `pyramid.levels[level]`. Corners whose patch would
/// leave the image are dropped. The patch is sampled from the level one octave coarser
/// (two half-octave levels up), which is already smoothed for the sampling distance.
pub fn describe(
    pyramid: &Pyramid,
    level: usize,
    corners: &[Corner],
    params: &DescriptorParams,
) -> Vec<(Keypoint, Descriptor)> {
    let Some(source) = pyramid.levels.get(level + 2) else { return Vec::new() };
    let scale = pyramid.scales[level];
    // Level coordinates → source coordinates: the source is one octave coarser.
    let ratio = 0.5f32;
    let spacing = params.spacing * ratio;
    let sigma = params.orientation_sigma * ratio;
    let window = OrientationWindow::new(sigma);
    corners
        .par_iter()
        .filter_map(|c| {
            let (sx, sy) = (c.x * ratio, c.y * ratio);
            let angle = if params.upright { params.roll } else { orientation(source, sx, sy, &window)? };
            let d = sample(source, sx, sy, angle, spacing)?;
            let kp = Keypoint {
                x: c.x * scale,
                y: c.y * scale,
                scale,
                angle,
                response: c.response,
                level: level as u8,
            };
            Some((kp, d))
        })
        .collect()
}

/// The Gaussian weights of [`orientation`]'s window, computed once per call of
/// [`describe`] rather than once per sample.
struct OrientationWindow {
    r: isize,
    /// Row-major `(2r+1)²` weights.
    weights: Vec<f32>,
}

impl OrientationWindow {
    fn new(sigma: f32) -> Self {
        let r = (2.0 * sigma).ceil() as isize;
        let inv = -1.0 / (2.0 * sigma * sigma);
        let weights = (-r..=r)
            .flat_map(|dy| (-r..=r).map(move |dx| ((dx * dx + dy * dy) as f32 * inv).exp()))
            .collect();
        Self { r, weights }
    }
}

/// Direction of the Gaussian-weighted mean gradient around `(x, y)`; `None` near the
/// border or where the gradient vanishes.
fn orientation(img: &GrayF32, x: f32, y: f32, window: &OrientationWindow) -> Option<f32> {
    let r = window.r;
    let (cx, cy) = (x.round() as isize, y.round() as isize);
    let (w, h) = (img.width() as isize, img.height() as isize);
    if cx - r - 1 < 0 || cy - r - 1 < 0 || cx + r + 1 >= w || cy + r + 1 >= h {
        return None;
    }
    let side = (2 * r + 1) as usize;
    let (mut gx, mut gy) = (0.0f32, 0.0f32);
    for (j, weights) in window.weights.chunks_exact(side).enumerate() {
        let py = (cy - r) as usize + j;
        let (up, row, down) = (img.row(py - 1), img.row(py), img.row(py + 1));
        let x0 = (cx - r) as usize;
        for (i, &wgt) in weights.iter().enumerate() {
            let px = x0 + i;
            gx += wgt * (row[px + 1] - row[px - 1]);
            gy += wgt * (down[px] - up[px]);
        }
    }
    (gx * gx + gy * gy > 1e-12).then(|| gy.atan2(gx))
}

/// The `SIDE × SIDE` patch centred on `(x, y)`, rotated by `angle`, normalised to zero
/// mean and unit norm; `None` if it leaves the image or is flat.
fn sample(img: &GrayF32, x: f32, y: f32, angle: f32, spacing: f32) -> Option<Descriptor> {
    let (s, c) = angle.sin_cos();
    let mut d = [0.0f32; LEN];
    let half = (SIDE as f32 - 1.0) / 2.0;
    for j in 0..SIDE {
        for i in 0..SIDE {
            let u = (i as f32 - half) * spacing;
            let v = (j as f32 - half) * spacing;
            let px = x + c * u - s * v;
            let py = y + s * u + c * v;
            d[j * SIDE + i] = bilinear(img, px, py)?;
        }
    }
    normalise(&mut d).then_some(d)
}

/// Zero mean, unit norm; `false` for a flat patch.
pub fn normalise(d: &mut [f32]) -> bool {
    let n = d.len() as f32;
    let mean = d.iter().sum::<f32>() / n;
    d.iter_mut().for_each(|v| *v -= mean);
    let norm = d.iter().map(|v| v * v).sum::<f32>().sqrt();
    if norm < 1e-6 {
        return false;
    }
    d.iter_mut().for_each(|v| *v /= norm);
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::harris::{HarrisParams, harris};
    use crate::imaging::pyramid::Pyramid;

    fn textured(w: usize, h: usize) -> GrayF32 {
        GrayF32::from_fn(w, h, |x, y| {
            let (xf, yf) = (x as f32, y as f32);
            0.5 + 0.2 * (xf * 0.13).sin() * (yf * 0.07).cos()
                + 0.15 * ((xf * 0.031 + yf * 0.047).sin() > 0.3) as u8 as f32
                + 0.1 * (((x / 9) ^ (y / 7)) % 3) as f32
        })
    }

    #[test]
    fn descriptors_are_normalised() {
        let p = Pyramid::half_octaves(textured(200, 160), 4, 16);
        let corners = harris(&p.levels[0], &HarrisParams::default());
        let described = describe(&p, 0, &corners, &DescriptorParams::default());
        assert!(described.len() > 10);
        for (_, d) in described {
            assert!(d.iter().sum::<f32>().abs() < 1e-4);
            assert!((d.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn patches_match_across_a_rotation_of_the_image() {
        // The facade turned by 90°: descriptors must still find the same corners.
        let img = crate::imaging::convert::luminance(&crate::synth::facade(240, 200, 5));
        let (w, h) = (img.width(), img.height());
        // rot(x', y') = img(y', h − 1 − x'), a quarter turn.
        let rot = GrayF32::from_fn(h, w, |x, y| img.get(y, h - 1 - x));
        let features = |g: GrayF32| {
            let p = Pyramid::half_octaves(g, 4, 16);
            let corners = harris(&p.levels[0], &HarrisParams::default());
            describe(&p, 0, &corners, &DescriptorParams::default())
        };
        let (fa, fb) = (features(img), features(rot));
        let da: Vec<_> = fa.iter().map(|f| f.1).collect();
        let db: Vec<_> = fb.iter().map(|f| f.1).collect();
        let matches = crate::features::match_descriptors(&da, &db, &Default::default());
        let correct = matches
            .iter()
            .filter(|m| {
                let (a, b) = (fa[m.key].0, fb[m.view].0);
                // img (x, y) lands at rot (h − 1 − y, x).
                ((h - 1) as f32 - a.y - b.x).abs() < 2.0 && (a.x - b.y).abs() < 2.0
            })
            .count();
        assert!(correct >= 40, "{correct} correct of {} matches", matches.len());
        assert!(correct as f32 >= 0.8 * matches.len() as f32, "{correct} correct of {}", matches.len());
    }
}
