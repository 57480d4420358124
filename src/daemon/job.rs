//! What travels from a source to the session engine (shell layer): a file's identity
//! ([`FileId`]), a decoded file ([`Job`]), and the one way a file of the watched folder
//! is read and decoded ([`load`], [`read_and_decode`]). The intake and the workers both
//! use it; neither imports the other.

use std::path::{Path, PathBuf};
use std::time::SystemTime;

use image::DynamicImage;

use super::paths::{Inbox, Refusal};
use super::state;
use super::watch::Role;
use crate::imaging::convert::plane_to_luma8;
use crate::imaging::decode::{DecodeError, DecodeLimits, decode, decode_mask};

/// Keyframes and views with a side shorter than this are refused: too few pixels for
/// corners to be found and matched.
pub const MIN_SIDE: u32 = 32;

/// Keyframes and views longer than this many times their other side are refused: strips,
/// not photographs of a facade.
pub const MAX_ASPECT: u32 = 10;

/// A file's identity: name, size and modification time. A file that changes is a new
/// view; saved alignments are keyed by it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileId {
    pub name: String,
    pub size: u64,
    pub mtime: SystemTime,
}

impl FileId {
    pub fn id(&self) -> String {
        let ns = self.mtime.duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        format!("{}|{}|{}", self.name, self.size, ns)
    }

    /// The view this file's content is: [`FileId::id`] and a digest of the decoded
    /// pixels, so a file replaced under the same name, size and time (a sync client that
    /// keeps times, a fixed-size format) is not mistaken for the old one.
    pub fn view_id(&self, image: &DynamicImage) -> ViewId {
        ViewId(format!("{}|{:016x}", self.id(), state::content_digest(image.as_bytes())))
    }

    pub fn of(path: &Path) -> std::io::Result<Self> {
        let meta = std::fs::metadata(path)?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(Self { name, size: meta.len(), mtime: meta.modified()? })
    }
}

/// A view's identity, as saved alignments and results are keyed by: for a file
/// `name|size|mtime_ns|pixel_digest` ([`FileId::view_id`]), for a video frame
/// `frame-NNNNNN|run` ([`ViewId::frame`]). The core ([`crate::session`]) keys views by the
/// same string; the file (or frame) name is always the part before the first `|`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ViewId(String);

impl ViewId {
    /// Frame `name` of the video run `run` (a run's frames never meet a saved state).
    pub fn frame(name: &str, run: u128) -> Self {
        Self(format!("{name}|{run}"))
    }

    /// An id as the core gives it back.
    pub fn from_core(id: &str) -> Self {
        Self(id.to_owned())
    }

