//! Several planes per view: the surfaces that stand off the wall (balcony fronts,
//! pilasters, signs), found from the matches the wall's homography leaves out, each a
//! homography per view with its own support region in the keyframe (pure layer, seeded).
//!
//! Sequential robust fitting: per view, what the wall does not explain is fitted again,
//! plane after plane. What stands off a wall is small, so among the leftovers (mismatches,
//! occluders, other slabs) its matches are few; samples are therefore drawn locally (a
//! point and its neighbours in the keyframe, as NAPSAC does) and scored by MSAC over all
//! leftovers. A plane is kept only with enough inliers, spread out, and clearly apart from
//! the wall. The views' planes are then matched to each other by their support in the
//! keyframe (the same keyframe corners), and every view's homography for a plane is fitted
//! on its own matches inside that support, so that plane `p` is one physical surface in
//! all views.

use nalgebra::Point2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::homography::{Homography, cross, dlt};
use super::robust::{Correspondence, refine};

/// Parameters of [`fit_planes`].
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneParams {
    /// Inlier threshold on the transfer distance, in keyframe pixels.
    pub threshold_px: f64,
    /// A match the wall explains within this many pixels is the wall's.
    pub wall_residual_px: f64,
    /// A plane needs at least this many inliers...
    pub min_inliers: usize,
    /// ...spread over at least this many pixels along their narrower principal axis
    /// (standard deviation): a plane fitted on a clump extrapolates badly.
    pub min_spread_px: f64,
    /// ...and must move its support by at least this much (mean, pixels) compared with the
    /// wall: otherwise the wall serves.
    pub min_departure_px: f64,
    /// At most this many planes besides the wall.
    pub max_planes: usize,
    /// Local samples take a point and three of its this many nearest neighbours.
    pub neighbours: usize,
    /// Samples drawn per plane search.
    pub iterations: usize,
}

impl Default for PlaneParams {
    fn default() -> Self {
        Self {
            threshold_px: 1.5,
            wall_residual_px: 2.5,
            min_inliers: 10,
            min_spread_px: 4.0,
            min_departure_px: 1.5,
            max_planes: 6,
            neighbours: 10,
            iterations: 300,
        }
    }
}

/// A plane off the wall: its homography in each view (`None` where the view's matches do
/// not support it) and where in the keyframe it was seen.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneFit {
    /// Per view (in the order given): keyframe → view.
    pub views: Vec<Option<Homography>>,
    /// Keyframe points that support the plane (in any view).
    pub support: Vec<Point2<f64>>,
    /// Bounding box of `support` in the keyframe: `(x0, y0, x1, y1)`.
    pub bounds: (f64, f64, f64, f64),
}

