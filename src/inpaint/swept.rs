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
    FillExtras, FillParams, Filled, Gathered, Observer, Quiet, Source, Stage, backed_by, backed_by_in,
    fill_gathered, fill_with,
};
use crate::imaging::convert::luminance;
use crate::imaging::{GrayF32, Mask, Plane, RgbF32, RgbPixel};

/// A fill made by [`fill_swept`].
#[derive(Debug, Clone)]
pub struct Swept {
    pub filled: Filled,
    /// The surfaces off the wall the sweep found (empty: none, and `filled` is the walls').
    pub planes: Vec<SurfacePlane>,
    /// Whether `filled` was made through any of `planes` ([`Filled::surface`] says where).
    pub used: bool,
    /// Per surface of `planes`: whether `filled` was made through it (the judge kept it).
    pub kept: Vec<bool>,
    /// The inputs as the judge saw them, reduced ([`FillParams::judge_max_pixels`]): a
    /// later judgement of the same inputs ([`judged_with_marks`]) takes them from here.
    judged_on: Option<Reduced>,
}

impl Swept {
    /// The surfaces `filled` was made through ([`Swept::kept`]).
    pub fn kept_planes(&self) -> Vec<SurfacePlane> {
        kept_of(&self.planes, &self.kept)
    }

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
            .zip(&self.kept)
            .map(|((p, filled_pixels), &kept)| SurfaceReport {
                region: [p.region.x + origin.0, p.region.y + origin.1, p.region.width, p.region.height],
                views: p.views.iter().flatten().count(),
                kept,
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
    /// Whether the result was filled through any of them: the views back the fill through
    /// them better than the walls' alone ([`fill_swept`]). When not, the result is the
    /// walls' fill.
    pub used: bool,
}

/// A surface off the wall that the sweep found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SurfaceReport {
    /// The keyframe rectangle it may be chosen in: x, y, width, height.
    pub region: [usize; 4],
    /// Views that see it (have a homography for it).
    pub views: usize,
    /// Whether the fill was made through it: the views back the fill through it, on the
    /// pixels it copied, better than the walls' ([`fill_swept`]).
    pub kept: bool,
    /// Masked pixels filled through it (none when it was not kept).
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

/// [`fill_with`] through those of the surfaces off the wall `planes` ([`sweep_surfaces`])
/// under which the views back the fill better than the walls' alone; without surfaces, or
/// with none backed, the walls' fill itself (`extras.planes` must be empty: the surfaces
/// are given here).
///
/// The fill through all the surfaces and the walls' fill are judged by the views (the share
/// of the mask the views that show the building back, as [`Filled::rival_quality`] says)
/// twice: the views warped through their walls' homographies, and through the surfaces.
/// Each fill agrees best with the evidence it was made from, so neither judgement alone can
/// tell; a surface is kept when, on the pixels the first fill copied through it, that fill
/// gains more under the surfaces' evidence than it loses under the walls', by more than its
/// part of [`FillParams::select_margin`] (the margin shared among the surfaces as the pixels
/// they copied; where the rival was filled through surfaces, unless it loses by more than
/// the whole margin: [`FillExtras::rival_swept`]). A surface that is there lines the views
/// up and gains much; one that is not (a label carried into the wall where a view it lacks
/// shows an occluder, a repeat of texture) gains little and loses where it moved the wall's lines
/// (BENCHMARKS.md, "Parallax"). Judged surface by surface, a false surface no longer takes
/// the true ones down with it, nor the true ones carry it (BENCHMARKS.md, eighty-fourth
/// session). When only some are kept, the fill is made again through those.
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
        return Swept { filled, planes, used: false, kept: Vec::new(), judged_on: None };
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
        let gains = judge(&r.key, &r.mask, &small, &with(&[]), params, quiet, through, &wall, &small_planes);
        let keep =
            if observer.cancelled() { vec![false; planes.len()] } else { gains.kept(margin(extras, params)) };
        let chosen = kept_of(&planes, &keep);
        let mut filled =
            fill_with(key, mask, sources, &FillExtras { planes: &chosen, ..*extras }, params, seed, observer);
        relabel(&mut filled, &keep);
        return Swept { filled, planes, used: !chosen.is_empty(), kept: keep, judged_on: Some(r) };
    }
    let (through, seen) =
        fill_gathered(key, mask, sources, &FillExtras { planes: &planes, ..*extras }, params, seed, observer);
    if observer.cancelled() {
        let kept = vec![false; planes.len()];
        return Swept { filled: through, planes, used: false, kept, judged_on: None };
    }
    observer.stage(Stage::Judge);
    let quiet = &mut Quiet(&*observer);
    // The walls' fill is the one made without the surfaces, the views' own occluders marked.
    let wall = fill_with(key, mask, sources, extras, params, seed, quiet);
    let gains = judge(key, mask, sources, extras, params, quiet, (&through, seen.as_ref()), &wall, &planes);
    drop(seen);
    let keep = gains.kept(margin(extras, params));
    if keep.iter().all(|&k| k) {
        Swept { filled: through, planes, used: true, kept: keep, judged_on: None }
    } else if keep.iter().all(|&k| !k) {
        Swept { filled: wall, planes, used: false, kept: keep, judged_on: None }
    } else {
        let chosen = kept_of(&planes, &keep);
        let mut filled =
            fill_with(key, mask, sources, &FillExtras { planes: &chosen, ..*extras }, params, seed, observer);
        relabel(&mut filled, &keep);
        Swept { filled, planes, used: true, kept: keep, judged_on: None }
    }
}

