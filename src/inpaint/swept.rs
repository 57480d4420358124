//! The fill through the surfaces standing off the wall (issue 14), as `clearview fill` and
//! the service both make it: the surfaces swept around the mask from the views
//! ([`swept_planes_memo`]); where there are any, the fill through them and the fill through
//! the walls alone, each judged by the views both ways, and the one the views back better
//! (pure layer).
//!
//! The sweep asks the fill's observer whether it is cancelled between its steps (the
//! matching of the keyframe's corners, of the grid beside the mask, the sweep itself).

use serde::Serialize;

use super::parallax::{SurfacePlane, SweepParams, ViewMatches, swept_planes_memo};
use super::reduced::{Reduced, levels_for, reduce_rgb};
use super::{
    FillExtras, FillParams, Filled, Gathered, Observer, Quiet, Source, Stage, backed_by, fill_gathered,
    fill_with,
};
use crate::imaging::convert::luminance;
use crate::imaging::{GrayF32, Mask, Plane, RgbF32, RgbPixel};

/// A fill made by [`fill_swept`].
#[derive(Debug, Clone)]
pub struct Swept {
    pub filled: Filled,
    /// The surfaces off the wall the sweep found (empty: none, and `filled` is the walls').
    pub planes: Vec<SurfacePlane>,
    /// Whether `filled` was made through `planes` ([`Filled::surface`] says where).
    pub used: bool,
    /// The inputs as the judge saw them, reduced ([`FillParams::judge_max_pixels`]): a
    /// later judgement of the same inputs ([`judged_with_marks`]) takes them from here.
    judged_on: Option<Reduced>,
}

impl Swept {
    /// What the sweep found and did, for a report: per surface, its region (moved by
    /// `origin`, the keyframe position of the part `mask` covers), its views and the masked
    /// pixels filled through it, and whether the fill was made through the surfaces.
    pub fn report(&self, mask: &Mask, origin: (usize, usize)) -> SurfacesReport {
        let mut filled = vec![0usize; self.planes.len()];
        for (&s, &m) in self.filled.surface.as_slice().iter().zip(mask.as_slice()) {
            if m > 127 && s > 0 {
                filled[usize::from(s) - 1] += 1;
            }
        }
        let surfaces = self
            .planes
            .iter()
            .zip(filled)
            .map(|(p, filled_pixels)| SurfaceReport {
                region: [p.region.x + origin.0, p.region.y + origin.1, p.region.width, p.region.height],
                views: p.views.iter().flatten().count(),
                filled_pixels,
            })
            .collect();
        SurfacesReport { surfaces, used: self.used }
    }

    /// Which surface filled each pixel, as a picture can hold it (`mask`'s size): 0 outside
    /// the mask, inside 1 where the pixel was filled through its view's wall and `2 + s`
    /// where through surface `s` ([`Swept::report`]'s `surfaces[s]`; 255 from surface 253
    /// on). `clearview fill --surfaces` writes it, and the service as `surfaces.png`.
    pub fn surface_map(&self, mask: &Mask) -> Plane<u8> {
        let surface = &self.filled.surface;
        Plane::from_fn(mask.width(), mask.height(), |x, y| {
            if mask.is_hole(x, y) { surface.get(x, y).saturating_add(1).min(255) as u8 } else { 0 }
        })
    }
}

/// What the sweep for surfaces off the wall found and did ([`Swept::report`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SurfacesReport {
    /// The surfaces off the wall the sweep found (empty: none).
    pub surfaces: Vec<SurfaceReport>,
    /// Whether the result was filled through them: the views back that fill better than
    /// the walls' alone ([`fill_swept`]). When not, the result is the walls' fill.
    pub used: bool,
}

/// A surface off the wall that the sweep found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SurfaceReport {
    /// The keyframe rectangle it may be chosen in: x, y, width, height.
    pub region: [usize; 4],
    /// Views that see it (have a homography for it).
    pub views: usize,
    /// Masked pixels filled through it (none when the walls' fill was kept).
    pub filled_pixels: usize,
}