/// Finds the planes besides the wall. `matches[v]` are view `v`'s putative keyframe → view
/// correspondences, `walls[v]` its wall homography; matches whose keyframe point `exclude`s
/// (the keyframe's occluders: a tree is not a facade plane) are not used.
pub fn fit_planes(
    matches: &[Vec<Correspondence>],
    walls: &[Homography],
    exclude: &dyn Fn(Point2<f64>) -> bool,
    params: &PlaneParams,
    seed: u64,
) -> Vec<PlaneFit> {
    assert_eq!(matches.len(), walls.len(), "one wall per view");
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x0091_a4e5);
    // 1. Per view, sequentially on what the wall leaves out.
    let mut candidates: Vec<Vec<Point2<f64>>> = Vec::new();
    for (data, wall) in matches.iter().zip(walls) {
        let mut pool: Vec<usize> = (0..data.len())
            .filter(|&i| !exclude(data[i].key) && data[i].residual(wall) > params.wall_residual_px)
            .collect();
        for _ in 0..params.max_planes {
            let Some((h, inliers)) = fit_local(data, &pool, params, &mut rng) else { break };
            if !acceptable(data, &inliers, &h, wall, params) {
                break;
            }
            candidates.push(inliers.iter().map(|&i| data[i].key).collect());
            pool.retain(|i| !inliers.contains(i));
        }
    }
    // 2. The same surface found in several views: merge by shared keyframe support.
    candidates.sort_by_key(|c| std::cmp::Reverse(c.len()));
    let mut clusters: Vec<Vec<Point2<f64>>> = Vec::new();
    for c in candidates {
        let same = |a: &Point2<f64>, b: &Point2<f64>| (a - b).norm() < 0.5;
        let found = clusters.iter_mut().find(|k| {
            let shared = c.iter().filter(|p| k.iter().any(|q| same(p, q))).count();
            shared * 10 >= 3 * c.len().min(k.len()) || overlap(bounds(&c), bounds(k)) > 0.5
        });
        match found {
            Some(k) => {
                for p in c {
                    if !k.iter().any(|q| same(&p, q)) {
                        k.push(p);
                    }
                }
            }
            None => clusters.push(c),
        }
        if clusters.len() >= params.max_planes {
            break;
        }
    }
    // 3. Each surface in each view, from that view's matches inside its support.
    clusters
        .into_iter()
        .filter_map(|support| {
            let bounds = bounds(&support);
            let grow = 4.0 * params.threshold_px;
            let inside = |p: Point2<f64>| {
                p.x >= bounds.0 - grow
                    && p.y >= bounds.1 - grow
                    && p.x <= bounds.2 + grow
                    && p.y <= bounds.3 + grow
            };
            let views: Vec<Option<Homography>> = matches
                .iter()
                .zip(walls)
                .map(|(data, wall)| {
                    let pool: Vec<usize> =
                        (0..data.len()).filter(|&i| inside(data[i].key) && !exclude(data[i].key)).collect();
                    let (h, inliers) = fit_local(data, &pool, params, &mut rng)?;
                    let spread_ok = spread(&inliers.iter().map(|&i| data[i].key).collect::<Vec<_>>())
                        >= params.min_spread_px;
                    // Where this view cannot tell the surface from the wall, the wall is it.
                    (inliers.len() >= params.min_inliers && spread_ok)
                        .then(|| if departure(data, &inliers, &h, wall) < 0.5 { *wall } else { h })
                })
                .collect();
            (views.iter().filter(|v| v.is_some()).count() >= 1).then_some(PlaneFit { views, support, bounds })
        })
        .collect()
}

/// Whether a plane found among the leftovers is one: enough inliers, spread, off the wall.
fn acceptable(
    data: &[Correspondence],
    inliers: &[usize],
    h: &Homography,
    wall: &Homography,
    params: &PlaneParams,
) -> bool {
    let pts: Vec<Point2<f64>> = inliers.iter().map(|&i| data[i].key).collect();
    inliers.len() >= params.min_inliers
        && spread(&pts) >= params.min_spread_px
        && departure(data, inliers, h, wall) >= params.min_departure_px
}

/// Mean distance, over the inliers' keyframe points, between where `h` and `wall` put them.
fn departure(data: &[Correspondence], inliers: &[usize], h: &Homography, wall: &Homography) -> f64 {
    let d: f64 = inliers
        .iter()
        .map(|&i| match (h.apply(data[i].key), wall.apply(data[i].key)) {
            (Some(a), Some(b)) => (a - b).norm(),
            _ => f64::INFINITY,
        })
        .sum();
    d / inliers.len().max(1) as f64
}

/// Standard deviation of `pts` along their narrower principal axis.
fn spread(pts: &[Point2<f64>]) -> f64 {
    if pts.len() < 3 {
        return 0.0;
    }
    let n = pts.len() as f64;
    let (mx, my) = (pts.iter().map(|p| p.x).sum::<f64>() / n, pts.iter().map(|p| p.y).sum::<f64>() / n);
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p.x - mx, p.y - my);
        sxx += dx * dx;
        syy += dy * dy;
        sxy += dx * dy;
    }
    let (sxx, syy, sxy) = (sxx / n, syy / n, sxy / n);
    let tr = sxx + syy;
    let det = sxx * syy - sxy * sxy;
    let small = 0.5 * tr - (0.25 * tr * tr - det).max(0.0).sqrt();
    small.max(0.0).sqrt()
}

/// Intersection over the smaller of two boxes `(x0, y0, x1, y1)`.
fn overlap(a: (f64, f64, f64, f64), b: (f64, f64, f64, f64)) -> f64 {
    let iw = (a.2.min(b.2) - a.0.max(b.0)).max(0.0);
    let ih = (a.3.min(b.3) - a.1.max(b.1)).max(0.0);
    let area = |r: (f64, f64, f64, f64)| ((r.2 - r.0) * (r.3 - r.1)).max(1e-9);
    iw * ih / area(a).min(area(b))
}

fn bounds(pts: &[Point2<f64>]) -> (f64, f64, f64, f64) {
    pts.iter().fold((f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY), |b, p| {
        (b.0.min(p.x), b.1.min(p.y), b.2.max(p.x), b.3.max(p.y))
    })
}

