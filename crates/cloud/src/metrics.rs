//! `/metrics` (docs/PORTAL.md §Metrics) in the Prometheus text format, through the `prometheus`
//! crate: every family with its HELP and TYPE (`promtool check metrics` clean), histograms of
//! what takes time — operator requests by route, gateway round trips by method, database writes
//! by what they write, webhook deliveries — the process's own figures (open descriptors against
//! its limit, resident memory, CPU) and `canlift_build_info`.
//!
//! The portal counts in atomics where the work happens (a connection, the telemetry writer, the
//! alarm service, the cluster); a scrape reads them ([`Sample`]) and sets the families here, so
//! counting stays one atomic add on the hot paths.

use std::sync::{Mutex, PoisonError};
use std::time::Duration;

pub use exposition::MetricsError;
use exposition::{registered, LATENCY_BUCKETS};
use prometheus::{HistogramOpts, HistogramVec, IntCounterVec, IntGaugeVec, Opts, Registry};

/// What a family is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Only rises (its name ends in `_total`).
    Counter,
    /// Goes up and down.
    Gauge,
}

/// A family the portal keeps in its own atomics: its name, kind, help and label (if any).
struct Family {
    name: &'static str,
    kind: Kind,
    help: &'static str,
    label: Option<&'static str>,
}

/// Every family [`Sample`]s may name.
const FAMILIES: &[Family] = &[
    family(Kind::Counter, "canlift_gateway_connections_total", "WebSocket connections gateways opened"),
    family(Kind::Counter, "canlift_gateway_upgrades_refused_total", "Upgrades to WebSocket refused (no cloud or lift subprotocol)"),
    family(Kind::Counter, "canlift_gateways_admitted_total", "CONNECTs admitted (CONNACK sent)"),
    labelled(Kind::Counter, "canlift_gateways_refused_total", "CONNECTs refused, by reason (domain, token, board, identity, taken, address)", "reason"),
    family(Kind::Counter, "canlift_gateways_registry_unavailable_total", "CONNECTs refused because the database did not answer (the gateway tries again after its backoff)"),
    family(Kind::Counter, "canlift_gateways_refusals_recorded_total", "Refused CONNECTs recorded and logged"),
    family(Kind::Counter, "canlift_gateways_refusals_unrecorded_total", "Refused CONNECTs over their address's recording rate: only counted"),
    family(Kind::Counter, "canlift_admission_lookups_total", "Statements that looked up CONNECTs in the registry (CONNECTs per lookup is what batching saves)"),
    family(Kind::Counter, "canlift_accept_failures_total", "Failed accepts, mostly for want of file descriptors (raise LimitNOFILE)"),
    family(Kind::Counter, "canlift_tls_handshakes_full_total", "TLS handshakes with the certificate"),
    family(Kind::Counter, "canlift_tls_handshakes_resumed_total", "TLS handshakes resumed by a session ticket"),
    family(Kind::Counter, "canlift_tls_handshakes_abandoned_total", "Connections whose client had closed them behind its ClientHello"),
    family(Kind::Counter, "canlift_memory_trims_total", "Times the allocator was asked to give back free memory after a burst of connections"),
    family(Kind::Counter, "canlift_memory_trimmed_bytes_total", "Bytes the resident set fell by through those trims"),
    family(Kind::Counter, "canlift_telemetry_stored_total", "Pushed values committed to the database"),
    labelled(Kind::Counter, "canlift_telemetry_dropped_total", "Pushed values not stored, by reason (database, queue, refused, too_large, unsubscribed, quota, stopping)", "reason"),
    family(Kind::Counter, "canlift_telemetry_waits_total", "Values a connection waited for room for (the database is the bottleneck; the portal slows its gateways down)"),
    family(Kind::Counter, "canlift_events_stored_total", "Bus events stored"),
    family(Kind::Counter, "canlift_events_dropped_total", "Bus events not stored"),
    family(Kind::Counter, "canlift_alarms_raised_total", "Alarms raised"),
    family(Kind::Counter, "canlift_alarms_cleared_total", "Alarms cleared"),
    family(Kind::Counter, "canlift_webhooks_delivered_total", "Webhook notifications a receiver took"),
    family(Kind::Counter, "canlift_webhook_attempts_failed_total", "Webhook attempts that failed (tried again later)"),
    family(Kind::Counter, "canlift_webhooks_given_up_total", "Webhook notifications given up three days after their change"),
    family(Kind::Gauge, "canlift_gateways_online", "Gateways connected to this process"),
    family(Kind::Gauge, "canlift_telemetry_queued", "Pushed values waiting for the database"),
    family(Kind::Gauge, "canlift_webhooks_pending", "Webhook notifications waiting for delivery"),
    family(Kind::Gauge, "canlift_database_healthy", "1 while the database takes writes (/healthz says why not)"),
    family(Kind::Gauge, "canlift_cluster_nats_connected", "1 while this process is connected to NATS"),
    family(Kind::Gauge, "canlift_cluster_lifts_held", "Lifts whose gateway is connected to this process"),
    family(Kind::Gauge, "canlift_cluster_lifts_elsewhere", "Lifts held by other processes of the cluster"),
    family(Kind::Gauge, "canlift_cluster_processes", "Processes of the cluster alive"),
    family(Kind::Counter, "canlift_cluster_requests_relayed_total", "Operator requests relayed to the lift's holder"),
    family(Kind::Counter, "canlift_cluster_requests_failed_total", "Relayed requests that failed"),
    family(Kind::Counter, "canlift_cluster_requests_served_total", "Requests other processes relayed here and this process served"),
    family(Kind::Counter, "canlift_cluster_replaced_total", "Connections closed here because the lift connected to another process"),
    family(Kind::Counter, "canlift_cluster_events_dropped_total", "Live events not published to NATS"),
    family(Kind::Counter, "canlift_cluster_events_unwatched_total", "Live events kept off NATS (no other process watched their lift)"),
    family(Kind::Counter, "canlift_cluster_watch_lapsed_total", "Watches of other processes that lapsed"),
    family(Kind::Counter, "canlift_cluster_entries_swept_total", "Holder entries of dead processes swept"),
    family(Kind::Counter, "canlift_cluster_nats_refused_total", "Publications and subscriptions NATS refused (permissions)"),
    family(Kind::Counter, "canlift_cluster_nats_slow_consumer_total", "Messages NATS dropped because this process read too slowly"),
];

