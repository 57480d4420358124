//! Issue 14: facades that are not flat. On generated facades with slabs standing off the
//! wall (`synth::facade`), the multi-plane fill — each masked pixel takes the plane under
//! which the views agree — must beat the single-plane fill through the wall's homography;
//! and on a flat wall the plane step must change nothing when it is given no planes.

mod common;

use clearview::imaging::metrics::masked_psnr;
use clearview::inpaint::{FillExtras, FillParams, Source, fill, fill_with};
use clearview::synth::facade::parallax_case;
use common::fill_in_batches;

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

/// The dense sweep (plane + parallax) finds the slabs of a facade where the keyframe's
/// surroundings or the views among themselves show them, true slab planes in every view
/// they have (all but a few pixels of the hole filled through one of those), and the fill
/// through them beats the wall alone; on the same scene without slabs it finds nothing, so
/// the fill stays the single-plane one.
#[test]
fn the_sweep_finds_slabs_where_there_are_some_and_nothing_on_a_flat_wall() {
    use clearview::align::{AlignParams, Frame, align};
    use clearview::imaging::convert::luminance;
    use clearview::inpaint::parallax::{SweepParams, swept_planes};
    // The walls as the product finds them: aligned views.
    let aligned = |key: &clearview::imaging::RgbF32, views: &[clearview::imaging::RgbF32]| {
        let params = AlignParams::default();
        let kf = Frame::new(luminance(key), &params);
        views
            .iter()
            .map(|v| {
                align(&kf, &Frame::new(luminance(v), &params), &params, None).homography.expect("aligned")
            })
            .collect::<Vec<_>>()
    };
    let c = parallax_case(640, 480, 3, 13, false);
    let walls = aligned(&c.key, &c.views);
    let grays: Vec<_> = c.views.iter().map(luminance).collect();
    let refs: Vec<&_> = grays.iter().collect();
    let planes = swept_planes(&luminance(&c.key), &refs, &walls, &c.mask, &SweepParams::default(), 1);
    assert!(!planes.is_empty(), "no surface found");
    let sources: Vec<Source<'_>> =
        c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
    let params = FillParams::default();
    let one = fill(&c.key, &c.mask, &sources, &params, 1, &mut ());
    let many = fill_with(
        &c.key,
        &c.mask,
        &sources,
        &FillExtras { planes: &planes, ..FillExtras::default() },
        &params,
        1,
        &mut (),
    );
    // The surfaces are true slab planes, seen by two views or more; the hole's own votes
    // (the views among themselves) add some a few pixels off, which win a few patches along
    // a window frame: at most 3 % of the hole is filled through such surfaces (on seed 13
    // two are, 4.8 and 8.6 px off, chosen on 2.5 % together; the band's votes alone found
    // none, and the fill gains 0.35 dB with them).
    let mut astray = 0;
    for (k, p) in planes.iter().enumerate() {
        assert!(p.views.iter().flatten().count() >= 2, "surface {k}: seen by one view only");
        let r = p.region;
        let at = nalgebra::Point2::new(r.x as f64 + 0.5 * r.width as f64, r.y as f64 + 0.5 * r.height as f64);
        let off = |t: usize| {
            p.views
                .iter()
                .zip(&c.planes)
                .filter_map(|(h, tp)| Some((h.as_ref()?.apply(at)? - tp[t].apply(at)?).norm()))
                .fold(0.0f64, f64::max)
        };
        let best = (1..c.planes[0].len()).map(off).fold(f64::INFINITY, f64::min);
        let chosen = many.surface.as_slice().iter().filter(|&&s| usize::from(s) == k + 1).count();
        eprintln!("surface {k}: {best:.2} px from the nearest slab plane, chosen on {chosen} px");
        if best >= 3.0 {
            astray += chosen;
        }
    }
    assert!(
        astray * 100 <= 3 * c.mask.hole_count(),
        "{astray} of {} px through surfaces off every slab",
        c.mask.hole_count()
    );
    let (a, b) = (masked_psnr(&one.image, &c.truth, &c.mask), masked_psnr(&many.image, &c.truth, &c.mask));
    eprintln!("wall only {a:.2} dB, swept planes {b:.2} dB");
    assert!(b > a + 1.5, "swept {b:.2} dB vs wall only {a:.2} dB");

    let flat = parallax_case(640, 480, 3, 13, true);
    let grays: Vec<_> = flat.views.iter().map(luminance).collect();
    let refs: Vec<&_> = grays.iter().collect();
    let none = swept_planes(
        &luminance(&flat.key),
        &refs,
        &aligned(&flat.key, &flat.views),
        &flat.mask,
        &SweepParams::default(),
        1,
    );
    assert!(none.is_empty(), "{} surfaces on a flat wall", none.len());
}

