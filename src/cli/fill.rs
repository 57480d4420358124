//! `clearview fill`: the keyframe with its masked region re-inpainted from the other
//! views, a report of what came from where, and a progress bar on a terminal (edge layer).

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use clap::Args;
use image::DynamicImage;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use super::exit;
use super::load::{LoadError, load_image, load_mask, load_photo};
use super::save::{output_format, result_format, save_image, save_result};
use crate::align::{AlignParams, Frame, align};
use crate::geometry::{Homography, Rows};
use crate::imaging::convert::{
    MASK_MAX_GREY, crop_rgb8, luminance, mask_grey_share, mask_to_luma8, plane_to_luma8, to_luminance, to_rgb,
};
use crate::imaging::decode::DecodeLimits;
use crate::imaging::encode::{EncodeOptions, OutputSpace};
use crate::imaging::meta::{Metadata, Provenance};
use crate::imaging::{Mask, Rect, Rgb8, RgbF32};
use crate::inpaint::parallax::{SweepParams, ViewMatches};
use crate::inpaint::region::{footprint, into_crop};
use crate::inpaint::{
    AutoMaskParams, FillExtras, FillParams, Observer, Source, Stage, SurfacesReport, auto_mask_report,
    fill_swept, sweep_surfaces,
};
use crate::session::{NO_COLOUR, shows_the_keyframe, the_same_shot, without_colour};

/// Views decoded and aligned at the same time. JPEG decoding is sequential, so with two in
/// flight (and the keyframe decoded beside them) both cores stay busy; the alignment inside
/// is parallel already. At most this many decoded photographs are held at once.
const VIEWS_IN_FLIGHT: usize = 2;

/// Keyframe pixels kept around the mask for the fill's patches, local search, photometric
/// ring and blending.
const MARGIN: usize = 64;

#[derive(Debug, Args)]
pub struct FillArgs {
    /// The photograph to clear.
    #[arg(long)]
    pub keyframe: PathBuf,
    /// An 8-bit image the keyframe's size, > 127 meaning "fill", or `auto` to find the
    /// transient objects (people, cars) where the keyframe disagrees with the views.
    #[arg(long)]
    pub mask: String,
    /// Where to write the result (format from the extension: png, jpg, tif, webp). It keeps
    /// the keyframe's EXIF, XMP, IPTC and colour profile; PNG and TIFF are 16-bit when the
    /// keyframe is deeper than 8 bits.
    #[arg(long)]
    pub out: PathBuf,
    /// Quality of a JPEG or WebP result, 1 to 100. JPEG: 75 when not given. WebP: lossy at
    /// this quality; lossless when not given.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=100))]
    pub quality: Option<u8>,
    /// The result's colour space: `keyframe` (the keyframe's own, with its profile) or `srgb`.
    #[arg(long, default_value = "keyframe")]
    pub colour_space: OutputSpace,
    /// Also write a JSON report: per view the verdict and what it filled; time per stage.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// With `--mask auto`, write the mask that was found.
    #[arg(long)]
    pub save_mask: Option<PathBuf>,
    /// Also write the confidence map: 8-bit, the keyframe's size, 0 outside the mask, inside
    /// how sure the fill is that the pixel shows the building (>= 128: sure; below: the
    /// fallback invented it, the views disagree or may show an occluder there, a sharp edge
    /// there may be a fraction of a pixel off, the blend moved it far from what the views saw,
    /// or its view contradicts the keyframe around the mask near it).
    #[arg(long)]
    pub confidence: Option<PathBuf>,
    /// Also write the surface map: 8-bit, the keyframe's size, 0 outside the mask, inside 1
    /// where the pixel was filled through its view's wall and `2 + s` where through the
    /// report's surface `s` off the wall (`planes.surfaces[s]`).
    #[arg(long)]
    pub surfaces: Option<PathBuf>,
    /// Refuse images with more pixels than this (decompression bombs).
    #[arg(long, default_value_t = DecodeLimits::default().max_pixels)]
    pub max_pixels: u64,
    /// Seed for every random choice.
    #[arg(long, default_value_t = crate::DEFAULT_SEED)]
    pub seed: u64,
    /// Fill through each view's wall alone: do not sweep for the surfaces standing off the
    /// wall (balconies, pilasters, signs). By default they are swept, and each masked pixel
    /// is filled through the one the views agree on wherever the views back that fill better
    /// than the walls' alone; where the sweep finds surfaces that costs seconds
    /// (BENCHMARKS.md, "Parallax").
    #[arg(long)]
    pub no_planes: bool,
    /// The default; kept so that commands written when the sweep was opt-in still run.
    #[arg(long, hide = true, conflicts_with = "no_planes")]
    pub planes: bool,
    /// Other photographs of the scene.
    #[arg(required = true)]
    pub views: Vec<PathBuf>,
}