/// The best homography over `pool` from local 4-point samples (a point and three of its
/// nearest neighbours in the keyframe), scored by MSAC over the whole pool and refined on
/// its inliers; `None` with too few points.
fn fit_local(
    data: &[Correspondence],
    pool: &[usize],
    params: &PlaneParams,
    rng: &mut ChaCha8Rng,
) -> Option<(Homography, Vec<usize>)> {
    if pool.len() < params.min_inliers.max(4) {
        return None;
    }
    let t2 = params.threshold_px * params.threshold_px;
    let k = params.neighbours.min(pool.len() - 1);
    // Each pool point's nearest neighbours (by keyframe position).
    let near: Vec<Vec<usize>> = pool
        .iter()
        .map(|&i| {
            let mut d: Vec<(f64, usize)> = pool
                .iter()
                .filter(|&&j| j != i)
                .map(|&j| ((data[j].key - data[i].key).norm_squared(), j))
                .collect();
            d.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            d.truncate(k);
            d.into_iter().map(|(_, j)| j).collect()
        })
        .collect();
    let score = |h: &Homography| -> f64 { pool.iter().map(|&i| data[i].residual_sq(h).min(t2)).sum() };
    let mut best: Option<(f64, Homography)> = None;
    for _ in 0..params.iterations {
        let s = rng.random_range(0..pool.len());
        if near[s].len() < 3 {
            continue;
        }
        let mut pick = [pool[s], 0, 0, 0];
        let mut chosen = 1;
        let mut tries = 0;
        while chosen < 4 && tries < 20 {
            tries += 1;
            let j = near[s][rng.random_range(0..near[s].len())];
            if !pick[..chosen].contains(&j) {
                pick[chosen] = j;
                chosen += 1;
            }
        }
        if chosen < 4 || !well_spread(data, &pick) {
            continue;
        }
        let key: Vec<_> = pick.iter().map(|&i| data[i].key).collect();
        let view: Vec<_> = pick.iter().map(|&i| data[i].view).collect();
        let Ok(h) = dlt(&key, &view) else { continue };
        let c = score(&h);
        if best.as_ref().is_none_or(|b| c < b.0) {
            best = Some((c, h));
        }
    }
    let (_, mut h) = best?;
    for _ in 0..3 {
        let inliers: Vec<usize> = pool.iter().copied().filter(|&i| data[i].residual_sq(&h) < t2).collect();
        if inliers.len() < 8 {
            break;
        }
        h = refine(data, &inliers, &h);
    }
    let inliers = pool.iter().copied().filter(|&i| data[i].residual_sq(&h) < t2).collect();
    Some((h, inliers))
}

/// No three of the four keyframe points nearly on a line.
fn well_spread(data: &[Correspondence], pick: &[usize; 4]) -> bool {
    let p: Vec<_> = pick.iter().map(|&i| data[i].key).collect();
    [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)].iter().all(|&(a, b, c)| cross(p[a], p[b], p[c]).abs() > 4.0)
}

/// Plane + parallax: the planes parallel to the wall, one parameter each. With the wall's
/// homography `M_v` of view `v` and its epipole `e_v`, a point off the wall maps as
/// `x_v ~ M_v·x + γ_v·e_v` (`x` the homogeneous keyframe pixel), where `γ_v` — the
/// projective depth relative to the wall — is the same for all views up to a per-view
/// scale (which [`ParallaxFamily::scaled`] fixes). A surface parallel to a near
/// fronto-parallel wall has one `γ`: its homography in view `v` is `M_v + γ·e_v·(0, 0, 1)`.
#[derive(Debug, Clone, PartialEq)]
pub struct ParallaxFamily {
    /// Per view: the wall's matrix as given (its scale fixes `γ`'s).
    pub walls: Vec<nalgebra::Matrix3<f64>>,
    /// Per view: the epipole, `None` where the view's matches did not give it.
    pub epipoles: Vec<Option<nalgebra::Vector3<f64>>>,
    /// Per view: `γ_v` of the off-wall matches that agreed with its epipole.
    pub observed: Vec<Vec<f64>>,
}

