//! End to end: the real gateway in front of the simulated lift, connected to the portal; an
//! operator reads, writes and watches through the REST API.

use std::path::Path;
use std::time::Duration;

use cloud::config::Config;
use cloud::server::Portal;
use cloud::store::Store;
use lift417::sim::{SimConfig, Simulator};
use serde_json::{json, Value};

/// The operator client with a key per call.
struct Client {
    url: String,
    ca: std::path::PathBuf,
}

impl Client {
    fn new(addr: std::net::SocketAddr, ca: &Path) -> Client {
        Client {
            url: format!("https://localhost:{}", addr.port()),
            ca: ca.to_path_buf(),
        }
    }

    async fn call(
        &self,
        method: &str,
        path: &str,
        key: Option<&str>,
        body: Option<Value>,
    ) -> (u16, Value) {
        let client = cloud::client::Client::new(&self.url, key, Some(&self.ca)).unwrap();
        client.call(method, path, body).await.unwrap()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_sqlite() {
    operator_reads_writes_and_watches_a_simulated_lift("sqlite", None).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_postgres() {
    let Some(url) = testkit::postgres("e2e").await else {
        return;
    };
    operator_reads_writes_and_watches_a_simulated_lift("postgres", Some(url)).await;
}

async fn operator_reads_writes_and_watches_a_simulated_lift(name: &str, database: Option<String>) {
    let dir = std::env::temp_dir().join(format!("canlift-e2e-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = Config::default();
    config.database.url = database;
    config.server.listen = "127.0.0.1:0".parse().unwrap();
    config.state.dir = dir.join("portal");
    let portal = Portal::bind(&config).await.unwrap();
    let addr = portal.local_addr();
    let store = Store::open(&config.database_url()).await.unwrap();
    let key = store.add_account("masora", "MAS").await.unwrap();
    let other = store.add_account("someone", "OTH").await.unwrap();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let portal_task = tokio::spawn(portal.run(stopped));

    let bus = format!("mem://e2e-{name}");
    let bus = bus.as_str();
    let sim = Simulator::start(
        bus,
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
    let mut gw =
        gateway::config::Config::for_portal(identity, &portal_ws, &ca, bus, &dir.join("gateway"));
    gw.bus.poll_ms = 100;
    let gateway = gateway::Gateway::bus_node(gw).await.unwrap();
    let (gw_stop, gw_stopped) = tokio::sync::watch::channel(false);
    let gw_task = tokio::spawn(gateway.run(gw_stopped));

    let client = Client::new(addr, &ca);
    let lift = "1050-4096-180917010200000102";
    // Online, with its identity.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let (status, lifts) = client.call("GET", "/api/v1/lifts", Some(&key), None).await;
        assert_eq!(status, 200, "{lifts}");
        if lifts[0]["online"] == true {
            assert_eq!(lifts[0]["id"], lift);
            assert_eq!(lifts[0]["liftnum"], "40/7289/20399-126");
            assert_eq!(lifts[0]["api"], 1);
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the gateway did not come online: {lifts}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The token was issued, confirmed and stored on both sides.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    let token = loop {
        if let Ok(token) = std::fs::read_to_string(dir.join("gateway/cloudtoken")) {
            break token;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "no token stored by the gateway"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(token.trim().len(), 32);
    // Auth and isolation.
    assert_eq!(client.call("GET", "/api/v1/lifts", None, None).await.0, 401);
    assert_eq!(
        client
            .call("GET", "/api/v1/lifts", Some("clk_nope"), None)
            .await
            .0,
        401
    );
    let (status, lifts) = client
        .call("GET", "/api/v1/lifts", Some(&other), None)
        .await;
    assert_eq!((status, lifts), (200, json!([])));
    let path = format!("/api/v1/lifts/{lift}/objects/0x652001?form=naked");
    assert_eq!(client.call("GET", &path, Some(&other), None).await.0, 404);
    // Read.
    let (status, trip) = client.call("GET", &path, Some(&key), None).await;
    assert_eq!(
        (status, &trip),
        (
            200,
            &json!({"object": {"mplex": "0x652001", "value": ["0"]}})
        )
    );
    let (status, full) = client
        .call(
            "GET",
            &format!("/api/v1/lifts/{lift}/objects/0x652001?lang=de"),
            Some(&key),
            None,
        )
        .await;
    assert_eq!(status, 200);
    assert_eq!(full["object"]["name"], "Fahrtenzähler [Fahrten]");
    // NXg errors as 4xx with code, message, data.
    let (status, e) = client
        .call(
            "GET",
            &format!("/api/v1/lifts/{lift}/objects/0x5FFF00"),
            Some(&key),
            None,
        )
        .await;
    assert_eq!(
        (status, &e["code"], &e["data"]),
        (404, &json!(0x0602_0000), &json!("0x5FFF00"))
    );
    // Subscribe, call the car, see the trip counter in the history.
    let (status, _) = client
        .call(
            "POST",
            &format!("/api/v1/lifts/{lift}/subscriptions"),
            Some(&key),
            Some(json!({"mplex": ["0x652001"]})),
        )
        .await;
    assert_eq!(status, 200);
    let put = json!({"value": "3", "datatype": 7, "physunit": 0});
    let (status, answer) = client
        .call(
            "PUT",
            &format!("/api/v1/lifts/{lift}/objects/0x502200"),
            Some(&key),
            Some(put),
        )
        .await;
    assert_eq!(
        (status, answer),
        (200, json!({"object": {"mplex": "0x502200"}}))
    );
    let (status, e) = client
        .call(
            "PUT",
            &format!("/api/v1/lifts/{lift}/objects/0x411200"),
            Some(&key),
            Some(json!({"value": "1", "datatype": 5, "physunit": 0})),
        )
        .await;
    assert_eq!(
        (status, &e["code"]),
        (403, &json!(0x0800_0021)),
        "service rights needed"
    );
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    loop {
        let (_, h) = client
            .call(
                "GET",
                &format!("/api/v1/lifts/{lift}/objects/0x652001/history"),
                Some(&key),
                None,
            )
            .await;
        let values: Vec<&str> = h["values"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|v| v["value"].as_str())
            .collect();
        if values.contains(&"1") {
            assert_eq!(values[0], "0", "the baseline came first");
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "no trip in the history: {h}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // Elevation with a password the gateway has no hash for, and the audit log.
    let (status, e) = client
        .call(
            "POST",
            &format!("/api/v1/lifts/{lift}/privilege"),
            Some(&key),
            Some(json!({"privilege": 1, "password": "service"})),
        )
        .await;
    assert_eq!((status, &e["code"]), (403, &json!(0x0800_0020)));
    let (status, audit) = client.call("GET", "/api/v1/audit", Some(&key), None).await;
    assert_eq!(status, 200);
    let entries = audit.as_array().unwrap();
    assert_eq!(entries.len(), 3);
    let put_entry = entries.iter().find(|e| e["object"] == "0x502200").unwrap();
    assert_eq!(
        (
            &put_entry["account"],
            &put_entry["result"],
            &put_entry["new_value"]
        ),
        (&json!("masora"), &json!("ok"), &json!("3"))
    );
    assert!(entries
        .iter()
        .any(|e| e["action"] == "elevate" && e["result"] == "error 134217760"));
    let (_, other_audit) = client
        .call("GET", "/api/v1/audit", Some(&other), None)
        .await;
    assert_eq!(other_audit, json!([]));
    // The OpenAPI document and health.
    let (status, doc) = client.call("GET", "/api/v1/openapi.json", None, None).await;
    assert_eq!((status, &doc["openapi"]), (200, &json!("3.0.3")));
    assert_eq!(client.call("GET", "/healthz", None, None).await.0, 200);
    // The gateway goes away: offline → 503.
    gw_stop.send(true).unwrap();
    gw_task.await.unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(client.call("GET", &path, Some(&key), None).await.0, 503);
    stop.send(true).unwrap();
    portal_task.await.unwrap();
    sim.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