#[derive(Debug, Serialize)]
struct ViewReport {
    path: PathBuf,
    accepted: bool,
    reason: Option<String>,
    homography: Option<Rows>,
    inliers: usize,
    matches: usize,
    median_residual_px: Option<f64>,
    /// Masked pixels this view sees, and how many the result took from it.
    covered_pixels: usize,
    filled_pixels: usize,
    gain: Option<[f32; 3]>,
    offset: Option<[f32; 3]>,
    /// Whether a tone curve was applied before the gain (the view's response is not linear
    /// in the keyframe's).
    tone_curve: Option<bool>,
    /// The largest shift (keyframe pixels) that moved the view onto the keyframe around a
    /// hole, beyond its homography (0: none).
    local_shift_px: Option<f64>,
}

impl ViewReport {
    fn refused(path: &Path, reason: String) -> Self {
        Self {
            path: path.to_owned(),
            accepted: false,
            reason: Some(reason),
            homography: None,
            inliers: 0,
            matches: 0,
            median_residual_px: None,
            covered_pixels: 0,
            filled_pixels: 0,
            gain: None,
            offset: None,
            tone_curve: None,
            local_shift_px: None,
        }
    }
}

#[derive(Debug, Serialize)]
struct Report<'a> {
    keyframe: &'a Path,
    mask: &'a str,
    out: &'a Path,
    masked_pixels: usize,
    from_views_pixels: usize,
    fallback_pixels: usize,
    /// Pixels copied from a view that also took in the other views' colours there (the
    /// rings showed their errors independent: noise, reflections).
    fused_pixels: usize,
    share_from_views: f64,
    /// Masked pixels the fill is sure of (confidence >= 128), and their share.
    confident_pixels: usize,
    share_confident: f64,
    /// Share of the mask invented by the fallback or filled without confidence: what to
    /// look at.
    share_doubtful: f64,
    /// Mean confidence over the mask (0..=1).
    expected_quality: f64,
    /// With `--mask auto`: what was found and how sure it is.
    #[serde(skip_serializing_if = "Option::is_none")]
    auto_mask: Option<AutoMaskSummary>,
    /// Unless `--no-planes`: the surfaces off the wall the sweep found, whether the result
    /// was filled through them, and what each filled.
    #[serde(skip_serializing_if = "Option::is_none")]
    planes: Option<SurfacesReport>,
    views: Vec<ViewReport>,
    /// Wall time per stage, in order.
    timings_ms: Vec<(&'static str, f64)>,
}

/// How sure `--mask auto` is of the mask it found.
#[derive(Debug, Serialize)]
struct AutoMaskSummary {
    /// Connected objects in the mask.
    objects: usize,
    /// Share of the mask the views contradict directly; the rest was joined to those objects
    /// (weaker evidence, the object's own colours, closed gaps and holes).
    share_certain: f64,
    /// Share of the keyframe that enough agreeing views saw to judge: an occluder elsewhere
    /// cannot be found.
    share_judged: f64,
}

