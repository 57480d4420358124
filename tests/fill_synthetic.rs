//! The multi-view fill on rendered scenes whose truth is known: a facade seen from several
//! viewpoints through known homographies, occluders pasted into each view at different
//! places (one of them over part of the keyframe's hole), exposure differences and noise.
//! Each piece of the fill has a test that fails when that piece is switched off.
//!
//! `CLEARVIEW_DUMP=/tmp` writes before/after PNGs of the main case there.

use nalgebra::Point2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use clearview::geometry::Homography;
use clearview::imaging::metrics::masked_psnr;
use clearview::imaging::{Mask, RgbF32};
use clearview::inpaint::{FALLBACK, FillExtras, FillParams, Filled, KEYFRAME, Source, fill, fill_with};
use clearview::synth::{self, Occluder, half};

const W: usize = 480;
const H: usize = 360;

struct Scene {
    truth: RgbF32,
    key: RgbF32,
    mask: Mask,
    views: Vec<RgbF32>,
    homographies: Vec<Homography>,
}

impl Scene {
    fn sources(&self) -> Vec<Source<'_>> {
        self.views
            .iter()
            .zip(&self.homographies)
            .map(|(v, &homography)| Source { image: v, homography })
            .collect()
    }

    fn run(&self, params: &FillParams) -> Filled {
        fill(&self.key, &self.mask, &self.sources(), params, 1, &mut ())
    }
}

/// The keyframe has a tree and a person in front of the facade; four views see the facade
/// from elsewhere, each with its own exposure (none the keyframe's), noise and occluder. View 0 — the cleanest,
/// least noisy one — has a tree right over part of the keyframe's tree.
fn scene(seed: u64) -> Scene {
    // Rendered at twice the size and box-averaged: the images are band-limited as a
    // camera's are, so a warp's resampling costs little and the PSNR measures the fill.
    let fine = synth::facade(2 * W, 2 * H, seed);
    let truth = half(&fine);
    let mut key = truth.clone();
    let mut mask = Mask::new(W, H, 0);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 200.0, 170.0, 150.0, seed + 1);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Person, 380.0, 230.0, 120.0, seed + 2);
    synth::add_noise(&mut key, 0.005, seed + 3);
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 10);
    let exposures = [(0.8, 0.03), (0.75, 0.04), (1.2, -0.03), (1.25, 0.0)];
    let noise = [0.003, 0.012, 0.012, 0.012];
    let mut views = Vec::new();
    let mut homographies = Vec::new();
    for (v, (&(gain, bias), &sigma)) in exposures.iter().zip(&noise).enumerate() {
        let hm = synth::random_homography(&mut rng, W, H, 0.05, 0.12, (0.92, 1.08));
        let mut view = synth::render_view_band(&fine, &hm.inverse().expect("regular"), W, H, [0.5; 3]);
        if v == 0 {
            // Over the keyframe's tree crown, where the keyframe's hole is.
            let c = hm.apply(Point2::new(185.0, 150.0)).expect("finite");
            synth::paint_occluder(&mut view, None, Occluder::Tree, c.x as f32, c.y as f32, 110.0, seed + 20);
        } else {
            let (cx, cy) = [(90.0, 250.0), (420.0, 90.0), (60.0, 80.0)][v - 1];
            let kind = [Occluder::Car, Occluder::Person, Occluder::Tree][v - 1];
            synth::paint_occluder(&mut view, None, kind, cx, cy, 100.0, seed + 20 + v as u64);
        }
        synth::expose(&mut view, gain, bias);
        synth::add_noise(&mut view, sigma, seed + 30 + v as u64);
        views.push(view);
        homographies.push(hm);
    }
    Scene { truth, key, mask, views, homographies }
}

fn dump(name: &str, img: &RgbF32) {
    if let Ok(dir) = std::env::var("CLEARVIEW_DUMP") {
        let path = std::path::Path::new(&dir).join(name);
        clearview::imaging::convert::to_rgb8(img).save(&path).expect("write PNG");
        eprintln!("wrote {}", path.display());
    }
}

