//! The portal's one TLS port: `/ws` for gateways (subprotocols `cloud`, `lift`), `/api/v1/…` for
//! operators, `/` the web UI, `/healthz`, `/metrics`.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{ConnectInfo, State, WebSocketUpgrade};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use nxg::names::ObjectNames;
use tls::tickets::TicketKeys;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};

use crate::alarms::rules::Rules;
use crate::alarms::{service, webhook, Alarms};
use crate::api;
use crate::auth::passwords::PasswordChecks;
use crate::auth::Auth;
use crate::config::{Config, ServerSection};
use crate::forwarded::TrustedProxies;
use crate::gateways::local::LocalLifts;
use crate::gateways::reports::Reports;
use crate::gateways::{self, telemetry, Registry, Shared};
use crate::metrics::{Exposition, Sample};
use crate::state::AppState;
use cloud_cluster::nats::{NatsAccess, NatsConfigError};
use cloud_cluster::Cluster;
use cloud_store::Store;

/// Why the portal cannot start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The database.
    #[error(transparent)]
    Store(#[from] cloud_store::StoreError),
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
    /// TLS handshakes with a certificate (full) and by a session ticket (resumed).
    handshakes_full: AtomicU64,
    handshakes_resumed: AtomicU64,
    /// Connections whose client had closed them behind its ClientHello: dropped unanswered.
    handshakes_abandoned: AtomicU64,
    /// `accept` calls that failed (out of file descriptors, mostly).
    accept_failures: AtomicU64,
    /// Memory given back to the system after bursts of connections ([`crate::memory`]).
    memory_trims: AtomicU64,
    memory_trimmed_bytes: AtomicU64,
}

/// Ask the allocator to give back what a burst of connections left free, once it is over.
async fn trim_after_bursts(metrics: Arc<Metrics>, registry: Arc<Registry>) {
    let mut bursts = crate::memory::Bursts::default();
    let mut look = tokio::time::interval(crate::memory::INTERVAL);
    look.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        look.tick().await;
        let opened = metrics.handshakes_full.load(Ordering::Relaxed)
            + metrics.handshakes_resumed.load(Ordering::Relaxed);
        if !bursts.look(opened, registry.online_count()) {
            continue;
        }
        let started = std::time::Instant::now();
        if let Ok(Some(bytes)) = tokio::task::spawn_blocking(crate::memory::trim).await {
            metrics.memory_trims.fetch_add(1, Ordering::Relaxed);
            metrics
                .memory_trimmed_bytes
                .fetch_add(bytes, Ordering::Relaxed);
            tracing::debug!(
                bytes,
                took_us = started.elapsed().as_micros() as u64,
                "memory given back after a burst of connections"
            );
        }
    }
}

struct WsState {
    /// One for all connections: each holds a pointer, not a copy (an idle connection's memory).
    shared: Arc<Shared>,
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
    /// The TLS acceptor (`reload.acceptor`) and what replaces its configuration.
    reload: TlsReload,
    router: Router,
    registry: Arc<Registry>,
    /// This process's lifts as the other processes of a cluster reach them: the cluster holds
    /// them weakly (they hold the cluster), the portal for as long as it runs.
    local: Arc<LocalLifts>,
    /// The state directory's lock of a portal on SQLite, held while it runs.
    state_lock: Option<std::fs::File>,
    /// Background work (retention, events, alarms, webhooks), ended with the portal.
    tasks: Vec<tokio::task::JoinHandle<()>>,
    /// The batch writers (telemetry, the gateways' records): when the portal stops they write
    /// what the ended connections queued, then end.
    writers: Vec<tokio::task::JoinHandle<()>>,
    stop_writers: watch::Sender<bool>,
    /// Closes the gateways' connections when the portal stops.
    closing: watch::Sender<bool>,
    metrics: Arc<Metrics>,
    /// Whose word on the client's address counts (`[server] trusted_proxies`).
    proxies: Arc<TrustedProxies>,
    /// Addresses whose CONNECTs keep being refused are turned away before TLS.
    refusals: Arc<gateways::refusals::Refusals>,
}

fn server_tls(
    config: &Config,
    tickets: Option<Arc<TicketKeys>>,
) -> Result<rustls::ServerConfig, ServerError> {
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
    if let Some(keys) = tickets {
        tls.ticketer = keys;
        // A gateway holds one connection: one ticket per handshake is all it uses.
        tls.send_tls13_tickets = 1;
    }
    Ok(tls)
}

/// Reads the portal's certificate, key and client CA again and serves new handshakes with them
/// (`canlift cloud` on SIGHUP; docs/OPERATIONS.md §Certificates): the connections already made
/// keep theirs, sessions resume across it. Files that do not make a configuration (a key that
/// is not the certificate's, half-written PEM) are refused and the certificate in use stays.
#[derive(Clone)]
pub struct TlsReload {
    config: Config,
    tickets: Option<Arc<TicketKeys>>,
    acceptor: tls::stream::Acceptor,
}

impl TlsReload {
    /// Read the files and use them from the next handshake on.
    pub fn reload(&self) -> Result<(), ServerError> {
        let tls = server_tls(&self.config, self.tickets.clone())?;
        self.acceptor.replace(tls);
        Ok(())
    }
}

