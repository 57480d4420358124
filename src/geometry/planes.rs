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
}
