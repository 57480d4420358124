//! The automatic mask: pixels where the keyframe disagrees with the consensus of the
//! aligned views are transient occluders (pure layer).
//!
//! A person or a car is where it is in one photograph only; the facade is the same in all
//! of them. So each view is warped into the keyframe, compensated photometrically, and
//! where at least `min_views` views agree with each other but not with the keyframe, the
//! keyframe shows something that was not there in the others. Small blobs (misregistration
//! along sharp edges, noise) are opened away, gaps closed, and the result grown a little so
//! that the fill also replaces the object's soft edge.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::Source;
use super::parallax::{SurfacePlane, SweepParams, parallax_family_with};
use crate::geometry::Homography;
use crate::imaging::convert::{luma, luminance, monochrome};
use crate::imaging::photometric::{Gain, ToneCurve, ToneParams, fit_tone};
use crate::imaging::warp::{Interpolation, Rect, warp};
use crate::imaging::{Mask, Plane, RgbF32, RgbPixel};

/// Parameters of [`auto_mask`].
#[derive(Debug, Clone, PartialEq)]
pub struct AutoMaskParams {
    /// At least this many views must see a pixel (and agree) to judge it.
    pub min_views: usize,
    /// RGB distance (Euclidean, 0..=√3) between the keyframe and the views' consensus
    /// above which a pixel is transient for certain (a seed of an object).
    pub threshold: f32,
    /// The lower threshold of the hysteresis: pixels whose keyframe differs from the
    /// consensus by more than this, or from every view that sees them by more than
    /// `threshold`, belong to an object when they are connected to a seed.
    pub low_threshold: f32,
    /// Views within this RGB distance of their median agree.
    pub agreement: f32,
    /// Both sides are box-averaged over `(2·r + 1)²` before comparing (tolerates the
    /// alignment's fraction of a pixel along sharp edges).
    pub blur_radius: usize,
    /// Opening radius of the seeds: removes specks and thin lines narrower than about twice
    /// this.
    pub open_radius: usize,
    /// Closing radius: joins a figure's parts.
    pub close_radius: usize,
    /// Holes inside an object (not reaching the image's border) up to this share of the
    /// image are part of it: an occluder is painted whole, not with the wall showing
    /// through where the views happened to agree with it.
    pub max_hole_share: f32,
    /// Where the keyframe's pixel looks more like the keyframe's own unflagged surroundings
    /// than the views' consensus does, by this factor of likelihood (averaged over a small
    /// window), it is the views that show something in front (an occluder every view shares,
    /// displaced by parallax), not the keyframe: such pixels are not flagged.
    pub background_ratio: f32,
    /// An object grows into neighbouring pixels whose colour is this many times more likely
    /// under the object's own colours than under the building's.
    pub colour_ratio: f32,
    /// Where no view shows what the keyframe shows, a view whose disagreement there is an
    /// object of its own (found where another view agrees with the keyframe) is not evidence
    /// against the keyframe ([`explain_by_own_occluders`]).
    pub own_objects: bool,
    /// After the first growth by colour, up to this many more around each object, each from
    /// the object as grown so far: an occluder the views share is found a crescent at a time
    /// (where its displaced copies in the views do not cover it), and the crescent's box is
    /// too small to reach across the crown.
    pub regrowth_passes: usize,
    /// In those passes, a pixel the views judged (they agree with each other there) is
    /// joined only when its colour is this many times likelier still: the views agreeing
    /// with the keyframe on a colour of the object is what an occluder they all show looks
    /// like, and also what the building looks like where it shares the object's colours
    /// (a dark car's road, a cloud's sky).
    pub judged_colour_factor: f32,
    /// The last growth by colour goes through pixels no two views agreed on only, and as
    /// far as this many quarters of the object's size beyond its box: where every view shows
    /// the same tree displaced its own way, the crown is unjudged wherever the copies land,
    /// and a seed at its rim is often a crescent whose box holds a fraction of the crown.
    /// Past the box, only where enough views see the pixel and disagree, or where every
    /// view that sees it differs from the keyframe (not where too few views reach).
    pub unjudged_reach: usize,
    /// The keyframe is also compared with the consensus moved by up to this many work
    /// pixels, patch against patch: what matches a little further along is the building seen
    /// with parallax or a slightly imperfect alignment (a pier standing off the wall, the
    /// edge of a window), not an object in front of it.
    pub parallax_radius: usize,
    /// What stands off the wall (a plinth, the pavement, a pier nearer than the facade) is
    /// displaced in each view along the line through the view's epipole, by as much as its
    /// depth says: tens of pixels for the ground in front of a building, far beyond
    /// `parallax_radius`. Where each of enough views shows the keyframe's patch somewhere on
    /// that line, within this share of the work image's diagonal (0: not looked for), the
    /// keyframe shows the scene at another depth, not an occluder: at least `min_views` views,
    /// and at least half of those that see the pixel. The epipoles come from the keyframe's
    /// corners matched in the views ([`super::parallax::parallax_family_with`]); a view without
    /// one explains nothing.
    pub epipolar_reach: f32,
    /// With a single view there is no consensus: where the keyframe and that view differ,
    /// either may show something in front, or the scene may stand off the wall and be seen
    /// from elsewhere (parallax tens of pixels wide, in directions no one epipole explains
    /// when the alignment's plane is itself a compromise). A person is where it is in one
    /// photograph only: the keyframe's 5 × 5 patch that the view shows anywhere within this
    /// share of the work image's diagonal (a nearest-patch search, PatchMatch's) is the
    /// scene, displaced, and no evidence of an occluder; the keyframe's own object is found
    /// nowhere near. 0: a single view judges nothing (`min_views` holds).
    pub lone_view_reach: f32,
    /// Where the views overlap in part, what one view alone sees is judged by that view, by
    /// the lone view's rule (`lone_view_reach`; 0 there: not judged); its disagreement
    /// seeds an object only where it is one 8-connected region of at least this share of the
    /// work image (0.001: about 1 500 work pixels, a passer-by's torso on a 1.5 MP work
    /// image), since one view alone has no second opinion.
    pub seen_once_seed: f32,
    /// The evidence compares the keyframe with the views' consensus in colour. Where the
    /// views show the building each a little differently (a slab off the wall, seen with
    /// another parallax in each; a face lit otherwise; mullions off curved glass), the
    /// consensus is a blend that matches none of them, and the keyframe's building is
    /// flagged as an occluder would be. Here each view is asked on its own: a pixel with
    /// texture (its 7 × 7 luminance window varies by more than [`SHADING_TEXTURE`]) whose
    /// window enough views show within a pixel, with this normalised cross-correlation or
    /// more (mean and contrast left free, the contrasts within [`SHADING_CONTRAST`] of each
    /// other), is no evidence of an occluder; not within [`SHADING_APART`] (or
    /// [`SHADING_APART_GREY`]) of what stays strong evidence (the outline of a passer-by's
    /// dark legs on a dark car correlates with the car). 0: not looked for.
    pub shading_ncc: f32,
    /// The sky is never an occluder: clouds drift between the shots, and the views agree on
    /// a sky the keyframe does not show, but there is no building behind it to bring back
    /// (filled, it came out a patchwork of the views' skies). Sky here is what is smooth and
    /// bright and reaches the top of the frame ([`sky`]): a pixel whose luminance gradient,
    /// averaged over 5 × 5 work pixels, is below `sky_gradient` (per work pixel; 0: no sky
    /// is looked for) and whose luminance is at least `sky_luma`, 4-connected through such
    /// pixels to the top 2 % of the rows, with its bright rim 2 px past the skyline. Foliage,
    /// branches and the edges of a building are far above that gradient: an occluder
    /// standing against the sky keeps its own pixels, and the sky stops at the skyline.
    pub sky_gradient: f32,
    pub sky_luma: f32,
    /// ...and no pixel of the sky is itself on an edge steeper than this (its own gradient,
    /// not averaged, in the steepest colour channel: a board of the sky's luminance but
    /// another hue is no sky either): the faint outline of a plain pale object against a
    /// plain pale wall that reaches the top (a white board before a rendered facade) stops
    /// the sky there, where the average alone let it through and the object was lost whole.
    pub sky_edge: f32,
    /// Clouds: from that sky, the sky goes on through pixels that are bright (`sky_luma`)
    /// and smooth in colour: the steepest channel's gradient (before the comparison's blur),
    /// averaged over 5 × 5 work pixels, below this (0: not looked for), and its own below
    /// `sky_cloud_edge`. A streaked or rippled cloud bank is too textured for `sky_gradient`
    /// and cut the sky off from the bands of cloud nearer the horizon, which drift between
    /// the shots and were flagged across the frame; its colours change slowly. The outline of
    /// an object against the sky is a step in some channel even where its luminance is the
    /// sky's, and stops it.
    pub sky_cloud_gradient: f32,
    pub sky_cloud_edge: f32,
    /// The mask is finally grown by this many pixels (full resolution). The comparison's
    /// blur already reaches a reduced pixel past the outline (2 px on a 1440 × 1080
    /// keyframe), so 1 px more ends about where a person paints, 2 px past it: at 3 px the
    /// mask lay 3 px and more past that and the IoU with it was held near 0.94 on cases with
    /// nothing else to find (`the_mask_keeps_near_the_outline_a_person_paints`).
    pub dilate_radius: usize,
    /// The comparison runs on an image box-reduced to at most this many pixels.
    pub work_pixels: usize,
}

impl Default for AutoMaskParams {
    fn default() -> Self {
        Self {
            min_views: 2,
            threshold: 0.15,
            low_threshold: 0.08,
            agreement: 0.12,
            blur_radius: 1,
            open_radius: 2,
            close_radius: 3,
            max_hole_share: 0.06,
            background_ratio: 4.0,
            colour_ratio: 4.0,
            own_objects: true,
            regrowth_passes: 2,
            judged_colour_factor: 16.0,
            unjudged_reach: 2,
            parallax_radius: 3,
            epipolar_reach: 0.12,
            lone_view_reach: 0.05,
            seen_once_seed: 0.001,
            shading_ncc: 0.8,
            sky_gradient: 0.015,
            sky_luma: 0.35,
            sky_edge: 0.02,
            sky_cloud_gradient: 0.03,
            sky_cloud_edge: 0.04,
            dilate_radius: 1,
            work_pixels: 1_500_000,
        }
    }
}

/// What [`auto_mask_report`] found, and how sure it is.
#[derive(Debug, Clone, PartialEq)]
pub struct AutoMask {
    /// 255 = fill, keyframe-sized.
    pub mask: Mask,
    /// Connected objects in the mask.
    pub objects: usize,
    /// Share of the mask (before the final growth) that the views contradict directly (the
    /// rest was joined to it as part of the same object: weaker evidence, closed gaps, holes).
    pub certain_share: f64,
    /// Share of the keyframe that at least `min_views` agreeing views judged: elsewhere an
    /// occluder cannot be found.
    pub judged_share: f64,
    /// Those pixels (255), keyframe-sized: where the mask says what the views saw, not what
    /// growth, closing and the keyframe's own colours made of it.
    pub judged: Mask,
}

