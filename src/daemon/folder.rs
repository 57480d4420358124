//! The folder source (shell layer): what a decoded file of a session folder does to its
//! session. [`super::policy`] says what the file is (keyframe, mask, view); this module
//! reads what else it needs from the folder (the keyframe's mask, a view to align again),
//! aligns views, and hands everything to the session engine ([`super::engine::Slot`]).
//! It runs on the worker thread that owns the session ([`super::worker`]).

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Instant;

use image::DynamicImage;

use super::engine::{Ctx, MaskOrigin, Offer, Slot, rgb8};
use super::event::{Event, FileSkipped};
use super::job::{DecodeOutcome, FileId, ViewId};
use super::paths::Inbox;
use super::policy::{self, KeyNow, KeySource, Listing, MaskFit};
use super::watch::{self, Role};
use crate::config::MaskRule;
use crate::imaging::convert::{to_luminance, to_mask};
use crate::imaging::decode::DecodeLimits;

/// The regular files of the session's folder, by name.
pub(super) fn listing(ctx: &Ctx, dir: &Path) -> Listing {
    let names = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .flatten()
                .filter(|e| e.path().is_file())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    Listing::new(names, &ctx.config.extensions)
}

/// The keyframe as the policy sees it.
fn key_now(slot: &Slot) -> (Option<String>, Option<KeySource>, Option<String>) {
    (slot.key_name(), slot.key_source, slot.state.key_file.clone())
}

/// What a decoded file of role `role` does to its session, or its deletion (`image`
/// `None`: a mask deleted, a view deleted or replaced by what cannot be used). The one
/// dispatch of the folder's worker threads and the NATS workers.
pub(super) fn apply(
    ctx: &Ctx,
    slot: &mut Slot,
    role: Role,
    file: &FileId,
    path: &Path,
    image: Option<&DynamicImage>,
) {
    let Some(image) = image else {
        match role {
            Role::Mask => mask_removed(ctx, slot, file),
            _ => view_gone(ctx, slot, &file.name, path),
        }
        return;
    };
    if role == Role::View {
        ctx.registry.metrics.views_received.fetch_add(1, Ordering::Relaxed);
    }
    match role {
        Role::Key => take_key(ctx, slot, file, path, image, KeySource::NamedKey),
        Role::Mask => take_mask(ctx, slot, file, image),
        Role::View => take_image(ctx, slot, file, path, image),
    }
}

/// A new image (not a mask) of the session: the keyframe, a view, or a view that waits
/// for the keyframe.
pub(super) fn take_image(ctx: &Ctx, slot: &mut Slot, file: &FileId, path: &Path, image: &DynamicImage) {
    let l = listing(ctx, &slot.dir);
    let (current, source, saved) = key_now(slot);
    let key = KeyNow { current: current.as_deref().zip(source), saved: saved.as_deref() };
    match policy::key_source_for(&ctx.config.keyframe, &l, key, &file.name) {
        Some(source) => take_key(ctx, slot, file, path, image, source),
        None if slot.session.key_id().is_none() => {
            tracing::info!(file = %watch::shown(&file.name), "waiting for the keyframe");
            let reason = "no keyframe yet: it is aligned when the keyframe arrives".to_owned();
            ctx.emitter.emit(Some(&slot.name), &Event::ViewWaiting { file: file.name.clone(), reason });
            slot.parked.insert(file.name.clone(), path.to_owned());
        }
        None => process_view(ctx, slot, file, path, image),
    }
}

