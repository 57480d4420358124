//! What a restart needs, per session (shell layer): each view's alignment keyed by the
//! view's identity and the keyframe's (file name, size, time and a digest of the pixels:
//! see [`content_digest`]), and the digest of the inputs of the last written result.
//! Saved atomically as JSON with a checksum of its own content; a file that does not
//! parse, has another version or fails its checksum is ignored with a warning and
//! rebuilt from the images, never trusted.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::session::AlignRecord;

/// Format version; a file with another is rebuilt.
pub const VERSION: u32 = 2;

/// Alignments kept per session (the oldest go first): bounded however long it runs.
pub const MAX_ALIGNMENTS: usize = 4096;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SavedAlignment {
    /// Identity of the keyframe it was aligned to.
    pub key: String,
    pub record: AlignRecord,
    /// Order of saving (for trimming).
    pub seq: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SavedResult {
    /// [`crate::session::Session::inputs_digest`] of the written result.
    pub digest: u64,
    pub score: f64,
    pub number: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionState {
    pub version: u32,
    /// File name of the keyframe chosen (so "the first to arrive" stays the same).
    pub key_file: Option<String>,
    /// View identity → alignment.
    pub alignments: BTreeMap<String, SavedAlignment>,
    pub result: Option<SavedResult>,
    /// Number of the last result written (history numbering goes on from it).
    pub last_number: u64,
    pub seq: u64,
    /// [`content_digest`] of the file's JSON with this field 0: a state edited, cut or
    /// damaged on disk fails it and is rebuilt.
    #[serde(default)]
    pub checksum: u64,
}

impl Default for SessionState {
    fn default() -> Self {
        Self {
            version: VERSION,
            key_file: None,
            alignments: BTreeMap::new(),
            result: None,
            last_number: 0,
            seq: 0,
            checksum: 0,
        }
    }
}

impl SessionState {
    /// The saved alignment of `view` to `key`, if any.
    pub fn alignment(&self, view: &str, key: &str) -> Option<&AlignRecord> {
        self.alignments.get(view).filter(|a| a.key == key).map(|a| &a.record)
    }

    /// Whether an alignment is saved for a view whose identity starts with `prefix` (its
    /// file's name, size and time, before its pixels are read) to the keyframe `key`.
    pub fn has_alignment_for(&self, prefix: &str, key_prefix: &str) -> bool {
        self.alignments.iter().any(|(v, a)| v.starts_with(prefix) && a.key.starts_with(key_prefix))
    }

    pub fn remember(&mut self, view: String, key: String, record: AlignRecord) {
        self.seq += 1;
        self.alignments.insert(view, SavedAlignment { key, record, seq: self.seq });
        if self.alignments.len() > MAX_ALIGNMENTS
            && let Some(oldest) = self.alignments.iter().min_by_key(|(_, a)| a.seq).map(|(k, _)| k.clone())
        {
            self.alignments.remove(&oldest);
        }
    }
}

/// A fast digest of `bytes` (pixels, a state file): a word-wise multiply–rotate hash,
/// against damage and mix-ups, not against an adversary.
pub fn content_digest(bytes: &[u8]) -> u64 {
    const K: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut h = 0xcbf2_9ce4_8422_2325 ^ (bytes.len() as u64).wrapping_mul(K);
    let mut words = bytes.chunks_exact(8);
    for w in &mut words {
        h = (h ^ u64::from_le_bytes(w.try_into().expect("8 bytes"))).wrapping_mul(K).rotate_left(29);
    }
    for &b in words.remainder() {
        h = (h ^ u64::from(b)).wrapping_mul(K).rotate_left(29);
    }
    h ^ (h >> 32)
}

/// The bytes of a state file: its JSON with `checksum` (the last member) set to the
/// digest of the same JSON with `checksum` 0.
fn encode(state: &SessionState) -> std::io::Result<Vec<u8>> {
    let plain =
        serde_json::to_vec(&SessionState { checksum: 0, ..state.clone() }).map_err(std::io::Error::other)?;
    let zero = b"\"checksum\":0}";
    if !plain.ends_with(zero) {
        return Err(std::io::Error::other("the state's JSON does not end with its checksum"));
    }
    let mut bytes = plain[..plain.len() - zero.len()].to_vec();
    bytes.extend_from_slice(format!("\"checksum\":{}}}", content_digest(&plain)).as_bytes());
    Ok(bytes)
}

/// Whether the file's bytes carry the right checksum (checked on the bytes as written,
/// so it does not depend on how numbers parse and print).
fn verifies(bytes: &[u8], checksum: u64) -> bool {
    let tail = format!("\"checksum\":{checksum}}}");
    let Some(head) = bytes.strip_suffix(tail.as_bytes()) else { return false };
    let mut plain = head.to_vec();
    plain.extend_from_slice(b"\"checksum\":0}");
    content_digest(&plain) == checksum
}

pub fn sessions_dir(state_dir: &Path) -> PathBuf {
    state_dir.join("sessions")
}

/// A session's state file: always directly in the sessions folder, whatever the name
/// ([`super::paths::session_dir_name`]).
/// Where the saved state of `session` is.
pub fn path(state_dir: &Path, session: &str) -> PathBuf {
    sessions_dir(state_dir).join(format!("{}.json", super::paths::session_dir_name(session)))
}

/// The saved state of `session`, or a fresh one (missing, unreadable, corrupt or of
/// another version: warned about and rebuilt).
pub fn load(state_dir: &Path, session: &str) -> SessionState {
    let p = path(state_dir, session);
    let bytes = match std::fs::read(&p) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return SessionState::default(),
        Err(e) => {
            tracing::warn!(file = %p.display(), error = %e, "cannot read saved state: rebuilding it");
            return SessionState::default();
        }
    };
    match parse(&bytes) {
        Ok(s) => s,
        Err(StateError::Version(version)) => {
            tracing::warn!(file = %p.display(), version, "saved state of another version: rebuilding it");
            SessionState::default()
        }
        Err(e) => {
            tracing::warn!(file = %p.display(), error = %e, "saved state not trusted: rebuilding it from the images");
            SessionState::default()
        }
    }
}

/// Why saved bytes were not taken as a session's state.
#[derive(Debug, Error)]
pub enum StateError {
    #[error("{0}")]
    Corrupt(#[from] serde_json::Error),
    #[error("format version {0}, not {VERSION}")]
    Version(u32),
    #[error("fails its checksum (damaged or edited)")]
    Checksum,
    #[error("implausible: {0}")]
    Implausible(String),
}

/// Counters beyond this (2^53) come from no real run: one save per file for millennia.
/// Refusing them keeps `+ 1` on a loaded counter from overflowing.
pub const MAX_COUNTER: u64 = 1 << 53;

/// The state in `bytes` (what [`load`] read), if it parses, has this version and could
/// have been written by the service: a file edited or damaged into valid JSON is not
/// trusted either.
pub fn parse(bytes: &[u8]) -> Result<SessionState, StateError> {
    let s: SessionState = serde_json::from_slice(bytes)?;
    if s.version != VERSION {
        return Err(StateError::Version(s.version));
    }
    if !verifies(bytes, s.checksum) {
        return Err(StateError::Checksum);
    }
    let implausible = |m: String| Err(StateError::Implausible(m));
    if s.seq > MAX_COUNTER || s.last_number > MAX_COUNTER {
        return implausible(format!("counters {} and {} beyond 2^53", s.seq, s.last_number));
    }
    if s.alignments.len() > MAX_ALIGNMENTS {
        return implausible(format!("{} alignments, more than {MAX_ALIGNMENTS}", s.alignments.len()));
    }
    for (view, a) in &s.alignments {
        let (w, h) = a.record.view_size;
        if a.seq > MAX_COUNTER || w == 0 || h == 0 {
            return implausible(format!("{view}: sequence {} and size {w}x{h}", a.seq));
        }
        if a.record.accepted && a.record.homography().is_none() {
            return implausible(format!("{view}: accepted without a regular homography"));
        }
    }
    Ok(s)
}

/// Saves atomically, making the state folder again if it was deleted; a failure is logged (the state is an optimisation, not a result) and
/// reported as `false`, so the caller can try again later.
pub fn save(state_dir: &Path, session: &str, state: &SessionState) -> bool {
    let p = path(state_dir, session);
    let write = |bytes: &[u8]| match crate::fsio::atomic_write(&p, bytes) {
        // The state folder was deleted under us: made again, not given up on (a restart
        // would otherwise realign every session).
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let dir = sessions_dir(state_dir);
            std::fs::create_dir_all(&dir)?;
            tracing::warn!(dir = %dir.display(), "the state folder was gone: made again");
            crate::fsio::atomic_write(&p, bytes)
        }
        r => r,
    };
    let r = encode(state).and_then(|bytes| write(&bytes));
    match r {
        Ok(()) => true,
        Err(e) => {
            tracing::warn!(file = %p.display(), error = %e, "cannot save state: trying again later");
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record() -> AlignRecord {
        AlignRecord {
            accepted: true,
            reason: None,
            homography: Some([[1.0, 0.0, 2.0], [0.0, 1.0, 3.0], [0.0, 0.0, 1.0]]),
            inliers: 40,
            matches: 50,
            checked: 60,
            median_residual_px: Some(0.4),
            coverage: 0.3,
            from_prior: true,
            view_size: (64, 48),
        }
    }

    #[test]
    fn round_trips_and_is_keyed_by_keyframe() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(sessions_dir(dir.path())).unwrap();
        let mut s = SessionState::default();
        s.remember("v|1|2".into(), "k|3|4".into(), record());
        s.result = Some(SavedResult { digest: u64::MAX - 3, score: 0.75, number: 4 });
        save(dir.path(), "s1", &s);
        let back = load(dir.path(), "s1");
        assert_ne!(back.checksum, 0);
        assert_eq!(back, SessionState { checksum: back.checksum, ..s.clone() });
        assert_eq!(back.alignment("v|1|2", "k|3|4"), Some(&record()));
        assert_eq!(back.alignment("v|1|2", "other key"), None);
    }

    #[test]
    fn any_session_name_stays_in_the_sessions_folder() {
        let root = tempfile::tempdir().unwrap();
        let state_dir = root.path().join("state");
        std::fs::create_dir_all(sessions_dir(&state_dir)).unwrap();
        let names = ["../../escaped", "/tmp/abs", "a/b", "..", ".", "", "new\nline", "x".repeat(250).leak()];
        for (i, name) in names.iter().enumerate() {
            save(&state_dir, name, &SessionState { last_number: i as u64, ..Default::default() });
        }
        for (i, name) in names.iter().enumerate() {
            assert_eq!(load(&state_dir, name).last_number, i as u64, "{name:?}");
        }
        let entries: Vec<_> =
            std::fs::read_dir(root.path()).unwrap().flatten().map(|e| e.file_name()).collect();
        assert_eq!(entries, ["state"], "nothing beside the state folder");
        assert_eq!(std::fs::read_dir(&state_dir).unwrap().count(), 1, "nothing beside sessions/");
        assert_eq!(std::fs::read_dir(sessions_dir(&state_dir)).unwrap().count(), names.len());
    }

    #[test]
    fn corrupt_state_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(sessions_dir(dir.path())).unwrap();
        std::fs::write(path(dir.path(), "s1"), b"{\"version\": 1, \"alignments\": [").unwrap();
        assert_eq!(load(dir.path(), "s1"), SessionState::default());
        std::fs::write(path(dir.path(), "s2"), b"{\"version\": 99}").unwrap();
        assert_eq!(load(dir.path(), "s2"), SessionState::default());
        // Valid JSON, edited: another homography under the same checksum.
        let mut s = SessionState::default();
        s.remember("v|1|2".into(), "k|3|4".into(), record());
        save(dir.path(), "s3", &s);
        let text = std::fs::read_to_string(path(dir.path(), "s3")).unwrap();
        assert!(load(dir.path(), "s3").alignment("v|1|2", "k|3|4").is_some());
        std::fs::write(path(dir.path(), "s3"), text.replace("2.0", "7.0")).unwrap();
        assert_eq!(load(dir.path(), "s3"), SessionState::default());
    }

    /// Valid JSON the service could not have written (found by the `state` fuzz target's
    /// seeds: a counter at `u64::MAX` overflowed on the next save).
    #[test]
    fn implausible_state_is_refused() {
        let mut good = SessionState::default();
        good.remember("v|1|2".into(), "k|3|4".into(), record());
        let json = |s: &SessionState| encode(s).unwrap();
        assert_eq!(SessionState { checksum: 0, ..parse(&json(&good)).unwrap() }, good);
        let mut s = good.clone();
        s.seq = u64::MAX;
        assert!(matches!(parse(&json(&s)), Err(StateError::Implausible(_))));
        let mut s = good.clone();
        s.last_number = MAX_COUNTER + 1;
        assert!(matches!(parse(&json(&s)), Err(StateError::Implausible(_))));
        let mut s = good.clone();
        s.alignments.values_mut().for_each(|a| a.record.view_size = (0, 48));
        assert!(matches!(parse(&json(&s)), Err(StateError::Implausible(_))));
        let mut s = good.clone();
        s.alignments.values_mut().for_each(|a| a.record.homography = Some([[0.0; 3]; 3]));
        assert!(matches!(parse(&json(&s)), Err(StateError::Implausible(_))));
        let mut s = good;
        s.alignments.values_mut().for_each(|a| {
            a.record.accepted = false;
            a.record.homography = None;
        });
        assert!(parse(&json(&s)).is_ok(), "a rejection without a homography is what the service saves");
    }
}