/// The mask of transient objects in `key` (255 = fill), judged against `sources`.
pub fn auto_mask<P: RgbPixel>(key: &RgbF32, sources: &[Source<'_, P>], params: &AutoMaskParams) -> Mask {
    auto_mask_report(key, sources, params).mask
}

/// Per pixel of the work image, what the views say about the keyframe.
struct Evidence {
    /// The keyframe differs from the agreeing views by more than `threshold`.
    strong: Plane<bool>,
    /// By more than `low_threshold`, or from every view that sees the pixel.
    weak: Plane<bool>,
    /// At least `min_views` views agree here.
    judged: Plane<bool>,
    /// At least `min_views` views see the pixel, and fewer agree: they disagree with each
    /// other (each may show the building, an occluder of its own, or the keyframe's
    /// occluder displaced), where too few views is no evidence at all.
    contested: Plane<bool>,
    /// The agreeing views' mean colour (the keyframe's own where none agree).
    consensus: RgbF32,
}

impl Evidence {
    /// Where there is evidence of an occluder, strong or weak.
    fn flagged(&self) -> Plane<bool> {
        Plane::from_fn(self.strong.width(), self.strong.height(), |x, y| {
            self.strong.get(x, y) || self.weak.get(x, y)
        })
    }
}

/// [`auto_mask`] with the figures that say how sure it is.
///
/// Stages: (1) each view warped into a reduced keyframe and compensated; (2) per pixel, the
/// consensus of the views that agree with each other, and the keyframe's distance to it
/// (strong and weak evidence), less what the views each show with the keyframe's texture,
/// only brighter or darker ([`AutoMaskParams::shading_ncc`]), what they show moved
/// along their epipolar lines
/// (the scene off the wall, [`AutoMaskParams::epipolar_reach`]) and, with a single view,
/// what it shows displaced ([`AutoMaskParams::lone_view_reach`]); (3) strong pixels where
/// the keyframe looks like its own surroundings and the consensus does not are dropped (the
/// views share an occluder there), and so is the sky ([`AutoMaskParams::sky_gradient`]), here and after every growth;
/// (4) seeds (strong, opened) grown by hysteresis through the weak pixels connected to them;
/// (5) closed, holes inside objects filled; (6) back to full size and grown.
pub fn auto_mask_report<P: RgbPixel>(
    key: &RgbF32,
    sources: &[Source<'_, P>],
    params: &AutoMaskParams,
) -> AutoMask {
    auto_mask_excluding(key, sources, &[], params)
}

/// [`auto_mask_report`] where some of the sources' pixels are known to show something in
/// front of the building (`known`: per source, or empty; source-sized, > 127 = an occluder,
/// as [`super::FillExtras::occluders`]): those pixels are no evidence, for or against the
/// keyframe.
///
/// # Panics
/// If `known` is neither empty nor one per source.
fn auto_mask_excluding<P: RgbPixel>(
    key: &RgbF32,
    sources: &[Source<'_, P>],
    known: &[Option<&Mask>],
    params: &AutoMaskParams,
) -> AutoMask {
    assert!(known.is_empty() || known.len() == sources.len(), "known occluders per source");
    let (w, h) = (key.width(), key.height());
    let empty = || AutoMask {
        mask: Mask::new(w, h, 0),
        objects: 0,
        certain_share: 0.0,
        judged_share: 0.0,
        judged: Mask::new(w, h, 0),
    };
    // One view, where two are asked for: judged by that view, each difference searched for
    // nearby in it ([`AutoMaskParams::lone_view_reach`]).
    let lone = sources.len() == 1 && params.min_views > 1 && params.lone_view_reach > 0.0;
    let lone_params;
    let params = if lone {
        lone_params = AutoMaskParams { min_views: 1, ..params.clone() };
        &lone_params
    } else {
        params
    };
    if sources.len() < params.min_views.max(1) || w == 0 || h == 0 {
        return empty();
    }
    let f = work_factor(w, h, params.work_pixels);
    let key_r = reduce(key, f);
    let (rw, rh) = (key_r.width(), key_r.height());
    let to_full = reduced_to_full(f);
    let from_full = to_full.inverse().expect("scaling is regular");
    // A black-and-white keyframe is compared by grey: the views' colours are not something
    // it shows wrongly (before, every colour view disagreed with it everywhere and the sky
    // and background vetoes took the whole frame: nothing was found).
    let grey = monochrome(&key_r);
    let warped: Vec<(RgbF32, Plane<bool>)> = sources
        .par_iter()
        .enumerate()
        .map(|(v, s)| {
            let mut view_r = reduce(s.image, f);
            if grey {
                view_r.as_mut_slice().iter_mut().for_each(|p| *p = [luma(*p); 3]);
            }
            let hr = from_full.after(&s.homography).after(&to_full);
            let mut wv = warp(&view_r, &hr, Rect::full(rw, rh), None, Interpolation::Bilinear);
            super::exclude(&mut wv, &s.homography.after(&to_full), known.get(v).copied().flatten());
            let light = fit_whole(&key_r, &wv.image, &wv.valid);
            let img = wv.image.map(|&p| light.apply(p));
            (box_blur(&img, &wv.valid, params.blur_radius), wv.valid)
        })
        .collect();
    let all = Plane::new(rw, rh, true);
    let key_b = box_blur(&key_r, &all, params.blur_radius);
    let mut ev = evidence(&key_b, &warped, params);
    if params.own_objects {
        explain_by_own_occluders(&key_b, &warped, &mut ev, params);
    }
    explain_by_parallax(&key_b, &mut ev, params);
    // One view's rule was measured without it (sixty-sixth session).
    if params.shading_ncc > 0.0 && !lone {
        let apart = if grey { SHADING_APART_GREY } else { SHADING_APART };
        explain_by_shading(&key_b, &warped, &mut ev, params, apart);
    }
    if lone {
        explain_by_displacement(&key_b, &warped, &mut ev, params);
    }
    let epipoles =
        if params.epipolar_reach > 0.0 { keyframe_epipoles(key, sources, &from_full) } else { Vec::new() };
    if params.epipolar_reach > 0.0 {
        explain_by_epipoles(&key_b, &warped, &epipoles, &mut ev, params);
    }
    // Where the views overlap only in part, what a single one of them sees is judged by it
    // alone, as a lone view is.
    if !lone && params.min_views > 1 && params.lone_view_reach > 0.0 {
        judge_seen_once(&key_b, &warped, &epipoles, &mut ev, params);
    }

    let sky = sky(&key_b, &key_r, params);
    let shared = shared_occluders(&key_b, &ev, params);
    let veto = Plane::from_fn(rw, rh, |x, y| shared.get(x, y) || sky.get(x, y));
    let keep = |p: &Plane<bool>| Plane::from_fn(rw, rh, |x, y| p.get(x, y) && !veto.get(x, y));
    let seeds = keep(&ev.strong);
    let seeds = dilate(&erode(&seeds, params.open_radius), params.open_radius);
    let reach = keep(&ev.flagged());
    let grown = grow_from(&seeds, &reach);
    // Up to `passes` growths of one kind, each from the objects as the last left them.
    let regrow = |mut objects: Plane<bool>, growth: Growth, passes: usize| {
        for _ in 0..passes {
            let next = grow_by_colour(&key_b, &objects, &ev, params, growth);
            if next == objects {
                break;
            }
            objects = next;
        }
        objects
    };
    let grown = regrow(grown, Growth::Around, 1);
    let grown = regrow(grown, Growth::Regrowth, params.regrowth_passes);
    // An object grown from crescents at a crown's edge is one object only now: grown again
    // through what the views could not judge, within and around its box
    // (`unjudged_reach`), it fills the crown.
    let grown = regrow(grown, Growth::ThroughUnjudged, 2);
    let closed = erode(&dilate(&grown, params.close_radius), params.close_radius);
    let max_hole = (params.max_hole_share.max(0.0) as f64 * (rw * rh) as f64) as usize;
    // Holes are looked for with the objects grown by 2 px, so that a hole joined to the
    // outside by a crack is one too.
    let thick = dilate(&closed, 2);
    let (filled, _) = fill_holes(&thick, max_hole);
    let with_holes =
        Plane::from_fn(rw, rh, |x, y| closed.get(x, y) || (filled.get(x, y) && !thick.get(x, y)));
    // Growth by colour, closing and holes take no sky either.
    let without_sky = Plane::from_fn(rw, rh, |x, y| with_holes.get(x, y) && !sky.get(x, y));
    let (objects, count) = fill_holes(&without_sky, 0);

    let total = objects.as_slice().iter().filter(|&&v| v).count();
    let certain = objects.as_slice().iter().zip(seeds.as_slice()).filter(|&(&o, &s)| o && s).count();
    let judged = ev.judged.as_slice().iter().filter(|&&v| v).count();
    let full = |p: &Plane<bool>| Plane::from_fn(w, h, |x, y| p.get((x / f).min(rw - 1), (y / f).min(rh - 1)));
    let byte = |b: &bool| if *b { 255 } else { 0 };
    AutoMask {
        mask: dilate(&full(&objects), params.dilate_radius).map(byte),
        objects: count,
        certain_share: if total == 0 { 0.0 } else { certain as f64 / total as f64 },
        judged_share: judged as f64 / (rw * rh) as f64,
        judged: full(&ev.judged).map(byte),
    }
}

/// Stage (2d): the pixels that one view only sees, when several were given. The views
/// often overlap in part: a passer-by at the keyframe's edge that one view reaches and the
/// others do not was judged by nobody (`min_views` agreeing views are asked for), and stayed
/// in the fill whole (photo-building-6: building1 and building3 for building2, the person on
/// the right seen by building3 alone, recall 0.75 and the fill 4.1 dB under the true mask's).
/// There the one view judges, by the rule a lone view is judged by
/// ([`AutoMaskParams::lone_view_reach`]: what it shows anywhere near is the scene,
/// displaced), and the epipolar lines are looked along as for the others.
///
/// One view's word is weaker than the views' consensus, and it only adds:
/// - it seeds an object only where its disagreement covers an object's size
///   ([`AutoMaskParams::seen_once_seed`]): the dark lip of a poster's frame at the keyframe's
///   edge, shown by one view as the grass beyond, seeded a blob grown through the speckle of a
///   vignette (hpatches-churchill, IoU 0.15–0.18 lower on all eight cases);
/// - where the stages before left a pixel flagged (no view shows the keyframe's colour, and
///   no object of the view's own explains that), it stays flagged, even where the one view
///   shows the keyframe's patch displaced: a passer-by's dark legs, found in a dark window
///   nearby, were cleared and stayed in the fill (photo-building-10, +0.8 → +4.2 dB).
fn judge_seen_once(
    key: &RgbF32,
    warped: &[(RgbF32, Plane<bool>)],
    epipoles: &[Option<Vector3<f64>>],
    ev: &mut Evidence,
    params: &AutoMaskParams,
) {
    let (w, h) = (key.width(), key.height());
    let once = Plane::from_fn(w, h, |x, y| warped.iter().filter(|(_, valid)| valid.get(x, y)).count() == 1);
    if !once.as_slice().iter().any(|&v| v) {
        return;
    }
    let one = AutoMaskParams { min_views: 1, ..params.clone() };
    let mut single = evidence(key, warped, &one);
    // Only those pixels are asked (the search is the costly part).
    for (i, _) in once.as_slice().iter().enumerate().filter(|&(_, &o)| !o) {
        single.strong.as_mut_slice()[i] = false;
        single.weak.as_mut_slice()[i] = false;
    }
    explain_by_parallax(key, &mut single, &one);
    explain_by_displacement(key, warped, &mut single, &one);
    if one.epipolar_reach > 0.0 {
        explain_by_epipoles(key, warped, epipoles, &mut single, &one);
    }
    let least = (f64::from(params.seen_once_seed.max(0.0)) * (w * h) as f64).ceil() as usize;
    // Measured as the seeds are: opened first ([`AutoMaskParams::open_radius`]).
    let r = params.open_radius;
    let seeds = without_specks(&dilate(&erode(&single.strong, r), r), least);
    for (i, _) in once.as_slice().iter().enumerate().filter(|&(_, &o)| o) {
        let flagged = ev.weak.as_slice()[i];
        ev.strong.as_mut_slice()[i] = seeds.as_slice()[i] && flagged;
        ev.weak.as_mut_slice()[i] = flagged || single.weak.as_slice()[i];
        ev.judged.as_mut_slice()[i] = single.judged.as_slice()[i];
        ev.contested.as_mut_slice()[i] = false;
        ev.consensus.as_mut_slice()[i] = single.consensus.as_slice()[i];
    }
}

/// `m` without its 8-connected components of fewer than `least` pixels.
fn without_specks(m: &Plane<bool>, least: usize) -> Plane<bool> {
    let mut out = m.clone();
    each_component(m, |members| {
        if members.len() < least {
            members.iter().for_each(|&(x, y)| out.set(x, y, false));
        }
    });
    out
}

/// Stage (4b): each object grows into the neighbouring pixels whose colour is much more
/// likely under its own colours than under the building's (the keyframe's unflagged pixels
/// that the views judged, around the object and in the whole keyframe), within a quarter of
/// its size: where the views show an occluder of their own over the keyframe's (and so agree
/// with it), the object is still one object.
fn grow_by_colour(
    key: &RgbF32,
    objects: &Plane<bool>,
    ev: &Evidence,
    params: &AutoMaskParams,
    growth: Growth,
) -> Plane<bool> {
    let judged = &ev.judged;
    let (w, h) = (key.width(), key.height());
    let near_objects = dilate(objects, 2);
    // The building is what the views saw and agreed with: a pixel no two views agree on
    // (the inside of a crown every view shows, each displaced its own way) is no sample of
    // it, even where nothing flagged it.
    let building_px = |x: usize, y: usize| !near_objects.get(x, y) && judged.get(x, y);
    let global = ColourHistogram::within(key, &Rect::full(w, h), building_px);
    let mut out = objects.clone();
    for component in components(objects) {
        let own = ColourHistogram::within(key, &component, |x, y| objects.get(x, y));
        let margin = (component.width.max(component.height) / 4).max(2);
        let zone = match growth {
            Growth::Around | Growth::Regrowth => component.grown(margin, w, h),
            Growth::ThroughUnjudged => component.grown(params.unjudged_reach * margin, w, h),
        };
        // The building as it looks around this object (a cloud is compared with the sky
        // about it, a tree with the wall behind it), outside the object's box only: what
        // lies within it may be more of the object that the views could not judge.
        let around = component.grown(2 * margin, w, h);
        let local =
            ColourHistogram::within(key, &around, |x, y| building_px(x, y) && !component.contains(x, y));
        // The building's colours over the whole keyframe, but not those of the zone the
        // object may grow into: an occluder whose inside the views could not judge (they
        // show the same tree, displaced) is unflagged there, and would count as building.
        let mut building = global.clone();
        building.remove(key, &zone, building_px);
        let likely = |x: usize, y: usize| {
            let c = key.get(x, y);
            let factor = match growth {
                Growth::Regrowth if judged.get(x, y) => params.judged_colour_factor,
                _ => 1.0,
            };
            own.density(c) > factor * params.colour_ratio * 0.5 * (local.density(c) + building.density(c))
        };
        let mut stack: Vec<(usize, usize)> = Vec::new();
        for y in zone.y..zone.y1() {
            for x in zone.x..zone.x1() {
                if objects.get(x, y) {
                    stack.push((x, y));
                }
            }
        }
        // Beyond its box, through what the views did not judge, only where they see and
        // disagree, or where what views there are all differ from the keyframe: a stretch
        // that a view sees as the keyframe does, or none sees (a frame's edge), says nothing
        // of an object there.
        let doubted =
            |x: usize, y: usize| component.contains(x, y) || ev.contested.get(x, y) || ev.weak.get(x, y);
        let open = |x: usize, y: usize| match growth {
            Growth::Around => true,
            Growth::Regrowth => judged.get(x, y) || doubted(x, y),
            Growth::ThroughUnjudged => !judged.get(x, y) && doubted(x, y),
        };
        grow_into(&mut out, stack, |x, y| zone.contains(x, y) && open(x, y) && likely(x, y));
    }
    out
}

/// Where [`grow_by_colour`] may take an object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Growth {
    /// Into its surroundings, up to a quarter of its size beyond its box.
    Around,
    /// The same again from the object as grown (`AutoMaskParams::regrowth_passes`), through
    /// judged pixels only on stronger colour evidence, and beyond its box through unjudged
    /// ones only where the views doubt the keyframe, as [`Growth::ThroughUnjudged`] goes:
    /// grown through what no view saw, a strip flagged at the edge of the views' reach (the
    /// far side of a wall's corner, `oxford-wall`) spread over the frame's corner that no
    /// view reached.
    Regrowth,
    /// Through pixels no two views agreed on only, within its box grown by
    /// [`AutoMaskParams::unjudged_reach`] quarters of its size (a later pass: the object's
    /// parts joined by the first pass; the views' judgement still stands).
    ThroughUnjudged,
}

/// Bounding boxes of the 8-connected components of `m`.
fn components(m: &Plane<bool>) -> Vec<Rect> {
    let mut out = Vec::new();
    each_component(m, |members| out.push(Rect::around(members)));
    out
}

/// The number of pixels of the largest 8-connected component of `m` (0 when it has none).
pub(crate) fn largest_component(m: &Plane<bool>) -> usize {
    let mut largest = 0;
    each_component(m, |members| largest = largest.max(members.len()));
    largest
}

/// Calls `f` with the pixels of each 8-connected component of `m`, in the order of their
/// first pixel in raster order.
pub(super) fn each_component(m: &Plane<bool>, mut f: impl FnMut(&[(usize, usize)])) {
    let (w, h) = (m.width(), m.height());
    let mut seen = Plane::new(w, h, false);
    let mut members = Vec::new();
    for start in 0..w * h {
        let (sx, sy) = (start % w, start / w);
        if !m.get(sx, sy) || seen.get(sx, sy) {
            continue;
        }
        seen.set(sx, sy, true);
        members.clear();
        flood(
            (w, h),
            vec![(sx, sy)],
            &NEIGHBOURS_8,
            |x, y| members.push((x, y)),
            |x, y| {
                let enter = m.get(x, y) && !seen.get(x, y);
                if enter {
                    seen.set(x, y, true);
                }
                enter
            },
        );
        f(&members);
    }
}

/// Euclidean RGB distance (0..=√3).
#[inline]
fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f32>()).sqrt()
}

/// Stage (2): per pixel, the consensus of the views that agree with each other and the
/// keyframe's distance to it.
fn evidence(key: &RgbF32, warped: &[(RgbF32, Plane<bool>)], params: &AutoMaskParams) -> Evidence {
    let (w, h) = (key.width(), key.height());
    // Each pixel is judged on its own: rows in parallel, each pixel's verdict as it was
    // one at a time ((strong, weak, contested), and the consensus where judged).
    type Verdict = (bool, bool, bool, Option<[f32; 3]>);
    let rows: Vec<Vec<Verdict>> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut vals: Vec<[f32; 3]> = Vec::with_capacity(warped.len());
            let mut chan: Vec<f32> = Vec::with_capacity(warped.len());
            (0..w)
                .map(|x| {
                    vals.clear();
                    vals.extend(warped.iter().filter(|(_, v)| v.get(x, y)).map(|(img, _)| img.get(x, y)));
                    if vals.is_empty() {
                        return (false, false, false, None);
                    }
                    let k = key.get(x, y);
                    // No view shows what the keyframe shows: weak evidence even where the
                    // views do not agree with each other (each may have an occluder of its
                    // own).
                    let unlike_all = vals.iter().all(|&v| dist(k, v) > params.threshold);
                    if vals.len() < params.min_views {
                        return (false, unlike_all, false, None);
                    }
                    let med: [f32; 3] = std::array::from_fn(|c| {
                        chan.clear();
                        chan.extend(vals.iter().map(|v| v[c]));
                        chan.sort_unstable_by(f32::total_cmp);
                        let n = chan.len();
                        0.5 * (chan[(n - 1) / 2] + chan[n / 2])
                    });
                    let (mut sum, mut n) = ([0.0f32; 3], 0usize);
                    for v in vals.iter().filter(|&&v| dist(v, med) < params.agreement) {
                        (0..3).for_each(|c| sum[c] += v[c]);
                        n += 1;
                    }
                    if n < params.min_views {
                        return (false, unlike_all, true, None);
                    }
                    let mean = sum.map(|s| s / n as f32);
                    let d = dist(k, mean);
                    let strong = d > params.threshold;
                    (strong, unlike_all || (!strong && d > params.low_threshold), false, Some(mean))
                })
                .collect()
        })
        .collect();
    let mut strong = Plane::new(w, h, false);
    let mut weak = Plane::new(w, h, false);
    let mut judged = Plane::new(w, h, false);
    let mut contested = Plane::new(w, h, false);
    let mut consensus = key.clone();
    for (y, row) in rows.into_iter().enumerate() {
        for (x, (s, wk, c, mean)) in row.into_iter().enumerate() {
            strong.set(x, y, s);
            weak.set(x, y, wk);
            contested.set(x, y, c);
            if let Some(mean) = mean {
                judged.set(x, y, true);
                consensus.set(x, y, mean);
            }
        }
    }
    Evidence { strong, weak, judged, contested, consensus }
}

/// Stage (2b): where no view shows what the keyframe shows and the views do not agree with
/// each other either, each view's disagreement may be an object of its own (a passer-by in
/// one, a car in the other) rather than the keyframe's. A view's own object is where it
/// differs from the keyframe while another view agrees with the keyframe (the keyframe
/// shows the building there), followed through the view's pixels that still differ from
/// the keyframe and look like that object rather than like the building. Where every view
/// that sees a pixel is explained so, and the keyframe's own colour there is no more like
/// those objects than like the building (an occluder every view shows, the keyframe
/// included, explains nothing), the pixel is not weak evidence against the keyframe.
fn explain_by_own_occluders(
    key: &RgbF32,
    warped: &[(RgbF32, Plane<bool>)],
    ev: &mut Evidence,
    params: &AutoMaskParams,
) {
    let (w, h) = (key.width(), key.height());
    // Only the pixels weak for want of any view showing the keyframe's colour are in doubt.
    let doubted = Plane::from_fn(w, h, |x, y| ev.weak.get(x, y) && !ev.judged.get(x, y));
    if !doubted.as_slice().iter().any(|&d| d) {
        return;
    }
    // Per view, its distance to the keyframe (infinite where it does not see the pixel)...
    let distance: Vec<Plane<f32>> = warped
        .iter()
        .map(|(img, valid)| {
            Plane::from_fn(w, h, |x, y| {
                if valid.get(x, y) { dist(img.get(x, y), key.get(x, y)) } else { f32::INFINITY }
            })
        })
        .collect();
    let differs = |v: usize, x: usize, y: usize| {
        let d = distance[v].get(x, y);
        d.is_finite() && d > params.threshold
    };
    // ...and how many views agree with the keyframe (a view that differs is not one of them).
    let agreeing =
        Plane::from_fn(w, h, |x, y| distance.iter().filter(|d| d.get(x, y) <= params.low_threshold).count());
    let building =
        ColourHistogram::within(key, &Rect::full(w, h), |x, y| ev.judged.get(x, y) && !ev.strong.get(x, y));
    let own: Vec<Option<(Plane<bool>, ColourHistogram)>> = (0..warped.len())
        .map(|v| {
            let seeds = Plane::from_fn(w, h, |x, y| differs(v, x, y) && agreeing.get(x, y) > 0);
            // Thin lines of disagreement are edges a little off: an object survives opening.
            let seeds = dilate(&erode(&seeds, params.open_radius), params.open_radius);
            if !seeds.as_slice().iter().any(|&s| s) {
                return None;
            }
            let img = &warped[v].0;
            let object = ColourHistogram::within(img, &Rect::full(w, h), |x, y| seeds.get(x, y));
            let reach = Plane::from_fn(w, h, |x, y| {
                differs(v, x, y) && {
                    let c = img.get(x, y);
                    object.density(c) > params.colour_ratio * building.density(c)
                }
            });
            Some((grow_from(&seeds, &reach), object))
        })
        .collect();
    let explained = |v: usize, x: usize, y: usize| {
        own[v].as_ref().is_some_and(|(object, colours)| {
            let k = key.get(x, y);
            object.get(x, y) && colours.density(k) <= building.density(k)
        })
    };
    for i in (0..w * h).filter(|&i| doubted.as_slice()[i]) {
        let (x, y) = (i % w, i / w);
        let mut seen = (0..warped.len()).filter(|&v| warped[v].1.get(x, y)).peekable();
        if seen.peek().is_some() && seen.all(|v| explained(v, x, y)) {
            ev.weak.set(x, y, false);
        }
    }
}

/// Half the side of the windows [`window_matches`] compares.
const HALF: isize = 2;
/// The pixels of such a window.
const WINDOW: usize = ((2 * HALF + 1) * (2 * HALF + 1)) as usize;

/// Whether the keyframe's 5×5 window at `(x, y)` (`key`, an image of `size`) matches
/// `other`'s moved by `(dx, dy)`: over the pixels inside both and `usable` at the moved
/// place, more than half the window, with a mean squared RGB distance of at most `t2`
/// ([`window_sum`]).
fn window_matches(
    key: &[[f32; 3]],
    other: &[[f32; 3]],
    usable: &[bool],
    size: (isize, isize),
    at: (isize, isize),
    by: (isize, isize),
    t2: f32,
) -> bool {
    window_sum(key, other, usable, size, at, by, t2)
        .is_some_and(|(sum, n)| n * 2 > WINDOW && sum <= t2 * n as f32)
}

/// The summed squared RGB distance of `key`'s 5 × 5 window at `(x, y)` to `other`'s moved
/// by `(dx, dy)` over the window's pixels `usable` in `other`, and their count; `None` as
/// soon as the sum is past what any count would bring to a mean of `bound`. Row by row,
/// taps in the order of a plain double loop.
fn window_sum(
    key: &[[f32; 3]],
    other: &[[f32; 3]],
    usable: &[bool],
    (wi, hi): (isize, isize),
    (x, y): (isize, isize),
    (dx, dy): (isize, isize),
    bound: f32,
) -> Option<(f32, usize)> {
    let hopeless = bound * WINDOW as f32;
    let (mut sum, mut n) = (0.0f32, 0usize);
    let (lo, up) = ((x - HALF).max(0).max(-dx), (x + HALF).min(wi - 1).min(wi - 1 - dx));
    for py in y - HALF..=y + HALF {
        let qy = py + dy;
        if py >= 0 && py < hi && qy >= 0 && qy < hi {
            let (row, moved) = ((py * wi) as usize, qy * wi + dx);
            for px in lo..=up {
                let q = (moved + px) as usize;
                if !usable[q] {
                    continue;
                }
                let (a, b) = (key[row + px as usize], other[q]);
                sum += (0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f32>();
                n += 1;
            }
        }
        if sum > hopeless {
            return None;
        }
    }
    Some((sum, n))
}

/// Strong pixels whose 5×5 patch matches the consensus moved by at most `parallax_radius`
/// become weak: the building, displaced.
fn explain_by_parallax(key: &RgbF32, ev: &mut Evidence, params: &AutoMaskParams) {
    let (w, h) = (key.width(), key.height());
    if params.parallax_radius == 0 {
        return;
    }
    let seen: &Evidence = ev;
    let search = Moves::new(key, &seen.consensus, &seen.judged, params.parallax_radius, params.threshold);
    let strong = seen.strong.as_slice();
    // Each pixel is judged on its own: in parallel, the same pixels as one at a time.
    let explained: Vec<usize> =
        (0..w * h).into_par_iter().filter(|&i| strong[i] && search.explains(i % w, i / w)).collect();
    for i in explained {
        ev.strong.as_mut_slice()[i] = false;
        ev.weak.as_mut_slice()[i] = true;
    }
}

/// The widest row of moves [`Moves::explains`] scores side by side (`2 · radius + 1`).
const MOVE_LANES: usize = 32;

/// Whether a pixel's 5 × 5 window of `key` matches `other` moved by up to `radius` pixels
/// each way, not by 0 ([`window_matches`] over every such move).
struct Moves<'a> {
    key: &'a [[f32; 3]],
    other: &'a [[f32; 3]],
    usable: &'a [bool],
    /// `other`'s channels apart, for the moves of a row scored side by side.
    channels: [Vec<f32>; 3],
    size: (usize, usize),
    radius: usize,
    /// The moves, the nearest first ([`window_matches`] one at a time, near the borders).
    moves: Vec<(isize, isize)>,
    /// Their rows (`dy`), the nearest first.
    rows: Vec<isize>,
    t2: f32,
}