/// Parameters of [`fit_parallax`].
#[derive(Debug, Clone, PartialEq)]
pub struct ParallaxFitParams {
    /// A match the wall explains within this many pixels says nothing about the epipole...
    pub min_parallax_px: f64,
    /// ...nor one it misses by more than this (a mismatch).
    pub max_parallax_px: f64,
    /// A match agrees with an epipole when its view point lies within this many pixels of
    /// the line through the wall's prediction and the epipole.
    pub line_px: f64,
    /// A view's epipole needs at least this many agreeing matches.
    pub min_inliers: usize,
    /// Two-point samples drawn per view.
    pub iterations: usize,
}

impl Default for ParallaxFitParams {
    fn default() -> Self {
        Self { min_parallax_px: 3.0, max_parallax_px: 80.0, line_px: 0.75, min_inliers: 6, iterations: 400 }
    }
}

impl ParallaxFamily {
    /// Keyframe → view `v` homography of the surface at projective depth `gamma`, in the
    /// matches' coordinates (`None` without an epipole).
    pub fn homography(&self, v: usize, gamma: f64) -> Option<Homography> {
        let e = self.epipoles[v]?;
        let mut m = self.walls[v];
        m.set_column(2, &(m.column(2) + e * gamma));
        Homography::from_matrix(m)
    }

    /// The family with view `v`'s epipole scaled by `scale[v]` (`None`: dropped), so that
    /// one `γ` serves all views.
    pub fn scaled(&self, scale: &[Option<f64>]) -> Self {
        let epipoles = self.epipoles.iter().zip(scale).map(|(e, k)| Some(e.as_ref()? * (*k)?)).collect();
        let observed = self
            .observed
            .iter()
            .zip(scale)
            .map(|(o, k)| k.map_or_else(Vec::new, |k| o.iter().map(|g| g / k).collect()))
            .collect();
        Self { walls: self.walls.clone(), epipoles, observed }
    }

    /// How many pixels per unit of `γ` a point at keyframe `p` moves in view `v` (0 without
    /// an epipole).
    pub fn rate(&self, v: usize, p: Point2<f64>) -> f64 {
        let Some(e) = self.epipoles[v] else { return 0.0 };
        let q = self.walls[v] * nalgebra::Vector3::new(p.x, p.y, 1.0);
        if q.z.abs() < 1e-12 {
            return 0.0;
        }
        // d/dγ of (q + γe)_xy / (q + γe)_z at γ = 0.
        let dx = (e.x * q.z - q.x * e.z) / (q.z * q.z);
        let dy = (e.y * q.z - q.y * e.z) / (q.z * q.z);
        dx.hypot(dy)
    }
}

/// `γ` of a match under wall matrix `m` and epipole `e` (least squares on `x_v × (m·x + γ·e) = 0`).
pub(crate) fn gamma_of(c: &Correspondence, m: &nalgebra::Matrix3<f64>, e: &nalgebra::Vector3<f64>) -> f64 {
    let p = m * nalgebra::Vector3::new(c.key.x, c.key.y, 1.0);
    let q = nalgebra::Vector3::new(c.view.x, c.view.y, 1.0);
    let a = q.cross(&p);
    let b = q.cross(e);
    -a.dot(&b) / b.norm_squared().max(1e-300)
}

/// Distance in the view from `c.view` to the line through the wall's prediction and `e`
/// (infinite when the prediction is undefined): the line test of [`fit_parallax`].
pub fn epipolar_distance(c: &Correspondence, m: &nalgebra::Matrix3<f64>, e: &nalgebra::Vector3<f64>) -> f64 {
    let p = m * nalgebra::Vector3::new(c.key.x, c.key.y, 1.0);
    if p.z.abs() < 1e-12 {
        return f64::INFINITY;
    }
    let w = Point2::new(p.x / p.z, p.y / p.z);
    // Direction from the prediction towards the epipole (homogeneous: finite or not).
    let d = nalgebra::Vector2::new(e.x - e.z * w.x, e.y - e.z * w.y);
    let n = d.norm();
    if n < 1e-12 {
        return f64::INFINITY;
    }
    let r = c.view - w;
    (d.x * r.y - d.y * r.x).abs() / n
}