/// Makes `image` the keyframe; views parked, buffered or refused against the old one
/// (and the old keyframe, if it was an ordinary image) are aligned again, and the new
/// keyframe's mask is read from beside it.
pub(super) fn take_key(
    ctx: &Ctx,
    slot: &mut Slot,
    file: &FileId,
    path: &Path,
    image: &DynamicImage,
    source: KeySource,
) {
    let id = file.view_id(image);
    if slot.session.key_id() == Some(id.as_str()) {
        return;
    }
    let old = slot.key_path.clone();
    // Views rejected against the old keyframe may well match the new one.
    let refused: Vec<PathBuf> =
        slot.refused_views().into_iter().map(|n| slot.dir.join(n)).filter(|p| p.is_file()).collect();
    // A session rebuilt from disk (a restart, a wake, a cluster rebuild) takes back at
    // once every view whose alignment to this keyframe is saved, before it can fill: a
    // fill of some of them would publish a worse result over the saved one.
    let restored =
        if slot.session.key_id().is_none() { saved_views(ctx, slot, &id, path) } else { Vec::new() };
    let mut again = slot.set_key(ctx, id, path.to_owned(), image, source, None);
    if let Some(old) = old
        && old != path
        && watch::classify(&ctx.config.watch_dir, &old, &ctx.config.extensions)
            .is_some_and(|c| c.role == Role::View)
    {
        // The previous keyframe was an ordinary image: it is a view now.
        again.push(old);
    }
    again.extend(std::mem::take(&mut slot.parked).into_values());
    again.extend(refused);
    again.extend(restored);
    again.retain(|p| p != path);
    again.sort();
    again.dedup();
    if slot.state.key_file.as_deref() != Some(&file.name) {
        slot.state.key_file = Some(file.name.clone());
        slot.state_dirty = true;
    }
    let (w, h) = (image.width(), image.height());
    tracing::info!(key = %watch::shown(&file.name), width = w, height = h, views = again.len(), "keyframe set");
    if let Some(mask) = listing(ctx, &slot.dir).mask_for(&file.name) {
        let mask_path = slot.dir.join(mask);
        match load(ctx, &mask_path, Role::Mask) {
            Ok((f, img)) => apply_mask(ctx, slot, &f, &img),
            Err(e) => skip(ctx, slot, &mask_path, &e.reason()),
        }
    }
    say_waiting(ctx, slot);
    for p in again {
        reprocess(ctx, slot, &p);
    }
    auto_mask(ctx, slot);
}

/// The session folder's views (other than `key_path`) whose alignment to keyframe `key`
/// is saved in the state, as their files are now (name, size and time unchanged).
fn saved_views(ctx: &Ctx, slot: &Slot, key: &ViewId, key_path: &Path) -> Vec<PathBuf> {
    if slot.state.alignments.is_empty() {
        return Vec::new();
    }
    watch::scan(&slot.dir, ctx.config.follow_symlinks)
        .into_iter()
        .filter(|p| p != key_path)
        .filter(|p| {
            watch::classify(&ctx.config.watch_dir, p, &ctx.config.extensions)
                .is_some_and(|c| c.role == Role::View)
        })
        .filter(|p| {
            FileId::of(p).is_ok_and(|f| slot.state.has_alignment_for(&format!("{}|", f.id()), key.as_str()))
        })
        .collect()
}

/// A keyframe without a mask (and no automatic mask configured) makes no result: said
/// once per keyframe (event `session_waiting`, naming the files it waits for).
fn say_waiting(ctx: &Ctx, slot: &mut Slot) {
    if slot.waiting_said || slot.session.mask_id().is_some() || !matches!(ctx.config.mask, MaskRule::File) {
        return;
    }
    let Some(key) = slot.key_name() else { return };
    let expected = watch::mask_names(watch::stem(&key), &["png".to_owned()]);
    let reason = format!(
        "waiting for a mask of the keyframe {key}: {} or mask.png beside it (white = remove), or paint one on the preview page",
        expected.join(", ")
    );
    tracing::info!(keyframe = %watch::shown(&key), "session waiting for a mask");
    let e = Event::SessionWaiting { keyframe: key, waiting_for: "mask".into(), expected, reason };
    ctx.emitter.emit(Some(&slot.name), &e);
    slot.waiting_said = true;
}

