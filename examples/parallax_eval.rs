//! Issue 14's figures on generated non-planar facades (`synth::facade::parallax_case`):
//! masked PSNR against the truth of
//! - `today`: the walls' fill (`clearview fill --no-planes`: views aligned, one homography each);
//! - `reference`: the single-plane fill with the true wall homography and the views' true
//!   occluders (their pixels are never copied) — the reference;
//! - `planes`: the multi-plane fill (planes fitted from the matches the wall leaves out,
//!   each pixel's surface chosen by photo-consistency), from the same alignment as `today`;
//! - `swept`: the multi-plane fill with the surfaces swept densely (plane + parallax,
//!   `swept_planes`), from the same alignment;
//! - `true-planes`: the multi-plane fill given the true planes (an upper bound for the fit);
//! - `judged`: what `clearview fill` makes of the swept surfaces: the fill through them where
//!   the views back it better than the walls' alone, else the walls' ([`fill_swept`]). This is
//!   the product's figure; `swept` is the fill through the surfaces whatever the judge says.
//!
//!
//! With `--oracles`, a second table says where the swept fill loses against the true planes:
//! the same sweep given the true epipoles (in each view's own scale, tied by the sweep as
//! the estimated ones are; or already in one scale), the estimated epipoles with their scales
//! tied by the truth, the estimated epipoles with the views whose own epipole is wrong left
//! out, and the true slab planes on the estimated walls; and, per fill, the share of masked
//! pixels whose chosen surface is not the one the truth shows there.
//!
//! With `--epipoles`, a third table gives each view's epipole error, and in brackets what the
//! fit had to go on ([`epipole_support`]). `--true-walls` takes the true wall homographies
//! instead of the aligned ones; `--match-pixels` and `--sweep-pixels` set the resolutions the
//! guided matching and the sweep run at, `--search-radius` how far the guided matching
//! searches (pixels at half the matching resolution).
//!
//! `cargo run --release --example parallax_eval -- [--seeds N] [--first K] [--size WxH] [--views N] [--flat] [--true-walls] [--dump DIR] [--oracles] [--epipoles] [--split] [--no-refine] [--no-supported-ties] [--no-inside] [--no-rejoin] [--repair] [--no-across] [--match-pixels N] [--search-radius N] [--sweep-pixels N]`

use std::path::PathBuf;
use std::time::Instant;

#[path = "common/facades.rs"]
mod facades;
use facades::Facades;

use clearview::align::{AlignParams, Frame, align};
use clearview::geometry::Homography;
use clearview::geometry::planes::{ParallaxFamily, common_scales, epipolar_distance};
use clearview::imaging::RgbF32;
use clearview::imaging::convert::{luminance, to_rgb8};
use clearview::imaging::metrics::{Honesty, honesty, masked_psnr};
use clearview::inpaint::parallax::{
    SurfaceParams, SurfacePlane, SweepParams, matching_map, parallax_family, surface_planes, sweep_family,
    swept_planes, tied_family,
};
use clearview::inpaint::{FillExtras, FillParams, Filled, Observer, Source, Stage, fill_swept, fill_with};
use clearview::synth::facade::{ParallaxCase, parallax_case};

/// Milliseconds per stage.
#[derive(Default)]
struct Timer {
    at: Option<(Stage, Instant)>,
    ms: Vec<(Stage, f64)>,
}

impl Observer for Timer {
    fn stage(&mut self, stage: Stage) {
        self.end();
        self.at = Some((stage, Instant::now()));
    }
}

impl Timer {
    fn end(&mut self) {
        if let Some((s, t)) = self.at.take() {
            self.ms.push((s, t.elapsed().as_secs_f64() * 1e3));
        }
    }
}

/// The case's views, each with its homography of `hs`.
fn sources<'a>(c: &'a ParallaxCase, hs: &[Homography]) -> Vec<Source<'a>> {
    c.views.iter().zip(hs).map(|(image, &homography)| Source { image, homography }).collect()
}

fn run(
    c: &ParallaxCase,
    hs: &[Homography],
    extras: &FillExtras<'_>,
    params: &FillParams,
    t: &mut Timer,
) -> Filled {
    let f = fill_with(&c.key, &c.mask, &sources(c, hs), extras, params, 1, t);
    t.end();
    f
}

/// The fill `clearview fill` makes through `swept` on the walls `hs`: through the surfaces
/// where the views back that fill better than the walls' alone ([`fill_swept`]'s judge).
fn judged(
    c: &ParallaxCase,
    hs: &[Homography],
    swept: &[SurfacePlane],
    params: &FillParams,
    t: &mut Timer,
) -> Filled {
    let f =
        fill_swept(&c.key, &c.mask, &sources(c, hs), &FillExtras::default(), params, swept.to_vec(), 1, t)
            .filled;
    t.end();
    f
}