/// The surfaces of `planes` that `keep` marks.
fn kept_of(planes: &[SurfacePlane], keep: &[bool]) -> Vec<SurfacePlane> {
    planes.iter().zip(keep).filter(|(_, k)| **k).map(|(p, _)| p.clone()).collect()
}

/// A fill made through the surfaces `keep` marks, its [`Filled::surface`] labels brought
/// back to the indices of all the surfaces.
fn relabel(filled: &mut Filled, keep: &[bool]) {
    let index: Vec<u16> = keep.iter().enumerate().filter(|(_, k)| **k).map(|(p, _)| p as u16 + 1).collect();
    for s in filled.surface.as_mut_slice() {
        if *s > 0 {
            *s = index[usize::from(*s) - 1];
        }
    }
}

/// How well the views back each of `images` (results of this keyframe and mask, as
/// [`Filled::judged_image`] gives them) through the surfaces `swept` was filled through
/// ([`Swept::kept_planes`]; `swept` is the [`fill_swept`] of these inputs, and its reduced
/// inputs are judged on), with each view's own
/// occluders marked ([`FillExtras::own`] if given, else found as [`FillParams::own`] says):
/// the share of the mask that the views showing the building back, as
/// [`Filled::rival_quality`] says of a rival. Judged on the inputs reduced to
/// [`FillParams::judge_max_pixels`], as [`fill_swept`] judges.
///
/// A fill through the surfaces marks no own occluders, because a slab seen through the
/// wall's homography is marked like one; so its own judgement hears a view's own van,
/// copied through a surface, as a witness. Judged here, two results that differ there are
/// told apart by the views that show the building. The marks found through the walls are
/// judged again through the surfaces ([`super::own_occluders_off_surfaces`]): kept on the
/// slabs, they silenced the views that back a fill through the surfaces, and a session
/// kept its walls' result while the one-shot fill of the same views was 5.8 dB closer to
/// the truth (BENCHMARKS.md, eighty-sixth session).
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
    let (small, small_planes) = (r.sources(), r.planes(&swept.kept_planes()));
    let (occluders, own) = r.marks();
    let by =
        FillExtras { marks_through_planes: true, ..r.extras(&small_planes, &occluders, own.as_deref(), &[]) };
    let reduced: Vec<RgbF32> = images.iter().map(|image| reduce_rgb(image, levels)).collect();
    let reduced: Vec<&RgbF32> = reduced.iter().collect();
    let params = FillParams { own: params.own.as_ref().map(|o| o.halved(levels, mask)), ..params.clone() };
    backed_by(&r.key, &r.mask, &small, &by, &params, &reduced, &mut Quiet(observer))
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

/// What the judge found ([`fill_swept`]): per surface off the wall, how much better the views
/// back the fill through the surfaces than the walls' on the pixels the former copied through
/// it, and those pixels' share of the mask.
#[derive(Debug, Clone, PartialEq)]
struct Gains {
    /// Per surface: the gain, a share of the mask.
    gain: Vec<f64>,
    /// Per surface: the share of the mask the fill through the surfaces copied through it.
    share: Vec<f64>,
}

