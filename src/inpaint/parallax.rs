//! Which surface each pixel of a region shows, when the scene is not one plane: per pixel,
//! the plane (the wall, or one standing off it) under which the views agree, as in
//! plane-sweep stereo, and each view's warp composed from its planes accordingly (pure
//! layer).
//!
//! The evidence, per pixel and plane hypothesis:
//! - outside the hole, the keyframe itself: how well each view, warped through the plane,
//!   reproduces the keyframe there (this is what carries the surfaces of the unmasked
//!   surroundings into the hole);
//! - inside the hole, the views among themselves: how far each view is from the views'
//!   per-channel median under the plane. A view that shows an occluder at the pixel
//!   disagrees with the others under every plane, so it does not decide; views that agree
//!   under a wrong plane do so on featureless surface, where the choice does not matter.
//!
//! Both are squared RGB distances, truncated (a surface edge or an occluder costs no more
//! than a bounded amount), averaged over a small window. The label field is then
//! regularised by semi-global aggregation along the four axis directions with a Potts
//! penalty (Hirschmüller's SGM over plane labels): labels form regions, the keyframe's
//! surroundings propagate into the hole where the views say nothing, and speckle goes.

use rayon::prelude::*;

use nalgebra::Point2;

use crate::features::harris::{HarrisParams, harris};
use crate::geometry::planes::{PlaneParams, fit_planes};
use crate::geometry::{Correspondence, Homography};
use crate::imaging::pyramid::half;
use crate::imaging::{GrayF32, Mask, Rect, bilinear};

/// A surface off the wall, as the fill takes it: its homography in each source (`None`
/// where that view's matches gave none) and the keyframe rectangle it may be chosen in.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfacePlane {
    /// Per source, in the order the fill gets them: keyframe → view.
    pub views: Vec<Option<Homography>>,
    /// Keyframe pixels where the plane may be the surface (its support, grown).
    pub region: Rect,
}

/// Parameters of [`surface_planes`].
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceParams {
    /// Matching runs on the images halved until they have at most this many pixels.
    pub max_pixels: usize,
    /// Keyframe corners matched (Harris, spread over a grid).
    pub corners: usize,
    /// Patches are `(2·r + 1)²` pixels (at the matching resolution)...
    pub patch_radius: usize,
    /// ...searched this far around the wall's prediction at half the matching resolution
    /// (parallax), then 2 pixels around that at the matching resolution.
    pub search_radius: usize,
    /// A match needs at least this normalised cross-correlation...
    pub min_ncc: f32,
    /// ...and must beat any other peak of the search farther than 2 pixels by this much.
    pub min_margin: f32,
    /// A plane may be chosen around its support grown by half its size, and at least this
    /// many (full-resolution) pixels.
    pub min_grow: usize,
    /// The sequential plane fit (thresholds in matching-resolution pixels).
    pub fit: PlaneParams,
}

impl Default for SurfaceParams {
    fn default() -> Self {
        Self {
            max_pixels: 1_200_000,
            corners: 4000,
            patch_radius: 4,
            search_radius: 16,
            min_ncc: 0.8,
            min_margin: 0.03,
            min_grow: 24,
            fit: PlaneParams::default(),
        }
    }
}

