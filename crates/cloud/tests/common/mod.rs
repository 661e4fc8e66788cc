//! A portal with one real gateway in front of the simulated lift (on an in-process bus), as the
//! end-to-end and browser tests use it.

use std::path::PathBuf;
use std::time::Duration;

use cloud::config::Config;
use cloud::server::Portal;
use cloud::store::Store;
use lift417::sim::{SimConfig, Simulator};
use serde_json::Value;
use tokio::sync::watch;
use tokio::task::JoinHandle;

/// The lift's id at the portal.
pub const LIFT: &str = "1050-4096-180917010200000102";
/// The service password the gateway accepts (it keeps only its SHA-1).
pub const SERVICE_PASSWORD: &str = "service-2026";

/// Portal, gateway and simulator, running.
pub struct Rig {
    pub dir: PathBuf,
    pub addr: std::net::SocketAddr,
    pub ca: PathBuf,
    pub key: String,
    pub other_key: String,
    portal: Option<(watch::Sender<bool>, JoinHandle<()>)>,
    gateway: Option<(watch::Sender<bool>, JoinHandle<()>)>,
    sim: Option<Simulator>,
}

impl Rig {
    /// Start everything; `database` absent: SQLite in the state directory. `elevation` gives
    /// the gateway the SHA-1 of [`SERVICE_PASSWORD`].
    pub async fn start(name: &str, database: Option<String>, elevation: bool) -> Rig {
        let dir = std::env::temp_dir().join(format!("canlift-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut config = Config::default();
        config.database.url = database;
        config.server.listen = "127.0.0.1:0".parse().unwrap();
        config.state.dir = dir.join("portal");
        // One dashboard object this lift lacks: the portal must fall back to subscribing the
        // others one by one (reg_canopen_object is all or none).
        config.dashboard.live.push("0x5FFF00".into());
        let portal = Portal::bind(&config).await.unwrap();
        let addr = portal.local_addr();
        let store = Store::open(&config.database_url()).await.unwrap();
        let key = store.add_account("masora", "MAS").await.unwrap();
        let other_key = store.add_account("someone", "OTH").await.unwrap();
        let (stop, stopped) = watch::channel(false);
        let portal_task = tokio::spawn(portal.run(stopped));

        let bus = format!("mem://{name}");
        let sim = Simulator::start(
            &bus,
            SimConfig {
                speed: 20.0,
                ..SimConfig::default()
            },
        )
        .await
        .unwrap();
        let ca = config.state.dir.join("dev-ca.pem");
        let identity = nxg::gateway::Identity {
            sernum: "180917010200000102".into(),
            vendorid: 1050,
            productcode: 4096,
            domaintoken: "MAS".into(),
            liftnum: "40/7289/20399-126".into(),
            ..Default::default()
        };
        let portal_ws = format!("wss://localhost:{}/ws", addr.port());
        let mut gw = gateway::config::Config::for_portal(
            identity,
            &portal_ws,
            &ca,
            &bus,
            &dir.join("gateway"),
        );
        gw.bus.poll_ms = 100;
        if elevation {
            let sha1 = ring::digest::digest(
                &ring::digest::SHA1_FOR_LEGACY_USE_ONLY,
                SERVICE_PASSWORD.as_bytes(),
            );
            gw.privileges.service_sha1 = Some(cloud::store::hex(sha1.as_ref()));
        }
        let gateway = gateway::Gateway::bus_node(gw).await.unwrap();
        let (gw_stop, gw_stopped) = watch::channel(false);
        let gw_task = tokio::spawn(gateway.run(gw_stopped));
        Rig {
            dir,
            addr,
            ca,
            key,
            other_key,
            portal: Some((stop, portal_task)),
            gateway: Some((gw_stop, gw_task)),
            sim: Some(sim),
        }
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
        let client = cloud::client::Client::new(&self.url(), key, Some(&self.ca)).unwrap();
        client.call(method, path, body).await.unwrap()
    }

    /// Wait until the lift is online at the portal.
    pub async fn online(&self) -> Value {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
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

    /// Stop the gateway (the lift goes offline).
    pub async fn stop_gateway(&mut self) {
        if let Some((stop, task)) = self.gateway.take() {
            stop.send(true).unwrap();
            task.await.unwrap();
        }
    }

    /// Stop everything and remove the state.
    pub async fn stop(mut self) {
        self.stop_gateway().await;
        if let Some((stop, task)) = self.portal.take() {
            stop.send(true).unwrap();
            task.await.unwrap();
        }
        if let Some(sim) = self.sim.take() {
            sim.stop().await;
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
