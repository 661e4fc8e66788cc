//! `canlift loadgen` against a portal: its gateways come online from several loopback source
//! addresses with first-contact tokens, come back later as known lifts with those tokens, and
//! push what the portal subscribes once the simulated values change.

use std::time::Duration;

use testkit::portal::Rig;

use crate::common;
use common::{canlift, interrupt};

async fn loadgen(args: &[&str]) -> String {
    let out = tokio::time::timeout(
        Duration::from_secs(120),
        canlift().arg("loadgen").args(args).output(),
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
    let rig = Rig::builder().without_lift().start().await;
    let store = rig.store().await;
    store.add_account("load", "LOAD").await.unwrap();
    let url = rig.ws_url();
    let ca = rig.ca.clone();
    let state = rig.dir().join("gateways");
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
    while rig.registry().online_count() > 0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "loadgen left gateways online"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // Changing values: the dashboard's objects are pushed and stored.
    let mut pushing = common.to_vec();
    pushing.extend(["--change-ms", "50"]);
    let mut child = canlift()
        .arg("loadgen")
        .args(&pushing)
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let values = store
            .values("1050-4097-LOAD-000042", "0x638301", 0, i64::MAX, 100)
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
    let status = interrupt(&mut child, Duration::from_secs(20)).await;
    assert!(status.success(), "loadgen stops on SIGINT: {status:?}");
    rig.stop().await;
}