/// For each swept surface (stderr): its region, and the true plane nearest to it at the
/// region's centre (mean over views of the distance between where each puts the centre).
fn describe(c: &ParallaxCase, walls: &[Homography], swept: &[SurfacePlane]) {
    for (k, s) in swept.iter().enumerate() {
        let (r, p) = (s.region, centre(s));
        let err = |t: usize| distance_to_true(c, s, t);
        let shift: Vec<String> = s
            .views
            .iter()
            .zip(walls)
            .map(|(h, w)| {
                h.and_then(|h| Some(format!("{:.1}", (h.apply(p)? - w.apply(p)?).norm())))
                    .unwrap_or("-".into())
            })
            .collect();
        let truth = c.surface.get(p.x as usize, p.y as usize);
        let errs: Vec<String> = (0..c.planes[0].len()).map(|t| format!("{:.1}", err(t))).collect();
        eprintln!(
            "  swept {k}: region {}x{}+{}+{}, off the wall {} px, truth at centre {truth}, error per true plane [{}]",
            r.width,
            r.height,
            r.x,
            r.y,
            shift.join("/"),
            errs.join(", ")
        );
    }
}

/// How well the fitted plane + parallax family reproduces each true slab plane (stderr):
/// per view, the best γ at the slab's centre and the distance left there.
fn family_check(c: &ParallaxCase, walls: &[Homography], views: &[&clearview::imaging::GrayF32]) {
    let Some((fam, g)) = clearview::inpaint::parallax::parallax_family(
        &luminance(&c.key),
        views,
        walls,
        &c.mask,
        &SweepParams::default(),
        1,
    ) else {
        eprintln!("  no parallax found");
        return;
    };
    let t_inv = g.t.inverse().unwrap();
    eprintln!(
        "  matches per view {:?}, epipoles {:?}, observed γ {:?}",
        g.matches.iter().map(Vec::len).collect::<Vec<_>>(),
        fam.epipoles.iter().map(Option::is_some).collect::<Vec<_>>(),
        fam.observed.iter().map(Vec::len).collect::<Vec<_>>()
    );
    for p in 1..c.planes[0].len() {
        let (mut sx, mut sy, mut k) = (0.0, 0.0, 0.0);
        for (i, &l) in c.surface.as_slice().iter().enumerate() {
            if l as usize == p {
                sx += (i % c.key.width()) as f64;
                sy += (i / c.key.width()) as f64;
                k += 1.0;
            }
        }
        if k == 0.0 {
            continue;
        }
        let at = nalgebra::Point2::new(sx / k, sy / k);
        let mut out = Vec::new();
        for v in 0..walls.len() {
            let truth = c.planes[v][p].apply(at).unwrap();
            let best = (-400..=400)
                .filter_map(|i| {
                    let gm =
                        f64::from(i) * 0.0025 * fam.observed[v].iter().map(|g| g.abs()).fold(0.0, f64::max);
                    let h = t_inv.after(&fam.homography(v, gm)?).after(&g.t);
                    Some((gm, (h.apply(at)? - truth).norm()))
                })
                .min_by(|a, b| a.1.total_cmp(&b.1));
            out.push(best.map_or("-".into(), |(gm, e)| format!("γ {gm:.4} err {e:.2}")));
        }
        eprintln!("  slab {p} at {:.0},{:.0}: {}", at.x, at.y, out.join(" | "));
    }
}

/// One case's oracle figures: seed, masked PSNR per column, wrongly chosen share per
/// column, surfaces found per column.
type OracleRow = (u64, Vec<f64>, Vec<f64>, Vec<usize>);

/// The true plane + parallax family of a case in the coordinates of the guided matching
/// (`t`: full resolution → there), its walls the estimated ones (`walls`): per view the
/// epipole `λ·T·K·t` (`λ` the estimated wall matrix's scale against the true one) and the
/// slabs' true depths `1/z − 1/WALL`, one scale for all views.
fn true_family(c: &ParallaxCase, walls: &[Homography], t: &Homography) -> ParallaxFamily {
    use clearview::synth::facade::WALL;
    let tm = *t.matrix();
    let tm_inv = tm.try_inverse().expect("regular");
    let gammas: Vec<f64> = c.slabs.iter().map(|s| 1.0 / (WALL - s.depth) - 1.0 / WALL).collect();
    let mut mats = Vec::new();
    let mut epipoles = Vec::new();
    for (cam, wall) in c.cameras.iter().zip(walls) {
        let est = tm * wall.matrix() * tm_inv;
        let tv = -(cam.r * cam.c);
        let truth = tm
            * cam.k
            * (cam.r + tv * nalgebra::Vector3::new(0.0, 0.0, 1.0).transpose() / WALL)
            * c.key_camera.k.try_inverse().expect("regular")
            * tm_inv;
        let lambda = est.dot(&truth) / truth.norm_squared();
        mats.push(est);
        epipoles.push(Some(tm * cam.k * tv * lambda));
    }
    let observed = vec![gammas; walls.len()];
    ParallaxFamily { walls: mats, epipoles, observed }
}

