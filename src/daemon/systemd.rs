//! systemd integration (shell layer): READY, STATUS, STOPPING and WATCHDOG through
//! sd_notify. Every call is a no-op unless `NOTIFY_SOCKET` is set (the service runs under
//! `Type=notify`).

use std::ffi::OsStr;
use std::io;
use std::os::unix::net::UnixDatagram;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use sd_notify::NotifyState;
use tokio_util::sync::CancellationToken;

use super::Stats;

/// Sends `states` to systemd without ever waiting for it. The notification socket is a
/// datagram socket with a short queue (10 messages on a stock kernel): when the manager
/// does not read it, a blocking send (`sd_notify::notify`'s) waits for room, and it did so
/// inside the watchdog's task and then in the shutdown itself, so that the service never
/// stopped. A message that finds the queue full is dropped (a missed WATCHDOG ping is what
/// a manager that cannot keep up should see).
fn send(states: &[NotifyState<'_>]) {
    let Some(path) = std::env::var_os("NOTIFY_SOCKET") else {
        return;
    };
    let msg: String = states.iter().map(|s| format!("{s}\n")).collect();
    match deliver(&path, msg.as_bytes()) {
        Ok(()) => {}
        Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
            static WARNED: AtomicBool = AtomicBool::new(false);
            if WARNED.swap(true, Ordering::Relaxed) {
                tracing::debug!("systemd's notification queue is full: a message was dropped");
            } else {
                tracing::warn!(
                    "systemd's notification queue is full: messages are dropped until it reads them"
                );
            }
        }
        Err(e) => tracing::warn!(error = %e, "cannot notify systemd"),
    }
}

/// One datagram to the socket at `path` (a leading `@` names an abstract socket, as
/// systemd writes it), never blocking.
fn deliver(path: &OsStr, msg: &[u8]) -> io::Result<()> {
    let sock = UnixDatagram::unbound()?;
    sock.set_nonblocking(true)?;
    match std::os::unix::ffi::OsStrExt::as_bytes(path).strip_prefix(b"@") {
        #[cfg(target_os = "linux")]
        Some(name) => {
            use std::os::linux::net::SocketAddrExt;
            sock.connect_addr(&std::os::unix::net::SocketAddr::from_abstract_name(name)?)?;
        }
        _ => sock.connect(path)?,
    }
    if sock.send(msg)? == msg.len() {
        Ok(())
    } else {
        Err(io::Error::new(io::ErrorKind::WriteZero, "incomplete datagram"))
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