/// The plane + parallax family of a keyframe and its views, from putative keyframe → view
/// matches (`matches[v]`) and the views' wall homographies: per view, the epipole is the
/// point the off-wall matches' displacements from the wall's prediction all point at
/// (two-point samples, the most agreeing kept, refined by least squares on the lines).
/// Each view's `γ` has its own scale: the sparse matches a facade gives off its wall are
/// too few to tie them together (the sweep does it densely). `None` when no view shows
/// parallax (a flat wall, or only rotation).
pub fn fit_parallax(
    matches: &[Vec<Correspondence>],
    walls: &[Homography],
    params: &ParallaxFitParams,
    seed: u64,
) -> Option<ParallaxFamily> {
    assert_eq!(matches.len(), walls.len(), "one wall per view");
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x00e9_1901);
    let mats: Vec<nalgebra::Matrix3<f64>> = walls.iter().map(|h| *h.matrix()).collect();
    // Per view: the epipole and its agreeing matches.
    let mut fits: Vec<Option<(nalgebra::Vector3<f64>, Vec<usize>)>> = Vec::with_capacity(matches.len());
    for (data, (wall, m)) in matches.iter().zip(walls.iter().zip(&mats)) {
        let pool: Vec<usize> = (0..data.len())
            .filter(|&i| {
                let r = data[i].residual(wall);
                r >= params.min_parallax_px && r <= params.max_parallax_px
            })
            .collect();
        let line = |i: usize| -> Option<nalgebra::Vector3<f64>> {
            let p = m * nalgebra::Vector3::new(data[i].key.x, data[i].key.y, 1.0);
            let q = nalgebra::Vector3::new(data[i].view.x, data[i].view.y, 1.0);
            let l = (p / p.z).cross(&q);
            let n = l.xy().norm();
            (n > 1e-9).then(|| l / n)
        };
        let agree = |e: &nalgebra::Vector3<f64>| -> Vec<usize> {
            pool.iter().copied().filter(|&i| epipolar_distance(&data[i], m, e) < params.line_px).collect()
        };
        if pool.len() < params.min_inliers {
            fits.push(None);
            continue;
        }
        let mut best: Option<(nalgebra::Vector3<f64>, Vec<usize>)> = None;
        for _ in 0..params.iterations {
            let (a, b) = (pool[rng.random_range(0..pool.len())], pool[rng.random_range(0..pool.len())]);
            if a == b {
                continue;
            }
            let (Some(la), Some(lb)) = (line(a), line(b)) else { continue };
            let e = la.cross(&lb);
            if e.norm() < 1e-12 {
                continue;
            }
            let inl = agree(&(e / e.norm()));
            if best.as_ref().is_none_or(|b| inl.len() > b.1.len()) {
                best = Some((e / e.norm(), inl));
            }
        }
        let refined = best.filter(|b| b.1.len() >= params.min_inliers).map(|(mut e, mut inl)| {
            for _ in 0..3 {
                // The point nearest all lines: the least eigenvector of Σ l·lᵀ.
                let ata: nalgebra::Matrix3<f64> =
                    inl.iter().filter_map(|&i| line(i)).map(|l| l * l.transpose()).sum();
                let eig = ata.symmetric_eigen();
                let cand: nalgebra::Vector3<f64> =
                    eig.eigenvectors.column(eig.eigenvalues.imin()).into_owned();
                let next = agree(&cand);
                if next.len() < inl.len() {
                    break;
                }
                (e, inl) = (cand, next);
            }
            (e, inl)
        });
        fits.push(refined.filter(|f| f.1.len() >= params.min_inliers));
    }
    let epipoles: Vec<Option<nalgebra::Vector3<f64>>> =
        fits.iter().map(|f| f.as_ref().map(|f| f.0)).collect();
    let observed: Vec<Vec<f64>> = fits
        .iter()
        .zip(matches.iter().zip(&mats))
        .map(|(f, (data, m))| {
            f.as_ref()
                .map_or_else(Vec::new, |(e, inl)| inl.iter().map(|&i| gamma_of(&data[i], m, e)).collect())
        })
        .collect();
    if epipoles.iter().all(Option::is_none) {
        return None;
    }
    Some(ParallaxFamily { walls: mats, epipoles, observed })
}