/// Take the state directory's lock (`portal.lock`) for as long as the returned file is open:
/// one portal at a time on a SQLite database, and `canlift cloud restore` only into a stopped
/// portal. `Err` of kind `WouldBlock` while another process holds it.
pub fn lock_state_dir(dir: &std::path::Path) -> std::io::Result<std::fs::File> {
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(dir.join("portal.lock"))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => Err(std::io::ErrorKind::WouldBlock.into()),
        Err(std::fs::TryLockError::Error(e)) => Err(e),
    }
}

/// How often a cluster's process looks for rotated ticket keys: a ticket made with a new key
/// resumes on every process within this time.
const TICKET_KEYS_CHECK: Duration = Duration::from_secs(60);

/// The TLS session-ticket keys (docs/SECURITY.md §TLS sessions): none when `ticket_rotate_h` is
/// 0; the state directory's file for one process; for a cluster the database's, which every
/// process follows (the task returned).
async fn ticket_keys(
    config: &Config,
    store: &Store,
) -> Result<(Option<Arc<TicketKeys>>, Option<tokio::task::JoinHandle<()>>), ServerError> {
    if config.server.ticket_rotate_h == 0 {
        return Ok((None, None));
    }
    let rotate = Duration::from_secs(u64::from(config.server.ticket_rotate_h) * 3600);
    if config.cluster.nats.is_none() {
        let keys = TicketKeys::open(&config.state.dir.join("tls-ticket-keys"), rotate)?;
        return Ok((Some(Arc::new(keys)), None));
    }
    let text = shared_ticket_keys(store, rotate).await?;
    let keys =
        Arc::new(TicketKeys::shared(&text, rotate).map_err(|e| ServerError::Other(e.to_string()))?);
    let follow = tokio::spawn(follow_ticket_keys(
        store.clone(),
        keys.clone(),
        rotate,
        text,
    ));
    Ok((Some(keys), Some(follow)))
}

/// The cluster's ticket keys as they should be now: made by the first process, rotated by the
/// first that finds them due — over the version it read, so of two at once one wins and the
/// other takes its keys.
async fn shared_ticket_keys(store: &Store, rotate: Duration) -> Result<String, ServerError> {
    for _ in 0..3 {
        let row = store.ticket_keys().await?;
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let due = TicketKeys::due(row.as_ref().map(|(text, _)| text.as_str()), rotate, now)
            .map_err(|e| ServerError::Other(format!("the database's {e}")))?;
        match (due, row) {
            (None, Some((text, _))) => return Ok(text),
            (Some(next), row) => {
                if store
                    .replace_ticket_keys(&next, row.map(|(_, version)| version))
                    .await?
                {
                    return Ok(next);
                }
            }
            (None, None) => {}
        }
    }
    Err(ServerError::Other(
        "the database's TLS ticket keys keep changing under this process".into(),
    ))
}

/// Keep `keys` (made of `installed`) the cluster's: rotated by whichever process finds them
/// due first; replaced here only when they changed.
async fn follow_ticket_keys(
    store: Store,
    keys: Arc<TicketKeys>,
    rotate: Duration,
    mut installed: String,
) {
    let mut check = tokio::time::interval(TICKET_KEYS_CHECK.min(rotate / 4));
    check.tick().await;
    loop {
        check.tick().await;
        let followed = match shared_ticket_keys(&store, rotate).await {
            Ok(text) if text == installed => Ok(()),
            Ok(text) => keys
                .install(&text)
                .map(|()| installed = text)
                .map_err(|e| ServerError::Other(e.to_string())),
            Err(e) => Err(e),
        };
        if let Err(e) = followed {
            tracing::warn!(error = %e, "TLS ticket keys not followed: sessions resume on this process only");
        }
    }
}