#[test]
fn fills_from_the_views_and_reports_consistently() {
    let s = scene(3);
    let out = s.run(&FillParams::default());
    let psnr = masked_psnr(&out.image, &s.truth, &s.mask);
    let before = masked_psnr(&s.key, &s.truth, &s.mask);
    eprintln!("masked PSNR: {before:.1} dB before, {psnr:.1} dB after; {:?}", out.report);
    dump("fill_synth_before.png", &s.key);
    dump("fill_synth_after.png", &out.image);
    assert!(psnr > 24.0, "masked PSNR {psnr:.1} dB");

    // Outside the mask: the keyframe, bit for bit, and provenance KEYFRAME.
    let r = &out.report;
    assert_eq!(r.masked, s.mask.hole_count());
    for i in 0..W * H {
        let hole = s.mask.as_slice()[i] > 127;
        let p = out.provenance.as_slice()[i];
        if !hole {
            assert_eq!(out.image.as_slice()[i], s.key.as_slice()[i]);
            assert_eq!(p, KEYFRAME);
        } else {
            assert_ne!(p, KEYFRAME, "a masked pixel left as it was");
        }
    }
    // Report and provenance agree, and everything masked was filled by someone.
    assert_eq!(r.sources.iter().map(|s| s.filled).sum::<usize>() + r.fallback, r.masked);
    for (v, sr) in r.sources.iter().enumerate() {
        let n = out.provenance.as_slice().iter().filter(|&&p| p == 1 + v as u16).count();
        assert_eq!(sr.filled, n, "view {v}");
        assert!(sr.filled <= sr.covered && sr.covered <= r.masked);
    }
    assert_eq!(out.provenance.as_slice().iter().filter(|&&p| p == FALLBACK).count(), r.fallback);
    // The gains undo the exposures: key ≈ gain · view + offset.
    let g1 = r.sources[1].gain[1];
    assert!((r.sources[3].gain[0] - 0.8).abs() < 0.08, "view 3 gain {:?}", r.sources[3].gain);
    assert!((g1 - 1.0 / 0.75).abs() < 0.08, "view 1 gain {g1}");
    // Deterministic.
    let again = s.run(&FillParams::default());
    assert!(again.image == out.image && again.provenance == out.provenance);
}

#[test]
fn occlusion_reasoning_keeps_the_views_own_tree_out() {
    let s = scene(3);
    // Without the views' expected errors, which on this scene also keep the treed views out
    // (their trees cross the ring around the hole): the model alone is judged here.
    // Nor with the views' own occluders marked before the fill (`FillParams::own`), which
    // keep the trees out by themselves (26.4 dB with the model, 26.5 without it).
    let base = FillParams { view_error_weight: 0.0, own: None, ..FillParams::default() };
    let on = masked_psnr(&s.run(&base).image, &s.truth, &s.mask);
    let off_img = s.run(&FillParams { occlusion: false, ..base }).image;
    dump("fill_synth_no_occlusion.png", &off_img);
    let off = masked_psnr(&off_img, &s.truth, &s.mask);
    eprintln!("occlusion reasoning on {on:.1} dB, off {off:.1} dB");
    assert!(on > 24.0 && off < on - 3.0, "on {on:.1} dB, off {off:.1} dB");
}

/// Without blending, which also hides part of an exposure difference (it removes the step
/// at the border, not the contrast change), and without the fusion, whose average of
/// darker and brighter views is nearer the keyframe's exposure, so that the compensation
/// alone is measured.
#[test]
fn photometric_compensation_removes_exposure_differences() {
    let s = scene(3);
    let base = FillParams { blend: false, fuse: None, ..FillParams::default() };
    let on = masked_psnr(&s.run(&base).image, &s.truth, &s.mask);
    let off_img = s.run(&FillParams { photometric: false, ..base }).image;
    dump("fill_synth_no_photometric.png", &off_img);
    let off = masked_psnr(&off_img, &s.truth, &s.mask);
    eprintln!("photometric on {on:.1} dB, off {off:.1} dB (no blending)");
    assert!(on > 24.0 && off < on - 3.0, "on {on:.1} dB, off {off:.1} dB");
}

