//! systemd readiness (`Type=notify`): `READY=1` once the node's GPU device and QUIC listener are
//! up, `STATUS=` lines for `systemctl status`, `STOPPING=1` on the way out. Outside systemd
//! (`NOTIFY_SOCKET` unset) every call does nothing.

use sd_notify::NotifyState;

fn send(states: &[NotifyState]) {
    if std::env::var_os("NOTIFY_SOCKET").is_none() {
        return;
    }
    if let Err(e) = sd_notify::notify(states) {
        tracing::warn!("cannot notify systemd (NOTIFY_SOCKET): {e}");
    }
}

/// A `STATUS=` line (what the node is doing, shown by `systemctl status`).
pub fn status(line: &str) {
    send(&[NotifyState::Status(line)]);
}

/// `READY=1` with a status line: the render device is open and the listener accepts connections.
pub fn ready(line: &str) {
    send(&[NotifyState::Ready, NotifyState::Status(line)]);
}

/// `STOPPING=1`: the node is shutting down.
pub fn stopping(line: &str) {
    send(&[NotifyState::Stopping, NotifyState::Status(line)]);
}
