//! The portal's one TLS port: `/ws` for gateways (subprotocols `cloud`, `lift`), `/api/v1/…` for
//! operators, `/` the web UI, `/healthz`, `/metrics`.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use axum::extract::{ConnectInfo, State, WebSocketUpgrade};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use hyper_util::rt::TokioIo;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};

use crate::api::{self, App};
use crate::config::Config;
use crate::gateways::{self, telemetry, Registry, Shared};
use crate::store::Store;

/// Why the portal cannot start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The database.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// TLS material.
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    /// Anything else (listening, the development PKI).
    #[error("{0}")]
    Other(String),
}

#[derive(Default)]
struct Metrics {
    connections: AtomicU64,
    upgrades_refused: AtomicU64,
}

struct WsState {
    shared: Shared,
    max_message: usize,
    metrics: Arc<Metrics>,
}

async fn ws(
    State(state): State<Arc<WsState>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    upgrade: WebSocketUpgrade,
) -> Response {
    let upgrade = upgrade
        .protocols(["cloud", "lift"])
        .max_message_size(state.max_message)
        .max_frame_size(state.max_message)
        .read_buffer_size(512)
        .write_buffer_size(0);
    if upgrade.selected_protocol().is_none() {
        // docs/PROTOCOL.md §Connection: a client offering neither subprotocol is refused.
        state
            .metrics
            .upgrades_refused
            .fetch_add(1, Ordering::Relaxed);
        return (
            StatusCode::BAD_REQUEST,
            "Sec-WebSocket-Protocol must offer cloud or lift",
        )
            .into_response();
    }
    let shared = state.shared.clone();
    state.metrics.connections.fetch_add(1, Ordering::Relaxed);
    upgrade.on_upgrade(move |socket| gateways::serve(socket, shared, peer.to_string()))
}

/// A portal bound to its port.
pub struct Portal {
    listener: TcpListener,
    tls: tokio_rustls::TlsAcceptor,
    router: Router,
    registry: Arc<Registry>,
}

fn server_tls(config: &Config) -> Result<Arc<rustls::ServerConfig>, ServerError> {
    let (cert, key) = match (&config.server.tls_cert, &config.server.tls_key) {
        (Some(c), Some(k)) => (c.clone(), k.clone()),
        (None, None) => {
            let pki = crate::devpki::ensure(&config.state.dir)
                .map_err(|e| ServerError::Other(format!("{e:#}")))?;
            tracing::warn!(ca = %pki.ca.display(), "no tls_cert/tls_key: serving a development certificate; gateways must trust this CA");
            (pki.cert, pki.key)
        }
        _ => {
            return Err(ServerError::Other(
                "server.tls_cert and server.tls_key come together".into(),
            ))
        }
    };
    let mut tls = tls::server_config(&cert, &key, config.server.client_ca.as_deref())?;
    tls.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Arc::new(tls))
}