/// Views whose camera answers the light with a curve, not a line (much darker, as the
/// Oxford leuven views are, and bent: `view = 0.4 · key^1.8`): one gain and offset per
/// channel cannot undo that, a tone curve fitted on the whole overlap can. Without
/// blending, as above; with the curve off, the fill is what it was before it.
#[test]
fn a_tone_curve_undoes_a_response_that_is_not_linear() {
    let mut s = scene(3);
    for view in &mut s.views {
        for p in view.as_mut_slice() {
            *p = p.map(|v| 0.4 * v.clamp(0.0, 1.0).powf(1.8));
        }
    }
    let base = FillParams { blend: false, ..FillParams::default() };
    let out = s.run(&base);
    assert!(out.report.sources.iter().all(|r| r.tone), "{:?}", out.report.sources);
    let on = masked_psnr(&out.image, &s.truth, &s.mask);
    let off_img = s.run(&FillParams { tone: false, ..base }).image;
    dump("fill_synth_no_tone.png", &off_img);
    let off = masked_psnr(&off_img, &s.truth, &s.mask);
    eprintln!("tone curve on {on:.1} dB, off {off:.1} dB (no blending)");
    // 25.3 against 23.5 dB: the ring's gain alone follows the curve's local slope, not
    // its bend.
    assert!(on > 24.5 && off < on - 1.2, "on {on:.1} dB, off {off:.1} dB");
}

/// The scene's exposures are linear: no view is given a curve, and the fill is the fill
/// without curves to the last bit, although view 0 has a tree over a good part of what it
/// shares with the keyframe.
#[test]
fn linear_exposures_get_no_tone_curve() {
    let s = scene(3);
    let out = s.run(&FillParams::default());
    assert!(out.report.sources.iter().all(|r| !r.tone), "{:?}", out.report.sources);
    let off = s.run(&FillParams { tone: false, ..FillParams::default() });
    assert!(out.image == off.image);
}

#[test]
fn the_local_search_absorbs_misregistration() {
    let mut s = scene(3);
    // Every homography off by two pixels, as a real alignment can be on a facade that is
    // not quite planar.
    for hm in &mut s.homographies {
        *hm = Homography::translation(2.0, -1.0).after(hm);
    }
    // Without the views' expected errors (every view is off alike; they would only steer
    // the choice between them) and without the local shift (which takes the offset out
    // before the search sees it: `a_view_off_by_two_pixels_is_moved_back_around_the_hole`).
    // Nor with the views' own occluders marked (15.9 dB with them: misregistered by 2 px,
    // a view's edges disagree with the others').
    let base = FillParams { view_error_weight: 0.0, local_shift: None, own: None, ..FillParams::default() };
    let on = masked_psnr(&s.run(&base).image, &s.truth, &s.mask);
    let off = masked_psnr(&s.run(&FillParams { search_radius: 0, ..base.clone() }).image, &s.truth, &s.mask);
    eprintln!("local search on {on:.1} dB, off {off:.1} dB");
    // Integer shifts leave up to half a pixel, so this does not reach the registered
    // case's figure; it must clearly beat trusting the homography. (17.2 against 14.8 dB
    // until the views' own occluders were followed across the gap into the hole; 16.2 since:
    // a cost of that change under a 2-px misregistration, left open in BENCHMARKS.md.)
    assert!(on > 16.0 && off < on - 1.0, "on {on:.1} dB, off {off:.1} dB");
}

