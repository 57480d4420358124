//! The service's shared, read-only view of itself (shell layer): a snapshot of each
//! session that its worker replaces after every step, counters for `/metrics`, and a
//! broadcast of "something changed" for the preview page.
//!
//! Workers are the only writers of session state; they publish immutable
//! [`SessionSnapshot`]s (an `Arc` swap under a short write lock). Readers (the HTTP
//! server) clone the `Arc` and never hold the lock while doing I/O.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use serde::{Deserialize, Serialize};
use tokio::sync::broadcast;

/// A view as the status API shows it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewSnapshot {
    pub file: String,
    /// `buffered`, `used`, `rejected`, `outside_mask`, `dropped`.
    pub status: String,
    pub accepted: bool,
    pub reason: Option<String>,
    pub from_state: bool,
    pub homography: Option<[[f64; 3]; 3]>,
    pub inliers: usize,
    pub matches: usize,
    pub median_residual_px: Option<f64>,
    /// Share of the keyframe the view sees.
    pub coverage: f64,
    /// Masked pixels it filled in the current result.
    pub filled: Option<usize>,
    /// Where the file is (never serialised; looked up by exact name).
    #[serde(skip)]
    pub path: PathBuf,
}

/// One colour of the provenance map.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct LegendEntry {
    /// `keyframe`, `fallback` or the view's file name.
    pub source: String,
    /// The provenance value (0 keyframe, 1 + i source i, 65535 fallback).
    pub value: u16,
    /// `#rrggbb`; the keyframe is transparent in the map.
    pub colour: String,
    pub pixels: usize,
}

/// A session as the status API shows it (read back by `clearview collect`, which serves
/// the snapshots the workers publish).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SessionSnapshot {
    pub id: String,
    pub keyframe: Option<String>,
    pub key_size: Option<(usize, usize)>,
    /// `file:<name>`, `auto`, or `None` before a mask.
    pub mask: Option<String>,
    pub masked_px: Option<usize>,
    pub views: Vec<ViewSnapshot>,
    /// The latest `result.json` (number, scores, views), `None` before a result.
    pub result: Option<serde_json::Value>,
    /// Share of the masked pixels filled from real views in the current result.
    pub coverage: Option<f64>,
    pub legend: Vec<LegendEntry>,
    /// Numbers of the results kept in `history/`, oldest first.
    pub history: Vec<u64>,
    /// Bumped at every publication.
    pub revision: u64,
    pub updated: String,
    #[serde(skip)]
    pub key_path: Option<PathBuf>,
    /// The session's folder in the watched inbox.
    #[serde(skip)]
    pub inbox_dir: PathBuf,
}

/// What the preview page hears about.
#[derive(Debug, Clone, Serialize)]
pub struct Update {
    pub session: String,
    /// `session` (anything changed) or `result` (a new result image).
    pub kind: &'static str,
    pub revision: u64,
    pub result: Option<u64>,
}

/// Upper bounds (seconds) of the update latency histogram.
pub const LATENCY_BUCKETS: [f64; 10] = [0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0];

/// A Prometheus histogram on atomics.
#[derive(Debug, Default)]
pub struct Histogram {
    buckets: [AtomicU64; LATENCY_BUCKETS.len()],
    count: AtomicU64,
    /// Sum in microseconds.
    sum_us: AtomicU64,
}

impl Histogram {
    pub fn observe(&self, seconds: f64) {
        for (b, &le) in self.buckets.iter().zip(&LATENCY_BUCKETS) {
            if seconds <= le {
                b.fetch_add(1, Ordering::Relaxed);
            }
        }
        self.count.fetch_add(1, Ordering::Relaxed);
        self.sum_us.fetch_add((seconds * 1e6).round() as u64, Ordering::Relaxed);
    }

    /// Cumulative bucket counts, the count and the sum in seconds.
    pub fn read(&self) -> (Vec<u64>, u64, f64) {
        let b = self.buckets.iter().map(|b| b.load(Ordering::Relaxed)).collect();
        (b, self.count.load(Ordering::Relaxed), self.sum_us.load(Ordering::Relaxed) as f64 / 1e6)
    }
}

/// Counters the workers bump; the gauges are computed when `/metrics` is read.
#[derive(Debug, Default)]
pub struct Metrics {
    pub views_received: AtomicU64,
    pub views_accepted: AtomicU64,
    /// Reason label → count (labels are normalised to a short slug: bounded).
    pub views_rejected: Mutex<BTreeMap<String, u64>>,
    pub views_dropped: AtomicU64,
    pub results_written: AtomicU64,
    pub results_not_better: AtomicU64,
    pub masks_painted: AtomicU64,
    /// From a view reaching its worker to the result it led to.
    pub update_latency: Histogram,
}

