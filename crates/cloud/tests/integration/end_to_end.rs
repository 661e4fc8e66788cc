//! End to end: the real gateway in front of the simulated lift, connected to the portal; an
//! operator reads, writes and watches through the REST API.

use std::time::Duration;

use serde_json::json;

use testkit::constants::LIFT;
use testkit::portal::Rig;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_sqlite() {
    operator_reads_writes_and_watches_a_simulated_lift(None).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_postgres() {
    let Some(url) = testkit::postgres("e2e").await else {
        return;
    };
    operator_reads_writes_and_watches_a_simulated_lift(Some(url.to_string())).await;
}

async fn operator_reads_writes_and_watches_a_simulated_lift(database: Option<String>) {
    let mut rig = Rig::builder()
        .database(database)
        // One dashboard object this lift lacks: the portal must fall back to subscribing the
        // others one by one (reg_canopen_object is all or none).
        .portal(|c| c.dashboard.live.push("0x5FFF00".into()))
        .start()
        .await;
    let (key, other) = (rig.key.clone(), rig.other_key.clone());
    let client = &rig;
    let lift = LIFT;
    // Online, with its identity.
    let lifts = rig.online().await;
    assert_eq!(lifts[0]["id"], lift);
    assert_eq!(lifts[0]["liftnum"], "40/7289/20399-126");
    assert_eq!(lifts[0]["api"], 1);
    // The dashboard's objects are pushed without any operator subscription (one of them is
    // missing on this lift, the others are subscribed one by one).
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let (_, h) = client
            .call(
                "GET",
                &format!("/api/v1/lifts/{lift}/objects/0x502400/history"),
                Some(&key),
                None,
            )
            .await;
        if h["points"].as_array().is_some_and(|v| !v.is_empty()) {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the lift state was not pushed: {h}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // The token was issued, confirmed and stored on both sides.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    let token = loop {
        if let Ok(token) = std::fs::read_to_string(rig.dir().join("gateway/cloudtoken")) {
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
    // The other address forms reach the same object, answered in the gateway's spelling.
    for address in ["0x6520:1", "6520sub1", "652001"] {
        let (status, same) = client
            .call(
                "GET",
                &format!("/api/v1/lifts/{lift}/objects/{address}?form=naked"),
                Some(&key),
                None,
            )
            .await;
        assert_eq!((status, &same), (200, &trip), "{address}");
    }
    // Names from the CiA 417 catalog, in the path or as ?name=, any case, a unique prefix.
    for path in [
        "objects/Trip%20counter?form=naked",
        "objects/fahrtenz%C3%A4hler?form=naked",
        "objects?name=TRIP%20COUNT&form=naked",
    ] {
        let url = format!("/api/v1/lifts/{lift}/{path}");
        let (status, same) = client.call("GET", &url, Some(&key), None).await;
        assert_eq!((status, &same), (200, &trip), "{path}");
    }
    let (status, e) = client
        .call(
            "GET",
            &format!("/api/v1/lifts/{lift}/objects?name=car"),
            Some(&key),
            None,
        )
        .await;
    let message = e["message"].as_str().unwrap_or_default();
    assert_eq!(status, 400, "{e}");
    assert!(
        message.contains("objects:"),
        "an ambiguous name lists them: {message}"
    );
    for missing in ["objects", "objects?name=no%20such%20object"] {
        let url = format!("/api/v1/lifts/{lift}/{missing}");
        assert_eq!(
            client.call("GET", &url, Some(&key), None).await.0,
            400,
            "{missing}"
        );
    }
    let bad = format!("/api/v1/lifts/{lift}/objects/0x6520:300");
    assert_eq!(client.call("GET", &bad, Some(&key), None).await.0, 400);
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
            &format!("/api/v1/lifts/{lift}/objects?name=hall%20lantern%20options"),
            Some(&key),
            Some(json!({"value": "1", "datatype": 5, "physunit": 0})),
        )
        .await;
    // Service rights needed: the portal refuses before the gateway is asked, since no one
    // elevated this lift's connection (docs/PORTAL.md §Users and roles).
    assert_eq!(status, 403, "{e}");
    assert!(
        e["message"]
            .as_str()
            .is_some_and(|m| m.starts_with("elevate first")),
        "{e}"
    );
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    loop {
        let (_, h) = client
            .call(
                "GET",
                // The last ten minutes in buckets of 60 ms: each value its own.
                &format!(
                    "/api/v1/lifts/{lift}/objects/0x652001/history?from={}&points=10000",
                    cloud_types::now_ms() - 600_000
                ),
                Some(&key),
                None,
            )
            .await;
        let values: Vec<&str> = h["points"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|v| v["last"].as_str())
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
    // Elevation with a wrong password, and the audit log.
    let (status, e) = client
        .call(
            "POST",
            &format!("/api/v1/lifts/{lift}/privilege"),
            Some(&key),
            Some(json!({"privilege": 1, "password": "not-the-password"})),
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
    assert!(
        entries.iter().any(|e| e["object"] == "0x411200"
            && e["result"]
                .as_str()
                .is_some_and(|r| r.starts_with("refused: elevate first"))),
        "a put by name is audited under its mplex: {entries:?}"
    );
    let (_, other_audit) = client
        .call("GET", "/api/v1/audit", Some(&other), None)
        .await;
    assert_eq!(other_audit, json!([]));
    // The OpenAPI document and health.
    let (status, doc) = client.call("GET", "/api/v1/openapi.json", None, None).await;
    assert_eq!((status, &doc["openapi"]), (200, &json!("3.1.0")));
    assert_eq!(client.call("GET", "/healthz", None, None).await.0, 200);
    // The gateway goes away: offline → 503.
    rig.stop_gateway().await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(rig.call("GET", &path, Some(&key), None).await.0, 503);
    rig.stop().await;
}

/// docs/PORTAL.md §Stores: a stopping portal closes its gateways' connections and writes what
/// they queued before it returns — here, when the lift was last seen (its connection's end).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopping_portal_records_when_its_gateways_were_last_seen() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let store = rig.store().await;
    let seen = || async {
        let account = cloud_types::users::Account {
            name: testkit::constants::ACCOUNT.into(),
            domain: testkit::constants::DOMAIN.into(),
        };
        let lift = store.lift(&account, LIFT).await;
        lift.expect("the store answers")
            .expect("the lift")
            .last_seen
    };
    let connected = seen().await;
    // Apart by more than the clock's resolution.
    tokio::time::sleep(Duration::from_millis(10)).await;
    let stopping = cloud_types::now_ms();
    assert!(connected < stopping);
    rig.stop_portal().await;
    assert_eq!(
        rig.registry().online_count(),
        0,
        "the portal returned before its gateways' connections ended"
    );
    let last = seen().await;
    assert!(
        last >= stopping,
        "last seen {last}: before the portal stopped at {stopping}"
    );
    rig.stop().await;
}

/// docs/PORTAL.md §TLS: the session-ticket keys live in the state directory, so a gateway
/// resumes its TLS session with a restarted portal (no certificate, no signature) instead of
/// making a full handshake.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_portal_resumes_its_gateways_tls_sessions() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let keys = rig.dir().join("portal/tls-ticket-keys");
    assert!(keys.exists(), "no ticket keys in the state directory");
    rig.restart_portal().await;
    assert_eq!(
        rig.metric("canlift_tls_handshakes_resumed_total").await,
        0.0
    );
    rig.online().await;
    // The gateway's handshake came before its CONNACK; the operator calls above were full
    // handshakes of new clients.
    assert_eq!(
        rig.metric("canlift_tls_handshakes_resumed_total").await,
        1.0,
        "the gateway did not resume its session"
    );
    assert!(rig.metric("canlift_tls_handshakes_full_total").await >= 2.0);
    rig.stop().await;
}

/// docs/PORTAL.md §TLS: clients that gave up while their connections waited (each sent its
/// ClientHello and closed the connection behind it, as a gateway whose connect timeout ran out)
/// are dropped unanswered and counted; none of them costs a handshake.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_that_gave_up_get_no_handshake() {
    let rig = Rig::builder().without_lift().start().await;
    let full_before = rig.metric("canlift_tls_handshakes_full_total").await;
    let config = tls::client_config(Some(&rig.ca), None).expect("a client configuration");
    const CLIENTS: usize = 20;
    for _ in 0..CLIENTS {
        let hello = testkit::net::client_hello(&config);
        let answer = testkit::net::gave_up(rig.addr, &hello).await;
        assert!(answer.is_empty(), "answered with {} bytes", answer.len());
    }
    assert_eq!(
        rig.metric("canlift_tls_handshakes_abandoned_total").await,
        CLIENTS as f64
    );
    // The only full handshakes since: the two metric calls' own.
    let full = rig.metric("canlift_tls_handshakes_full_total").await - full_before;
    assert_eq!(full, 2.0, "full handshakes");
    rig.stop().await;
}

/// docs/PORTAL.md §Memory: once a burst of connections is over, the portal asks the allocator to
/// give its free pages back, and counts it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_portal_gives_memory_back_after_a_burst_of_connections() {
    if !cfg!(all(target_os = "linux", target_env = "gnu")) {
        testkit::skip("only glibc's allocator can be asked to give memory back");
        return;
    }
    let rig = Rig::builder().without_lift().start().await;
    // Each call is a new TLS connection: 300 of them are a burst.
    for _ in 0..300 {
        rig.metric("canlift_memory_trims_total").await;
    }
    // The portal looks every 5 s: the burst is over at the first look that sees few.
    testkit::portal::until(
        Duration::from_secs(20),
        "a trim after the burst",
        || async {
            // Slowly: the polls themselves are connections too.
            tokio::time::sleep(Duration::from_millis(400)).await;
            rig.metric("canlift_memory_trims_total").await >= 1.0
        },
    )
    .await;
    rig.stop().await;
}

