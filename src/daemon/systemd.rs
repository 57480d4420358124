//! systemd integration (shell layer): READY, STATUS, STOPPING and WATCHDOG through
//! sd_notify. Every call is a no-op unless `NOTIFY_SOCKET` is set (the service runs under
//! `Type=notify`).

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

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
/// half its interval for as long as every registered loop (the intake, each video
/// source) has beaten within the interval: a stuck loop stops the pings and systemd
/// restarts the service.
pub async fn supervise(stats: Arc<Stats>, cancel: CancellationToken) {
    if std::env::var_os("NOTIFY_SOCKET").is_none() {
        return;
    }
    let watchdog = sd_notify::watchdog_enabled();
    let period = watchdog.map_or(Duration::from_secs(5), |w| (w / 2).min(Duration::from_secs(5)));
    let mut tick = tokio::time::interval(period);
    let mut stuck = false;
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
        let Some(w) = watchdog else {
            send(&[NotifyState::Status(&status)]);
            continue;
        };
        match stats.heartbeats.stalest() {
            Some((name, age)) if age >= w => {
                if !stuck {
                    tracing::error!(
                        task = %name,
                        silent_ms = age.as_millis() as u64,
                        "a loop has stopped beating: no more watchdog pings, systemd will restart the service"
                    );
                }
                stuck = true;
                send(&[NotifyState::Status(&format!("stuck: {name}"))]);
            }
            _ => {
                stuck = false;
                send(&[NotifyState::Status(&status), NotifyState::Watchdog]);
            }
        }
    }
}
