//! Planar homographies: the type, its algebra, and the normalised DLT of the paper's
//! eq. (9) (pure layer).
//!
//! Convention (ARCHITECTURE.md): a view's `H` maps keyframe pixel coordinates to view pixel
//! coordinates, `x_view ~ H · x_key`, 0-based with pixel centres at integers.

use nalgebra::{DMatrix, Matrix3, Point2, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// A 3×3 projective map of the plane, kept normalised to unit Frobenius norm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Homography(Matrix3<f64>);

/// Why a set of point pairs does not determine a homography.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum DltError {
    #[error("{have} point pairs, at least 4 are needed")]
    TooFewPoints { have: usize },
    #[error("the points are degenerate (coincident or collinear)")]
    Degenerate,
}

impl Homography {
    pub fn identity() -> Self {
        Self(Matrix3::identity())
    }

    /// Wraps a matrix; `None` when it is singular or not finite.
    pub fn from_matrix(m: Matrix3<f64>) -> Option<Self> {
        if !m.iter().all(|v| v.is_finite()) {
            return None;
        }
        let norm = m.norm();
        if norm < 1e-300 || m.determinant().abs() / norm.powi(3) < 1e-15 {
            return None;
        }
        Some(Self(m / norm))
    }

    /// From row-major rows, as in the Oxford `H1toNp` files and our JSON.
    pub fn from_rows(rows: [[f64; 3]; 3]) -> Option<Self> {
        Self::from_matrix(Matrix3::from_fn(|r, c| rows[r][c]))
    }

    /// A pure translation by `(dx, dy)`.
    pub fn translation(dx: f64, dy: f64) -> Self {
        Self::from_rows([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]).expect("translation is regular")
    }

    /// A scaling about the origin by `s` (maps image coordinates to those of an image
    /// resized by `s` when pixel centres scale as `x' = s·x`).
    pub fn scaling(s: f64) -> Self {
        Self::from_rows([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, 1.0]]).expect("scaling is regular")
    }

    pub fn matrix(&self) -> &Matrix3<f64> {
        &self.0
    }

    /// Row-major rows scaled so that `h33 = 1` where that is possible (the usual way to
    /// print a homography), otherwise unit Frobenius norm.
    pub fn rows(&self) -> [[f64; 3]; 3] {
        let m = self.0;
        let s = if m[(2, 2)].abs() > 1e-12 { 1.0 / m[(2, 2)] } else { 1.0 };
        std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)] * s))
    }

    /// Maps a point; `None` when it lands at (or behind) infinity.
    #[inline]
    pub fn apply(&self, p: Point2<f64>) -> Option<Point2<f64>> {
        let m = &self.0;
        let w = m[(2, 0)] * p.x + m[(2, 1)] * p.y + m[(2, 2)];
        if w.abs() < 1e-12 {
            return None;
        }
        Some(Point2::new(
            (m[(0, 0)] * p.x + m[(0, 1)] * p.y + m[(0, 2)]) / w,
            (m[(1, 0)] * p.x + m[(1, 1)] * p.y + m[(1, 2)]) / w,
        ))
    }

    /// The homogeneous `w` a point gets; its sign says on which side of the horizon the
    /// point is.
    #[inline]
    pub fn w(&self, p: Point2<f64>) -> f64 {
        let m = &self.0;
        m[(2, 0)] * p.x + m[(2, 1)] * p.y + m[(2, 2)]
    }

    pub fn inverse(&self) -> Option<Self> {
        self.0.try_inverse().and_then(Self::from_matrix)
    }

    /// `self ∘ first`: apply `first`, then `self`.
    pub fn after(&self, first: &Homography) -> Self {
        Self::from_matrix(self.0 * first.0).expect("product of regular matrices is regular")
    }

    /// The same map expressed for images resized by `s_from` (source) and `s_to` (target):
    /// `S_to · H · S_from⁻¹`.
    pub fn rescaled(&self, s_from: f64, s_to: f64) -> Self {
        Self::scaling(s_to).after(self).after(&Self::scaling(1.0 / s_from))
    }

    /// Mean distance between where `self` and `other` send the four corners of a
    /// `width × height` image: the usual accuracy measure for homographies.
    pub fn mean_corner_error(&self, other: &Homography, width: usize, height: usize) -> f64 {
        let corners = image_corners(width, height);
        corners
            .iter()
            .map(|&c| match (self.apply(c), other.apply(c)) {
                (Some(a), Some(b)) => (a - b).norm(),
                _ => f64::INFINITY,
            })
            .sum::<f64>()
            / 4.0
    }

    /// The median, over an 8 × 8 grid of cell centres of a `width × height` image that `keep`
    /// accepts, of the distance between where `self` and `other` send them (infinite where
    /// either sends a point nowhere, or `other` behind the camera); `None` when no point is
    /// kept. Whether two maps place an image differently, robust to a corner far off.
    pub fn median_grid_gap(
        &self,
        other: &Homography,
        width: f64,
        height: f64,
        keep: impl Fn(Point2<f64>) -> bool,
    ) -> Option<f64> {
        const N: usize = 8;
        let mut d = Vec::with_capacity(N * N);
        for j in 0..N {
            for i in 0..N {
                let p =
                    Point2::new((i as f64 + 0.5) * width / N as f64, (j as f64 + 0.5) * height / N as f64);
                if !keep(p) {
                    continue;
                }
                d.push(match (self.apply(p), other.apply(p)) {
                    (Some(a), Some(b)) if other.w(p) > 0.0 => (a - b).norm(),
                    _ => f64::INFINITY,
                });
            }
        }
        if d.is_empty() {
            return None;
        }
        d.sort_by(f64::total_cmp);
        Some(d[d.len() / 2])
    }

    /// The local area scale `|det J|` of the map at `p` (how much a small patch around
    /// `p` grows).
    pub fn area_scale(&self, p: Point2<f64>) -> f64 {
        let m = &self.0;
        let w = self.w(p);
        // Determinant of the Jacobian of a homography: det(H) / w³.
        m.determinant() / (w * w * w)
    }

    /// The 2×2 Jacobian of the map at `p`, row-major.
    pub fn jacobian(&self, p: Point2<f64>) -> [[f64; 2]; 2] {
        let m = &self.0;
        let w = self.w(p);
        let u = m[(0, 0)] * p.x + m[(0, 1)] * p.y + m[(0, 2)];
        let v = m[(1, 0)] * p.x + m[(1, 1)] * p.y + m[(1, 2)];
        let w2 = w * w;
        [
            [(m[(0, 0)] * w - u * m[(2, 0)]) / w2, (m[(0, 1)] * w - u * m[(2, 1)]) / w2],
            [(m[(1, 0)] * w - v * m[(2, 0)]) / w2, (m[(1, 1)] * w - v * m[(2, 1)]) / w2],
        ]
    }
}