/// Times the stages and drives the progress bar.
struct Progress {
    bar: ProgressBar,
    stage: Option<(&'static str, Instant)>,
    timings: Vec<(&'static str, f64)>,
}

impl Progress {
    fn new() -> Self {
        let bar = if std::io::stderr().is_terminal() { ProgressBar::new(0) } else { ProgressBar::hidden() };
        bar.set_style(
            ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} {elapsed}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        Self { bar, stage: None, timings: Vec::new() }
    }

    fn begin(&mut self, name: &'static str, total: usize) {
        self.end();
        self.stage = Some((name, Instant::now()));
        self.bar.set_message(name);
        self.bar.set_length(total as u64);
        self.bar.set_position(0);
    }

    fn end(&mut self) {
        if let Some((name, start)) = self.stage.take() {
            self.timings.push((name, start.elapsed().as_secs_f64() * 1e3));
        }
    }

    fn finish(mut self) -> Vec<(&'static str, f64)> {
        self.end();
        self.bar.finish_and_clear();
        self.timings
    }
}

impl Observer for Progress {
    fn stage(&mut self, stage: Stage) {
        self.begin(stage.name(), 0);
    }

    fn progress(&mut self, done: usize, total: usize) {
        self.bar.set_length(total as u64);
        self.bar.set_position(done as u64);
    }
}

/// Marks an aligned view as not used, with the reason, and says so on stderr.
fn skip(report: &mut ViewReport, reason: &str) {
    eprintln!("clearview fill: {}: skipped: {reason}", report.path.display());
    report.accepted = false;
    report.reason = Some(reason.to_owned());
}

/// Why an output cannot be written where it is named, as far as its folder says: the folder
/// is missing or is not a folder. (Whether the folder lets us write is known only by
/// writing; the write reports it.)
fn unwritable_folder(path: &Path) -> Option<String> {
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    match std::fs::metadata(parent) {
        Ok(m) if m.is_dir() => None,
        Ok(_) => Some(format!("{} is not a folder", parent.display())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            Some(format!("the folder {} does not exist", parent.display()))
        }
        Err(e) => Some(format!("{}: {e}", parent.display())),
    }
}

/// A view that survived alignment: the part of it the fill needs, in 8 bits (a quarter of
/// the memory of `f32`; the fill reads it as `f32` where it samples it).
struct Aligned {
    crop: Rgb8,
    homography: Homography,
    report: usize,
}

impl Aligned {
    /// The view as the fill takes it.
    fn source(&self) -> Source<'_, [u8; 3]> {
        Source { image: &self.crop, homography: self.homography }
    }
}

pub fn run(args: &FillArgs) -> u8 {
    match try_run(args) {
        Ok(code) => code,
        Err((code, message)) => {
            eprintln!("clearview fill: {message}");
            code
        }
    }
}

fn try_run(args: &FillArgs) -> Result<u8, (u8, String)> {
    let usage = |m: String| (exit::USAGE, m);
    let failure = |m: String| (exit::FAILURE, m);
    result_format(&args.out).map_err(|e| usage(e.to_string()))?;
    for p in [&args.save_mask, &args.confidence, &args.surfaces].into_iter().flatten() {
        output_format(p).map_err(|e| usage(e.to_string()))?;
    }
    let auto = args.mask == "auto";
    if let (Some(p), false) = (&args.save_mask, auto) {
        return Err(usage(format!(
            "{}: --save-mask writes the mask --mask auto finds; the mask here is the file {}",
            p.display(),
            args.mask
        )));
    }
    let mut inputs: Vec<&Path> = vec![&args.keyframe];
    inputs.extend(args.views.iter().map(PathBuf::as_path));
    if !auto {
        inputs.push(Path::new(&args.mask));
    }
    let outputs = [&args.report, &args.save_mask, &args.confidence, &args.surfaces];
    for written in std::iter::once(&args.out).chain(outputs.into_iter().flatten()) {
        if inputs.iter().any(|i| same_file(i, written)) {
            return Err(usage(format!(
                "{}: is one of the inputs; refusing to overwrite it",
                written.display()
            )));
        }
        // Checked before the work, not after it: a fill at camera resolution takes seconds.
        if let Some(why) = unwritable_folder(written) {
            return Err(failure(format!("{}: cannot write: {why}", written.display())));
        }
    }

    let limits = DecodeLimits { max_pixels: args.max_pixels };
    let params = AlignParams { seed: args.seed, ..AlignParams::default() };
    let mut progress = Progress::new();

    progress.begin("decode", 1);
    // The views are decoded while the keyframe is; they wait for its frame to be aligned.
    let key_ready: OnceLock<Option<KeyInfo>> = OnceLock::new();
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let outcomes: Vec<OnceLock<ViewOutcome>> = args.views.iter().map(|_| OnceLock::new()).collect();
    let keyed = std::thread::scope(|s| {
        for _ in 0..VIEWS_IN_FLIGHT.min(args.views.len()) {
            let bar = progress.bar.clone();
            let (key_ready, next, done, outcomes) = (&key_ready, &next, &done, &outcomes);
            let (limits, params) = (&limits, &params);
            s.spawn(move || {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(path) = args.views.get(i) else { break };
                    let _span = tracing::info_span!("view", path = %path.display()).entered();
                    let decoded = decode_view(path, limits, params);
                    let Some(key) = key_ready.wait() else { break };
                    let outcome = match decoded {
                        Ok((img, frame)) => align_view(path, img, &frame, key, params),
                        Err(e) => ViewOutcome::unreadable(path, &e),
                    };
                    outcomes[i].set(outcome).ok().expect("each view is taken once");
                    bar.set_position(done.fetch_add(1, Ordering::Relaxed) as u64 + 1);
                }
            });
        }
        match load_key(args, auto, &limits, &params) {
            Ok((rgb, mask, info, meta)) => {
                key_ready.set(Some(info)).ok();
                progress.begin("align", args.views.len());
                progress.bar.set_position(done.load(Ordering::Relaxed) as u64);
                Ok((rgb, mask, meta))
            }
            Err(e) => {
                key_ready.set(None).ok();
                Err(e)
            }
        }
    });
    let (key_rgb, given_mask, key_meta) = keyed?;
    // The keyframe's alignment pyramid is not needed any more.
    drop(key_ready);