impl<'a> Moves<'a> {
    fn new(
        key: &'a RgbF32,
        other: &'a RgbF32,
        usable: &'a Plane<bool>,
        radius: usize,
        threshold: f32,
    ) -> Self {
        let r = radius as isize;
        // The nearest moves first: the building moved by a pixel or two is the usual
        // answer, and the search stops at the first move that explains the pixel.
        let mut moves: Vec<(isize, isize)> =
            (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))).filter(|&m| m != (0, 0)).collect();
        moves.sort_by_key(|&(dx, dy)| dx * dx + dy * dy);
        let other_px = other.as_slice();
        Self {
            key: key.as_slice(),
            other: other_px,
            usable: usable.as_slice(),
            channels: std::array::from_fn(|c| other_px.iter().map(|p| p[c]).collect()),
            size: (key.width(), key.height()),
            radius,
            moves,
            rows: std::iter::once(0).chain((1..=r).flat_map(|d| [-d, d])).collect(),
            t2: threshold * threshold,
        }
    }

    /// Whether the window at `(x, y)` matches `other` moved by one of the moves. Away from
    /// the borders, the `2 · radius + 1` moves of a row (one `dy`) are scored side by side,
    /// the rows nearest first: each move's sum adds the same taps in the same order as
    /// [`window_sum`] (a tap not usable adds nothing), so each gets the same bits, and a
    /// sum that [`window_sum`] would give up on is past the bound and matches neither way.
    fn explains(&self, x: usize, y: usize) -> bool {
        let (w, h) = self.size;
        let (r, half) = (self.radius, HALF as usize);
        let lanes = 2 * r + 1;
        if x < r + half || x + r + half >= w || lanes > MOVE_LANES {
            let size = (w as isize, h as isize);
            let at = (x as isize, y as isize);
            return self
                .moves
                .iter()
                .any(|&m| window_matches(self.key, self.other, self.usable, size, at, m, self.t2));
        }
        let (y, r) = (y as isize, r as isize);
        let [c0, c1, c2] = &self.channels;
        let (mut sums, mut counts) = ([0.0f32; MOVE_LANES], [0u8; MOVE_LANES]);
        let hopeless = self.t2 * WINDOW as f32;
        for &dy in &self.rows {
            let (sums, counts) = (&mut sums[..lanes], &mut counts[..lanes]);
            sums.fill(0.0);
            counts.fill(0);
            for py in y - HALF..=y + HALF {
                let qy = py + dy;
                if py < 0 || py >= h as isize || qy < 0 || qy >= h as isize {
                    continue;
                }
                for px in x - half..=x + half {
                    let k = self.key[py as usize * w + px];
                    // `other`'s row at the moves of this tap: `px - r ..= px + r`.
                    let from = qy as usize * w + px - r as usize;
                    let row = from..from + lanes;
                    let taps = c0[row.clone()]
                        .iter()
                        .zip(&c1[row.clone()])
                        .zip(&c2[row.clone()])
                        .zip(&self.usable[row]);
                    for ((s, n), (((&a, &b), &c), &u)) in sums.iter_mut().zip(counts.iter_mut()).zip(taps) {
                        let d = (k[0] - a).powi(2) + (k[1] - b).powi(2) + (k[2] - c).powi(2);
                        *s += if u { d } else { 0.0 };
                        *n += u8::from(u);
                    }
                }
                // Every move of the row past what any count would bring to the bound.
                if sums.iter().all(|&s| s > hopeless) {
                    break;
                }
            }
            let matched = sums.iter().zip(counts.iter()).enumerate().any(|(j, (&s, &n))| {
                let n = usize::from(n);
                (dy != 0 || j != r as usize) && n * 2 > WINDOW && s <= self.t2 * n as f32
            });
            if matched {
                return true;
            }
        }
        false
    }
}

/// Stage (2b'), a single view ([`AutoMaskParams::lone_view_reach`]): strong and weak
/// pixels whose keyframe patch the view shows displaced by more than `parallax_radius` and
/// at most the reach are the scene seen from elsewhere: no evidence of an occluder. Only
/// patches with detail are searched (a plain one matches any plain patch of its colour);
/// the view's nearest patches are found as PatchMatch finds them ([`Displacements`]). A
/// plain stretch of flagged pixels goes with the detail around it ([`PLAIN_VERDICT`]).
fn explain_by_displacement(
    key: &RgbF32,
    warped: &[(RgbF32, Plane<bool>)],
    ev: &mut Evidence,
    params: &AutoMaskParams,
) {
    let (w, h) = (key.width(), key.height());
    let reach = (f64::from(params.lone_view_reach) * (w as f64).hypot(h as f64)).round() as isize;
    if reach <= params.parallax_radius as isize {
        return;
    }
    let t2 = params.threshold * params.threshold;
    // A patch whose own colours stray from their mean by less than the tolerance matches
    // any plain patch of its mean colour: found elsewhere, it says nothing of where it is
    // (the plain coat of a passer-by, found in a dark window nearby). Only patches with more
    // detail than that are searched.
    let spread = window_spread(key);
    let any = ev.flagged().as_slice().to_vec();
    let detailed: Vec<bool> = spread.as_slice().iter().map(|&v| v > t2).collect();
    let flagged: Vec<bool> = any.iter().zip(&detailed).map(|(&a, &d)| a && d).collect();
    let found: Vec<Vec<bool>> = warped
        .par_iter()
        .enumerate()
        .map(|(v, (img, valid))| {
            let search = Displacements { reach, near: params.parallax_radius as isize, t2 };
            search.matches(key, img, valid, &flagged, DISPLACEMENT_SEED ^ v as u64)
        })
        .collect();
    let explained: Vec<bool> = (0..w * h)
        .map(|i| {
            let seeing = warped.iter().filter(|(_, valid)| valid.as_slice()[i]).count();
            let found = found.iter().filter(|f| f[i]).count();
            flagged[i] && found >= params.min_views && 2 * found >= seeing
        })
        .collect();
    // A plain stretch takes the verdict of the detail around it: a plain wall between
    // window frames that the view shows displaced is the scene displaced too, while the
    // plain coat of a passer-by is bordered by the outline of the passer-by, found nowhere.
    let drop = with_plain_stretches(w, h, &any, &detailed, &explained);
    for (i, _) in drop.iter().enumerate().filter(|&(_, &d)| d) {
        ev.strong.as_mut_slice()[i] = false;
        ev.weak.as_mut_slice()[i] = false;
    }
}