impl Gains {
    /// Which surfaces the fill is made through: each whose gain is more than its part of
    /// `margin` (the margin shared among the surfaces as the pixels they copied). Where the
    /// margin is negative (a rival filled through surfaces, [`margin`]), a surface stays
    /// unless it loses more than the whole margin: a part as small as a small surface's is
    /// below the wandering of its gain from one view to the next (a surface copying 4 % of
    /// the mask: +0.0013 to −0.0003 over five landings of the service's depth bench, its part
    /// 0.0003), and each flip is a result the views judge apart. A surface that copied nothing
    /// stays (its fill is the fill through them); when none that copied is kept, none is.
    fn kept(&self, margin: f64) -> Vec<bool> {
        let copied: f64 = self.share.iter().sum();
        let part = |a: f64| if margin < 0.0 { margin } else { margin * a / copied };
        let keep: Vec<bool> =
            self.gain.iter().zip(&self.share).map(|(&g, &a)| a == 0.0 || g > part(a)).collect();
        if keep.iter().zip(&self.share).any(|(&k, &a)| k && a > 0.0) { keep } else { vec![false; keep.len()] }
    }
}

/// How much better the views back the fill through the surfaces (`through`) than the walls'
/// (`wall`) on the pixels `through` copied through each surface: both fills judged under both
/// evidences, the views warped through the surfaces (`seen`, what `through` was made from)
/// and through their walls, no view's own occluders marked in either ([`fill_swept`]).
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
) -> Gains {
    // Through the walls with no view's own occluders marked, as through the surfaces
    // (`fill_with` marks none there), which is the evidence `through` was made from.
    let unmarked = FillParams { own: None, ..params.clone() };
    let by_walls = FillExtras { planes: &[], ..*extras };
    // Per class of pixel: the walls (0) and each surface `p` (`1 + p`) the fill through the
    // surfaces copied it through.
    let bins = planes.len() + 1;
    let surface = &through.surface;
    let bin = |x: usize, y: usize| usize::from(surface.get(x, y)).min(bins - 1);
    let (through_image, wall_image) = (through.judged_image(), wall.judged_image());
    let walls = backed_by_in(
        key,
        mask,
        sources,
        &by_walls,
        &unmarked,
        &[&through_image, &wall_image],
        &bin,
        bins,
        quiet,
    );
    let (mut by_surfaces, mut copied) = (vec![vec![0.0; bins]; 2], vec![0usize; bins]);
    if let Some(g) = seen {
        by_surfaces =
            [&through_image, &wall_image].map(|image| g.judge_by(key, mask, image, &bin, bins)).to_vec();
    }
    for (&s, &m) in surface.as_slice().iter().zip(mask.as_slice()) {
        if m > 127 {
            copied[usize::from(s).min(bins - 1)] += 1;
        }
    }
    let masked = mask.hole_count().max(1) as f64;
    let gains = Gains {
        gain: (1..bins)
            .map(|k| (by_surfaces[0][k] - by_surfaces[1][k]) + (walls[0][k] - walls[1][k]))
            .collect(),
        share: copied[1..].iter().map(|&n| n as f64 / masked).collect(),
    };
    tracing::debug!(
        walls_pixels = (by_surfaces[0][0] - by_surfaces[1][0]) + (walls[0][0] - walls[1][0]),
        through = ?(by_surfaces[0].iter().sum::<f64>(), walls[0].iter().sum::<f64>()),
        wall = ?(by_surfaces[1].iter().sum::<f64>(), walls[1].iter().sum::<f64>()),
        ?gains.gain,
        ?gains.share,
        regions = ?planes.iter().map(|p| p.region).collect::<Vec<_>>(),
        "surfaces judged against the walls"
    );
    gains
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

    /// Each surface is judged on the pixels it copied: on this facade (seed 25, the true
    /// surfaces) the fill through all of them gains too little as a whole for the judge of
    /// the whole (the two evidences nearly cancel), and the first surface gains a fifth of
    /// the mask on its own pixels. It is kept, and the result is 6 dB closer to the truth
    /// than the walls' fill.
    #[test]
    fn a_surface_that_gains_on_its_own_pixels_is_kept() {
        use crate::imaging::metrics::masked_psnr;
        let c = parallax_case(640, 480, 3, 25, false);
        let planes = c.true_surfaces(24);
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let (none, params) = (FillExtras::default(), FillParams::default());
        let through_extras = FillExtras { planes: &planes, ..none };
        let (through, seen) = fill_gathered(&c.key, &c.mask, &sources, &through_extras, &params, 7, &mut ());
        let wall = fill_with(&c.key, &c.mask, &sources, &none, &params, 7, &mut ());
        let gains = judge(
            &c.key,
            &c.mask,
            &sources,
            &none,
            &params,
            &mut Quiet(&()),
            (&through, seen.as_ref()),
            &wall,
            &planes,
        );
        // The judge of the whole (each fill under its own evidence, the walls' with the views'
        // own occluders marked, and under the other's) would have taken the walls' fill.
        let unmarked = FillParams { own: None, ..params.clone() };
        let by_walls =
            backed_by(&c.key, &c.mask, &sources, &none, &unmarked, &[&through.judged_image()], &mut ())[0];
        let wall_by_planes =
            seen.as_ref().expect("a fill was made").judge(&c.key, &c.mask, &wall.judged_image());
        let whole =
            (through.report.witnessed_quality - wall_by_planes) + (by_walls - wall.report.witnessed_quality);
        assert!(whole < params.select_margin, "as a whole, the surfaces gain {whole:.4}");
        assert!(gains.gain[0] > 0.1, "{gains:?}");
        let swept = fill_swept(&c.key, &c.mask, &sources, &none, &params, planes.clone(), 7, &mut ());
        assert!(swept.used && swept.kept[0], "{:?}", swept.kept);
        let through_first = swept.filled.surface.as_slice().iter().filter(|&&s| s == 1).count();
        assert!(through_first > c.mask.hole_count() / 4, "{through_first} pixels through the first surface");
        let (result, walls_fill) = (
            masked_psnr(&swept.filled.image, &c.truth, &c.mask),
            masked_psnr(&wall.image, &c.truth, &c.mask),
        );
        assert!(result > walls_fill + 6.0, "{result:.2} dB against the walls' {walls_fill:.2}");
    }

    /// Each surface is kept on its part of the margin, shared as the pixels the surfaces
    /// copied: a small surface that gains little is kept, a large one that gains as little
    /// is not; with a negative margin (a rival through surfaces) a surface goes only when it
    /// loses more than the whole margin. One that copied nothing stays, unless nothing else
    /// does.
    #[test]
    fn each_surface_is_kept_on_its_part_of_the_margin() {
        let gains =
            Gains { gain: vec![0.004, 0.004, 0.2, -0.001, 0.0], share: vec![0.02, 0.6, 0.18, 0.2, 0.0] };
        assert_eq!(gains.kept(0.01), [true, false, true, false, true]);
        assert_eq!(gains.kept(-0.01), [true, true, true, true, true]);
        assert_eq!(gains.kept(5.0), [false; 5], "none that copied is kept");
        let losing = Gains { gain: vec![-0.01, 0.0], share: vec![0.4, 0.0] };
        assert_eq!(losing.kept(-0.005), [false, false]);
        assert_eq!(losing.kept(-0.05), [true, true]);
        // Against a rival through surfaces, a small surface that loses a little more than its
        // part stays: it goes on the whole margin.
        let small = Gains { gain: vec![0.14, -0.0003, 0.066], share: vec![0.57, 0.04, 0.18] };
        assert_eq!(small.kept(0.005), [true, false, true]);
        assert_eq!(small.kept(-0.005), [true, true, true]);
        assert_eq!(small.kept(-0.0002), [true, false, true]);
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
        let gains =
            judge(&c.key, &c.mask, &sources, &none, &params, &mut Quiet(&()), through, &wall, &planes);
        assert!(gains.kept(params.select_margin).iter().all(|&k| k), "the true surfaces gain: {gains:?}");
        // Above every surface's gain on its part of the margin.
        let copied: f64 = gains.share.iter().sum();
        let most =
            gains.gain.iter().zip(&gains.share).filter(|(_, a)| **a > 0.0).map(|(g, a)| g * copied / a);
        let near = FillParams { select_margin: 2.0 * most.fold(0.0, f64::max), ..params };
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