/// A mask file arrived (or changed).
pub(super) fn take_mask(ctx: &Ctx, slot: &mut Slot, file: &FileId, image: &DynamicImage) {
    let l = listing(ctx, &slot.dir);
    let (current, source, saved) = key_now(slot);
    let key = KeyNow { current: current.as_deref().zip(source), saved: saved.as_deref() };
    // A mask names its image: that image is the keyframe unless one was named more
    // strongly (`key.*`, the configuration), whatever the order the files landed in.
    if let Some(image_name) = policy::key_named_by_mask(&ctx.config.keyframe, &l, key, &file.name) {
        let image_path = slot.dir.join(image_name);
        if let Ok((f, img)) = load(ctx, &image_path, Role::View) {
            tracing::info!(mask = %watch::shown(&file.name), key = %watch::shown(&f.name), "the mask names its image: it is the keyframe");
            // take_key finds and applies this mask.
            take_key(ctx, slot, &f, &image_path, &img, KeySource::Masked);
            return;
        }
    }
    let Some(key_name) = current else {
        tracing::debug!(mask = %file.name, "mask waits for its keyframe");
        return;
    };
    match policy::mask_fit(&l, &key_name, &file.name) {
        MaskFit::Applies => apply_mask(ctx, slot, file, image),
        MaskFit::OtherImage(owner) => skip(
            ctx,
            slot,
            &slot.dir.join(&file.name),
            &format!("a mask for another image ({owner}) than the keyframe {key_name}"),
        ),
        MaskFit::Shadowed => tracing::info!(mask = %file.name, "ignored: the keyframe has a mask of its own"),
    }
}

fn apply_mask(ctx: &Ctx, slot: &mut Slot, file: &FileId, image: &DynamicImage) {
    let id = String::from(file.view_id(image));
    if slot.session.mask_id() == Some(id.as_str()) {
        return;
    }
    if slot.refused_mask.as_deref() == Some(id.as_str()) {
        tracing::debug!(mask = %watch::shown(&file.name), "refused already for this keyframe");
        return;
    }
    if let Err(reason) =
        set_mask_and_retake(ctx, slot, id.clone(), to_mask(image), MaskOrigin::File(&file.name))
    {
        skip(ctx, slot, &slot.dir.join(&file.name), &reason);
        slot.refused_mask = Some(id);
    }
}

/// The mask file `file` was deleted. If it was the session's mask, the session forgets
/// it: no new result until a mask arrives; the last result stays as it is.
pub(super) fn mask_removed(ctx: &Ctx, slot: &mut Slot, file: &FileId) {
    let key_name = slot.key_name();
    let current = slot.mask_is_file(&file.name);
    // A session rebuilt from disk since (put to sleep and woken) no longer has it.
    let was_its = key_name.as_deref().is_some_and(|k| {
        let owner = watch::mask_owner(watch::stem(&file.name));
        slot.session.mask_id().is_none() && (owner == Some("") || owner == Some(watch::stem(k)))
    });
    if !current && !was_its {
        tracing::debug!(mask = %watch::shown(&file.name), "a mask that was not in use was deleted");
        return;
    }
    slot.clear_mask(ctx, &file.name, current);
    // Another mask beside the keyframe (`mask.<ext>`) takes over.
    if let Some(k) = &key_name
        && let Some(other) = listing(ctx, &slot.dir).mask_for(k)
        && let Ok((f, img)) = load(ctx, &slot.dir.join(other), Role::Mask)
    {
        apply_mask(ctx, slot, &f, &img);
    }
}

/// The most views an automatic mask is found from in a folder session.
const AUTO_MASK_MAX_VIEWS: usize = 8;