/// `explained` (per pixel, among the flagged detail), with each plain stretch of flagged
/// pixels (flagged, not `detailed`, 8-connected) that takes the verdict of the flagged
/// detail bordering it. Where an object's colour runs on into the scene's without an edge,
/// the stretch is both, and is kept unless the detail explained outnumbers the rest
/// [`PLAIN_VERDICT`] times.
fn with_plain_stretches(
    w: usize,
    h: usize,
    any: &[bool],
    detailed: &[bool],
    explained: &[bool],
) -> Vec<bool> {
    let plain: Vec<bool> = any.iter().zip(detailed).map(|(&a, &d)| a && !d).collect();
    let mut seen = vec![false; w * h];
    let mut drop = explained.to_vec();
    for start in 0..w * h {
        if !plain[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let mut members = Vec::new();
        let (mut for_scene, mut against) = (0usize, 0usize);
        let start = (start % w, start / w);
        flood(
            (w, h),
            vec![start],
            &NEIGHBOURS_8,
            |x, y| members.push(y * w + x),
            |x, y| {
                let j = y * w + x;
                if plain[j] {
                    let enter = !seen[j];
                    seen[j] = true;
                    return enter;
                }
                if any[j] && detailed[j] {
                    if explained[j] {
                        for_scene += 1;
                    } else {
                        against += 1;
                    }
                }
                false
            },
        );
        if for_scene > PLAIN_VERDICT * against {
            members.into_iter().for_each(|i| drop[i] = true);
        }
    }
    drop
}

/// The least standard deviation of a 7 × 7 luminance window for it to have texture
/// ([`AutoMaskParams::shading_ncc`]): a plain window correlates with any plain one.
pub const SHADING_TEXTURE: f32 = 0.03;
/// The largest ratio of the two windows' contrasts (standard deviations, either way) for
/// them to show the same texture under other light ([`AutoMaskParams::shading_ncc`]): the
/// outline of an occluder against the building has more contrast than the building alone.
pub const SHADING_CONTRAST: f32 = 2.0;
/// Pixels within this distance of strong evidence that stays are not explained by shading
/// ([`AutoMaskParams::shading_ncc`]); the window's radius.
pub const SHADING_APART: usize = 3;
/// [`SHADING_APART`] for a keyframe compared by grey: there the evidence around an occluder
/// is thinner, and at 3 a pasted person lost 12 % of its pixels (at 6 in colour too, the
/// 44 cases of seeds 9–12 lose 0.009 of mean IoU and 0.09 dB of mean loss against 3:
/// BENCHMARKS.md, sixty-eighth session).
pub const SHADING_APART_GREY: usize = 6;

/// Stage (2a'): strong and weak pixels with texture whose window enough views (at least
/// `min_views`, and half of those that see them) each show, only brighter or darker, are
/// the building ([`AutoMaskParams::shading_ncc`]), unless within `apart` of strong evidence
/// that stays. Each view's luminance window is compared
/// with the keyframe's at the nine shifts within a pixel, by normalised cross-correlation
/// (mean and contrast left free, the contrasts within [`SHADING_CONTRAST`] of each other).
/// A plain stretch of flagged pixels goes with the texture around it ([`PLAIN_VERDICT`]).
fn explain_by_shading(
    key: &RgbF32,
    warped: &[(RgbF32, Plane<bool>)],
    ev: &mut Evidence,
    params: &AutoMaskParams,
    apart: usize,
) {
    // The 7 × 7 window's radius.
    const R: usize = 3;
    let (w, h) = (key.width(), key.height());
    let all = Plane::new(w, h, true);
    let k = key.map(|&p| luma(p));
    let kk = k.map(|&a| a * a);
    let (km, kkm) = (box_mean(&k, &all, R), box_mean(&kk, &all, R));
    let flagged = ev.flagged().as_slice().to_vec();
    let textured: Vec<bool> = (0..w * h)
        .map(|i| {
            let (m, m2) = (km.as_slice()[i], kkm.as_slice()[i]);
            m2 - m * m > SHADING_TEXTURE * SHADING_TEXTURE
        })
        .collect();
    let asked: Vec<bool> = (0..w * h).map(|i| flagged[i] && textured[i]).collect();
    let c2 = SHADING_CONTRAST * SHADING_CONTRAST;
    // Windows wholly inside the picture, moved by a pixel too.
    let inner = |x: usize, y: usize| x > R && y > R && x + R + 1 < w && y + R + 1 < h;
    let found: Vec<Vec<bool>> = warped
        .par_iter()
        .map(|(img, valid)| {
            // The view's window means, and where its window is whole; the window moved by
            // (dx, dy) is the one centred there.
            let v = img.map(|&p| luma(p));
            let (vm, vvm) = (box_mean(&v, &all, R), box_mean(&v.map(|&a| a * a), &all, R));
            let whole = box_mean(&valid.map(|&o| if o { 1.0 } else { 0.0 }), &all, R);
            let mut same = vec![false; w * h];
            for dy in -1isize..=1 {
                for dx in -1isize..=1 {
                    let moved = |x: usize, y: usize| ((x as isize + dx) as usize, (y as isize + dy) as usize);
                    let product = Plane::from_fn(w, h, |x, y| {
                        if !inner(x, y) {
                            return 0.0;
                        }
                        let (mx, my) = moved(x, y);
                        k.get(x, y) * v.get(mx, my)
                    });
                    let cross = box_mean(&product, &all, R);
                    for (i, s) in same.iter_mut().enumerate() {
                        let (x, y) = (i % w, i / w);
                        if *s || !asked[i] || !inner(x, y) {
                            continue;
                        }
                        let j = {
                            let (mx, my) = moved(x, y);
                            my * w + mx
                        };
                        if whole.as_slice()[j] < 1.0 {
                            continue;
                        }
                        let (a, a2, ab) = (km.as_slice()[i], kkm.as_slice()[i], cross.as_slice()[i]);
                        let (b, b2) = (vm.as_slice()[j], vvm.as_slice()[j]);
                        let (va, vb) = ((a2 - a * a).max(0.0), (b2 - b * b).max(0.0));
                        if va <= f32::EPSILON || vb <= f32::EPSILON || va > c2 * vb || vb > c2 * va {
                            continue;
                        }
                        *s = (ab - a * b) / (va * vb).sqrt() >= params.shading_ncc;
                    }
                }
            }
            same
        })
        .collect();
    let explained: Vec<bool> = (0..w * h)
        .map(|i| {
            if !asked[i] {
                return false;
            }
            let seeing = warped.iter().filter(|(_, valid)| valid.as_slice()[i]).count();
            let same = found.iter().filter(|f| f[i]).count();
            same >= params.min_views.max(1) && 2 * same >= seeing
        })
        .collect();
    let standing = Plane::from_fn(w, h, |x, y| ev.strong.get(x, y) && !explained[y * w + x]);
    let near = dilate(&standing, apart);
    let explained: Vec<bool> = explained.iter().zip(near.as_slice()).map(|(&e, &n)| e && !n).collect();
    // A plain stretch (no texture to correlate) goes with the texture around it.
    let drop = with_plain_stretches(w, h, &flagged, &textured, &explained);
    for (i, _) in drop.iter().enumerate().filter(|&(_, &d)| d) {
        ev.strong.as_mut_slice()[i] = false;
        ev.weak.as_mut_slice()[i] = false;
    }
}

/// How many times the flagged detail found displaced must outnumber the detail found
/// nowhere around a plain stretch for the stretch to be the scene displaced
/// ([`explain_by_displacement`]). Over 95 one-view cases (`bench/automask_cases.py`):
/// 1 lost whole trees whose plain crowns ran into the plain scene; 6 kept a whole roofscape
/// seen with parallax; 3 keeps the most of both (BENCHMARKS.md, sixty-sixth session).
const PLAIN_VERDICT: usize = 3;

/// Per pixel, the mean squared RGB distance of the 5 × 5 window's pixels to their mean
/// (the window clipped at the border).
fn window_spread(img: &RgbF32) -> Plane<f32> {
    let (w, h) = (img.width(), img.height());
    let all = Plane::new(w, h, true);
    let mut spread = Plane::new(w, h, 0.0f32);
    for c in 0..3 {
        let v = Plane::from_fn(w, h, |x, y| img.get(x, y)[c]);
        let sq = v.map(|&a| a * a);
        let (mean, mean_sq) = (box_mean(&v, &all, HALF as usize), box_mean(&sq, &all, HALF as usize));
        for (s, (m, m2)) in
            spread.as_mut_slice().iter_mut().zip(mean.as_slice().iter().zip(mean_sq.as_slice()))
        {
            *s += (m2 - m * m).max(0.0);
        }
    }
    spread
}

/// The seed of [`explain_by_displacement`]'s random search.
const DISPLACEMENT_SEED: u64 = 0xd15b_1ace;

/// A nearest-patch search of the keyframe's flagged pixels in one view (Barnes et al.,
/// PatchMatch, 2009): displacements up to `reach` on either axis, those within `near` of
/// none left out (the small moves are [`explain_by_parallax`]'s).
struct Displacements {
    reach: isize,
    near: isize,
    t2: f32,
}

impl Displacements {
    /// Rounds of propagation and random search, alternately forwards and backwards.
    const ROUNDS: usize = 5;

    /// Per pixel of `key`: whether it is flagged and the view `other` shows its 5 × 5 patch
    /// at some allowed displacement with a mean squared RGB distance of at most `t2` (over
    /// the window's usable pixels, more than half of it).
    fn matches(
        &self,
        key: &RgbF32,
        other: &RgbF32,
        usable: &Plane<bool>,
        flagged: &[bool],
        seed: u64,
    ) -> Vec<bool> {
        use rand::{Rng, SeedableRng};
        let (w, h) = (key.width(), key.height());
        let (ks, os, us) = (key.as_slice(), other.as_slice(), usable.as_slice());
        let size = (w as isize, h as isize);
        let allowed = |(dx, dy): (isize, isize)| {
            dx.abs().max(dy.abs()) > self.near && dx.abs() <= self.reach && dy.abs() <= self.reach
        };
        let cost = |i: usize, d: (isize, isize), bound: f32| {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let (tx, ty) = (x + d.0, y + d.1);
            if !allowed(d) || tx < 0 || ty < 0 || tx >= size.0 || ty >= size.1 {
                return f32::INFINITY;
            }
            window_cost(ks, os, us, size, (x, y), d, bound)
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        // rand draws no `isize` (its width is the platform's): drawn as i64.
        let mut pick = |r: isize| rng.random_range(-(r as i64)..=r as i64) as isize;
        let mut best: Vec<((isize, isize), f32)> = vec![((0, 0), f32::INFINITY); w * h];
        for i in (0..w * h).filter(|&i| flagged[i]) {
            let d = (pick(self.reach), pick(self.reach));
            best[i] = (d, cost(i, d, f32::INFINITY));
        }
        for round in 0..Self::ROUNDS {
            let forward = round % 2 == 0;
            let step: isize = if forward { -1 } else { 1 };
            for k in 0..w * h {
                let i = if forward { k } else { w * h - 1 - k };
                if !flagged[i] {
                    continue;
                }
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                // The displacements of the neighbours already visited this round.
                for (nx, ny) in [(x + step, y), (x, y + step)] {
                    if nx < 0 || ny < 0 || nx >= size.0 || ny >= size.1 {
                        continue;
                    }
                    let j = (ny * size.0 + nx) as usize;
                    if flagged[j] && best[j].0 != best[i].0 {
                        let c = cost(i, best[j].0, best[i].1);
                        if c < best[i].1 {
                            best[i] = (best[j].0, c);
                        }
                    }
                }
                // Random search around the best, the radius halved each time.
                let mut r = self.reach;
                while r >= 1 {
                    let (bx, by) = best[i].0;
                    let d = (
                        (bx + pick(r)).clamp(-self.reach, self.reach),
                        (by + pick(r)).clamp(-self.reach, self.reach),
                    );
                    let c = cost(i, d, best[i].1);
                    if c < best[i].1 {
                        best[i] = (d, c);
                    }
                    r /= 2;
                }
            }
        }
        best.iter().zip(flagged).map(|(&(_, c), &f)| f && c <= self.t2).collect()
    }
}

/// The mean squared RGB distance of `key`'s 5 × 5 window at `(x, y)` to `other`'s moved by
/// `(dx, dy)` ([`window_sum`]): infinite where half the window or less is usable, or as soon
/// as the sum shows it cannot come under `bound`.
fn window_cost(
    key: &[[f32; 3]],
    other: &[[f32; 3]],
    usable: &[bool],
    size: (isize, isize),
    at: (isize, isize),
    by: (isize, isize),
    bound: f32,
) -> f32 {
    match window_sum(key, other, usable, size, at, by, bound) {
        Some((sum, n)) if n * 2 > WINDOW => sum / n as f32,
        _ => f32::INFINITY,
    }
}

/// Per source, the keyframe's epipole of its view (work resolution, homogeneous; `None`
/// where the view gives none): in the view warped through its wall, a point off the wall at
/// keyframe `x` shows at `x + γ·ê` (homogeneous), on the line through `x` and `ê`. With the
/// view's wall `M` and its epipole `e` ([`crate::geometry::planes::ParallaxFamily`]), `ê = M⁻¹·e`.
fn keyframe_epipoles<P: RgbPixel>(
    key: &RgbF32,
    sources: &[Source<'_, P>],
    from_full: &Homography,
) -> Vec<Option<Vector3<f64>>> {
    let none = vec![None; sources.len()];
    let gray = luminance(key);
    // Each view's luminance as it is matched: eight 12 MP views as floats are 384 MB.
    let view = |v: usize| luminance(sources[v].image);
    let walls: Vec<Homography> = sources.iter().map(|s| s.homography).collect();
    let nothing = Mask::new(key.width(), key.height(), 0);
    let Some((family, guided)) =
        parallax_family_with(&gray, &view, &walls, &nothing, &SweepParams::default(), EPIPOLE_SEED)
    else {
        return none;
    };
    let Some(t_inv) = guided.t.inverse() else { return none };
    let to_work = *from_full.after(&t_inv).matrix();
    family.epipoles.iter().zip(&family.walls).map(|(e, m)| Some(to_work * m.try_inverse()? * (*e)?)).collect()
}

/// The seed of the epipoles' fit in [`keyframe_epipoles`].
const EPIPOLE_SEED: u64 = 0x5eed_e919;

/// Stage (2c): strong and weak pixels that enough views show moved along their epipolar
/// lines are the scene at another depth (a plinth, the pavement, a pier standing off the
/// wall, seen through the wall's homography), not an occluder: they are no evidence of one.
///
/// A view explains a pixel when the keyframe's 5×5 patch matches the view's (the views as
/// warped and compensated) at exactly one run of offsets along the line through the pixel
/// and the view's keyframe epipole, within [`AutoMaskParams::epipolar_reach`] on either
/// side: a patch that passes at two places is a repeat (a window among windows, a dark coat
/// against dark glass), not a position. The pixel is explained when at least
/// [`AutoMaskParams::min_views`] views and half of those that see it explain it, and its
/// colour is no likelier among the flagged pixels than among the rest of the keyframe: the
/// scene off the wall looks like the scene, while a tree every view shows, displaced along
/// the same lines, keeps its own colours.
fn explain_by_epipoles(
    key: &RgbF32,
    warped: &[(RgbF32, Plane<bool>)],
    epipoles: &[Option<Vector3<f64>>],
    ev: &mut Evidence,
    params: &AutoMaskParams,
) {
    let (w, h) = (key.width(), key.height());
    let reach = (f64::from(params.epipolar_reach) * (w as f64).hypot(h as f64)).round() as isize;
    if reach < 1 || epipoles.iter().all(Option::is_none) {
        return;
    }
    let t2 = params.threshold * params.threshold;
    let ks = key.as_slice();
    let size = (w as isize, h as isize);
    let matches = |img: &RgbF32, valid: &Plane<bool>, x: isize, y: isize, qx: isize, qy: isize| {
        window_matches(ks, img.as_slice(), valid.as_slice(), size, (x, y), (qx - x, qy - y), t2)
    };
    // Whether the view `img` shows the keyframe's patch at `(x, y)` at one run of offsets
    // along the unit direction `(ux, uy)`, from the far end on one side to the far end on
    // the other (the pixel itself left out: there the views disagree with the keyframe).
    let unique = |img: &RgbF32, valid: &Plane<bool>, x: isize, y: isize, ux: f64, uy: f64| {
        let (mut runs, mut previous) = (0usize, false);
        let mut last = (x, y);
        for s in -reach..=reach {
            let q =
                ((x as f64 + s as f64 * ux).round() as isize, (y as f64 + s as f64 * uy).round() as isize);
            if q == last {
                continue;
            }
            last = q;
            let ok = q != (x, y) && matches(img, valid, x, y, q.0, q.1);
            runs += usize::from(ok && !previous);
            previous = ok;
            if runs > 1 {
                return false;
            }
        }
        runs == 1
    };
    let seen: &Evidence = ev;
    let any = seen.flagged();
    let flagged = dilate(&any, 2);
    let scene = ColourHistogram::of(key, &flagged);
    let objects = ColourHistogram::within(key, &Rect::full(w, h), |x, y| flagged.get(x, y));
    let explained: Vec<usize> = (0..w * h)
        .into_par_iter()
        .filter(|&i| any.as_slice()[i])
        .filter(|&i| scene.density(ks[i]) >= objects.density(ks[i]))
        .filter(|&i| {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            let (mut seeing, mut found) = (0usize, 0usize);
            for ((img, valid), e) in warped.iter().zip(epipoles) {
                if !valid.as_slice()[i] {
                    continue;
                }
                seeing += 1;
                let Some(e) = e else { continue };
                let (dx, dy) = (e.x - e.z * x as f64, e.y - e.z * y as f64);
                let norm = dx.hypot(dy);
                if norm > 1e-9 && unique(img, valid, x, y, dx / norm, dy / norm) {
                    found += 1;
                }
            }
            found >= params.min_views && 2 * found >= seeing
        })
        .collect();
    for i in explained {
        ev.strong.as_mut_slice()[i] = false;
        ev.weak.as_mut_slice()[i] = false;
    }
}

/// Stage (3): the strong pixels where the views, not the keyframe, show something in front.
///
/// The keyframe's unflagged pixels are the building as the keyframe sees it; a colour
/// histogram of them says how building-like a colour is. A transient occluder in the
/// keyframe is unlike the building and its consensus is like it; an occluder that every view
/// shows (a tree off the wall, displaced by parallax) puts its colours in the consensus where
/// the keyframe shows plain wall. Compared over a small window, since single pixels of a
/// facade take all sorts of colours.
fn shared_occluders(key: &RgbF32, ev: &Evidence, params: &AutoMaskParams) -> Plane<bool> {
    let (w, h) = (key.width(), key.height());
    let flagged = dilate(&ev.flagged(), 2);
    let hist = ColourHistogram::of(key, &flagged);
    let ratio = Plane::from_fn(w, h, |x, y| {
        if ev.strong.get(x, y) {
            hist.log_density(key.get(x, y)) - hist.log_density(ev.consensus.get(x, y))
        } else {
            0.0
        }
    });
    let smooth = box_mean(&ratio, &ev.strong, 3);
    let cut = params.background_ratio.max(1.0).ln();
    Plane::from_fn(w, h, |x, y| ev.strong.get(x, y) && smooth.get(x, y) > cut)
}

/// The sky of `key` (work resolution, blurred; `sharp` the same before the blur): the
/// pixels smooth and bright enough ([`AutoMaskParams::sky_gradient`],
/// [`AutoMaskParams::sky_edge`], [`AutoMaskParams::sky_luma`]) 4-connected through such
/// pixels to the top rows (the top 2 %), the clouds 4-connected to those
/// ([`AutoMaskParams::sky_cloud_gradient`]), and the bright pixels within 2 px of them.
fn sky(key: &RgbF32, sharp: &RgbF32, params: &AutoMaskParams) -> Plane<bool> {
    let (w, h) = (key.width(), key.height());
    if params.sky_gradient <= 0.0 || w < 3 || h < 3 {
        return Plane::new(w, h, false);
    }
    let l = luminance(key);
    let gradient = Plane::from_fn(w, h, |x, y| sobel(w, h, x, y, |x, y| l.get(x, y)));
    let smooth = box_mean(&gradient, &Plane::new(w, h, true), 2);
    let colour = colour_gradient(key);
    let like = Plane::from_fn(w, h, |x, y| {
        smooth.get(x, y) < params.sky_gradient
            && colour.get(x, y) < params.sky_edge
            && l.get(x, y) >= params.sky_luma
    });
    let mut out = Plane::new(w, h, false);
    // From the top rows (a frame's first row or two are often an edge of their own).
    let band = (h / 50).max(1);
    let top: Vec<(usize, usize)> =
        (0..band).flat_map(|y| (0..w).map(move |x| (x, y))).filter(|&(x, y)| like.get(x, y)).collect();
    for &(x, y) in &top {
        out.set(x, y, true);
    }
    grow_through(&mut out, top, &NEIGHBOURS_4, |x, y| like.get(x, y));
    if params.sky_cloud_gradient > 0.0 {
        // Before the blur, where an object's outline is still a step.
        let colour = colour_gradient(sharp);
        let smooth = box_mean(&colour, &Plane::new(w, h, true), 2);
        let cloud = |x: usize, y: usize| {
            smooth.get(x, y) < params.sky_cloud_gradient
                && colour.get(x, y) < params.sky_cloud_edge
                && l.get(x, y) >= params.sky_luma
        };
        let edge: Vec<(usize, usize)> =
            (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).filter(|&(x, y)| out.get(x, y)).collect();
        grow_through(&mut out, edge, &NEIGHBOURS_4, cloud);
    }
    // The gradient's average reaches 2 px past the skyline: the sky's rim along it is sky
    // too, where it is bright.
    let rim = dilate(&out, 2);
    Plane::from_fn(w, h, |x, y| rim.get(x, y) && l.get(x, y) >= params.sky_luma)
}

/// The steepest of the three channels' Sobel gradients at each pixel.
fn colour_gradient(img: &RgbF32) -> Plane<f32> {
    let (w, h) = (img.width(), img.height());
    Plane::from_fn(w, h, |x, y| {
        (0..3).map(|c| sobel(w, h, x, y, |x, y| img.get(x, y)[c])).fold(0.0, f32::max)
    })
}

/// The Sobel gradient's magnitude of `v` at `(x, y)`, per unit of distance; the border takes
/// its inner neighbour's. The image is at least 3 × 3.
fn sobel(w: usize, h: usize, x: usize, y: usize, v: impl Fn(usize, usize) -> f32) -> f32 {
    let (x, y) = (x.clamp(1, w - 2), y.clamp(1, h - 2));
    let p = |dx: isize, dy: isize| v((x as isize + dx) as usize, (y as isize + dy) as usize);
    let gx = (p(1, -1) + 2.0 * p(1, 0) + p(1, 1) - p(-1, -1) - 2.0 * p(-1, 0) - p(-1, 1)) / 8.0;
    let gy = (p(-1, 1) + 2.0 * p(0, 1) + p(1, 1) - p(-1, -1) - 2.0 * p(0, -1) - p(1, -1)) / 8.0;
    (gx * gx + gy * gy).sqrt()
}

/// A colour histogram (`levels`³ bins) with add-one smoothing.
#[derive(Clone)]
pub(super) struct ColourHistogram {
    levels: usize,
    bins: Vec<f32>,
    total: f32,
}

impl ColourHistogram {
    /// The grain `--mask auto` tells colours apart at.
    const LEVELS: usize = 16;

    fn bin(&self, p: [f32; 3]) -> usize {
        let n = self.levels;
        let q = |v: f32| ((v.clamp(0.0, 1.0) * n as f32) as usize).min(n - 1);
        (q(p[0]) * n + q(p[1])) * n + q(p[2])
    }

    /// The histogram of `colours`, `levels` per channel.
    pub(super) fn of_colours(levels: usize, colours: impl Iterator<Item = [f32; 3]>) -> Self {
        let bins = vec![1.0f32; levels.pow(3)];
        let total = bins.len() as f32;
        let mut hist = Self { levels, bins, total };
        for c in colours {
            let b = hist.bin(c);
            hist.bins[b] += 1.0;
            hist.total += 1.0;
        }
        hist
    }

    fn of(img: &RgbF32, excluded: &Plane<bool>) -> Self {
        Self::within(img, &Rect::full(img.width(), img.height()), |x, y| !excluded.get(x, y))
    }

    /// The histogram of the pixels of `img` inside `r` where `take` holds.
    fn within(img: &RgbF32, r: &Rect, take: impl Fn(usize, usize) -> bool) -> Self {
        let pixels = (r.y..r.y1()).flat_map(|y| (r.x..r.x1()).map(move |x| (x, y)));
        Self::of_colours(Self::LEVELS, pixels.filter(|&(x, y)| take(x, y)).map(|(x, y)| img.get(x, y)))
    }

    /// Takes out of the histogram the pixels of `img` inside `r` where `take` holds (those
    /// it was built with).
    fn remove(&mut self, img: &RgbF32, r: &Rect, take: impl Fn(usize, usize) -> bool) {
        for y in r.y..r.y1() {
            for x in r.x..r.x1() {
                if take(x, y) {
                    let b = self.bin(img.get(x, y));
                    self.bins[b] -= 1.0;
                    self.total -= 1.0;
                }
            }
        }
    }

    fn density(&self, p: [f32; 3]) -> f32 {
        self.bins[self.bin(p)] / self.total
    }

    fn log_density(&self, p: [f32; 3]) -> f32 {
        self.density(p).ln()
    }

    /// Whether colour `p` is one of these colours (at least `share` of them fall in its bin)
    /// and more likely under them than under `other`'s. A colour neither has seen is not
    /// typical of either.
    pub(super) fn typical(&self, p: [f32; 3], other: &ColourHistogram, share: f32) -> bool {
        let bin = self.bins[self.bin(p)] - 1.0;
        let seen = self.total - self.bins.len() as f32;
        bin >= share * seen && self.density(p) > other.density(p)
    }
}

/// Mean of `v` over the `(2r + 1)²` window's pixels where `on` is set (0 where none are).
fn box_mean(v: &Plane<f32>, on: &Plane<bool>, r: usize) -> Plane<f32> {
    let (w, h) = (v.width(), v.height());
    // Summed-area tables of the values and of the count.
    let mut s = vec![0.0f64; (w + 1) * (h + 1)];
    let mut c = vec![0u32; (w + 1) * (h + 1)];
    for y in 0..h {
        for x in 0..w {
            let i = (y + 1) * (w + 1) + x + 1;
            let (val, n) = if on.get(x, y) { (v.get(x, y) as f64, 1) } else { (0.0, 0) };
            s[i] = val + s[i - 1] + s[i - w - 1] - s[i - w - 2];
            c[i] = n + c[i - 1] + c[i - w - 1] - c[i - w - 2];
        }
    }
    Plane::from_fn(w, h, |x, y| {
        let (x0, y0) = (x.saturating_sub(r), y.saturating_sub(r));
        let (x1, y1) = ((x + r + 1).min(w), (y + r + 1).min(h));
        let at = |xx: usize, yy: usize| yy * (w + 1) + xx;
        let n = c[at(x1, y1)] + c[at(x0, y0)] - c[at(x0, y1)] - c[at(x1, y0)];
        if n == 0 {
            return 0.0;
        }
        ((s[at(x1, y1)] + s[at(x0, y0)] - s[at(x0, y1)] - s[at(x1, y0)]) / n as f64) as f32
    })
}

/// The pixels of `reach` 8-connected to a pixel of `seeds` (seeds outside `reach` count).
fn grow_from(seeds: &Plane<bool>, reach: &Plane<bool>) -> Plane<bool> {
    let (w, h) = (seeds.width(), seeds.height());
    let mut out = seeds.clone();
    let stack = (0..w * h).filter(|&i| seeds.as_slice()[i]).map(|i| (i % w, i / w)).collect();
    grow_into(&mut out, stack, |x, y| reach.get(x, y));
    out
}

/// Sets in `out` every pixel 8-connected to `stack` through pixels `reach` accepts.
fn grow_into(out: &mut Plane<bool>, stack: Vec<(usize, usize)>, reach: impl Fn(usize, usize) -> bool) {
    grow_through(out, stack, &NEIGHBOURS_8, reach);
}

/// Sets in `out` every pixel connected (through `neighbours`) to `stack` through pixels
/// `reach` accepts.
fn grow_through(
    out: &mut Plane<bool>,
    stack: Vec<(usize, usize)>,
    neighbours: &[(isize, isize)],
    reach: impl Fn(usize, usize) -> bool,
) {
    let size = (out.width(), out.height());
    flood(
        size,
        stack,
        neighbours,
        |_, _| {},
        |x, y| {
            let enter = !out.get(x, y) && reach(x, y);
            if enter {
                out.set(x, y, true);
            }
            enter
        },
    );
}

/// Depth-first flood from `stack` over a `w × h` grid: each pixel popped is given to
/// `visit`; each of its `neighbours` inside the grid to `enter`, which says whether to go
/// there (and marks it, so that it is not entered twice).
fn flood(
    (w, h): (usize, usize),
    mut stack: Vec<(usize, usize)>,
    neighbours: &[(isize, isize)],
    mut visit: impl FnMut(usize, usize),
    mut enter: impl FnMut(usize, usize) -> bool,
) {
    while let Some((x, y)) = stack.pop() {
        visit(x, y);
        for &(dx, dy) in neighbours {
            let (nx, ny) = (x as isize + dx, y as isize + dy);
            if nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h && enter(nx as usize, ny as usize)
            {
                stack.push((nx as usize, ny as usize));
            }
        }
    }
}

const NEIGHBOURS_8: [(isize, isize); 8] =
    [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)];
const NEIGHBOURS_4: [(isize, isize); 4] = [(0, -1), (-1, 0), (1, 0), (0, 1)];

/// Stage (5): fills the 4-connected holes of `m` that do not reach the border and have at
/// most `max_hole` pixels, and counts the 8-connected objects.
fn fill_holes(m: &Plane<bool>, max_hole: usize) -> (Plane<bool>, usize) {
    let (w, h) = (m.width(), m.height());
    let mut out = m.clone();
    let mut seen = Plane::new(w, h, false);
    let mut region = Vec::new();
    for start in 0..w * h {
        let (sx, sy) = (start % w, start / w);
        if m.get(sx, sy) || seen.get(sx, sy) {
            continue;
        }
        seen.set(sx, sy, true);
        region.clear();
        let mut touches_border = false;
        let visit = |x: usize, y: usize| {
            region.push((x, y));
            touches_border |= x == 0 || y == 0 || x + 1 == w || y + 1 == h;
        };
        flood((w, h), vec![(sx, sy)], &NEIGHBOURS_4, visit, |x, y| {
            let enter = !m.get(x, y) && !seen.get(x, y);
            if enter {
                seen.set(x, y, true);
            }
            enter
        });
        if !touches_border && region.len() <= max_hole {
            region.iter().for_each(|&(x, y)| out.set(x, y, true));
        }
    }
    let objects = components(&out).len();
    (out, objects)
}

/// How a whole warped view's light differs from the keyframe's, fitted on a grid of samples:
/// the tone curve where it explains the pairs clearly better than the line ([`fit_tone`]),
/// the line otherwise.
fn fit_whole(key: &RgbF32, view: &RgbF32, valid: &Plane<bool>) -> Photometry {
    let n = valid.as_slice().iter().filter(|&&v| v).count();
    let step = (n / 40_000).max(1);
    let pairs: Vec<([f32; 3], [f32; 3])> = valid
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, v)| **v)
        .step_by(step)
        .map(|(i, _)| (view.as_slice()[i], key.as_slice()[i]))
        .collect();
    let fit = fit_tone(&pairs, &ToneParams::default());
    match fit.curve {
        Some(curve) => Photometry::Tone(curve),
        None => Photometry::Line(fit.line),
    }
}

/// How a view's colours are brought to the keyframe's light ([`fit_whole`]).
enum Photometry {
    /// A line per channel: the exposure changed, the camera's response did not bend it.
    Line(Gain),
    /// A monotone curve per channel: a view much darker or brighter than the keyframe,
    /// whose camera answered with a curve (Oxford's leuven, img2 to img5 against img1 with
    /// the true homographies: a least-squares line per channel left 4 to 28 % of the overlap
    /// further than `threshold` from the keyframe, flagged as occluders; a curve 0.5 to 2.4 %).
    Tone(ToneCurve),
}

impl Photometry {
    fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        match self {
            Photometry::Line(g) => g.apply(p),
            Photometry::Tone(c) => c.apply(p),
        }
    }
}

