//! The occlusion model on generated cases whose every occluder is known
//! (`synth::occlusion_case`): the fill with the model beats the fill that takes every view
//! at its word, and its confidence map is honest about its gross errors. Each assertion is
//! checked against the model bypassed too, so that these tests fail without it.
//!
//! The full figures (more seeds, larger images, per family): `cargo run --release --example
//! honesty` (BENCHMARKS.md).

use clearview::imaging::metrics::{Honesty, honesty, masked_psnr};
use clearview::inpaint::{AutoMaskParams, CONFIDENT, FillParams, Filled, OwnParams, fill, own_occluders};
use clearview::synth::{CaseFamily, OcclusionCase, occlusion_case};

fn run(c: &OcclusionCase, params: &FillParams) -> Filled {
    fill(&c.key, &c.mask, &c.sources(), params, 1, &mut ())
}

fn figures(c: &OcclusionCase, params: &FillParams) -> (f64, Honesty) {
    let f = run(c, params);
    (masked_psnr(&f.image, &c.truth, &c.mask), honesty(&f.image, &c.truth, &c.mask, &f.confidence))
}

/// Every view taken at its word: no model, no view's own occluders marked, and no view
/// doubted for how it reproduces the keyframe around the hole either (that alone keeps a
/// view whose occluder crosses the hole's edge out).
fn bypassed() -> FillParams {
    FillParams { occlusion: false, view_error_weight: 0.0, own: None, ..FillParams::default() }
}

#[test]
fn views_with_occluders_of_their_own_are_not_copied() {
    // Planar: every view has a tree, person or car of its own, some over the keyframe's.
    // The model against the bypass is measured on copies (no fusion on either side): an
    // average of four views, each with an occluder of its own elsewhere, dilutes a copied
    // occluder to a quarter, which the PSNR rewards and a photographer would not.
    let (mut on, mut off) = (0.0, 0.0);
    for seed in [1, 3] {
        let c = occlusion_case(CaseFamily::Planar, 320, 240, 4, seed);
        let (_, h) = figures(&c, &FillParams::default());
        let (p_on, _) = figures(&c, &FillParams { fuse: None, ..FillParams::default() });
        let (p_off, _) = figures(&c, &FillParams { fuse: None, ..bypassed() });
        eprintln!("planar seed {seed}: model {p_on:.2} dB, bypassed {p_off:.2} dB (copies), {h:?}");
        on += p_on;
        off += p_off;
        assert!(h.confident_error_rate() <= 0.08, "seed {seed}: {h:?}");
        assert!(h.confident_share() >= 0.5, "seed {seed}: {h:?}");
    }
    assert!(on / 2.0 > off / 2.0 + 2.0, "model {:.2} dB, bypassed {:.2} dB (means)", on / 2.0, off / 2.0);
}

#[test]
fn a_shared_occluder_is_flagged_not_called_confident() {
    // The keyframe's tree stands off the wall: every view shows it too, shifted. What no
    // view sees must not be passed off as sure. Bypassed, the model's confidence believes
    // every view, and the tree copied back is called confident.
    let c = occlusion_case(CaseFamily::Shared, 320, 240, 4, 2);
    let (p_on, h_on) = figures(&c, &FillParams::default());
    let (p_off, h_off) = figures(&c, &bypassed());
    eprintln!("shared: model {p_on:.2} dB {h_on:?}; bypassed {p_off:.2} dB {h_off:?}");
    assert!(h_on.confident_error_rate() < 0.6 * h_off.confident_error_rate(), "{h_on:?} vs {h_off:?}");
    assert!(p_on > p_off + 1.0, "model {p_on:.2} dB, bypassed {p_off:.2} dB");
    // Where a view's true occluder was copied, the result says so.
    let f = run(&c, &FillParams::default());
    let (mut copied, mut flagged) = (0, 0);
    for (v, occ) in c.view_occluders.iter().enumerate() {
        for i in 0..occ.len() {
            let p = f.provenance.as_slice()[i];
            if c.mask.as_slice()[i] > 127 && occ.as_slice()[i] > 127 && usize::from(p) == v + 1 {
                copied += 1;
                flagged += usize::from(f.confidence.as_slice()[i] < CONFIDENT);
            }
        }
    }
    eprintln!("occluder pixels copied: {copied}, flagged {flagged}");
    assert!(flagged as f64 >= 0.6 * copied as f64, "{flagged} of {copied} copied occluder pixels flagged");
}

