//! The operator CLI against a running portal, gateway and simulated lift: `lifts`, `get`, `put`
//! (learning datatype and unit first) and `watch` until the trip counter rises.

use std::process::Stdio;
use std::time::Duration;

use cloud::config::Config;
use cloud::server::Portal;
use cloud::store::Store;
use lift417::sim::{SimConfig, Simulator};
use tokio::io::{AsyncBufReadExt, BufReader};

fn canlift(portal: &str, key: &str, ca: &std::path::Path) -> tokio::process::Command {
    let mut cmd = tokio::process::Command::new(env!("CARGO_BIN_EXE_canlift"));
    cmd.env("CANLIFT_PORTAL", portal)
        .env("CANLIFT_API_KEY", key)
        .env("CANLIFT_CA", ca)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    cmd
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lifts_get_put_watch() {
    let dir = std::env::temp_dir().join(format!("canlift-opcli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = Config::default();
    config.server.listen = "127.0.0.1:0".parse().unwrap();
    config.state.dir = dir.join("portal");
    let portal = Portal::bind(&config).await.unwrap();
    let port = portal.local_addr().port();
    let key = Store::open(&config.database_url())
        .await
        .unwrap()
        .add_account("masora", "MAS")
        .await
        .unwrap();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let portal_task = tokio::spawn(portal.run(stopped));
    let bus = "mem://opcli";
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
        sernum: "OP-1".into(),
        vendorid: 1050,
        productcode: 4096,
        domaintoken: "MAS".into(),
        ..Default::default()
    };
    let portal_ws = format!("wss://localhost:{port}/ws");
    let gw =
        gateway::config::Config::for_portal(identity, &portal_ws, &ca, bus, &dir.join("gateway"));
    let gateway = gateway::Gateway::bus_node(gw).await.unwrap();
    let (gw_stop, gw_stopped) = tokio::sync::watch::channel(false);
    let gw_task = tokio::spawn(gateway.run(gw_stopped));
    let url = format!("https://localhost:{port}");
    let lift = "1050-4096-OP-1";
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let out = canlift(&url, &key, &ca)
            .args(["lifts", "--json"])
            .output()
            .await
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let lifts: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        if lifts[0]["online"] == true {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "not online: {lifts}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let table = canlift(&url, &key, &ca)
        .arg("lifts")
        .output()
        .await
        .unwrap();
    assert!(String::from_utf8_lossy(&table.stdout).contains("1050-4096-OP-1"));
    let get = canlift(&url, &key, &ca)
        .args(["get", lift, "0x652001", "--naked"])
        .output()
        .await
        .unwrap();
    let answer: serde_json::Value = serde_json::from_slice(&get.stdout).unwrap();
    assert_eq!(answer["object"]["value"][0], "0");
    // watch first, then call the car: the baseline and the new trip count come out.
    let mut watch = canlift(&url, &key, &ca)
        .args(["watch", lift, "0x652001", "--count", "2"])
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(watch.stdout.take().unwrap()).lines();
    let first = tokio::time::timeout(Duration::from_secs(10), lines.next_line())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(first.ends_with(" 0x652001 0"), "{first}");
    let put = canlift(&url, &key, &ca)
        .args(["put", lift, "0x502200", "2"])
        .output()
        .await
        .unwrap();
    assert!(
        put.status.success(),
        "{}",
        String::from_utf8_lossy(&put.stderr)
    );
    let second = tokio::time::timeout(Duration::from_secs(15), lines.next_line())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(second.ends_with(" 0x652001 1"), "{second}");
    assert!(tokio::time::timeout(Duration::from_secs(5), watch.wait())
        .await
        .unwrap()
        .unwrap()
        .success());
    // Errors are reported with the abort code.
    let refused = canlift(&url, &key, &ca)
        .args(["put", lift, "0x652001", "5"])
        .output()
        .await
        .unwrap();
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("06010002h"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
    gw_stop.send(true).unwrap();
    gw_task.await.unwrap();
    stop.send(true).unwrap();
    portal_task.await.unwrap();
    sim.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
