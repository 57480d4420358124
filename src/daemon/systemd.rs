//! systemd integration (shell layer): READY, STATUS, STOPPING and WATCHDOG through
//! sd_notify. Every call is a no-op unless `NOTIFY_SOCKET` is set (the service runs under
//! `Type=notify`).

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use sd_notify::NotifyState;
use tokio_util::sync::CancellationToken;

use super::Stats;

fn send(states: &[NotifyState<'_>]) {
    if std::env::var_os("NOTIFY_SOCKET").is_none() {
        return;
    }
    if let Err(e) = sd_notify::notify(states) {
        tracing::warn!(error = %e, "cannot notify systemd");
    }
}

pub fn ready() {
    send(&[NotifyState::Ready, NotifyState::Status("watching")]);
}

pub fn stopping() {
    send(&[NotifyState::Stopping, NotifyState::Status("stopping: finishing the step in hand")]);
}

/// Updates STATUS every few seconds and, when systemd asks for a watchdog, pings it at
/// half its interval for as long as the intake's heartbeat is recent (a stuck intake
/// stops the pings and systemd restarts the service).
pub async fn supervise(stats: Arc<Stats>, started: Instant, cancel: CancellationToken) {
    if std::env::var_os("NOTIFY_SOCKET").is_none() {
        return;
    }
    let watchdog = sd_notify::watchdog_enabled();
    let period = watchdog.map_or(Duration::from_secs(5), |w| (w / 2).min(Duration::from_secs(5)));
    let mut tick = tokio::time::interval(period);
    loop {
        tokio::select! {
            () = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let status = format!(
            "{} views handled, {} results written, {} files skipped",
            stats.views.load(Ordering::Relaxed),
            stats.results.load(Ordering::Relaxed),
            stats.skipped.load(Ordering::Relaxed)
        );
        let beat = super::millis_since(started).saturating_sub(super::load(&stats.heartbeat_ms));
        let alive = watchdog.is_none_or(|w| Duration::from_millis(beat) < w);
        if alive && watchdog.is_some() {
            send(&[NotifyState::Status(&status), NotifyState::Watchdog]);
        } else {
            send(&[NotifyState::Status(&status)]);
        }
    }
}