    let mut reports = Vec::with_capacity(args.views.len());
    let mut aligned: Vec<Aligned> = Vec::new();
    for cell in outcomes {
        let o = cell.into_inner().expect("every view was handled");
        if let Some(note) = &o.note {
            eprintln!("clearview fill: {note}");
        }
        if let Some((crop, homography)) = o.kept {
            aligned.push(Aligned { crop, homography, report: reports.len() });
        }
        reports.push(o.report);
    }

    // A black-and-white view of a colour keyframe has no colour to give: what it filled
    // would take one tint from the ring around the hole.
    aligned.retain(|a| {
        let grey = without_colour(&key_rgb, &a.crop);
        if grey {
            skip(&mut reports[a.report], NO_COLOUR);
        }
        !grey
    });
    // A view given twice (the same file, a copy of it, the same shot saved again as
    // another file) would witness its own errors twice: only the first is kept. Compared
    // over the mask, or over the whole frame when the mask is still to be found.
    let whole;
    let over = match &given_mask {
        Some(m) => m,
        None => {
            whole = Mask::new(key_rgb.width(), key_rgb.height(), 255);
            &whole
        }
    };
    let mut kept: Vec<Aligned> = Vec::with_capacity(aligned.len());
    for a in aligned {
        match kept.iter().find(|k| the_same_shot(over, (&k.homography, &k.crop), (&a.homography, &a.crop))) {
            Some(first) => {
                let first = reports[first.report].path.display().to_string();
                skip(
                    &mut reports[a.report],
                    &format!(
                        "the same picture as {first} (the same pixels, or the same shot saved again); it adds nothing"
                    ),
                );
            }
            None => kept.push(a),
        }
    }
    let mut aligned = kept;
    let (mask, auto): (Mask, Option<AutoMaskSummary>) = match given_mask {
        Some(m) => (m, None),
        None => {
            match aligned.len() {
                0 => eprintln!(
                    "clearview fill: --mask auto: the mask is what the views show otherwise than the keyframe, and 0 views aligned: nothing can be judged, the result is the keyframe (paint a mask, or add views)"
                ),
                1 => eprintln!(
                    "clearview fill: --mask auto: 1 view aligned: the mask is what it shows otherwise and nowhere near, where two views agreeing would be surer (check the mask with --save-mask, or add views)"
                ),
                _ => {}
            }
            progress.begin("auto mask", 0);
            let sources: Vec<Source<'_, [u8; 3]>> = aligned.iter().map(Aligned::source).collect();
            let mut found = auto_mask_report(&key_rgb, &sources, &AutoMaskParams::default());
            // A copy of the keyframe agrees with it everywhere and hides its occluders from
            // the consensus: the mask is found again without such views.
            let copies: Vec<bool> = aligned
                .iter()
                .map(|a| shows_the_keyframe(&key_rgb, &found.mask, &a.homography, &a.crop))
                .collect();
            if copies.contains(&true) {
                let rest: Vec<Source<'_, [u8; 3]>> =
                    sources.into_iter().zip(&copies).filter(|&(_, &c)| !c).map(|(s, _)| s).collect();
                found = auto_mask_report(&key_rgb, &rest, &AutoMaskParams::default());
            }
            if let Some(p) = &args.save_mask {
                save_image(p, &DynamicImage::ImageLuma8(mask_to_luma8(&found.mask)))
                    .map_err(|e| failure(e.to_string()))?;
            }
            let summary = AutoMaskSummary {
                objects: found.objects,
                share_certain: found.certain_share,
                share_judged: found.judged_share,
            };
            (found.mask, Some(summary))
        }
    };
    // A view that shows what the keyframe shows over the mask (the keyframe's own file
    // among the views, a shot from the same spot with the occluder where it was) can only
    // paint the occluder back: it is skipped, as the service turns it down.
    aligned.retain(|a| {
        let same = shows_the_keyframe(&key_rgb, &mask, &a.homography, &a.crop);
        if same {
            skip(
                &mut reports[a.report],
                "shows what the keyframe shows where the mask is (the same picture): it adds nothing",
            );
        }
        !same
    });
    let sources: Vec<Source<'_, [u8; 3]>> = aligned.iter().map(Aligned::source).collect();
    let sweep = !args.no_planes;
    let params = FillParams::default();
    let planes = if sweep {
        let mut memo = vec![ViewMatches::default(); sources.len()];
        sweep_surfaces(
            &luminance(&key_rgb),
            &mask,
            &sources,
            &SweepParams::default(),
            args.seed,
            &mut memo,
            &mut progress,
        )
    } else {
        Vec::new()
    };
    let swept = fill_swept(
        &key_rgb,
        &mask,
        &sources,
        &FillExtras::default(),
        &params,
        planes,
        args.seed,
        &mut progress,
    );
    let planes = swept.report(&mask, (0, 0));
    let surface_map = args.surfaces.is_some().then(|| swept.surface_map(&mask));
    let filled = swept.filled;
    for (a, s) in aligned.iter().zip(&filled.report.sources) {
        let r = &mut reports[a.report];
        r.covered_pixels = s.covered;
        r.filled_pixels = s.filled;
        r.gain = Some(s.gain);
        r.offset = Some(s.offset);
        r.tone_curve = Some(s.tone);
        r.local_shift_px = Some(s.shift_px);
    }

