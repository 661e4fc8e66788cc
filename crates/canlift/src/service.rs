//! The daemons under a service manager (docs/OPERATIONS.md §systemd): stopped by SIGINT or
//! SIGTERM, told to read their certificates again by SIGHUP, and telling systemd
//! (`Type=notify`) when they serve, reload and stop.

/// Resolves on SIGINT or SIGTERM: the daemons' graceful-shutdown trigger.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
    tracing::info!("shutdown requested");
}

/// Where a daemon stands, as systemd's `sd_notify(3)` says it.
#[derive(Debug, Clone, Copy)]
pub enum State<'a> {
    /// Serving (what `Type=notify` waits for before the unit counts as started), with a line
    /// for `systemctl status`.
    Ready(&'a str),
    /// Reading its certificates again (SIGHUP).
    Reloading,
    /// Serving again after a reload.
    Reloaded,
    /// Shutting down.
    Stopping,
}

/// Tell the service manager `state`. Nothing happens outside one (no `NOTIFY_SOCKET`); a
/// manager that does not take the message is logged, not fatal: the daemon serves regardless.
pub fn notify(state: State<'_>) {
    use sd_notify::NotifyState;
    let states: &[NotifyState<'_>] = match state {
        State::Ready(status) => &[NotifyState::Ready, NotifyState::Status(status)],
        State::Reloading => &[NotifyState::Reloading],
        State::Reloaded => &[NotifyState::Ready],
        State::Stopping => &[NotifyState::Stopping],
    };
    if let Err(e) = sd_notify::notify(states) {
        tracing::warn!(error = %e, "the service manager's NOTIFY_SOCKET refused a message");
    }
}

/// Call `reload` at every SIGHUP for as long as the process runs (`systemctl reload`), telling
/// the service manager the reload began and ended. `what` names it in the log.
pub fn on_hangup<E: std::fmt::Display>(
    what: &'static str,
    reload: impl Fn() -> Result<(), E> + Send + 'static,
) {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let mut hangups = match signal(SignalKind::hangup()) {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!(error = %e, "no SIGHUP handler: {what} reloads need a restart");
                return;
            }
        };
        tokio::spawn(async move {
            while hangups.recv().await.is_some() {
                notify(State::Reloading);
                match reload() {
                    Ok(()) => tracing::info!("SIGHUP: {what} read again"),
                    Err(e) => {
                        tracing::error!(error = %e, "SIGHUP: {what} not reloaded, the ones in use stay")
                    }
                }
                notify(State::Reloaded);
            }
        });
    }
    #[cfg(not(unix))]
    {
        let _ = (what, reload);
    }
}
