//! Alignment on real photographs: the Oxford affine and HPatches sequences against their
//! ground truth, and the multi-view building sets.

mod common;

use std::path::Path;

use clearview::align::{AlignParams, Alignment, Frame, align};
use clearview::geometry::Homography;
use clearview::imaging::convert::to_luminance;
use clearview::imaging::{GrayF32, bilinear};
use nalgebra::Point2;

fn frame(path: &Path, params: &AlignParams) -> Frame {
    let img = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    Frame::new(to_luminance(&img), params)
}

/// Pairs whose mean corner error must be at most 1 px (issue 2).
const REQUIRED: &[(&str, &[usize])] = &[
    ("graf", &[2, 3]),
    ("wall", &[2, 3, 4]),
    ("boat", &[2, 3]),
    ("leuven", &[2, 3, 4, 5, 6]),
    ("bikes", &[2, 3]),
    ("trees", &[2, 3]),
];

#[test]
fn oxford_and_hpatches_pairs_against_ground_truth() {
    let Some(data) = common::data_dir() else { return };
    let params = AlignParams::default();
    let mut failures = Vec::new();
    println!("{:<22} {:>9} {:>8} {:>8} {:>9}  verdict", "pair", "error px", "putative", "inliers", "median");
    let sequences: Vec<(String, std::path::PathBuf)> =
        ["graf", "wall", "boat", "bark", "bikes", "trees", "leuven", "ubc"]
            .iter()
            .map(|s| (format!("oxford/{s}"), data.join("oxford").join(s)))
            .chain(
                ["v_churchill", "v_wormhole"]
                    .iter()
                    .map(|s| (format!("hpatches/{s}"), data.join("hpatches").join(s))),
            )
            .collect();
    for (name, seq) in &sequences {
        let key_path = common::sequence_image(seq, 1);
        let key = frame(&key_path, &params);
        for n in 2..=6 {
            let view = frame(&common::sequence_image(seq, n), &params);
            // graf's refined files were fitted densely over the whole frame, off-plane car
            // roof included, and are pulled by it; the originals fit the wall better (see
            // `graf_estimate_fits_the_wall_better_than_the_refined_truth`).
            let truth = if name == "oxford/graf" {
                common::read_homography(&seq.join(format!("H1to{n}p")))
            } else {
                common::ground_truth(seq, n)
            };
            let a: Alignment = align(&key, &view, &params, None);
            let err = a
                .homography
                .map_or(f64::INFINITY, |h| h.mean_corner_error(&truth, key.width(), key.height()));
            let verdict = a.rejection.as_ref().map_or("accepted".to_string(), |r| format!("rejected: {r}"));
            println!(
                "{:<22} {:>9.3} {:>8} {:>8} {:>9.3}  {verdict}",
                format!("{name} 1->{n}"),
                err,
                a.putative,
                a.inliers,
                a.median_residual_px
            );
            let seq_name = name.trim_start_matches("oxford/");
            let required = REQUIRED.iter().any(|(s, ns)| *s == seq_name && ns.contains(&n));
            if required && (!a.accepted() || err > 1.0) {
                failures.push(format!("{name} 1->{n}: error {err:.3} px, {verdict}"));
            }
            // Whatever is accepted must be right: a wrong homography corrupts a fill.
            // (HPatches pairs are reported, not held to this: their mostly featureless
            // corners make the corner error an extrapolation; BENCHMARKS.md compares.)
            if name.starts_with("oxford") && a.accepted() && err > 5.0 {
                failures.push(format!("{name} 1->{n}: accepted with error {err:.3} px"));
            }
        }
    }
    assert!(failures.is_empty(), "failures:\n{}", failures.join("\n"));
}