/// Per view, `pool:fitted t true`: the guided matches the wall misses by a parallax the fit
/// considers, how many of them the fitted epipole took, and how many the true epipole would
/// take under the same line test: when the true one explains few of the pool, the matches
/// off the wall are not of the surfaces off it (repeats, not parallax), and no fit can find it.
fn epipole_support(
    c: &ParallaxCase,
    walls: &[Homography],
    t: &Homography,
    own: &ParallaxFamily,
    matches: &[Vec<clearview::geometry::Correspondence>],
    fit: &clearview::geometry::planes::ParallaxFitParams,
) -> String {
    let truth = true_family(c, walls, t);
    own.observed
        .iter()
        .enumerate()
        .map(|(v, fitted)| {
            let (m, e) = (truth.walls[v], truth.epipoles[v].expect("every view has its true epipole"));
            let wall = Homography::from_matrix(m).expect("regular");
            let pool: Vec<_> = matches[v]
                .iter()
                .filter(|c| (fit.min_parallax_px..=fit.max_parallax_px).contains(&c.residual(&wall)))
                .collect();
            let agree = pool.iter().filter(|c| epipolar_distance(c, &m, &e) < fit.line_px).count();
            format!("{}:{}t{agree}", pool.len(), fitted.len())
        })
        .collect::<Vec<_>>()
        .join("/")
}

/// How far a tied family's views are from the truth, per view (keyframe-scale pixels): per
/// true slab, the one `γ` (shared by all views, as the joint sweep takes it) that brings the
/// family closest to the slab's true homographies over the slab's pixels within 40 px of the
/// mask, then the mean distance there; per view, the mean over slabs weighted by their
/// pixels. `None` for a view the family left out.
fn epipole_errors(c: &ParallaxCase, t: &Homography, fam: &ParallaxFamily) -> Vec<Option<f64>> {
    let (w, h) = (c.key.width(), c.key.height());
    let t_inv = t.inverse().expect("regular");
    let near = clearview::inpaint::automask::dilate(
        &clearview::imaging::Plane::from_fn(w, h, |x, y| c.mask.is_hole(x, y)),
        40,
    );
    let nv = fam.epipoles.len();
    let (mut sum, mut weight) = (vec![0.0f64; nv], vec![0.0f64; nv]);
    let centre = t.apply(nalgebra::Point2::new(0.5 * w as f64, 0.5 * h as f64)).expect("affine");
    let rate = (0..nv).map(|v| fam.rate(v, centre)).fold(0.0f64, f64::max).max(1e-12);
    for p in 1..c.planes[0].len() {
        let pts: Vec<nalgebra::Point2<f64>> = (0..h)
            .step_by(3)
            .flat_map(|y| (0..w).step_by(3).map(move |x| (x, y)))
            .filter(|&(x, y)| c.surface.get(x, y) == p as u16 && near.get(x, y))
            .map(|(x, y)| nalgebra::Point2::new(x as f64, y as f64))
            .collect();
        if pts.len() < 10 {
            continue;
        }
        let per_view = |gamma: f64| -> Vec<Option<f64>> {
            (0..nv)
                .map(|v| {
                    let hm = t_inv.after(&fam.homography(v, gamma)?).after(t);
                    let d: f64 = pts
                        .iter()
                        .map(|&x| (hm.apply(x).unwrap() - c.planes[v][p].apply(x).unwrap()).norm())
                        .sum();
                    Some(d / pts.len() as f64)
                })
                .collect()
        };
        let total = |gamma: f64| per_view(gamma).iter().flatten().sum::<f64>();
        let mut best = (0.0, total(0.0));
        let mut step = 0.5 / rate;
        for pass in 0..4 {
            let c0 = best.0;
            let reach = if pass == 0 { 200 } else { 12 };
            for k in -reach..=reach {
                let g = c0 + f64::from(k) * step;
                let e = total(g);
                if e < best.1 {
                    best = (g, e);
                }
            }
            step /= 6.0;
        }
        for (v, d) in per_view(best.0).into_iter().enumerate() {
            if let Some(d) = d {
                sum[v] += d * pts.len() as f64;
                weight[v] += pts.len() as f64;
            }
        }
    }
    (0..nv).map(|v| (fam.epipoles[v].is_some() && weight[v] > 0.0).then(|| sum[v] / weight[v])).collect()
}

/// [`epipole_errors`] of each view alone (its own scale of `γ`).
fn epipole_errors_alone(c: &ParallaxCase, t: &Homography, fam: &ParallaxFamily) -> Vec<Option<f64>> {
    (0..fam.epipoles.len())
        .map(|v| {
            let mut one = fam.clone();
            for (u, e) in one.epipoles.iter_mut().enumerate() {
                if u != v {
                    *e = None;
                }
            }
            epipole_errors(c, t, &one)[v]
        })
        .collect()
}