#[test]
fn confidence_is_zero_outside_the_mask_and_the_report_adds_up() {
    let c = occlusion_case(CaseFamily::NonPlanar, 240, 180, 3, 4);
    let f = run(&c, &FillParams::default());
    let r = &f.report;
    for (&m, &v) in c.mask.as_slice().iter().zip(f.confidence.as_slice()) {
        if m <= 127 {
            assert_eq!(v, 0);
        }
    }
    let confident = f.confidence.as_slice().iter().filter(|&&v| v >= CONFIDENT).count();
    assert_eq!(confident, r.confident);
    assert!((r.confident_share() + r.doubtful_share() - 1.0).abs() < 1e-12);
    assert!(r.expected_quality() > 0.0 && r.expected_quality() <= 1.0);
    // Every pixel the fallback invented is doubtful.
    for (i, &p) in f.provenance.as_slice().iter().enumerate() {
        if p == clearview::inpaint::FALLBACK {
            assert!(f.confidence.as_slice()[i] < CONFIDENT);
        }
    }
}

#[test]
fn a_sole_view_that_does_not_fit_around_the_hole_is_not_called_confident() {
    // One view, registered 8 px off (beyond the local search and the local shift, which
    // moves a view by at most 3.9 px): nothing witnesses against it, but around the hole it
    // does not reproduce the keyframe, and neither does its fill.
    let mut c = occlusion_case(CaseFamily::Planar, 320, 240, 1, 5);
    c.homographies[0] = clearview::geometry::Homography::translation(8.0, -6.0).after(&c.homographies[0]);
    let (p, h) = figures(&c, &FillParams::default());
    eprintln!("misregistered sole view: {p:.2} dB, {h:?}");
    assert!(h.confident_error_rate() <= 0.08, "{h:?}");
    // Registered, the same view is trusted.
    let good = occlusion_case(CaseFamily::Planar, 320, 240, 1, 5);
    let (_, h_good) = figures(&good, &FillParams::default());
    assert!(h_good.confident_share() > h.confident_share() + 0.3, "{h_good:?} vs {h:?}");
}

/// Of the masked pixels, the share the fill copied from a view that truly shows one of its
/// own occluders there.
fn pasted_share(c: &OcclusionCase, f: &Filled) -> f64 {
    let (mut masked, mut pasted) = (0usize, 0usize);
    for i in 0..c.mask.as_slice().len() {
        if c.mask.as_slice()[i] > 127 {
            masked += 1;
            let p = usize::from(f.provenance.as_slice()[i]);
            pasted += usize::from(
                (1..=c.view_occluders.len()).contains(&p) && c.view_occluders[p - 1].as_slice()[i] > 127,
            );
        }
    }
    pasted as f64 / masked.max(1) as f64
}