/// Per reference view `r`, per view `v`: the factor that ties `v`'s scale of `γ` to `r`'s
/// from the keyframe points both matched off the wall. A point at one depth has
/// `γ_v = k·γ_r`, so `k` is the ratio the common points agree on (their median, then a
/// least-squares fit over those within `tolerance` of it), with the number of points that
/// agree. `None` for a view with no epipole or fewer than `min_common` agreeing points, or
/// where they are not the larger part of the common ones (repeats of texture matched in one
/// view).
pub fn common_scales(
    family: &ParallaxFamily,
    matches: &[Vec<Correspondence>],
    params: &ParallaxFitParams,
    min_common: usize,
    tolerance: f64,
) -> Vec<Vec<Option<(f64, usize)>>> {
    // Per view: the off-wall matches on its epipolar lines, by keyframe point.
    let depths: Vec<std::collections::HashMap<(u64, u64), f64>> = (0..matches.len())
        .map(|v| {
            let Some(e) = family.epipoles[v] else { return Default::default() };
            let m = &family.walls[v];
            let Some(wall) = Homography::from_matrix(*m) else { return Default::default() };
            matches[v]
                .iter()
                .filter(|c| {
                    let r = c.residual(&wall);
                    r >= params.min_parallax_px
                        && r <= params.max_parallax_px
                        && epipolar_distance(c, m, &e) < params.line_px
                })
                .map(|c| ((c.key.x.to_bits(), c.key.y.to_bits()), gamma_of(c, m, &e)))
                .collect()
        })
        .collect();
    let tie = |r: usize, v: usize| -> Option<(f64, usize)> {
        if v == r {
            return family.epipoles[v].map(|_| (1.0, depths[v].len()));
        }
        let pairs: Vec<(f64, f64)> = depths[r]
            .iter()
            .filter_map(|(k, &g)| Some((g, *depths[v].get(k)?)))
            .filter(|(g, _)| g.abs() > 1e-12)
            .collect();
        if pairs.len() < min_common {
            return None;
        }
        let mut ratios: Vec<f64> = pairs.iter().map(|(g, gv)| gv / g).collect();
        ratios.sort_by(f64::total_cmp);
        let med = ratios[ratios.len() / 2];
        let agree: Vec<&(f64, f64)> =
            pairs.iter().filter(|(g, gv)| (gv / g / med - 1.0).abs() <= tolerance).collect();
        if agree.len() < min_common || 2 * agree.len() <= pairs.len() {
            return None;
        }
        let num: f64 = agree.iter().map(|(g, gv)| g * gv).sum();
        let den: f64 = agree.iter().map(|(g, _)| g * g).sum();
        Some((num / den, agree.len()))
    };
    (0..matches.len()).map(|r| (0..matches.len()).map(|v| tie(r, v)).collect()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A wall and two slabs seen by two views; outliers besides.
    #[test]
    fn finds_the_slabs_the_wall_leaves_out_and_matches_them_across_views() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let walls = [
            Homography::from_rows([[1.02, 0.01, 5.0], [-0.01, 1.0, 2.0], [1e-5, 0.0, 1.0]]).unwrap(),
            Homography::from_rows([[0.97, 0.02, -6.0], [0.0, 1.01, 1.0], [-2e-5, 1e-5, 1.0]]).unwrap(),
        ];
        // Slab planes: the wall plus a shift that grows with x (a plane closer to the camera).
        let slab = |v: usize, s: usize| {
            let d = [[6.0, 1.0], [-7.0, 0.5]][v][0] * [1.0, 0.6][s];
            walls[v]
                .after(&Homography::from_rows([[1.0, 0.0, d], [0.0, 1.0, 0.3 * d], [0.0, 0.0, 1.0]]).unwrap())
        };
        let regions = [(40.0, 40.0, 130.0, 90.0), (200.0, 20.0, 240.0, 200.0)];
        // The keyframe's corners, matched in both views.
        let corners: Vec<Point2<f64>> = (0..300)
            .map(|_| Point2::new(rng.random_range(0.0..320.0), rng.random_range(0.0..240.0)))
            .collect();
        let matches: Vec<Vec<Correspondence>> = (0..2)
            .map(|v| {
                let mut m = Vec::new();
                for &p in &corners {
                    let h = regions
                        .iter()
                        .position(|r| p.x >= r.0 && p.x <= r.2 && p.y >= r.1 && p.y <= r.3)
                        .map_or(walls[v], |s| slab(v, s));
                    m.push(Correspondence::new(p, h.apply(p).unwrap()));
                }
                for _ in 0..40 {
                    let p = Point2::new(rng.random_range(0.0..320.0), rng.random_range(0.0..240.0));
                    let q = Point2::new(rng.random_range(0.0..320.0), rng.random_range(0.0..240.0));
                    m.push(Correspondence::new(p, q));
                }
                m
            })
            .collect();
        let planes = fit_planes(&matches, &walls, &|_| false, &PlaneParams::default(), 1);
        assert_eq!(planes.len(), 2, "{planes:?}");
        for p in &planes {
            let s = regions
                .iter()
                .position(|r| p.bounds.0 >= r.0 - 1.0 && p.bounds.2 <= r.2 + 1.0)
                .expect("a plane's support lies on one slab");
            for v in 0..2 {
                let h = p.views[v].expect("both views see both slabs");
                let c = Point2::new(0.5 * (regions[s].0 + regions[s].2), 0.5 * (regions[s].1 + regions[s].3));
                let e = (h.apply(c).unwrap() - slab(v, s).apply(c).unwrap()).norm();
                assert!(e < 0.5, "view {v} slab {s}: off by {e}");
            }
        }
        // What the mask excludes is not fitted.
        let none = fit_planes(&matches, &walls, &|p| p.x < 260.0, &PlaneParams::default(), 1);
        assert!(none.is_empty(), "{none:?}");
    }

    /// Points off the wall displaced along lines through each view's epipole (one finite,
    /// one at infinity), among wall points and mismatches: the epipoles come back, and the
    /// depths of the agreeing matches are the true ones up to one scale per view.
    #[test]
    fn the_epipole_is_where_the_parallax_points_and_depths_follow_it() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let walls = [
            Homography::from_rows([[1.01, 0.02, 4.0], [-0.01, 0.99, -3.0], [2e-5, 1e-5, 1.0]]).unwrap(),
            Homography::from_rows([[0.98, -0.01, -5.0], [0.01, 1.02, 2.0], [-1e-5, 0.0, 1.0]]).unwrap(),
        ];
        let epipoles = [nalgebra::Vector3::new(900.0, 300.0, 1.0), nalgebra::Vector3::new(1.0, -0.05, 0.0)];
        let truth: Vec<(Point2<f64>, f64)> = (0..400)
            .map(|i| {
                let p = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
                (p, if i % 4 == 0 { rng.random_range(0.2..1.0) } else { 0.0 })
            })
            .collect();
        let matches: Vec<Vec<Correspondence>> = (0..2)
            .map(|v| {
                let m = walls[v].matrix();
                // The view's own scale of γ: a displacement of up to about 25 pixels.
                let e = epipoles[v] / epipoles[v].norm() * 25.0 * m[(2, 2)];
                let mut out: Vec<Correspondence> = truth
                    .iter()
                    .map(|&(p, g)| {
                        let q: nalgebra::Vector3<f64> = m * nalgebra::Vector3::new(p.x, p.y, 1.0) + e * g;
                        Correspondence::new(p, Point2::new(q.x / q.z, q.y / q.z))
                    })
                    .collect();
                for _ in 0..40 {
                    let p = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
                    let d =
                        nalgebra::Vector2::new(rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0));
                    out.push(Correspondence::new(p, walls[v].apply(p).unwrap() + d));
                }
                out
            })
            .collect();
        let fam = fit_parallax(&matches, &walls, &ParallaxFitParams::default(), 3).expect("parallax");
        for (v, &t) in epipoles.iter().enumerate() {
            let e = fam.epipoles[v].expect("each view has its epipole");
            assert!(e.normalize().cross(&t.normalize()).norm() < 1e-3, "view {v}: {e} vs {t}");
            // The agreeing matches are the points off the wall, their depths in one scale.
            assert!(fam.observed[v].len() >= 90, "view {v}: {} depths", fam.observed[v].len());
            let off: Vec<f64> = truth.iter().filter(|t| t.1 > 0.0).map(|t| t.1).collect();
            let (lo, hi) = fam.observed[v]
                .iter()
                .fold((f64::INFINITY, 0.0f64), |(a, b), g| (a.min(g.abs()), b.max(g.abs())));
            let (tlo, thi) = off.iter().fold((f64::INFINITY, 0.0f64), |(a, b), &g| (a.min(g), b.max(g)));
            assert!(
                (hi / lo - thi / tlo).abs() < 0.05 * thi / tlo,
                "view {v}: depth range {lo}..{hi} vs {tlo}..{thi}"
            );
        }
        // A flat wall: no parallax.
        let flat: Vec<Vec<Correspondence>> = (0..2)
            .map(|v| truth.iter().map(|&(p, _)| Correspondence::new(p, walls[v].apply(p).unwrap())).collect())
            .collect();
        assert!(fit_parallax(&flat, &walls, &ParallaxFitParams::default(), 3).is_none());
    }

    /// Three views of points off the wall, each view's `γ` in a scale of its own. Views 0
    /// and 1 share the points, a third of them matched in view 1 at a repeat of texture (a
    /// wrong depth on the right line): the ratio of their scales comes back from the points
    /// that agree. View 2 shares too few points to say.
    #[test]
    fn points_two_views_matched_off_the_wall_tie_their_scales_of_depth() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let walls = [
            Homography::from_rows([[1.01, 0.02, 4.0], [-0.01, 0.99, -3.0], [2e-5, 1e-5, 1.0]]).unwrap(),
            Homography::from_rows([[0.98, -0.01, -5.0], [0.01, 1.02, 2.0], [-1e-5, 0.0, 1.0]]).unwrap(),
            Homography::from_rows([[1.0, 0.0, 7.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]]).unwrap(),
        ];
        // The views' epipoles (as for a wall matrix with a unit corner), their lengths (the
        // scales of γ) far apart: 0.002 × 12000 is a displacement of 24 pixels at γ = 1.
        let epipoles = [
            nalgebra::Vector3::new(9000.0, 3000.0, 10.0),
            nalgebra::Vector3::new(-12000.0, 600.0, 0.0),
            nalgebra::Vector3::new(-300.0, 5000.0, 4.0),
        ];
        let truth: Vec<(Point2<f64>, f64)> = (0..400)
            .map(|i| {
                let p = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
                (p, if i % 4 == 0 { rng.random_range(0.2..1.0) } else { 0.0 })
            })
            .collect();
        let matches: Vec<Vec<Correspondence>> = (0..3)
            .map(|v| {
                let m = walls[v].matrix();
                let mut shared = 0;
                truth
                    .iter()
                    .enumerate()
                    .filter_map(|(i, &(p, g))| {
                        if v == 2 && g > 0.0 {
                            // View 2 matches only a few of the points off the wall.
                            shared += 1;
                            if shared > 4 {
                                return None;
                            }
                        }
                        // A repeat: the same line, another depth.
                        let g = if v == 1 && g > 0.0 && i % 3 == 0 { g * 1.6 + 0.15 } else { g };
                        let q: nalgebra::Vector3<f64> =
                            m * nalgebra::Vector3::new(p.x, p.y, 1.0) + epipoles[v] * g * 0.002 * m[(2, 2)];
                        Some(Correspondence::new(p, Point2::new(q.x / q.z, q.y / q.z)))
                    })
                    .collect()
            })
            .collect();
        // View 2 has its own off-wall points elsewhere, enough for its epipole.
        let mut matches = matches;
        for _ in 0..60 {
            let p = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            let q: nalgebra::Vector3<f64> = walls[2].matrix() * nalgebra::Vector3::new(p.x, p.y, 1.0)
                + epipoles[2] * rng.random_range(0.2..1.0) * 0.002 * walls[2].matrix()[(2, 2)];
            matches[2].push(Correspondence::new(p, Point2::new(q.x / q.z, q.y / q.z)));
        }
        let params = ParallaxFitParams::default();
        let fam = fit_parallax(&matches, &walls, &params, 3).expect("parallax");
        assert!(fam.epipoles.iter().all(Option::is_some), "every view has its epipole");
        let k = &common_scales(&fam, &matches, &params, 6, 0.2)[0];
        let (k1, n1) = k[1].expect("views 0 and 1 share enough points");
        assert_eq!(k[0].map(|k| k.0), Some(1.0));
        assert!(k[2].is_none(), "view 2 shares 4 points: {:?}", k[2]);
        // Under the tied scales, a point off the wall has one depth in both views.
        let tied = fam.scaled(&[Some(1.0), Some(k1), None]);
        let (e0, e1) = (tied.epipoles[0].unwrap(), tied.epipoles[1].unwrap());
        let mut checked = 0;
        for (i, &(p, g)) in truth.iter().enumerate() {
            if g == 0.0 || i % 3 == 0 {
                continue;
            }
            if (0..2).any(|v| matches[v][i].residual(&walls[v]) < params.min_parallax_px) {
                continue;
            }
            let g0 = gamma_of(&matches[0][i], &tied.walls[0], &e0);
            let g1 = gamma_of(&matches[1][i], &tied.walls[1], &e1);
            assert!((g1 / g0 - 1.0).abs() < 0.01, "at {p}: {g0} vs {g1}");
            checked += 1;
        }
        assert!(checked > 40 && n1 == checked, "{checked} points, {n1} agreeing");
    }
}