    progress.begin("write", 1);
    let provenance = Provenance {
        report: args.report.as_deref().map(|r| relative_to_result(r, &args.out)),
        views: reports
            .iter()
            .filter(|v| v.filled_pixels > 0)
            .map(|v| v.path.file_name().unwrap_or(v.path.as_os_str()).to_string_lossy().into_owned())
            .collect(),
    };
    let opts = EncodeOptions { quality: args.quality, space: args.colour_space };
    let left_out = save_result(&args.out, &filled.image, &opts, &key_meta, &provenance)
        .map_err(|e| failure(e.to_string()))?;
    for w in left_out {
        eprintln!("clearview fill: {}: {w}", args.out.display());
    }
    if let Some(p) = &args.confidence {
        save_image(p, &DynamicImage::ImageLuma8(plane_to_luma8(&filled.confidence)))
            .map_err(|e| failure(e.to_string()))?;
    }
    if let (Some(p), Some(map)) = (&args.surfaces, &surface_map) {
        save_image(p, &DynamicImage::ImageLuma8(plane_to_luma8(map))).map_err(|e| failure(e.to_string()))?;
    }
    let timings = progress.finish();

    let fr = &filled.report;
    let from_views = fr.sources.iter().map(|s| s.filled).sum::<usize>();
    let report = Report {
        keyframe: &args.keyframe,
        mask: &args.mask,
        out: &args.out,
        masked_pixels: fr.masked,
        from_views_pixels: from_views,
        fallback_pixels: fr.fallback,
        fused_pixels: fr.fused,
        share_from_views: fr.from_views(),
        confident_pixels: fr.confident,
        share_confident: fr.confident_share(),
        share_doubtful: fr.doubtful_share(),
        expected_quality: fr.expected_quality(),
        auto_mask: auto,
        planes: sweep.then_some(planes),
        views: reports,
        timings_ms: timings,
    };
    if let Some(p) = &args.report {
        let json = serde_json::to_vec_pretty(&report).expect("report serialises");
        super::save::write_atomic(p, &json).map_err(|e| failure(e.to_string()))?;
    }
    print_summary(&report);
    let accepted = report.views.iter().filter(|v| v.accepted).count();
    Ok(if accepted == 0 { exit::REJECTED } else { exit::OK })
}

