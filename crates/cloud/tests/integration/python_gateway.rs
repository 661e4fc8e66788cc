//! The portal's identity and token rules, checked by a fake gateway written with Python
//! `websockets` over Python's ssl (an independent implementation).

use std::collections::HashMap;
use std::time::Duration;

use serde_json::{json, Value};
use testkit::portal::Rig;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identity_and_token_rules() {
    let Some(python) = testkit::python() else {
        return;
    };
    let rig = Rig::builder()
        .without_lift()
        .portal(|config| {
            config.gateways.connect_timeout_s = 1;
            config.gateways.heartbeat_s = 1;
            // The fake gateway has no dictionary: no dashboard subscriptions, so that every
            // message it gets after CONNACK is the one the token rules predict.
            config.dashboard.live.clear();
        })
        .start()
        .await;
    let out = tokio::time::timeout(
        Duration::from_secs(120),
        tokio::process::Command::new(&python)
            .arg(testkit::interop_script("fake_gateway.py"))
            .arg(rig.ws_url())
            .arg(&rig.ca)
            .output(),
    )
    .await
    .expect("the fake gateway finishes")
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("DONE"), "{stdout}");
    let facts: HashMap<&str, Value> = stdout
        .lines()
        .filter_map(|l| l.split_once(' '))
        .map(|(k, v)| (k, serde_json::from_str(v).unwrap()))
        .collect();
    assert_eq!(facts["subprotocol"], "cloud");
    assert_eq!(
        facts["connack"],
        json!({"jsonrpc": "2.0", "id": 1, "result": "CONNACK", "api": 1})
    );
    assert_eq!(facts["update_method"], "update_unique_token");
    assert_eq!(facts["token_sernum"], "PY-0001");
    assert_eq!(facts["token_length"], 32);
    assert_eq!(facts["wrong_token"], "closed");
    assert_eq!(facts["missing_token"], "closed");
    assert_eq!(facts["known"], "CONNACK");
    assert_eq!(facts["second"], "CONNACK");
    assert_eq!(facts["first_after_second"], "closed");
    assert_eq!(facts["heartbeat"], "get_heartbeat");
    // Bus events are asked for by name of every gateway (docs/PROTOCOL.md §Events): this one, NXg
    // v1.0.0 only, answered −32601 (at least on the connection that got the heartbeat after it)
    // and was served on.
    let refused = facts["events_refused"].as_array().unwrap();
    assert!(!refused.is_empty());
    assert!(
        refused
            .iter()
            .all(|e| *e == json!(["emcy", "state", "bus"])),
        "{refused:?}"
    );
    assert_eq!(facts["silent"], "closed");
    // Liveness is NXg messages alone (NXg §5.3): websockets' pings and pongs every 0.5 s kept
    // nothing alive; the silence limit (2 × 1 s + 30 s) ended it, heartbeats unanswered.
    assert_eq!(facts["pinging_unanswered"], "closed");
    let lasted = facts["pinging_lasted_s"].as_u64().unwrap();
    assert!((31..=40).contains(&lasted), "closed after {lasted} s");
    assert!(facts["pinging_heartbeats"].as_u64().unwrap() >= 20);
    assert_eq!(facts["no_subprotocol"], 400);
    // The refusals were recorded.
    let refusals = rig
        .store()
        .await
        .refusals("1050-4096-PY-0001")
        .await
        .unwrap();
    assert_eq!(refusals.len(), 2, "{refusals:?}");
    assert!(refusals.iter().any(|r| r.cause == "wrong cloud token"));
    rig.stop().await;
}
