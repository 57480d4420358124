//! The JSON API, the images, server-sent events, and the two changes a user can make:
//! paint the mask and choose the keyframe (shell layer).
//!
//! Both changes go through the watched inbox, so the workers stay the only writers of
//! session state and a restart sees exactly what the user chose:
//! - a painted mask is written atomically as `<key stem>.mask.png` in the session's
//!   folder. A mask file of the user's already there (`<key stem>.mask.<ext>`, any
//!   extension) is first renamed to `<name>.user-N` (N the first free number), which no
//!   watcher reads; a mask we painted before (byte-identical to the copy kept as
//!   `painted-mask.png` beside the results) is simply replaced.
//! - a chosen keyframe is renamed to `key.<ext>`; a `key.<ext>` already there (any case)
//!   is renamed to `former-key-N.<ext>` first, so it stays in the session as a view, and
//!   its mask is set aside; the chosen image's own mask (`<stem>.mask.<ext>`,
//!   `<stem>_mask.<ext>`, `<stem>-mask.<ext>`) goes with it as `key.mask.<ext>`. Nothing
//!   the user gave is overwritten or deleted.

use std::convert::Infallible;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path as UrlPath, State};
use axum::http::{StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;

use super::limits::ThumbKey;
use super::{AppState, Shared};
use crate::daemon::paths::{Inbox, Refusal};
use crate::daemon::registry::SessionSnapshot;
use crate::daemon::watch;
use crate::fsio::atomic_write;
use crate::imaging::convert::mask_to_luma8;
use crate::imaging::decode::{DecodeLimits, decode, decode_mask};

/// A refusal with its status and a JSON `{"error": ...}` body.
pub struct ApiError(StatusCode, String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(json!({ "error": self.1 }))).into_response()
    }
}

fn err(status: StatusCode, message: impl Into<String>) -> ApiError {
    ApiError(status, message.into())
}

fn session(s: &Shared, id: &str) -> Result<Arc<SessionSnapshot>, ApiError> {
    s.registry.get(id).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no session {id:?}")))
}

fn content_type(name: &str) -> &'static str {
    match name.rsplit_once('.').map(|(_, e)| e.to_ascii_lowercase()).as_deref() {
        Some("png") => "image/png",
        Some("jpg" | "jpeg") => "image/jpeg",
        Some("webp") => "image/webp",
        Some("tif" | "tiff") => "image/tiff",
        _ => "application/octet-stream",
    }
}

/// An open file as a response body, read as it is sent (never whole in memory).
fn streamed(file: tokio::fs::File, name: &str) -> Response {
    let body = axum::body::Body::from_stream(tokio_util::io::ReaderStream::new(file));
    ([(header::CONTENT_TYPE, content_type(name)), (header::CACHE_CONTROL, "no-store")], body).into_response()
}

/// A file the service knows, never cached by the browser (it changes).
async fn file(path: PathBuf, what: &str) -> Result<Response, ApiError> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_owned();
    match tokio::fs::File::open(&path).await {
        Ok(f) => Ok(streamed(f, &name)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            Err(err(StatusCode::NOT_FOUND, format!("no {what} yet")))
        }
        Err(e) => {
            tracing::warn!(file = %path.display(), error = %e, "cannot read for the HTTP API");
            Err(err(StatusCode::INTERNAL_SERVER_ERROR, format!("cannot read the {what}")))
        }
    }
}

pub async fn list(State(s): AppState) -> Json<serde_json::Value> {
    let sessions: Vec<serde_json::Value> = s
        .registry
        .all()
        .iter()
        .map(|x| {
            json!({
                "id": x.id,
                "keyframe": x.keyframe,
                "mask": x.mask,
                "views": x.views.len(),
                "accepted": x.views.iter().filter(|v| v.accepted).count(),
                "rejected": x.views.iter().filter(|v| !v.accepted).count(),
                "result": x.result.as_ref().and_then(|r| r.get("number")).cloned(),
                "coverage": x.coverage,
                "revision": x.revision,
                "updated": x.updated,
            })
        })
        .collect();
    Json(json!({ "sessions": sessions, "read_only": s.read_only.is_some() }))
}