#[test]
fn with_one_witness_against_one_an_object_crossing_the_mask_edge_is_not_pasted() {
    // Two views: where they disagree inside the mask, no consensus can say which is right.
    // A view's own occluder that crosses the mask's edge (a car, a person) is seen outside
    // the mask and followed in, across its other colours too (a car's roof above its body):
    // the other view's wall is copied there. Bypassed, both views are taken at their word.
    let (mut psnr, mut pasted) = ([0.0; 2], [0.0; 2]);
    for seed in 1..=6 {
        let c = occlusion_case(CaseFamily::Planar, 480, 360, 2, seed);
        let f = run(&c, &FillParams::default());
        let off = run(&c, &bypassed());
        let (p_on, p_off) =
            (masked_psnr(&f.image, &c.truth, &c.mask), masked_psnr(&off.image, &c.truth, &c.mask));
        eprintln!(
            "planar seed {seed}, 2 views: model {p_on:.2} dB, pasted {:.2} %; bypassed {p_off:.2} dB, pasted {:.2} %",
            100.0 * pasted_share(&c, &f),
            100.0 * pasted_share(&c, &off)
        );
        psnr = [psnr[0] + p_on / 6.0, psnr[1] + p_off / 6.0];
        pasted = [pasted[0] + pasted_share(&c, &f) / 6.0, pasted[1] + pasted_share(&c, &off) / 6.0];
    }
    // Before the object was followed across the mask's edge: 4.5 % pasted, 25.05 dB.
    assert!(pasted[0] <= 0.5 * pasted[1], "pasted occluders, model and bypassed (means): {pasted:?}");
    assert!(psnr[0] >= psnr[1] + 2.0, "masked PSNR, model and bypassed (means): {psnr:?}");
}

/// The fill of views 1..k for every k, masked PSNR against the truth.
fn prefixes(c: &OcclusionCase, params: &FillParams) -> Vec<f64> {
    let sources = c.sources();
    (1..=sources.len())
        .map(|k| {
            let f = fill(&c.key, &c.mask, &sources[..k], params, 1, &mut ());
            masked_psnr(&f.image, &c.truth, &c.mask)
        })
        .collect()
}

#[test]
fn a_view_that_only_adds_disagreement_does_not_make_the_fill_worse() {
    // Taken in, the fourth view costs 1.6 dB (shared, seed 6: a piece of the shared tree
    // from another view) and 1.8 dB (non-planar, seed 7: a view with parallax takes over part
    // of the mask). A view joins the fill only when the judge finds the fill with it no worse.
    let drop = |s: &[f64]| s.windows(2).map(|p| p[0] - p[1]).fold(0.0, f64::max);
    // The views' own occluders are not marked here: they change these cases (with them
    // the fourth view costs shared-6 0.59 dB, taken in or not), and the choice of views is
    // what is tested. With the marks, the service's figures: BENCHMARKS.md, "Each view's own
    // occluders, judged near the mask".
    let base = FillParams { own: None, ..FillParams::default() };
    for (family, seed) in [(CaseFamily::Shared, 6), (CaseFamily::NonPlanar, 7)] {
        let c = occlusion_case(family, 320, 240, 4, seed);
        let on = prefixes(&c, &base);
        let off = prefixes(&c, &FillParams { select_views: false, ..base.clone() });
        eprintln!("{family:?} seed {seed}, views 1..k: selected {on:.2?}; every view {off:.2?}");
        assert!(drop(&on) <= 0.3, "{family:?}: a view costs {:.2} dB: {on:.2?}", drop(&on));
        // Every view taken in: the case is the one it is meant to be.
        assert!(drop(&off) > 1.0, "{family:?}: {off:.2?}");
    }
}

/// Where views with no occluder fill a planar wall, what goes grossly wrong is edges (brick,
/// window frames) a fraction of a pixel off; the confidence must flag most of those too, not
/// only the occluders. With edges counted at a fixed share of their step (0.4), seed 2's
/// mortar lines, split in its softer views, stayed confident: 0.40 of its gross errors were
/// flagged. Each view's share is now what its ring shows, and the 0.6 holds on each
/// case (BENCHMARKS.md, "Confidence at edges, measured on the ring").
#[test]
fn gross_errors_along_edges_are_flagged() {
    for seed in 1..=3 {
        let c = occlusion_case(CaseFamily::Planar, 480, 360, 4, seed);
        let (_, h) = figures(&c, &FillParams::default());
        eprintln!(
            "planar seed {seed}: flagged recall {:.3}, confident {:.3}, confident wrong {:.4}",
            h.flagged_recall(),
            h.confident_share(),
            h.confident_error_rate()
        );
        assert!(h.flagged_recall() >= 0.6, "seed {seed}: {h:?}: flagged recall {:.2}", h.flagged_recall());
        assert!(h.confident_error_rate() <= 0.08, "seed {seed}: {h:?}");
        assert!(h.confident_share() >= 0.5, "seed {seed}: {h:?}");
    }
}