/// The centres of the four corner pixels of a `width × height` image.
pub fn image_corners(width: usize, height: usize) -> [Point2<f64>; 4] {
    let (w, h) = ((width.max(1) - 1) as f64, (height.max(1) - 1) as f64);
    [Point2::new(0.0, 0.0), Point2::new(w, 0.0), Point2::new(w, h), Point2::new(0.0, h)]
}

/// A matrix in the row-major nested-list form used in JSON reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Rows(pub [[f64; 3]; 3]);

impl From<&Homography> for Rows {
    fn from(h: &Homography) -> Self {
        Rows(h.rows())
    }
}

/// Hartley's conditioning: the similarity that moves the centroid to the origin and makes
/// the mean distance from it √2.
fn conditioner(points: impl Iterator<Item = Point2<f64>> + Clone) -> Option<Matrix3<f64>> {
    let n = points.clone().count() as f64;
    let (sx, sy) = points.clone().fold((0.0, 0.0), |(a, b), p| (a + p.x, b + p.y));
    let (cx, cy) = (sx / n, sy / n);
    let mean_dist = points.map(|p| ((p.x - cx).powi(2) + (p.y - cy).powi(2)).sqrt()).sum::<f64>() / n;
    if mean_dist < 1e-9 {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_dist;
    Some(Matrix3::new(s, 0.0, -s * cx, 0.0, s, -s * cy, 0.0, 0.0, 1.0))
}

/// Homography from `n ≥ 4` point pairs by the normalised DLT: condition both point sets,
/// solve eq. (9) by SVD (the right singular vector of the smallest singular value), undo
/// the conditioning.
pub fn dlt(key: &[Point2<f64>], view: &[Point2<f64>]) -> Result<Homography, DltError> {
    assert_eq!(key.len(), view.len(), "dlt needs paired points");
    let n = key.len();
    if n < 4 {
        return Err(DltError::TooFewPoints { have: n });
    }
    let tk = conditioner(key.iter().copied()).ok_or(DltError::Degenerate)?;
    let tv = conditioner(view.iter().copied()).ok_or(DltError::Degenerate)?;
    // Pad to at least 9 rows so the thin SVD yields the full right null space.
    let rows = (2 * n).max(9);
    let mut a = DMatrix::<f64>::zeros(rows, 9);
    for (i, (k, v)) in key.iter().zip(view).enumerate() {
        let k = tk * Vector3::new(k.x, k.y, 1.0);
        let v = tv * Vector3::new(v.x, v.y, 1.0);
        let (u, w, up, vp) = (k.x, k.y, v.x, v.y);
        let r = 2 * i;
        a.row_mut(r).copy_from_slice(&[u, w, 1.0, 0.0, 0.0, 0.0, -u * up, -w * up, -up]);
        a.row_mut(r + 1).copy_from_slice(&[0.0, 0.0, 0.0, u, w, 1.0, -u * vp, -w * vp, -vp]);
    }
    let svd = a.svd(false, true);
    let vt = svd.v_t.as_ref().ok_or(DltError::Degenerate)?;
    let sv = &svd.singular_values;
    let smallest = sv.imin();
    // A second (near-)zero singular value means the points do not pin H down.
    let mut sorted: Vec<f64> = sv.iter().copied().collect();
    sorted.sort_by(f64::total_cmp);
    if sorted[1] <= 1e-9 * sorted[8].max(1e-300) {
        return Err(DltError::Degenerate);
    }
    let h = vt.row(smallest);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let tv_inv = tv.try_inverse().ok_or(DltError::Degenerate)?;
    Homography::from_matrix(tv_inv * hn * tk).ok_or(DltError::Degenerate)
}

/// Twice the signed area of the triangle `a b c` (positive when counter-clockwise in a
/// y-up frame).
#[inline]
pub fn cross(a: Point2<f64>, b: Point2<f64>, c: Point2<f64>) -> f64 {
    (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x)
}

/// The least-squares similarity `v = a·k + b` (complex `a`) of point pairs, as rows.
pub fn similarity_lsq(pairs: &[&(Point2<f64>, Point2<f64>)]) -> Option<[[f64; 3]; 3]> {
    if pairs.len() < 2 {
        return None;
    }
    let n = pairs.len() as f64;
    let kc = pairs.iter().fold(nalgebra::Vector2::zeros(), |a, (k, _)| a + k.coords) / n;
    let vc = pairs.iter().fold(nalgebra::Vector2::zeros(), |a, (_, v)| a + v.coords) / n;
    let (mut re, mut im, mut nk) = (0.0, 0.0, 0.0);
    for (k, v) in pairs {
        let (dk, dv) = (k.coords - kc, v.coords - vc);
        re += dv.x * dk.x + dv.y * dk.y;
        im += dv.y * dk.x - dv.x * dk.y;
        nk += dk.norm_squared();
    }
    if nk < 1e-9 {
        return None;
    }
    let (ar, ai) = (re / nk, im / nk);
    let b = (vc.x - (ar * kc.x - ai * kc.y), vc.y - (ai * kc.x + ar * kc.y));
    Some([[ar, -ai, b.0], [ai, ar, b.1], [0.0, 0.0, 1.0]])
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn sample_h() -> Homography {
        Homography::from_rows([[0.9, 0.12, 14.0], [-0.08, 1.05, -6.0], [2e-4, -1e-4, 1.0]]).unwrap()
    }

    #[test]
    fn inverse_undoes_apply() {
        let h = sample_h();
        let hi = h.inverse().unwrap();
        for p in [Point2::new(0.0, 0.0), Point2::new(123.4, 56.7), Point2::new(640.0, 480.0)] {
            let q = hi.apply(h.apply(p).unwrap()).unwrap();
            assert!((p - q).norm() < 1e-9);
        }
    }

    #[test]
    fn dlt_recovers_exact_h_from_four_and_many_points() {
        let h = sample_h();
        let key: Vec<_> =
            [(0.0, 0.0), (300.0, 10.0), (280.0, 240.0), (5.0, 200.0), (150.0, 100.0), (40.0, 60.0)]
                .iter()
                .map(|&(x, y)| Point2::new(x, y))
                .collect();
        let view: Vec<_> = key.iter().map(|&p| h.apply(p).unwrap()).collect();
        for n in [4, 6] {
            let est = dlt(&key[..n], &view[..n]).unwrap();
            assert!(est.mean_corner_error(&h, 320, 240) < 1e-8, "n = {n}");
        }
    }

    #[test]
    fn dlt_rejects_collinear_points() {
        let key: Vec<_> = (0..5).map(|i| Point2::new(i as f64, 2.0 * i as f64)).collect();
        let view = key.clone();
        assert_eq!(dlt(&key, &view), Err(DltError::Degenerate));
        assert_eq!(dlt(&key[..3], &view[..3]), Err(DltError::TooFewPoints { have: 3 }));
    }

    #[test]
    fn rescaling_commutes_with_resizing() {
        let h = sample_h();
        let small = h.rescaled(1.0, 1.0).rescaled(0.5, 0.5);
        let p = Point2::new(100.0, 80.0);
        let big = h.apply(Point2::new(p.x * 2.0, p.y * 2.0)).unwrap();
        let q = small.apply(p).unwrap();
        assert!((q.x - big.x * 0.5).abs() < 1e-9 && (q.y - big.y * 0.5).abs() < 1e-9);
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let h = sample_h();
        let p = Point2::new(200.0, 150.0);
        let j = h.jacobian(p);
        let e = 1e-4;
        let dx = (h.apply(Point2::new(p.x + e, p.y)).unwrap() - h.apply(Point2::new(p.x - e, p.y)).unwrap())
            / (2.0 * e);
        assert!((j[0][0] - dx.x).abs() < 1e-6 && (j[1][0] - dx.y).abs() < 1e-6);
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        assert!((det - h.area_scale(p)).abs() < 1e-6);
    }
}