impl Metrics {
    pub fn rejected(&self, reason: &str) {
        let mut map = self.views_rejected.lock().expect("metrics lock");
        let slug = reason_slug(reason);
        // A bound on label values whatever the reasons say.
        let slug = if map.len() >= 32 && !map.contains_key(&slug) { "other".to_owned() } else { slug };
        *map.entry(slug).or_default() += 1;
    }
}

/// `too few inliers: 5 < 12` → `too_few_inliers`: the words before the first number,
/// colon or parenthesis.
pub fn reason_slug(reason: &str) -> String {
    let head = reason.split([':', '(', ',', ';']).next().unwrap_or("");
    let mut out = String::new();
    for word in head.split_whitespace() {
        if word.chars().any(|c| c.is_ascii_digit()) || out.len() > 40 {
            break;
        }
        let w: String = word.chars().filter(|c| c.is_ascii_alphanumeric()).collect::<String>().to_lowercase();
        if w.is_empty() {
            continue;
        }
        if !out.is_empty() {
            out.push('_');
        }
        out.push_str(&w);
    }
    if out.is_empty() { "other".into() } else { out }
}

/// The registry the workers publish to and the HTTP server reads.
#[derive(Debug)]
pub struct Registry {
    sessions: RwLock<BTreeMap<String, Arc<SessionSnapshot>>>,
    pub metrics: Metrics,
    updates: broadcast::Sender<Update>,
    revision: AtomicU64,
}

impl Default for Registry {
    fn default() -> Self {
        Self {
            sessions: RwLock::default(),
            metrics: Metrics::default(),
            updates: broadcast::channel(64).0,
            revision: AtomicU64::new(0),
        }
    }
}

impl Registry {
    /// Replaces a session's snapshot (its revision is set here) and tells listeners.
    pub fn publish(&self, mut snapshot: SessionSnapshot, new_result: Option<u64>) {
        let revision = self.revision.fetch_add(1, Ordering::Relaxed) + 1;
        snapshot.revision = revision;
        let session = snapshot.id.clone();
        self.sessions.write().expect("registry lock").insert(session.clone(), Arc::new(snapshot));
        let kind = if new_result.is_some() { "result" } else { "session" };
        // No listener is fine.
        let _ = self.updates.send(Update { session, kind, revision, result: new_result });
    }

    pub fn get(&self, id: &str) -> Option<Arc<SessionSnapshot>> {
        self.sessions.read().expect("registry lock").get(id).cloned()
    }

    pub fn all(&self) -> Vec<Arc<SessionSnapshot>> {
        self.sessions.read().expect("registry lock").values().cloned().collect()
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Update> {
        self.updates.subscribe()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_is_cumulative() {
        let h = Histogram::default();
        for s in [0.05, 0.3, 0.3, 7.0, 1000.0] {
            h.observe(s);
        }
        let (b, count, sum) = h.read();
        assert_eq!(b, [1, 1, 3, 3, 3, 3, 4, 4, 4, 4]);
        assert_eq!(count, 5);
        assert!((sum - 1007.65).abs() < 1e-6);
    }

    #[test]
    fn reasons_become_short_slugs() {
        assert_eq!(reason_slug("too few inliers: 5 < 12"), "too_few_inliers");
        assert_eq!(reason_slug("not the same scene"), "not_the_same_scene");
        assert_eq!(reason_slug("12 px residual"), "other");
        let m = Metrics::default();
        for i in 0..40 {
            m.rejected(&format!("reason {}", char::from(b'a' + (i % 26) as u8)));
            m.rejected(&format!("kind{i} of trouble"));
        }
        let map = m.views_rejected.lock().unwrap();
        assert!(map.len() <= 33, "{}", map.len());
        assert!(map.contains_key("other"));
    }

    #[test]
    fn publishing_replaces_and_notifies() {
        let r = Registry::default();
        let mut rx = r.subscribe();
        let snap = |id: &str| SessionSnapshot {
            id: id.into(),
            keyframe: None,
            key_size: None,
            mask: None,
            masked_px: None,
            views: Vec::new(),
            result: None,
            coverage: None,
            legend: Vec::new(),
            history: Vec::new(),
            revision: 0,
            updated: String::new(),
            key_path: None,
            inbox_dir: PathBuf::new(),
        };
        r.publish(snap("a"), None);
        r.publish(snap("a"), Some(3));
        assert_eq!(r.all().len(), 1);
        assert_eq!(r.get("a").unwrap().revision, 2);
        assert!(r.get("b").is_none());
        assert_eq!(rx.try_recv().unwrap().kind, "session");
        let u = rx.try_recv().unwrap();
        assert_eq!((u.kind, u.result), ("result", Some(3)));
    }
}
