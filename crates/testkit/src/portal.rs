//! The portal with the simulated lift and its gateway connected: what the end-to-end, browser
//! and CLI tests start.
//!
//! ```no_run
//! # async fn t() {
//! let rig = testkit::portal::Rig::builder().start().await;
//! rig.online().await;
//! let (status, lifts) = rig.call("GET", "/api/v1/lifts", Some(&rig.key), None).await;
//! # }
//! ```

use std::path::PathBuf;
use std::time::Duration;

use cloud::config::Config;
use cloud::server::Portal;
use cloud_store::Store;
use serde_json::Value;
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::constants::*;
use crate::lift::{gateway_config, Lift};

/// Wait until the async `check` holds, trying every 100 ms, for at most `limit` (then fail,
/// naming `what`); how long it took.
pub async fn until<F: std::future::Future<Output = bool>>(
    limit: Duration,
    what: &str,
    mut check: impl FnMut() -> F,
) -> Duration {
    let begin = tokio::time::Instant::now();
    while !check().await {
        assert!(begin.elapsed() < limit, "{what}: not within {limit:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    begin.elapsed()
}

/// How a [`Rig`] is set up.
pub struct Builder {
    database: Option<String>,
    lift: bool,
    portal: Box<dyn FnOnce(&mut Config)>,
    gateway: Box<dyn FnOnce(&mut gateway::config::Config)>,
    sim: Box<dyn FnOnce(&mut lift417::sim::SimConfig)>,
}

impl Builder {
    /// The portal's database (absent: SQLite in the state directory).
    pub fn database(mut self, url: Option<String>) -> Builder {
        self.database = url;
        self
    }

    /// No lift: the portal alone (for tests that bring their own gateway).
    pub fn without_lift(mut self) -> Builder {
        self.lift = false;
        self
    }

    /// Change the portal's configuration before it starts.
    pub fn portal(mut self, f: impl FnOnce(&mut Config) + 'static) -> Builder {
        self.portal = Box::new(f);
        self
    }

    /// Change the gateway's configuration before it starts.
    pub fn gateway(mut self, f: impl FnOnce(&mut gateway::config::Config) + 'static) -> Builder {
        self.gateway = Box::new(f);
        self
    }

    /// Change the simulator's configuration before it starts.
    pub fn sim(mut self, f: impl FnOnce(&mut lift417::sim::SimConfig) + 'static) -> Builder {
        self.sim = Box::new(f);
        self
    }

    /// Start the portal (accounts `masora` for the lift's domain and `someone` for another),
    /// the simulator and the gateway.
    pub async fn start(self) -> Rig {
        let dir = crate::scratch();
        let mut config = Config::default();
        config.database.url = self.database;
        config.server.listen = "127.0.0.1:0".parse().expect("an address");
        config.state.dir = dir.path().join("portal");
        config.server.metrics_token = Some(METRICS_TOKEN.into());
        (self.portal)(&mut config);
        let portal = Portal::bind(&config, lift417::catalog::Catalog::builtin().names())
            .await
            .expect("the portal binds");
        let addr = portal.local_addr();
        let registry = portal.registry();
        let store = Store::open(&config.database_url())
            .await
            .expect("the store opens");
        let key = store
            .add_account(ACCOUNT, DOMAIN)
            .await
            .expect("an account");
        let other_key = store
            .add_account("someone", "OTH")
            .await
            .expect("a second account");
        let (stop, stopped) = watch::channel(false);
        let portal_task = tokio::spawn(portal.run(stopped));
        let ca = config.state.dir.join("dev-ca.pem");
        let mut lift = None;
        if self.lift {
            let bus = format!("mem://rig-{}", addr.port());
            let ws = format!("wss://localhost:{}/ws", addr.port());
            let mut gw = gateway_config(&ws, &ca, &bus, &dir.path().join("gateway"));
            (self.gateway)(&mut gw);
            let mut sim = crate::lift::sim_config();
            (self.sim)(&mut sim);
            lift = Some((Lift::start(&bus, sim, gw.clone()).await, gw));
        }
        Rig {
            addr,
            ca,
            database_url: config.database_url(),
            config,
            registry,
            key,
            other_key,
            portal: Some((stop, portal_task)),
            lift,
            dir,
        }
    }
}

/// A hand-made gateway's WebSocket ([`Rig::hand_made_gateway`]).
pub type GatewaySocket =
    tokio_tungstenite::WebSocketStream<tokio_rustls::client::TlsStream<tokio::net::TcpStream>>;

/// Portal, gateway and simulator, running.
pub struct Rig {
    /// The portal's address.
    pub addr: std::net::SocketAddr,
    /// The development CA the portal serves a certificate of.
    pub ca: PathBuf,
    /// The API key of the lift's account.
    pub key: String,
    /// The API key of another account.
    pub other_key: String,
    database_url: String,
    config: Config,
    registry: std::sync::Arc<cloud::gateways::Registry>,
    portal: Option<(watch::Sender<bool>, JoinHandle<()>)>,
    /// The lift, and its gateway's configuration as the builder left it.
    lift: Option<(Lift, gateway::config::Config)>,
    dir: tempfile::TempDir,
}

impl Rig {
    /// A rig with the defaults.
    pub fn builder() -> Builder {
        Builder {
            database: None,
            lift: true,
            portal: Box::new(|_| {}),
            gateway: Box::new(|_| {}),
            sim: Box::new(|_| {}),
        }
    }

    /// The simulated lift (a rig built without one has none).
    pub fn sim(&self) -> &lift417::sim::Simulator {
        &self.lift.as_ref().expect("a rig with a lift").0.sim
    }

    /// The scratch directory (the portal's state in `portal/`, the gateway's in `gateway/`).
    pub fn dir(&self) -> &std::path::Path {
        self.dir.path()
    }

    /// The portal's store (another connection to its database).
    pub async fn store(&self) -> Store {
        Store::open(&self.database_url)
            .await
            .expect("the store opens")
    }

    /// The live gateways.
    pub fn registry(&self) -> &cloud::gateways::Registry {
        &self.registry
    }

    /// A hand-made gateway of the account of domain `domain` (the rig has `MAS` and `OTH`),
    /// identity `sernum`, admitted by the portal: a bare TLS WebSocket that says CONNECT and
    /// then only what the test sends (it answers none of the portal's requests).
    pub async fn hand_made_gateway(&self, sernum: &str, domain: &str) -> GatewaySocket {
        match self.try_hand_made_gateway(sernum, domain).await {
            Ok(ws) => ws,
            Err(answer) => panic!("not admitted: {answer}"),
        }
    }

    /// [`Rig::hand_made_gateway`], or what the portal answered instead of CONNACK (a closed
    /// socket: `closed`).
    pub async fn try_hand_made_gateway(
        &self,
        sernum: &str,
        domain: &str,
    ) -> Result<GatewaySocket, String> {
        use futures_util::StreamExt;
        use tokio_tungstenite::tungstenite::Message;
        let mut ws = self.hand_made_connect(sernum, domain).await;
        match ws.next().await {
            Some(Ok(Message::Text(answer))) if answer.contains("CONNACK") => Ok(ws),
            Some(Ok(other)) => Err(other.to_string()),
            Some(Err(e)) => Err(e.to_string()),
            None => Err("closed".into()),
        }
    }

    /// A hand-made gateway as [`Rig::hand_made_gateway`] makes it, its CONNECT sent and the
    /// portal's answer not read.
    pub async fn hand_made_connect(&self, sernum: &str, domain: &str) -> GatewaySocket {
        use futures_util::SinkExt;
        use tokio_tungstenite::tungstenite::client::IntoClientRequest;
        use tokio_tungstenite::tungstenite::Message;
        let config = tls::client_config(Some(&self.ca), None).expect("the portal's CA");
        let tcp = tokio::net::TcpStream::connect(self.addr)
            .await
            .expect("TCP");
        let name =
            tokio_rustls::rustls::pki_types::ServerName::try_from("localhost").expect("a name");
        let tls = tokio_rustls::TlsConnector::from(config)
            .connect(name, tcp)
            .await
            .expect("TLS");
        let mut request = self.ws_url().into_client_request().expect("a request");
        request.headers_mut().insert(
            "Sec-WebSocket-Protocol",
            tokio_tungstenite::tungstenite::http::HeaderValue::from_static("cloud"),
        );
        let (mut ws, _) = tokio_tungstenite::client_async(request, tls)
            .await
            .expect("the upgrade");
        let connect = serde_json::json!({
            "jsonrpc": "2.0",
            "method": "CONNECT",
            "id": 1,
            "params": {
                "identity": {
                    "sernum": sernum, "vendorid": 1050, "productcode": 4096, "liftnum": "x",
                    "hardware": "x", "software": "1", "api": 1, "boardhash": "00"
                },
                "domaintoken": domain
            }
        });
        ws.send(Message::Text(connect.to_string().into()))
            .await
            .expect("sent");
        ws
    }

    /// `wss://localhost:PORT/ws`, where gateways connect.
    pub fn ws_url(&self) -> String {
        format!("wss://localhost:{}/ws", self.addr.port())
    }

    /// `https://localhost:PORT`.
    pub fn url(&self) -> String {
        format!("https://localhost:{}", self.addr.port())
    }

    /// One REST call with `key`: (status, JSON body).
    pub async fn call(
        &self,
        method: &str,
        path: &str,
        key: Option<&str>,
        body: Option<Value>,
    ) -> (u16, Value) {
        let client = cloud::client::Client::new(&self.url(), key, Some(&self.ca))
            .expect("a client of the portal");
        client
            .call(method, path, body)
            .await
            .expect("the portal answers")
    }

    /// The lift's value of `mplex` as the portal reads it now (`?form=naked`, first value).
    pub async fn naked(&self, mplex: &str) -> Value {
        let path = format!("/api/v1/lifts/{LIFT}/objects/{mplex}?form=naked");
        let (status, body) = self.call("GET", &path, Some(&self.key), None).await;
        assert_eq!(status, 200, "{mplex}: {body}");
        body["object"]["value"][0].clone()
    }

    /// One counter or gauge of the portal's `/metrics`.
    pub async fn metric(&self, name: &str) -> f64 {
        let client = cloud::client::Client::new(&self.url(), Some(METRICS_TOKEN), Some(&self.ca))
            .expect("a client of the portal");
        match client.metric(name).await {
            Ok(Some(value)) => value,
            other => panic!("/metrics, {name}: {other:?}"),
        }
    }

    /// Wait until the lift is online at the portal; the list of lifts.
    pub async fn online(&self) -> Value {
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            let (status, lifts) = self
                .call("GET", "/api/v1/lifts", Some(&self.key), None)
                .await;
            assert_eq!(status, 200, "{lifts}");
            if lifts[0]["online"] == true {
                return lifts;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "the gateway did not come online: {lifts}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Stop the portal and start it again on the same address, state and database (its
    /// gateways reconnect as after any restart).
    pub async fn restart_portal(&mut self) {
        self.stop_portal().await;
        let mut config = self.config.clone();
        config.server.listen = self.addr;
        let portal = Portal::bind(&config, lift417::catalog::Catalog::builtin().names())
            .await
            .expect("the portal binds again");
        self.registry = portal.registry();
        let (stop, stopped) = watch::channel(false);
        self.portal = Some((stop, tokio::spawn(portal.run(stopped))));
    }

    /// Stop the portal (as on SIGTERM): it returns once its gateways' connections ended and
    /// what they queued is written.
    pub async fn stop_portal(&mut self) {
        if let Some((stop, task)) = self.portal.take() {
            let _ = stop.send(true);
            let _ = task.await;
        }
    }

    /// Stop the gateway (the lift goes offline).
    pub async fn stop_gateway(&mut self) {
        if let Some((lift, _)) = &mut self.lift {
            lift.stop_gateway().await;
        }
    }

    /// Stop the gateway and start another in front of the same lift, with the rig's gateway
    /// configuration changed by `change` (another board, a wiped state directory, …).
    pub async fn restart_gateway(&mut self, change: impl FnOnce(&mut gateway::config::Config)) {
        let (lift, base) = self.lift.as_mut().expect("a rig with a lift");
        let mut config = base.clone();
        change(&mut config);
        lift.start_gateway(config).await;
    }

    /// The cloud token the gateway has stored, if any.
    pub fn gateway_token(&self) -> Option<String> {
        let (_, config) = self.lift.as_ref()?;
        gateway::token::TokenStore::new(&config.state.dir).load()
    }

    /// Stop everything; the scratch directory goes with the rig.
    pub async fn stop(mut self) {
        if let Some((lift, _)) = self.lift.take() {
            lift.stop().await;
        }
        self.stop_portal().await;
    }
}