#[test]
fn a_view_off_by_two_pixels_is_moved_back_around_the_hole() {
    let mut s = scene(3);
    let registered = masked_psnr(&s.run(&FillParams::default()).image, &s.truth, &s.mask);
    for hm in &mut s.homographies {
        *hm = Homography::translation(2.0, -1.0).after(hm);
    }
    let filled = s.run(&FillParams::default());
    let shifted = masked_psnr(&filled.image, &s.truth, &s.mask);
    let unshifted = masked_psnr(
        &s.run(&FillParams { local_shift: None, ..FillParams::default() }).image,
        &s.truth,
        &s.mask,
    );
    eprintln!(
        "registered {registered:.1} dB; 2 px off: shifted {shifted:.1} dB, not shifted {unshifted:.1} dB"
    );
    assert!(shifted > unshifted + 2.0, "shifted {shifted:.1} dB, not {unshifted:.1} dB");
    assert!(shifted > registered - 1.0, "shifted {shifted:.1} dB, registered {registered:.1} dB");
    // The report says how far each view was moved (about 2.2 px: the offset seen from the
    // keyframe).
    for src in &filled.report.sources {
        assert!((1.5..3.0).contains(&src.shift_px), "{:?}", filled.report.sources);
    }
}

#[test]
fn views_that_reproduce_the_keyframe_badly_around_the_hole_are_avoided() {
    let mut s = scene(3);
    // Two views misregistered by more than the local search reaches (a wrong homography on a
    // facade that is not quite planar): around the hole they reproduce the keyframe worse
    // than the others, and would fill the same way.
    for hm in &mut s.homographies[2..] {
        *hm = Homography::translation(3.5, -3.0).after(hm);
    }
    // Every view in the fill (the choice of views by the judge would leave these two out
    // too, and this test is about the expected error).
    // Nor moved back by the local shift, which would take most of the offset out.
    // Nor with the views' own occluders marked, which take the misregistered views' edges
    // for occluders (13.2 dB against 13.6 without the expected errors).
    let all = FillParams { select_views: false, local_shift: None, own: None, ..FillParams::default() };
    let on = masked_psnr(&s.run(&all).image, &s.truth, &s.mask);
    let off = masked_psnr(&s.run(&FillParams { view_error_weight: 0.0, ..all }).image, &s.truth, &s.mask);
    let chosen = masked_psnr(&s.run(&FillParams::default()).image, &s.truth, &s.mask);
    eprintln!("expected view errors on {on:.1} dB, off {off:.1} dB; views chosen {chosen:.1} dB");
    assert!(on > off + 0.5, "on {on:.1} dB, off {off:.1} dB");
}