/// Per view of `c`, the share of its occluder pixels that `own` marks and the share of its
/// wall pixels it marks, over the keyframe pixels near the mask (the mask's bounds grown
/// by `margin`) that the view sees, outside the keyframe's mask: (hits, occluder pixels,
/// false marks, wall pixels).
fn own_marks_against_truth(
    c: &OcclusionCase,
    own: &[Option<clearview::imaging::Mask>],
    margin: usize,
) -> [usize; 4] {
    let (w, h) = (c.key.width(), c.key.height());
    let near = c.mask.hole_bounds().expect("a mask").grown(margin, w, h);
    let mut counts = [0usize; 4];
    for (v, marks) in own.iter().enumerate() {
        let Some(marks) = marks else { continue };
        for y in near.y..near.y + near.height {
            for x in near.x..near.x + near.width {
                let Some(p) = c.homographies[v].apply(nalgebra::Point2::new(x as f64, y as f64)) else {
                    continue;
                };
                let (u, t) = (p.x.round(), p.y.round());
                let Some(level) =
                    (u >= 0.0 && t >= 0.0).then(|| marks.get_checked(u as isize, t as isize)).flatten()
                else {
                    continue;
                };
                let (truth, marked) = (c.view_occluders[v].get(x, y) > 127, level > 127);
                let slot = if truth { 0 } else { 2 };
                counts[slot] += usize::from(marked);
                counts[slot + 1] += 1;
            }
        }
    }
    counts
}

/// The marks of `c`'s views from [`own_occluders`] at the defaults, against the truth:
/// (share of the views' occluder pixels marked, share of their wall pixels marked).
fn own_marks(c: &OcclusionCase) -> (f64, f64) {
    let own = own_occluders(&c.key, &c.mask, &c.sources(), &OwnParams::default(), &AutoMaskParams::default());
    let [hits, occluder, false_marks, wall] = own_marks_against_truth(c, &own, OwnParams::default().margin);
    (hits as f64 / occluder.max(1) as f64, false_marks as f64 / wall.max(1) as f64)
}

#[test]
fn each_views_own_occluders_are_marked_and_little_of_its_wall() {
    for seed in 1..=3 {
        let c = occlusion_case(CaseFamily::Planar, 320, 240, 4, seed);
        let (recall, false_share) = own_marks(&c);
        eprintln!(
            "planar seed {seed}: occluder pixels marked {recall:.3}, wall pixels marked {false_share:.3}"
        );
        assert!(recall >= 0.9 && false_share <= 0.05, "seed {seed}: {recall:.3} {false_share:.3}");
    }
    // Every view shows the keyframe's tree, displaced. Two views agreeing on it where a
    // third sees the wall outvoted the wall: 14 % and 12 % of the wall marked on seeds 1
    // and 6 before their pixels in the tree's colours stopped counting as witnesses.
    let (mut pooled, mut n) = (0.0, 0.0);
    for seed in [1, 2, 6] {
        let c = occlusion_case(CaseFamily::Shared, 320, 240, 4, seed);
        let (recall, false_share) = own_marks(&c);
        eprintln!(
            "shared seed {seed}: occluder pixels marked {recall:.3}, wall pixels marked {false_share:.3}"
        );
        assert!(recall >= 0.9, "seed {seed}: {recall:.3}");
        pooled += false_share;
        n += 1.0;
    }
    assert!(pooled / n <= 0.08, "shared: wall marked {:.3} on average", pooled / n);
}

