//! Laws of the projective geometry, checked on random homographies (proptest): the
//! inverse undoes, composition associates, the DLT returns the map that made exact
//! correspondences, the robust estimators do too, and the Jacobian agrees with the map.

use clearview::geometry::robust::Consensus;
use clearview::geometry::{Correspondence, Homography, Method, RobustParams, dlt};
use nalgebra::Point2;
use proptest::prelude::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const W: f64 = 640.0;
const H: f64 = 480.0;

/// A plausible keyframe → view map for a 640×480 frame: rotation, anisotropic scale,
/// shear, perspective and shift, all of moderate size, so the frame stays in front.
fn homography() -> impl Strategy<Value = Homography> {
    (
        -0.6..0.6f64,
        0.6..1.6f64,
        0.6..1.6f64,
        -0.2..0.2f64,
        -6e-4..6e-4f64,
        -6e-4..6e-4f64,
        -80.0..80.0f64,
        -80.0..80.0f64,
    )
        .prop_map(|(a, sx, sy, shear, p, q, tx, ty)| {
            let (c, s) = (a.cos(), a.sin());
            let m = Homography::from_rows([[sx * c, -sy * s + shear, tx], [sx * s, sy * c, ty], [p, q, 1.0]])
                .expect("regular");
            // About the frame's centre, as cameras turn.
            Homography::translation(W / 2.0, H / 2.0)
                .after(&m)
                .after(&Homography::translation(-W / 2.0, -H / 2.0))
        })
        .prop_filter("frame stays in front of the camera", |h| {
            clearview::geometry::homography::image_corners(W as usize, H as usize)
                .iter()
                .all(|&p| h.w(p) > 0.0)
        })
}

fn point() -> impl Strategy<Value = Point2<f64>> {
    (0.0..W, 0.0..H).prop_map(|(x, y)| Point2::new(x, y))
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn inverse_undoes_the_map(h in homography(), p in point()) {
        let back = h.inverse().unwrap().apply(h.apply(p).unwrap()).unwrap();
        prop_assert!((back - p).norm() < 1e-6, "{p:?} came back as {back:?}");
        prop_assert!(h.after(&h.inverse().unwrap()).mean_corner_error(&Homography::identity(), 640, 480) < 1e-6);
    }

    #[test]
    fn composition_applies_right_to_left_and_associates(a in homography(), b in homography(), c in homography(), p in point()) {
        let ab = a.after(&b);
        if let (Some(direct), Some(step)) = (ab.apply(p), b.apply(p).and_then(|q| a.apply(q))) {
            prop_assert!((direct - step).norm() < 1e-6 * (1.0 + step.coords.norm()));
        }
        let left = a.after(&b).after(&c);
        let right = a.after(&b.after(&c));
        prop_assert!(left.mean_corner_error(&right, 640, 480) < 1e-6);
    }

    #[test]
    fn dlt_returns_the_map_that_made_exact_correspondences(h in homography(), pts in prop::collection::vec(point(), 4..40)) {
        let view: Vec<_> = pts.iter().map(|&p| h.apply(p).unwrap()).collect();
        // Four or more points in general position pin H down; near-degenerate draws are
        // refused, never answered wrongly.
        match dlt(&pts, &view) {
            Ok(est) => {
                for (&k, &v) in pts.iter().zip(&view) {
                    prop_assert!((est.apply(k).unwrap() - v).norm() < 1e-5);
                }
            }
            Err(_) => prop_assume!(false),
        }
    }

    #[test]
    fn every_estimator_recovers_h_from_exact_correspondences(h in homography(), seed in any::<u64>()) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let data: Vec<Correspondence> = (0..60)
            .map(|_| {
                use rand::Rng;
                let k = Point2::new(rng.random_range(0.0..W), rng.random_range(0.0..H));
                Correspondence::new(k, h.apply(k).unwrap())
            })
            .collect();
        for method in [Method::Lmeds, Method::Msac, Method::Ransac] {
            let params = RobustParams { method, ..RobustParams::default() };
            let est = Consensus::new(params, ChaCha8Rng::seed_from_u64(seed)).estimate(&data).unwrap();
            prop_assert!(est.homography.mean_corner_error(&h, 640, 480) < 1e-4, "{method:?}");
            prop_assert_eq!(est.inliers.len(), 60);
        }
    }

    #[test]
    fn the_jacobian_is_the_local_linear_map(h in homography(), p in point()) {
        let j = h.jacobian(p);
        let e = 1e-4;
        let base = h.apply(p).unwrap();
        let dx = (h.apply(Point2::new(p.x + e, p.y)).unwrap() - base) / e;
        let dy = (h.apply(Point2::new(p.x, p.y + e)).unwrap() - base) / e;
        prop_assert!((dx.x - j[0][0]).abs() < 1e-4 && (dx.y - j[1][0]).abs() < 1e-4);
        prop_assert!((dy.x - j[0][1]).abs() < 1e-4 && (dy.y - j[1][1]).abs() < 1e-4);
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        prop_assert!((det - h.area_scale(p)).abs() < 1e-6 * det.abs().max(1.0));
    }
}