/// How the result's XMP names the report: its file name when both are in one folder.
fn relative_to_result(report: &Path, out: &Path) -> String {
    let parent = |p: &Path| p.parent().map(|d| d.canonicalize().unwrap_or_else(|_| d.to_owned()));
    match report.file_name() {
        Some(name) if parent(report) == parent(out) => name.to_string_lossy().into_owned(),
        _ => report.display().to_string(),
    }
}

/// What the view workers need of the keyframe.
struct KeyInfo {
    frame: Frame,
    /// The keyframe region the fill works in (`None`: the mask is empty).
    region: Option<Rect>,
}

/// The keyframe in RGB, the given mask (checked against it), what the views need of it and
/// the metadata its result keeps.
#[allow(clippy::type_complexity)]
fn load_key(
    args: &FillArgs,
    auto: bool,
    limits: &DecodeLimits,
    params: &AlignParams,
) -> Result<(RgbF32, Option<Mask>, KeyInfo, Metadata), (u8, String)> {
    let failure = |m: String| (exit::FAILURE, m);
    let key = load_photo(&args.keyframe, limits).map_err(|e| failure(e.to_string()))?;
    let key_img = key.image;
    let (kw, kh) = (key_img.width() as usize, key_img.height() as usize);
    let given_mask = if auto {
        None
    } else {
        let path = Path::new(&args.mask);
        let m = load_mask(path, limits).map_err(|e| failure(e.to_string()))?;
        if (m.width(), m.height()) != (kw, kh) {
            return Err(failure(format!(
                "{}: the mask is {}x{} but the keyframe {} is {kw}x{kh}",
                path.display(),
                m.width(),
                m.height(),
                args.keyframe.display()
            )));
        }
        let grey = mask_grey_share(&m);
        if grey > MASK_MAX_GREY {
            return Err(failure(format!(
                "{}: not a mask: {:.0} % of its pixels are neither black nor white (a photograph?); a mask is white where to remove, black elsewhere",
                path.display(),
                100.0 * grey
            )));
        }
        if let Some(w) = m.mistake().or_else(|| m.inverted()) {
            eprintln!("clearview fill: {}: {w}", path.display());
        }
        Some(m)
    };
    let key_rgb = to_rgb(&key_img);
    // The keyframe region the fill works in; with an automatic mask, all of it.
    let region = match &given_mask {
        Some(m) => m.hole_bounds().map(|r| r.grown(MARGIN, kw, kh)),
        None => Some(Rect::full(kw, kh)),
    };
    let mut frame = Frame::new(to_luminance(&key_img), params);
    // What is under the mask is to be removed: its corners are not matched.
    frame.set_mask(given_mask.as_ref());
    Ok((key_rgb, given_mask, KeyInfo { frame, region }, key.meta))
}

/// One view's part of the result: its report line, the 8-bit crop of it the fill needs with
/// the homography into that crop (accepted views that see the region), and what to tell the
/// user about it.
struct ViewOutcome {
    report: ViewReport,
    kept: Option<(Rgb8, Homography)>,
    note: Option<String>,
}

impl ViewOutcome {
    /// A view that could not be read or decoded.
    fn unreadable(path: &Path, e: &LoadError) -> Self {
        Self {
            report: ViewReport::refused(path, e.to_string()),
            kept: None,
            note: Some(format!("{e}: skipped")),
        }
    }
}

/// Decodes a view and builds its alignment frame (the part that needs no keyframe).
fn decode_view(
    path: &Path,
    limits: &DecodeLimits,
    params: &AlignParams,
) -> Result<(DynamicImage, Frame), LoadError> {
    let img = load_image(path, limits)?;
    let frame = Frame::new(to_luminance(&img), params);
    Ok((img, frame))
}