/// The surfaces off the wall around the mask, swept from the views ([`swept_planes_memo`]),
/// in the keyframe's coordinates (see [`SurfacePlane::in_part`] for a part of it). `memo`
/// holds one entry per source: each view's guided matches, kept for the next sweep of the
/// same keyframe and mask (a session's next fill matches only its new views); give fresh
/// entries (`ViewMatches::default()`) for a view not swept before. `observer` is asked
/// between the sweep's steps whether it is cancelled; a cancelled sweep finds no surfaces
/// (the fill after it, asked too, is then unfinished). `key` is the keyframe's luminance
/// ([`crate::imaging::convert::luminance`]): a session holds it already, for alignment.
pub fn sweep_surfaces<P: RgbPixel>(
    key: &GrayF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    params: &SweepParams,
    seed: u64,
    memo: &mut [ViewMatches],
    observer: &mut dyn Observer,
) -> Vec<SurfacePlane> {
    if mask.hole_count() == 0 || sources.is_empty() {
        return Vec::new();
    }
    observer.stage(Stage::Sweep);
    let view = |v: usize| luminance(sources[v].image);
    let walls: Vec<_> = sources.iter().map(|s| s.homography).collect();
    let observer: &dyn Observer = observer;
    swept_planes_memo(key, &view, &walls, mask, params, seed, memo, &|| observer.cancelled())
}

/// [`fill_with`] through the surfaces off the wall `planes` ([`sweep_surfaces`]) where the
/// views back that fill better than the walls' alone; without surfaces, the walls' fill
/// itself (`extras.planes` must be empty: the surfaces are given here).
///
/// Each fill is judged by the views ([`Filled::rival_quality`]: the share of the mask the
/// views that show the building back) twice: the views warped through their walls'
/// homographies, and through the surfaces. Each fill agrees best with the evidence it was
/// made from, so neither judgement alone can tell; the surfaces are kept when their fill
/// gains more under the surfaces' evidence than it loses under the walls', by more than
/// [`FillParams::select_margin`] (where the rival was filled through surfaces, unless they
/// lose by more than it: [`FillExtras::rival_swept`]). A surface that is there lines the
/// views up and gains much;
/// one that is not (a label carried into the wall where a view it lacks shows an occluder, a
/// repeat of texture) gains little and loses where it moved the wall's lines (BENCHMARKS.md,
/// "Parallax").
///
/// A cancelled fill returns what [`fill_with`] returns when cancelled.
#[allow(clippy::too_many_arguments)]
pub fn fill_swept<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    planes: Vec<SurfacePlane>,
    seed: u64,
    observer: &mut dyn Observer,
) -> Swept {
    assert!(extras.planes.is_empty(), "the surfaces are given as `planes`");
    if planes.is_empty() {
        let filled = fill_with(key, mask, sources, extras, params, seed, observer);
        return Swept { filled, planes, used: false, judged_on: None };
    }
    let levels = levels_for(key.width(), key.height(), params.judge_max_pixels);
    if levels > 0 {
        // Judged on the inputs reduced; then the fill the judge chose, at full resolution.
        observer.stage(Stage::Judge);
        let r = Reduced::new(key, mask, sources, extras, levels);
        let (small, small_planes) = (r.sources(), r.planes(&planes));
        let (occluders, own) = r.marks();
        let quiet = &mut Quiet(&*observer);
        let with = |planes| r.extras(planes, &occluders, own.as_deref(), extras.choice);
        let (through, seen) =
            fill_gathered(&r.key, &r.mask, &small, &with(&small_planes), params, seed, quiet);
        let wall = fill_with(&r.key, &r.mask, &small, &with(&[]), params, seed, quiet);
        let through = (&through, seen.as_ref());
        let gain = judge(&r.key, &r.mask, &small, &with(&[]), params, quiet, through, &wall, &small_planes);
        let used = gain > margin(extras, params) && !observer.cancelled();
        let chosen = FillExtras { planes: if used { &planes } else { &[] }, ..*extras };
        let filled = fill_with(key, mask, sources, &chosen, params, seed, observer);
        return Swept { filled, planes, used, judged_on: Some(r) };
    }
    let (through, seen) =
        fill_gathered(key, mask, sources, &FillExtras { planes: &planes, ..*extras }, params, seed, observer);
    if observer.cancelled() {
        return Swept { filled: through, planes, used: false, judged_on: None };
    }
    observer.stage(Stage::Judge);
    let quiet = &mut Quiet(&*observer);
    // The walls' fill is the one made without the surfaces, the views' own occluders marked.
    let wall = fill_with(key, mask, sources, extras, params, seed, quiet);
    let gain = judge(key, mask, sources, extras, params, quiet, (&through, seen.as_ref()), &wall, &planes);
    drop(seen);
    if gain > margin(extras, params) {
        Swept { filled: through, planes, used: true, judged_on: None }
    } else {
        Swept { filled: wall, planes, used: false, judged_on: None }
    }
}