    /// The file (or frame) name.
    pub fn name(&self) -> &str {
        name_of(&self.0)
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl From<ViewId> for String {
    fn from(id: ViewId) -> Self {
        id.0
    }
}

/// The file (or frame) name of a view id as the core keeps it (see [`ViewId`]).
pub fn name_of(id: &str) -> &str {
    id.split('|').next().unwrap_or(id)
}

/// A decoded file for a session.
pub struct Job {
    pub session: String,
    pub path: PathBuf,
    pub role: Role,
    pub file: FileId,
    /// 8-bit RGB for keyframes and views, 8-bit grey for masks; `None`: a mask was
    /// deleted, or a view's file now holds something that cannot be used.
    pub image: Option<DynamicImage>,
}

/// Why a ready file did not become a job.
#[derive(Debug)]
pub enum DecodeOutcome {
    /// Its size or time changed while it was read.
    Changed,
    Io(String),
    Failed(String),
    /// Its metadata could not be read (deleted, or its folder gone) before it was read.
    Gone(String),
}

impl DecodeOutcome {
    /// In words, for an event or a log line.
    pub fn reason(&self) -> String {
        match self {
            Self::Changed => "changed while being read".into(),
            Self::Io(r) | Self::Failed(r) | Self::Gone(r) => r.clone(),
        }
    }
}

/// Reads and decodes a file of the watched folder, opened through `inbox` (no symbolic
/// link followed unless configured, see [`super::paths`]), checking it did not change
/// meanwhile; views and keyframes come back as 8-bit RGB, masks as 8-bit grey.
pub fn read_and_decode(
    path: &Path,
    role: Role,
    size: u64,
    mtime: SystemTime,
    limits: &DecodeLimits,
    inbox: &Inbox,
) -> Result<DynamicImage, DecodeOutcome> {
    use std::io::Read;
    let mut file = inbox.open(path).map_err(|e| match e {
        Refusal::Io(e) => DecodeOutcome::Io(format!("cannot read: {e}")),
        refused => DecodeOutcome::Io(refused.to_string()),
    })?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes).map_err(|e| DecodeOutcome::Io(format!("cannot read: {e}")))?;
    // The same file as was read (its descriptor), not whatever the name means now.
    let meta = file.metadata().map_err(|e| DecodeOutcome::Io(format!("cannot read: {e}")))?;
    if meta.len() != size || meta.modified().ok() != Some(mtime) || bytes.len() as u64 != size {
        return Err(DecodeOutcome::Changed);
    }
    // A warning the decoder logs (an unusable colour profile, read as sRGB) names the file.
    // At the warning's own level, so that a filter that shows the warning shows the name.
    let span = tracing::warn_span!("decode", file = %super::watch::shown_path(path));
    let img = span
        .in_scope(|| decode_as(&bytes, role, limits))
        .map_err(|e| DecodeOutcome::Failed(e.to_string()))?;
    if role != Role::Mask
        && let Some(reason) = shape_problem(img.width(), img.height())
    {
        return Err(DecodeOutcome::Failed(reason));
    }
    Ok(img)
}

/// The bytes half of [`read_and_decode`] (also what the fuzz targets drive): decoded
/// within `limits`, views and keyframes as 8-bit RGB, masks as 8-bit grey
/// ([`crate::imaging::convert::to_mask`]: what is transparent is kept).
pub fn decode_as(bytes: &[u8], role: Role, limits: &DecodeLimits) -> Result<DynamicImage, DecodeError> {
    if role == Role::Mask {
        return Ok(DynamicImage::ImageLuma8(plane_to_luma8(&decode_mask(bytes, limits)?)));
    }
    Ok(match decode(bytes, limits)? {
        DynamicImage::ImageRgb8(c) => DynamicImage::ImageRgb8(c),
        other => DynamicImage::ImageRgb8(other.to_rgb8()),
    })
}

/// Why a `width × height` image cannot be a keyframe or a view, if it cannot.
pub fn shape_problem(width: u32, height: u32) -> Option<String> {
    let (short, long) = (width.min(height), width.max(height));
    if short < MIN_SIDE {
        Some(format!("{width}x{height} is too small to align (at least {MIN_SIDE} pixels a side)"))
    } else if u64::from(long) > u64::from(short) * u64::from(MAX_ASPECT) {
        Some(format!(
            "{width}x{height} is a strip ({}:1), not a photograph of a facade (at most {MAX_ASPECT}:1)",
            long / short
        ))
    } else {
        None
    }
}

/// Reads file `path` as it is now: its identity, then its pixels, checked not to have
/// changed in between. [`DecodeOutcome::Gone`] when it is no longer there to look at.
pub fn load(
    path: &Path,
    role: Role,
    limits: &DecodeLimits,
    inbox: &Inbox,
) -> Result<(FileId, DynamicImage), DecodeOutcome> {
    let file = FileId::of(path).map_err(|e| DecodeOutcome::Gone(e.to_string()))?;
    let image = read_and_decode(path, role, file.size, file.mtime, limits, inbox)?;
    Ok((file, image))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn photographs_pass_and_dots_and_strips_do_not() {
        for (w, h) in [(400, 300), (32, 32), (320, 32), (4000, 3000), (300, 3000)] {
            assert_eq!(shape_problem(w, h), None, "{w}x{h}");
        }
        for (w, h) in [(1, 1), (31, 400), (400, 0), (20_000, 50), (33, 331)] {
            assert!(shape_problem(w, h).is_some(), "{w}x{h}");
        }
    }
}