const fn family(kind: Kind, name: &'static str, help: &'static str) -> Family {
    Family {
        name,
        kind,
        help,
        label: None,
    }
}

const fn labelled(
    kind: Kind,
    name: &'static str,
    help: &'static str,
    label: &'static str,
) -> Family {
    Family {
        name,
        kind,
        help,
        label: Some(label),
    }
}

/// The names of the families the portal may expose (the cluster's too, which a portal of its
/// own leaves out), beside those of [`Exposition::render`]'s histograms and process figures:
/// what dashboards and alert rules may name.
pub fn family_names() -> impl Iterator<Item = &'static str> {
    FAMILIES.iter().map(|f| f.name)
}

/// One value read at a scrape: a family of [`family_names`], its label's value if it has one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    /// The family.
    pub name: &'static str,
    /// The label's value.
    pub label: Option<&'static str>,
    /// The value.
    pub value: u64,
}

impl Sample {
    /// `name` at `value`.
    pub fn of(name: &'static str, value: u64) -> Sample {
        Sample {
            name,
            label: None,
            value,
        }
    }

    /// `name{label}` at `value`.
    pub fn labelled(name: &'static str, label: &'static str, value: u64) -> Sample {
        Sample {
            name,
            label: Some(label),
            value,
        }
    }
}

/// The time things take, as histograms (seconds).
#[derive(Clone)]
pub struct Timings {
    /// Operator requests (REST and web UI) by route template and method.
    pub requests: HistogramVec,
    /// Requests to gateways, from sending to the answer, by NXg method.
    pub round_trips: Timer,
    /// Database writes by what they write (telemetry, gateway records, admission lookups).
    pub database: Timer,
    /// Webhook attempts by outcome (delivered, failed).
    pub webhooks: Timer,
}

/// Where durations of one kind go: a histogram with one label, or nowhere (the tests and
/// benchmarks that run a part of the portal alone).
#[derive(Clone, Default)]
pub struct Timer(Option<HistogramVec>);

impl Timer {
    /// `took`, for the series `label`.
    pub fn observe(&self, label: &str, took: Duration) {
        if let Some(family) = &self.0 {
            family
                .with_label_values(&[label])
                .observe(took.as_secs_f64());
        }
    }

    /// A batched database statement, timed ([`cloud_store::timed`] logs the slow ones).
    pub async fn statement<T>(
        &self,
        what: &'static str,
        rows: usize,
        statement: impl std::future::Future<Output = T>,
    ) -> T {
        let started = std::time::Instant::now();
        let done = cloud_store::timed(what, rows, statement).await;
        self.observe(what, started.elapsed());
        done
    }
}