/// Parameters of [`own_occluders`].
#[derive(Debug, Clone, PartialEq)]
pub struct OwnParams {
    /// Views needed (the keyframe not counted) before any view is judged. Where two see the
    /// region judged, each is judged against the keyframe and the other one: where two
    /// references disagree with a view in the building's own colours, it may be the
    /// building seen at another depth, so such a view keeps only the objects
    /// [`OwnParams::foreign_share`] lets through.
    pub min_views: usize,
    /// The judgement runs on images brought down to at most this many pixels.
    pub work_pixels: usize,
    /// The automatic mask's parallax radius there: a disagreement that is the same
    /// building moved by up to this many (reduced) pixels is parallax, not an occluder. On
    /// the real photo cases the default 3 took the depth of a curved glass wall or a
    /// cornice for occluders (BENCHMARKS.md, "Each view's own occluders").
    pub parallax_radius: usize,
    /// The mark given ([`super::FillExtras::occluders`]): soft, a doubt rather than a
    /// verdict, so that a pixel every view is marked on is still copied.
    pub mark: u8,
    /// A view is judged against the keyframe and at most this many other views
    /// ([`Viewpoints::farthest`]). Against every other view, 16 frames of a walk took 14 s.
    pub references: usize,
    /// A caller that keeps each view's marks from one call to the next
    /// ([`own_occluders_memo`]) keeps them while they were judged against as many views as
    /// a fresh choice of references would take, spread at least `1 / keep_spread` as far
    /// apart ([`Viewpoints::spread`]); 0 keeps them only for the same choice. Choosing
    /// afresh at each call, a session's buffer of 9 judged 5 to 9 of its views again at each
    /// landing (the new view changes the choice of half the others, and the view it evicts
    /// is among the references of up to all of them; BENCHMARKS.md, "Capture service").
    pub keep_spread: f64,
    /// Views are judged over the mask's bounds grown by this many keyframe pixels (and
    /// what the views show of them), whatever the caller cropped the images to: the
    /// command and the service crop differently and must find the same occluders (judged
    /// over the whole crops, 8 of the service's 96 cases ended more than 0.5 dB from the
    /// command's fill; BENCHMARKS.md, "Each view's own occluders, judged near the mask").
    pub margin: usize,
    /// Whether another view's pixels in the colours of the keyframe's occluder (rather than
    /// of its building) still count as witnesses. Where every view shows the keyframe's
    /// tree a little displaced, two of them agreeing on it outvote a view that sees the
    /// wall there.
    pub foreign_witnesses: bool,
    /// A view's marks are finally grown by this many work pixels
    /// ([`AutoMaskParams::dilate_radius`] there). A view's occluder blends into the wall
    /// along its outline, and a rim left unmarked is copied. The keyframe's automatic mask
    /// ends a pixel past the outline, where a person paints; the views' marks were measured
    /// grown by 3, and grown by 1 (as the keyframe's mask, which they followed for a while)
    /// the honesty cases lost 0.29 dB and their confident pixels were more often wrong
    /// (BENCHMARKS.md, "A view's marks grown as they were measured").
    pub growth: usize,
    /// Where only two views see the region judged, a view keeps a marked object
    /// (8-connected, after the growth) when at least this share of its pixels has a colour
    /// the building around the mask does not have (`LIFTED_FOREIGN` on the keyframe's
    /// unmasked colours near the mask): a sign, a coat, a car's paint. A curved glass
    /// wall's mullions, displaced between the views, were marked and the fill lost them
    /// (photo-building, −0.34 dB over nine two-view cases with every object kept;
    /// BENCHMARKS.md, "Each view's own occluders from two views up").
    pub foreign_share: f32,
}

impl OwnParams {
    /// These parameters for the same inputs halved `levels` times (a judge on reduced
    /// inputs, [`super::judged_with_marks`]), `mask` being the full-resolution mask: the
    /// margin (keyframe pixels) halved with them, and the radii (working pixels) scaled so
    /// that they reach as far on the building as at full resolution. There a 12 MP
    /// keyframe's region is judged at a third of its size and the parallax radius spans
    /// about 24 pixels of it; at the judge's eighth, unscaled, it spanned 64.
    pub fn halved(&self, levels: u32, mask: &Mask) -> Self {
        let s = 1usize << levels;
        let Some(whole) = judged_region(mask, self) else { return self.clone() };
        let full = work_factor(whole.width, whole.height, self.work_pixels);
        let reduced = work_factor(whole.width / s, whole.height / s, self.work_pixels);
        let scale = |r: usize| ((r * full) as f64 / (reduced * s) as f64).round().max(1.0) as usize;
        Self {
            margin: self.margin.div_ceil(s),
            parallax_radius: scale(self.parallax_radius),
            growth: scale(self.growth),
            ..self.clone()
        }
    }
}

impl Default for OwnParams {
    fn default() -> Self {
        Self {
            min_views: 2,
            work_pixels: 500_000,
            parallax_radius: 8,
            mark: 160,
            references: 4,
            keep_spread: 1.5,
            margin: 48,
            foreign_witnesses: false,
            growth: 3,
            foreign_share: 0.33,
        }
    }
}

/// Per source, the pixels where it shows something in front of the building, marked
/// [`OwnParams::mark`] (source-sized, as [`super::FillExtras::occluders`]): the automatic
/// mask of that view, judged near the keyframe's mask ([`OwnParams::margin`]) against the
/// keyframe (its masked pixels kept out: there it shows its own occluder) and a few other
/// views ([`OwnParams::references`]). A view's car or passer-by next to the keyframe's
/// tree is otherwise copied into the hole whenever it happens to look like the building
/// around it (planar-8: 27.79 → 33.25 dB; BENCHMARKS.md, "Each view's own occluders,
/// judged near the mask"). Empty below [`OwnParams::min_views`] views or with an empty
/// mask; `None` for a view that does not see the mask's surroundings or whose map cannot
/// be inverted.
pub fn own_occluders<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    params: &OwnParams,
    auto: &AutoMaskParams,
) -> Vec<Option<Mask>> {
    let ids: Vec<u64> = (0..sources.len() as u64).collect();
    let mut memo = vec![OwnMarks::default(); sources.len()];
    let judged = !own_occluders_memo(key, mask, sources, &ids, params, auto, &mut memo).is_empty();
    if !judged {
        return Vec::new();
    }
    memo.into_iter().map(|m| m.judged.and_then(|j| j.marks)).collect()
}

/// Of each view's own occluders found through its wall (`marks`, as [`own_occluders`] or
/// [`own_occluders_memo`] found them for these inputs), those that no surface off the wall
/// explains. A slab standing off the wall, seen through the wall's homography, disagrees
/// with the keyframe and the other views as an occluder does, and was marked like one (on
/// the depth facades, 42 % of the marks lay on slabs, 45 % on the views' occluders). Each
/// surface in `planes` (its maps per source, in the order of `sources`) judges its own
/// region again, every map taken through it: a view's pixel marked through the wall stays
/// marked unless a surface whose region it shows finds nothing of the view's own there.
/// An occluder disagrees under every plane; a slab agrees under its own.
pub fn own_occluders_off_surfaces<P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    marks: &[Option<&Mask>],
    planes: &[SurfacePlane],
    params: &OwnParams,
    auto: &AutoMaskParams,
) -> Vec<Option<Mask>> {
    let mut out: Vec<Option<Mask>> = marks.iter().map(|m| m.cloned()).collect();
    let Some(whole) = judged_region(mask, params) else { return out };
    for plane in planes {
        let r = whole.intersection(&plane.region);
        let on: Vec<(usize, Homography)> = (0..sources.len().min(marks.len()))
            .filter_map(|v| Some((v, plane.views.get(v).copied().flatten()?)))
            .collect();
        if r.area() == 0 || !on.iter().any(|&(v, _)| out[v].is_some()) {
            continue;
        }
        let through: Vec<Source<'_, P>> =
            on.iter().map(|&(v, homography)| Source { image: sources[v].image, homography }).collect();
        let ids: Vec<u64> = (0..through.len() as u64).collect();
        let mut memo = vec![OwnMarks::default(); through.len()];
        let found = judge_own(key, mask, &through, &ids, params, auto, &mut memo, Some(r));
        for (&(v, h), under) in on.iter().zip(found) {
            let (Some(m), Some(under), Some(back)) = (out[v].as_mut(), under, h.inverse()) else { continue };
            let (w, ht) = (m.width(), m.height());
            for y in 0..ht {
                for x in 0..w {
                    if m.get(x, y) == 0 || under.get(x, y) > 0 {
                        continue;
                    }
                    let shown = back.apply(nalgebra::Point2::new(x as f64, y as f64)).is_some_and(|q| {
                        q.x >= r.x as f64 && q.y >= r.y as f64 && q.x < r.x1() as f64 && q.y < r.y1() as f64
                    });
                    if shown {
                        m.set(x, y, 0);
                    }
                }
            }
        }
    }
    out
}

/// One view's marks from an earlier [`own_occluders_memo`], with the references they were
/// judged against. A view's marks depend on the keyframe, the mask, the parameters, the
/// view itself and its references only.
#[derive(Debug, Clone, Default)]
pub struct OwnMarks {
    judged: Option<Judged>,
}

#[derive(Debug, Clone)]
struct Judged {
    /// The view's identity and its references' (in the order taken).
    ids: Vec<u64>,
    /// How far apart the references were ([`Viewpoints::spread`]).
    spread: f64,
    /// Whether only its objects in foreign colours were kept ([`OwnParams::foreign_share`]).
    foreign_only: bool,
    marks: Option<Mask>,
}

/// [`own_occluders`] for a caller that keeps each view's marks from one call to the next
/// (a session's fills, one more view each time): a view is judged again only when a fresh
/// choice of references would take more views than its marks were judged against, or views
/// spread much farther apart ([`OwnParams::keep_spread`]). Its marks stand when views it
/// was judged against have left since: what they showed was evidence then, and is still.
/// With `keep_spread` 0, a view is judged again whenever the fresh choice changed. `ids` names each
/// source (a source's pixels and map never change under its identity); `memo`, one entry
/// per source, holds what the last call found for it (`OwnMarks::default()` for a source
/// not judged before), and is only valid for the same keyframe, mask and parameters. The
/// marks are returned borrowed from `memo`: empty where [`own_occluders`] is empty.
///
/// # Panics
/// If `ids` or `memo` do not give one entry per source.
pub fn own_occluders_memo<'m, P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    ids: &[u64],
    params: &OwnParams,
    auto: &AutoMaskParams,
    memo: &'m mut [OwnMarks],
) -> Vec<Option<&'m Mask>> {
    judge_own(key, mask, sources, ids, params, auto, memo, None)
}

/// The region [`own_occluders_memo`] judges: the mask's bounds grown by
/// [`OwnParams::margin`] (`None` for an empty mask).
fn judged_region(mask: &Mask, params: &OwnParams) -> Option<Rect> {
    Some(mask.hole_bounds()?.grown(params.margin, mask.width(), mask.height()))
}

/// [`own_occluders_memo`], judged only `within` that part of the keyframe when given, each
/// image brought down as for the whole region judged (so that a part is judged at the scale
/// the whole is).
#[allow(clippy::too_many_arguments)]
fn judge_own<'m, P: RgbPixel>(
    key: &RgbF32,
    mask: &Mask,
    sources: &[Source<'_, P>],
    ids: &[u64],
    params: &OwnParams,
    auto: &AutoMaskParams,
    memo: &'m mut [OwnMarks],
    within: Option<Rect>,
) -> Vec<Option<&'m Mask>> {
    assert!(ids.len() == sources.len() && memo.len() == sources.len(), "ids and memo per source");
    if sources.len() < params.min_views.max(1) {
        return Vec::new();
    }
    // Judged near the mask only, whatever the caller cropped the images to.
    let Some(whole) = judged_region(mask, params) else { return Vec::new() };
    let r = within.map_or(whole, |w| whole.intersection(&w));
    if r.area() == 0 {
        return Vec::new();
    }
    // Per source: the part of it that shows `r`, and the map into that part.
    let cut_of = |r: Rect| -> Vec<Option<(Rect, Homography)>> {
        let into_r = Homography::translation(r.x as f64, r.y as f64);
        sources
            .iter()
            .map(|s| {
                let h = s.homography.after(&into_r);
                let f = super::region::footprint(
                    &Rect::full(r.width, r.height),
                    &h,
                    s.image.width(),
                    s.image.height(),
                    0,
                )?;
                Some((f, super::region::into_crop(&h, &f)))
            })
            .collect()
    };
    let cut = cut_of(r);
    let kept: Vec<usize> = (0..sources.len()).filter(|&v| cut[v].is_some()).collect();
    if kept.len() < params.min_views.max(1) {
        return Vec::new();
    }
    // Each kept view brought down to the working size (its size and map there; the pixels
    // only where they are needed), by the factor the whole region judged takes.
    let factor = |w: usize, h: usize| work_factor(w, h, params.work_pixels);
    let fk = factor(whole.width, whole.height);
    let cut_whole = if r == whole { cut.clone() } else { cut_of(whole) };
    let reduced: Vec<Reduced> = kept
        .iter()
        .map(|&v| {
            let (f, h) = cut[v].expect("kept");
            let fv = cut_whole[v].map_or(1, |(f, _)| factor(f.width, f.height));
            let back = reduced_to_full(fv).inverse().expect("scaling is regular");
            Reduced {
                factor: fv,
                size: (f.width.div_ceil(fv), f.height.div_ceil(fv)),
                map: back.after(&h).after(&reduced_to_full(fk)),
            }
        })
        .collect();
    // Only two views see the region: each keeps only its objects in foreign colours
    // ([`OwnParams::foreign_share`]).
    let foreign_only = kept.len() < 3;
    // Per kept view: its map back to the keyframe, the references a fresh choice takes,
    // and how far apart they are.
    let plans: Vec<Option<(Homography, Vec<usize>, f64)>> = reduced
        .iter()
        .enumerate()
        .map(|(k, red)| {
            let back = red.map.inverse()?;
            let views = Viewpoints::of(red.size, &back, &reduced, k);
            let refs = views.farthest(params.references);
            let spread = views.spread(&refs).expect("chosen among those that see it");
            Some((back, refs, spread))
        })
        .collect();
    // What a view's marks are judged from: the view itself, then its references.
    let wanted = |k: usize| -> Vec<u64> {
        let refs = plans[k].as_ref().map_or(&[][..], |(_, refs, _)| &refs[..]);
        std::iter::once(ids[kept[k]]).chain(refs.iter().map(|&j| ids[kept[j]])).collect()
    };
    // A view keeps its marks when they were judged against the fresh choice, or against as
    // many views spread at least `1 / keep_spread` as far apart ([`OwnParams::keep_spread`]),
    // whether or not those views are still here: what they showed was evidence then and is
    // still. Otherwise it is judged again, and so is a view judged when only two views saw
    // the region (foreign objects only), or when more did.
    let stale: Vec<usize> = (0..kept.len())
        .filter(|&k| {
            let Some(before) = &memo[kept[k]].judged else { return true };
            if before.foreign_only != foreign_only {
                return true;
            }
            let Some((_, refs, spread)) = &plans[k] else { return before.ids != wanted(k) };
            let kept_up = before.ids.len() > refs.len() && before.spread * params.keep_spread >= *spread;
            !kept_up && before.ids != wanted(k)
        })
        .collect();
    tracing::debug!(judged = stale.len(), kept = kept.len(), "views' own occluders");
    if !stale.is_empty() {
        let mut needed = vec![false; kept.len()];
        for &k in &stale {
            needed[k] = true;
            if let Some((_, refs, _)) = &plans[k] {
                for &j in refs {
                    needed[j] = true;
                }
            }
        }
        let key_c = key.crop(r);
        let mask_c = mask.crop(r);
        let key_r = reduce(&key_c, fk);
        let mask_r = Mask::from_fn(key_r.width(), key_r.height(), |x, y| {
            let any = (y * fk..((y + 1) * fk).min(mask_c.height()))
                .any(|yy| (x * fk..((x + 1) * fk).min(mask_c.width())).any(|xx| mask_c.is_hole(xx, yy)));
            if any { 255 } else { 0 }
        });
        let images: Vec<Option<RgbF32>> = (0..kept.len())
            .into_par_iter()
            .map(|k| {
                needed[k].then(|| {
                    let (f, _) = cut[kept[k]].expect("kept");
                    reduce(&sources[kept[k]].image.crop(f), reduced[k].factor)
                })
            })
            .collect();
        // A view's pixels in the colours of the keyframe's occluder rather than its
        // building are no witness for the building around another view
        // ([`OwnParams::foreign_witnesses`]).
        let unlike: Vec<Option<Mask>> = if params.foreign_witnesses {
            vec![None; kept.len()]
        } else {
            let hole = Plane::from_fn(key_r.width(), key_r.height(), |x, y| mask_r.is_hole(x, y));
            let inner = erode(&hole, 2);
            let full = Rect::full(key_r.width(), key_r.height());
            let occluder = ColourHistogram::within(&key_r, &full, |x, y| inner.get(x, y));
            let building = ColourHistogram::within(&key_r, &full, |x, y| !hole.get(x, y));
            images
                .iter()
                .map(|img| {
                    let img = img.as_ref()?;
                    Some(img.map(|&p| if occluder.density(p) > 2.0 * building.density(p) { 255 } else { 0 }))
                })
                .collect()
        };
        // The building's colours, for `foreign_only`.
        let building: Option<super::occlusion::Histogram> = foreign_only.then(|| {
            let pixels = (0..key_r.height()).flat_map(|y| (0..key_r.width()).map(move |x| (x, y)));
            super::occlusion::Histogram::new(
                pixels.filter(|&(x, y)| !mask_r.is_hole(x, y)).map(|(x, y)| key_r.get(x, y)),
            )
        });
        let mut auto = auto.clone();
        auto.parallax_radius = params.parallax_radius;
        auto.min_views = auto.min_views.min(params.references + 1);
        // No sky is looked for in a view: a plain bright surface reaching its top (a poster's
        // pale strip in HPatches v_wormhole) would count as sky, and its own occluders there
        // went unmarked (−1.47 dB on that case). The keyframe's mask is where the sky
        // matters: it decides what is filled.
        auto.sky_gradient = 0.0;
        // A view's own objects grow within their boxes only: reaching beyond them changed
        // the fills of 2 of the 106 evaluation cases, both for the worse (photo-ece-2
        // −0.12 dB, shared-5 −0.19 dB), and improved none.
        auto.unjudged_reach = 0;
        // Nor are the views' epipoles looked for, nor a lone witness's displaced patches,
        // nor faces shaded otherwise:
        // the views' own marks were measured without them.
        auto.epipolar_reach = 0.0;
        auto.lone_view_reach = 0.0;
        auto.shading_ncc = 0.0;
        auto.dilate_radius = params.growth;
        let found: Vec<Option<Mask>> = stale
            .par_iter()
            .map(|&k| {
                let (back, refs, _) = plans[k].as_ref()?;
                let img = images[k].as_ref().expect("needed");
                let mut witnesses: Vec<Source<'_, [f32; 3]>> =
                    vec![Source { image: &key_r, homography: *back }];
                let mut known: Vec<Option<&Mask>> = vec![Some(&mask_r)];
                for &j in refs {
                    let image = images[j].as_ref().expect("needed");
                    witnesses.push(Source { image, homography: reduced[j].map.after(back) });
                    known.push(unlike[j].as_ref());
                }
                let mut found = auto_mask_excluding(img, &witnesses, &known, &auto).mask;
                if let Some(building) = &building {
                    keep_foreign(&mut found, img, building, params.foreign_share);
                }
                // Back to the source's pixels: the reduced marks over the part judged.
                let (f, _) = cut[kept[k]].expect("kept");
                let s = &sources[kept[k]].image;
                let (fv, rw, rh) = (reduced[k].factor, found.width(), found.height());
                Some(Mask::from_fn(s.width(), s.height(), |x, y| {
                    let inside = x >= f.x && y >= f.y && x < f.x + f.width && y < f.y + f.height;
                    if inside && found.get(((x - f.x) / fv).min(rw - 1), ((y - f.y) / fv).min(rh - 1)) > 127 {
                        params.mark
                    } else {
                        0
                    }
                }))
            })
            .collect();
        for (&k, marks) in stale.iter().zip(found) {
            let spread = plans[k].as_ref().map_or(0.0, |p| p.2);
            memo[kept[k]].judged = Some(Judged { ids: wanted(k), spread, foreign_only, marks });
        }
    }
    let mut out: Vec<Option<&Mask>> = vec![None; sources.len()];
    let memo: &'m [OwnMarks] = memo;
    for &v in &kept {
        out[v] = memo[v].judged.as_ref().and_then(|j| j.marks.as_ref());
    }
    out
}

/// Keeps, of `found`'s marks on `img`, the objects whose colours the building does not
/// have: at least `share` of an object's pixels foreign to `building`
/// ([`OwnParams::foreign_share`]).
fn keep_foreign(found: &mut Mask, img: &RgbF32, building: &super::occlusion::Histogram, share: f32) {
    let marked = Plane::from_fn(found.width(), found.height(), |x, y| found.get(x, y) > 127);
    each_component(&marked, |members| {
        let foreign = members
            .iter()
            .filter(|&&(x, y)| building.foreign(img.get(x, y)) >= super::LIFTED_FOREIGN)
            .count();
        if (foreign as f32) < share * members.len() as f32 {
            members.iter().for_each(|&(x, y)| found.set(x, y, 0));
        }
    });
}

