//! Issue 14: facades that are not flat. On generated facades with slabs standing off the
//! wall (`synth::facade`), the multi-plane fill — each masked pixel takes the plane under
//! which the views agree — must beat the single-plane fill through the wall's homography;
//! and on a flat wall the plane step must change nothing when it is given no planes.

use clearview::imaging::metrics::masked_psnr;
use clearview::inpaint::{FillExtras, FillParams, Source, fill, fill_with};
use clearview::synth::facade::parallax_case;

#[test]
fn choosing_the_plane_per_pixel_beats_the_wall_alone_on_a_facade_with_slabs() {
    let (mut single, mut multi) = (0.0, 0.0);
    let seeds = [1u64, 3, 5];
    for seed in seeds {
        let c = parallax_case(320, 240, 3, seed, false);
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let params = FillParams::default();
        let one = fill(&c.key, &c.mask, &sources, &params, 1, &mut ());
        let planes = c.true_surfaces(12);
        assert!(!planes.is_empty(), "seed {seed}: the keyframe shows no slab");
        let extras = FillExtras { planes: &planes, ..FillExtras::default() };
        let many = fill_with(&c.key, &c.mask, &sources, &extras, &params, 1, &mut ());
        // Some masked pixels were filled through a slab's plane: the provenance says which.
        let off_wall = (0..c.mask.len())
            .filter(|&i| c.mask.as_slice()[i] > 127 && many.surface.as_slice()[i] > 0)
            .count();
        assert!(off_wall > 100, "seed {seed}: {off_wall} pixels filled through a slab");
        let (a, b) =
            (masked_psnr(&one.image, &c.truth, &c.mask), masked_psnr(&many.image, &c.truth, &c.mask));
        eprintln!("seed {seed}: wall only {a:.2} dB, planes {b:.2} dB");
        single += a;
        multi += b;
    }
    let n = seeds.len() as f64;
    let (single, multi) = (single / n, multi / n);
    assert!(multi > single + 1.5, "multi-plane {multi:.2} dB vs wall only {single:.2} dB");
}

#[test]
fn with_no_planes_the_fill_is_the_single_plane_fill() {
    let c = parallax_case(160, 120, 2, 2, true);
    let sources: Vec<Source<'_>> =
        c.views.iter().zip(c.wall()).map(|(image, homography)| Source { image, homography }).collect();
    let params = FillParams::default();
    let a = fill(&c.key, &c.mask, &sources, &params, 1, &mut ());
    let b = fill_with(&c.key, &c.mask, &sources, &FillExtras::default(), &params, 1, &mut ());
    assert!(a.image == b.image && a.provenance == b.provenance);
    assert!(b.surface.as_slice().iter().all(|&s| s == 0));
}