/// Share of the masked pixels (not on a slab's side) whose chosen surface is not the true
/// one, given which true plane each chosen surface is (`None`: none).
fn wrong_choice(c: &ParallaxCase, f: &Filled, truth_of: &[Option<u16>]) -> f64 {
    let (mut bad, mut all) = (0usize, 0usize);
    for y in 0..c.key.height() {
        for x in 0..c.key.width() {
            let t = c.surface.get(x, y);
            if !c.mask.is_hole(x, y) || t == clearview::synth::facade::SIDE {
                continue;
            }
            all += 1;
            let s = f.surface.get(x, y) as usize;
            let chosen = if s == 0 { Some(0) } else { truth_of.get(s - 1).copied().flatten() };
            if chosen != Some(t) {
                bad += 1;
            }
        }
    }
    bad as f64 / all.max(1) as f64
}

/// The centre of a surface's region.
fn centre(s: &SurfacePlane) -> nalgebra::Point2<f64> {
    let r = s.region;
    nalgebra::Point2::new(r.x as f64 + 0.5 * r.width as f64, r.y as f64 + 0.5 * r.height as f64)
}

/// How far (pixels, mean over the views) a surface's homographies send its region's centre
/// from where true plane `t` does.
fn distance_to_true(c: &ParallaxCase, s: &SurfacePlane, t: usize) -> f64 {
    let p = centre(s);
    let d: Vec<f64> = s
        .views
        .iter()
        .zip(&c.planes)
        .filter_map(|(h, tp)| Some((h.as_ref()?.apply(p)? - tp[t].apply(p)?).norm()))
        .collect();
    d.iter().sum::<f64>() / d.len().max(1) as f64
}