#[test]
fn the_views_own_occluders_are_kept_out_of_the_fill() {
    let psnr = |c: &OcclusionCase, params: &FillParams| masked_psnr(&run(c, params).image, &c.truth, &c.mask);
    let without = FillParams { own: None, ..FillParams::default() };
    // Planar: a view's car or person next to the keyframe's tree is copied into the hole.
    let (mut on, mut off) = (0.0, 0.0);
    for seed in [2, 4] {
        let c = occlusion_case(CaseFamily::Planar, 320, 240, 4, seed);
        let (p_on, p_off) = (psnr(&c, &FillParams::default()), psnr(&c, &without));
        eprintln!("planar seed {seed}: own occluders marked {p_on:.2} dB, not {p_off:.2} dB");
        on += p_on / 2.0;
        off += p_off / 2.0;
    }
    assert!(on > off + 0.7, "planar: {on:.2} dB against {off:.2} dB");
    // Shared: the marks must not cost what the model already knew (1.6 dB on average over
    // these seeds when the views' tree pixels still counted as witnesses).
    let (mut on, mut off) = (0.0, 0.0);
    for seed in 1..=6 {
        let c = occlusion_case(CaseFamily::Shared, 320, 240, 4, seed);
        let (p_on, p_off) = (psnr(&c, &FillParams::default()), psnr(&c, &without));
        eprintln!("shared seed {seed}: own occluders marked {p_on:.2} dB, not {p_off:.2} dB");
        on += p_on / 6.0;
        off += p_off / 6.0;
    }
    assert!(on > off - 0.3, "shared: {on:.2} dB against {off:.2} dB");
}

/// A pale pier runs down the keyframe to the mask's edge, and no view shows it (as through
/// a wrong surface, whose plane carried the pier off): inside the mask the views agree with
/// each other as before, so each copied pixel is as well witnessed as without the pier. Only
/// where the pier meets the mask's edge does the blend see the disagreement, and it spreads
/// the pier's colour inwards as a glow: those pixels are no longer what a view saw, and none
/// of them may be reported sure (without the pier, one in four of them are: the others lie
/// on edges the views' ring shows a little off).
#[test]
fn pixels_the_blend_moved_grossly_are_not_called_confident() {
    let plain = occlusion_case(CaseFamily::Planar, 320, 240, 4, 1);
    // Down to the mask, over the 16 columns where the most of it lies.
    let (w, h) = (plain.mask.width(), plain.mask.height());
    let column = |x: usize| (0..h).filter(|&y| plain.mask.is_hole(x, y)).count();
    let x0 = (0..w - 16).max_by_key(|&x| (x..x + 16).map(column).sum::<usize>()).unwrap();
    let mut c = plain.clone();
    for x in x0..x0 + 16 {
        for y in (0..h).take_while(|&y| !plain.mask.is_hole(x, y)) {
            c.key.set(x, y, [0.9, 0.88, 0.82]);
        }
    }
    let (f, g) = (run(&c, &FillParams::default()), run(&plain, &FillParams::default()));
    let (mut moved, mut sure, mut sure_before) = (0usize, 0usize, 0usize);
    for (i, &m) in c.mask.as_slice().iter().enumerate() {
        let (a, b) = (f.image.as_slice()[i], g.image.as_slice()[i]);
        if m > 127 && (0..3).any(|k| (a[k] - b[k]).abs() > 40.0 / 255.0) {
            moved += 1;
            sure += usize::from(f.confidence.as_slice()[i] >= CONFIDENT);
            sure_before += usize::from(g.confidence.as_slice()[i] >= CONFIDENT);
        }
    }
    eprintln!(
        "{moved} masked pixels moved by the pier's glow: {sure} reported sure, {sure_before} without the pier"
    );
    assert!(moved >= 100, "the blend did not glow: {moved} pixels moved");
    assert!(sure_before * 5 >= moved, "{sure_before} of {moved} sure without the pier");
    assert!(sure * 50 <= moved, "{sure} of {moved} moved pixels reported sure");
}

