//! `canlift loadgen` against a portal: its gateways come online from several loopback source
//! addresses with first-contact tokens, come back later as known lifts with those tokens, and
//! push what the portal subscribes once the simulated values change.

use std::time::Duration;

use cloud::config::Config;
use cloud::server::Portal;
use cloud::store::Store;

async fn loadgen(args: &[&str]) -> String {
    let out = tokio::time::timeout(
        Duration::from_secs(120),
        tokio::process::Command::new(env!("CARGO_BIN_EXE_canlift"))
            .arg("loadgen")
            .args(args)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("loadgen finishes")
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gateways_connect_reconnect_and_push() {
    let dir = std::env::temp_dir().join(format!("canlift-loadgen-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = Config::default();
    config.server.listen = "127.0.0.1:0".parse().unwrap();
    config.state.dir = dir.join("portal");
    let portal = Portal::bind(&config).await.unwrap();
    let port = portal.local_addr().port();
    let registry = portal.registry();
    let store = Store::open(&config.database_url()).await.unwrap();
    store.add_account("load", "LOAD").await.unwrap();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(portal.run(stopped));
    let url = format!("wss://localhost:{port}/ws");
    let ca = config.state.dir.join("dev-ca.pem");
    let state = dir.join("gateways");
    let common = [
        "--portal",
        url.as_str(),
        "--ca",
        ca.to_str().unwrap(),
        "--domain",
        "LOAD",
        "--gateways",
        "60",
        "--sources",
        "4",
        "--state",
        state.to_str().unwrap(),
    ];

    // First contact: every gateway gets a token and keeps it.
    let mut first = common.to_vec();
    first.push("--until-online");
    let out = loadgen(&first).await;
    assert!(out.contains("all 60 online"), "{out}");
    let lifts = store.lifts("LOAD").await.unwrap();
    assert_eq!(lifts.len(), 60);
    assert!(lifts.iter().any(|l| l.id == "1050-4097-LOAD-000060"));
    for n in [1, 30, 60] {
        let token = std::fs::read_to_string(state.join(format!("gw-{n:06}/cloudtoken"))).unwrap();
        assert_eq!(token.trim().len(), 32);
    }

    // Again, as known lifts: the stored tokens are accepted, nothing is refused.
    let out = loadgen(&first).await;
    assert!(out.contains("all 60 online"), "{out}");
    for n in [1, 60] {
        let refused = store
            .refusals(&format!("1050-4097-LOAD-{n:06}"))
            .await
            .unwrap();
        assert!(refused.is_empty(), "{refused:?}");
    }
    // Exiting closed every connection.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while registry.online_count() > 0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "loadgen left gateways online"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // Changing values: the dashboard's objects are pushed and stored.
    let mut pushing = common.to_vec();
    pushing.extend(["--change-ms", "50"]);
    let mut child = tokio::process::Command::new(env!("CARGO_BIN_EXE_canlift"))
        .arg("loadgen")
        .args(&pushing)
        .stdout(std::process::Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let values = store
            .history("1050-4097-LOAD-000042", "0x638301", 0, i64::MAX)
            .await
            .unwrap();
        if values.len() >= 3 {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "no pushed positions: {values:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let pid = child.id().unwrap().to_string();
    let _ = std::process::Command::new("kill")
        .args(["-INT", &pid])
        .status();
    let status = tokio::time::timeout(Duration::from_secs(20), child.wait())
        .await
        .expect("loadgen stops on SIGINT")
        .unwrap();
    assert!(status.success());
    stop.send(true).unwrap();
    task.await.unwrap();
    let _ = std::fs::remove_dir_all(&dir);
}