/// Which true plane each surface is: the one nearest at its region's centre (mean over
/// views), if within 1.5 pixels.
fn identify(c: &ParallaxCase, surfaces: &[SurfacePlane]) -> Vec<Option<u16>> {
    surfaces
        .iter()
        .map(|s| {
            (0..c.planes[0].len())
                .map(|t| (t as u16, distance_to_true(c, s, t)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .filter(|b| b.1 < 1.5)
                .map(|b| b.0)
        })
        .collect()
}

/// Where the swept fill's error is (`--split`): per masked pixel, what the truth shows there
/// (wall, a slab, a slab's side) against what the fill chose (the wall, the surface that is
/// that slab, another surface, or none found for the slab), and whether the view the pixel
/// came from shows an occluder there (its own passer-by, or the tree, at the true surface's
/// place). Per category: share of pixels, share of the squared error, and the masked PSNR
/// the fill would have if those pixels were as in the true-planes fill (`better`).
const SPLIT: [&str; 9] = [
    "wall, wall",
    "wall, as a surface",
    "slab, its surface",
    "slab, wall (found)",
    "slab, wall (not found)",
    "slab, other surface",
    "side",
    "fallback",
    "view occluded there",
];

/// Per category of [`SPLIT`]: pixels, squared error of the fill, squared error of `better`.
type Split = Vec<(usize, f64, f64)>;

/// [`Split`] of `f` (the swept fill, from `swept`) against `better` (the true-planes fill).
fn split(c: &ParallaxCase, f: &Filled, swept: &[SurfacePlane], better: &Filled) -> Split {
    let truth_of = identify(c, swept);
    let mut out = vec![(0usize, 0.0f64, 0.0f64); SPLIT.len()];
    let se = |img: &clearview::imaging::RgbF32, x: usize, y: usize| -> f64 {
        let (a, b) = (img.get(x, y), c.truth.get(x, y));
        (0..3).map(|k| f64::from(a[k] - b[k]).powi(2)).sum()
    };
    for y in 0..c.key.height() {
        for x in 0..c.key.width() {
            if !c.mask.is_hole(x, y) {
                continue;
            }
            let t = c.surface.get(x, y);
            let s = f.surface.get(x, y) as usize;
            let chosen = if s == 0 { Some(0) } else { truth_of.get(s - 1).copied().flatten() };
            let prov = f.provenance.get(x, y);
            let occluded = t != clearview::synth::facade::SIDE
                && prov != clearview::inpaint::FALLBACK
                && prov != clearview::inpaint::KEYFRAME
                && {
                    let v = prov as usize - 1;
                    c.planes[v][t as usize].apply(nalgebra::Point2::new(x as f64, y as f64)).is_some_and(
                        |q| {
                            let (qx, qy) = (q.x.round(), q.y.round());
                            qx >= 0.0
                                && qy >= 0.0
                                && (qx as usize) < c.occluders[v].width()
                                && (qy as usize) < c.occluders[v].height()
                                && c.occluders[v].is_hole(qx as usize, qy as usize)
                        },
                    )
                };
            let k = if t == clearview::synth::facade::SIDE {
                6
            } else if prov == clearview::inpaint::FALLBACK {
                7
            } else if occluded {
                8
            } else if t == 0 {
                if s == 0 { 0 } else { 1 }
            } else if chosen == Some(t) {
                2
            } else if s == 0 {
                if truth_of.contains(&Some(t)) { 3 } else { 4 }
            } else {
                5
            };
            out[k].0 += 1;
            out[k].1 += se(&f.image, x, y);
            out[k].2 += se(&better.image, x, y);
        }
    }
    out
}

fn main() {
    // `RUST_LOG=clearview=debug` prints what the stages decided (the judge's gain among them).
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (mut facades, mut flat, mut dump) = (Facades::new(8, 3), false, None);
    let mut oracles = false;
    let mut true_walls = false;
    let mut epipoles = false;
    let mut splits: Vec<(u64, Split)> = Vec::new();
    let mut want_split = false;
    let mut geo_min: Option<usize> = None;
    let mut epipole_rows: Vec<String> = Vec::new();
    let mut sp = SweepParams::default();
    let mut oracle_rows: Vec<OracleRow> = Vec::new();
    let mut fp = FillParams::default();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            f if facades.read(f, &mut it) => {}
            "--flat" => flat = true,
            "--true-walls" => true_walls = true,
            "--oracles" => oracles = true,
            "--epipoles" => epipoles = true,
            "--split" => want_split = true,
            "--no-refine" => sp.refine_epipoles = false,
            "--no-supported-ties" => sp.supported_ties = false,
            "--no-inside" => sp.inside = false,
            "--no-rejoin" => sp.rejoin = false,
            "--repair" => sp.repair_ties = true,
            "--no-across" => sp.across_hole = false,
            "--no-common-ties" => sp.common_ties = false,
            "--match-pixels" => {
                sp.matching.max_pixels = it.next().and_then(|v| v.parse().ok()).expect("--match-pixels N")
            }
            "--search-radius" => {
                sp.matching.search_radius = it.next().and_then(|v| v.parse().ok()).expect("--search-radius N")
            }
            "--sweep-pixels" => {
                sp.max_pixels = it.next().and_then(|v| v.parse().ok()).expect("--sweep-pixels N")
            }
            // Only the `--epipoles` table's column of scales tied by the points alone.
            "--geo-min-common" => {
                geo_min = Some(it.next().and_then(|v| v.parse().ok()).expect("--geo-min-common N"))
            }
            "--min-band-votes" => {
                sp.min_band_votes = it.next().and_then(|v| v.parse().ok()).expect("--min-band-votes N")
            }
            "--penalty" => fp.parallax.penalty = it.next().and_then(|v| v.parse().ok()).expect("--penalty X"),
            "--bias" => fp.parallax.wall_bias = it.next().and_then(|v| v.parse().ok()).expect("--bias X"),
            "--truncate" => {
                fp.parallax.truncate = it.next().and_then(|v| v.parse().ok()).expect("--truncate X")
            }
            "--window" => fp.parallax.window = it.next().and_then(|v| v.parse().ok()).expect("--window N"),
            "--dump" => dump = Some(PathBuf::from(it.next().expect("--dump DIR"))),
            other => panic!("unknown argument {other}"),
        }
    }
    let Facades { seeds, width: w, height: h, views: n, .. } = facades;
    let geo_min_common = geo_min.unwrap_or(sp.min_common);
    let names = ["today", "reference", "planes", "swept", "true-planes", "judged"];
    let mut sums = [0.0f64; 6];
    let mut honest: [Honesty; 6] = Default::default();
    let mut stage_ms: Vec<(String, f64)> = Vec::new();
    println!("| seed | slabs | masked px | planes found | swept found | {} |", names.join(" | "));
    println!("|---:|---:|---:|---:|---:|{}", "---:|".repeat(names.len()));
    for seed in facades.seed_range() {
        let c = parallax_case(w, h, n, seed, flat);
        let params = AlignParams::default();
        let t0 = Instant::now();
        let kf = Frame::new(luminance(&c.key), &params);
        let frames: Vec<Frame> = c.views.iter().map(|v| Frame::new(luminance(v), &params)).collect();
        let walls: Vec<Homography> = if true_walls {
            c.wall()
        } else {
            frames.iter().map(|f| align(&kf, f, &params, None).homography.expect("aligned")).collect()
        };
        let align_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        let grays: Vec<_> = c.views.iter().map(luminance).collect();
        let refs: Vec<&_> = grays.iter().collect();
        let planes = surface_planes(&luminance(&c.key), &refs, &walls, &c.mask, &SurfaceParams::default(), 1);
        let fit_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = Instant::now();
        let swept = swept_planes(&luminance(&c.key), &refs, &walls, &c.mask, &sp, 1);
        let sweep_ms = t2.elapsed().as_secs_f64() * 1e3;
        if std::env::var_os("PARALLAX_DEBUG").is_some() {
            family_check(&c, &walls, &refs);
            describe(&c, &walls, &swept);
        }
        let true_planes = c.true_surfaces(24);
        let occ: Vec<Option<&clearview::imaging::Mask>> = c.occluders.iter().map(Some).collect();
        let mut timers: Vec<Timer> = (0..6).map(|_| Timer::default()).collect();
        let results = [
            run(&c, &walls, &FillExtras::default(), &fp, &mut timers[0]),
            run(&c, &c.wall(), &FillExtras { occluders: &occ, ..FillExtras::default() }, &fp, &mut timers[1]),
            run(&c, &walls, &FillExtras { planes: &planes, ..FillExtras::default() }, &fp, &mut timers[2]),
            run(&c, &walls, &FillExtras { planes: &swept, ..FillExtras::default() }, &fp, &mut timers[3]),
            run(
                &c,
                &c.wall(),
                &FillExtras { planes: &true_planes, ..FillExtras::default() },
                &fp,
                &mut timers[4],
            ),
            judged(&c, &walls, &swept, &fp, &mut timers[5]),
        ];
        let psnr: Vec<f64> = results.iter().map(|f| masked_psnr(&f.image, &c.truth, &c.mask)).collect();
        for (h, f) in honest.iter_mut().zip(&results) {
            h.add(&honesty(&f.image, &c.truth, &c.mask, &f.confidence));
        }
        if want_split {
            splits.push((seed, split(&c, &results[3], &swept, &results[4])));
        }
        if epipoles {
            // Per view, pixels off the true slab planes: the sparse epipoles (each view at its
            // own best depth), the tied ones the joint sweep runs on (one depth for all).
            let key_gray = luminance(&c.key);
            let t = matching_map(w, h, &sp.matching);
            let fmt = |e: &[Option<f64>]| {
                e.iter().map(|e| e.map_or("-".into(), |e| format!("{e:.2}"))).collect::<Vec<_>>().join(" / ")
            };
            let (sparse, tied) = match parallax_family(&key_gray, &refs, &walls, &c.mask, &sp, 1) {
                Some((own, g)) => {
                    // The scales tied geometrically, from the keyframe points every pair of
                    // views matched off the wall; the reference that ties the most views.
                    let geo =
                        common_scales(&own, &g.matches, &sp.epipoles, geo_min_common, sp.common_tolerance)
                            .into_iter()
                            .max_by_key(|k| {
                                (k.iter().flatten().count(), k.iter().flatten().map(|k| k.1).sum::<usize>())
                            })
                            .filter(|k| k.iter().flatten().count() >= 2)
                            .map_or("none".into(), |k| {
                                let f = own.scaled(&k.iter().map(|k| k.map(|k| k.0)).collect::<Vec<_>>());
                                format!(
                                    "{} ({})",
                                    fmt(&epipole_errors(&c, &t, &f)),
                                    k.iter()
                                        .map(|k| k.map_or("-".into(), |k| k.1.to_string()))
                                        .collect::<Vec<_>>()
                                        .join("/")
                                )
                            });
                    (
                        format!(
                            "{} [{}] | {geo}",
                            fmt(&epipole_errors_alone(&c, &t, &own)),
                            epipole_support(&c, &walls, &t, &own, &g.matches, &sp.epipoles),
                        ),
                        tied_family(&key_gray, &refs, &c.mask, &sp, &own, &g.matches, &t)
                            .map_or("none".into(), |f| fmt(&epipole_errors(&c, &t, &f))),
                    )
                }
                None => ("none | none".into(), "none".into()),
            };
            epipole_rows.push(format!(
                "| {seed} | {sparse} | {tied} | {:.2} | {:+.2} |",
                psnr[3],
                psnr[3] - psnr[0]
            ));
        }
        if oracles {
            let key_gray = luminance(&c.key);
            let t = matching_map(w, h, &sp.matching);
            let truth = true_family(&c, &walls, &t);
            let est = parallax_family(&key_gray, &refs, &walls, &c.mask, &sp, 1).map(|f| f.0);
            // Each view's true epipole in a scale of its own (unit norm): the sweep ties them.
            let untied = {
                let k: Vec<Option<f64>> = truth.epipoles.iter().map(|e| e.map(|e| 1.0 / e.norm())).collect();
                truth.scaled(&k)
            };
            // The estimated epipoles, each scaled to the true one's length along it.
            let est_tied = est.as_ref().map(|f| {
                let k: Vec<Option<f64>> = f
                    .epipoles
                    .iter()
                    .zip(&truth.epipoles)
                    .map(|(e, t)| Some(e.as_ref()?.dot(t.as_ref()?) / e.as_ref()?.norm_squared()))
                    .collect();
                let mut s = f.scaled(&k);
                s.observed = truth.observed.clone();
                s
            });
            let sweeps: Vec<Vec<SurfacePlane>> = vec![
                swept.clone(),
                est_tied.map_or_else(Vec::new, |f| {
                    sweep_family(&key_gray, &refs, &c.mask, &sp, &f, &[], &t, true)
                }),
                sweep_family(&key_gray, &refs, &c.mask, &sp, &untied, &[], &t, false),
                sweep_family(&key_gray, &refs, &c.mask, &sp, &truth, &[], &t, true),
                true_planes.clone(),
            ];
            // The true family's surfaces, each given the true plane it is (the regions the
            // sweep found, the depths exact); the true slabs allowed everywhere.
            let snapped: Vec<SurfacePlane> = sweeps[3]
                .iter()
                .zip(identify(&c, &sweeps[3]))
                .filter_map(|(s, t)| {
                    let t = usize::from(t.filter(|&t| t > 0)?);
                    Some(SurfacePlane {
                        views: c.planes.iter().map(|v| Some(v[t])).collect(),
                        region: s.region,
                    })
                })
                .collect();
            let everywhere: Vec<SurfacePlane> = true_planes
                .iter()
                .map(|s| SurfacePlane {
                    views: s.views.clone(),
                    region: clearview::imaging::Rect::from_corners(0, 0, w, h),
                })
                .collect();
            let anywhere = |s: &[SurfacePlane]| -> Vec<SurfacePlane> {
                s.iter()
                    .map(|s| SurfacePlane {
                        views: s.views.clone(),
                        region: clearview::imaging::Rect::from_corners(0, 0, w, h),
                    })
                    .collect()
            };
            let (swept_any, tied_any) = (anywhere(&sweeps[0]), anywhere(&sweeps[3]));
            // The estimated family with each view whose own epipole is more than 1.5 px off
            // the true slabs left out: what a check that knew a wrong epipole would give.
            let dropped =
                parallax_family(&key_gray, &refs, &walls, &c.mask, &sp, 1).map_or_else(Vec::new, |(f, g)| {
                    let errors = epipole_errors_alone(&c, &t, &f);
                    let mut kept = f.clone();
                    for (e, err) in kept.epipoles.iter_mut().zip(&errors) {
                        if err.is_none_or(|d| d > 1.5) {
                            *e = None;
                        }
                    }
                    if kept.epipoles.iter().all(Option::is_none) {
                        return Vec::new();
                    }
                    sweep_family(&key_gray, &refs, &c.mask, &sp, &kept, &g.matches, &t, false)
                });
            let sweeps: Vec<Vec<SurfacePlane>> =
                sweeps.into_iter().chain([snapped, everywhere, swept_any, tied_any, dropped]).collect();
            let mut p = Vec::new();
            let mut wrong = Vec::new();
            let mut found = Vec::new();
            for (k, s) in sweeps.iter().enumerate() {
                let f = if k == 0 {
                    results[3].clone()
                } else {
                    run(
                        &c,
                        &walls,
                        &FillExtras { planes: s, ..FillExtras::default() },
                        &fp,
                        &mut Timer::default(),
                    )
                };
                p.push(masked_psnr(&f.image, &c.truth, &c.mask));
                wrong.push(wrong_choice(&c, &f, &identify(&c, s)));
                found.push(s.len());
            }
            p.push(psnr[4]);
            wrong.push(wrong_choice(&c, &results[4], &identify(&c, &true_planes)));
            oracle_rows.push((seed, p, wrong, found));
        }
        for (s, p) in sums.iter_mut().zip(&psnr) {
            *s += p;
        }
        stage_ms.push(("align".into(), align_ms));
        stage_ms.push(("plane fit".into(), fit_ms));
        stage_ms.push(("plane sweep".into(), sweep_ms));
        for (s, ms) in &timers[3].ms {
            stage_ms.push((format!("fill: {}", s.name()), *ms));
        }
        println!(
            "| {seed} | {} | {} | {} | {} | {} |",
            c.slabs.len(),
            c.mask.hole_count(),
            planes.len(),
            swept.len(),
            psnr.iter().map(|p| format!("{p:.2}")).collect::<Vec<_>>().join(" | ")
        );
        if let Some(d) = &dump {
            std::fs::create_dir_all(d).unwrap();
            let tag = format!("{}-{seed}", if flat { "flat" } else { "parallax" });
            to_rgb8(&c.truth).save(d.join(format!("{tag}-truth.png"))).unwrap();
            to_rgb8(&c.key).save(d.join(format!("{tag}-key.png"))).unwrap();
            for (name, f) in names.iter().zip(&results) {
                to_rgb8(&f.image).save(d.join(format!("{tag}-{name}.png"))).unwrap();
            }
            // The surfaces the multi-plane fill chose (grey: keyframe; colours: planes).
            let pal = [
                [0.2, 0.2, 0.8],
                [0.9, 0.3, 0.2],
                [0.2, 0.8, 0.2],
                [0.9, 0.8, 0.1],
                [0.7, 0.2, 0.8],
                [0.1, 0.8, 0.8],
                [1.0, 1.0, 1.0],
            ];
            for (name, r) in [("planes", &results[2]), ("swept", &results[3]), ("true-planes", &results[4])] {
                let map = RgbF32::from_fn(w, h, |x, y| {
                    if c.mask.is_hole(x, y) {
                        pal[(r.surface.get(x, y) as usize).min(6)]
                    } else {
                        c.key.get(x, y).map(|v| 0.3 * v)
                    }
                });
                to_rgb8(&map).save(d.join(format!("{tag}-{name}-surfaces.png"))).unwrap();
            }
            let truth_map = RgbF32::from_fn(w, h, |x, y| {
                let s = c.surface.get(x, y);
                if s == clearview::synth::facade::SIDE { [0.5; 3] } else { pal[(s as usize).min(6)] }
            });
            to_rgb8(&truth_map).save(d.join(format!("{tag}-truth-surfaces.png"))).unwrap();
        }
    }
    let k = seeds as f64;
    println!(
        "| **mean** | | | | | {} |",
        sums.iter().map(|s| format!("{:.2}", s / k)).collect::<Vec<_>>().join(" | ")
    );
    println!("\nhonesty over all seeds (confident share | confident error rate | flagged recall):");
    println!("| {} |", names.join(" | "));
    println!("|{}", "---|".repeat(names.len()));
    let cells: Vec<String> = honest
        .iter()
        .map(|h| {
            format!(
                "{:.3} / {:.3} / {:.3}",
                h.confident as f64 / h.masked.max(1) as f64,
                h.confident_error_rate(),
                h.flagged_recall()
            )
        })
        .collect();
    println!("| {} |", cells.join(" | "));
    if epipoles {
        println!("\nepipole error, px off the true slab planes near the mask, per view:");
        println!(
            "| seed | sparse (own depth each) [pool:fitted t true] | geometric tie (common points) | tied (one depth) | swept dB | swept − today |"
        );
        println!("|---:|---|---|---:|---:|");
        for r in &epipole_rows {
            println!("{r}");
        }
    }
    if want_split {
        // Per category: share of masked pixels, of the swept fill's squared error, and the
        // masked PSNR gained (mean over cases) were those pixels as in the true-planes fill.
        println!(
            "\nwhere the swept fill's error is (truth, chosen): share of masked px, of the squared \
             error, and dB gained were those pixels as in the true-planes fill (mean; per seed)"
        );
        let seeds_row: Vec<String> = splits.iter().map(|s| s.0.to_string()).collect();
        println!("| category | px % | error % | dB | {} |", seeds_row.join(" | "));
        println!("|---|---:|---:|---:|{}", "---:|".repeat(splits.len()));
        let k = splits.len().max(1) as f64;
        for (i, name) in SPLIT.iter().enumerate() {
            let (mut px, mut err) = (0.0, 0.0);
            let gains: Vec<f64> = splits
                .iter()
                .map(|(_, cats)| {
                    let n: usize = cats.iter().map(|c| c.0).sum();
                    let total: f64 = cats.iter().map(|c| c.1).sum();
                    let psnr = |se: f64| 10.0 * (3.0 * n as f64 / se.max(1e-12)).log10();
                    px += cats[i].0 as f64 / n.max(1) as f64;
                    err += cats[i].1 / total.max(1e-12);
                    psnr(total - cats[i].1 + cats[i].2) - psnr(total)
                })
                .collect();
            println!(
                "| {name} | {:.1} | {:.1} | {:+.2} | {} |",
                100.0 * px / k,
                100.0 * err / k,
                gains.iter().sum::<f64>() / k,
                gains.iter().map(|g| format!("{g:+.2}")).collect::<Vec<_>>().join(" | ")
            );
        }
    }
    if oracles {
        let cols = [
            "swept",
            "est. E, scales*",
            "E* untied",
            "E* tied",
            "true slabs, est. wall",
            "E* tied, depths*",
            "true slabs anywhere",
            "swept anywhere",
            "E* tied anywhere",
            "est. E, wrong ones out",
            "true planes",
        ];
        println!("\nmasked PSNR dB (surfaces found | wrongly chosen masked pixels %):");
        println!("| seed | {} |", cols.join(" | "));
        println!("|---:|{}", "---:|".repeat(cols.len()));
        let mut sums = vec![0.0; cols.len()];
        for (seed, p, wrong, found) in &oracle_rows {
            let cells: Vec<String> = (0..cols.len())
                .map(|k| {
                    sums[k] += p[k];
                    let n = found.get(k).map_or(String::new(), |n| format!("{n} | "));
                    format!("{:.2} ({n}{:.0})", p[k], 100.0 * wrong[k])
                })
                .collect();
            println!("| {seed} | {} |", cells.join(" | "));
        }
        println!(
            "| **mean** | {} |",
            sums.iter().map(|s| format!("{:.2}", s / k)).collect::<Vec<_>>().join(" | ")
        );
    }
    // Median cost per stage over the cases.
    let mut keys: Vec<String> = stage_ms.iter().map(|(s, _)| s.clone()).collect();
    keys.dedup();
    let mut seen = std::collections::BTreeSet::new();
    println!("\nmedian ms per stage (multi-plane fill, {w}x{h}, {n} views):");
    for key in keys {
        if !seen.insert(key.clone()) {
            continue;
        }
        let mut v: Vec<f64> = stage_ms.iter().filter(|(s, _)| *s == key).map(|(_, m)| *m).collect();
        v.sort_by(f64::total_cmp);
        println!("  {key}: {:.1}", v[v.len() / 2]);
    }
}
