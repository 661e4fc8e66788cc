//! Subscriptions that belong to someone (docs/PORTAL.md §Subscriptions), seen from a fake
//! gateway written with Python `websockets` that reports every `reg_canopen_object` and
//! `unreg_canopen_object` the portal sends: the gateway always has the union of what the
//! dashboard, an account and a live watcher hold — the smallest inhibit and threshold — one
//! holder letting go never ends another's pushes, and a reconnect registers everything again —
//! the account's subscriptions also after the portal restarted.

use std::time::Duration;

use serde_json::json;
use testkit::constants::WAIT;
use testkit::portal::Rig;
use testkit::script::Script;

const LIFT: &str = "1050-4096-PY-SUBS";

/// Wait until the gateway has reported exactly `expected` (registrations and unregistrations,
/// in order) and no more.
async fn registrations(gateway: &Script, expected: &[&str]) {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let seen: Vec<String> = gateway
            .seen("")
            .into_iter()
            .filter(|l| l.starts_with("REG ") || l.starts_with("UNREG "))
            .collect();
        if seen.len() >= expected.len() {
            assert_eq!(seen, expected);
            // Nothing more follows a moment later.
            tokio::time::sleep(Duration::from_millis(300)).await;
            assert_eq!(
                gateway.seen("REG ").len() + gateway.seen("UNREG ").len(),
                expected.len()
            );
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "expected {expected:?}, seen {seen:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_has_the_union_of_what_everyone_holds() {
    let Some(python) = testkit::python() else {
        return;
    };
    let mut rig = Rig::builder()
        .without_lift()
        .portal(|c| {
            c.dashboard.live = vec!["0x652001".into(), "0x100100".into()];
            c.dashboard.inhibit_ms = 500;
        })
        .start()
        .await;
    let ca = rig.ca.display().to_string();
    let mut gateway = Script::start(
        &python,
        "event_gateway.py",
        &[&rig.ws_url(), &ca, "PY-SUBS"],
    );
    gateway.wait_for("CONNACK", 1, WAIT).await;
    let mut expected = vec!["REG 500 0.0 0x100100,0x652001"];
    registrations(&gateway, &expected).await;

    // A live watcher wants the trip counter every 100 ms.
    let client = cloud::client::Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca)).unwrap();
    let path = format!("/api/v1/lifts/{LIFT}/events?mplex=0x652001&inhibit=100");
    let watcher = client
        .events(&path)
        .await
        .unwrap()
        .expect("an event stream");
    expected.push("REG 100 0.0 0x652001");
    registrations(&gateway, &expected).await;

    // An account holds it more coarsely (nothing changes at the gateway) and the speed.
    let subscriptions = format!("/api/v1/lifts/{LIFT}/subscriptions");
    let hold = |body| rig.call("POST", &subscriptions, Some(&rig.key), Some(body));
    let speed = json!({"mplex": ["0x638301"], "inhibit": 1000, "threshold": 2.0});
    assert_eq!(
        hold(json!({"mplex": ["0x652001"], "inhibit": 1000}))
            .await
            .0,
        200
    );
    assert_eq!(hold(speed.clone()).await.0, 200);
    expected.push("REG 1000 2.0 0x638301");
    registrations(&gateway, &expected).await;

    // The account lets go of the trip counter and of an object it never held: the watcher's
    // and the dashboard's stay.
    let release = |body| rig.call("DELETE", &subscriptions, Some(&rig.key), Some(body));
    assert_eq!(
        release(json!({"mplex": ["0x652001", "0x100100"]})).await.0,
        200
    );
    registrations(&gateway, &expected).await;

    // The gateway reconnects: everything held is registered again, grouped by terms.
    gateway.say("CLOSE").await;
    gateway.wait_for("CLOSED", 1, WAIT).await;
    gateway.say("CONNECT").await;
    gateway.wait_for("CONNACK", 2, WAIT).await;
    expected.extend([
        "REG 500 0.0 0x100100",
        "REG 1000 2.0 0x638301",
        "REG 100 0.0 0x652001",
    ]);
    registrations(&gateway, &expected).await;

    // The watcher's stream ends: the trip counter goes back to the dashboard's terms.
    drop(watcher);
    expected.push("REG 500 0.0 0x652001");
    registrations(&gateway, &expected).await;
    // The account's last object goes: the only unregistration.
    assert_eq!(release(json!({"mplex": ["0x638301"]})).await.0, 200);
    expected.push("UNREG 0x638301");
    registrations(&gateway, &expected).await;

    // Another account cannot touch this lift's subscriptions; a bad threshold is refused.
    let (status, _) = rig
        .call(
            "POST",
            &subscriptions,
            Some(&rig.other_key),
            Some(json!({"mplex": ["0x652001"]})),
        )
        .await;
    assert_eq!(status, 404);
    assert_eq!(
        hold(json!({"mplex": ["0x652001"], "threshold": -1}))
            .await
            .0,
        400
    );
    registrations(&gateway, &expected).await;

    // The account's subscriptions outlive the portal: after a restart the gateway's new
    // connection gets them from the database (a watcher's ended with its stream).
    assert_eq!(hold(speed.clone()).await.0, 200);
    expected.push("REG 1000 2.0 0x638301");
    registrations(&gateway, &expected).await;
    gateway.say("CLOSE").await;
    gateway.wait_for("CLOSED", 2, WAIT).await;
    rig.restart_portal().await;
    gateway.say("CONNECT").await;
    gateway.wait_for("CONNACK", 3, WAIT).await;
    expected.extend(["REG 500 0.0 0x100100,0x652001", "REG 1000 2.0 0x638301"]);
    registrations(&gateway, &expected).await;
    rig.stop().await;
}