impl Portal {
    /// Open the database, prepare TLS and bind the port. `names` are the object names operators
    /// may use instead of an mplex (the `canlift` binary gives the CiA 417 catalog's).
    pub async fn bind(config: &Config, names: ObjectNames) -> Result<Portal, ServerError> {
        std::fs::create_dir_all(&config.state.dir)
            .map_err(|e| ServerError::Other(format!("{}: {e}", config.state.dir.display())))?;
        let database = config.database_url();
        let state_lock = match database.starts_with("sqlite:") && !database.contains(":memory:") {
            true => Some(lock_state_dir(&config.state.dir).map_err(|e| {
                ServerError::Other(match e.kind() {
                    std::io::ErrorKind::WouldBlock => format!(
                        "another portal runs on {} (its portal.lock is taken)",
                        config.state.dir.display()
                    ),
                    _ => format!("{}/portal.lock: {e}", config.state.dir.display()),
                })
            })?),
            false => None,
        };
        let store = Store::open_pooled(&config.database_url(), config.database.connections).await?;
        // Told at every start: anyone who guesses a short domain token adds lifts to its
        // account (docs/SECURITY.md §Tenants).
        for account in store.short_domains(SHORT_DOMAIN_TOKEN).await? {
            tracing::warn!(
                %account,
                "the account's domain token is shorter than {SHORT_DOMAIN_TOKEN} characters: a guess away from admitting lifts into it"
            );
        }
        let (tickets, follow_tickets) = ticket_keys(config, &store).await?;
        let tls = server_tls(config, tickets.clone())?;
        let mut tasks: Vec<_> = follow_tickets.into_iter().collect();
        let mut cluster = None;
        if let Some(url) = &config.cluster.nats {
            // Told at start: past PostgreSQL's limit the pools fail under load, not now.
            let wanted = i64::from(config.database.connections) + 2;
            if let Ok(Some(free)) = store.free_connections().await {
                if free + 1 < wanted {
                    tracing::warn!(
                        free,
                        wanted,
                        "PostgreSQL takes fewer connections than this process may open: lower \
                         [database] connections or raise max_connections (docs/CLUSTER.md)"
                    );
                }
            }
            cluster = Some(join_cluster(config, url).await?);
        }
        let exposition =
            Arc::new(Exposition::new().map_err(|e| ServerError::Other(e.to_string()))?);
        let timings = exposition.timings.clone();
        let registry = Arc::new(Registry::new(
            cluster.as_ref().map(|(c, _)| c.clone()),
            timings.round_trips.clone(),
        ));
        let insights = Arc::new(config.insights.insights().map_err(ServerError::Other)?);
        let dashboard = Arc::new(config.dashboard.dashboard().map_err(ServerError::Other)?);
        // Insights read what is stored: what the gateways are not asked to push stays unknown.
        let unread: Vec<String> = insights
            .objects()
            .iter()
            .filter(|m| !dashboard.live.contains(m))
            .map(ToString::to_string)
            .collect();
        if !unread.is_empty() {
            tracing::warn!(
                objects = %unread.join(", "),
                "[insights] reads objects that are not in [dashboard] live: no gateway pushes them, \
                 so reports and trend rules will not see them (docs/PORTAL.md §Availability)"
            );
        }
        let subscriptions = Arc::new(gateways::subscriptions::Subscriptions::new(
            registry.clone(),
            store.clone(),
            &dashboard,
        ));
        // What the other processes reach here; the cluster holds it weakly, the portal keeps it.
        let local = Arc::new(LocalLifts::new(registry.clone(), subscriptions.clone()));
        if let Some((cluster, events)) = cluster {
            let weak: std::sync::Weak<dyn cloud_cluster::Local> = Arc::downgrade(&local) as _;
            cluster.serve(weak);
            tasks.push(tokio::spawn(cluster.clone().run()));
            tasks.push(tokio::spawn(cluster.publish_events(events)));
        }
        let (telemetry, telemetry_rx) =
            telemetry::Queue::new(config.database.telemetry_queue, Arc::default());
        let (records, records_rx) = gateways::records::Records::new(store.clone());
        let (admissions, admitting) =
            gateways::admissions::Admissions::start(store.clone(), timings.database.clone());
        tasks.push(admitting);
        let admitted = admissions.counters.clone();
        let (stop_writers, stopping) = watch::channel(false);
        let writers = vec![
            tokio::spawn(telemetry::writer(
                store.clone(),
                telemetry_rx,
                telemetry.counters().clone(),
                stopping.clone(),
                timings.database.clone(),
            )),
            tokio::spawn(gateways::records::writer(
                store.clone(),
                records_rx,
                stopping,
                timings.database.clone(),
            )),
        ];
        tasks.extend([
            tokio::spawn(telemetry::retention(
                telemetry::Retained::Telemetry,
                store.clone(),
                config.database.telemetry_days,
            )),
            tokio::spawn(telemetry::retention(
                telemetry::Retained::Events,
                store.clone(),
                config.database.events_days,
            )),
            tokio::spawn(telemetry::retention(
                telemetry::Retained::RollUps,
                store.clone(),
                config.database.rollup_days,
            )),
            tokio::spawn(telemetry::retention(
                telemetry::Retained::Refused {
                    rows: config.gateways.refused_keep_rows,
                },
                store.clone(),
                config.gateways.refused_keep_days.max(1),
            )),
            tokio::spawn(telemetry::retention(
                telemetry::Retained::Idempotency,
                store.clone(),
                1,
            )),
            tokio::spawn(telemetry::roll_up(store.clone())),
            // A full disk or an outage is noticed when nothing else writes, and its end within
            // a second (`/healthz`).
            tokio::spawn(store.clone().watch_writes(Duration::from_secs(5))),
        ]);
        let (alarms, reports) =
            start_alarms(config, &store, &registry, &insights, &timings, &mut tasks)?;
        // Rights taken away anywhere reach this process within a second.
        tasks.push(tokio::spawn(
            store
                .clone()
                .follow_auth_epoch(std::time::Duration::from_secs(1)),
        ));
        let (closing, closing_rx) = watch::channel(false);
        let refusals = Arc::new(gateways::refusals::Refusals::new(store.clone()));
        let proxies = Arc::new(
            TrustedProxies::parse(&config.server.trusted_proxies).map_err(ServerError::Other)?,
        );
        let metrics = Arc::new(Metrics::default());
        if crate::memory::SUPPORTED {
            tasks.push(tokio::spawn(trim_after_bursts(
                metrics.clone(),
                registry.clone(),
            )));
        }
        let ws_state = Arc::new(WsState {
            shared: Arc::new(Shared {
                store: store.clone(),
                registry: registry.clone(),
                policy: gateways::Policy::of(&config.gateways),
                telemetry: telemetry.clone(),
                admissions,
                records,
                dashboard: dashboard.clone(),
                subscriptions: subscriptions.clone(),
                insights: insights.clone(),
                reports: reports.clone(),
                refusals: refusals.clone(),
                closing: closing_rx,
            }),
            max_message: config.gateways.max_message_bytes,
            metrics: metrics.clone(),
        });
        let m = metrics.clone();
        let r = registry.clone();
        let a = alarms.counters.clone();
        let (telemetry, admitted, reports) = (telemetry.clone(), admitted.clone(), reports.clone());
        let exposition = exposition.clone();
        let health_of = store.clone();
        let refused = refusals.clone();
        // `/metrics` (docs/PORTAL.md §Metrics): on a listener of its own, or on the public port
        // for the bearer of `metrics_token`, or not at all.
        let render: Metered = Arc::new(move || {
            let mut now = samples(&m, &r, &telemetry, &a, &reports, &admitted);
            // 1 while the database takes writes (docs/PORTAL.md §Health).
            let healthy = health_of.health().trouble().is_none();
            now.push(Sample::of("canlift_database_healthy", u64::from(healthy)));
            now.extend(refused.counts().into_iter().map(|(reason, n)| {
                Sample::labelled("canlift_gateways_refused_total", reason.name(), n)
            }));
            now.extend([
                Sample::of(
                    "canlift_gateways_refusals_recorded_total",
                    refused.recorded.load(Ordering::Relaxed),
                ),
                Sample::of(
                    "canlift_gateways_refusals_unrecorded_total",
                    refused.unrecorded.load(Ordering::Relaxed),
                ),
            ]);
            exposition.render(&now)
        });
        if let Some(listen) = config.server.metrics_listen {
            tasks.push(serve_metrics(listen, render.clone()).await?);
        }
        let mut router = Router::new()
            .route("/ws", get(ws).with_state(ws_state))
            .route(
                "/healthz",
                get(health).with_state((registry.clone(), store.clone())),
            )
            .merge({
                let (audit, auditing) = crate::audit::AuditTrail::start(store.clone());
                tasks.push(auditing);
                let app = Arc::new(AppState {
                    audit,
                    auth: Auth {
                        elevations: crate::auth::elevation::Elevations::new(store.clone()),
                        sessions: crate::auth::sessions::Sessions::default(),
                        key_rates: std::sync::Mutex::new(crate::throttle::KeyRates::new(
                            config.server.requests_per_key_s,
                        )),
                        sign_ins: std::sync::Mutex::default(),
                        passwords: password_checks(&config.server)?,
                        sso: match &config.oidc {
                            Some(section) => Some(Arc::new(
                                crate::auth::oidc::Sso::new(section.clone())
                                    .map_err(ServerError::Other)?,
                            )),
                            None => None,
                        },
                    },
                    store,
                    registry: registry.clone(),
                    dashboard,
                    subscriptions,
                    alarms,
                    names: Arc::new(names),
                    insights: insights.clone(),
                    recent: crate::insights::Recent::default(),
                });
                // Pages, scripts and JSON gzip-compressed when the browser accepts it (a phone
                // on a mobile network); tower-http leaves event streams and images alone.
                api::routes(app.clone())
                    .merge(crate::web::routes(app))
                    .layer(tower_http::compression::CompressionLayer::new())
                    .layer(axum::middleware::from_fn_with_state(
                        timings.requests.clone(),
                        time_request,
                    ))
            });
        if let Some(token) = config.server.metrics_token.clone() {
            let token = Arc::new(token);
            router = router.route(
                "/metrics",
                get(move |headers: axum::http::HeaderMap| async move {
                    public_metrics(&token, &headers, &render)
                }),
            );
        }
        // Around every route: every refusal, the router's own (404, 405) too, finds a small
        // body read; HSTS below goes on its own answers (408, 400) too.
        router = router.layer(axum::middleware::from_fn(crate::request_body::read_first));
        // A browser that once came over HTTPS with the portal's own certificate never tries
        // anything else for a year (RFC 6797); a development certificate is not worth pinning.
        if config.server.tls_cert.is_some() {
            router = router.layer(axum::middleware::map_response(
                |mut response: Response| async move {
                    response.headers_mut().insert(
                        axum::http::header::STRICT_TRANSPORT_SECURITY,
                        axum::http::HeaderValue::from_static("max-age=31536000"),
                    );
                    response
                },
            ));
        }
        let listener = listen(config.server.listen).map_err(|e| {
            ServerError::Other(format!("listening on {}: {e}", config.server.listen))
        })?;
        Ok(Portal {
            listener,
            reload: TlsReload {
                config: config.clone(),
                tickets,
                acceptor: tls::stream::Acceptor::new(Arc::new(tls)),
            },
            router,
            registry,
            local,
            state_lock,
            tasks,
            writers,
            stop_writers,
            closing,
            metrics,
            proxies,
            refusals,
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

    /// What reloads the certificate while the portal runs.
    pub fn tls_reload(&self) -> TlsReload {
        self.reload.clone()
    }

    /// Serve until `shutdown` turns true.
    pub async fn run(self, mut shutdown: watch::Receiver<bool>) {
        let Portal {
            listener,
            reload: TlsReload { acceptor: tls, .. },
            router,
            registry,
            local,
            state_lock,
            tasks,
            writers,
            stop_writers,
            closing,
            metrics,
            proxies,
            refusals,
        } = self;
        loop {
            let (tcp, peer) = tokio::select! {
                accepted = accept_next(&listener, |e, first| {
                    metrics.accept_failures.fetch_add(1, Ordering::Relaxed);
                    if first {
                        tracing::warn!(error = %e, "accept failed: new connections wait in the listen queue until it works again (canlift_accept_failures_total counts the attempts)");
                    }
                }) => accepted,
                _ = shutdown.changed() => break,
            };
            let _ = tcp.set_nodelay(true);
            let (tls, router, metrics) = (tls.clone(), router.clone(), metrics.clone());
            let (proxies, refusals) = (proxies.clone(), refusals.clone());
            tokio::spawn(async move {
                let mut tcp = tcp;
                // The client behind a trusted balancer's PROXY header (docs/PORTAL.md §Behind
                // a load balancer); an address whose CONNECTs keep being refused gets no TLS.
                let peer = match proxies.client_of(&mut tcp, peer, HANDSHAKE_TIMEOUT).await {
                    Ok(client) => client,
                    Err(e) => {
                        tracing::debug!(%peer, error = %e, "a trusted proxy's header failed");
                        return;
                    }
                };
                if !proxies.trusts(peer.ip()) && !refusals.admits(&peer.to_string()) {
                    return;
                }
                let handshake = tokio::time::timeout(HANDSHAKE_TIMEOUT, tls.accept(tcp)).await;
                let stream = match handshake {
                    Ok(Ok(s)) => {
                        let counter = match s.handshake_kind() {
                            Some(rustls::HandshakeKind::Resumed) => &metrics.handshakes_resumed,
                            _ => &metrics.handshakes_full,
                        };
                        counter.fetch_add(1, Ordering::Relaxed);
                        s
                    }
                    Ok(Err(e)) if tls::stream::abandoned(&e) => {
                        metrics.handshakes_abandoned.fetch_add(1, Ordering::Relaxed);
                        return;
                    }
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
                        let client = proxies.client_of_request(peer, request.headers());
                        request.extensions_mut().insert(ConnectInfo(client));
                        request
                    },
                );
                // HTTP/1.1 only (the ALPN offer): WebSocket upgrades and the API need no more.
                let connection = crate::connection::serve(stream, service);
                if let Err(e) = connection.await {
                    tracing::debug!(%peer, error = %e, "connection ended with an error");
                }
            });
        }
        // Refused from now on (a gateway reconnecting at once tries again later, with its TLS
        // session ticket unspent), not left in the listen queue.
        drop(listener);
        let _ = closing.send(true);
        // The gateways' connections close their sockets (queuing when each was last seen);
        // then what is queued is written — all within a bound, whatever the database does.
        let deadline = tokio::time::Instant::now() + STOP_WITHIN;
        while registry.online_count() > 0 && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
        let _ = stop_writers.send(true);
        for mut writer in writers {
            if tokio::time::timeout_at(deadline, &mut writer)
                .await
                .is_err()
            {
                tracing::warn!("stopping: queued telemetry or gateway records not all written");
                writer.abort();
            }
        }
        for task in tasks {
            task.abort();
        }
        // Nothing is relayed here any more; another portal (or a restore) may have the state.
        drop(local);
        drop(state_lock);
        tracing::info!("portal stopped");
    }
}

/// Connections the kernel completes and queues for `accept` while the portal is busy: as many
/// as the system allows (Linux truncates it to `net.core.somaxconn`, 4096 by default). After
/// an outage a fleet reconnects at once; beyond the queue the kernel drops SYNs, and each gateway
/// dropped loses its SYN retransmission time (1 s, then 3 s, 7 s) on top of its wait for the
/// portal — the tail of a reconnect storm (docs/BENCHMARKS.md §The listen queue, and patience
/// for CONNACK). tokio's `TcpListener::bind` listens with 128, as the standard library does.
const LISTEN_BACKLOG: u32 = 65_535;

/// The portal's listening socket: `addr` (reused at once after a restart), [`LISTEN_BACKLOG`].
fn listen(addr: SocketAddr) -> std::io::Result<TcpListener> {
    let socket = match addr {
        SocketAddr::V4(_) => tokio::net::TcpSocket::new_v4()?,
        SocketAddr::V6(_) => tokio::net::TcpSocket::new_v6()?,
    };
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(LISTEN_BACKLOG)
}

/// How long to wait before the next `accept` after one failed, `last` the wait before it: 5 ms,
/// doubling to 1 s (as Go's `net/http` does). A process out of file descriptors (EMFILE) has its
/// new connections wait in the listen queue; they are taken as soon as a descriptor is free
/// again, without a busy loop or a warning every few milliseconds meanwhile (docs/PORTAL.md
/// §Metrics).
fn accept_retry(last: Option<Duration>) -> Duration {
    last.map_or(Duration::from_millis(5), |w| {
        (w * 2).min(Duration::from_secs(1))
    })
}

/// The next connection on `listener`, accepts that fail tried again after [`accept_retry`]'s
/// waits; `failed` hears of each failure, and whether it is the first since one succeeded.
async fn accept_next(
    listener: &TcpListener,
    mut failed: impl FnMut(&std::io::Error, bool),
) -> (tokio::net::TcpStream, SocketAddr) {
    let mut retry = None;
    loop {
        match listener.accept().await {
            Ok(accepted) => return accepted,
            Err(e) => {
                failed(&e, retry.is_none());
                let wait = accept_retry(retry);
                retry = Some(wait);
                tokio::time::sleep(wait).await;
            }
        }
    }
}

/// How long a stopping portal waits for its gateways' connections to end and for what they
/// queued to be written.
const STOP_WITHIN: std::time::Duration = std::time::Duration::from_secs(5);

/// Join the cluster of `[cluster] nats`: one PostgreSQL database for all processes. Returns
/// the cluster and the queue of live events to publish; it runs once it has this process's
/// lifts to serve.
async fn join_cluster(
    config: &Config,
    url: &str,
) -> Result<(Arc<Cluster>, mpsc::Receiver<(String, Vec<u8>)>), ServerError> {
    let database = config.database_url();
    if !(database.starts_with("postgres://") || database.starts_with("postgresql://")) {
        return Err(ServerError::Other(format!(
            "[cluster] needs the processes' shared database: set [database] url = \"postgres://…\" (now {})",
            cloud_store::shown_url(&database)
        )));
    }
    let ttl = std::time::Duration::from_secs(config.cluster.holder_ttl_s);
    // The holder's own request timeout answers first; this one covers a holder that died.
    let timeout = config.gateways.settings().request_timeout + std::time::Duration::from_secs(1);
    let failed = |e: NatsConfigError| ServerError::Other(e.to_string());
    let access = NatsAccess::from_config(&config.cluster, url).map_err(failed)?;
    let replicas = config.cluster.nats_replicas;
    if !(1..=5).contains(&replicas) {
        return Err(ServerError::Other(format!(
            "[cluster] nats_replicas = {replicas}: NATS keeps 1 to 5 copies of a bucket"
        )));
    }
    let (cluster, events) = Cluster::connect(&access, config.node_name(), ttl, timeout, replicas)
        .await
        .map_err(failed)?;
    tracing::info!(
        node = cluster.node(),
        nats = access.shown(),
        "portal process of a cluster"
    );
    Ok((cluster, events))
}

/// The sign-in secret checkers of `[server] password_checks_at_once`.
fn password_checks(server: &ServerSection) -> Result<PasswordChecks, ServerError> {
    let threads = match server.password_checks_at_once {
        0 => std::thread::available_parallelism().map_or(1, usize::from),
        n => n,
    };
    PasswordChecks::start(threads)
        .map_err(|e| ServerError::Other(format!("starting the password checks: {e}")))
}

/// Domain tokens shorter than this are warned about at every start.
pub const SHORT_DOMAIN_TOKEN: usize = 16;

/// `/healthz`: `ok`; 503 `unavailable: database: disk full` (or `unreachable`, `busy`, `I/O
/// error`) while the database takes no writes; in a cluster without NATS, or with a NATS that
/// refuses part of its work, `degraded` with the reason (still 200: the process serves the
/// gateways it holds).
async fn health(State((registry, store)): State<(Arc<Registry>, Store)>) -> Response {
    if let Some((trouble, since)) = store.health().trouble() {
        let text = format!(
            "unavailable: database: {trouble} (for {} s; writes wait or are refused, reads go on)\n",
            since.as_secs()
        );
        return (StatusCode::SERVICE_UNAVAILABLE, text).into_response();
    }
    let text: String = match registry.cluster() {
        Some(cluster) if !cluster.connected() => {
            let why = cluster
                .last_error()
                .map(|e| format!(": {e}"))
                .unwrap_or_default();
            format!("degraded: NATS unreachable{why} (lifts held by other processes answer 503)\n")
        }
        Some(cluster) => match cluster.refused() {
            Some(why) => format!(
                "degraded: NATS refuses this process: {why} (the permissions of its NATS user)\n"
            ),
            None => "ok\n".into(),
        },
        None => "ok\n".into(),
    };
    text.into_response()
}

/// How long a client may take for its TLS handshake, as for each HTTP request head after it
/// (docs/SECURITY.md §Bounds): a connection that says nothing, or says it slowly, is closed.
pub const HANDSHAKE_TIMEOUT: std::time::Duration = crate::connection::HEAD_TIMEOUT;

/// The alarm service and the webhook worker, started, and the queue the gateway connections
/// report into.
fn start_alarms(
    config: &Config,
    store: &Store,
    registry: &Arc<Registry>,
    insights: &crate::config::Insights,
    timings: &crate::metrics::Timings,
    tasks: &mut Vec<tokio::task::JoinHandle<()>>,
) -> Result<(Arc<Alarms>, Reports), ServerError> {
    let receivers = config
        .alarms
        .webhooks
        .iter()
        .enumerate()
        .map(|(i, section)| webhook::Receiver::new(section, i + 1))
        .collect::<Result<Vec<_>, _>>()
        .map_err(ServerError::Other)?;
    let (reports, reports_rx) = Reports::channel(65536);
    let (acknowledged, acknowledged_rx) = mpsc::channel(1024);
    let alarms = Arc::new(Alarms {
        store: store.clone(),
        registry: registry.clone(),
        acknowledged,
        webhooks: config.alarms.webhooks.clone(),
        outbox: Arc::default(),
        counters: Arc::default(),
    });
    let rules = Rules {
        severities: config.alarms.severity,
    };
    let offline_after = std::time::Duration::from_secs(config.alarms.offline_after_s.max(1));
    let (trends, trends_rx) = mpsc::channel(16);
    tasks.push(tokio::spawn(crate::insights::trends::run(
        store.clone(),
        insights.trends.clone(),
        rules,
        trends,
    )));
    tasks.push(tokio::spawn(service::run(
        alarms.clone(),
        rules,
        offline_after,
        reports_rx,
        acknowledged_rx,
        trends_rx,
    )));
    tasks.push(tokio::spawn(webhook::deliver(
        alarms.clone(),
        receivers,
        timings.webhooks.clone(),
    )));
    Ok((alarms, reports))
}

/// Time an operator request (REST API or web UI) until its answer's head, by its route's
/// template (`/api/v1/lifts/{id}/objects/{mplex}`: the ids are not labels) and method.
async fn time_request(
    State(requests): State<prometheus::HistogramVec>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    let route = request
        .extensions()
        .get::<axum::extract::MatchedPath>()
        .map_or_else(|| "unmatched".to_owned(), |p| p.as_str().to_owned());
    let method = request.method().clone();
    let started = std::time::Instant::now();
    let response = next.run(request).await;
    requests
        .with_label_values(&[route.as_str(), method.as_str()])
        .observe(started.elapsed().as_secs_f64());
    response
}

/// What renders `/metrics`.
type Metered = Arc<dyn Fn() -> String + Send + Sync>;

/// `/metrics` on the public port: for the bearer of `[server] metrics_token` alone (compared in
/// constant time).
fn public_metrics(token: &str, headers: &axum::http::HeaderMap, render: &Metered) -> Response {
    let given = headers
        .get(axum::http::header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .unwrap_or_default();
    let digest = |t: &str| cloud_store::digest(t);
    if !nxg::digest::matches(&digest(given.trim()), &digest(token)) {
        return (
            StatusCode::UNAUTHORIZED,
            [(axum::http::header::WWW_AUTHENTICATE, "Bearer")],
            "metrics: Authorization: Bearer [server] metrics_token\n",
        )
            .into_response();
    }
    metrics_response(render)
}

/// The metrics in Prometheus's text format.
fn metrics_response(render: &Metered) -> Response {
    (
        [(
            axum::http::header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        render(),
    )
        .into_response()
}

/// `/metrics` alone, in plain HTTP, on `listen` (`[server] metrics_listen`: a scraper on the
/// portal's network); the task that serves it. Its connections have the public port's bounds
/// (`connection::serve`): a scraper keeps its connection between scrapes, a client that says
/// nothing is closed.
async fn serve_metrics(
    listen: SocketAddr,
    render: Metered,
) -> Result<tokio::task::JoinHandle<()>, ServerError> {
    let listener = tokio::net::TcpListener::bind(listen)
        .await
        .map_err(|e| ServerError::Other(format!("[server] metrics_listen {listen}: {e}")))?;
    let router = Router::new().route(
        "/metrics",
        get(move || async move { metrics_response(&render) }),
    );
    Ok(tokio::spawn(async move {
        loop {
            let (tcp, _) = accept_next(&listener, |e, first| {
                if first {
                    tracing::warn!(error = %e, "the metrics listener's accept failed");
                }
            })
            .await;
            let router = router.clone();
            tokio::spawn(async move {
                let _ = crate::connection::serve(tcp, router).await;
            });
        }
    }))
}

/// The values of the families the portal counts in its own atomics (docs/PORTAL.md §Metrics).
fn samples(
    m: &Metrics,
    r: &Registry,
    telemetry: &telemetry::Queue,
    a: &service::Counters,
    reports: &Reports,
    admitted: &gateways::admissions::AdmissionCounters,
) -> Vec<Sample> {
    let t = telemetry.counters();
    let load = |c: &AtomicU64| c.load(Ordering::Relaxed);
    let mut samples = vec![
        Sample::of("canlift_gateway_connections_total", load(&m.connections)),
        Sample::of(
            "canlift_gateway_upgrades_refused_total",
            load(&m.upgrades_refused),
        ),
        Sample::of("canlift_gateways_admitted_total", load(&admitted.admitted)),
        Sample::of(
            "canlift_gateways_registry_unavailable_total",
            load(&admitted.unavailable),
        ),
        Sample::of("canlift_admission_lookups_total", load(&admitted.lookups)),
        Sample::of("canlift_accept_failures_total", load(&m.accept_failures)),
        Sample::of(
            "canlift_tls_handshakes_full_total",
            load(&m.handshakes_full),
        ),
        Sample::of(
            "canlift_tls_handshakes_resumed_total",
            load(&m.handshakes_resumed),
        ),
        Sample::of(
            "canlift_tls_handshakes_abandoned_total",
            load(&m.handshakes_abandoned),
        ),
        Sample::of("canlift_memory_trims_total", load(&m.memory_trims)),
        Sample::of(
            "canlift_memory_trimmed_bytes_total",
            load(&m.memory_trimmed_bytes),
        ),
        Sample::of("canlift_telemetry_stored_total", load(&t.stored)),
        Sample::of("canlift_telemetry_waits_total", load(&t.waits)),
        Sample::of("canlift_events_stored_total", load(&a.events_stored)),
        Sample::of(
            "canlift_events_dropped_total",
            load(&a.events_dropped) + reports.dropped(),
        ),
        Sample::of("canlift_alarms_raised_total", load(&a.raised)),
        Sample::of("canlift_alarms_cleared_total", load(&a.cleared)),
        Sample::of(
            "canlift_webhooks_delivered_total",
            load(&a.webhooks_delivered),
        ),
        Sample::of(
            "canlift_webhook_attempts_failed_total",
            load(&a.webhooks_failed),
        ),
        Sample::of(
            "canlift_webhooks_given_up_total",
            load(&a.webhooks_given_up),
        ),
        Sample::of("canlift_gateways_online", r.online_count() as u64),
        Sample::of("canlift_telemetry_queued", telemetry.queued() as u64),
        Sample::of(
            "canlift_webhooks_pending",
            a.webhooks_pending.load(Ordering::Relaxed),
        ),
    ];
    samples.extend(telemetry::Dropped::ALL.iter().map(|why| {
        Sample::labelled(
            "canlift_telemetry_dropped_total",
            why.name(),
            t.dropped(*why),
        )
    }));
    if let Some(c) = r.cluster() {
        let n = &c.counters;
        samples.extend([
            Sample::of("canlift_cluster_nats_connected", u64::from(c.connected())),
            Sample::of("canlift_cluster_lifts_held", c.held_count() as u64),
            Sample::of("canlift_cluster_lifts_elsewhere", c.known_count() as u64),
            Sample::of("canlift_cluster_processes", c.processes() as u64),
            Sample::of("canlift_cluster_requests_relayed_total", load(&n.relayed)),
            Sample::of(
                "canlift_cluster_requests_failed_total",
                load(&n.relay_failed),
            ),
            Sample::of("canlift_cluster_requests_served_total", load(&n.served)),
            Sample::of("canlift_cluster_replaced_total", load(&n.replaced)),
            Sample::of(
                "canlift_cluster_events_dropped_total",
                load(&n.events_dropped),
            ),
            Sample::of(
                "canlift_cluster_events_unwatched_total",
                load(&n.events_unwatched),
            ),
            Sample::of("canlift_cluster_watch_lapsed_total", load(&n.watch_lapsed)),
            Sample::of("canlift_cluster_entries_swept_total", load(&n.swept)),
            Sample::of("canlift_cluster_nats_refused_total", load(&n.nats_refused)),
            Sample::of(
                "canlift_cluster_nats_slow_consumer_total",
                load(&n.nats_slow),
            ),
        ]);
    }
    samples
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use std::os::fd::AsRawFd;

    use super::*;

    /// The bound of a listening socket's accept queue, as Linux reports it (`tcpi_sacked` of a
    /// listener's `TCP_INFO`).
    fn accept_queue_bound(listener: &TcpListener) -> u32 {
        // SAFETY: `tcp_info` is plain integers, for which all zeroes is a value.
        let mut info: libc::tcp_info = unsafe { std::mem::zeroed() };
        let mut len = std::mem::size_of::<libc::tcp_info>() as libc::socklen_t;
        // SAFETY: `info` is a valid `tcp_info` of `len` bytes; the descriptor is the listener's.
        let rc = unsafe {
            libc::getsockopt(
                listener.as_raw_fd(),
                libc::IPPROTO_TCP,
                libc::TCP_INFO,
                std::ptr::addr_of_mut!(info).cast(),
                &mut len,
            )
        };
        assert_eq!(rc, 0, "{}", std::io::Error::last_os_error());
        info.tcpi_sacked
    }

    #[test]
    fn a_failing_accept_is_tried_again_later_each_time_up_to_a_second() {
        let waits: Vec<u128> =
            std::iter::successors(Some(accept_retry(None)), |&w| Some(accept_retry(Some(w))))
                .take(10)
                .map(|w| w.as_millis())
                .collect();
        assert_eq!(waits, [5, 10, 20, 40, 80, 160, 320, 640, 1000, 1000]);
    }

    #[tokio::test]
    async fn the_listen_queue_is_as_long_as_the_system_allows() {
        let listener = listen(SocketAddr::from(([127, 0, 0, 1], 0))).unwrap();
        let somaxconn: u32 = std::fs::read_to_string("/proc/sys/net/core/somaxconn")
            .unwrap()
            .trim()
            .parse()
            .unwrap();
        assert_eq!(accept_queue_bound(&listener), somaxconn.min(LISTEN_BACKLOG));
    }
}
