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
    // Rows are padded with zeros to whole SIMD chunks so the correlation below runs on
    // fixed-width chunks the compiler vectorises: template rows to `tw`, view rows to
    // `vw` (every shift's `tw`-wide slice stays inside its row).
    let tw = side.next_multiple_of(LANES);
    let vw = big - side + tw;

    // Template from the key at its octave.
    let (kx, ky) = (p.x / step, p.y / step);
    let mut t = vec![0.0f32; side * tw];
    sample_template(key_img, kx, ky, r, &mut t, tw)?;
    let mut valid = vec![0.0f32; side * side];
    for (dst, src) in valid.chunks_exact_mut(side).zip(t.chunks_exact(tw)) {
        dst.copy_from_slice(&src[..side]);
    }
    if !normalise(&mut valid) {
        return None;
    }
    for (dst, src) in t.chunks_exact_mut(tw).zip(valid.chunks_exact(side)) {
        dst[..side].copy_from_slice(src);
    }
    // View samples over the template plus the search margin, through h.
    let mut v = vec![0.0f32; big * vw];
    sample_view(view_img, h, p, r + s, step, view_scale, &mut v, vw)?;
    // Window sums of the view samples and their squares (summed-area tables, in f64 so
    // the variance keeps its digits).
    let n = (side * side) as f64;
    let stride = big + 1;
    let mut sat = vec![0.0f64; stride * stride];
    let mut sat2 = vec![0.0f64; stride * stride];
    for y in 0..big {
        let (mut row, mut row2) = (0.0f64, 0.0f64);
        for x in 0..big {
            let a = v[y * vw + x] as f64;
            row += a;
            row2 += a * a;
            sat[(y + 1) * stride + x + 1] = sat[y * stride + x + 1] + row;
            sat2[(y + 1) * stride + x + 1] = sat2[y * stride + x + 1] + row2;
        }
    }
    let window = |t: &[f64], x: usize, y: usize| {
        t[(y + side) * stride + x + side] - t[y * stride + x + side] - t[(y + side) * stride + x]
            + t[y * stride + x]
    };
    // NCC at every integer shift.
    let shifts = (2 * s + 1) as usize;
    let mut scores = vec![f32::MIN; shifts * shifts];
    for sy in 0..shifts {
        for sx in 0..shifts {
            let mut acc = [0.0f32; LANES];
            for ty in 0..side {
                let row = &v[(sy + ty) * vw + sx..][..tw];
                let trow = &t[ty * tw..][..tw];
                for (a, b) in row.chunks_exact(LANES).zip(trow.chunks_exact(LANES)) {
                    for k in 0..LANES {
                        acc[k] += a[k] * b[k];
                    }
                }
            }
            let cross: f32 = acc.iter().sum();
            let sum = window(&sat, sx, sy);
            let var = window(&sat2, sx, sy) - sum * sum / n;
            // The template has zero mean and unit norm, so the cross term needs no mean
            // correction.
            scores[sy * shifts + sx] = if var > 1e-12 { cross / (var.sqrt() as f32) } else { f32::MIN };
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

/// Lanes of the correlation's accumulators (two SSE or one AVX register of f32).
const LANES: usize = 8;

/// The `(2r+1)²` template centred on `(x, y)` of `img`, row `j` into `out[j * stride..]`;
/// `None` if it leaves the image. The offsets are whole pixels, so all samples share one
/// set of bilinear weights.
fn sample_template(img: &GrayF32, x: f64, y: f64, r: isize, out: &mut [f32], stride: usize) -> Option<()> {
    let side = (2 * r + 1) as usize;
    let (x0, y0) = (x - r as f64, y - r as f64);
    let (w, h) = (img.width() as f64, img.height() as f64);
    if x0 >= 0.0 && y0 >= 0.0 && x0.floor() + side as f64 <= w - 1.0 && y0.floor() + side as f64 <= h - 1.0 {
        let (ix, iy) = (x0.floor() as usize, y0.floor() as usize);
        let (fx, fy) = ((x0 - x0.floor()) as f32, (y0 - y0.floor()) as f32);
        for j in 0..side {
            let (top, bottom) =
                (&img.row(iy + j)[ix..ix + side + 1], &img.row(iy + j + 1)[ix..ix + side + 1]);
            for (i, o) in out[j * stride..j * stride + side].iter_mut().enumerate() {
                let t = top[i] + (top[i + 1] - top[i]) * fx;
                let b = bottom[i] + (bottom[i + 1] - bottom[i]) * fx;
                *o = t + (b - t) * fy;
            }
        }
        return Some(());
    }
    for j in 0..side {
        for i in 0..side {
            let (dx, dy) = (i as isize - r, j as isize - r);
            out[j * stride + i] = bilinear(img, (x + dx as f64) as f32, (y + dy as f64) as f32)?;
        }
    }
    Some(())
}

/// The view through `h` on the key's grid around `p`: sample `(i, j)` (row `j` into
/// `out[j * stride..]`) shows key point `p + ((i, j) − reach)·step`, read at
/// `view_scale` × its view position; `None` if any sample leaves the view.
#[allow(clippy::too_many_arguments)]
fn sample_view(
    img: &GrayF32,
    h: &Homography,
    p: Point2<f64>,
    reach: isize,
    step: f64,
    view_scale: f64,
    out: &mut [f32],
    stride: usize,
) -> Option<()> {
    let side = (2 * reach + 1) as usize;
    let key_at =
        |i: isize, j: isize| Point2::new(p.x + (i - reach) as f64 * step, p.y + (j - reach) as f64 * step);
    // The window is a square and h keeps it in front of the camera (w > 0 at its corners,
    // so everywhere in it), so its image is the convex hull of the corners' images: if
    // those are inside (with a margin for rounding), every sample is.
    let (w, hgt) = (img.width() as f64, img.height() as f64);
    let inside =
        [(0, 0), (side as isize - 1, 0), (0, side as isize - 1), (side as isize - 1, side as isize - 1)]
            .iter()
            .all(|&(i, j)| {
                let q = key_at(i, j);
                h.w(q) > 1e-9
                    && h.apply(q).is_some_and(|m| {
                        let (x, y) = (m.x * view_scale, m.y * view_scale);
                        x >= 0.5 && y >= 0.5 && x <= w - 2.5 && y <= hgt - 2.5
                    })
            });
    if !inside {
        for j in 0..side {
            for i in 0..side {
                let m = h.apply(key_at(i as isize, j as isize))?;
                out[j * stride + i] = bilinear(img, (m.x * view_scale) as f32, (m.y * view_scale) as f32)?;
            }
        }
        return Some(());
    }
    let m = h.matrix();
    let (iw, data) = (img.width(), img.as_slice());
    for j in 0..side {
        let q = key_at(0, j as isize);
        let mut hx = m[(0, 0)] * q.x + m[(0, 1)] * q.y + m[(0, 2)];
        let mut hy = m[(1, 0)] * q.x + m[(1, 1)] * q.y + m[(1, 2)];
        let mut hw = m[(2, 0)] * q.x + m[(2, 1)] * q.y + m[(2, 2)];
        let (dx, dy, dw) = (m[(0, 0)] * step, m[(1, 0)] * step, m[(2, 0)] * step);
        for o in &mut out[j * stride..j * stride + side] {
            let inv = view_scale / hw;
            let (x, y) = ((hx * inv) as f32, (hy * inv) as f32);
            // In range by the check above, so the cheaper i32 conversion is exact.
            let (x0, y0) = (x as i32 as usize, y as i32 as usize);
            let (fx, fy) = (x - x0 as f32, y - y0 as f32);
            let i0 = y0 * iw + x0;
            let (a, b) = (data[i0], data[i0 + 1]);
            let (c, e) = (data[i0 + iw], data[i0 + iw + 1]);
            let top = a + (b - a) * fx;
            let bottom = c + (e - c) * fx;
            *o = top + (bottom - top) * fy;
            hx += dx;
            hy += dy;
            hw += dw;
        }
    }
    Some(())
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

    /// The incremental view sampling and the shared-weight template sampling against
    /// per-sample `bilinear` through the homography, inside the image and near its border
    /// (where the checked path is taken).
    #[test]
    fn window_sampling_matches_per_sample_bilinear() {
        let img = GrayF32::from_fn(160, 120, |x, y| {
            let (xf, yf) = (x as f32, y as f32);
            0.5 + 0.4 * (xf * 0.31 + yf * 0.07).sin() * (yf * 0.19).cos()
        });
        let h = Homography::from_rows([[0.93, 0.12, 6.3], [-0.08, 1.04, 2.7], [4e-4, -2e-4, 1.0]]).unwrap();
        // A grid of points over the whole key, so windows well inside (the incremental
        // path), straddling the border (the checked path, some of them all inside) and
        // leaving the image are all met, at two octave combinations.
        let (mut sampled, mut refused) = (0, 0);
        for (reach, step, view_scale) in [(6isize, 1.0, 1.0), (5, 2.0, 0.5)] {
            let side = (2 * reach + 1) as usize;
            let stride = side + 3;
            for p in (0..44).flat_map(|i| (0..33).map(move |j| Point2::new(i as f64 * 3.7, j as f64 * 3.7))) {
                let mut got = vec![0.0f32; side * stride];
                let ok = sample_view(&img, &h, p, reach, step, view_scale, &mut got, stride);
                let mut all = true;
                for j in 0..side {
                    for i in 0..side {
                        let q = Point2::new(
                            p.x + (i as f64 - reach as f64) * step,
                            p.y + (j as f64 - reach as f64) * step,
                        );
                        let m = h.apply(q).unwrap();
                        match bilinear(&img, (m.x * view_scale) as f32, (m.y * view_scale) as f32) {
                            Some(want) if ok.is_some() => {
                                let d = (got[j * stride + i] - want).abs();
                                assert!(d < 1e-4, "{p:?} ({i}, {j}): {} vs {want}", got[j * stride + i]);
                            }
                            Some(_) => {}
                            None => all = false,
                        }
                    }
                }
                assert_eq!(ok.is_some(), all, "{p:?}: sampled {ok:?}, all inside {all}");
                if all {
                    sampled += 1;
                } else {
                    refused += 1;
                }
            }
        }
        assert!(sampled > 100 && refused > 100, "{sampled} sampled, {refused} refused");
        for (x, y) in [(40.37, 30.81), (7.0, 7.5), (3.2, 50.0), (152.9, 60.0)] {
            let r = 7isize;
            let side = (2 * r + 1) as usize;
            let mut got = vec![0.0f32; side * 16];
            let ok = sample_template(&img, x, y, r, &mut got, 16);
            let want: Option<Vec<f32>> = (0..side * side)
                .map(|k| {
                    let (i, j) = ((k % side) as f64 - r as f64, (k / side) as f64 - r as f64);
                    bilinear(&img, (x + i) as f32, (y + j) as f32)
                })
                .collect();
            assert_eq!(ok.is_some(), want.is_some(), "({x}, {y})");
            if let Some(want) = want {
                for (k, w) in want.iter().enumerate() {
                    let g = got[(k / side) * 16 + k % side];
                    assert!((g - w).abs() < 1e-5, "({x}, {y}) sample {k}: {g} vs {w}");
                }
            }
        }
    }
}
