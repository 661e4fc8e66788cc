//! Structured logs on stderr: human-readable text or JSON lines (`--log-format json`, or
//! `CANLIFT_LOG_FORMAT=json`); the level comes from `RUST_LOG` (default `info`). Each JSON line
//! names the service (the subcommand: `cloud`, `gateway`, `hub` …) and the version, as a log
//! collector receiving the lines of many processes needs.

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

/// JSON lines that begin with the service and the version: tracing-subscriber's JSON line
/// (timestamp, level, fields, target), the two fields put first.
struct Stamped {
    head: String,
    json: tracing_subscriber::fmt::format::Format<tracing_subscriber::fmt::format::Json>,
}

impl<S, N> tracing_subscriber::fmt::FormatEvent<S, N> for Stamped
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
    N: for<'a> tracing_subscriber::fmt::FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        ctx: &tracing_subscriber::fmt::FmtContext<'_, S, N>,
        mut writer: tracing_subscriber::fmt::format::Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result {
        let mut line = String::new();
        self.json.format_event(
            ctx,
            tracing_subscriber::fmt::format::Writer::new(&mut line),
            event,
        )?;
        match line.strip_prefix('{') {
            Some(rest) => write!(writer, "{{{},{rest}", self.head),
            None => writer.write_str(&line),
        }
    }
}

/// Install the global subscriber for `service` (the subcommand); `default` is the level when
/// `RUST_LOG` is unset.
pub fn init(format: LogFormat, service: &str, default: &str) {
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
        LogFormat::Json => {
            let head = format!(
                "\"service\":{},\"version\":{}",
                serde_json::Value::from(service),
                serde_json::Value::from(env!("CARGO_PKG_VERSION"))
            );
            let json = tracing_subscriber::fmt::format().json().flatten_event(true);
            layer
                .json()
                .flatten_event(true)
                .event_format(Stamped { head, json })
                .boxed()
        }
    };
    tracing_subscriber::registry()
        .with(layer.with_filter(targets))
        .init();
    if let Some(e) = refused {
        tracing::warn!("logging at info: {e}");
    }
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