pub async fn one(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    Ok(Json(&*session(&s, &id)?).into_response())
}

pub async fn result(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    file(s.emitter.session_dir(&x.id).join(result_name(&s, &x)), "result").await
}

/// The result image's name: the one its `result.json` gives (`image.file`, a plain
/// `result.<ext>`: the workers of `clearview collect` may write another format than the
/// collector's configuration says), else this service's own.
fn result_name(s: &Shared, x: &SessionSnapshot) -> String {
    let named = x.result.as_ref().and_then(|r| r["image"]["file"].as_str());
    match named {
        Some(n) if n.starts_with("result.") && !n.contains(['/', '\\']) && !n.contains("..") => n.to_owned(),
        _ => s.emitter.result_name(),
    }
}

/// `405` for a change asked of a server that only shows results (`clearview collect
/// --http`: the sessions' files are where ingest watches them, on another machine).
fn refuse_change(s: &Shared) -> Option<Response> {
    let reason = s.read_only?;
    let mut r = err(StatusCode::METHOD_NOT_ALLOWED, reason).into_response();
    r.headers_mut().insert(header::ALLOW, header::HeaderValue::from_static("GET, HEAD"));
    Some(r)
}

/// The bytes of a file of the watched folder, opened as the intake opens it (no symbolic
/// link followed unless configured, nothing outside the folder).
async fn inbox_file(s: &Shared, path: PathBuf, what: &'static str) -> Result<Response, ApiError> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_owned();
    let f = open_inbox(Inbox::of(&s.config), path, what).await?;
    Ok(streamed(tokio::fs::File::from_std(f), &name))
}

/// A file's identity for the thumbnail cache (path, size, modification time, inode).
fn thumb_key(path: &Path, f: &std::fs::File) -> std::io::Result<ThumbKey> {
    use std::os::unix::fs::MetadataExt;
    let meta = f.metadata()?;
    Ok((path.to_owned(), meta.len(), meta.mtime(), meta.mtime_nsec(), meta.ino()))
}

fn io_error(path: &Path, what: &str, e: std::io::Error) -> ApiError {
    tracing::warn!(file = %path.display(), error = %e, "cannot read for the HTTP API");
    err(StatusCode::INTERNAL_SERVER_ERROR, format!("cannot read the {what}"))
}

/// Opens a file of the watched folder as the intake does.
async fn open_inbox(inbox: Inbox, path: PathBuf, what: &'static str) -> Result<std::fs::File, ApiError> {
    tokio::task::spawn_blocking(move || match inbox.open(&path) {
        Ok(f) => Ok(f),
        Err(Refusal::Io(e)) if e.kind() == std::io::ErrorKind::NotFound => {
            Err(err(StatusCode::NOT_FOUND, format!("the {what}'s file is gone")))
        }
        Err(Refusal::Outside { .. }) => {
            Err(err(StatusCode::NOT_FOUND, format!("the {what} is not a file of the watched folder")))
        }
        Err(e @ (Refusal::Symlink { .. } | Refusal::NotAFile)) => {
            tracing::warn!(file = %path.display(), reason = %e, "refused to the HTTP API");
            Err(err(StatusCode::FORBIDDEN, e.to_string()))
        }
        Err(e) => {
            tracing::warn!(file = %path.display(), error = %e, "cannot read for the HTTP API");
            Err(err(StatusCode::INTERNAL_SERVER_ERROR, format!("cannot read the {what}")))
        }
    })
    .await
    .map_err(|_| err(StatusCode::INTERNAL_SERVER_ERROR, "read task failed"))?
}