/// The surfaces off the wall of a keyframe and its views (luminance), given each view's
/// wall homography (keyframe → view) and the keyframe's mask (its occluders: a tree is not
/// a facade surface, so nothing under it is matched).
///
/// The paper's matching again, guided: keyframe corners are matched by normalised
/// cross-correlation in each view, searched around where the wall puts them (the view
/// resampled through the wall's homography, so that the patches compare at the same
/// perspective). On the wall the match is where the wall says; off it, it is displaced by
/// parallax. What the wall leaves out is fitted plane after plane ([`fit_planes`]). A plane
/// may be chosen around its support, grown by half its size: a surface goes on under the
/// occluder beyond where its corners were seen.
pub fn surface_planes(
    key: &GrayF32,
    views: &[&GrayF32],
    walls: &[Homography],
    mask: &Mask,
    params: &SurfaceParams,
    seed: u64,
) -> Vec<SurfacePlane> {
    let (w, h) = (key.width(), key.height());
    let mut levels = 0;
    while (w >> levels) * (h >> levels) > params.max_pixels {
        levels += 1;
    }
    let shrink = |img: &GrayF32| (0..levels).fold(img.clone(), |g, _| half(&g));
    let s = (1u32 << levels) as f64;
    // Full resolution → matching resolution, pixel centres kept (x_s = (x − (s − 1)/2) / s).
    let off = (s - 1.0) / (2.0 * s);
    let t = Homography::from_rows([[1.0 / s, 0.0, -off], [0.0, 1.0 / s, -off], [0.0, 0.0, 1.0]])
        .expect("regular");
    let t_inv = t.inverse().expect("regular");
    let key_s = shrink(key);
    let hp = HarrisParams {
        max_corners: params.corners,
        border: params.patch_radius + 2,
        ..HarrisParams::default()
    };
    let guard = 3 * (1usize << levels) as isize;
    let points: Vec<Point2<f64>> = harris(&key_s, &hp)
        .into_iter()
        .map(|c| Point2::new(f64::from(c.x), f64::from(c.y)))
        .filter(|p| {
            let q = t_inv.apply(*p).expect("affine");
            let (x, y) = (q.x.round() as isize, q.y.round() as isize);
            !(-guard..=guard).any(|dy| {
                (-guard..=guard).any(|dx| mask.get_checked(x + dx, y + dy).is_some_and(|m| m > 127))
            })
        })
        .collect();
    // Coarse to fine: the search at half the matching resolution (parallax of tens of
    // pixels), then a small one around its answer.
    let t1 = Homography::from_rows([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]]).expect("regular");
    let t1_inv = t1.inverse().expect("regular");
    let key_c = half(&key_s);
    let coarse: Vec<(Point2<f64>, (f64, f64))> =
        points.iter().map(|p| (t1.apply(*p).expect("affine"), (0.0, 0.0))).collect();
    let matches: Vec<Vec<Correspondence>> = views
        .iter()
        .zip(walls)
        .map(|(view, wall)| {
            let view_s = shrink(view);
            let wall_s = t.after(wall).after(&t_inv);
            let view_c = half(&view_s);
            let wall_c = t1.after(&wall_s).after(&t1_inv);
            let found = guided_matches(&key_c, &view_c, &wall_c, &coarse, params.search_radius, params);
            let fine: Vec<(Point2<f64>, (f64, f64))> = points
                .iter()
                .zip(&found)
                .filter_map(|(p, d)| d.map(|d| (*p, (2.0 * d.0, 2.0 * d.1))))
                .collect();
            let refined = guided_matches(&key_s, &view_s, &wall_s, &fine, 2, params);
            fine.iter()
                .zip(refined)
                .filter_map(|((p, _), d)| {
                    let d = d?;
                    let q = wall_s.apply(Point2::new(p.x + d.0, p.y + d.1))?;
                    Some(Correspondence::new(*p, q))
                })
                .collect()
        })
        .collect();
    let walls_s: Vec<Homography> = walls.iter().map(|h| t.after(h).after(&t_inv)).collect();
    fit_planes(&matches, &walls_s, &|_| false, &params.fit, seed)
        .into_iter()
        .map(|f| {
            // Back to full resolution.
            let a = t_inv.apply(Point2::new(f.bounds.0, f.bounds.1)).expect("affine");
            let b = t_inv.apply(Point2::new(f.bounds.2, f.bounds.3)).expect("affine");
            let gx = (0.5 * (b.x - a.x)).max(params.min_grow as f64);
            let gy = (0.5 * (b.y - a.y)).max(params.min_grow as f64);
            let clip = |v: f64, hi: usize| v.clamp(0.0, hi as f64) as usize;
            let region = Rect::from_corners(
                clip(a.x - gx, w),
                clip(a.y - gy, h),
                clip(b.x + gx + 1.0, w),
                clip(b.y + gy + 1.0, h),
            );
            let views = f.views.iter().map(|o| o.map(|hv| t_inv.after(&hv).after(&t))).collect();
            SurfacePlane { views, region }
        })
        .collect()
}

