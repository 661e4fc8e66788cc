//! Events, alarms and webhooks on the portal, against a fake gateway (NXg api 1 with the events) written with Python
//! `websockets` and a webhook receiver written with Python's http.server that checks every
//! delivery with the Standard Webhooks reference library and with the verifier of
//! docs/PORTAL.md §Webhooks (independent implementations of the connector's client side and of
//! the signature check).

use std::time::Duration;

use serde_json::{json, Value};
use testkit::constants::WAIT;
use testkit::free_port;
use testkit::portal::Rig;
use testkit::script::Script;

const LIFT: &str = "1050-4096-PY-EVENTS";
/// The receiver's signing key, as Standard Webhooks writes one (base64 of the key's bytes).
const SECRET: &str = "whsec_czNjcmV0LWZvci10aGUtcmVjZWl2ZXI=";
/// The receiver's Basic credentials and a key in its query: never shown, anywhere.
const USERINFO: &str = "hooks:pa55word";
const QUERY_KEY: &str = "topsecret";

/// The verifier of docs/PORTAL.md §Webhooks, as a Python file in `dir`.
fn documented_verifier(dir: &std::path::Path) -> std::path::PathBuf {
    let doc = include_str!("../../../../docs/PORTAL.md");
    let section = &doc[doc.find("### Webhooks").expect("§Webhooks")..];
    let code = section
        .split("```python\n")
        .nth(1)
        .and_then(|rest| rest.split("```").next())
        .expect("a Python block in §Webhooks");
    let path = dir.join("verifier.py");
    std::fs::write(&path, code).expect("written");
    path
}

fn emcy(code: &str, register: &str, text: &str) -> String {
    let event = json!({"type": "emcy", "node": {"id": 1, "net": 1}, "time": "2026-11-23T10:11:12.345Z",
        "code": code, "register": register, "data": "0000000000", "text": text});
    format!("EVENT {event}")
}