/// Aligns a decoded view to the keyframe and, when it is accepted and sees the region, takes
/// the 8-bit crop the fill needs; the decoded image is dropped here.
fn align_view(
    path: &Path,
    img: DynamicImage,
    frame: &Frame,
    key: &KeyInfo,
    params: &AlignParams,
) -> ViewOutcome {
    let a = align(&key.frame, frame, params, None);
    let mut report = ViewReport {
        path: path.to_owned(),
        accepted: a.accepted(),
        reason: a.rejection.as_ref().map(ToString::to_string),
        homography: a.homography.as_ref().map(Rows::from),
        inliers: a.inliers,
        matches: a.matches,
        median_residual_px: a.median_residual_px.is_finite().then_some(a.median_residual_px),
        covered_pixels: 0,
        filled_pixels: 0,
        gain: None,
        offset: None,
        tone_curve: None,
        local_shift_px: None,
    };
    let (mut kept, mut note) = (None, None);
    match (&a.homography, &a.rejection, &key.region) {
        (Some(h), None, Some(region)) => {
            let (vw, vh) = (img.width() as usize, img.height() as usize);
            match footprint(region, h, vw, vh, 0) {
                Some(crop) => kept = Some((crop_rgb8(&img, crop), into_crop(h, &crop))),
                None => report.reason = Some("the view does not show the masked region".into()),
            }
        }
        (_, Some(r), _) => note = Some(format!("{}: rejected: {r}", path.display())),
        _ => {}
    }
    ViewOutcome { report, kept, note }
}

fn print_summary(r: &Report<'_>) {
    if r.masked_pixels == 0 {
        // No share of nothing is told: "100 % confident" would claim a fill that never was.
        println!("{}: no masked pixel: nothing filled, the result is the keyframe", r.out.display());
    } else {
        print_shares(r);
    }
    if let Some(a) = &r.auto_mask {
        println!(
            "  auto mask: {} object{}, {:.1} % of it contradicted by the views directly, the rest joined to it; {:.1} % of the keyframe could be judged",
            a.objects,
            if a.objects == 1 { "" } else { "s" },
            100.0 * a.share_certain,
            100.0 * a.share_judged
        );
    }
    if let Some(p) = r.planes.as_ref().filter(|_| r.masked_pixels > 0) {
        let filled: usize = p.surfaces.iter().map(|s| s.filled_pixels).sum();
        let n = p.surfaces.len();
        let found = format!("{n} surface{} off the wall found", if n == 1 { "" } else { "s" });
        if n == 0 {
            println!("  planes: no surface off the wall found; the wall's homography filled every pixel");
        } else if p.used {
            let kept = p.surfaces.iter().filter(|s| s.kept).count();
            let through = match (n, kept) {
                (1, _) => "it".to_string(),
                (n, k) if k == n => "them".to_string(),
                (_, k) => format!("the {k} of them the views back"),
            };
            println!("  planes: {found}, {filled} masked pixels filled through {through}");
        } else {
            println!("  planes: {found}, but the views back the wall's fill better: the result is that fill");
        }
    }
    for v in &r.views {
        match (&v.accepted, &v.reason) {
            (true, _) => println!(
                "  {}: accepted, {} inliers, filled {} of the {} masked pixels it sees",
                v.path.display(),
                v.inliers,
                v.filled_pixels,
                v.covered_pixels
            ),
            (false, Some(reason)) => println!("  {}: skipped: {reason}", v.path.display()),
            (false, None) => println!("  {}: skipped", v.path.display()),
        }
    }
    let stages: Vec<String> = r.timings_ms.iter().map(|(n, ms)| format!("{n} {ms:.0} ms")).collect();
    println!("  time: {}", stages.join(", "));
}

/// The summary's first line: the mask's shares. "From views" says where pixels came from,
/// not that they are right: the confident share comes first, and a doubtful share is always
/// told.
fn print_shares(r: &Report<'_>) {
    println!(
        "{}: {} masked pixels, {:.1} % confident, {:.1} % doubtful or invented ({:.1} % taken from views, {} from the single-image fallback)",
        r.out.display(),
        r.masked_pixels,
        100.0 * r.share_confident,
        100.0 * r.share_doubtful,
        100.0 * r.share_from_views,
        r.fallback_pixels
    );
}

/// Whether two paths name the same file (the second may not exist yet).
fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => a == b,
    }
}