/// How well the views back each of `images` (results of this keyframe and mask, as
/// [`Filled::judged_image`] gives them) through the surfaces of `swept` (the
/// [`fill_swept`] of these inputs; its reduced inputs are judged on), with each view's own
/// occluders marked ([`FillExtras::own`] if given, else found as [`FillParams::own`] says):
/// the share of the mask that the views showing the building back, as
/// [`Filled::rival_quality`] says of a rival. Judged on the inputs reduced to
/// [`FillParams::judge_max_pixels`], as [`fill_swept`] judges.
///
/// A fill through the surfaces marks no own occluders, because a slab seen through the
/// wall's homography is marked like one; so its own judgement hears a view's own van,
/// copied through a surface, as a witness. Judged here, two results that differ there are
/// told apart by the views that show the building.
#[allow(clippy::too_many_arguments)]
pub fn judged_with_marks<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    swept: &Swept,
    images: &[&RgbF32],
    observer: &dyn Observer,
) -> Vec<f64> {
    let levels = levels_for(key.width(), key.height(), params.judge_max_pixels);
    let reduced;
    let r = match &swept.judged_on {
        Some(r) if r.levels() == levels => r,
        _ => {
            reduced = Reduced::new(key, mask, sources, extras, levels);
            &reduced
        }
    };
    let (small, small_planes) = (r.sources(), r.planes(&swept.planes));
    let (occluders, own) = r.marks();
    let by =
        FillExtras { marks_through_planes: true, ..r.extras(&small_planes, &occluders, own.as_deref(), &[]) };
    let reduced: Vec<RgbF32> = images.iter().map(|image| reduce_rgb(image, levels)).collect();
    let reduced: Vec<&RgbF32> = reduced.iter().collect();
    backed_by(&r.key, &r.mask, &small, &by, params, &reduced, &mut Quiet(observer))
}

/// The gain by which the surfaces are kept ([`fill_swept`]): [`FillParams::select_margin`],
/// or, where the rival was filled through surfaces ([`FillExtras::rival_swept`]), the same
/// margin the other way: the walls' fill replaces it only when clearly better. In a session
/// the judge's gain wanders around the margin as views arrive (a ten-view facade: −0.010,
/// +0.001, +0.002, +0.004, +0.006, +0.003), and each flip changed the published result by
/// up to 3 dB.
fn margin(extras: &FillExtras<'_>, params: &FillParams) -> f64 {
    if extras.rival_swept && extras.rival.is_some() { -params.select_margin } else { params.select_margin }
}