/// The session's own folder in the watched inbox, where a painted mask or a chosen
/// keyframe goes: `409` for a session that has none (a video stream's).
fn inbox_dir(s: &Shared, x: &SessionSnapshot) -> Result<PathBuf, ApiError> {
    let root = &s.config.watch_dir;
    let dir = &x.inbox_dir;
    let plain = dir == root
        || (dir.parent() == Some(root.as_path())
            && dir.file_name().and_then(|n| n.to_str()).is_some_and(|n| !watch::is_partial_or_hidden(n)));
    if !s.config.watch_enabled || !plain {
        return Err(err(
            StatusCode::CONFLICT,
            "this session has no folder in the watched inbox (a video stream): its keyframe and mask come from the configuration",
        ));
    }
    if let Some(link) = Inbox::of(&s.config).symlink_on_path(dir) {
        return Err(err(StatusCode::FORBIDDEN, Refusal::Symlink { link }.to_string()));
    }
    Ok(dir.clone())
}

pub async fn keyframe(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    let path = x.key_path.clone().ok_or_else(|| err(StatusCode::NOT_FOUND, "no keyframe yet"))?;
    inbox_file(&s, path, "keyframe").await
}

pub async fn mask(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    if x.mask.is_none() {
        return Err(err(StatusCode::NOT_FOUND, "no mask yet"));
    }
    file(s.emitter.session_dir(&x.id).join("mask.png"), "mask").await
}

pub async fn provenance(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    if x.legend.is_empty() {
        return Err(err(StatusCode::NOT_FOUND, "no provenance map yet"));
    }
    file(s.emitter.session_dir(&x.id).join("provenance.png"), "provenance map").await
}

/// `GET /api/sessions/{id}/surfaces`: the current result's surface map (`surfaces.png`)
/// as an overlay ([`crate::daemon::provenance::render_surfaces`]); 404 before a result, and
/// when the session does not sweep for surfaces off the wall.
pub async fn surfaces(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    let path = s.emitter.session_dir(&x.id).join(crate::daemon::provenance::SURFACES);
    let bytes = match tokio::fs::read(&path).await {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(err(
                StatusCode::NOT_FOUND,
                "no surface map: no result yet, or the session does not sweep",
            ));
        }
        Err(e) => return Err(io_error(&path, "surface map", e)),
    };
    let limits = DecodeLimits { max_pixels: s.config.max_pixels };
    let _turn = s.limits.decode().await;
    let png = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let map = decode(&bytes, &limits)
            .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, format!("the surface map: {e}")))?
            .into_luma8();
        crate::daemon::provenance::render_surfaces(&map).map_err(|e| io_error(&path, "surface map", e))
    })
    .await
    .map_err(|_| err(StatusCode::INTERNAL_SERVER_ERROR, "surface overlay task failed"))??;
    Ok(([(header::CONTENT_TYPE, "image/png"), (header::CACHE_CONTROL, "no-cache")], png).into_response())
}

pub async fn legend(State(s): AppState, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    let number = x.result.as_ref().and_then(|r| r.get("number")).cloned();
    Ok(Json(json!({
        "result": number,
        "legend": x.legend,
        "meaning": "value 0: the keyframe's own pixel (transparent); 1 + i: filled from view i; 65534: filled from a view but doubtful (confidence below 128: it may show an occluder, or the views disagree); 65535: the fallback (no view saw it)",
    }))
    .into_response())
}

/// Longest side of a view thumbnail.
const THUMB: u32 = 240;