/// Poll `path` until `check` holds on the answer.
async fn until(rig: &Rig, path: &str, check: impl Fn(&Value) -> bool) -> Value {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let (status, body) = rig.call("GET", path, Some(&rig.key), None).await;
        assert_eq!(status, 200, "{body}");
        if check(&body) {
            return body;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{path}: not as expected: {body}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn alarms_of(body: &Value) -> Vec<Value> {
    body["alarms"].as_array().cloned().unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_become_alarms_that_reach_people() {
    let Some(python) = testkit::python() else {
        return;
    };
    let hook_port = free_port();
    let url = format!("http://{USERINFO}@127.0.0.1:{hook_port}/canlift?apikey={QUERY_KEY}");
    let mut rig = Rig::builder()
        .without_lift()
        .portal(move |config| {
            config.dashboard.live.clear();
            config.alarms.offline_after_s = 2;
            config.alarms.webhooks.push(cloud::config::WebhookSection {
                name: Some("alerts".into()),
                url,
                secret: SECRET.into(),
                min_severity: cloud_types::alarms::Severity::Major,
                ca_file: None,
            });
        })
        .start()
        .await;
    // The receiver refuses the first two deliveries.
    let verifier = documented_verifier(rig.dir());
    let verifier = verifier.to_str().expect("UTF-8");
    let receiver = Script::start(
        &python,
        "webhook_receiver.py",
        &[&hook_port.to_string(), SECRET, "2", verifier],
    );
    receiver.wait_for("READY", 1, WAIT).await;
    let ca = rig.ca.display().to_string();
    let mut gateway = Script::start(
        &python,
        "event_gateway.py",
        &[&rig.ws_url(), &ca, "PY-EVENTS"],
    );
    assert_eq!(gateway.wait_for("CONNACK", 1, WAIT).await[0], "CONNACK 1");
    // The portal registers the dashboard's event kinds.
    let registered = gateway.wait_for("EVENTS", 1, WAIT).await;
    assert_eq!(registered[0], r#"EVENTS ["emcy", "state", "bus"]"#);

    // An EMCY: stored, and an alarm raised.
    gateway.say(&emcy("0xFF01", "0x21", "Door blocked")).await;
    let log = until(&rig, &format!("/api/v1/lifts/{LIFT}/event-log"), |b| {
        !b["events"].as_array().unwrap().is_empty()
    })
    .await;
    assert_eq!(log["events"][0]["code"], "0xFF01");
    assert_eq!(log["events"][0]["time"], "2026-11-23T10:11:12.345Z");
    let active = until(&rig, "/api/v1/alarms", |b| alarms_of(b).len() == 1).await;
    let alarm = &active["alarms"][0];
    assert_eq!(alarm["lift"], LIFT);
    assert_eq!(alarm["kind"], "emcy");
    assert_eq!(alarm["code"], "0xFF01");
    assert_eq!(alarm["severity"], "major");
    assert_eq!(alarm["node"], json!({"id": 1, "net": 1}));
    assert_eq!(alarm["text"], "Node 1: Door blocked (FF01)");
    assert_eq!(alarm["acknowledged"], Value::Null);
    assert_eq!(alarm["cleared"], Value::Null);
    // The same condition again: no second alarm.
    gateway.say(&emcy("0xFF01", "0x21", "Door blocked")).await;
    let id = alarm["id"].as_i64().unwrap();

    // Acknowledged (another account cannot, nor see it).
    let ack = format!("/api/v1/alarms/{id}/ack");
    let body = json!({"comment": "technician on the way"});
    let (status, _) = rig
        .call("POST", &ack, Some(&rig.other_key), Some(body.clone()))
        .await;
    assert_eq!(status, 404);
    let (status, acked) = rig
        .call("POST", &ack, Some(&rig.key), Some(body.clone()))
        .await;
    assert_eq!(status, 200, "{acked}");
    assert_eq!(acked["acknowledged"]["by"], "masora");
    assert_eq!(acked["acknowledged"]["comment"], "technician on the way");
    let (status, _) = rig.call("POST", &ack, Some(&rig.key), Some(body)).await;
    assert_eq!(status, 409, "acknowledged once");
    let (_, other) = rig
        .call(
            "GET",
            "/api/v1/alarms?state=all",
            Some(&rig.other_key),
            None,
        )
        .await;
    assert!(alarms_of(&other).is_empty(), "{other}");
    let (status, _) = rig
        .call(
            "GET",
            &format!("/api/v1/lifts/{LIFT}/event-log"),
            Some(&rig.other_key),
            None,
        )
        .await;
    assert_eq!(status, 404);

    // Cleared by the error reset.
    gateway.say(&emcy("0x0000", "0x00", "Error reset")).await;
    until(&rig, "/api/v1/alarms", |b| alarms_of(b).is_empty()).await;
    let all = until(&rig, "/api/v1/alarms?state=all", |b| {
        alarms_of(b).len() == 1
    })
    .await;
    assert!(all["alarms"][0]["cleared"].is_string());
    assert_eq!(all["alarms"][0]["acknowledged"]["by"], "masora");

    // The receiver got raised, acknowledged, cleared — signed, with its Basic credentials, a
    // replay of each refused — after refusing two attempts.
    let hooks = receiver
        .wait_for("HOOK 204", 3, Duration::from_secs(30))
        .await;
    assert_eq!(receiver.seen("HOOK 500").len(), 2, "retried after a 500");
    let checked = format!(" valid replay-refused {USERINFO} ");
    assert!(
        receiver.seen("HOOK").iter().all(|l| l.contains(&checked)),
        "{hooks:?}"
    );
    let changes: Vec<Value> = hooks
        .iter()
        .map(|l| serde_json::from_str(l.splitn(6, ' ').nth(5).unwrap()).unwrap())
        .collect();
    assert!(changes
        .iter()
        .all(|c| c["account"] == "masora" && c["alarm"]["lift"] == LIFT));
    let mut names: Vec<&str> = changes
        .iter()
        .map(|c| c["change"].as_str().unwrap())
        .collect();
    names.sort_unstable();
    assert_eq!(names, ["acknowledged", "cleared", "raised"]);
    assert!(changes.iter().all(|c| c["alarm"]["id"] == id));

    // The gateway goes away: lift-offline after 2 s, cleared when it returns.
    gateway.say("CLOSE").await;
    gateway.wait_for("CLOSED", 1, WAIT).await;
    let offline = until(&rig, "/api/v1/alarms", |b| alarms_of(b).len() == 1).await;
    assert_eq!(offline["alarms"][0]["kind"], "lift-offline");
    assert_eq!(offline["alarms"][0]["severity"], "critical");
    assert_eq!(offline["alarms"][0]["node"], Value::Null);
    gateway.say("CONNECT").await;
    gateway.wait_for("CONNACK", 2, WAIT).await;
    until(&rig, "/api/v1/alarms", |b| alarms_of(b).is_empty()).await;
    // The offline alarm's two notifications reach this receiver (not, late, the next one).
    receiver
        .wait_for("HOOK 204", 5, Duration::from_secs(30))
        .await;

    // A notification queued while the receiver is down survives a portal restart.
    drop(receiver);
    gateway.say(&emcy("0xF001", "0x03", "Drive fault")).await;
    until(&rig, "/api/v1/alarms", |b| alarms_of(b).len() == 1).await;
    rig.restart_portal().await;
    let receiver = Script::start(
        &python,
        "webhook_receiver.py",
        &[&hook_port.to_string(), SECRET, "0", verifier],
    );
    let hooks = receiver
        .wait_for("HOOK 204", 1, Duration::from_secs(30))
        .await;
    assert!(
        hooks
            .iter()
            .any(|h| h.contains("0xF001") && h.contains(&checked)),
        "{hooks:?}"
    );
    // The attempts are in the audit log and the metrics.
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    let webhook_entries = audit
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["action"] == "webhook")
        .count();
    assert!(webhook_entries >= 4, "{audit}");
    // The receiver's URL — credentials, query, address — is in no answer and on no page:
    // the audit log names it by its name.
    let port = format!(":{hook_port}");
    let secrets = ["pa55word", QUERY_KEY, port.as_str(), "127.0.0.1"];
    let (_, alarms) = rig
        .call("GET", "/api/v1/alarms?state=all", Some(&rig.key), None)
        .await;
    let browser = cloud::client::Client::new(&rig.url(), None, Some(&rig.ca)).expect("a client");
    let form = [("key", rig.key.as_str())];
    let signed_in = browser
        .exchange("POST", "/login", cloud::client::Body::Form(&form))
        .await
        .expect("signed in");
    let browser = browser.with_cookie(&signed_in.set_cookie.expect("a session"));
    let mut shown = vec![audit.to_string(), alarms.to_string()];
    for page in ["/audit", "/alarms", &format!("/lifts/{LIFT}")] {
        let (status, html) = browser.call("GET", page, None).await.expect("a page");
        assert_eq!(status, 200, "{page}");
        shown.push(html.to_string());
    }
    for text in &shown {
        for secret in secrets {
            assert!(!text.contains(secret), "{secret} shown: {text}");
        }
    }
    assert!(
        audit.to_string().contains("\"object\":\"alerts\""),
        "{audit}"
    );
    let token = Some(testkit::constants::METRICS_TOKEN);
    let (status, metrics) = rig.call("GET", "/metrics", token, None).await;
    assert_eq!(status, 200);
    assert!(
        metrics
            .as_str()
            .unwrap()
            .contains("canlift_webhooks_delivered_total 1"),
        "{metrics}"
    );
    drop(gateway);
    rig.stop().await;
}
