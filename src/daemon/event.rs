//! Every line of `events.jsonl`, as one type (shell layer).
//!
//! A line is a JSON object: `time`, `event` (the kind, snake case), `session` (absent for
//! the service's own events), then the kind's fields ([`super::emit::Emitter::emit`]).
//! Each kind is one variant here, written from wherever it happens (the folder source,
//! the video source, the session engine), so the same kind has the same fields whatever
//! wrote it. A field that does not apply is written as `null`, never left out, and
//! fields are only ever added: readers of older logs keep working. README ("Outputs")
//! lists the kinds.

use std::path::PathBuf;

use serde::Serialize;

/// One event of the log (its `event` field is the variant's name in snake case).
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    ServiceStarted {
        watch: PathBuf,
        pid: u32,
    },
    /// The last line of a run (written by [`super::emit::Emitter::close`]).
    ServiceStopped {
        clean: bool,
    },
    WatchDirVanished {
        dir: PathBuf,
        reason: String,
    },
    WatchDirRestored {
        dir: PathBuf,
        rewatched: Option<bool>,
    },
    FileSkipped(FileSkipped),
    SessionRemoved {
        dir: PathBuf,
        reason: String,
        results_kept: PathBuf,
        last_result: Option<u64>,
        unwritten_result: Option<u64>,
    },
    ViewWaiting {
        file: String,
        reason: String,
    },
    SessionStarted(KeyframeSet),
    KeyframeChanged(KeyframeSet),
    /// A keyframe without a mask: said once per keyframe.
    SessionWaiting {
        keyframe: String,
        waiting_for: String,
        expected: Vec<String>,
        reason: String,
    },
    MaskSet(MaskSet),
    MaskRemoved {
        file: String,
        reason: String,
    },
    /// The video's mask does not fit its keyframe.
    MaskRejected {
        reason: String,
    },
    ViewAccepted(ViewAccepted),
    ViewRejected(ViewRejected),
    ViewDropped {
        file: String,
        reason: String,
    },
    ResultUnchanged {
        number: u64,
        score: f64,
    },
    ResultNotBetter {
        score: f64,
        best: Option<f64>,
        /// The share of the mask the views back in the new fill, and in the current
        /// result (`None` after a restart: the saved score decided).
        backed: f64,
        current_backed: Option<f64>,
        fill_ms: f64,
    },
    ResultUpdated(ResultUpdated),
    ResultFailed {
        number: u64,
        file: PathBuf,
        reason: String,
        tries: u32,
        retry_in_ms: u64,
    },
    StreamUnavailable {
        input: String,
        reason: String,
        retry_ms: u64,
    },
    StreamStarted(StreamOpened),
    StreamReconnected(StreamOpened),
    StreamLost {
        input: String,
        frames: u64,
        reason: Option<String>,
        retry_ms: u64,
    },
    VideoProgress(VideoCounters),
    KeyframeRefused {
        input: String,
        reason: String,
    },
    /// A work message of the NATS scale-out whose step failed on every delivery: it went
    /// to the dead-letter subject (`clearview.dead.<session>`) and is not tried again.
    MessageDeadLettered {
        file: Option<String>,
        reason: String,
        deliveries: i64,
    },
    VideoEnded {
        #[serde(flatten)]
        counters: VideoCounters,
        input: String,
        reason: Option<String>,
        results: u64,
    },
}

/// A file that is not used, and why.
#[derive(Debug, Clone, Serialize)]
pub struct FileSkipped {
    pub file: Option<String>,
    pub path: String,
    pub reason: String,
    /// When the file is tried again (`null`: when it arrives again).
    pub retried: Option<&'static str>,
    /// The file is a symbolic link that is not followed.
    pub symlink: bool,
}

/// A keyframe set (`session_started` for the first, `keyframe_changed` after).
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeSet {
    pub keyframe: String,
    pub width: u32,
    pub height: u32,
    /// Why it is the keyframe: `named_key`, `configured`, `masked`, `first`, `video`.
    pub key_source: &'static str,
    /// Video: the frame's index, its stream time (s) and the input.
    pub frame: Option<u64>,
    pub t: Option<f64>,
    pub input: Option<String>,
}