/// A facade and the square in front of it are two planes, and the points near where they
/// meet are inliers of both models, at the same place in the view. That is not a repeating
/// pattern. parapano_ece's ece4, with a tree and a person pasted on the facade where
/// `examples/service_cases` puts them for seed 8 (`photo-ece-8`), against ece3, was refused
/// without its mask as "a repeating pattern (177 and 103 points)": 41 of the second model's
/// inliers were the winner's, 36 of them sent within 3 px of where the winner sends them.
/// `fill --mask auto` aligns without a mask, so the building's best view was lost and the
/// mask found missed both occluders.
#[test]
fn two_planes_that_share_their_seam_are_not_a_repeating_pattern() {
    use clearview::imaging::Mask;
    use clearview::imaging::convert::{luminance, to_rgb};
    use clearview::synth::{Occluder, dilate_mask, paint_occluder};
    use rand::{Rng, SeedableRng};

    let Some(data) = common::data_dir() else { return };
    let set = data.join("multiview/parapano_ece");
    let load = |f: &str| {
        let p = set.join(f);
        to_rgb(&image::open(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display())))
    };
    let mut key = load("ece4.jpeg");
    let (w, h) = (key.width() as f32, key.height() as f32);
    // `examples/service_cases.rs`'s `photo` for seed 8: a tree and a person.
    let seed = 8u64;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
    let mut painted = Mask::new(key.width(), key.height(), 0);
    for (i, kind) in [Occluder::Tree, Occluder::Person].into_iter().enumerate() {
        let size = match kind {
            Occluder::Tree => rng.random_range(0.3..0.42),
            _ => rng.random_range(0.25..0.35),
        } * w.min(h);
        let cx = rng.random_range(0.22..0.78) * w;
        let cy = rng.random_range(0.35..0.65) * h;
        paint_occluder(&mut key, Some(&mut painted), kind, cx, cy, size, seed * 10 + i as u64);
    }
    let params = AlignParams::default();
    let view = Frame::new(luminance(&load("ece3.jpeg")), &params);
    let mut masked = Frame::new(luminance(&key), &params);
    masked.set_mask(Some(&dilate_mask(&painted, 2)));
    let reference = align(&masked, &view, &params, None);
    assert!(reference.accepted(), "with its mask: {reference:?}");
    let a = align(&Frame::new(luminance(&key), &params), &view, &params, None);
    assert!(a.accepted(), "without its mask: {:?}", a.rejection);
    let gap = a
        .homography
        .unwrap()
        .median_grid_gap(&reference.homography.unwrap(), w as f64, h as f64, |_| true)
        .unwrap();
    println!("without the mask: {} inliers, {gap:.2} px from the fit with it", a.inliers);
    assert!(gap < 3.0, "{gap:.2} px from the fit with the mask");
}

#[test]
fn unrelated_scenes_are_rejected() {
    let Some(data) = common::data_dir() else { return };
    let params = AlignParams::default();
    let graf = frame(&data.join("oxford/graf/img1.png"), &params);
    let boat = frame(&data.join("oxford/boat/img1.png"), &params);
    let a = align(&graf, &boat, &params, None);
    assert!(!a.accepted(), "graf against boat was accepted: {a:?}");
    let wall = frame(&data.join("oxford/wall/img1.png"), &params);
    let leuven = frame(&data.join("oxford/leuven/img1.png"), &params);
    let b = align(&wall, &leuven, &params, None);
    assert!(!b.accepted(), "wall against leuven was accepted: {b:?}");
}

/// Normalised cross-correlation of `key` with `view` warped through `h`, over the key's
/// rows `rows` (pixels that land outside the view are left out).
fn warped_ncc(key: &GrayF32, view: &GrayF32, h: &Homography, rows: std::ops::Range<usize>) -> f64 {
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for y in rows {
        for x in 0..key.width() {
            let q = h.apply(Point2::new(x as f64, y as f64)).unwrap();
            if let Some(v) = bilinear(view, q.x as f32, q.y as f32) {
                a.push(key.get(x, y) as f64);
                b.push(v as f64);
            }
        }
    }
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(&b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}

/// graf img1 has a car roof in front of the wall along its bottom. Above it, on the planar
/// wall itself, clearview's homography must agree with the images at least as well as the
/// refined ground truth does: that is why the main test measures graf against the original.
#[test]
fn graf_estimate_fits_the_wall_better_than_the_refined_truth() {
    let Some(data) = common::data_dir() else { return };
    let seq = data.join("oxford/graf");
    let params = AlignParams::default();
    let key_img = to_luminance(&image::open(seq.join("img1.png")).unwrap());
    let key = Frame::new(key_img.clone(), &params);
    for n in [2, 3] {
        let view_img = to_luminance(&image::open(seq.join(format!("img{n}.png"))).unwrap());
        let view = Frame::new(view_img.clone(), &params);
        let ours = align(&key, &view, &params, None).homography.unwrap();
        let refined = common::read_homography(&seq.join(format!("H1to{n}p.refined")));
        let wall = 0..500;
        let (a, b) = (
            warped_ncc(&key_img, &view_img, &ours, wall.clone()),
            warped_ncc(&key_img, &view_img, &refined, wall),
        );
        println!("graf 1->{n}: wall NCC ours {a:.4}, refined truth {b:.4}");
        assert!(a >= b, "graf 1->{n}: ours {a:.4} < refined {b:.4}");
    }
}