#[test]
fn blending_removes_the_seam_at_the_border() {
    let mut s = scene(3);
    // A view whose exposure drifts across the frame (vignetting): one gain cannot match it
    // everywhere, so without blending the border of the fill shows a step.
    for v in &mut s.views {
        let w = v.width() as f32;
        for y in 0..v.height() {
            for (x, p) in v.row_mut(y).iter_mut().enumerate() {
                let f = 0.85 + 0.3 * x as f32 / w;
                *p = p.map(|c| (c * f).clamp(0.0, 1.0));
            }
        }
    }
    // The step across the mask's border (inside pixel minus outside neighbour) less the
    // truth's step there, averaged over 24×24 blocks so that noise and texture cancel and a
    // systematic brightness step remains; the mean size of those block averages.
    let seam = |img: &RgbF32| -> f64 {
        const B: usize = 24;
        let (bw, bh) = (W.div_ceil(B), H.div_ceil(B));
        let mut acc = vec![([0.0f64; 3], 0usize); bw * bh];
        for y in 1..H - 1 {
            for x in 1..W - 1 {
                if !s.mask.is_hole(x, y) {
                    continue;
                }
                for (nx, ny) in [(x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)] {
                    if !s.mask.is_hole(nx, ny) {
                        let (a, b) = (img.get(x, y), img.get(nx, ny));
                        let (ta, tb) = (s.truth.get(x, y), s.truth.get(nx, ny));
                        let cell = &mut acc[(y / B) * bw + x / B];
                        for c in 0..3 {
                            cell.0[c] += ((a[c] - b[c]) - (ta[c] - tb[c])) as f64;
                        }
                        cell.1 += 1;
                    }
                }
            }
        }
        let cells: Vec<f64> = acc
            .iter()
            .filter(|c| c.1 >= 10)
            .map(|c| c.0.iter().map(|v| (v / c.1 as f64).abs()).sum::<f64>() / 3.0)
            .collect();
        cells.iter().sum::<f64>() / cells.len() as f64
    };
    // Blending alone is judged here: the occlusion model reads a ±15 % drift as views that
    // disagree and picks differently with and without it (with it on, blending removes
    // about 30 % of the step instead of 40 %; tests/occlusion.rs judges the model).
    let base = FillParams { occlusion: false, view_error_weight: 0.0, ..FillParams::default() };
    let on = s.run(&base).image;
    let off = s.run(&FillParams { blend: false, ..base }).image;
    dump("fill_synth_vignette_blend.png", &on);
    dump("fill_synth_vignette_noblend.png", &off);
    let (son, soff) = (seam(&on), seam(&off));
    eprintln!("border step error: blended {son:.4}, not blended {soff:.4}");
    assert!(son < 0.65 * soff, "blended {son:.4}, not blended {soff:.4}");
}

#[test]
fn an_empty_mask_leaves_the_image_unchanged() {
    let s = scene(5);
    let empty = Mask::new(W, H, 0);
    let out = fill(&s.key, &empty, &s.sources(), &FillParams::default(), 1, &mut ());
    assert!(out.image == s.key);
    assert!(out.provenance.as_slice().iter().all(|&p| p == KEYFRAME));
    assert_eq!(out.report.masked, 0);
    assert_eq!(out.report.fallback, 0);
}

#[test]
fn what_no_view_saw_comes_from_the_fallback() {
    let s = scene(7);
    // A hole in the top-left corner; the views are moved so that none reaches it.
    let mut mask = Mask::new(W, H, 0);
    for y in 5..40 {
        for x in 5..50 {
            mask.set(x, y, 255);
        }
    }
    let hs: Vec<Homography> =
        (0..s.views.len()).map(|i| Homography::translation(-80.0 - 10.0 * i as f64, 0.0)).collect();
    let sources: Vec<Source<'_>> =
        s.views.iter().zip(&hs).map(|(v, &homography)| Source { image: v, homography }).collect();
    let out = fill(&s.key, &mask, &sources, &FillParams::default(), 1, &mut ());
    let r = &out.report;
    assert_eq!(r.fallback, r.masked);
    assert!(r.sources.iter().all(|s| s.filled == 0 && s.covered == 0));
    assert_eq!(out.provenance.as_slice().iter().filter(|&&p| p == FALLBACK).count(), r.masked);
}

/// A source the choice keeps out (the service's view judged worse before) makes no pixel of
/// the result, but is still heard; one already in is not tried again; candidates are.
#[test]
fn a_source_kept_out_makes_no_pixel_and_one_in_is_not_tried_again() {
    let s = scene(3);
    let sources = s.sources();
    let n = sources.len();
    assert!(n >= 3);
    let run = |choice: &[Option<bool>]| {
        let extras = FillExtras { choice, ..FillExtras::default() };
        fill_with(&s.key, &s.mask, &sources, &extras, &FillParams::default(), 1, &mut ())
    };
    let mut choice = vec![None; n];
    choice[0] = Some(true);
    choice[1] = Some(false);
    let out = run(&choice);
    let from = |v: usize| out.provenance.as_slice().iter().filter(|&&p| usize::from(p) == 1 + v).count();
    assert_eq!(from(1), 0, "a source kept out filled pixels");
    assert_eq!(out.report.sources[1].filled, 0);
    assert!(!out.report.sources[1].joined);
    assert!(out.report.sources[0].joined, "a source in the result was left out");
    assert!(from(0) > 0);
    // Every source kept out but one: the fill is that one's, whatever the others show.
    let mut only = vec![Some(false); n];
    only[2] = Some(true);
    let out = run(&only);
    assert!(out.report.sources.iter().enumerate().all(|(v, r)| r.joined == (v == 2)));
    assert_eq!(out.report.sources.iter().map(|r| r.filled).sum::<usize>(), out.report.sources[2].filled);
}

