//! What a restart needs, per session (shell layer): each view's alignment keyed by the
//! view's file identity and the keyframe's, and the digest of the inputs of the last
//! written result. Saved atomically as JSON; a file that does not parse or has another
//! version is ignored with a warning and rebuilt, never trusted.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::session::AlignRecord;

/// Format version; a file with another is rebuilt.
pub const VERSION: u32 = 1;

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
        }
    }
}

impl SessionState {
    /// The saved alignment of `view` to `key`, if any.
    pub fn alignment(&self, view: &str, key: &str) -> Option<&AlignRecord> {
        self.alignments.get(view).filter(|a| a.key == key).map(|a| &a.record)
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

pub fn sessions_dir(state_dir: &Path) -> PathBuf {
    state_dir.join("sessions")
}

fn path(state_dir: &Path, session: &str) -> PathBuf {
    sessions_dir(state_dir).join(format!("{session}.json"))
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
    match serde_json::from_slice::<SessionState>(&bytes) {
        Ok(s) if s.version == VERSION => s,
        Ok(s) => {
            tracing::warn!(file = %p.display(), version = s.version, "saved state of another version: rebuilding it");
            SessionState::default()
        }
        Err(e) => {
            tracing::warn!(file = %p.display(), error = %e, "saved state is corrupt: ignoring and rebuilding it");
            SessionState::default()
        }
    }
}

/// Saves atomically; a failure is logged (the state is an optimisation, not a result) and
/// reported as `false`, so the caller can try again later.
pub fn save(state_dir: &Path, session: &str, state: &SessionState) -> bool {
    let p = path(state_dir, session);
    let r = serde_json::to_vec(state)
        .map_err(std::io::Error::other)
        .and_then(|bytes| super::emit::atomic_write(&p, &bytes));
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
        assert_eq!(back, s);
        assert_eq!(back.alignment("v|1|2", "k|3|4"), Some(&record()));
        assert_eq!(back.alignment("v|1|2", "other key"), None);
    }

    #[test]
    fn corrupt_state_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(sessions_dir(dir.path())).unwrap();
        std::fs::write(path(dir.path(), "s1"), b"{\"version\": 1, \"alignments\": [").unwrap();
        assert_eq!(load(dir.path(), "s1"), SessionState::default());
        std::fs::write(path(dir.path(), "s2"), b"{\"version\": 99}").unwrap();
        assert_eq!(load(dir.path(), "s2"), SessionState::default());
    }
}
