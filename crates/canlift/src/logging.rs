//! Structured logs on stderr: human-readable text or JSON lines (`--log-format json`); the
//! level comes from `RUST_LOG` (default `info`).

use std::io::IsTerminal;

use tracing_subscriber::filter::Targets;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

/// Log output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// One human-readable line per event.
    Text,
    /// One JSON object per event.
    Json,
}

/// The levels `RUST_LOG` asks for: comma-separated `target=level` directives and at most one
/// bare level for everything else (`info,gateway=debug`). A plain target filter and no
/// `EnvFilter`: span and field directives are not worth the regular-expression engine they
/// would put into every gateway's binary.
fn filter(rust_log: Option<&str>, default: &str) -> Result<Targets, String> {
    let default: Targets = default.parse().map_err(|e| format!("{default:?}: {e}"))?;
    match rust_log.map(str::trim).filter(|s| !s.is_empty()) {
        None => Ok(default),
        Some(directives) => directives
            .parse()
            .map_err(|e| format!("RUST_LOG={directives:?}: {e}")),
    }
}

/// Install the global subscriber; `default` is the level when `RUST_LOG` is unset.
pub fn init(format: LogFormat, default: &str) {
    let rust_log = std::env::var("RUST_LOG").ok();
    let (targets, refused) = match filter(rust_log.as_deref(), default) {
        Ok(t) => (t, None),
        Err(e) => (filter(None, "info").unwrap_or_default(), Some(e)),
    };
    // Colours only for a person at a terminal, not for journald, files or pipes.
    let layer = tracing_subscriber::fmt::layer()
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr);
    let layer = match format {
        LogFormat::Text => layer.boxed(),
        LogFormat::Json => layer.json().boxed(),
    };
    tracing_subscriber::registry()
        .with(layer.with_filter(targets))
        .init();
    if let Some(e) = refused {
        tracing::warn!("logging at info: {e}");
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;
    use tracing::level_filters::LevelFilter;

    #[test]
    fn rust_log_names_levels_per_target() {
        let t = filter(Some("warn,gateway=debug,canbus::hub=trace"), "info").unwrap();
        assert_eq!(t.default_level(), Some(LevelFilter::WARN));
        assert!(t.would_enable("gateway::connection", &tracing::Level::DEBUG));
        assert!(!t.would_enable("gateway::connection", &tracing::Level::TRACE));
        assert!(t.would_enable("canbus::hub", &tracing::Level::TRACE));
        assert!(!t.would_enable("cloud", &tracing::Level::INFO));
        let unset = filter(None, "info").unwrap();
        assert_eq!(unset.default_level(), Some(LevelFilter::INFO));
        assert_eq!(
            filter(Some("  "), "debug").unwrap().default_level(),
            Some(LevelFilter::DEBUG)
        );
        assert!(filter(Some("gateway=loud"), "info").is_err());
    }
}