/// The service sweeps as `clearview fill` does: a session fed a facade with slabs view by
/// view (the camera uploading) and all at once (a batch) ends filled through the surfaces,
/// well above the same session with the sweep off (`SessionParams::sweep`), and one by one
/// within the issues' 0.5 dB of all at once. `tests/cli_fill.rs` checks the command on the
/// same scene.
#[test]
fn a_session_fills_through_the_surfaces_view_by_view_as_the_command_does() {
    use clearview::session::{Session, SessionParams};

    let c = parallax_case(640, 480, 3, 13, false);
    let run = |sweep: bool, batches: &[usize]| {
        let params = SessionParams { sweep: sweep.then(Default::default), ..SessionParams::default() };
        let mut s = Session::new(params);
        s.set_key("key".into(), c.key.clone());
        s.set_mask("mask".into(), c.mask.clone()).unwrap();
        let outcomes = fill_in_batches(&mut s, &c.views, batches);
        for o in &outcomes {
            assert_eq!(o.surfaces.is_some(), sweep, "surfaces reported only when swept");
        }
        let last = outcomes.into_iter().rfind(|o| o.image.is_some()).expect("a published result");
        (masked_psnr(last.image.as_ref().unwrap(), &c.truth, &c.mask), last.surfaces)
    };
    let (walls, _) = run(false, &[3]);
    let ((all, report), (one_by_one, _)) = (run(true, &[3]), run(true, &[1, 1, 1]));
    // The outcome says what the sweep did, in the keyframe's coordinates.
    let report = report.expect("surfaces reported");
    assert!(report.used, "{report:?}");
    let filled: usize = report.surfaces.iter().map(|p| p.filled_pixels).sum();
    assert!(filled > 0 && filled < c.mask.hole_count(), "{report:?}");
    for p in &report.surfaces {
        let [x, y, w, h] = p.region;
        assert!(x + w <= c.key.width() && y + h <= c.key.height() && p.views >= 2, "{p:?}");
    }
    eprintln!("walls only {walls:.2} dB; swept, all at once {all:.2} dB, one by one {one_by_one:.2} dB");
    assert!(all > walls + 1.5, "swept {all:.2} dB against the walls' {walls:.2} dB");
    assert!(one_by_one >= all - 0.5, "one by one {one_by_one:.2} dB against all at once {all:.2} dB");
}

/// A facade with a pipe standing off the wall, part of it masked, and five views that all
/// see past the pipe to the bricks behind it there (the sixth, which shows the pipe, left
/// out). Through the wall's homography they agree on the bricks; the keyframe's ring, where
/// the pipe enters the mask, contradicts them. The fill through the wall is wrong there and
/// must not say it is sure: before the ring was read near each copied pixel, 42 % of the
/// pixels it called sure were grossly wrong.
#[test]
fn the_wall_behind_a_masked_slab_that_every_view_sees_past_is_not_called_sure() {
    use clearview::imaging::metrics::honesty;
    let c = parallax_case(1000, 750, 6, 3, false);
    let walls = c.wall();
    let sources: Vec<Source<'_>> = c
        .views
        .iter()
        .zip(&walls)
        .enumerate()
        .filter(|&(v, _)| v != 2)
        .map(|(_, (image, &homography))| Source { image, homography })
        .collect();
    let f = fill(&c.key, &c.mask, &sources, &FillParams::default(), 1, &mut ());
    let h = honesty(&f.image, &c.truth, &c.mask, &f.confidence);
    eprintln!("{h:?}: confident error rate {:.3}", h.confident_error_rate());
    assert!(h.confident_error_rate() < 0.3, "{h:?}");
}