/// How much better the views back the fill through the surfaces (`through`) than the walls'
/// (`wall`), each judged under its own evidence and the other's ([`fill_swept`]).
#[allow(clippy::too_many_arguments)]
fn judge<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    extras: &FillExtras<'_>,
    params: &FillParams,
    quiet: &mut Quiet<'_>,
    (through, seen): (&Filled, Option<&Gathered>),
    wall: &Filled,
    planes: &[SurfacePlane],
) -> f64 {
    // Through the walls with no view's own occluders marked, as through the surfaces
    // (`fill_with` marks none there), which is the evidence `through` was made from.
    let unmarked = FillParams { own: None, ..params.clone() };
    let by_walls = FillExtras { planes: &[], ..*extras };
    let through_by_walls =
        backed_by(key, mask, sources, &by_walls, &unmarked, &[&through.judged_image()], quiet)[0];
    let wall_by_planes = seen.map_or(0.0, |g| g.judge(key, mask, &wall.judged_image()));
    let gain = (through.report.witnessed_quality - wall_by_planes)
        + (through_by_walls - wall.report.witnessed_quality);
    tracing::debug!(
        gain,
        through = through.report.witnessed_quality,
        through_by_walls,
        wall = wall.report.witnessed_quality,
        wall_by_planes,
        regions = ?planes.iter().map(|p| p.region).collect::<Vec<_>>(),
        "surfaces judged against the walls"
    );
    gain
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::facade::parallax_case;

    /// The judge's default budget keeps the evaluations' size (640 × 480) as it is and brings
    /// a 12 MP keyframe down to the same order (500 × 375), not to 1000 × 750, where its four
    /// fills cost 2.5 s more and decided no better (BENCHMARKS.md).
    #[test]
    fn the_default_judge_works_at_about_a_third_of_a_megapixel() {
        let budget = FillParams::default().judge_max_pixels;
        assert_eq!(levels_for(640, 480, budget), 0);
        assert_eq!(levels_for(1280, 960, budget), 1);
        assert_eq!(levels_for(4000, 3000, budget), 3);
    }

    /// The fill of case `c` through `planes` (seed 7).
    fn through_planes(
        c: &crate::synth::facade::ParallaxCase,
        sources: &[Source<'_>],
        planes: &[SurfacePlane],
        params: &FillParams,
    ) -> Filled {
        let extras = FillExtras { planes, ..FillExtras::default() };
        fill_with(&c.key, &c.mask, sources, &extras, params, 7, &mut ())
    }

    /// A near tie keeps what the current result was filled through: with the judge's margin
    /// set above the surfaces' gain, the walls' fill is taken when the rival was filled
    /// through the walls (or there is none), and the surfaces when it was filled through
    /// them. The gain is the judge's own, measured first.
    #[test]
    fn a_near_tie_keeps_what_the_rival_was_filled_through() {
        let c = parallax_case(320, 240, 3, 3, false);
        let planes = c.true_surfaces(12);
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let none = FillExtras::default();
        let params = FillParams::default();
        let through_extras = FillExtras { planes: &planes, ..none };
        let (through, seen) = fill_gathered(&c.key, &c.mask, &sources, &through_extras, &params, 7, &mut ());
        let wall = fill_with(&c.key, &c.mask, &sources, &none, &params, 7, &mut ());
        let through = (&through, seen.as_ref());
        let gain = judge(&c.key, &c.mask, &sources, &none, &params, &mut Quiet(&()), through, &wall, &planes);
        assert!(gain > params.select_margin, "the true surfaces gain {gain:.4}");
        let near = FillParams { select_margin: 2.0 * gain, ..params };
        let rival = wall.judged_image();
        let used = |rival: Option<&RgbF32>, rival_swept: bool| {
            let extras = FillExtras { rival, rival_swept, ..none };
            fill_swept(&c.key, &c.mask, &sources, &extras, &near, planes.clone(), 7, &mut ()).used
        };
        assert!(!used(None, false), "no rival: a near tie goes to the walls");
        assert!(!used(Some(&rival), false), "a rival through the walls: the walls");
        assert!(used(Some(&rival), true), "a rival through the surfaces: the surfaces");
        assert!(!used(None, true), "no rival to keep");
    }

    /// The judge's shortcuts judge as a fill would: [`backed_by`] gives an image the figure
    /// a fill with that image as its rival gives it (none made), and the evidence a fill
    /// through the surfaces was made from ([`fill_gathered`]) judges another result as
    /// [`backed_by`] does through the same surfaces with no view's occluders marked.
    #[test]
    fn a_result_is_judged_without_a_fill_as_a_fill_judges_it() {
        let c = parallax_case(320, 240, 3, 3, false);
        let planes = c.true_surfaces(12);
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let params = FillParams::default();
        let none = FillExtras::default();
        let surfaces = FillExtras { planes: &planes, ..none };
        let wall = fill_with(&c.key, &c.mask, &sources, &none, &params, 7, &mut ()).judged_image();
        let (through, seen) = fill_gathered(&c.key, &c.mask, &sources, &surfaces, &params, 7, &mut ());
        let through = through.judged_image();
        let judging = FillParams { select_views: false, fuse: None, ..params.clone() };
        for (extras, image, other) in [(&none, &through, &wall), (&surfaces, &wall, &through)] {
            let as_rival = FillExtras { rival: Some(image), ..*extras };
            let rival = fill_with(&c.key, &c.mask, &sources, &as_rival, &judging, 7, &mut ()).rival_quality;
            let rival = rival.expect("judged");
            let both = backed_by(&c.key, &c.mask, &sources, extras, &params, &[image, other], &mut ());
            assert!((both[0] - rival).abs() < 1e-9, "{} against {rival}", both[0]);
            assert!((both[0] - both[1]).abs() > 1e-3, "the two results are told apart: {both:?}");
        }
        let unmarked = FillParams { own: None, ..params.clone() };
        let by = backed_by(&c.key, &c.mask, &sources, &surfaces, &unmarked, &[&wall], &mut ())[0];
        let seen = seen.expect("a fill was made").judge(&c.key, &c.mask, &wall);
        assert!((seen - by).abs() < 1e-9, "{seen} against {by}");
    }

    /// A judgement with the marks after a fill through the surfaces reads the inputs the
    /// fill's judge reduced, and judges as on inputs reduced afresh.
    #[test]
    fn the_judgement_with_the_marks_reads_the_inputs_the_judge_reduced() {
        let c = parallax_case(640, 480, 3, 3, false);
        let planes = c.true_surfaces(24);
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let none = FillExtras::default();
        let params = FillParams { judge_max_pixels: 640 * 480 / 4, ..FillParams::default() };
        let swept = fill_swept(&c.key, &c.mask, &sources, &none, &params, planes, 7, &mut ());
        assert_eq!(swept.judged_on.as_ref().map(Reduced::levels), Some(1), "judged halved");
        let wall = fill_with(&c.key, &c.mask, &sources, &none, &params, 7, &mut ()).judged_image();
        let images = [&swept.filled.judged_image(), &wall];
        let kept = judged_with_marks(&c.key, &c.mask, &sources, &none, &params, &swept, &images, &());
        let afresh = Swept { judged_on: None, ..swept.clone() };
        let fresh = judged_with_marks(&c.key, &c.mask, &sources, &none, &params, &afresh, &images, &());
        assert_eq!(kept, fresh);
        assert!((kept[0] - kept[1]).abs() > 1e-3, "the two results are told apart: {kept:?}");
        let other =
            Swept { judged_on: Some(Reduced::new(&c.key, &c.mask, &sources, &none, 2)), ..swept.clone() };
        let at_two = judged_with_marks(&c.key, &c.mask, &sources, &none, &params, &other, &images, &());
        assert_eq!(at_two, fresh, "inputs reduced otherwise are reduced again");
    }

    /// A keyframe over the judge's budget is judged on its inputs halved, and the result is
    /// the full-size fill the judge chose: through the true surfaces of a facade with slabs,
    /// which line the views up where the walls cannot.
    #[test]
    fn a_large_keyframe_is_judged_halved_and_filled_at_full_size() {
        let c = parallax_case(640, 480, 3, 3, false);
        let planes = c.true_surfaces(24);
        assert!(!planes.is_empty());
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let none = FillExtras::default();
        for budget in [usize::MAX, 640 * 480 / 4] {
            let params = FillParams { judge_max_pixels: budget, ..FillParams::default() };
            let swept = fill_swept(&c.key, &c.mask, &sources, &none, &params, planes.clone(), 7, &mut ());
            assert!(swept.used, "budget {budget}: the true surfaces are chosen");
            let direct = through_planes(&c, &sources, &planes, &params);
            assert_eq!((swept.filled.image.width(), swept.filled.image.height()), (640, 480));
            assert!(
                swept.filled.image.as_slice() == direct.image.as_slice(),
                "budget {budget}: the fill through them"
            );
        }
    }
}
