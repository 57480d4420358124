//! Correspondences between keyframe and view (the paper's step 2): putative matches by
//! SSD of normalised patches with a ratio test and mutual check, and guided matching that
//! searches a small window around where a homography predicts each point (pure layer).

use nalgebra::Point2;
use rayon::prelude::*;

use super::descriptor::{Descriptor, LEN, normalise};
use crate::geometry::{Correspondence, Homography};
use crate::imaging::{GrayF32, bilinear};

/// Parameters of [`match_descriptors`].
#[derive(Debug, Clone, PartialEq)]
pub struct MatchParams {
    /// Keep a match only if its patch distance is below this share of the second best's
    /// (Lowe's ratio test on `√SSD`).
    pub max_ratio: f32,
    /// Keep a match only if each side is the other's best.
    pub mutual: bool,
    /// Largest accepted SSD of two unit-norm patches (0 = identical, 2 = unrelated,
    /// 4 = inverted).
    pub max_ssd: f32,
}

impl Default for MatchParams {
    fn default() -> Self {
        Self { max_ratio: 0.85, mutual: true, max_ssd: 1.0 }
    }
}

/// A putative match: indices into the two descriptor lists and its SSD.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    pub key: usize,
    pub view: usize,
    pub ssd: f32,
}

/// Best-match search between two descriptor sets by SSD (as `2 − 2·dot` of unit-norm
/// patches), with the ratio test and, optionally, the mutual check.
///
/// All dot products come from one matrix product (a tuned, vectorised GEMM), then one
/// pass over rows and one over columns.
pub fn match_descriptors(key: &[Descriptor], view: &[Descriptor], params: &MatchParams) -> Vec<Match> {
    if key.is_empty() || view.len() < 2 {
        return Vec::new();
    }
    let (nk, nv) = (key.len(), view.len());
    // dots[i * nv + j] = key i · view j: each key's scores are one contiguous row.
    let mut dots = vec![0.0f32; nk * nv];
    let a = key.as_flattened();
    let b = view.as_flattened();
    // SAFETY: `a` is nk×LEN row-major (row stride LEN), `b` read as LEN×nv through strides
    // (1, LEN), `dots` nk×nv row-major; all three slices hold exactly those many elements.
    unsafe {
        matrixmultiply::sgemm(
            nk,
            LEN,
            nv,
            1.0,
            a.as_ptr(),
            LEN as isize,
            1,
            b.as_ptr(),
            1,
            LEN as isize,
            0.0,
            dots.as_mut_ptr(),
            nv as isize,
            1,
        );
    }
    let rows: Vec<(usize, f32, f32)> = dots
        .par_chunks(nv)
        .map(|row| {
            let (mut best, mut b1, mut b2) = (0, f32::MIN, f32::MIN);
            for (j, &d) in row.iter().enumerate() {
                if d > b2 {
                    if d > b1 {
                        b2 = b1;
                        b1 = d;
                        best = j;
                    } else {
                        b2 = d;
                    }
                }
            }
            (best, b1, b2)
        })
        .collect();
    let column_best: Vec<usize> = if params.mutual {
        let mut best = vec![(usize::MAX, f32::MIN); nv];
        for (i, col) in dots.chunks(nv).enumerate() {
            for (slot, &d) in best.iter_mut().zip(col) {
                if d > slot.1 {
                    *slot = (i, d);
                }
            }
        }
        best.into_iter().map(|(i, _)| i).collect()
    } else {
        Vec::new()
    };
    let ratio_sq = params.max_ratio * params.max_ratio;
    rows.iter()
        .enumerate()
        .filter_map(|(i, &(j, b1, b2))| {
            let (ssd1, ssd2) = ((2.0 - 2.0 * b1).max(0.0), (2.0 - 2.0 * b2).max(0.0));
            let passes = ssd1 <= params.max_ssd && ssd1 < ratio_sq * ssd2;
            let mutual = !params.mutual || column_best[j] == i;
            (passes && mutual).then_some(Match { key: i, view: j, ssd: ssd1 })
        })
        .collect()
}

/// Parameters of [`guided_match`].
#[derive(Debug, Clone, PartialEq)]
pub struct GuidedParams {
    /// The template is `(2·radius + 1)²` samples.
    pub radius: usize,
    /// Integer shifts up to this many samples are searched in each direction.
    pub search: usize,
    /// Normalised cross-correlation a match must reach.
    pub min_ncc: f32,
}

impl Default for GuidedParams {
    fn default() -> Self {
        Self { radius: 7, search: 4, min_ncc: 0.8 }
    }
}

/// Octave pyramid of one image: `octaves[o]` is the image halved `o` times.
pub type Octaves = [GrayF32];

/// For each keyframe point, the view point it shows, found by a local search around
/// where `h` predicts it (the paper's "SSD within the selected area", on zero-mean,
/// normalised patches so exposure changes do not matter).
///
/// The view patch is resampled through `h` into the keyframe's geometry, so rotation,
/// zoom and perspective are undone before comparing; each point is matched at the
/// octaves where one key sample spans about one view pixel, starting at `octave` of the
/// key. Points whose best match is weak, ambiguous or on the border of the search window
/// are left out.
pub fn guided_match(
    key: &Octaves,
    view: &Octaves,
    points: &[Point2<f64>],
    h: &Homography,
    octave: usize,
    params: &GuidedParams,
) -> Vec<Correspondence> {
    points.par_iter().filter_map(|&p| match_one(key, view, p, h, octave, params)).collect()
}