pub async fn thumb(
    State(s): AppState,
    UrlPath((id, name)): UrlPath<(String, String)>,
) -> Result<Response, ApiError> {
    let x = session(&s, &id)?;
    let path = if x.keyframe.as_deref() == Some(name.as_str()) {
        x.key_path.clone()
    } else {
        x.views.iter().find(|v| v.file == name).map(|v| v.path.clone())
    }
    .ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no view {name:?} in session {id:?}")))?;
    let limits = DecodeLimits { max_pixels: s.config.max_pixels };
    let mut f = open_inbox(Inbox::of(&s.config), path.clone(), "view").await?;
    let key = thumb_key(&path, &f).map_err(|e| io_error(&path, "view", e))?;
    let reply = |jpeg: Bytes| {
        ([(header::CONTENT_TYPE, "image/jpeg"), (header::CACHE_CONTROL, "max-age=60")], jpeg).into_response()
    };
    // Made once per version of the file, then served from the cache without reading it.
    if let Some(jpeg) = s.limits.thumb(&key) {
        return Ok(reply(jpeg));
    }
    // One decode at a time (a 24 MP view is 72 MB decoded): 48 thumbnails asked at once
    // took 3.6 GB. Whoever waited may find it made by the one before.
    let _turn = s.limits.decode().await;
    if let Some(jpeg) = s.limits.thumb(&key) {
        return Ok(reply(jpeg));
    }
    let jpeg = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let mut bytes = Vec::new();
        f.read_to_end(&mut bytes).map_err(|e| io_error(&path, "view", e))?;
        let img =
            decode(&bytes, &limits).map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e.to_string()))?;
        drop(bytes);
        let small = img.thumbnail(THUMB, THUMB).to_rgb8();
        drop(img);
        let mut out = std::io::Cursor::new(Vec::new());
        small
            .write_to(&mut out, image::ImageFormat::Jpeg)
            .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        Ok(out.into_inner())
    })
    .await
    .map_err(|_| err(StatusCode::INTERNAL_SERVER_ERROR, "thumbnail task failed"))??;
    let jpeg = Bytes::from(jpeg);
    s.limits.keep_thumb(key, jpeg.clone());
    Ok(reply(jpeg))
}

/// The first `base-N` (N = 1, 2, ...) for which `exists` is false.
fn free_name(dir: &Path, name: impl Fn(u32) -> String) -> PathBuf {
    (1..).map(|n| dir.join(name(n))).find(|p| !p.exists()).expect("some number is free")
}