/// With `mask = "auto"`: once `auto_mask_views` views are accepted, the mask from their
/// consensus; then found again from all the accepted views each time their number doubles,
/// up to [`AUTO_MASK_MAX_VIEWS`]. Two views say little where they disagree: one shows a
/// passer-by of the keyframe's who had not moved, the other the wall behind him (or each
/// has an occluder of its own there); he stays unmasked until more views agree on the
/// wall. A mask found again with the same pixels changes nothing; a changed one is set as a
/// new mask is (`mask_set`, every buffered view taken again, a new result). A mask from a
/// file is the user's, and stays.
fn auto_mask(ctx: &Ctx, slot: &mut Slot) {
    let MaskRule::Auto { views } = ctx.config.mask else { return };
    if slot.session.key_id().is_none() {
        return;
    }
    // As many as the buffer holds at most.
    let most = AUTO_MASK_MAX_VIEWS.min(slot.session.params().buffer).max(views);
    let wanted = match (slot.session.mask_id(), slot.auto_views) {
        (None, _) => views,
        (Some(_), 0) => return,
        (Some(_), from) if from >= most => return,
        (Some(_), from) => (2 * from).min(most),
    };
    // Views that see none of the current mask count too: they may see what a new one holds.
    let mut chosen = slot.accepted_views();
    chosen.truncate(most);
    if chosen.len() < wanted {
        return;
    }
    // 8-bit pixels: up to eight whole views at once (a 12 MP view is 36 MB so, 144 MB as
    // floats). A file that no longer holds what was aligned is left to the intake, which
    // brings its new content.
    let mut images = Vec::new();
    for (id, h) in &chosen {
        let path = slot.paths.get(id.as_str()).cloned().unwrap_or_else(|| slot.dir.join(id.name()));
        let Ok((file, img)) = load(ctx, &path, Role::View) else { return };
        if file.view_id(&img) != *id {
            return;
        }
        images.push((rgb8(&img), *h));
    }
    let Ok(mask) = slot.session.auto_mask(&images) else { return };
    drop(images);
    if slot.session.mask().is_some_and(|m| *m == mask) {
        tracing::debug!(views = chosen.len(), "the automatic mask found again is the same");
        slot.auto_views = chosen.len();
        return;
    }
    let id = format!("auto|{}", chosen.iter().map(|c| c.0.as_str()).collect::<Vec<_>>().join("|"));
    // A mask found from the views always fits the keyframe they were aligned to.
    let _ = set_mask_and_retake(ctx, slot, id, mask, MaskOrigin::Auto(chosen.len()));
}

/// Sets the session's mask ([`Slot::set_mask`]) and offers again every buffered view and
/// every view refused against the old mask (or none): they may see this one, or align with
/// it. `Err`: why the mask does not fit the keyframe.
fn set_mask_and_retake(
    ctx: &Ctx,
    slot: &mut Slot,
    id: String,
    mask: crate::imaging::Mask,
    origin: MaskOrigin,
) -> Result<(), String> {
    let refused: Vec<PathBuf> =
        slot.refused_views().into_iter().map(|n| slot.dir.join(n)).filter(|p| p.is_file()).collect();
    let mut again = slot.set_mask(ctx, id, mask, origin)?;
    for p in refused {
        if !again.contains(&p) {
            again.push(p);
        }
    }
    for p in again {
        reprocess(ctx, slot, &p);
    }
    Ok(())
}

/// Reads a file of the session's folder again, as it is now (see [`super::job::load`]).
pub(super) fn load(ctx: &Ctx, path: &Path, role: Role) -> Result<(FileId, DynamicImage), DecodeOutcome> {
    let limits = DecodeLimits { max_pixels: ctx.config.max_pixels };
    super::job::load(path, role, &limits, &Inbox::of(&ctx.config))
}

fn skip(ctx: &Ctx, slot: &Slot, path: &Path, reason: &str) {
    ctx.stats.skipped.fetch_add(1, Ordering::Relaxed);
    tracing::warn!(file = %watch::shown_path(path), %reason, "file skipped");
    let e = FileSkipped {
        file: path.file_name().map(|n| n.to_string_lossy().into_owned()),
        path: path.to_string_lossy().into_owned(),
        reason: reason.to_owned(),
        retried: None,
        symlink: false,
    };
    ctx.emitter.emit(Some(&slot.name), &Event::FileSkipped(e));
}

