//! The gateway's own metrics (docs/GATEWAY.md §Metrics) on an optional local listener
//! (`[metrics] listen`): whether it is connected, how often it (re)connected, what the portal
//! asked of the bus and how long the bus took, what it pushed — with the process's figures and
//! the build, in the Prometheus text format (`promtool check metrics` clean).

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use exposition::registered;
use prometheus::{Histogram, HistogramOpts, IntCounter, IntCounterVec, IntGauge, Opts, Registry};

/// The gateway's families.
#[derive(Clone)]
pub struct GatewayMetrics {
    registry: Registry,
    /// 1 while a connection is in service (CONNACK came).
    pub connected: IntGauge,
    /// Connections that came into service.
    pub connections: IntCounter,
    /// Connections that ended (any cause).
    pub disconnects: IntCounter,
    /// Accesses to the object dictionary the portal asked for (a get, a put, a subscription's
    /// first read), by outcome (`ok`, `refused`).
    pub accesses: IntCounterVec,
    /// How long an access to a bus node took (SDO), until its answer.
    pub access_seconds: Histogram,
    /// Subscribed values pushed to the portal.
    pub notifications: IntCounter,
}

pub use exposition::MetricsError;

impl GatewayMetrics {
    /// Every family registered, the process collector and the build information.
    pub fn new() -> Result<GatewayMetrics, MetricsError> {
        let registry = Registry::new();
        let counter = |name: &str, help: &str| -> Result<IntCounter, MetricsError> {
            registered(&registry, IntCounter::new(name, help)?)
        };
        let connected = registered(
            &registry,
            IntGauge::new(
                "canlift_gateway_connected",
                "1 while a connection to the portal is in service (CONNACK received)",
            )?,
        )?;
        let accesses = registered(
            &registry,
            IntCounterVec::new(
                Opts::new(
                    "canlift_gateway_accesses_total",
                    "Object dictionary accesses the portal asked for, by outcome (ok, refused)",
                ),
                &["outcome"],
            )?,
        )?;
        let access_seconds = registered(
            &registry,
            Histogram::with_opts(
                HistogramOpts::new(
                    "canlift_gateway_bus_access_duration_seconds",
                    "Accesses to bus nodes (SDO) until their answer",
                )
                .buckets(exposition::LATENCY_BUCKETS.to_vec()),
            )?,
        )?;
        exposition::register_standard(&registry)?;
        Ok(GatewayMetrics {
            connections: counter(
                "canlift_gateway_connections_total",
                "Connections to the portal that came into service",
            )?,
            disconnects: counter(
                "canlift_gateway_disconnects_total",
                "Connections to the portal that ended, whatever the cause",
            )?,
            notifications: counter(
                "canlift_gateway_notifications_total",
                "Subscribed values pushed to the portal",
            )?,
            registry,
            connected,
            accesses,
            access_seconds,
        })
    }

    /// An access of the portal's ended after `took`, answered or refused.
    pub fn access(&self, ok: bool, took: Option<Duration>) {
        self.accesses
            .with_label_values(&[if ok { "ok" } else { "refused" }])
            .inc();
        if let Some(took) = took {
            self.access_seconds.observe(took.as_secs_f64());
        }
    }

    /// The exposition.
    pub fn render(&self) -> String {
        exposition::render(&self.registry)
    }
}

/// Serve `GET /metrics` in plain HTTP on `listen` until the task is aborted: for a scraper on
/// the gateway's own network (the listener is best kept on loopback or a management address).
pub async fn serve(listen: SocketAddr, metrics: Arc<GatewayMetrics>) -> std::io::Result<()> {
    use http_body_util::Full;
    use hyper::body::Bytes;
    let listener = tokio::net::TcpListener::bind(listen).await?;
    tracing::info!(%listen, "metrics listener");
    loop {
        let (tcp, _) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                tracing::warn!(error = %e, "metrics listener: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let metrics = metrics.clone();
        tokio::spawn(async move {
            let service = hyper::service::service_fn(move |request: hyper::Request<_>| {
                let metrics = metrics.clone();
                async move {
                    let response = if request.uri().path() == "/metrics" {
                        hyper::Response::builder()
                            .header("content-type", "text/plain; version=0.0.4; charset=utf-8")
                            .body(Full::new(Bytes::from(metrics.render())))
                    } else {
                        hyper::Response::builder()
                            .status(404)
                            .body(Full::new(Bytes::from_static(b"/metrics only\n")))
                    };
                    response
                }
            });
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(Duration::from_secs(10))
                .serve_connection(hyper_util::rt::TokioIo::new(tcp), service);
            if let Err(e) = connection.await {
                tracing::debug!(error = %e, "metrics connection ended with an error");
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_listener_serves_the_families() {
        let metrics = Arc::new(GatewayMetrics::new().unwrap());
        metrics.connected.set(1);
        metrics.connections.inc();
        metrics.access(true, Some(Duration::from_millis(2)));
        metrics.access(false, None);
        let listen = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap();
        let server = tokio::spawn(serve(listen, metrics.clone()));
        let text = loop {
            if let Ok(mut tcp) = tokio::net::TcpStream::connect(listen).await {
                use tokio::io::{AsyncReadExt, AsyncWriteExt};
                tcp.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
                    .await
                    .unwrap();
                let mut answer = String::new();
                tcp.read_to_string(&mut answer).await.unwrap();
                break answer;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        };
        server.abort();
        assert!(text.starts_with("HTTP/1.1 200"), "{text}");
        assert!(
            text.contains("# TYPE canlift_gateway_connected gauge\ncanlift_gateway_connected 1")
        );
        assert!(text.contains("canlift_gateway_accesses_total{outcome=\"refused\"} 1"));
        assert!(
            text.contains("canlift_gateway_bus_access_duration_seconds_bucket{le=\"0.0025\"} 1")
        );
    }
}