impl Portal {
    /// Open the database, prepare TLS and bind the port.
    pub async fn bind(config: &Config) -> Result<Portal, ServerError> {
        std::fs::create_dir_all(&config.state.dir)
            .map_err(|e| ServerError::Other(format!("{}: {e}", config.state.dir.display())))?;
        let store = Store::open(&config.database_url()).await?;
        let tls = server_tls(config)?;
        let registry = Arc::new(Registry::default());
        let dashboard = Arc::new(config.dashboard.dashboard().map_err(ServerError::Other)?);
        let (telemetry, telemetry_rx) = mpsc::channel(65536);
        let counters = Arc::new(gateways::TelemetryCounters::default());
        tokio::spawn(telemetry::retention(
            store.clone(),
            config.database.telemetry_days,
        ));
        tokio::spawn(telemetry::writer(
            store.clone(),
            telemetry_rx,
            counters.clone(),
        ));
        let metrics = Arc::new(Metrics::default());
        let ws_state = Arc::new(WsState {
            shared: Shared {
                store: store.clone(),
                registry: registry.clone(),
                settings: config.gateways.settings(),
                telemetry,
                counters: counters.clone(),
                dashboard: dashboard.clone(),
            },
            max_message: config.gateways.max_message_bytes,
            metrics: metrics.clone(),
        });
        let m = metrics.clone();
        let r = registry.clone();
        let t = counters;
        let router = Router::new()
            .route("/ws", get(ws).with_state(ws_state))
            .route("/healthz", get(|| async { "ok\n" }))
            .route(
                "/metrics",
                get(move || {
                    let (m, r, t) = (m.clone(), r.clone(), t.clone());
                    async move { metrics_text(&m, &r, &t) }
                }),
            )
            .merge({
                let app = Arc::new(App {
                    store,
                    registry: registry.clone(),
                    sessions: crate::web::Sessions::default(),
                    dashboard,
                });
                api::routes(app.clone()).merge(crate::web::routes(app))
            });
        let listener = TcpListener::bind(config.server.listen).await.map_err(|e| {
            ServerError::Other(format!("listening on {}: {e}", config.server.listen))
        })?;
        Ok(Portal {
            listener,
            tls: tokio_rustls::TlsAcceptor::from(tls),
            router,
            registry,
        })
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.listener
            .local_addr()
            .unwrap_or_else(|_| SocketAddr::from(([127, 0, 0, 1], 0)))
    }

    /// The live gateways.
    pub fn registry(&self) -> Arc<Registry> {
        self.registry.clone()
    }

    /// Serve until `shutdown` turns true.
    pub async fn run(self, mut shutdown: watch::Receiver<bool>) {
        let Portal {
            listener,
            tls,
            router,
            ..
        } = self;
        loop {
            let (tcp, peer) = tokio::select! {
                accepted = listener.accept() => match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        tracing::warn!(error = %e, "accept failed");
                        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                        continue;
                    }
                },
                _ = shutdown.changed() => break,
            };
            let _ = tcp.set_nodelay(true);
            let (tls, router) = (tls.clone(), router.clone());
            tokio::spawn(async move {
                let handshake =
                    tokio::time::timeout(std::time::Duration::from_secs(10), tls.accept(tcp)).await;
                let stream = match handshake {
                    Ok(Ok(s)) => s,
                    Ok(Err(e)) => {
                        tracing::debug!(%peer, error = %e, "TLS handshake failed");
                        return;
                    }
                    Err(_) => return,
                };
                // The peer address goes into each request (cheaper than layering the router
                // per connection, which rebuilds every route).
                let service = tower::ServiceExt::map_request(
                    router,
                    move |mut request: hyper::Request<hyper::body::Incoming>| {
                        request.extensions_mut().insert(ConnectInfo(peer));
                        request
                    },
                );
                let hyper = TowerToHyperService::new(service);
                // HTTP/1.1 only (the ALPN offer): WebSocket upgrades and the API need no more.
                let connection = hyper::server::conn::http1::Builder::new()
                    .serve_connection(TokioIo::new(stream), hyper)
                    .with_upgrades();
                if let Err(e) = connection.await {
                    tracing::debug!(%peer, error = %e, "connection ended with an error");
                }
            });
        }
        tracing::info!("portal stopped");
    }
}

fn metrics_text(m: &Metrics, r: &Registry, t: &gateways::TelemetryCounters) -> String {
    format!(
        "# TYPE canlift_gateways_online gauge\ncanlift_gateways_online {}\n\
         # TYPE canlift_gateway_connections_total counter\ncanlift_gateway_connections_total {}\n\
         # TYPE canlift_gateway_upgrades_refused_total counter\ncanlift_gateway_upgrades_refused_total {}\n\
         # TYPE canlift_telemetry_stored_total counter\ncanlift_telemetry_stored_total {}\n\
         # TYPE canlift_telemetry_dropped_total counter\ncanlift_telemetry_dropped_total {}\n",
        r.online_count(),
        m.connections.load(Ordering::Relaxed),
        m.upgrades_refused.load(Ordering::Relaxed),
        t.stored.load(Ordering::Relaxed),
        t.dropped.load(Ordering::Relaxed)
    )
}