/// Reads a view again from disk (after a keyframe or mask change) and offers it.
fn reprocess(ctx: &Ctx, slot: &mut Slot, path: &Path) {
    match load(ctx, path, Role::View) {
        Ok((file, img)) => process_view(ctx, slot, &file, path, &img),
        Err(DecodeOutcome::Gone(e)) => {
            tracing::debug!(file = %path.display(), error = %e, "gone before it could be read again");
        }
        // A change means the intake will bring the new version.
        Err(DecodeOutcome::Changed) => {}
        Err(e) => skip(ctx, slot, path, &e.reason()),
    }
}

/// Aligns a view against the keyframe (or takes its saved alignment) and offers it.
fn process_view(ctx: &Ctx, slot: &mut Slot, file: &FileId, path: &Path, image: &DynamicImage) {
    let span = tracing::info_span!("view", file = %watch::shown(&file.name));
    let _enter = span.enter();
    let id: ViewId = file.view_id(image);
    let Some(basis) = slot.alignment_basis() else { return };
    if slot.decided(&id) {
        // Taken already against this keyframe and mask (a restored session takes its
        // saved views before the intake brings their files again).
        tracing::debug!("already taken");
        return;
    }
    slot.forget_old_content(ctx, &file.name, Some(&id), "its file was replaced");
    let start = Instant::now();
    let (record, from_state) = match slot.state.alignment(id.as_str(), &basis) {
        Some(r) => (r.clone(), true),
        None => match slot.session.align(to_luminance(image)) {
            Ok(r) => {
                slot.state.remember(id.as_str().to_owned(), basis, r.clone());
                slot.state_dirty = true;
                (r, false)
            }
            Err(e) => return skip(ctx, slot, path, &e.to_string()),
        },
    };
    let align_ms = start.elapsed().as_secs_f64() * 1e3;
    let pixels = (record.accepted && slot.session.mask_id().is_some()).then(|| rgb8(image));
    let offer =
        Offer { id, frame: None, record, from_state, align_ms, since: start, path: Some(path.to_owned()) };
    if let Err(reason) = slot.admit(ctx, offer, pixels.as_ref()) {
        return skip(ctx, slot, path, &reason);
    }
    drop(pixels);
    auto_mask(ctx, slot);
}

/// The view file `name` now holds nothing usable (deleted or replaced by what cannot be
/// read): its old pixels go.
pub(super) fn view_gone(ctx: &Ctx, slot: &mut Slot, name: &str, path: &Path) {
    let why =
        if path.exists() { "its file was replaced by something unusable" } else { "its file was deleted" };
    slot.forget_old_content(ctx, name, None, why);
}

#[cfg(test)]
mod tests {

    use super::*;
    use crate::config::Config;
    use crate::daemon::engine::publish::FillStep;
    use crate::geometry::Homography;
    use crate::imaging::convert::{mask_to_luma8, to_rgb8};
    use crate::imaging::{Mask, RgbF32};
    use std::collections::BTreeMap;

    fn ctx(root: &Path) -> Ctx {
        let config = Config {
            watch_dir: root.join("inbox"),
            out_dir: root.join("out"),
            state_dir: root.join("state"),
            ..Config::default()
        };
        Ctx::for_test(config)
    }

    /// Session `s` in the watched folder: a generated tree scene's keyframe (`key.png`), its
    /// mask (`key.mask.png`) and three views (`v1.png`..`v3.png`). Returns its folder.
    fn tree_session(ctx: &Ctx) -> PathBuf {
        let dir = ctx.config.watch_dir.join("s");
        std::fs::create_dir_all(&dir).unwrap();
        let scene = crate::synth::tree_scene(320, 240, 5, 3);
        to_rgb8(&scene.key).save(dir.join("key.png")).unwrap();
        mask_to_luma8(&scene.mask).save(dir.join("key.mask.png")).unwrap();
        for (i, v) in scene.views.iter().enumerate() {
            to_rgb8(v).save(dir.join(format!("v{}.png", i + 1))).unwrap();
        }
        dir
    }