/// The portal's families, ready to be filled and rendered.
pub struct Exposition {
    registry: Registry,
    counters: Vec<(&'static str, IntCounterVec)>,
    gauges: Vec<(&'static str, IntGaugeVec)>,
    /// Filling and rendering is one step (two scrapes at once would interleave).
    render: Mutex<()>,
    /// The histograms, for the code that times things.
    pub timings: Timings,
}

impl Exposition {
    /// Every family registered, the process collector and the build information.
    pub fn new() -> Result<Exposition, MetricsError> {
        let registry = Registry::new();
        let (mut counters, mut gauges) = (Vec::new(), Vec::new());
        for f in FAMILIES {
            let labels: &[&str] = f.label.as_slice();
            match f.kind {
                Kind::Counter => {
                    let c = IntCounterVec::new(Opts::new(f.name, f.help), labels)?;
                    counters.push((f.name, registered(&registry, c)?));
                }
                Kind::Gauge => {
                    let g = IntGaugeVec::new(Opts::new(f.name, f.help), labels)?;
                    gauges.push((f.name, registered(&registry, g)?));
                }
            }
        }
        exposition::register_standard(&registry)?;
        let histogram = |name: &str, help: &str, label: &str| -> Result<Timer, MetricsError> {
            let h = HistogramVec::new(
                HistogramOpts::new(name, help).buckets(LATENCY_BUCKETS.to_vec()),
                &[label],
            )?;
            Ok(Timer(Some(registered(&registry, h)?)))
        };
        let timings = Timings {
            requests: registered(
                &registry,
                HistogramVec::new(
                    HistogramOpts::new(
                        "canlift_http_request_duration_seconds",
                        "Operator requests (REST API and web UI) until the answer's head, by route and method",
                    )
                    .buckets(LATENCY_BUCKETS.to_vec()),
                    &["route", "method"],
                )?,
            )?,
            round_trips: histogram(
                "canlift_gateway_round_trip_seconds",
                "Requests to gateways from sending to the answer, by NXg method",
                "method",
            )?,
            database: histogram(
                "canlift_database_write_duration_seconds",
                "Batched database writes and lookups, by what they write",
                "what",
            )?,
            webhooks: histogram(
                "canlift_webhook_attempt_duration_seconds",
                "Webhook attempts, by outcome",
                "outcome",
            )?,
        };
        Ok(Exposition {
            registry,
            counters,
            gauges,
            render: Mutex::new(()),
            timings,
        })
    }

    /// The exposition with `samples` as the families' values.
    pub fn render(&self, samples: &[Sample]) -> String {
        let _one = self.render.lock().unwrap_or_else(PoisonError::into_inner);
        for s in samples {
            let labels: &[&str] = s.label.as_slice();
            if let Some((_, c)) = self.counters.iter().find(|(n, _)| *n == s.name) {
                let counter = c.with_label_values(labels);
                counter.reset();
                counter.inc_by(s.value);
            } else if let Some((_, g)) = self.gauges.iter().find(|(n, _)| *n == s.name) {
                g.with_label_values(labels)
                    .set(i64::try_from(s.value).unwrap_or(i64::MAX));
            } else {
                tracing::debug!(name = s.name, "a sample of no family");
            }
        }
        exposition::render(&self.registry)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn families_render_with_help_type_and_labels() {
        let exposition = Exposition::new().unwrap();
        exposition
            .timings
            .database
            .observe("telemetry", Duration::from_millis(3));
        let text = exposition.render(&[
            Sample::of("canlift_gateways_online", 3),
            Sample::labelled("canlift_telemetry_dropped_total", "quota", 7),
        ]);
        assert!(
            text.contains("# HELP canlift_gateways_online Gateways connected"),
            "{text}"
        );
        assert!(text.contains("# TYPE canlift_gateways_online gauge\ncanlift_gateways_online 3"));
        assert!(text.contains("canlift_telemetry_dropped_total{reason=\"quota\"} 7"));
        assert!(text.contains(
            "canlift_database_write_duration_seconds_bucket{what=\"telemetry\",le=\"0.005\"} 1"
        ));
        assert!(text.contains(&format!(
            "canlift_build_info{{version=\"{}\"}} 1",
            env!("CARGO_PKG_VERSION")
        )));
        // A counter read again is set, not added to.
        let again = exposition.render(&[Sample::labelled(
            "canlift_telemetry_dropped_total",
            "quota",
            9,
        )]);
        assert!(
            again.contains("canlift_telemetry_dropped_total{reason=\"quota\"} 9"),
            "{again}"
        );
        #[cfg(target_os = "linux")]
        assert!(text.contains("process_open_fds "), "{text}");
    }
}
