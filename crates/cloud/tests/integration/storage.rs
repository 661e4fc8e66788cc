//! The portal's storage at the edges users meet (docs/PORTAL.md §Stores, §History, §Audit):
//! a full disk under SQLite and under PostgreSQL, gateways that push what nobody asked for or
//! more than they may store, a history read over the whole range it names, portals started
//! together on a fresh database, and writes retried with an `Idempotency-Key`.

use std::time::{Duration, Instant};

use cloud_types::api::History;
use serde_json::json;
use testkit::constants::LIFT;
use testkit::portal::Rig;
use testkit::{PostgresServer, Tmpfs};

/// The passenger call (0x502200, privilege 0): what the full-disk tests write.
const CALL: &str = "0x502200";

/// The passenger call the lift has now, read through the portal (reads need no write).
async fn call_now(rig: &Rig) -> Option<String> {
    let path = format!("/api/v1/lifts/{LIFT}/objects/{CALL}?form=naked");
    let (status, body) = rig.call("GET", &path, Some(&rig.key), None).await;
    (status == 200).then(|| body["object"]["value"][0].as_str().map(str::to_owned))?
}

/// One put of a call other than the one the lift has: (floor, status). A put answered 5xx
/// must not have reached the lift: its floor is not what the lift has right after.
async fn put_a_call(rig: &Rig, step: u32) -> (String, u16) {
    let now = call_now(rig).await.unwrap_or_default();
    let floor = (2..=8)
        .map(|f| ((f + step) % 7 + 2).to_string())
        .find(|f| *f != now)
        .expect("another floor");
    let body = json!({"value": floor, "datatype": 7, "physunit": 0});
    let path = format!("/api/v1/lifts/{LIFT}/objects/{CALL}");
    let (status, answer) = rig.call("PUT", &path, Some(&rig.key), Some(body)).await;
    if status >= 500 {
        assert_ne!(
            call_now(rig).await.as_deref(),
            Some(floor.as_str()),
            "a put answered {status} reached the lift: {answer}"
        );
    }
    (floor, status)
}

/// `/healthz`: status and text.
async fn health(rig: &Rig) -> (u16, String) {
    let (status, body) = rig.call("GET", "/healthz", None, None).await;
    (status, body.as_str().unwrap_or_default().to_owned())
}