/// A view's occluder blends into the wall along its outline (the renderer's soft edge, a
/// camera's blur), and the rim is copied wherever it is left unmarked: the marks reach 2 px
/// past each view's occluder, all of it. Measured on these cases: 1.000 with the marks
/// grown by 3 work pixels (`OwnParams::growth`), 0.969–0.978 grown by 1 as the keyframe's
/// mask is.
#[test]
fn each_views_marks_reach_past_its_occluders_rim() {
    for seed in 1..=3 {
        let mut c = occlusion_case(CaseFamily::Planar, 320, 240, 4, seed);
        c.view_occluders = c.view_occluders.iter().map(|m| clearview::synth::dilate_mask(m, 2)).collect();
        let own =
            own_occluders(&c.key, &c.mask, &c.sources(), &OwnParams::default(), &AutoMaskParams::default());
        let [hits, rim, _, _] = own_marks_against_truth(&c, &own, OwnParams::default().margin);
        let recall = hits as f64 / rim.max(1) as f64;
        eprintln!("planar seed {seed}: occluders grown by 2 px marked {recall:.3}");
        assert!(recall >= 0.995, "seed {seed}: {recall:.3} of {rim} pixels");
    }
}

/// Two views: each is judged against the keyframe and the other view, and keeps only its
/// objects in colours the building does not have (`OwnParams::foreign_share`). A
/// passer-by's coat or a van that one view shows is marked and kept out of the fill; the
/// building the two views show displaced (the non-planar family's pier, seen through the
/// wall's homography) is marked far less than with every object kept.
#[test]
fn with_two_views_a_views_own_occluder_is_marked_and_the_displaced_wall_is_not() {
    let all_kept = OwnParams { foreign_share: 0.0, ..OwnParams::default() };
    let without = FillParams { own: None, ..FillParams::default() };
    let psnr = |c: &OcclusionCase, params: &FillParams| masked_psnr(&run(c, params).image, &c.truth, &c.mask);
    let marks = |c: &OcclusionCase, p: &OwnParams| {
        let own = own_occluders(&c.key, &c.mask, &c.sources(), p, &AutoMaskParams::default());
        own_marks_against_truth(c, &own, p.margin)
    };
    // Marked and kept out: 0.78 dB on average over these eight cases (0 to 2.08 each).
    let (mut on, mut off) = (0.0, 0.0);
    let (mut hits, mut hits_all_kept) = (0, 0);
    for family in [CaseFamily::Planar, CaseFamily::Shared] {
        for seed in 1..=4 {
            let c = occlusion_case(family, 320, 240, 2, seed);
            let (p_on, p_off) = (psnr(&c, &FillParams::default()), psnr(&c, &without));
            eprintln!("{} seed {seed}: own occluders marked {p_on:.2} dB, not {p_off:.2} dB", family.name());
            on += p_on / 8.0;
            off += p_off / 8.0;
            if family == CaseFamily::Shared {
                hits += marks(&c, &OwnParams::default())[0];
                hits_all_kept += marks(&c, &all_kept)[0];
            }
        }
    }
    assert!(on > off + 0.5, "two views: {on:.2} dB against {off:.2} dB without the views' own occluders");
    // The shared family's occluders are foreign: every mark kept (68 675 of their 69 264 pixels).
    assert!(
        hits as f64 >= 0.95 * hits_all_kept as f64,
        "shared: {hits} occluder pixels marked, {hits_all_kept} with all kept"
    );
    // The pier's displaced wall: 5 752 wall pixels marked against 12 978 with every object kept.
    let (mut wall, mut wall_all_kept) = (0, 0);
    for seed in 1..=4 {
        let c = occlusion_case(CaseFamily::NonPlanar, 320, 240, 2, seed);
        let [_, _, false_marks, _] = marks(&c, &OwnParams::default());
        let [_, _, false_all_kept, _] = marks(&c, &all_kept);
        eprintln!("nonplanar seed {seed}: wall pixels marked {false_marks}, {false_all_kept} with all kept");
        wall += false_marks;
        wall_all_kept += false_all_kept;
    }
    assert!(
        (wall as f64) <= 0.6 * wall_all_kept as f64,
        "nonplanar: {wall} wall pixels marked, {wall_all_kept} with every object kept"
    );
}