fn match_one(
    key: &Octaves,
    view: &Octaves,
    p: Point2<f64>,
    h: &Homography,
    octave: usize,
    params: &GuidedParams,
) -> Option<Correspondence> {
    let j = h.jacobian(p);
    let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
    if det.is_nan() || det <= 0.0 || h.w(p) <= 0.0 {
        return None;
    }
    // log2 of the local zoom key → view.
    let zoom = 0.5 * det.log2();
    let (ok, ov) = if zoom >= 0.0 {
        (octave, octave + zoom.round() as usize)
    } else {
        (octave + (-zoom).round() as usize, octave)
    };
    let (ok, ov) = (ok.min(key.len() - 1), ov.min(view.len() - 1));
    let key_img = &key[ok];
    let view_img = &view[ov];
    let step = (1u32 << ok) as f64;
    let view_scale = 1.0 / (1u32 << ov) as f64;

    let r = params.radius as isize;
    let s = params.search as isize;
    let side = (2 * r + 1) as usize;
    let big = (2 * (r + s) + 1) as usize;

    // Template from the key at its octave.
    let (kx, ky) = (p.x / step, p.y / step);
    let mut t = Vec::with_capacity(side * side);
    for dy in -r..=r {
        for dx in -r..=r {
            t.push(bilinear(key_img, (kx + dx as f64) as f32, (ky + dy as f64) as f32)?);
        }
    }
    if !normalise(&mut t) {
        return None;
    }
    // View samples over the template plus the search margin, through h.
    let mut v = Vec::with_capacity(big * big);
    for dy in -(r + s)..=(r + s) {
        for dx in -(r + s)..=(r + s) {
            let q = Point2::new(p.x + dx as f64 * step, p.y + dy as f64 * step);
            let m = h.apply(q)?;
            v.push(bilinear(view_img, (m.x * view_scale) as f32, (m.y * view_scale) as f32)?);
        }
    }
    // NCC at every integer shift.
    let n = (side * side) as f32;
    let shifts = (2 * s + 1) as usize;
    let mut scores = vec![f32::MIN; shifts * shifts];
    for sy in 0..shifts {
        for sx in 0..shifts {
            let (mut sum, mut sum2, mut cross) = (0.0f32, 0.0f32, 0.0f32);
            for ty in 0..side {
                let row = &v[(sy + ty) * big + sx..(sy + ty) * big + sx + side];
                let trow = &t[ty * side..(ty + 1) * side];
                for (a, b) in row.iter().zip(trow) {
                    sum += a;
                    sum2 += a * a;
                    cross += a * b;
                }
            }
            let var = sum2 - sum * sum / n;
            // The template has zero mean and unit norm, so the cross term needs no mean
            // correction.
            scores[sy * shifts + sx] = if var > 1e-12 { cross / var.sqrt() } else { f32::MIN };
        }
    }
    let (best, &score) = scores.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
    let (bx, by) = (best % shifts, best / shifts);
    if score < params.min_ncc || bx == 0 || by == 0 || bx == shifts - 1 || by == shifts - 1 {
        return None;
    }
    let fit = |m: f32, c: f32, p: f32| {
        let denom = m - 2.0 * c + p;
        if denom < 0.0 { (0.5 * (m - p) / denom).clamp(-0.5, 0.5) } else { 0.0 }
    };
    let ox = fit(scores[best - 1], score, scores[best + 1]);
    let oy = fit(scores[best - shifts], score, scores[best + shifts]);
    let dx = (bx as f32 - s as f32 + ox) as f64 * step;
    let dy = (by as f32 - s as f32 + oy) as f64 * step;
    let matched = h.apply(Point2::new(p.x + dx, p.y + dy))?;
    Some(Correspondence::new(p, matched))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(seed: u32) -> Descriptor {
        let mut d = [0.0f32; 64];
        let mut s = seed.wrapping_mul(2654435761).wrapping_add(1);
        for v in &mut d {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            *v = (s % 1000) as f32 / 1000.0;
        }
        assert!(normalise(&mut d));
        d
    }

    #[test]
    fn identical_descriptors_match_each_other() {
        let a: Vec<_> = (0..50).map(unit).collect();
        let mut b = a.clone();
        b.reverse();
        let matches = match_descriptors(&a, &b, &MatchParams::default());
        assert_eq!(matches.len(), 50);
        assert!(matches.iter().all(|m| m.view == 49 - m.key && m.ssd < 1e-5));
    }

    #[test]
    fn ambiguous_descriptors_fail_the_ratio_test() {
        let a = vec![unit(1)];
        let b = vec![unit(1), unit(1)];
        assert!(match_descriptors(&a, &b, &MatchParams::default()).is_empty());
    }

    #[test]
    fn guided_matching_corrects_a_wrong_prediction() {
        let img = GrayF32::from_fn(120, 120, |x, y| {
            let (xf, yf) = (x as f32, y as f32);
            0.5 + 0.3 * (xf * 0.21).sin() * (yf * 0.17).cos() + 0.2 * (((x / 5) + (y / 3)) % 2) as f32
        });
        // The view is the key shifted by (2.4, −1.7); the prediction says identity.
        let view =
            GrayF32::from_fn(120, 120, |x, y| bilinear(&img, x as f32 - 2.4, y as f32 + 1.7).unwrap_or(0.0));
        let pts = [Point2::new(60.0, 60.0), Point2::new(40.0, 70.0)];
        let c = guided_match(
            std::slice::from_ref(&img),
            std::slice::from_ref(&view),
            &pts,
            &Homography::identity(),
            0,
            &GuidedParams::default(),
        );
        assert_eq!(c.len(), 2);
        for m in c {
            let d = m.view - m.key;
            assert!((d.x - 2.4).abs() < 0.15 && (d.y + 1.7).abs() < 0.15, "{d:?}");
        }
    }
}