/// Telemetry and operator writes while the disk fills, then space freed: writing resumes
/// within 10 s, every value counted as stored is in the database, every put answered 2xx has a
/// complete audit entry and none answered 5xx reached the lift. `postgres`: the database's
/// server, revived after space returns (a PostgreSQL whose WAL found no room stops itself).
async fn a_full_disk_is_ridden_out(rig: Rig, disk: &Tmpfs, postgres: Option<&mut PostgresServer>) {
    let mut rig = rig;
    rig.online().await;
    let mut puts = Vec::new();
    for step in 0..3 {
        puts.push(put_a_call(&rig, step).await);
    }
    assert!(puts.iter().all(|p| p.1 == 200), "{puts:?}");
    // Full: the telemetry of the moving car and the puts' audit entries find no room.
    let filler = disk.fill(24 << 10);
    let full = Instant::now();
    let mut seen = (false, 0);
    let mut step = 3;
    while full.elapsed() < Duration::from_secs(40) && !(seen.0 && seen.1 >= 3) {
        let put = put_a_call(&rig, step).await;
        step += 1;
        if put.1 == 503 {
            seen.1 += 1;
        }
        puts.push(put);
        let (status, text) = health(&rig).await;
        if status == 503 && text.contains("database") {
            seen.0 = true;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(seen.0, "/healthz never said the database takes no writes");
    assert!(seen.1 >= 3, "puts while full: {puts:?}");
    // Space again.
    std::fs::remove_file(&filler).expect("the filler goes");
    if let Some(pg) = postgres {
        pg.revive();
    }
    let freed = Instant::now();
    let stored_before = rig.metric("canlift_telemetry_stored_total").await;
    loop {
        let (status, _) = health(&rig).await;
        let stored = rig.metric("canlift_telemetry_stored_total").await;
        if status == 200 && stored > stored_before {
            break;
        }
        assert!(
            freed.elapsed() < Duration::from_secs(10),
            "writing did not resume within 10 s of space returning"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!("writing resumed {:?} after space returned", freed.elapsed());
    for _ in 0..3 {
        let put = put_a_call(&rig, step).await;
        step += 1;
        assert_eq!(put.1, 200, "after space returned: {put:?}");
        puts.push(put);
    }
    // Nothing more pushed: what was counted as stored is what the database holds.
    rig.stop_gateway().await;
    let mut stable = (f64::NAN, Instant::now());
    let stored = loop {
        let stored = rig.metric("canlift_telemetry_stored_total").await;
        let queued = rig.metric("canlift_telemetry_queued").await;
        if queued == 0.0 && stored == stable.0 && stable.1.elapsed() > Duration::from_secs(1) {
            break stored;
        }
        if stored != stable.0 {
            stable = (stored, Instant::now());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let store = rig.store().await;
    assert_eq!(
        store.count_telemetry().await.expect("counted") as f64,
        stored,
        "values counted as stored that are not (or the other way round)"
    );
    // Audit: every put answered 2xx complete, none pending; none more than were answered 2xx.
    let entries = store
        .audit_log(testkit::constants::DOMAIN)
        .await
        .expect("the log");
    let puts_ok = puts.iter().filter(|p| p.1 == 200).count();
    let audited_ok = entries
        .iter()
        .filter(|e| e.action == "put" && e.result == "ok")
        .count();
    assert_eq!(audited_ok, puts_ok, "{puts:?}\n{entries:?}");
    assert!(
        entries
            .iter()
            .all(|e| e.result != cloud_types::audit::PENDING),
        "{entries:?}"
    );
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_under_sqlite_loses_nothing_counted_as_stored() {
    let Some(disk) = Tmpfs::mount(4 << 20) else {
        return;
    };
    let state = disk.path().join("portal");
    let rig = Rig::builder()
        .portal(move |c| {
            c.state.dir = state;
            c.dashboard.inhibit_ms = 0;
        })
        .start()
        .await;
    a_full_disk_is_ridden_out(rig, &disk, None).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_under_postgres_loses_nothing_counted_as_stored() {
    let Some(disk) = Tmpfs::mount(96 << 20) else {
        return;
    };
    let Some(mut server) = PostgresServer::start_in(Some(disk.path())) else {
        return;
    };
    let rig = Rig::builder()
        .database(Some(server.url()))
        .portal(|c| c.dashboard.inhibit_ms = 0)
        .start()
        .await;
    a_full_disk_is_ridden_out(rig, &disk, Some(&mut server)).await;
}

/// Sends `text` to a hand-made gateway's socket.
async fn send(ws: &mut testkit::portal::GatewaySocket, text: String) {
    use futures_util::SinkExt;
    ws.send(tokio_tungstenite::tungstenite::Message::Text(text.into()))
        .await
        .expect("sent");
}

/// A push of `value` for object `mplex`, as a gateway writes it (NXg §7.4).
fn push(mplex: &str, value: &str) -> String {
    json!({"jsonrpc": "2.0", "method": "canopen_object", "result": {"mplex": mplex, "value": value}})
        .to_string()
}

/// A gateway pushing 60 KB values, values of objects nobody subscribed to, and more than its
/// lift may store in an hour: what is stored stays within the quota, the lift gets a
/// `storage-quota` alarm, the other account's lift goes on storing without one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_gateway_stores_beyond_its_quota() {
    const QUOTA: u64 = 100_000;
    let rig = Rig::builder()
        .portal(|c| {
            c.gateways.max_stored_bytes_per_hour = QUOTA;
            c.dashboard.inhibit_ms = 0;
        })
        .start()
        .await;
    rig.online().await;
    let mut ws = rig.hand_made_gateway("QUOTA-1", "OTH").await;
    let lift = "1050-4096-QUOTA-1";
    for _ in 0..20 {
        send(&mut ws, push("0x652001", &"x".repeat(60_000))).await;
    }
    for i in 0..500 {
        send(&mut ws, push("0x2FFF01", &i.to_string())).await;
    }
    // A subscribed object (the dashboard's trip counter), far beyond the quota.
    for i in 0..5000 {
        send(&mut ws, push("0x652001", &format!("{i:040}"))).await;
    }
    let dropped = |reason: &'static str| {
        let rig = &rig;
        async move {
            rig.metric(&format!(
                "canlift_telemetry_dropped_total{{reason=\"{reason}\"}}"
            ))
            .await
        }
    };
    let started = Instant::now();
    while dropped("quota").await < 1.0 || dropped("unsubscribed").await < 500.0 {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "drops not counted"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(dropped("too_large").await, 20.0);
    let store = rig.store().await;
    // What fit is written within the writer's batch time.
    let mut stored = Vec::new();
    let mut stable = Instant::now();
    while stored.is_empty() || stable.elapsed() < Duration::from_secs(1) {
        let now = store
            .values(lift, "0x652001", 0, i64::MAX, 100_000)
            .await
            .expect("read");
        if now.len() != stored.len() {
            stable = Instant::now();
        }
        stored = now;
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "nothing stored"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let bytes: usize = stored
        .iter()
        .map(|(_, v)| lift.len() + "0x652001".len() + v.len() + 32)
        .sum();
    assert!(bytes as u64 <= QUOTA, "{bytes} bytes stored");
    assert!(
        stored.len() > 100,
        "the quota's worth was stored: {}",
        stored.len()
    );
    assert!(store
        .values(lift, "0x2fff01", 0, i64::MAX, 10)
        .await
        .expect("read")
        .is_empty());
    // The alarm, for the account whose lift it is; none on the other account's lift.
    let alarms = |key: String| {
        let rig = &rig;
        async move {
            let (status, body) = rig.call("GET", "/api/v1/alarms", Some(&key), None).await;
            assert_eq!(status, 200, "{body}");
            body["alarms"].as_array().cloned().unwrap_or_default()
        }
    };
    let started = Instant::now();
    while !alarms(rig.other_key.clone())
        .await
        .iter()
        .any(|a| a["kind"] == "storage-quota" && a["lift"] == lift)
    {
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "no storage-quota alarm"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(!alarms(rig.key.clone())
        .await
        .iter()
        .any(|a| a["kind"] == "storage-quota"));
    // The rig's lift goes on storing.
    let path = format!("/api/v1/lifts/{LIFT}/objects/{CALL}");
    let (status, body) = rig
        .call(
            "PUT",
            &path,
            Some(&rig.key),
            Some(json!({"value": "5", "datatype": 7, "physunit": 0})),
        )
        .await;
    assert_eq!(status, 200, "{body}");
    let started = Instant::now();
    while store
        .values(LIFT, "0x638301", 0, i64::MAX, 100_000)
        .await
        .unwrap()
        .len()
        < 3
    {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "the other lift stored nothing"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    rig.stop().await;
}

/// 50,000 values of one object over 15 seconds, with a spike at the start and one at the
/// end: the 1,000-point answer spans the first value to the last and holds both spikes in its
/// minima and maxima; the CSV of the web UI lists every value.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_history_covers_its_whole_range() {
    const N: usize = 50_000;
    const SPREAD_MS: u64 = 15_000;
    let rig = Rig::builder()
        .portal(|c| c.dashboard.inhibit_ms = 0)
        .start()
        .await;
    rig.online().await;
    let mut ws = rig.hand_made_gateway("HISTORY-1", "OTH").await;
    let lift = "1050-4096-HISTORY-1";
    let first = cloud_types::now_ms();
    let started = Instant::now();
    for i in 0..N {
        let value = match i {
            0 => "-1000".to_owned(),
            i if i == N - 1 => "99999".to_owned(),
            i => (i % 50).to_string(),
        };
        send(&mut ws, push("0x638301", &value)).await;
        // 50,000 in 15 s, paced in steps of 10: 3,333 a second, within a gateway's 5,000
        // messages a second (`max_messages_per_s`), over enough milliseconds for 1,000 buckets.
        if i % 10 == 9 {
            let due = Duration::from_millis((i as u64 + 1) * SPREAD_MS / N as u64);
            tokio::time::sleep_until((started + due).into()).await;
        }
    }
    let store = rig.store().await;
    let deadline = Instant::now() + Duration::from_secs(20);
    while store
        .values(lift, "0x638301", 0, i64::MAX, N + 1)
        .await
        .unwrap()
        .len()
        < N
    {
        assert!(Instant::now() < deadline, "not all stored");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let stored = store
        .values(lift, "0x638301", 0, i64::MAX, N + 1)
        .await
        .unwrap();
    let (first_at, to) = (stored[0].0, stored[N - 1].0);
    assert!(first_at >= first);
    let first = first_at;
    let path =
        format!("/api/v1/lifts/{lift}/objects/0x638301/history?from={first}&to={to}&points=1000");
    let (status, body) = rig.call("GET", &path, Some(&rig.other_key), None).await;
    assert_eq!(status, 200, "{body}");
    let history: History = serde_json::from_value(body).expect("a history");
    assert!(
        history.points.len() <= 1000 && history.points.len() > 500,
        "{} buckets",
        history.points.len()
    );
    assert_eq!(
        history.points.iter().map(|p| p.count).sum::<i64>(),
        N as i64
    );
    assert!(history.points[0].at <= first && history.points[0].min == Some(-1000.0));
    let last = history.points.last().expect("a bucket");
    assert_eq!(
        (last.last_at, last.last.as_str(), last.max),
        (to, "99999", Some(99999.0))
    );
    // The CSV of the web UI, in a browser's session: every value.
    let client = cloud::client::Client::new(&rig.url(), None, Some(&rig.ca)).expect("a client");
    let signed_in = client
        .exchange(
            "POST",
            "/login",
            cloud::client::Body::Form(&[("key", &rig.other_key)]),
        )
        .await
        .expect("signed in");
    let cookie = signed_in.set_cookie.expect("a session");
    let csv = client
        .with_cookie(&cookie)
        .exchange(
            "GET",
            &format!("/lifts/{lift}/history.csv?mplex=0x638301&from={first}&to={to}"),
            cloud::client::Body::Empty,
        )
        .await
        .expect("the CSV");
    let csv = csv.body.as_str().expect("text").to_owned();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], "time,object,value");
    assert_eq!(lines.len(), N + 1);
    assert!(lines[1].ends_with(",-1000") && lines[N].ends_with(",99999"));
    rig.stop().await;
}

/// Three portals started at once on a fresh PostgreSQL database all come up (the schema is
/// made under a lock, once).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn portals_started_together_on_a_fresh_postgres_all_serve() {
    let Some(url) = testkit::postgres("together").await else {
        return;
    };
    let dirs: Vec<_> = (0..3).map(|_| testkit::scratch()).collect();
    let binds = dirs.iter().map(|dir| {
        let mut config = cloud::config::Config::default();
        config.database.url = Some(url.to_string());
        config.server.listen = "127.0.0.1:0".parse().expect("an address");
        config.state.dir = dir.path().to_owned();
        async move {
            cloud::server::Portal::bind(&config, lift417::catalog::Catalog::builtin().names()).await
        }
    });
    let portals = futures_util::future::join_all(binds).await;
    for portal in &portals {
        assert!(portal.is_ok(), "{:?}", portal.as_ref().err());
    }
}

/// The same `Idempotency-Key` twice writes once and answers the same; with another request it
/// is refused (422); another operator's key of the same name is hers alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idempotency_key_writes_once() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    let client = cloud::client::Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca))
        .expect("a client")
        .with_header("Idempotency-Key", "\"call-4-once\"");
    let path = format!("/api/v1/lifts/{LIFT}/objects/{CALL}");
    let body = json!({"value": "4", "datatype": 7, "physunit": 0});
    let first = client
        .call("PUT", &path, Some(body.clone()))
        .await
        .expect("answered");
    let again = client
        .call("PUT", &path, Some(body))
        .await
        .expect("answered");
    assert_eq!(first.0, 200, "{first:?}");
    assert_eq!(first, again);
    let other = client
        .call(
            "PUT",
            &path,
            Some(json!({"value": "5", "datatype": 7, "physunit": 0})),
        )
        .await
        .expect("answered");
    assert_eq!(other.0, 422, "{other:?}");
    // Another operator's key of the same name is another key: the call is made again.
    let store = rig.store().await;
    store
        .add_user("masora", "tess", cloud_types::users::Role::Technician)
        .await
        .expect("a user");
    let (_, tess) = store.add_key("masora", "tess", None).await.expect("a key");
    let hers = cloud::client::Client::new(&rig.url(), Some(&tess), Some(&rig.ca))
        .expect("a client")
        .with_header("Idempotency-Key", "\"call-4-once\"");
    let (status, _) = hers
        .call(
            "PUT",
            &path,
            Some(json!({"value": "4", "datatype": 7, "physunit": 0})),
        )
        .await
        .expect("answered");
    assert_eq!(status, 200);
    let entries = rig
        .store()
        .await
        .audit_log(testkit::constants::DOMAIN)
        .await
        .expect("the log");
    let written = entries
        .iter()
        .filter(|e| e.action == "put" && e.new_value == "4")
        .count();
    assert_eq!(written, 2, "once for each operator: {entries:?}");
    rig.stop().await;
}