/// Gateways that give up waiting for their CONNACK (their look-ups held up by the database, as
/// in a reconnect storm on a busy one) and leave are let go at once, their sockets closed, not
/// kept until their look-ups end; one that left while waiting for a look-up of its own is not
/// asked about at all. Look-ups are held up here by a transaction that locks the accounts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gateways_that_leave_before_connack_are_let_go() {
    use sqlx::Connection;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let Some(database) = testkit::postgres("left_early").await else {
        return;
    };
    let rig = Rig::builder()
        .database(Some(database.to_string()))
        .without_lift()
        .start()
        .await;
    let mut lock = sqlx::PgConnection::connect(&database).await.unwrap();
    let mut watch = sqlx::PgConnection::connect(&database).await.unwrap();
    sqlx::query("BEGIN").execute(&mut lock).await.unwrap();
    sqlx::query("LOCK TABLE accounts IN ACCESS EXCLUSIVE MODE")
        .execute(&mut lock)
        .await
        .unwrap();
    // The portal's admission look-ups (`lookup_sql`) waiting for the lock, not its other work.
    let waiting = "SELECT COUNT(*) FROM pg_stat_activity WHERE datname = current_database() \
                   AND wait_event_type = 'Lock' AND query LIKE '%AS subscribed%'";
    // One look-up per CONNECT, each waiting on the lock, until the portal asks no more at once.
    let mut asked = Vec::new();
    let mut in_flight = 0;
    loop {
        let ws = rig
            .hand_made_connect(&format!("EARLY-{}", asked.len()), "MAS")
            .await;
        asked.push(ws);
        let before = in_flight;
        let settle = tokio::time::Instant::now() + Duration::from_secs(2);
        while tokio::time::Instant::now() < settle {
            let n: i64 = sqlx::query_scalar(waiting)
                .fetch_one(&mut watch)
                .await
                .unwrap();
            in_flight = n;
            if in_flight > before {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        if in_flight == before {
            break;
        }
        assert!(asked.len() < 10, "the look-ups are not held up");
    }
    assert!(in_flight >= 1, "no look-up waits for the lock");
    // The last gateway's CONNECT waits for a look-up; the one before it has one under way.
    // Both leave (TLS close_notify, then the write side shut): the portal closes its side.
    for ws in asked.iter_mut().rev().take(2) {
        let tls = ws.get_mut();
        tls.shutdown().await.unwrap();
        let mut rest = Vec::new();
        let closed =
            tokio::time::timeout(Duration::from_secs(10), tls.read_to_end(&mut rest)).await;
        assert!(
            closed.is_ok(),
            "the portal keeps the connection of a gateway that left while its CONNECT was looked up"
        );
    }
    sqlx::query("COMMIT").execute(&mut lock).await.unwrap();
    // The others are admitted once the look-ups go on.
    let stayed = asked.len() - 2;
    for ws in asked.iter_mut().take(stayed) {
        let answer =
            tokio::time::timeout(Duration::from_secs(20), futures_util::StreamExt::next(ws))
                .await
                .expect("an answer");
        assert!(
            matches!(answer, Some(Ok(ref m)) if m.to_string().contains("CONNACK")),
            "{answer:?}"
        );
    }
    // The gateway that left before its look-up began was not asked about: the look-ups are
    // those that were held up, once the queue behind them has been taken (the admitted ones'
    // records written meanwhile need no look-up).
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        rig.metric("canlift_admission_lookups_total").await,
        in_flight as f64,
        "a look-up for a gateway that had left"
    );
}

/// NXg §7.1's sample writes `"threshold": 1`: the portal's registrations write an integral
/// threshold as an integer too, on the wire.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registrations_write_an_integral_threshold_as_an_integer() {
    use futures_util::StreamExt;
    let rig = testkit::portal::Rig::builder().without_lift().start().await;
    let mut ws = rig.hand_made_gateway("WIRE-1", "MAS").await;
    let registration = loop {
        let message = tokio::time::timeout(std::time::Duration::from_secs(10), ws.next())
            .await
            .expect("the portal registers the dashboard's objects")
            .expect("open")
            .expect("a message");
        let text = message.to_text().unwrap_or_default().to_owned();
        if text.contains("\"reg_canopen_object\"") {
            break text;
        }
    };
    assert!(
        registration.contains(r#""inhibit":500,"threshold":0}"#),
        "{registration}"
    );
    rig.stop().await;
}