/// A view as [`own_occluders_memo`] judges it: brought down by `factor` to `size`, and the
/// map from the reduced keyframe region into it.
struct Reduced {
    factor: usize,
    size: (usize, usize),
    map: Homography,
}

/// How view `i` sees the other views, for the choice of the views its own occluders are
/// judged against ([`Viewpoints::farthest`]).
struct Viewpoints {
    /// Per other view that sees some of view `i`: its index, how many points of view `i`
    /// it sees, and how far the map from view `i` to it is from a translation (its Jacobian
    /// at view `i`'s centre, less the identity; a translation says nothing, as the images
    /// may be crops).
    seen: Vec<(usize, usize, [f64; 4])>,
}

impl Viewpoints {
    /// `size`: view `i`'s reduced size; `back`: its pixels to the keyframe's; `views`' maps:
    /// keyframe to view. Overlap is counted on a grid of about 32 × 32 points.
    fn of(size: (usize, usize), back: &Homography, views: &[Reduced], i: usize) -> Self {
        use nalgebra::Point2;
        let (w, h) = size;
        let step = (w.max(h) / 32).max(1);
        let points: Vec<Point2<f64>> = (0..h)
            .step_by(step)
            .flat_map(|y| (0..w).step_by(step).map(move |x| Point2::new(x as f64, y as f64)))
            .filter_map(|p| back.apply(p))
            .collect();
        let centre = Point2::new((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let seen = views
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .filter_map(|(j, other)| {
                let (ow, oh) = (other.size.0 as f64, other.size.1 as f64);
                let hj = &other.map;
                let inside = |r: &Point2<f64>| r.x >= 0.0 && r.y >= 0.0 && r.x <= ow - 1.0 && r.y <= oh - 1.0;
                let n = points.iter().filter_map(|q| hj.apply(*q)).filter(inside).count();
                let to_j = hj.after(back);
                let at = |dx: f64, dy: f64| to_j.apply(Point2::new(centre.x + dx, centre.y + dy));
                let (c, x, y) = (at(0.0, 0.0)?, at(1.0, 0.0)?, at(0.0, 1.0)?);
                let jac = [x.x - c.x - 1.0, y.x - c.x, x.y - c.y, y.y - c.y - 1.0];
                (n > 0).then_some((j, n, jac))
            })
            .collect();
        Self { seen }
    }

    /// At most `k` views to judge view `i` against: among the views that see at least half
    /// as much of it as the one that sees most, those farthest apart in viewpoint, each next
    /// one the farthest from view `i` and from those already taken. Frames taken next to
    /// view `i` on a walk show its own tree nearly where it stands and agree with it there;
    /// the frames farther along show the tree moved off the wall behind.
    fn farthest(&self, k: usize) -> Vec<usize> {
        let most = self.seen.iter().map(|s| s.1).max().unwrap_or(0);
        let mut left: Vec<(usize, [f64; 4])> =
            self.seen.iter().filter(|s| s.1 * 2 >= most).map(|s| (s.0, s.2)).collect();
        let mut taken: Vec<[f64; 4]> = vec![[0.0; 4]];
        let mut chosen = Vec::new();
        while chosen.len() < k && !left.is_empty() {
            let distance = |m: &[f64; 4]| taken.iter().map(|t| squared(m, t)).fold(f64::INFINITY, f64::min);
            let best = (0..left.len())
                .max_by(|&a, &b| {
                    distance(&left[a].1).total_cmp(&distance(&left[b].1)).then(left[b].0.cmp(&left[a].0))
                })
                .expect("some left");
            let (j, m) = left.swap_remove(best);
            taken.push(m);
            chosen.push(j);
        }
        chosen
    }

    /// How far apart in viewpoint the views `refs` are, from view `i` and from each other:
    /// the sum over them of the distance to the nearest of view `i` and the others. `None`
    /// when one of them does not see view `i`.
    fn spread(&self, refs: &[usize]) -> Option<f64> {
        let jacs: Vec<[f64; 4]> =
            refs.iter().map(|&j| self.seen.iter().find(|s| s.0 == j).map(|s| s.2)).collect::<Option<_>>()?;
        let nearest = |a: usize| {
            let others = jacs.iter().enumerate().filter(|&(b, _)| b != a).map(|(_, m)| squared(&jacs[a], m));
            others.fold(squared(&jacs[a], &[0.0; 4]), f64::min).sqrt()
        };
        Some((0..jacs.len()).map(nearest).sum())
    }
}

fn squared(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    (0..4).map(|c| (a[c] - b[c]).powi(2)).sum()
}

/// The factor [`reduce`] brings a `w × h` image down by to at most `work_pixels` pixels.
fn work_factor(w: usize, h: usize, work_pixels: usize) -> usize {
    ((w * h) as f64 / work_pixels.max(1) as f64).sqrt().ceil().max(1.0) as usize
}

/// Reduced pixel → full pixel for [`reduce`] by `f`: x_full = f·x_reduced + (f − 1)/2 on
/// both axes.
fn reduced_to_full(f: usize) -> Homography {
    let f = f as f64;
    Homography::from_rows([[f, 0.0, (f - 1.0) / 2.0], [0.0, f, (f - 1.0) / 2.0], [0.0, 0.0, 1.0]])
        .expect("scaling is regular")
}

/// Box average of `f × f` blocks (the last ones partial).
fn reduce<P: RgbPixel>(img: &Plane<P>, f: usize) -> RgbF32 {
    if f <= 1 {
        return img.map(|p| p.to_f32());
    }
    let (w, h) = (img.width(), img.height());
    let (rw, rh) = (w.div_ceil(f), h.div_ceil(f));
    RgbF32::from_fn(rw, rh, |x, y| {
        let mut s = [0.0f32; 3];
        let mut n = 0.0;
        for yy in y * f..((y + 1) * f).min(h) {
            for xx in x * f..((x + 1) * f).min(w) {
                let p = img.get(xx, yy).to_f32();
                for c in 0..3 {
                    s[c] += p[c];
                }
                n += 1.0;
            }
        }
        s.map(|v| v / n)
    })
}

/// Box average over `(2r + 1)²` of the valid pixels only.
fn box_blur(img: &RgbF32, valid: &Plane<bool>, r: usize) -> RgbF32 {
    if r == 0 {
        return img.clone();
    }
    let (w, h) = (img.width(), img.height());
    let (px, ok) = (img.as_slice(), valid.as_slice());
    RgbF32::from_fn(w, h, |x, y| {
        let mut s = [0.0f32; 3];
        let mut n = 0.0;
        // The window clipped to the image, taps in the order of the plain double loop.
        let (x0, x1) = (x.saturating_sub(r), (x + r).min(w - 1));
        for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
            for i in yy * w + x0..=yy * w + x1 {
                if ok[i] {
                    let p = px[i];
                    for c in 0..3 {
                        s[c] += p[c];
                    }
                    n += 1.0;
                }
            }
        }
        if n > 0.0 { s.map(|v| v / n) } else { img.get(x, y) }
    })
}

/// 1-D max (`grow`) or min filter of radius `r` along rows (`vertical` false) or columns.
fn filter_1d(m: &Plane<bool>, r: usize, grow: bool, vertical: bool) -> Plane<bool> {
    let (w, h) = (m.width(), m.height());
    let src = m.as_slice();
    let mut out = vec![false; w * h];
    let verdict = |count: u32, window: u32| if grow { count > 0 } else { count == window };
    if vertical {
        // Down the rows, a running count per column: each step reads and writes whole rows.
        let mut count = vec![0u32; w];
        for row in src.chunks_exact(w.max(1)).take(r.min(h)) {
            count.iter_mut().zip(row).for_each(|(c, &v)| *c += u32::from(v));
        }
        for y in 0..h {
            if y + r < h {
                count.iter_mut().zip(&src[(y + r) * w..][..w]).for_each(|(c, &v)| *c += u32::from(v));
            }
            if y > r {
                count.iter_mut().zip(&src[(y - r - 1) * w..][..w]).for_each(|(c, &v)| *c -= u32::from(v));
            }
            let window = ((y + r).min(h - 1) + 1 - y.saturating_sub(r)) as u32;
            out[y * w..][..w].iter_mut().zip(&count).for_each(|(o, &c)| *o = verdict(c, window));
        }
        return Plane::from_vec(w, h, out);
    }
    for (line, row) in src.chunks_exact(w.max(1)).enumerate().take(h) {
        // Running count of `true` in the window [k − r, k + r] ∩ [0, w).
        let mut count = row.iter().take(r.min(w)).map(|&v| u32::from(v)).sum::<u32>();
        for k in 0..w {
            if k + r < w {
                count += u32::from(row[k + r]);
            }
            if k > r {
                count -= u32::from(row[k - r - 1]);
            }
            let window = ((k + r).min(w - 1) + 1 - k.saturating_sub(r)) as u32;
            out[line * w + k] = verdict(count, window);
        }
    }
    Plane::from_vec(w, h, out)
}

/// Dilation by a `(2r + 1)²` square.
pub fn dilate(m: &Plane<bool>, r: usize) -> Plane<bool> {
    if r == 0 {
        return m.clone();
    }
    filter_1d(&filter_1d(m, r, true, false), r, true, true)
}

/// Erosion by a `(2r + 1)²` square (pixels beyond the border do not count against).
pub fn erode(m: &Plane<bool>, r: usize) -> Plane<bool> {
    if r == 0 {
        return m.clone();
    }
    filter_1d(&filter_1d(m, r, false, false), r, false, true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{Occluder, facade, paint_occluder, render_view};

    /// Judged on the inputs halved three times, a 12 MP keyframe's region judged (1296 ×
    /// 1096, worked at half size at full resolution) is worked whole: the radii shrink so
    /// that they reach as far on the building, the margin with the pixels.
    #[test]
    fn own_params_halved_reach_as_far_on_the_building() {
        let p = OwnParams::default();
        let mut mask = Mask::new(4000, 3000, 0);
        for y in 1000..2000 {
            for x in 1500..2700 {
                mask.set(x, y, 255);
            }
        }
        let same = p.halved(0, &mask);
        assert_eq!((same.margin, same.parallax_radius, same.growth), (p.margin, p.parallax_radius, p.growth));
        let h = p.halved(3, &mask);
        assert_eq!((h.margin, h.parallax_radius, h.growth), (6, 2, 1));
    }

    /// A slab off the wall, seen through the wall's homography, is marked as a view's own
    /// occluder; judged again through the surfaces, its marks go and the views' occluders'
    /// stay (through the walls, half the marks or more lie on the slabs of these facades;
    /// through the true surfaces, 71–73 % of those go and 0.5–7 % of the occluders').
    #[test]
    fn a_slab_marked_through_the_wall_is_unmarked_through_its_surface() {
        for seed in [2, 4] {
            let c = facade::parallax_case(640, 480, 5, seed, false);
            let walls = c.wall();
            let sources: Vec<Source<'_>> =
                c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
            let (own, auto) = (OwnParams::default(), AutoMaskParams::default());
            let through_walls = own_occluders(&c.key, &c.mask, &sources, &own, &auto);
            let marks: Vec<Option<&Mask>> = through_walls.iter().map(Option::as_ref).collect();
            let off = own_occluders_off_surfaces(
                &c.key,
                &c.mask,
                &sources,
                &marks,
                &c.true_surfaces(24),
                &own,
                &auto,
            );
            let (before, after) = (c.where_marks_lie(&through_walls), c.where_marks_lie(&off));
            assert!(
                before.slab * 2 > before.occluder,
                "seed {seed}: the slabs are marked through the walls {before:?}"
            );
            assert!(
                after.slab * 5 < before.slab * 2,
                "seed {seed}: the slabs' marks stay {before:?} → {after:?}"
            );
            assert!(
                after.occluder * 10 >= before.occluder * 9,
                "seed {seed}: the occluders' marks go {before:?} → {after:?}"
            );
        }
    }

    /// Erosion and dilation by a square, pixel by pixel: the reference for `filter_1d`.
    fn by_hand(m: &Plane<bool>, r: usize, grow: bool) -> Plane<bool> {
        let (w, h) = (m.width() as isize, m.height() as isize);
        let r = r as isize;
        Plane::from_fn(m.width(), m.height(), |x, y| {
            let seen = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (x as isize + dx, y as isize + dy)));
            let inside = |&(nx, ny): &(isize, isize)| nx >= 0 && ny >= 0 && nx < w && ny < h;
            if grow {
                seen.filter(inside).any(|(nx, ny)| m.get(nx as usize, ny as usize))
            } else {
                seen.filter(inside).all(|(nx, ny)| m.get(nx as usize, ny as usize))
            }
        })
    }