/// Keyframe `points` matched in `view`, each searched `radius` pixels around where `wall`
/// puts it shifted by its prior displacement (keyframe pixels, in the view resampled
/// through `wall`); the displacement found, `None` where the match is weak or ambiguous.
fn guided_matches(
    key: &GrayF32,
    view: &GrayF32,
    wall: &Homography,
    points: &[(Point2<f64>, (f64, f64))],
    radius: usize,
    params: &SurfaceParams,
) -> Vec<Option<(f64, f64)>> {
    let r = params.patch_radius as isize;
    let sr = radius as isize;
    let side = (2 * r + 1) as usize;
    let span = 2 * (r + sr) + 1;
    points
        .par_iter()
        .map(|&(p, prior)| {
            let (px, py) = (p.x.round() as isize, p.y.round() as isize);
            let (ox0, oy0) = (prior.0.round() as isize, prior.1.round() as isize);
            // The keyframe patch, zero-mean and unit norm.
            let mut kp = Vec::with_capacity(side * side);
            for dy in -r..=r {
                for dx in -r..=r {
                    kp.push(key.get_checked(px + dx, py + dy)?);
                }
            }
            let km = kp.iter().sum::<f32>() / kp.len() as f32;
            kp.iter_mut().for_each(|v| *v -= km);
            let kn = kp.iter().map(|v| v * v).sum::<f32>().sqrt();
            if kn < 0.02 * side as f32 {
                return None;
            }
            // The view resampled through the wall over the search area.
            let mut area = vec![0.0f32; (span * span) as usize];
            for (j, a) in area.iter_mut().enumerate() {
                let (ax, ay) = ((j as isize % span) - r - sr + ox0, (j as isize / span) - r - sr + oy0);
                let q = wall.apply(Point2::new((px + ax) as f64, (py + ay) as f64))?;
                *a = bilinear(view, q.x as f32, q.y as f32)?;
            }
            let n = (2 * sr + 1) as usize;
            let mut score = vec![-1.0f32; n * n];
            for oy in 0..n {
                for ox in 0..n {
                    let (mut sum, mut sum2, mut dot) = (0.0f32, 0.0f32, 0.0f32);
                    let mut k = 0;
                    for y in 0..side {
                        let row = &area[(oy + y) * span as usize + ox..][..side];
                        for &v in row {
                            sum += v;
                            sum2 += v * v;
                            dot += v * kp[k];
                            k += 1;
                        }
                    }
                    let var = sum2 - sum * sum / kp.len() as f32;
                    if var > 1e-8 {
                        score[oy * n + ox] = dot / (kn * var.sqrt());
                    }
                }
            }
            let best = (0..n * n).max_by(|&a, &b| score[a].total_cmp(&score[b]))?;
            let (bx, by) = (best % n, best / n);
            let second = (0..n * n)
                .filter(|&j| (j % n).abs_diff(bx) > 2 || (j / n).abs_diff(by) > 2)
                .map(|j| score[j])
                .fold(-1.0f32, f32::max);
            if score[best] < params.min_ncc || score[best] - second < params.min_margin {
                return None;
            }
            // Sub-pixel: a parabola through the peak and its neighbours, per axis.
            let sub = |l: f32, c: f32, r: f32| {
                let d = l - 2.0 * c + r;
                if d < -1e-6 { (0.5 * (l - r) / d).clamp(-0.5, 0.5) } else { 0.0 }
            };
            let at = |x: usize, y: usize| score[y * n + x];
            let fx = if bx > 0 && bx + 1 < n { sub(at(bx - 1, by), at(bx, by), at(bx + 1, by)) } else { 0.0 };
            let fy = if by > 0 && by + 1 < n { sub(at(bx, by - 1), at(bx, by), at(bx, by + 1)) } else { 0.0 };
            Some((
                (bx as isize - sr + ox0) as f64 + f64::from(fx),
                (by as isize - sr + oy0) as f64 + f64::from(fy),
            ))
        })
        .collect()
}

/// Parameters of [`choose_planes`].
#[derive(Debug, Clone, PartialEq)]
pub struct ParallaxParams {
    /// Costs are averaged over `(2·r + 1)²` pixels.
    pub window: usize,
    /// Squared RGB distance at which a disagreement stops costing more.
    pub truncate: f32,
    /// Potts penalty of a label change between neighbours, in the cost's units.
    pub penalty: f32,
    /// Extra cost of any plane but the wall (the wall is the default surface).
    pub wall_bias: f32,
}

impl Default for ParallaxParams {
    fn default() -> Self {
        Self { window: 2, truncate: 0.03, penalty: 0.08, wall_bias: 0.0005 }
    }
}

/// A view warped over a region: its pixels and which of them are valid.
pub type WarpedView<'a> = (&'a [[f32; 3]], &'a [bool]);

/// One region's input: `width × height` buffers, `planes[p][v]` the view `v` warped
/// through plane `p` (0 the wall) with its valid pixels, `None` where the view has no
/// such plane; `allowed[p]` where plane `p` may be chosen.
pub struct PlaneInput<'a> {
    pub width: usize,
    pub height: usize,
    pub key: &'a [[f32; 3]],
    pub hole: &'a [bool],
    pub need: &'a [bool],
    pub blocked: &'a [bool],
    pub planes: &'a [Vec<Option<WarpedView<'a>>>],
    pub allowed: &'a [Vec<bool>],
}