/// The stages are reported in order, with progress: with several views the fill, fallback
/// and blend run inside the choice of views (one trial per view), and the chosen views are
/// then averaged into the copies; with one view they run as they are.
#[test]
fn the_observer_sees_every_stage() {
    use clearview::inpaint::{Observer, Stage};
    #[derive(Default)]
    struct Log(Vec<Stage>, usize);
    impl Observer for Log {
        fn stage(&mut self, stage: Stage) {
            self.0.push(stage);
        }
        fn progress(&mut self, _done: usize, _total: usize) {
            self.1 += 1;
        }
    }
    let s = scene(3);
    let mut log = Log::default();
    fill(&s.key, &s.mask, &s.sources(), &FillParams::default(), 1, &mut log);
    assert_eq!(
        log.0,
        vec![Stage::Own, Stage::Warp, Stage::Photometric, Stage::Occlusion, Stage::Select, Stage::Fuse]
    );
    assert!(log.1 >= 4);
    let mut log = Log::default();
    fill(&s.key, &s.mask, &s.sources()[..1], &FillParams::default(), 1, &mut log);
    assert_eq!(
        log.0,
        vec![Stage::Warp, Stage::Photometric, Stage::Occlusion, Stage::Fill, Stage::Fallback, Stage::Blend]
    );
    assert!(log.1 >= 4);
}

#[test]
fn views_with_independent_noise_are_averaged_into_the_copy() {
    // Three views of the facade with noise of their own and nothing in front of it: their
    // average is closer to the facade than any one copy, and the ring around the hole
    // shows it.
    let seed = 11;
    let fine = synth::facade(2 * W, 2 * H, seed);
    let truth = half(&fine);
    let mut key = truth.clone();
    let mut mask = Mask::new(W, H, 0);
    synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Person, 240.0, 200.0, 150.0, seed + 1);
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 10);
    let mut views = Vec::new();
    let mut homographies = Vec::new();
    for v in 0..3 {
        let hm = synth::random_homography(&mut rng, W, H, 0.05, 0.12, (0.92, 1.08));
        let mut view = synth::render_view_band(&fine, &hm.inverse().expect("regular"), W, H, [0.5; 3]);
        synth::add_noise(&mut view, 0.04, seed + 30 + v);
        views.push(view);
        homographies.push(hm);
    }
    let s = Scene { truth, key, mask, views, homographies };
    let copies = FillParams { fuse: None, ..FillParams::default() };
    let out = s.run(&FillParams::default());
    let copied = s.run(&copies);
    let (fused, plain) =
        (masked_psnr(&out.image, &s.truth, &s.mask), masked_psnr(&copied.image, &s.truth, &s.mask));
    eprintln!(
        "fused {fused:.2} dB ({} of {} pixels), copies only {plain:.2} dB",
        out.report.fused, out.report.masked
    );
    assert!(fused > plain + 1.0, "fused {fused:.2} dB, copies only {plain:.2} dB");
    assert!(out.report.fused > out.report.masked * 9 / 10, "{:?}", out.report);
    assert_eq!(copied.report.fused, 0);
    assert!(copied.unfused.is_empty());
    // The same views and picks: the judged image is the copies', pixel for pixel.
    let filled = |f: &Filled| f.report.sources.iter().map(|s| s.filled).collect::<Vec<_>>();
    assert_eq!(filled(&out), filled(&copied));
    assert!(out.judged_image() == copied.image);
    assert_eq!(out.unfused.len(), out.report.fused);
}

