//! What the portal's `/metrics` (docs/PORTAL.md §Metrics) and the gateway's
//! (docs/GATEWAY.md §Metrics) both hold beside their own families: `canlift_build_info`, the
//! process's own figures (`process_open_fds` against `process_max_fds`, resident memory, CPU,
//! threads) and the buckets their latency histograms share.

use prometheus::{Encoder, IntGaugeVec, Opts, Registry, TextEncoder};

/// Upper bounds of the latency buckets (s): 0.5 ms to 10 s.
pub const LATENCY_BUCKETS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// A family that could not be registered: two of one name, a name Prometheus does not take.
#[derive(Debug, thiserror::Error)]
#[error("metrics: {0}")]
pub struct MetricsError(#[from] prometheus::Error);

/// `metric`, registered in `registry`: the registry gathers from one handle, the caller counts
/// with the other.
pub fn registered<M>(registry: &Registry, metric: M) -> Result<M, MetricsError>
where
    M: prometheus::core::Collector + Clone + 'static,
{
    registry.register(Box::new(metric.clone()))?;
    Ok(metric)
}

/// Register `canlift_build_info{version}` (always 1) and, on Linux, the process collector in
/// `registry`.
pub fn register_standard(registry: &Registry) -> Result<(), prometheus::Error> {
    let build = IntGaugeVec::new(
        Opts::new(
            "canlift_build_info",
            "The running canlift's version (always 1)",
        ),
        &["version"],
    )?;
    build.with_label_values(&[env!("CARGO_PKG_VERSION")]).set(1);
    registry.register(Box::new(build))?;
    #[cfg(target_os = "linux")]
    registry.register(Box::new(
        prometheus::process_collector::ProcessCollector::for_self(),
    ))?;
    Ok(())
}

/// `registry`'s families in the Prometheus text format (empty when they cannot be encoded,
/// which only a family of clashing label names could cause: a programming error, logged).
pub fn render(registry: &Registry) -> String {
    let mut text = Vec::new();
    if let Err(e) = TextEncoder::new().encode(&registry.gather(), &mut text) {
        eprintln!("metrics not encoded: {e}");
    }
    String::from_utf8(text).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_build_and_the_process_are_registered() {
        let registry = Registry::new();
        register_standard(&registry).unwrap();
        let names: Vec<String> = registry
            .gather()
            .iter()
            .map(|f| f.name().to_owned())
            .collect();
        assert!(
            names.contains(&"canlift_build_info".to_owned()),
            "{names:?}"
        );
        #[cfg(target_os = "linux")]
        assert!(names.contains(&"process_open_fds".to_owned()), "{names:?}");
    }
}