/// A mask in use from now on.
#[derive(Debug, Clone, Serialize)]
pub struct MaskSet {
    /// The mask file (a video's: its configured path); `null` for an automatic mask.
    pub mask: Option<String>,
    pub file: Option<String>,
    /// `file` or `auto`.
    pub source: &'static str,
    pub masked: usize,
    /// Share of the keyframe masked.
    pub share: f64,
    /// Automatic mask: the views it was made from.
    pub views: Option<usize>,
    /// A mask that is probably a mistake says what will come of it.
    pub warning: Option<&'static str>,
}

/// What every view event says of the view's alignment.
#[derive(Debug, Clone, Serialize)]
pub struct ViewAligned {
    pub file: String,
    /// Video: the frame's index and stream time (s).
    pub frame: Option<u64>,
    pub t: Option<f64>,
    pub from_state: bool,
    pub from_prior: bool,
    pub inliers: usize,
    pub matches: usize,
    pub median_residual_px: Option<f64>,
    pub homography: Option<[[f64; 3]; 3]>,
    pub align_ms: f64,
}

/// A view aligned and accepted: buffered, or seeing none of the mask.
#[derive(Debug, Clone, Serialize)]
pub struct ViewAccepted {
    #[serde(flatten)]
    pub view: ViewAligned,
    pub buffered: bool,
    /// Why it is not buffered.
    pub reason: Option<String>,
    pub improves: Option<bool>,
    pub fallback_px: Option<usize>,
    pub weakly_witnessed_px: Option<usize>,
    pub doubtful_px: Option<usize>,
}

/// A view aligned and refused.
#[derive(Debug, Clone, Serialize)]
pub struct ViewRejected {
    #[serde(flatten)]
    pub view: ViewAligned,
    pub reason: String,
}

/// A result written.
#[derive(Debug, Clone, Serialize)]
pub struct ResultUpdated {
    pub number: u64,
    pub path: PathBuf,
    pub result: String,
    pub views: usize,
    pub masked: usize,
    pub from_views: f64,
    pub from_fallback: f64,
    pub confident: f64,
    pub doubtful: f64,
    pub score: f64,
    pub previous_score: Option<f64>,
    /// The share of the mask the views back in this result, and in the one it replaced,
    /// judged on the same views (the publish rule's two figures; `None` for the first
    /// result, or after a restart, when the saved score decided).
    pub backed: f64,
    pub current_backed: Option<f64>,
    pub fill_ms: f64,
    pub write_ms: f64,
    pub stages_ms: serde_json::Map<String, serde_json::Value>,
    pub tries: u32,
}

/// A stream opened (`stream_started`, then `stream_reconnected`).
#[derive(Debug, Clone, Serialize)]
pub struct StreamOpened {
    pub input: String,
    pub width: usize,
    pub height: usize,
    pub fps: f64,
    pub source_size: [usize; 2],
    pub live: bool,
}

/// A video source's counters.
#[derive(Debug, Clone, Serialize)]
pub struct VideoCounters {
    pub frames_read: u64,
    pub warmup: u64,
    pub before_key: u64,
    pub blurred: u64,
    pub still: u64,
    pub rate_capped: u64,
    pub kept: u64,
    pub dropped: u64,
    pub aligned: u64,
    pub reconnects: u64,
    pub mean_update_latency_ms: Option<u64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kind_is_the_snake_case_name_and_fields_sit_beside_it() {
        let e = Event::ViewDropped { file: "a.jpg".into(), reason: "r".into() };
        let v = serde_json::to_value(&e).unwrap();
        assert_eq!(v["event"], "view_dropped");
        assert_eq!(v["file"], "a.jpg");
        let view = ViewAligned {
            file: "frame-000003".into(),
            frame: Some(3),
            t: Some(0.1),
            from_state: false,
            from_prior: true,
            inliers: 40,
            matches: 50,
            median_residual_px: None,
            homography: None,
            align_ms: 1.5,
        };
        let e = Event::ViewRejected(ViewRejected { view, reason: "few inliers".into() });
        let v = serde_json::to_value(&e).unwrap();
        assert_eq!(v["event"], "view_rejected");
        assert_eq!(v["frame"], 3);
        assert_eq!(v["reason"], "few inliers");
        assert!(v.as_object().unwrap().contains_key("median_residual_px"), "null, not left out: {v}");
    }
}