    #[test]
    fn erosion_and_dilation_are_those_of_a_square() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for (w, h) in [(1, 1), (1, 9), (9, 1), (23, 17), (40, 3)] {
            for density in [0.2, 0.8, 0.97] {
                let m = Plane::from_fn(w, h, |_, _| rng.random::<f64>() < density);
                for r in [0, 1, 2, 5, 30] {
                    assert!(erode(&m, r) == by_hand(&m, r, false), "erode {w}x{h} r {r} density {density}");
                    assert!(dilate(&m, r) == by_hand(&m, r, true), "dilate {w}x{h} r {r} density {density}");
                }
            }
        }
    }

    /// The moves of a row scored side by side explain exactly the pixels that the moves one
    /// at a time explain ([`window_matches`]): over images where the other is the keyframe
    /// moved, noisy and with pixels not usable, at thresholds where some windows match and
    /// some do not, every pixel (the borders too), radii that fit the lanes and one that
    /// does not.
    #[test]
    fn moves_side_by_side_explain_what_each_move_explains() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (w, h) = (61, 37);
        // Per radius and case, how many pixels were explained and how many not.
        let mut tally: Vec<(usize, usize, usize)> = Vec::new();
        let key = RgbF32::from_fn(w, h, |x, y| {
            let t = (x as f32 * 0.37).sin() + (y as f32 * 0.23).cos();
            [0.5 + 0.3 * t.sin(), 0.4 + 0.2 * t, 0.6 - 0.1 * t]
        });
        for (move_by, noise, unusable) in
            [((2isize, 1isize), 0.02f32, 0.1f64), ((-5, 3), 0.05, 0.3), ((0, 0), 0.1, 0.0)]
        {
            let other = RgbF32::from_fn(w, h, |x, y| {
                let (sx, sy) = (
                    (x as isize - move_by.0).clamp(0, w as isize - 1),
                    (y as isize - move_by.1).clamp(0, h as isize - 1),
                );
                key.get(sx as usize, sy as usize).map(|c| c + noise * (rng.random::<f32>() - 0.5))
            });
            let usable = Plane::from_fn(w, h, |_, _| rng.random::<f64>() >= unusable);
            for radius in [1, 3, 8, 16] {
                for threshold in [0.01f32, 0.03, 0.08] {
                    let moves = Moves::new(&key, &other, &usable, radius, threshold);
                    let size = (w as isize, h as isize);
                    let (mut yes, mut no) = (0, 0);
                    for y in 0..h {
                        for x in 0..w {
                            let at = (x as isize, y as isize);
                            let each = moves.moves.iter().any(|&m| {
                                window_matches(
                                    key.as_slice(),
                                    other.as_slice(),
                                    usable.as_slice(),
                                    size,
                                    at,
                                    m,
                                    threshold * threshold,
                                )
                            });
                            assert_eq!(
                                moves.explains(x, y),
                                each,
                                "({x}, {y}) radius {radius} threshold {threshold}"
                            );
                            if each { yes += 1 } else { no += 1 }
                        }
                    }
                    tally.push((radius, yes, no));
                }
            }
        }
        for radius in [1, 3, 8, 16] {
            let of = || tally.iter().filter(|t| t.0 == radius);
            assert!(
                of().any(|t| t.1 > 100) && of().any(|t| t.2 > 100),
                "radius {radius}: both verdicts {tally:?}"
            );
        }
    }

    #[test]
    fn morphology_grows_and_shrinks_squares() {
        let m = Plane::from_fn(20, 20, |x, y| x == 10 && y == 10);
        let d = dilate(&m, 2);
        assert_eq!(d.as_slice().iter().filter(|&&v| v).count(), 25);
        assert!(d.get(8, 12) && !d.get(7, 10));
        assert_eq!(erode(&d, 2).as_slice().iter().filter(|&&v| v).count(), 1);
        assert!(erode(&d, 3).as_slice().iter().all(|&v| !v));
    }

    /// One view at one step of [`arrivals`]: the identities of the views it was judged
    /// against (itself first; `None`: not judged), its marks, and those found afresh.
    type Step = (Option<Vec<u64>>, Option<Mask>, Option<Mask>);

    /// Views arriving one by one, and one leaving, as in a session, each call given the
    /// marks of the last (`keep_spread`): per step, per view, its marks and the identities
    /// of the views it was judged against (`None`: not judged), and the marks found afresh.
    fn arrivals(keep_spread: f64) -> Vec<Vec<Step>> {
        let c = crate::synth::occlusion_case(crate::synth::CaseFamily::Planar, 320, 240, 10, 11);
        assert!(fresh_marks_exist(&c, &OwnParams::default(), &AutoMaskParams::default()), "nothing to mark");
        let all = c.sources();
        let (params, auto) = (OwnParams { keep_spread, ..OwnParams::default() }, AutoMaskParams::default());
        // (id, memo) of the views present, in arrival order; view 2 leaves after view 5.
        let mut present: Vec<(u64, OwnMarks)> = Vec::new();
        let mut steps = Vec::new();
        for step in 0..all.len() {
            present.push((step as u64, OwnMarks::default()));
            if step == 5 {
                present.retain(|(id, _)| *id != 2);
            }
            let ids: Vec<u64> = present.iter().map(|(id, _)| *id).collect();
            let sources: Vec<Source<'_, [f32; 3]>> = ids.iter().map(|&id| all[id as usize]).collect();
            let mut memo: Vec<OwnMarks> = present.iter().map(|(_, m)| m.clone()).collect();
            let fresh = own_occluders(&c.key, &c.mask, &sources, &params, &auto);
            let kept: Vec<Option<Mask>> =
                own_occluders_memo(&c.key, &c.mask, &sources, &ids, &params, &auto, &mut memo)
                    .into_iter()
                    .map(|m| m.cloned())
                    .collect();
            assert_eq!(kept.len(), fresh.len(), "step {step}");
            steps.push(
                memo.iter()
                    .zip(kept)
                    .zip(fresh)
                    .map(|((m, k), f)| (m.judged.as_ref().map(|j| j.ids.clone()), k, f))
                    .collect(),
            );
            for (entry, m) in present.iter_mut().zip(memo) {
                entry.1 = m;
            }
        }
        steps
    }

    /// Judging a view again whenever the fresh choice of its references changed, the marks
    /// kept from call to call are at each step those found afresh; views whose references
    /// stayed are not judged again, and a view whose references changed is.
    #[test]
    fn marks_kept_between_calls_are_those_found_afresh() {
        let steps = arrivals(0.0);
        for (step, views) in steps.iter().enumerate() {
            for (k, (_, marks, fresh)) in views.iter().enumerate() {
                assert!(marks == fresh, "step {step}, view {k}: the kept marks are not those found afresh");
            }
        }
        let (kept, judged_again, _) = tally(&steps);
        assert!(kept > 0 && judged_again > 0, "kept {kept}, judged again {judged_again}");
    }

    /// Over the views judged at each step of `steps`, those judged at the step before too:
    /// with the same references (marks kept) and with others (judged again); and those
    /// judged for the first time.
    fn tally(steps: &[Vec<Step>]) -> (usize, usize, usize) {
        let (mut kept, mut again, mut first) = (0, 0, 0);
        for (step, views) in steps.iter().enumerate() {
            for refs in views.iter().filter_map(|v| v.0.as_ref()) {
                let before = step
                    .checked_sub(1)
                    .and_then(|s| steps[s].iter().filter_map(|v| v.0.as_ref()).find(|r| r[0] == refs[0]));
                match before {
                    Some(b) if b == refs => kept += 1,
                    Some(_) => again += 1,
                    None => first += 1,
                }
            }
        }
        (kept, again, first)
    }

    /// Kept with their references (the default): a view judged again has the marks found
    /// afresh, against the views a fresh choice takes; the others keep theirs, judged against
    /// as many views, also after one of those left; and fewer views are judged than when
    /// each fresh choice is followed.
    #[test]
    fn marks_stand_while_their_references_are_as_many_and_nearly_as_far_apart() {
        let judged = |steps: &[Vec<Step>]| {
            let (_, again, first) = tally(steps);
            again + first
        };
        let (sticky, afresh) = (arrivals(OwnParams::default().keep_spread), arrivals(0.0));
        let mut outlived = 0;
        for (step, (views, fresh_views)) in sticky.iter().zip(&afresh).enumerate() {
            let present: Vec<u64> = views.iter().filter_map(|v| v.0.as_ref().map(|r| r[0])).collect();
            for ((refs, marks, fresh), (fresh_refs, _, _)) in views.iter().zip(fresh_views) {
                let (Some(refs), Some(fresh_refs)) = (refs, fresh_refs) else { continue };
                if refs == fresh_refs {
                    assert!(
                        marks == fresh,
                        "step {step}, view {}: judged against the fresh choice, not its marks",
                        refs[0]
                    );
                } else {
                    assert!(
                        refs.len() >= fresh_refs.len(),
                        "step {step}: {refs:?} kept against fewer than {fresh_refs:?}"
                    );
                }
                outlived += usize::from(refs[1..].iter().any(|id| !present.contains(id)));
            }
        }
        let (s, a) = (judged(&sticky), judged(&afresh));
        assert!(s < a, "{s} judgements kept with their references, {a} afresh");
        assert!(outlived > 0, "no view kept marks judged against a view that left");
    }

    fn fresh_marks_exist(c: &crate::synth::OcclusionCase, params: &OwnParams, auto: &AutoMaskParams) -> bool {
        own_occluders(&c.key, &c.mask, &c.sources(), params, auto)
            .iter()
            .flatten()
            .any(|m| m.as_slice().iter().any(|&v| v > 0))
    }

    /// The automatic mask's IoU with the true one on a generated case of a tree every view
    /// shows too (320 × 240, `views` views).
    fn shared_tree_iou(seed: u64, views: usize) -> f64 {
        let c = crate::synth::occlusion_case(crate::synth::CaseFamily::Shared, 320, 240, views, seed);
        let found = auto_mask_report(&c.key, &c.sources(), &AutoMaskParams::default());
        crate::imaging::metrics::mask_iou(&found.mask, &c.mask)
    }

    /// The mask ends near the outline a person paints, 2 px past the occluder, and every
    /// occluder pixel is in it. Grown by 3 px after the comparison's blur, it lay 3 px and
    /// more past that outline all round (the IoU with it 0.92 to 0.945 on these cases; now
    /// 0.98). At 480 × 360 the comparison runs at full resolution, at 1 800 × 1 000 on a
    /// half-size image.
    #[test]
    fn the_mask_keeps_near_the_outline_a_person_paints() {
        for (w, h, seed) in [(480, 360, 7001), (480, 360, 7002), (1800, 1000, 7003)] {
            let c = crate::synth::occlusion_case(crate::synth::CaseFamily::Planar, w, h, 3, seed);
            let found = |p: &AutoMaskParams| auto_mask_report(&c.key, &c.sources(), p).mask;
            let on = |m: &Mask, i: usize| m.as_slice()[i] > 127;
            let n = c.key.as_slice().len();
            // The painted mask's outline: its pixels with an unmasked 4-neighbour.
            let painted = c.mask.map(|&v| v > 127);
            let inside = erode(&painted, 1);
            let outline = (0..n).filter(|&i| painted.as_slice()[i] && !inside.as_slice()[i]).count();
            let near = dilate(&painted, 1);
            let past = |m: &Mask| (0..n).filter(|&i| on(m, i) && !near.as_slice()[i]).count();
            let occluder = (0..n).filter(|&i| on(&c.key_occluders, i)).count();
            let m = found(&AutoMaskParams::default());
            let kept = (0..n).filter(|&i| on(&c.key_occluders, i) && on(&m, i)).count();
            let wide = found(&AutoMaskParams { dilate_radius: 3, ..AutoMaskParams::default() });
            println!(
                "{w} x {h} seed {seed}: outline {outline} px; masked more than 1 px past it {} (grown by 3 px: {}); IoU {:.3} ({:.3}); occluder {kept} of {occluder}",
                past(&m),
                past(&wide),
                crate::imaging::metrics::mask_iou(&m, &c.mask),
                crate::imaging::metrics::mask_iou(&wide, &c.mask),
            );
            assert_eq!(kept, occluder, "every occluder pixel is masked");
            assert!(2 * past(&m) < outline, "{} px more than 1 px past an outline of {outline}", past(&m));
            // The case holds: grown by 3 px, the mask is a ring wider all round.
            assert!(
                past(&wide) > outline / 2,
                "grown by 3 px: {} px past an outline of {outline}",
                past(&wide)
            );
        }
    }

    /// The automatic mask of case `c` under `params`: how many pixels it takes more than
    /// 6 px from the true occluders, and the share of the true mask it covers.
    fn masked_away_and_recall(c: &crate::synth::OcclusionCase, params: &AutoMaskParams) -> (usize, f64) {
        let near = dilate(&c.mask.map(|&m| m > 127), 6);
        let m = auto_mask_report(&c.key, &c.sources(), params).mask;
        let on = |i: usize| m.as_slice()[i] > 127;
        let away = (0..m.as_slice().len()).filter(|&i| on(i) && !near.as_slice()[i]).count();
        let hit = (0..m.as_slice().len()).filter(|&i| on(i) && c.mask.as_slice()[i] > 127).count();
        (away, hit as f64 / c.mask.hole_count() as f64)
    }

    /// A facade with slabs standing off the wall (piers, sign boards) and the keyframe's own
    /// tree and passer-by. Seen through the wall's homography, the slabs' edges disagree with
    /// the views as an occluder does; each view shows them moved along its epipolar line.
    /// Without that explanation 1 169 to 9 092 pixels away from the occluders are masked,
    /// with it 12 to 2 323; every occluder pixel is found either way.
    /// With one view there is no consensus. Judged by that view alone, with what it shows
    /// displaced not searched for (`min_views` 1, the way a walk's frame is judged), the
    /// slabs off the wall and the view's own occluders are masked too; searched for, the mask
    /// keeps to the keyframe's occluders.
    #[test]
    fn a_lone_view_masks_what_it_shows_nowhere_near() {
        let (mut away_naive, mut away_lone, mut recalls) = (0, 0, Vec::new());
        for seed in [6003, 6005, 8005, 8011] {
            let c = crate::synth::occlusion_case(crate::synth::CaseFamily::NonPlanar, 480, 360, 1, seed);
            let found = |p: &AutoMaskParams| masked_away_and_recall(&c, p);
            // The views one by one (`shading_ncc`) would explain the slabs in the naive
            // judgement too: left out, so that the search is what is measured.
            let (naive, naive_recall) =
                found(&AutoMaskParams { min_views: 1, shading_ncc: 0.0, ..AutoMaskParams::default() });
            let (lone, recall) = found(&AutoMaskParams::default());
            println!(
                "seed {seed}: {naive} → {lone} pixels away from the occluders, recall {naive_recall:.3} → {recall:.3}"
            );
            (away_naive, away_lone) = (away_naive + naive, away_lone + lone);
            recalls.push(recall);
        }
        assert!(away_naive > 4000, "the cases hold: {away_naive} pixels off the occluders");
        assert!(
            2 * away_lone < away_naive,
            "{away_lone} pixels off the occluders, {away_naive} without the search"
        );
        let mean = recalls.iter().sum::<f64>() / recalls.len() as f64;
        assert!(mean > 0.8, "recall {recalls:?}");
    }

    /// A planar case of two views whose first is cut to the left two fifths of its frame,
    /// so that part of the keyframe is seen by the second alone; the cut view.
    fn cut_case(seed: u64) -> (crate::synth::OcclusionCase, RgbF32) {
        let c = crate::synth::occlusion_case(crate::synth::CaseFamily::Planar, 480, 360, 2, seed);
        let v = &c.views[0];
        let cut = Plane::from_fn(v.width() * 2 / 5, v.height(), |x, y| v.get(x, y));
        (c, cut)
    }

    /// The cut view and the whole second view of [`cut_case`], as the fill takes them.
    fn cut_sources<'a>(c: &'a crate::synth::OcclusionCase, cut: &'a RgbF32) -> Vec<Source<'a>> {
        vec![
            Source { image: cut, homography: c.homographies[0] },
            Source { image: &c.views[1], homography: c.homographies[1] },
        ]
    }

    /// Whether `s` shows the keyframe's pixel `(x, y)`.
    fn shows(s: &Source<'_>, x: usize, y: usize) -> bool {
        s.homography.apply(nalgebra::Point2::new(x as f64, y as f64)).is_some_and(|p| {
            p.x >= 0.0
                && p.y >= 0.0
                && p.x < (s.image.width() - 1) as f64
                && p.y < (s.image.height() - 1) as f64
        })
    }

    /// Two views, one of them cut to the left part of its frame: the keyframe's occluders
    /// that only the other view reaches are judged by that view alone, as a lone view is.
    /// Before, nobody judged them (two agreeing views were asked for) and they stayed in
    /// the fill whole.
    #[test]
    fn what_one_view_alone_sees_is_judged_by_it() {
        let (mut off, mut on, mut cases) = (0.0, 0.0, 0);
        for seed in [7101, 7102, 7103, 7104, 7105, 7106] {
            let (c, cut) = cut_case(seed);
            let sources = cut_sources(&c, &cut);
            let (w, h) = (c.key.width(), c.key.height());
            let once: Vec<usize> = (0..w * h)
                .filter(|&i| c.key_occluders.as_slice()[i] > 127)
                // The keyframe's occluder pixels that only the whole view sees.
                .filter(|&i| !shows(&sources[0], i % w, i / w) && shows(&sources[1], i % w, i / w))
                .collect();
            if once.len() < 2000 {
                continue;
            }
            let recall = |p: &AutoMaskParams| {
                let m = auto_mask(&c.key, &sources, p);
                once.iter().filter(|&&i| m.as_slice()[i] > 127).count() as f64 / once.len() as f64
            };
            let (without, with) = (
                recall(&AutoMaskParams { lone_view_reach: 0.0, ..AutoMaskParams::default() }),
                recall(&AutoMaskParams::default()),
            );
            println!(
                "seed {seed}: {} occluder pixels seen by one view only, found {without:.3} -> {with:.3}",
                once.len()
            );
            (off, on, cases) = (off + without, on + with, cases + 1);
        }
        assert!(cases >= 3, "only {cases} cases with an occluder one view alone sees");
        let (off, on) = (off / cases as f64, on / cases as f64);
        // Without the stage, only what grows into it from the occluders' other parts is
        // found (0.40 over these seeds).
        assert!(off < 0.6, "the case holds: {off:.3} found without the stage");
        assert!(on > 0.9, "{on:.3} of what one view alone sees found");
    }

    /// One view's word alone seeds no sliver: a dark lip 3 px high along the keyframe's
    /// lower edge, where only one view reaches and shows the wall (a poster's frame, which
    /// the view sees from elsewhere), is no object. With any size taken as a seed, it grew
    /// through the keyframe's speckle (hpatches-churchill).
    #[test]
    fn one_view_alone_seeds_no_sliver() {
        let (mut kept, mut taken, mut cases) = (0.0, 0.0, 0);
        for seed in [7101, 7102, 7103, 7104, 7105, 7106] {
            let (mut c, cut) = cut_case(seed);
            let (w, h) = (c.key.width(), c.key.height());
            let near_occluder = dilate(&c.key_occluders.map(|&v| v > 127), 12);
            // 30 columns along the lower edge (off the corners) that the whole view alone sees,
            // clear of occluders.
            let clear = |x: usize| {
                let sources = cut_sources(&c, &cut);
                (h - 6..h).all(|y| {
                    !shows(&sources[0], x, y) && shows(&sources[1], x, y) && !near_occluder.get(x, y)
                })
            };
            let Some(x0) = (10..w - 40).find(|&x0| (x0..x0 + 30).all(clear)) else { continue };
            let lip: Vec<(usize, usize)> =
                (h - 3..h).flat_map(|y| (x0..x0 + 30).map(move |x| (x, y))).collect();
            lip.iter().for_each(|&(x, y)| c.key.set(x, y, [0.03; 3]));
            let sources = cut_sources(&c, &cut);
            let share = |p: &AutoMaskParams| {
                let m = auto_mask(&c.key, &sources, p);
                lip.iter().filter(|&&(x, y)| m.get(x, y) > 127).count() as f64 / lip.len() as f64
            };
            let (without, with) = (
                share(&AutoMaskParams { seen_once_seed: 0.0, ..AutoMaskParams::default() }),
                share(&AutoMaskParams::default()),
            );
            println!(
                "seed {seed}: the lip at x {x0}, masked {without:.3} without a least seed, {with:.3} with"
            );
            (taken, kept, cases) = (taken + without, kept + with, cases + 1);
        }
        assert!(cases >= 3, "only {cases} cases with a lower edge one view alone sees");
        let (taken, kept) = (taken / cases as f64, kept / cases as f64);
        assert!(taken > 0.5, "the case holds: {taken:.3} of the lip masked with any seed");
        assert!(kept < 0.1, "{kept:.3} of the lip masked");
    }

    /// A facade with a slab standing off the wall, seen with another parallax in each view:
    /// the views' consensus there is a blend that matches neither the keyframe nor any view,
    /// while views one by one can show the keyframe's texture. Without the stage that asks them
    /// one by one ([`AutoMaskParams::shading_ncc`]) the slab is masked (375, 2 851 and 343
    /// pixels more than 6 px from the occluders); with it, 7, 32 and 3. The occluders are
    /// found whole.
    #[test]
    fn faces_shaded_otherwise_are_not_occluders() {
        for (seed, views) in [(6005, 4), (8005, 2), (6007, 3)] {
            let c = crate::synth::occlusion_case(crate::synth::CaseFamily::NonPlanar, 480, 360, views, seed);
            let found = |shading_ncc: f32| {
                masked_away_and_recall(&c, &AutoMaskParams { shading_ncc, ..AutoMaskParams::default() })
            };
            let (without, recall_without) = found(0.0);
            let (with, recall) = found(AutoMaskParams::default().shading_ncc);
            println!(
                "seed {seed}, {views} views: {without} → {with} pixels away from the occluders, recall {recall_without:.3} → {recall:.3}"
            );
            assert!(without > 300, "seed {seed}: the case holds ({without} pixels off the occluders)");
            assert!(3 * with < without, "seed {seed}: {with} pixels off the occluders, {without} without");
            assert!(recall > 0.98 && recall >= recall_without - 0.01, "seed {seed}: recall {recall:.3}");
        }
    }

    #[test]
    fn what_stands_off_the_wall_is_explained_along_the_epipolar_lines() {
        for (seed, views) in [(6003, 3), (6005, 4), (8005, 2)] {
            let c = crate::synth::occlusion_case(crate::synth::CaseFamily::NonPlanar, 480, 360, views, seed);
            // Without the views asked one by one (`shading_ncc`), which explain most of the
            // slabs before the epipolar lines are looked along: this measures the lines.
            let found = |reach: f32| {
                let p =
                    AutoMaskParams { epipolar_reach: reach, shading_ncc: 0.0, ..AutoMaskParams::default() };
                masked_away_and_recall(&c, &p)
            };
            let (without, recall_without) = found(0.0);
            let (with, recall) = found(AutoMaskParams::default().epipolar_reach);
            println!("seed {seed}, {views} views: {without} → {with} pixels away from the occluders");
            assert!(without > 1000, "seed {seed}: the case holds ({without} pixels off the occluders)");
            assert!(2 * with < without, "seed {seed}: {with} pixels off the occluders, {without} without");
            assert!(recall > 0.98 && recall >= recall_without - 0.01, "seed {seed}: recall {recall:.3}");
        }
    }

    /// Views with occluders of their own over the keyframe's (so that they agree with it
    /// there): the keyframe's objects are still found whole, as a person would paint them.
    #[test]
    fn finds_whole_objects_where_the_views_are_occluded_too() {
        for seed in [1001, 1002, 1003] {
            let c = crate::synth::occlusion_case(crate::synth::CaseFamily::Planar, 320, 240, 3, seed);
            let found = auto_mask_report(&c.key, &c.sources(), &AutoMaskParams::default());
            let score = crate::imaging::metrics::mask_iou(&found.mask, &c.mask);
            assert!(score > 0.85, "seed {seed}: IoU {score:.3} with the true mask");
            assert!(found.objects >= 1 && found.objects <= 6, "seed {seed}: {} objects", found.objects);
            assert!(
                found.certain_share > 0.3 && found.certain_share < 1.0,
                "seed {seed}: {:?}",
                found.certain_share
            );
            assert!(found.judged_share > 0.5, "seed {seed}: judged {:.3}", found.judged_share);
        }
    }

    /// A tree every view shows too, displaced: the views agree with the keyframe inside its
    /// crown, so only a crescent at its edge is flagged, and the crown must be grown from it
    /// by its colours. The unflagged inside of the crown is not the building's colours.
    /// (On these two cases the crown stayed a crescent while the growth compared it with
    /// the whole keyframe's unflagged pixels: IoU 0.53 and 0.38.)
    #[test]
    fn a_tree_the_views_share_is_grown_whole_from_its_edge() {
        // (2005, 4): the four views' crowns, displaced four ways, agree on no colour inside
        // the keyframe's crown, so nothing there is flagged or judged; it was counted as
        // building until only judged pixels were (IoU 0.53 then, 0.79 now). (2002, 4): the
        // first growth joins crescents at the crown's edge; only the passes through unjudged
        // pixels within (and around) the object's box fill the crown (IoU 0.58 without them,
        // 0.76 with them when they were added; 0.87 now).
        for (seed, views) in [(2002, 2), (2005, 3), (2005, 4), (2002, 4)] {
            let score = shared_tree_iou(seed, views);
            assert!(score > 0.65, "seed {seed}, {views} views: IoU {score:.3} with the true mask");
        }
    }

    /// Two views, each showing the tree displaced over part of the keyframe's crown: a
    /// crescent at the crown's rim is all that is flagged, and what lies below it is unjudged
    /// (the two views disagree there). The crescent's box held the top of the crown only;
    /// grown through the unjudged pixels beyond it, the crown is found whole. (With
    /// `unjudged_reach` 0: IoU 0.530 and 0.551; with 2: 0.755 and 0.771.)
    #[test]
    fn a_crown_flagged_only_at_its_rim_is_grown_beyond_the_rims_box() {
        for seed in [2007, 2009] {
            let score = shared_tree_iou(seed, 2);
            assert!(score > 0.7, "seed {seed}: IoU {score:.3} with the true mask");
        }
    }

    /// The growth past an object's box through what the views did not judge: a stretch of the
    /// object's colour beside it is taken where the views see it and disagree, or where every
    /// view differs from the keyframe, and not where no view sees it (a frame's edge: on
    /// parapano_building a streak at the skyline grew along the left building's grey roof,
    /// 13 092 pixels, where only one view reached).
    #[test]
    fn past_its_box_an_object_grows_only_where_the_views_see_and_doubt() {
        let (w, h) = (60, 40);
        let green = [0.2, 0.5, 0.2];
        let key = RgbF32::from_fn(w, h, |x, y| match (x, y) {
            (10..28, 10..20) => green,
            _ if y % 4 == 0 => [0.8, 0.78, 0.75],
            _ => [0.6, 0.35, 0.25],
        });
        let object = Plane::from_fn(w, h, |x, y| (10..20).contains(&x) && (10..20).contains(&y));
        let beside = |x: usize, y: usize| (20..28).contains(&x) && (10..20).contains(&y);
        let grown_by = |growth: Growth, contested: bool, weak: bool| {
            let ev = Evidence {
                strong: object.clone(),
                weak: Plane::from_fn(w, h, |x, y| beside(x, y) && weak),
                judged: Plane::from_fn(w, h, |x, y| !object.get(x, y) && !beside(x, y)),
                contested: Plane::from_fn(w, h, |x, y| beside(x, y) && contested),
                consensus: key.clone(),
            };
            let out = grow_by_colour(&key, &object, &ev, &AutoMaskParams::default(), growth);
            (0..w * h).filter(|&i| out.get(i % w, i / w) && beside(i % w, i / w)).count()
        };
        let grown = |contested: bool, weak: bool| grown_by(Growth::ThroughUnjudged, contested, weak);
        // The box (10..20) grown by twice a quarter of its size reaches x = 24: 4 columns.
        assert_eq!(grown(true, false), 40, "seen and contested");
        assert_eq!(grown(false, true), 40, "every view unlike the keyframe");
        assert_eq!(grown(false, false), 0, "seen by too few views to say");
        // The regrowth passes reach a quarter of its size beyond the box (x = 22), by the
        // same rule where the views did not judge (they took 20 pixels there too).
        let regrown = |contested: bool, weak: bool| grown_by(Growth::Regrowth, contested, weak);
        assert_eq!(regrown(true, false), 20);
        assert_eq!(regrown(false, true), 20);
        assert_eq!(regrown(false, false), 0, "seen by too few views to say");
        assert_eq!(grown_by(Growth::Around, false, false), 20, "the first growth goes anywhere near");
    }

    #[test]
    fn a_tree_the_views_share_is_grown_across_the_crown_from_a_crescent() {
        // Where the views' displaced crowns cover the keyframe's, they agree with it and only
        // a crescent is found; grown once, its box is too small to reach across the crown.
        // Without the regrowth passes: IoU 0.49, 0.64 and 0.49 (0.86, 0.89, 0.85 with them).
        for (seed, views) in [(2001, 4), (2003, 3), (2010, 2)] {
            let score = shared_tree_iou(seed, views);
            assert!(score > 0.75, "seed {seed}, {views} views: IoU {score:.3} with the true mask");
        }
    }

    /// Two views, each with an object of its own beside the keyframe's car, where the other
    /// view is occluded too: no view shows the keyframe's wall there, yet the wall is not
    /// the keyframe's occluder. Each view's disagreement is its own object's, seen where the
    /// other view agrees with the keyframe. (Without that explanation the keyframe's car
    /// grew over the wall where the two objects overlap: 788 pixels of them; 3 with it.)
    #[test]
    fn the_views_own_objects_side_by_side_are_not_the_keyframes() {
        let (w, h) = (240, 180);
        let scene = facade(w, h, 12);
        let mut key = scene.clone();
        let mut truth = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut truth), Occluder::Car, 80.0, 120.0, 40.0, 5);
        let hs = [Homography::translation(5.5, -2.0), Homography::translation(-6.0, 3.0)];
        let mut own = Mask::new(w, h, 0);
        let views: Vec<RgbF32> = hs
            .iter()
            .zip([Occluder::Person, Occluder::Car])
            .enumerate()
            .map(|(i, (hm, kind))| {
                let mut v = render_view(&scene, &hm.inverse().unwrap(), w, h, [0.5; 3]);
                // Placed in keyframe coordinates, beside the car's right end.
                let at = hm.apply(nalgebra::Point2::new(108.0, 100.0)).unwrap();
                paint_occluder(&mut v, None, kind, at.x as f32, at.y as f32, 70.0, 7 + i as u64);
                let mut m = Mask::new(w, h, 0);
                paint_occluder(
                    &mut RgbF32::new(w, h, [0.0; 3]),
                    Some(&mut m),
                    kind,
                    108.0,
                    100.0,
                    70.0,
                    7 + i as u64,
                );
                own.as_mut_slice().iter_mut().zip(m.as_slice()).for_each(|(o, &n)| *o = (*o).max(n));
                v
            })
            .collect();
        let sources: Vec<Source<'_>> =
            views.iter().zip(&hs).map(|(v, &homography)| Source { image: v, homography }).collect();
        let m = auto_mask(&key, &sources, &AutoMaskParams::default());
        let count = |f: &dyn Fn(usize) -> bool| (0..w * h).filter(|&i| f(i)).count();
        let found = count(&|i| truth.as_slice()[i] > 127 && m.as_slice()[i] > 127);
        let car = truth.hole_count();
        assert!(found as f32 > 0.9 * car as f32, "found {found} of the car's {car}");
        let ring = dilate(&truth.map(|&v| v > 127), 6);
        let beside = count(&|i| m.as_slice()[i] > 127 && !ring.as_slice()[i] && own.as_slice()[i] > 127);
        assert!(beside < 60, "{beside} pixels of the views' own objects flagged in the keyframe");
    }

    /// A person pasted at `x` on the facade of `seed` (its shape drawn from `seed` too),
    /// found with three views of the
    /// facade at `hs`, each rendered and then changed by `change(i, view)`: the pixels of
    /// the mask on the person, those beside it, the person's size, and the pixels flagged
    /// on the clean facade as keyframe.
    fn person_found(
        seed: u64,
        x: f32,
        hs: &[Homography; 3],
        change: impl Fn(usize, &mut RgbF32),
    ) -> (usize, usize, usize, usize) {
        person_found_by(seed, x, hs, change, |key| key.clone())
    }

    /// [`person_found`] with the keyframe (and the clean facade as keyframe) taken through
    /// `as_key`.
    fn person_found_by(
        seed: u64,
        x: f32,
        hs: &[Homography; 3],
        change: impl Fn(usize, &mut RgbF32),
        as_key: impl Fn(&RgbF32) -> RgbF32,
    ) -> (usize, usize, usize, usize) {
        let (w, h) = (240, 180);
        let scene = facade(w, h, seed);
        let mut key = scene.clone();
        let mut truth = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut truth), Occluder::Person, x, 95.0, 90.0, seed % 8);
        let key = as_key(&key);
        let views: Vec<RgbF32> = hs
            .iter()
            .enumerate()
            .map(|(i, hm)| {
                let mut v = render_view(&scene, &hm.inverse().unwrap(), w, h, [0.5; 3]);
                change(i, &mut v);
                v
            })
            .collect();
        let sources: Vec<Source<'_>> =
            views.iter().zip(hs).map(|(v, &homography)| Source { image: v, homography }).collect();
        let m = auto_mask(&key, &sources, &AutoMaskParams::default());
        let (mut hit, mut false_pos) = (0, 0);
        for (&t, &p) in truth.as_slice().iter().zip(m.as_slice()) {
            hit += usize::from(t > 127 && p > 127);
            false_pos += usize::from(t <= 127 && p > 127);
        }
        let clean = auto_mask(&as_key(&scene), &sources, &AutoMaskParams::default()).hole_count();
        (hit, false_pos, truth.hole_count(), clean)
    }

    #[test]
    fn finds_a_pasted_person_and_not_the_facade() {
        let hs = [
            Homography::translation(6.5, -3.0),
            Homography::from_rows([[1.02, 0.01, -5.0], [-0.01, 0.99, 4.0], [1e-5, 0.0, 1.0]]).unwrap(),
            Homography::translation(-7.0, 2.5),
        ];
        // Views of the same facade, one of them darker and each with a tree elsewhere.
        let (hit, false_pos, person, clean) = person_found(11, 120.0, &hs, |i, v| {
            if i == 1 {
                crate::synth::expose(v, 0.8, 0.02);
            }
            paint_occluder(v, None, Occluder::Tree, 30.0 + 80.0 * i as f32, 40.0, 40.0, i as u64);
        });
        assert!(hit as f32 > 0.9 * person as f32, "found {hit} of {person}");
        // Allowed: the dilation ring around the person (≈ perimeter × 3), nothing else.
        assert!(false_pos < person, "{false_pos} false positives for a {person}-pixel person");
        // A keyframe equal to the scene: nothing is transient.
        assert!(clean < 240 * 180 / 200, "{clean} pixels flagged on a clean keyframe");
    }

    /// A black-and-white keyframe among colour views is judged by grey: the person is
    /// found, and a clean grey keyframe flags nothing. Compared by colour, every colour view
    /// disagreed with it everywhere; on hunt3 in grey with its four colour views not a pixel
    /// was found (in colour, eight objects).
    #[test]
    fn a_black_and_white_keyframe_is_judged_by_its_grey() {
        let hs = [
            Homography::translation(6.5, -3.0),
            Homography::from_rows([[1.02, 0.01, -5.0], [-0.01, 0.99, 4.0], [1e-5, 0.0, 1.0]]).unwrap(),
            Homography::translation(-7.0, 2.5),
        ];
        let grey = |img: &RgbF32| img.map(|&p| [luma(p); 3]);
        let (hit, false_pos, person, clean) = person_found_by(11, 120.0, &hs, |_, _| {}, grey);
        assert!(hit as f32 > 0.9 * person as f32, "found {hit} of {person}");
        assert!(false_pos < person, "{false_pos} false positives for a {person}-pixel person");
        assert!(clean < 240 * 180 / 200, "{clean} pixels flagged on a clean keyframe");
    }

    /// Oxford's leuven: the same facade as the light falls, each view darker than the last,
    /// through the camera's curve (gamma), not a line: a line fitted to the whole overlap
    /// leaves the shadows and highlights of the darkest views beyond the threshold, and the
    /// mask took walls, cars and the hedge for occluders (IoU 0.14–0.22 on the leuven
    /// service cases with four views).
    #[test]
    fn views_darkened_through_a_curve_flag_the_person_and_not_the_facade() {
        let hs = [
            Homography::translation(4.5, -2.0),
            Homography::translation(-5.0, 3.5),
            Homography::translation(2.0, 4.0),
        ];
        let (hit, false_pos, person, clean) = person_found(5, 110.0, &hs, |i, v| {
            let gamma = 1.8 + 0.6 * i as f32;
            *v = v.map(|p| p.map(|c| 0.9 * c.clamp(0.0, 1.0).powf(gamma)));
        });
        assert!(hit as f32 > 0.9 * person as f32, "found {hit} of {person}");
        // Allowed: the dilation ring around the person (with a line, 6 732 pixels).
        assert!(false_pos < person, "{false_pos} false positives for a {person}-pixel person");
        assert!(clean < 240 * 180 / 200, "{clean} pixels flagged on a clean keyframe");
    }

    /// Three views a few pixels off the keyframe each way, with their homographies (view →
    /// keyframe); `scene_at(i)` is the scene as view `i` saw it.
    fn nudged_views(w: usize, h: usize, scene_at: impl Fn(usize) -> RgbF32) -> Vec<(RgbF32, Homography)> {
        [
            Homography::translation(2.5, -1.0),
            Homography::translation(-3.0, 1.5),
            Homography::translation(1.0, 2.0),
        ]
        .into_iter()
        .enumerate()
        .map(|(i, hm)| (render_view(&scene_at(i), &hm.inverse().unwrap(), w, h, [0.5; 3]), hm))
        .collect()
    }

    fn sources_of(views: &[(RgbF32, Homography)]) -> Vec<Source<'_>> {
        views.iter().map(|(image, homography)| Source { image, homography: *homography }).collect()
    }

    /// The holes of `m` in `rows`.
    fn holes_in_rows(m: &Mask, rows: std::ops::Range<usize>) -> usize {
        rows.flat_map(|y| (0..m.width()).map(move |x| (x, y))).filter(|&(x, y)| m.is_hole(x, y)).count()
    }

    /// The pixels of `truth` that the mask `m` found.
    fn found_of(truth: &Mask, m: &Mask) -> usize {
        truth.as_slice().iter().zip(m.as_slice()).filter(|&(&t, &f)| t > 127 && f > 127).count()
    }

    /// More than 90 % of the occluders' pixels (`truth`) are in the mask `m`.
    fn assert_most_found(truth: &Mask, m: &Mask) {
        let (hit, objects) = (found_of(truth, m), truth.hole_count());
        assert!(hit as f32 > 0.9 * objects as f32, "found {hit} of the occluders' {objects} pixels");
    }

    /// A plain board of `colour` over `xs` × `ys` in the keyframe and in its truth.
    fn paint_board(
        key: &mut RgbF32,
        truth: &mut Mask,
        xs: std::ops::Range<usize>,
        ys: std::ops::Range<usize>,
        colour: [f32; 3],
    ) {
        for y in ys {
            for x in xs.clone() {
                key.set(x, y, colour);
                truth.set(x, y, 255);
            }
        }
    }

    /// A facade under a sky whose clouds drifted between the shots: the views, taken a
    /// moment apart, agree on a sky the keyframe (taken earlier) does not show. In front of
    /// the facade a passer-by and a glazed screen that reflects the sky (both the truth).
    fn under_drifting_clouds(params: &AutoMaskParams) -> (Mask, Mask, usize) {
        use rand::SeedableRng;
        let (w, h, sky_rows) = (240, 180, 64);
        let wall = facade(w, h, 11);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let clouds = crate::synth::value_noise(w + 160, sky_rows + 40, 28.0, 3, &mut rng);
        let scene_at = |t: f32| {
            RgbF32::from_fn(w, h, |x, y| {
                if y >= sky_rows {
                    return wall.get(x, y);
                }
                let c = 0.5 + 0.45 * clouds.get(x + (40.0 * t) as usize, y + (8.0 * t) as usize);
                [0.93 * c, 0.96 * c, c]
            })
        };
        let mut key = scene_at(0.0);
        let mut truth = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut truth), Occluder::Person, 150.0, 130.0, 80.0, 3);
        // A glazed screen just below the skyline, its panes reflecting the sky between dark
        // frames: its colours are the sky's, and an object grown by its colours reaches
        // into the sky.
        let sky_at = scene_at(1.5);
        for y in sky_rows..sky_rows + 38 {
            for x in 30..98 {
                let frame = (x - 30) % 12 < 2 || (y - sky_rows) % 12 < 2 || x >= 96 || y >= sky_rows + 36;
                key.set(x, y, if frame { [0.2, 0.22, 0.25] } else { sky_at.get(x, y - sky_rows) });
                truth.set(x, y, 255);
            }
        }
        let views = nudged_views(w, h, |i| scene_at(3.0 + 0.05 * i as f32));
        (auto_mask(&key, &sources_of(&views), params), truth, sky_rows)
    }

    #[test]
    fn drifting_clouds_are_not_an_occluder_and_what_stands_below_them_is() {
        let (m, truth, sky_rows) = under_drifting_clouds(&AutoMaskParams::default());
        let w = m.width();
        assert_most_found(&truth, &m);
        // The sky but its last rows, where the mask's blur and final growth
        // (`dilate_radius`) reach over the skyline from what stands against it.
        let above = sky_rows - 4;
        let sky = holes_in_rows(&m, 0..above);
        assert!(sky < w * above / 100, "{sky} of the {} sky pixels taken", w * above);
        // Without the sky looked for, the clouds the keyframe shows are taken: the case
        // tests the rule.
        let (m, _, _) =
            under_drifting_clouds(&AutoMaskParams { sky_gradient: 0.0, ..AutoMaskParams::default() });
        let sky = holes_in_rows(&m, 0..above);
        assert!(sky > w * above / 5, "only {sky} of the {} sky pixels taken without the rule", w * above);
    }

    /// A facade under a sky whose top is plain, then a rippled cloud bank across the whole
    /// width (too textured to be sky by its luminance's gradient), then bands of cloud along
    /// the horizon that sank 6 px between the keyframe and the views. Against the ripples a
    /// board of the sky's luminance but another hue, and a passer-by before the facade (both
    /// the truth). Returns the mask, the truth and the rows the bands take.
    fn under_a_rippled_cloud_bank(params: &AutoMaskParams) -> (Mask, Mask, std::ops::Range<usize>) {
        let (w, h, skyline) = (240, 180, 72);
        let wall = facade(w, h, 5);
        let scene_at = |sunk: f32| {
            RgbF32::from_fn(w, h, |x, y| {
                if y >= skyline {
                    return wall.get(x, y);
                }
                let (xf, yf) = (x as f32, y as f32);
                let mut c = 0.78;
                if (16..40).contains(&y) {
                    // Ripples 12 px apart, their crests slanting.
                    c += 0.067 * (std::f32::consts::TAU * (yf + 0.15 * xf) / 12.0).sin();
                }
                // Two soft grey bands, 6 px deep (σ) and 0.2 darker at their middle.
                for centre in [46.0, 62.0] {
                    c -= 0.2 * (-((yf - centre - sunk) / 6.0).powi(2) / 2.0).exp();
                }
                [0.94 * c, 0.97 * c, c]
            })
        };
        let mut key = scene_at(0.0);
        let mut truth = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut truth), Occluder::Person, 180.0, 140.0, 70.0, 3);
        // The board: luminance about the sky's, a warm hue against its blue-grey.
        paint_board(&mut key, &mut truth, 40..90, 20..36, [0.93, 0.74, 0.62]);
        let views = nudged_views(w, h, |_| scene_at(6.0));
        (auto_mask(&key, &sources_of(&views), params), truth, 40..skyline - 4)
    }

    #[test]
    fn bands_of_cloud_below_a_rippled_bank_are_sky_and_a_board_against_it_is_not() {
        let (m, truth, bands) = under_a_rippled_cloud_bank(&AutoMaskParams::default());
        let w = m.width();
        assert_most_found(&truth, &m);
        let band_pixels = w * bands.len();
        let in_bands = holes_in_rows(&m, bands.clone());
        assert!(in_bands < band_pixels / 50, "{in_bands} of the bands' {band_pixels} pixels taken");
        // Without the clouds looked for, the ripples cut the bands off from the sky and the
        // bands are taken: the case tests the rule. (The views asked one by one,
        // `shading_ncc`, see the same bands only darker and explain most of them too: left
        // out here, so that the rule is what is measured.)
        let (m, _, _) = under_a_rippled_cloud_bank(&AutoMaskParams {
            sky_cloud_gradient: 0.0,
            shading_ncc: 0.0,
            ..AutoMaskParams::default()
        });
        let in_bands = holes_in_rows(&m, bands);
        assert!(
            in_bands > band_pixels / 5,
            "only {in_bands} of the bands' {band_pixels} pixels taken without the rule"
        );
    }

    #[test]
    fn a_plain_pale_board_before_a_plain_pale_wall_reaching_the_top_is_not_sky() {
        // The assumption the sky rests on, broken: the frame's top is a plain rendered wall,
        // and a white board stands before it, its outline faint.
        let (w, h, top) = (240, 180, 64);
        let wall = facade(w, h, 11);
        let scene = RgbF32::from_fn(w, h, |x, y| if y < top { [0.86, 0.85, 0.82] } else { wall.get(x, y) });
        let mut key = scene.clone();
        let mut truth = Mask::new(w, h, 0);
        paint_board(&mut key, &mut truth, 60..140, 30..110, [0.92, 0.92, 0.93]);
        let views = nudged_views(w, h, |_| scene.clone());
        let sources = sources_of(&views);
        let found = |params: &AutoMaskParams| found_of(&truth, &auto_mask(&key, &sources, params));
        let board = truth.hole_count();
        let with_edges = found(&AutoMaskParams::default());
        assert!(with_edges as f32 > 0.9 * board as f32, "found {with_edges} of the board's {board} pixels");
        // Without the edge check the sky runs through the board's outline and takes it.
        let averaged_only = found(&AutoMaskParams { sky_edge: f32::INFINITY, ..AutoMaskParams::default() });
        assert!((averaged_only as f32) < 0.1 * board as f32, "found {averaged_only} without the edge check");
    }
}