/// A fill cancelled once the views are being averaged in stops there and returns the
/// keyframe as it is, as a fill cancelled at any other stage does: the service, stopping,
/// does not wait for the averaging (half a second at 12 MP) nor publish a half-fused image.
#[test]
fn a_fill_cancelled_while_averaging_returns_nothing_of_it() {
    use clearview::inpaint::{Observer, Stage};
    struct StopAt(Stage, bool);
    impl Observer for StopAt {
        fn stage(&mut self, stage: Stage) {
            self.1 |= stage == self.0;
        }
        fn cancelled(&self) -> bool {
            self.1
        }
    }
    let s = scene(3);
    let whole = s.run(&FillParams::default());
    assert!(whole.report.fused > 0, "the scene must be fused for the test to mean anything");
    let mut stop = StopAt(Stage::Fuse, false);
    let out = fill(&s.key, &s.mask, &s.sources(), &FillParams::default(), 1, &mut stop);
    assert!(stop.1, "the fill never reached the averaging");
    assert!(out.image == s.key, "a cancelled fill returned an image of its own");
    assert_eq!(out.report.fused, 0);
    assert!(out.unfused.is_empty());
}

#[test]
fn a_fill_cancelled_while_marking_the_views_occluders_goes_no_further() {
    use clearview::inpaint::{Observer, Stage};
    // The views' own occluders take seconds on many views: a stop asked for then is heard
    // before the views are warped.
    struct StopAt(Vec<Stage>);
    impl Observer for StopAt {
        fn stage(&mut self, stage: Stage) {
            self.0.push(stage);
        }
        fn cancelled(&self) -> bool {
            self.0.contains(&Stage::Own)
        }
    }
    let s = scene(3);
    let mut stop = StopAt(Vec::new());
    let out = fill(&s.key, &s.mask, &s.sources(), &FillParams::default(), 1, &mut stop);
    assert_eq!(stop.0, vec![Stage::Own], "stages after the stop was asked for");
    assert!(out.image == s.key, "a cancelled fill returned an image of its own");
}

#[test]
fn views_that_share_their_error_are_not_averaged() {
    // Every view a blurred rendering of the facade: their errors around the hole are the
    // same blur, and an average of them would only be as blurred as each.
    let mut s = scene(3);
    for v in &mut s.views {
        *v = blur3(v);
    }
    let out = s.run(&FillParams::default());
    let copied = s.run(&FillParams { fuse: None, ..FillParams::default() });
    let (fused, plain) =
        (masked_psnr(&out.image, &s.truth, &s.mask), masked_psnr(&copied.image, &s.truth, &s.mask));
    eprintln!("fused {fused:.2} dB ({} pixels), copies only {plain:.2} dB", out.report.fused);
    assert!(fused > plain - 0.1, "fused {fused:.2} dB, copies only {plain:.2} dB");
    // The rings say so: nothing is averaged (forced, every pixel would be, at the same
    // PSNR, so the figure alone could not tell).
    assert_eq!(out.report.fused, 0, "{:?}", out.report);
}

/// Two passes of a 3 × 3 box.
fn blur3(img: &RgbF32) -> RgbF32 {
    let mut out = img.clone();
    for _ in 0..2 {
        let src = out.clone();
        let (w, h) = (src.width(), src.height());
        out = RgbF32::from_fn(w, h, |x, y| {
            let mut acc = [0.0f32; 3];
            let mut n = 0.0;
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    let p = src.get(xx, yy);
                    for c in 0..3 {
                        acc[c] += p[c];
                    }
                    n += 1.0;
                }
            }
            acc.map(|a| a / n)
        });
    }
    out
}