    fn give(ctx: &Ctx, slot: &mut Slot, name: &str) {
        let path = slot.dir.join(name);
        let role = watch::classify(&ctx.config.watch_dir, &path, &ctx.config.extensions).unwrap().role;
        let (file, image) = load(ctx, &path, role).unwrap();
        apply(ctx, slot, role, &file, &path, Some(&image));
        slot.save_state(ctx);
    }

    fn events(ctx: &Ctx) -> Vec<serde_json::Value> {
        let log = std::fs::read_to_string(ctx.config.out_dir.join("events.jsonl")).unwrap();
        log.lines().map(|l| serde_json::from_str(l).unwrap()).collect()
    }

    /// The accepted views' inliers, by file, from the events after line `from`.
    fn inliers(ctx: &Ctx, from: usize) -> BTreeMap<String, u64> {
        events(ctx)[from..]
            .iter()
            .filter(|e| e["event"] == "view_accepted")
            .map(|e| (e["file"].as_str().unwrap().to_owned(), e["inliers"].as_u64().unwrap()))
            .collect()
    }

    /// A keyframe with a tree in front, its mask, and three views with people of their own.
    fn scene(seed: u64) -> (RgbF32, Mask, Vec<RgbF32>) {
        use crate::synth::{self, Occluder};
        use rand::SeedableRng;
        let (w, h) = (400, 300);
        let facade = synth::facade(w * 3 / 2, h * 3 / 2, seed);
        let centre = Homography::translation(w as f64 / 4.0, h as f64 / 4.0);
        let mut key = synth::render_view(&facade, &centre, w, h, [0.5; 3]);
        let mut mask = Mask::new(w, h, 0);
        synth::paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 200.0, 160.0, 110.0, 3);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let views = (0..3u64)
            .map(|i| {
                let k2v = synth::random_homography(&mut rng, w, h, 0.1, 0.2, (0.9, 1.1));
                let mut v =
                    synth::render_view(&facade, &centre.after(&k2v.inverse().unwrap()), w, h, [0.5; 3]);
                synth::paint_occluder(
                    &mut v,
                    None,
                    Occluder::Person,
                    60.0 + 120.0 * i as f32,
                    170.0,
                    40.0,
                    100 + i,
                );
                synth::expose(&mut v, 0.9 + 0.03 * i as f32, 0.01);
                v
            })
            .collect();
        (key, mask, views)
    }

    /// The keyframe's corners under the mask are not matched, so a view aligned before
    /// the mask came is aligned again once it has: the order in which a photographer drops
    /// the files changes neither the alignments nor the result.
    #[test]
    fn views_given_before_the_mask_are_aligned_as_if_it_had_come_first() {
        let run = |order: &[&str]| {
            let tmp = tempfile::tempdir().unwrap();
            let ctx = ctx(tmp.path());
            let dir = ctx.config.watch_dir.join("s");
            std::fs::create_dir_all(&dir).unwrap();
            let (key, mask, views) = scene(17);
            let mut slot = Slot::new(&ctx, "s", dir.clone());
            // Each file is written when it arrives (a keyframe takes a mask lying beside it).
            for name in order {
                match *name {
                    "key.png" => to_rgb8(&key).save(dir.join(name)).unwrap(),
                    "key.mask.png" => mask_to_luma8(&mask).save(dir.join(name)).unwrap(),
                    _ => {
                        let i: usize = name[1..name.len() - 4].parse().unwrap();
                        to_rgb8(&views[i - 1]).save(dir.join(name)).unwrap();
                    }
                }
                give(&ctx, &mut slot, name);
            }
            let FillStep::Written(_) = slot.fill(&ctx) else { panic!("no result") };
            let png = std::fs::read(ctx.config.out_dir.join("s/result.png")).unwrap();
            (inliers(&ctx, 0), png)
        };
        let (first, first_png) = run(&["key.png", "key.mask.png", "v1.png", "v2.png", "v3.png"]);
        let (last, last_png) = run(&["key.png", "v1.png", "v2.png", "v3.png", "key.mask.png"]);
        assert_eq!(first.len(), 3, "{first:?}");
        assert_eq!(first, last);
        assert!(first_png == last_png, "the results differ");
    }

    /// A view that sees none of the mask is not buffered; when the photographer paints a
    /// new mask that it does see, it is taken again rather than left out for good.
    #[test]
    fn a_view_outside_the_old_mask_is_taken_for_a_new_one_it_sees() {
        let tmp = tempfile::tempdir().unwrap();
        let ctx = ctx(tmp.path());
        let dir = ctx.config.watch_dir.join("s");
        std::fs::create_dir_all(&dir).unwrap();
        let (key, _, views) = scene(17);
        let (w, h) = (key.width(), key.height());
        let rect = |x0: usize, x1: usize| {
            Mask::from_fn(w, h, |x, y| u8::from((x0..x1).contains(&x) && (100..200).contains(&y)) * 255)
        };
        // The view is the keyframe's right half, seen from elsewhere.
        let right = views[0].crop(crate::imaging::Rect { x: w / 2, y: 0, width: w / 2, height: h });
        to_rgb8(&key).save(dir.join("key.png")).unwrap();
        mask_to_luma8(&rect(20, 80)).save(dir.join("key.mask.png")).unwrap();
        to_rgb8(&right).save(dir.join("v1.png")).unwrap();
        let mut slot = Slot::new(&ctx, "s", dir.clone());
        for name in ["key.png", "v1.png"] {
            give(&ctx, &mut slot, name);
        }
        let said = |from: usize| -> Vec<serde_json::Value> {
            events(&ctx)[from..].iter().filter(|e| e["event"] == "view_accepted").cloned().collect()
        };
        let first = said(0);
        assert_eq!(first.len(), 1, "{first:#?}");
        assert_eq!(first[0]["buffered"], false, "{first:#?}");
        let lines = events(&ctx).len();
        mask_to_luma8(&rect(w - 120, w - 40)).save(dir.join("key.mask.png")).unwrap();
        give(&ctx, &mut slot, "key.mask.png");
        let again = said(lines);
        assert_eq!(again.len(), 1, "{:#?}", &events(&ctx)[lines..]);
        assert_eq!(again[0]["buffered"], true, "{again:#?}");
        assert!(matches!(slot.fill(&ctx), FillStep::Written(_)));
    }

    /// `result.json` is the last file of a result written, and it names only the maps
    /// written for it, each with its size and digest: a map an earlier result left (a
    /// surface map, when this result has none) goes before it, and a map that is not the
    /// one it names makes the result on disk untrusted at the next start (it is made again).
    #[test]
    fn result_json_names_only_its_own_maps_and_a_restart_checks_them() {
        let tmp = tempfile::tempdir().unwrap();
        // No sweep for surfaces off the wall: its results have no surface map.
        let mut config = ctx(tmp.path()).config.as_ref().clone();
        config.session.sweep = None;
        let ctx = Ctx::for_test(config);
        let dir = tree_session(&ctx);
        let out = ctx.config.out_dir.join("s");
        let own_maps = |number: u64| {
            let report: serde_json::Value =
                serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
            assert_eq!(report["number"], number);
            let maps = report["maps"].as_object().expect("result.json lists its maps");
            for name in crate::daemon::emit::MAPS {
                let path = out.join(name);
                match maps.get(name) {
                    Some(m) => {
                        let bytes = std::fs::read(&path).unwrap();
                        assert_eq!(m["bytes"], bytes.len(), "{name}");
                        assert_eq!(m["fnv64"], crate::daemon::emit::fnv64_hex(&bytes), "{name}");
                    }
                    None => assert!(!path.exists(), "{name} is there and result {number} has none"),
                }
            }
            assert!(maps.contains_key("confidence.png") && maps.contains_key("provenance.png"), "{report}");
            maps.contains_key(crate::daemon::provenance::SURFACES)
        };
        let mut slot = Slot::new(&ctx, "s", dir.clone());
        for name in ["key.png", "key.mask.png", "v1.png"] {
            give(&ctx, &mut slot, name);
        }
        let FillStep::Written(first) = slot.fill(&ctx) else { panic!("no first result") };
        assert!(!own_maps(first));
        assert_eq!(crate::daemon::emit::check_result(&out), Ok(first));
        // A surface map of an earlier result (one that swept), which the next one has not.
        let surfaces = out.join(crate::daemon::provenance::SURFACES);
        std::fs::write(&surfaces, std::fs::read(out.join("confidence.png")).unwrap()).unwrap();
        for name in ["v2.png", "v3.png"] {
            give(&ctx, &mut slot, name);
        }
        let second = match slot.fill(&ctx) {
            FillStep::Written(n) => n,
            other => panic!("no second result: {other:?}"),
        };
        assert!(!own_maps(second));
        assert_eq!(crate::daemon::emit::check_result(&out), Ok(second));
        slot.save_state(&ctx);
        // Another map where result.json names its own: not trusted at the next start.
        let conf = out.join("confidence.png");
        let own = std::fs::read(&conf).unwrap();
        let mut bytes = own.clone();
        bytes.push(0);
        std::fs::write(&conf, &bytes).unwrap();
        let reason = crate::daemon::emit::check_result(&out).unwrap_err();
        assert!(reason.contains("confidence.png"), "{reason}");
        assert!(Slot::new(&ctx, "s", dir.clone()).state.result.is_none());
        std::fs::remove_file(&conf).unwrap();
        assert!(crate::daemon::emit::check_result(&out).unwrap_err().contains("confidence.png"));
        std::fs::write(&conf, &own).unwrap();
        assert_eq!(crate::daemon::emit::check_result(&out), Ok(second));
        // A map the result has none of, left beside it.
        std::fs::write(&surfaces, b"stale").unwrap();
        let reason = crate::daemon::emit::check_result(&out).unwrap_err();
        assert!(reason.contains("surfaces.png"), "{reason}");
    }

    /// After a restart the intake brings a session's files again, in any order and not
    /// all at once. The keyframe takes back every view whose alignment is saved before the
    /// session can fill, so the first fill has the saved result's inputs (unchanged, not
    /// rewritten) instead of publishing a fill of one view over the three-view result; the
    /// files that come after are not taken twice.
    #[test]
    fn a_restored_session_takes_back_its_saved_views_before_it_fills() {
        let tmp = tempfile::tempdir().unwrap();
        let ctx = ctx(tmp.path());
        let dir = tree_session(&ctx);
        let first = {
            let mut slot = Slot::new(&ctx, "s", dir.clone());
            for name in ["key.png", "key.mask.png", "v1.png", "v2.png", "v3.png"] {
                give(&ctx, &mut slot, name);
            }
            let FillStep::Written(n) = slot.fill(&ctx) else { panic!("no first result") };
            slot.save_state(&ctx);
            n
        };
        let lines = events(&ctx).len();
        let result = std::fs::read(ctx.config.out_dir.join("s/result.json")).unwrap();

        let mut slot = Slot::new(&ctx, "s", dir.clone());
        give(&ctx, &mut slot, "v2.png");
        give(&ctx, &mut slot, "key.png");
        assert!(matches!(slot.fill(&ctx), FillStep::Unchanged(n) if n == first));
        for name in ["v1.png", "key.mask.png", "v3.png"] {
            give(&ctx, &mut slot, name);
        }
        let again = &events(&ctx)[lines..];
        let accepted: Vec<_> = again.iter().filter(|e| e["event"] == "view_accepted").collect();
        assert_eq!(accepted.len(), 3, "{again:#?}");
        assert!(accepted.iter().all(|e| e["from_state"] == true), "{again:#?}");
        assert!(again.iter().all(|e| e["event"] != "result_updated"), "{again:#?}");
        assert_eq!(std::fs::read(ctx.config.out_dir.join("s/result.json")).unwrap(), result);
    }
}