#[inline]
fn sq(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

/// The plane index of every pixel of the region (0 where nothing says otherwise).
pub fn choose_planes(input: &PlaneInput<'_>, params: &ParallaxParams) -> Vec<u16> {
    let (w, h) = (input.width, input.height);
    let n = w * h;
    let np = input.planes.len();
    if np <= 1 {
        return vec![0; n];
    }
    let t = params.truncate;
    // Per plane: the raw cost and whether it says anything, per pixel.
    let raw: Vec<(Vec<f32>, Vec<f32>)> = input
        .planes
        .par_iter()
        .enumerate()
        .map(|(p, views)| {
            let mut cost = vec![0.0f32; n];
            let mut weight = vec![0.0f32; n];
            for i in 0..n {
                if !input.need[i] || input.blocked[i] {
                    continue;
                }
                let seen = views.iter().flatten().filter(|(_, ok)| ok[i]);
                if !input.hole[i] {
                    let (mut s, mut c) = (0.0f32, 0usize);
                    for (img, _) in seen {
                        s += sq(img[i], input.key[i]).min(t);
                        c += 1;
                    }
                    // A plane no view shows here is as bad as a disagreement.
                    cost[i] = if c > 0 { s / c as f32 } else { t };
                    weight[i] = 1.0;
                } else {
                    let vals: Vec<[f32; 3]> = seen.map(|(img, _)| img[i]).collect();
                    cost[i] = consensus_cost(&vals, t);
                    weight[i] = 1.0;
                }
                if p > 0 {
                    cost[i] += params.wall_bias;
                }
            }
            (cost, weight)
        })
        .collect();
    // Window means; a plane outside where it may be chosen costs more than any evidence.
    let forbidden = 4.0 * t + 16.0 * params.penalty;
    let costs: Vec<Vec<f32>> = raw
        .par_iter()
        .enumerate()
        .map(|(p, (c, wt))| {
            let sum = box_sum(c, w, h, params.window);
            let cnt = box_sum(wt, w, h, params.window);
            (0..n)
                .map(|i| {
                    if !input.allowed[p][i] {
                        forbidden
                    } else if cnt[i] > 0.0 {
                        sum[i] / cnt[i]
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    sgm(&costs, w, h, params.penalty)
}

/// Mean truncated distance of the views' colours to their per-channel median (`t` with
/// fewer than two views: nothing is known).
fn consensus_cost(vals: &[[f32; 3]], t: f32) -> f32 {
    let c = vals.len();
    if c < 2 {
        return t;
    }
    let mut med = [0.0f32; 3];
    let mut chan = [0.0f32; 16];
    for (k, m) in med.iter_mut().enumerate() {
        for (j, v) in vals.iter().take(16).enumerate() {
            chan[j] = v[k];
        }
        let s = &mut chan[..c.min(16)];
        s.sort_unstable_by(f32::total_cmp);
        *m = 0.5 * (s[(s.len() - 1) / 2] + s[s.len() / 2]);
    }
    vals.iter().map(|&v| sq(v, med).min(t)).sum::<f32>() / c as f32
}

/// Sum over a `(2r + 1)²` window (clipped at the borders).
fn box_sum(v: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let mut rows = vec![0.0f32; w * h];
    for y in 0..h {
        let row = &v[y * w..(y + 1) * w];
        let mut acc: f32 = row[..(r + 1).min(w)].iter().sum();
        for x in 0..w {
            rows[y * w + x] = acc;
            if x + r + 1 < w {
                acc += row[x + r + 1];
            }
            if x >= r {
                acc -= row[x - r];
            }
        }
    }
    let mut out = vec![0.0f32; w * h];
    for x in 0..w {
        let mut acc = 0.0f32;
        for y in 0..(r + 1).min(h) {
            acc += rows[y * w + x];
        }
        for y in 0..h {
            out[y * w + x] = acc;
            if y + r + 1 < h {
                acc += rows[(y + r + 1) * w + x];
            }
            if y >= r {
                acc -= rows[(y - r) * w + x];
            }
        }
    }
    out
}

/// Semi-global aggregation of `costs[p][i]` along the four axis directions with a Potts
/// penalty, then the cheapest label per pixel (ties to the lower index).
fn sgm(costs: &[Vec<f32>], w: usize, h: usize, penalty: f32) -> Vec<u16> {
    let np = costs.len();
    let n = w * h;
    let mut total = vec![0.0f32; n * np];
    // One step of a path: `cur = C(i) + min(prev, min(prev) + P) − min(prev)`.
    let step = |i: usize, prev: &[f32], first: bool, cur: &mut [f32]| {
        let pmin = prev.iter().copied().fold(f32::INFINITY, f32::min);
        for p in 0..np {
            let c = costs[p][i];
            cur[p] = if first { c } else { c + prev[p].min(pmin + penalty) - pmin };
        }
    };
    // Left to right and back: rows are independent.
    total.par_chunks_mut(w * np).enumerate().for_each(|(y, row)| {
        let (mut prev, mut cur) = (vec![0.0f32; np], vec![0.0f32; np]);
        for reverse in [false, true] {
            for s in 0..w {
                let x = if reverse { w - 1 - s } else { s };
                step(y * w + x, &prev, s == 0, &mut cur);
                for p in 0..np {
                    row[x * np + p] += cur[p];
                }
                std::mem::swap(&mut prev, &mut cur);
            }
        }
    });
    // Top to bottom and back: a whole row of paths at a time.
    for reverse in [false, true] {
        let mut prev = vec![0.0f32; w * np];
        let mut cur = vec![0.0f32; w * np];
        for s in 0..h {
            let y = if reverse { h - 1 - s } else { s };
            cur.par_chunks_mut(np).zip(prev.par_chunks(np)).enumerate().for_each(|(x, (c, pv))| {
                step(y * w + x, pv, s == 0, c);
            });
            for (t, c) in total[y * w * np..(y + 1) * w * np].iter_mut().zip(&cur) {
                *t += c;
            }
            std::mem::swap(&mut prev, &mut cur);
        }
    }
    (0..n)
        .map(|i| {
            let t = &total[i * np..(i + 1) * np];
            let mut best = 0;
            for p in 1..np {
                if t[p] < t[best] {
                    best = p;
                }
            }
            best as u16
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A region whose left half is a "slab": the views agree there only under plane 1.
    #[test]
    fn the_plane_under_which_the_views_agree_wins_and_labels_form_regions() {
        let (w, h) = (40, 30);
        let n = w * h;
        let tex = |x: usize, y: usize, s: usize| {
            let v = (((x + s) * 7 + y * 13) % 11) as f32 / 11.0;
            [v, 1.0 - v, 0.5]
        };
        let slab = |x: usize| x < 20;
        // View a and b under plane 0 show the slab shifted by different amounts; under
        // plane 1 they show it in place. The wall is right under plane 0 only.
        let view = |p: usize, shift: usize| -> Vec<[f32; 3]> {
            (0..n)
                .map(|i| {
                    let (x, y) = (i % w, i / w);
                    match (slab(x), p) {
                        (true, 0) => tex(x, y, shift),
                        (true, _) => tex(x, y, 0),
                        (false, 0) => tex(x, y, 0),
                        (false, _) => tex(x, y, shift + 3),
                    }
                })
                .collect()
        };
        let (a0, a1, b0, b1) = (view(0, 2), view(1, 2), view(0, 5), view(1, 5));
        let ok = vec![true; n];
        let key: Vec<[f32; 3]> = (0..n).map(|i| tex(i % w, i / w, 0)).collect();
        let hole: Vec<bool> =
            (0..n).map(|i| (5..25).contains(&(i / w)) && (8..32).contains(&(i % w))).collect();
        let planes = vec![
            vec![Some((a0.as_slice(), ok.as_slice())), Some((b0.as_slice(), ok.as_slice()))],
            vec![Some((a1.as_slice(), ok.as_slice())), Some((b1.as_slice(), ok.as_slice()))],
        ];
        let allowed = vec![vec![true; n], vec![true; n]];
        let input = PlaneInput {
            width: w,
            height: h,
            key: &key,
            hole: &hole,
            need: &ok,
            blocked: &vec![false; n],
            planes: &planes,
            allowed: &allowed,
        };
        let labels = choose_planes(&input, &ParallaxParams::default());
        let wrong = (0..n).filter(|&i| labels[i] != u16::from(slab(i % w))).count();
        assert!(wrong * 50 < n, "{wrong} of {n} pixels wrong");
        // Forbidden planes are not chosen.
        let allowed = vec![vec![true; n], vec![false; n]];
        let labels = choose_planes(&PlaneInput { allowed: &allowed, ..input }, &ParallaxParams::default());
        assert!(labels.iter().all(|&l| l == 0));
    }
}