/// `PUT /api/sessions/{id}/mask`: the body is an image the keyframe's size (PNG, white =
/// remove); 202 once it is stored in the inbox (the service re-inpaints from there).
pub async fn put_mask(
    State(s): AppState,
    UrlPath(id): UrlPath<String>,
    body: Bytes,
) -> Result<Response, ApiError> {
    if let Some(refused) = refuse_change(&s) {
        return Ok(refused);
    }
    let x = session(&s, &id)?;
    let (Some(key), Some((kw, kh))) = (x.keyframe.clone(), x.key_size) else {
        return Err(err(StatusCode::CONFLICT, "the session has no keyframe yet"));
    };
    let limits = DecodeLimits { max_pixels: s.config.max_pixels };
    let extensions = s.config.extensions.clone();
    let record = s.emitter.session_dir(&x.id).join("painted-mask.png");
    let dir = inbox_dir(&s, &x)?;
    let inbox = Inbox::of(&s.config);
    // The size from the header, before anything is decoded: a 10000x10000 mask is refused
    // for what it says it is, not after 100 MB were spent on it.
    let (w, h) = image::ImageReader::new(std::io::Cursor::new(&body[..]))
        .with_guessed_format()
        .map_err(|e| err(StatusCode::BAD_REQUEST, format!("not a readable image: {e}")))?
        .into_dimensions()
        .map_err(|e| err(StatusCode::BAD_REQUEST, format!("not a readable image: {e}")))?;
    if (w as usize, h as usize) != (kw, kh) {
        return Err(err(StatusCode::BAD_REQUEST, format!("the mask is {w}x{h}, the keyframe {kw}x{kh}")));
    }
    let _turn = s.limits.decode().await;
    let stored = tokio::task::spawn_blocking(move || -> Result<serde_json::Value, ApiError> {
        let mask = decode_mask(&body, &limits)
            .map_err(|e| err(StatusCode::BAD_REQUEST, format!("not a readable image: {e}")))?;
        if (mask.width(), mask.height()) != (kw, kh) {
            return Err(err(
                StatusCode::BAD_REQUEST,
                format!("the mask is {}x{}, the keyframe {kw}x{kh}", mask.width(), mask.height()),
            ));
        }
        let masked = mask.hole_count();
        let luma = mask_to_luma8(&mask);
        let mut png = std::io::Cursor::new(Vec::new());
        luma.write_to(&mut png, image::ImageFormat::Png)
            .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        let png = png.into_inner();
        let stem = watch::stem(&key).to_owned();
        let ours = std::fs::read(&record).ok();
        let mut backups = Vec::new();
        for ext in &extensions {
            let existing = dir.join(format!("{stem}.mask.{ext}"));
            if !existing.is_file() {
                continue;
            }
            let theirs = || {
                let mut b = Vec::new();
                inbox.open(&existing).ok()?.read_to_end(&mut b).ok()?;
                Some(b)
            };
            let painted_by_us = ext == "png" && ours.is_some() && theirs() == ours;
            if painted_by_us {
                continue;
            }
            let name = format!("{stem}.mask.{ext}");
            let backup = free_name(&dir, |n| format!("{name}.user-{n}"));
            std::fs::rename(&existing, &backup).map_err(|e| {
                err(StatusCode::INTERNAL_SERVER_ERROR, format!("cannot keep the existing {name}: {e}"))
            })?;
            tracing::info!(from = %existing.display(), to = %backup.display(), "kept the user's mask before painting");
            backups.push(backup.file_name().map(|n| n.to_string_lossy().into_owned()));
        }
        if let Some(parent) = record.parent() {
            let _ = std::fs::create_dir_all(parent);
        }
        atomic_write(&record, &png).map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        let target = dir.join(format!("{stem}.mask.png"));
        atomic_write(&target, &png).map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        Ok(json!({ "stored": target.file_name().map(|n| n.to_string_lossy()), "masked_px": masked, "kept": backups }))
    })
    .await
    .map_err(|_| err(StatusCode::INTERNAL_SERVER_ERROR, "mask task failed"))??;
    s.registry.metrics.masks_painted.fetch_add(1, Ordering::Relaxed);
    tracing::info!(session = %id, "mask painted on the preview page");
    Ok((StatusCode::ACCEPTED, Json(stored)).into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyChoice {
    file: String,
}

/// `PUT /api/sessions/{id}/keyframe` with `{"file": NAME}`, NAME one of the session's views.
pub async fn choose_keyframe(
    State(s): AppState,
    UrlPath(id): UrlPath<String>,
    body: Bytes,
) -> Result<Response, ApiError> {
    if let Some(refused) = refuse_change(&s) {
        return Ok(refused);
    }
    let x = session(&s, &id)?;
    let choice: KeyChoice = serde_json::from_slice(&body)
        .map_err(|e| err(StatusCode::BAD_REQUEST, format!("expected {{\"file\": NAME}}: {e}")))?;
    if x.keyframe.as_deref() == Some(choice.file.as_str()) {
        return Ok(
            (StatusCode::OK, Json(json!({ "keyframe": choice.file, "changed": false }))).into_response()
        );
    }
    let view =
        x.views.iter().find(|v| v.file == choice.file).ok_or_else(|| {
            err(StatusCode::NOT_FOUND, format!("no view {:?} in session {id:?}", choice.file))
        })?;
    let from = view.path.clone();
    let dir = inbox_dir(&s, &x)?;
    if from.parent() != Some(dir.as_path()) {
        return Err(err(
            StatusCode::CONFLICT,
            format!("{:?} is not a file of the session's folder", choice.file),
        ));
    }
    let extensions = s.config.extensions.clone();
    let done = tokio::task::spawn_blocking(move || -> Result<serde_json::Value, ApiError> {
        let ext = from.extension().and_then(|e| e.to_str()).unwrap_or("png").to_ascii_lowercase();
        let mut kept = Vec::new();
        // Every `key.<ext>` and `key.mask.<ext>` whatever the extension's case: a `key.JPG`
        // left beside the new `key.jpg` took the session back after a restart.
        let entries = std::fs::read_dir(&dir)
            .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, format!("cannot list the session's folder: {e}")))?;
        let mut olds: Vec<(String, &'static str, String)> = Vec::new();
        for entry in entries.flatten() {
            let Ok(name) = entry.file_name().into_string() else { continue };
            let Some((stem, ext)) = name.rsplit_once('.') else { continue };
            if !entry.file_type().is_ok_and(|t| t.is_file()) || !extensions.iter().any(|e| e.eq_ignore_ascii_case(ext)) {
                continue;
            }
            match stem {
                "key" => olds.push((name.clone(), "former-key", ext.to_owned())),
                // Its mask belongs to the old keyframe: kept aside, not applied to the new one.
                "key.mask" => olds.push((name.clone(), "mask", ext.to_owned())),
                _ => {}
            }
        }
        olds.sort();
        for (name, kind, ext) in olds {
            let to = if kind == "mask" {
                free_name(&dir, |n| format!("{name}.user-{n}"))
            } else {
                free_name(&dir, |n| format!("former-key-{n}.{ext}"))
            };
            std::fs::rename(dir.join(&name), &to)
                .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, format!("cannot keep {name}: {e}")))?;
            kept.push(to.file_name().map(|n| n.to_string_lossy().into_owned()));
        }
        // The chosen image's own mask goes with it (`<stem>.mask.png` → `key.mask.png`).
        let stem = from.file_stem().and_then(|s| s.to_str()).unwrap_or_default().to_owned();
        let own_mask = watch::mask_names(&stem, &extensions).into_iter().map(|n| dir.join(n)).find(|p| p.is_file());
        let to = dir.join(format!("key.{ext}"));
        std::fs::rename(&from, &to).map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        let mut carried = None;
        if let Some(mask) = own_mask {
            let mext = mask.extension().and_then(|e| e.to_str()).unwrap_or("png").to_owned();
            let target = dir.join(format!("key.mask.{mext}"));
            if !target.exists() && std::fs::rename(&mask, &target).is_ok() {
                carried = mask.file_name().map(|n| n.to_string_lossy().into_owned());
            }
        }
        Ok(json!({ "keyframe": to.file_name().map(|n| n.to_string_lossy()), "was": from.file_name().map(|n| n.to_string_lossy()), "kept": kept, "mask_carried": carried, "changed": true }))
    })
    .await
    .map_err(|_| err(StatusCode::INTERNAL_SERVER_ERROR, "keyframe task failed"))??;
    tracing::info!(session = %id, file = %choice.file, "keyframe chosen on the preview page");
    Ok((StatusCode::ACCEPTED, Json(done)).into_response())
}

