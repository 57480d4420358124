//! `/metrics` in the Prometheus text exposition format, version 0.0.4 (shell layer).

use std::fmt::Write;
use std::sync::atomic::Ordering;

use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;

use super::{AppState, Shared};
use crate::daemon::registry::LATENCY_BUCKETS;

pub async fn handler(State(s): AppState) -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], render(&s))
}

/// A label value with `\`, `"` and newlines escaped.
fn escape(v: &str) -> String {
    v.replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n")
}

fn family(out: &mut String, name: &str, kind: &str, help: &str) {
    let _ = writeln!(out, "# HELP {name} {help}");
    let _ = writeln!(out, "# TYPE {name} {kind}");
}

fn render(s: &Shared) -> String {
    let m = &s.registry.metrics;
    let mut out = String::new();
    let counter = |out: &mut String, name: &str, help: &str, v: u64| {
        family(out, name, "counter", help);
        let _ = writeln!(out, "{name} {v}");
    };
    for (name, help, v) in [
        (
            "clearview_views_received_total",
            "Views handed to a session (image files that are neither keyframes nor masks, and video frames kept after the keyframe).",
            &m.views_received,
        ),
        (
            "clearview_views_accepted_total",
            "Views admitted with a trusted alignment (views offered again after a keyframe or mask change count again).",
            &m.views_accepted,
        ),
    ] {
        counter(&mut out, name, help, v.load(Ordering::Relaxed));
    }
    family(
        &mut out,
        "clearview_views_rejected_total",
        "counter",
        "Views rejected, by reason (counted like accepted views).",
    );
    for (reason, n) in m.views_rejected.lock().expect("metrics lock").iter() {
        let _ = writeln!(out, "clearview_views_rejected_total{{reason=\"{}\"}} {n}", escape(reason));
    }
    family(
        &mut out,
        "clearview_frames_dropped_total",
        "counter",
        "Frames dropped: from a full view buffer (buffer_full) or unreadable files skipped (unreadable).",
    );
    let _ = writeln!(
        out,
        "clearview_frames_dropped_total{{reason=\"buffer_full\"}} {}",
        m.views_dropped.load(Ordering::Relaxed)
    );
    let _ = writeln!(
        out,
        "clearview_frames_dropped_total{{reason=\"unreadable\"}} {}",
        s.stats.skipped.load(Ordering::Relaxed)
    );
    for (name, help, v) in [
        ("clearview_results_written_total", "Result images written.", &m.results_written),
        (
            "clearview_results_not_better_total",
            "Fills that scored lower than the current result (which was kept).",
            &m.results_not_better,
        ),
        ("clearview_masks_painted_total", "Masks painted on the preview page.", &m.masks_painted),
    ] {
        counter(&mut out, name, help, v.load(Ordering::Relaxed));
    }
    let name = "clearview_update_latency_seconds";
    family(&mut out, name, "histogram", "From a view reaching its worker to the result it led to.");
    let (buckets, count, sum) = m.update_latency.read();
    for (le, n) in LATENCY_BUCKETS.iter().zip(&buckets) {
        let _ = writeln!(out, "{name}_bucket{{le=\"{le}\"}} {n}");
    }
    let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {count}");
    let _ = writeln!(out, "{name}_sum {sum}");
    let _ = writeln!(out, "{name}_count {count}");
    family(&mut out, "clearview_queue_depth", "gauge", "Decoded images waiting in each worker's queue.");
    for (i, q) in s.queues.iter().enumerate() {
        let _ = writeln!(out, "clearview_queue_depth{{worker=\"{i}\"}} {}", q.len());
    }
    family(
        &mut out,
        "clearview_files_pending",
        "gauge",
        "Files complete on disk and not yet handled by a worker.",
    );
    let _ = writeln!(out, "clearview_files_pending {}", s.backlog.total());
    let sessions = s.registry.all();
    family(&mut out, "clearview_sessions", "gauge", "Sessions seen since start.");
    let _ = writeln!(out, "clearview_sessions {}", sessions.len());
    family(
        &mut out,
        "clearview_session_mask_coverage",
        "gauge",
        "Share of a session's masked pixels filled from real views in its current result (0..1).",
    );
    for x in &sessions {
        if let Some(c) = x.coverage {
            let _ = writeln!(out, "clearview_session_mask_coverage{{session=\"{}\"}} {c}", escape(&x.id));
        }
    }
    family(&mut out, "clearview_session_masked_pixels", "gauge", "Pixels of a session's mask.");
    for x in &sessions {
        if let Some(n) = x.masked_px {
            let _ = writeln!(out, "clearview_session_masked_pixels{{session=\"{}\"}} {n}", escape(&x.id));
        }
    }
    family(&mut out, "clearview_uptime_seconds", "gauge", "Seconds since the service started.");
    let _ = writeln!(out, "clearview_uptime_seconds {}", s.started.elapsed().as_secs_f64());
    out
}