/// Server-sent events: `session` when a session changed, `result` when a new result
/// landed (`data` is the JSON of [`crate::daemon::registry::Update`]). Ends on shutdown.
/// At most [`super::limits::MAX_EVENT_STREAMS`] at once: 503 beyond.
pub async fn events(State(s): AppState) -> Response {
    let Some(place) = s.limits.stream() else {
        return super::busy("too many event streams open: try again shortly\n");
    };
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let mut updates = s.registry.subscribe();
    let cancel = s.cancel.clone();
    tokio::spawn(async move {
        let _place = place;
        loop {
            tokio::select! {
                () = cancel.cancelled() => break,
                () = tx.closed() => break,
                r = updates.recv() => match r {
                    Ok(u) => {
                        let ev = Event::default().event(u.kind).data(serde_json::to_string(&u).unwrap_or_default());
                        if tx.send(ev).await.is_err() {
                            break;
                        }
                    }
                    // Missed some: tell the page to re-read everything.
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {
                        if tx.send(Event::default().event("session").data("{}")).await.is_err() {
                            break;
                        }
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
                },
            }
        }
    });
    let hello = tokio_stream::once(Event::default().event("hello").data("{}"));
    let stream = hello.chain(ReceiverStream::new(rx)).map(Ok::<_, Infallible>);
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}
