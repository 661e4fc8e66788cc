//! The portal as a cluster (docs/CLUSTER.md): `canlift cloud` processes on one PostgreSQL
//! database and one NATS server (both started here), a TCP load balancer in front of them and
//! the simulated lift's gateway behind it. Every lift is read, written and watched through
//! every process, also in a browser session opened on another and after elevating on another;
//! subscriptions follow the lift from process to process; a gateway that reconnects elsewhere
//! is dropped by its old holder; a process killed with SIGKILL loses its lifts to the others,
//! which resume its TLS sessions; NATS down degrades, NATS back heals.

use std::time::Duration;

use serde_json::{json, Value};
use testkit::balancer::Balancer;
use testkit::constants::{DOMAIN, LIFT, SERVICE_PASSWORD};
use testkit::lift::{gateway_config, Lift};
use testkit::nats::Nats;
use testkit::portal::until;

use crate::common;
use common::PortalProcess;

/// How long any step may take before the test fails (each is expected within a few seconds).
const LIMIT: Duration = Duration::from_secs(30);

/// Portal processes, NATS, the balancer and the lift.
struct Cluster {
    /// The NATS server, or the servers of a NATS cluster.
    nats: Vec<Nats>,
    portals: Vec<PortalProcess>,
    balancer: Balancer,
    lift: Lift,
    /// The lift's account's API key, and another account's.
    key: String,
    other: String,
    /// The lift's gateway's configuration (through the balancer), to start it again.
    gateway: gateway::config::Config,
    dir: tempfile::TempDir,
    /// Dropped last, after the processes that use it.
    _database: testkit::PostgresDatabase,
}

impl Cluster {
    /// `count` portal processes (nodes `p0`, `p1`, …) sharing one database and one NATS; the
    /// lift's gateway connects through the balancer to `p0`. `None`: no NATS or PostgreSQL
    /// here (the test printed why it is skipped).
    async fn start(name: &str, count: usize) -> Option<Cluster> {
        Cluster::start_with(name, count, 6, "").await
    }

    /// The same with holder entries living `ttl` seconds (watches twice that) and `more`
    /// appended to every process's configuration.
    async fn start_with(name: &str, count: usize, ttl: u64, more: &str) -> Option<Cluster> {
        let nats = Nats::start()?;
        let url = nats.url();
        Cluster::start_on(vec![nats], &url, name, count, ttl, more).await
    }

    /// The same on a NATS server of the caller's, which the processes reach at `url`.
    async fn start_on(
        nats: Vec<Nats>,
        url: &str,
        name: &str,
        count: usize,
        ttl: u64,
        more: &str,
    ) -> Option<Cluster> {
        let database = testkit::postgres(name).await?;
        let dir = testkit::scratch();
        let pki = testkit::pki::pki(dir.path());
        let portals: Vec<PortalProcess> = (0..count)
            .map(|i| {
                let extra = format!(
                    "tls_cert = \"{}\"\ntls_key = \"{}\"\n[database]\nurl = \"{database}\"\n\
                     [cluster]\nnats = \"{url}\"\nnode = \"p{i}\"\nholder_ttl_s = {ttl}\n{more}",
                    pki.cert.display(),
                    pki.key.display(),
                );
                let mut portal =
                    PortalProcess::configure(&dir.path().join(format!("p{i}")), &extra);
                portal.ca = pki.ca.clone();
                portal
            })
            .collect();
        let key = portals[0].add_account("masora", DOMAIN).await;
        let other = portals[0].add_account("someone", "OTH").await;
        let mut portals = portals;
        for portal in &mut portals {
            portal.restart().await;
        }
        let backends = portals
            .iter()
            .map(|p| std::net::SocketAddr::from(([127, 0, 0, 1], p.port)))
            .collect();
        let balancer = Balancer::start(backends).await;
        let bus = format!("mem://cluster-{name}");
        let ws = format!("wss://localhost:{}/ws", balancer.addr().port());
        let gateway = gateway_config(&ws, &pki.ca, &bus, &dir.path().join("gateway"));
        let lift = Lift::start(&bus, testkit::lift::sim_config(), gateway.clone()).await;
        let cluster = Cluster {
            nats,
            portals,
            balancer,
            lift,
            key,
            other,
            gateway,
            dir,
            _database: database,
        };
        cluster.wait_held_by(0).await;
        Some(cluster)
    }

    /// Wait until process `index` holds the lift and every running process sees it online;
    /// how long it took.
    async fn wait_held_by(&self, index: usize) -> Duration {
        let holder = &self.portals[index];
        let held = until(LIMIT, &format!("p{index} holds the lift"), || async {
            holder.metric("canlift_cluster_lifts_held").await == 1
        })
        .await;
        held + until(LIMIT, "every process sees the lift online", || async {
            for portal in self.portals.iter().filter(|p| p.child.is_some()) {
                if portal.online(&self.key).await != 1 {
                    return false;
                }
            }
            true
        })
        .await
    }

    /// Wait until `/metrics` of process `index` shows `value` for `name` (naming `what` if
    /// it does not within the limit); how long it took.
    async fn until_metric(&self, index: usize, name: &str, value: u64, what: &str) -> Duration {
        let portal = &self.portals[index];
        until(LIMIT, what, || async { portal.metric(name).await == value }).await
    }

    /// `METHOD PATH` on process `index` with the lift account's key.
    async fn call(
        &self,
        index: usize,
        method: &str,
        path: &str,
        body: Option<Value>,
    ) -> (u16, Value) {
        self.portals[index]
            .client(&self.key)
            .call(method, path, body)
            .await
            .expect("the portal answers")
    }

    /// The trip counter read through process `index`: the status and the answer.
    async fn read(&self, index: usize) -> (u16, Value) {
        let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
        self.call(index, "GET", &path, None).await
    }

    /// The account subscribes to `mplex` through process `index`.
    async fn subscribe(&self, index: usize, mplex: &str) {
        let path = format!("/api/v1/lifts/{LIFT}/subscriptions");
        let body = json!({ "mplex": [mplex] });
        let (status, subscribed) = self.call(index, "POST", &path, Some(body)).await;
        assert_eq!(status, 200, "{subscribed}");
    }

    /// A live watcher on process `index` that holds the hall lantern options.
    async fn watch_lantern(&self, index: usize) -> cloud::client::EventStream {
        self.portals[index]
            .client(&self.key)
            .events(&format!(
                "/api/v1/lifts/{LIFT}/events?mplex=hall%20lantern%20options"
            ))
            .await
            .expect("connected")
            .expect("an event stream")
    }

    /// Object 0x502200 (an unsigned 8) written through process `index`.
    async fn write_0x502200(&self, index: usize, value: u8) {
        let put = json!({"value": value.to_string(), "datatype": 7, "physunit": 0});
        let path = format!("/api/v1/lifts/{LIFT}/objects/0x502200");
        let (status, answer) = self.call(index, "PUT", &path, Some(put)).await;
        assert_eq!(status, 200, "{answer}");
    }

    /// The hall lantern options written through p0, the holder (elevated there first, which
    /// the write needs).
    async fn write_lantern(&self, value: u8) {
        let elevate = json!({"privilege": 1, "password": SERVICE_PASSWORD});
        let privilege = format!("/api/v1/lifts/{LIFT}/privilege");
        let (status, granted) = self.call(0, "POST", &privilege, Some(elevate)).await;
        assert_eq!(status, 200, "{granted}");
        let lantern = json!({"value": value.to_string(), "datatype": 5, "physunit": 0});
        let path = format!("/api/v1/lifts/{LIFT}/objects?name=hall%20lantern%20options");
        let (status, answer) = self.call(0, "PUT", &path, Some(lantern)).await;
        assert_eq!(status, 200, "{answer}");
    }

    /// The values of `mplex` stored by the portal (read through p0).
    /// The values stored in the last ten minutes, in buckets of 60 ms (one value each).
    /// The last value of each of the history's buckets over the last ten minutes.
    async fn history(&self, mplex: &str) -> Vec<String> {
        self.history_points(mplex)
            .await
            .into_iter()
            .map(|p| p.last)
            .collect()
    }

    /// The history's buckets over the last ten minutes. Their bounds move with the time of the
    /// request: two values in one bucket now may be in two a moment later (compare counts).
    async fn history_points(&self, mplex: &str) -> Vec<cloud_types::api::HistoryPoint> {
        let from = cloud_types::now_ms() - 600_000;
        let path = format!("/api/v1/lifts/{LIFT}/objects/{mplex}/history?from={from}&points=10000");
        let (status, history) = self.call(0, "GET", &path, None).await;
        assert_eq!(status, 200, "{history}");
        let history: cloud_types::api::History =
            serde_json::from_value(history).expect("a history answer");
        history.points
    }

    async fn stop(self) {
        self.lift.stop().await;
        drop(self.balancer);
        drop(self.portals);
        drop(self.nats);
        drop(self.dir);
    }
}

/// A lift held by p0 is read, written, subscribed and watched through p1 and p2 exactly as
/// through p0; another account's key gets 404 there; the gateway connecting again through p1
/// makes p0 drop its connection; p1 killed with SIGKILL, the lift reconnects to another process
/// and is reachable from every one left.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_lift_is_served_by_every_process() {
    let Some(mut cluster) = Cluster::start("cluster_serve", 3).await else {
        return;
    };
    let (status, direct) = cluster.read(0).await;
    assert_eq!(status, 200, "{direct}");
    for index in [1, 2] {
        let (status, relayed) = cluster.read(index).await;
        assert_eq!(status, 200, "through p{index}: {relayed}");
        assert_eq!(relayed["object"]["mplex"], direct["object"]["mplex"]);
    }
    // Not found in another account, through any process (as for a lift held locally).
    for index in 0..3 {
        let (status, _) = cluster.portals[index]
            .client(&cluster.other)
            .call(
                "GET",
                &format!("/api/v1/lifts/{LIFT}/objects/0x652001"),
                None,
            )
            .await
            .expect("an answer");
        assert_eq!(status, 404, "p{index} hides the lift from another account");
    }
    // A browser session opened on p0 works on p1 and p2.
    let browser = |index: usize| {
        let url = format!("https://localhost:{}", cluster.portals[index].port);
        cloud::client::Client::new(&url, None, Some(&cluster.portals[index].ca)).expect("a client")
    };
    let form = [("key", cluster.key.as_str())];
    let signed_in = browser(0)
        .exchange("POST", "/login", cloud::client::Body::Form(&form))
        .await
        .expect("an answer");
    let cookie = signed_in.set_cookie.expect("a session cookie");
    for index in [1, 2] {
        let (status, lifts) = browser(index)
            .with_cookie(&cookie)
            .call("GET", "/api/v1/lifts", None)
            .await
            .expect("an answer");
        assert_eq!(status, 200, "the session on p{index}: {lifts}");
        assert_eq!(lifts[0]["online"], true, "{lifts}");
    }
    // A write through p2, audited as any write.
    let put = json!({"value": "3", "datatype": 7, "physunit": 0});
    let (status, answer) = cluster
        .call(
            2,
            "PUT",
            &format!("/api/v1/lifts/{LIFT}/objects/0x502200"),
            Some(put),
        )
        .await;
    assert_eq!(
        (status, answer),
        (200, json!({"object": {"mplex": "0x502200"}}))
    );
    let (status, audit) = cluster.call(1, "GET", "/api/v1/audit", None).await;
    assert_eq!(status, 200);
    assert!(
        audit.as_array().is_some_and(|a| a
            .iter()
            .any(|e| e["object"] == "0x502200" && e["result"] == "ok")),
        "the relayed write is audited: {audit}"
    );
    // Elevated through p1, a write that needs the privilege through p0 (the lift's holder)
    // and p2: the grant is known everywhere.
    let elevate = json!({"privilege": 1, "password": SERVICE_PASSWORD});
    let privilege = format!("/api/v1/lifts/{LIFT}/privilege");
    let (status, granted) = cluster.call(1, "POST", &privilege, Some(elevate)).await;
    assert_eq!(status, 200, "{granted}");
    for index in [0, 2] {
        let lantern = json!({"value": "1", "datatype": 5, "physunit": 0});
        let path = format!("/api/v1/lifts/{LIFT}/objects?name=hall%20lantern%20options");
        let (status, answer) = cluster.call(index, "PUT", &path, Some(lantern)).await;
        assert_eq!(status, 200, "a privileged write through p{index}: {answer}");
    }
    // Nobody elsewhere watched the lift yet: its holder published none of its pushed values
    // to NATS (they are counted instead).
    let unwatched = cluster.portals[0]
        .metric("canlift_cluster_events_unwatched_total")
        .await;
    assert!(unwatched > 0, "the holder published unwatched events");
    // A watcher on p0 holds the hall lantern options: its terms follow the lift to every
    // process that holds it later.
    let mut lantern_watch = cluster.watch_lantern(0).await;
    // Watched through p1, subscribed through p2: the value the gateway pushes arrives.
    let client = cluster.portals[1].client(&cluster.key);
    let mut stream = client
        .events(&format!("/api/v1/lifts/{LIFT}/events"))
        .await
        .expect("connected")
        .expect("an event stream");
    cluster.subscribe(2, "0x502200").await;
    let value = tokio::time::timeout(LIMIT, async {
        while let Some(Ok((name, data))) = stream.next().await {
            // The dashboard's objects come too; a new subscription pushes its value first.
            if name == "value" && data.contains("0x502200") {
                return data;
            }
        }
        panic!("the stream ended");
    })
    .await
    .expect("a pushed value reaches p1's stream");
    assert!(
        value.contains("\"value\":\"3\""),
        "the value written through p2: {value}"
    );

    // The same gateway connects again through p1 (its old connection to p0 still open, as
    // after a NAT dropped it silently): p0 closes its connection within a second.
    cluster.balancer.route_to(1);
    let second = gateway_config(
        &format!("wss://localhost:{}/ws", cluster.portals[1].port),
        &cluster.portals[1].ca,
        "mem://cluster-second",
        &cluster.dir.path().join("gateway"),
    );
    let bus = second.bus.url.clone();
    let sim = testkit::lift::simulator(&bus).await;
    let replacement = gateway::Gateway::bus_node(second).await.expect("a gateway");
    let replacement = testkit::lift::RunningGateway::spawn(replacement);
    let dropped = cluster
        .until_metric(
            0,
            "canlift_cluster_replaced_total",
            1,
            "p0 drops the old connection",
        )
        .await;
    eprintln!("p0 dropped its connection {dropped:?} after the gateway connected to p1");
    assert_eq!(
        cluster.portals[0].metric("canlift_gateways_online").await,
        0
    );
    replacement.stop().await;
    sim.stop().await;
    // The first gateway reconnects (through the balancer: to p1).
    cluster.wait_held_by(1).await;

    // p1 killed: the gateway reconnects through the balancer to p2, reachable from p0 and p2.
    cluster.balancer.route_to(2);
    cluster.portals[1].kill().await;
    let back = cluster.wait_held_by(2).await;
    eprintln!("the lift of the killed process was online again after {back:?}");
    // The processes share their TLS ticket keys: the gateway resumed on p2 the session p1
    // gave it (operators' clients here start each with an empty session cache).
    assert_eq!(
        cluster.portals[2]
            .metric("canlift_tls_handshakes_resumed_total")
            .await,
        1,
        "the gateway's session resumed on another process"
    );
    for index in [0, 2] {
        let (status, answer) = cluster.read(index).await;
        assert_eq!(status, 200, "through p{index} after the kill: {answer}");
    }
    // Two moves later, p2 registered the subscription made through p2 while p0 held the
    // lift (from the database), and p0's watcher handed its objects to p1, then to p2: both
    // objects' new values reach p0's stream.
    cluster.write_0x502200(0, 5).await;
    cluster.write_lantern(2).await;
    let (mut subscribed, mut watched) = (false, false);
    tokio::time::timeout(LIMIT, async {
        while !(subscribed && watched) {
            let Some(Ok((name, data))) = lantern_watch.next().await else {
                panic!("the stream ended");
            };
            if name != "value" {
                continue;
            }
            subscribed |= data.contains("0x502200") && data.contains("\"value\":\"5\"");
            watched |= data.contains("0x4112") && data.contains("\"value\":\"2\"");
        }
    })
    .await
    .unwrap_or_else(|_| {
        panic!(
            "pushed after two moves: the user's subscription {subscribed}, the watcher's {watched}"
        )
    });
    cluster.stop().await;
}

/// The hall lantern options' mplex, when `watch` brings its new `value` within 3 s.
async fn pushed(watch: &mut cloud::client::EventStream, value: u8) -> Option<String> {
    let wanted = format!("\"value\":\"{value}\"");
    tokio::time::timeout(Duration::from_secs(3), async {
        while let Some(Ok((name, data))) = watch.next().await {
            if name == "value" && data.contains("0x4112") && data.contains(&wanted) {
                let event: cloud_types::live::ValueMessage =
                    serde_json::from_str(&data).expect("a value event");
                return Some(event.object.mplex);
            }
        }
        None
    })
    .await
    .ok()
    .flatten()
}

/// A watcher on p1 of the lift p0 holds asks for the hall lantern options. NATS away for
/// longer than p1's watch lease: p0 lets go of the watcher's object, and p1 hands it over again
/// when NATS is back. p1 killed: its lease lapses and p0 lets go for good — the lantern's
/// changes are no longer pushed, while an account's subscription stays.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watching_process_that_goes_away_lets_go() {
    let Some(mut cluster) = Cluster::start_with("cluster_lapse", 2, 3, "").await else {
        return;
    };
    cluster.subscribe(0, "0x502200").await;
    let mut watch = cluster.watch_lantern(1).await;
    cluster.write_lantern(1).await;
    let lantern = pushed(&mut watch, 1)
        .await
        .expect("the watcher's object is pushed to p1's stream");

    // NATS away for longer than the lease (6 s here).
    cluster.nats[0].stop();
    cluster
        .until_metric(
            0,
            "canlift_cluster_watch_lapsed_total",
            1,
            "p0 lets go of p1's watcher",
        )
        .await;
    cluster.nats[0].start_again();
    let back = tokio::time::Instant::now();
    let mut last = 1;
    for value in [2, 3].into_iter().cycle() {
        cluster.write_lantern(value).await;
        last = value;
        if pushed(&mut watch, value).await.is_some() {
            break;
        }
        assert!(
            back.elapsed() < LIMIT,
            "the watcher's object is not pushed again after NATS came back"
        );
    }
    let handed = back.elapsed();
    eprintln!("p1's watcher was pushed to again {handed:?} after NATS came back");

    // p1 killed: once its lease lapses, p0 lets go of the lantern for good.
    cluster.portals[1].kill().await;
    cluster
        .until_metric(
            0,
            "canlift_cluster_watch_lapsed_total",
            2,
            "p0 lets go of the killed process's watcher",
        )
        .await;
    let stored = cluster.history_points(&lantern).await;
    assert!(
        stored.iter().any(|p| p.last == "1"),
        "a pushed lantern value is stored: {stored:?}"
    );
    let count =
        |points: &[cloud_types::api::HistoryPoint]| -> i64 { points.iter().map(|p| p.count).sum() };
    // The lantern changed first, the account's object after it: the gateway pushes in order
    // and the portal stores in order, so once the second is stored, a push of the first
    // would be too.
    cluster.write_lantern(5 - last).await;
    cluster.write_0x502200(0, 4).await;
    until(LIMIT, "the account's object is still pushed", || async {
        cluster.history("0x502200").await.contains(&"4".to_owned())
    })
    .await;
    let after = cluster.history_points(&lantern).await;
    assert_eq!(
        count(&after),
        count(&stored),
        "the lantern was pushed after its last watcher's process died: {stored:?}, then {after:?}"
    );
    cluster.stop().await;
}

/// A process killed while its lift's gateway cannot reach another: within the holder TTL
/// (3 s here) no process shows the lift online or relays to the dead one, and the dead
/// process's entry is gone; started again, the process holds the lift again and every
/// process sees it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_holder_leaves_no_lift_online() {
    let Some(mut cluster) = Cluster::start_with("cluster_dead", 2, 3, "").await else {
        return;
    };
    assert_eq!(
        cluster.portals[1].metric("canlift_cluster_processes").await,
        2
    );
    cluster.balancer.route_only_to(0);
    cluster.portals[0].kill().await;
    let offline = until(LIMIT, "p1 shows the lift offline", || async {
        cluster.portals[1].online(&cluster.key).await == 0
    })
    .await;
    eprintln!("the dead holder's lift was offline on p1 after {offline:?}");
    assert_eq!(
        cluster.portals[1].metric("canlift_cluster_processes").await,
        1
    );
    let (status, answer) = cluster.read(1).await;
    assert_eq!(status, 503, "nobody holds the lift: {answer}");
    assert_eq!(
        cluster.portals[1]
            .metric("canlift_cluster_lifts_elsewhere")
            .await,
        0
    );
    // p1, the only process alive, deleted the dead one's entry.
    cluster
        .until_metric(
            1,
            "canlift_cluster_entries_swept_total",
            1,
            "p1 deletes the dead holder's entry",
        )
        .await;
    cluster.portals[0].restart().await;
    let back = cluster.wait_held_by(0).await;
    eprintln!("held again {back:?} after p0 started again");
    assert_eq!(cluster.read(1).await.0, 200, "relayed to the new p0");
    assert_eq!(
        cluster.portals[1].metric("canlift_cluster_processes").await,
        2
    );
    cluster.stop().await;
}

/// A holder frozen (SIGSTOP) for longer than the holder TTL: the other process takes its lift
/// for offline and deletes its entry; thawed, the holder renews its lease, sees its entry gone,
/// writes it again, and every process serves the lift as before.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_holder_frozen_past_its_lease_writes_its_entry_again() {
    let Some(cluster) = Cluster::start_with("cluster_frozen", 2, 3, "").await else {
        return;
    };
    let pid = cluster.portals[0]
        .child
        .as_ref()
        .and_then(|c| c.id())
        .expect("p0 runs");
    let signal = |name: &str| {
        let status = std::process::Command::new("kill")
            .args([format!("-{name}"), pid.to_string()])
            .status()
            .expect("kill runs");
        assert!(status.success(), "kill -{name} {pid}");
    };
    signal("STOP");
    cluster
        .until_metric(
            1,
            "canlift_cluster_entries_swept_total",
            1,
            "p1 deletes the frozen holder's entry",
        )
        .await;
    assert_eq!(cluster.portals[1].online(&cluster.key).await, 0);
    signal("CONT");
    let back = cluster.wait_held_by(0).await;
    eprintln!("the lift was held again {back:?} after p0 was thawed");
    assert_eq!(cluster.read(1).await.0, 200, "relayed to the thawed p0");
    cluster.stop().await;
}

/// NATS stopped: the holder still serves its lift, the other process answers 503 and reports
/// itself degraded; NATS started again: full service without restarting a portal.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nats_outage_degrades_and_heals() {
    let Some(mut cluster) = Cluster::start("cluster_nats", 2).await else {
        return;
    };
    assert_eq!(cluster.read(1).await.0, 200);
    cluster.nats[0].stop();
    until(LIMIT, "p1 reports itself degraded", || async {
        let health = cluster.call(1, "GET", "/healthz", None).await;
        health.1.as_str().is_some_and(|h| h.starts_with("degraded"))
    })
    .await;
    assert_eq!(
        cluster.portals[1]
            .metric("canlift_cluster_nats_connected")
            .await,
        0
    );
    assert_eq!(cluster.read(0).await.0, 200, "the holder serves its lift");
    let (status, answer) = cluster.read(1).await;
    assert_eq!(status, 503, "a lift held elsewhere: {answer}");
    cluster.nats[0].start_again();
    let healed = until(LIMIT, "p1 reads the lift again", || async {
        cluster.read(1).await.0 == 200
    })
    .await;
    eprintln!("full service {healed:?} after NATS came back");
    assert_eq!(
        cluster.portals[1]
            .metric("canlift_cluster_nats_connected")
            .await,
        1
    );
    assert_eq!(
        cluster.call(1, "GET", "/healthz", None).await.1,
        json!("ok\n")
    );
    cluster.stop().await;
}

/// NATS as a cluster of three servers, the holder bucket in three copies: the server the
/// holding process is connected to is killed; the holder goes on through another, still holding
/// the lift, which p1 reads and writes again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nats_cluster_outlives_one_of_its_servers() {
    let Some(servers) = testkit::nats::cluster(3) else {
        return;
    };
    let (nats, monitors): (Vec<Nats>, Vec<u16>) = servers.into_iter().unzip();
    let url = nats.iter().map(Nats::url).collect::<Vec<_>>().join(",");
    let more = "nats_replicas = 3\n";
    let Some(mut cluster) = Cluster::start_on(nats, &url, "cluster_nats3", 2, 6, more).await else {
        return;
    };
    assert_eq!(cluster.read(1).await.0, 200);
    for monitor in &monitors {
        let page = testkit::nats::monitoring(*monitor, "/jsz?streams=true");
        assert!(
            page.contains("KV_canlift-holders"),
            "a copy of the bucket on each server: {page}"
        );
    }
    let p0_on = |monitor: &u16| testkit::nats::serves(*monitor, "canlift portal p0");
    let lost = monitors
        .iter()
        .position(p0_on)
        .expect("p0 is connected to one of the NATS servers");
    cluster.nats[lost].stop();
    let back = until(LIMIT, "p1 reads the lift again", || async {
        cluster.read(1).await.0 == 200
    })
    .await;
    eprintln!("read through p1 {back:?} after NATS server n{lost} was killed");
    until(LIMIT, "p0 goes on through another NATS server", || async {
        monitors
            .iter()
            .enumerate()
            .any(|(i, monitor)| i != lost && p0_on(monitor))
    })
    .await;
    cluster.wait_held_by(0).await;
    cluster.write_0x502200(1, 7).await;
    assert_eq!(cluster.read(1).await.0, 200);
    cluster.stop().await;
}

/// A NATS grown into a cluster: the processes keep the holder bucket in one copy until p1 is
/// started again asking for three — then every server has one, p0 (still asking for one) does
/// not take them away, and the lift stays reachable through both.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_holder_bucket_gains_copies_when_asked() {
    let Some(servers) = testkit::nats::cluster(3) else {
        return;
    };
    let (nats, monitors): (Vec<Nats>, Vec<u16>) = servers.into_iter().unzip();
    let url = nats.iter().map(Nats::url).collect::<Vec<_>>().join(",");
    let Some(mut cluster) = Cluster::start_on(
        nats,
        &url,
        "cluster_more_copies",
        2,
        6,
        "nats_replicas = 1\n",
    )
    .await
    else {
        return;
    };
    let copies = || {
        monitors
            .iter()
            .filter(|m| {
                testkit::nats::monitoring(**m, "/jsz?streams=true").contains("KV_canlift-holders")
            })
            .count()
    };
    assert_eq!(copies(), 1, "one copy, as asked");
    let p1 = &mut cluster.portals[1];
    p1.kill().await;
    let config = std::fs::read_to_string(&p1.config).expect("p1's configuration");
    let three = config.replace("nats_replicas = 1\n", "nats_replicas = 3\n");
    assert_ne!(config, three);
    std::fs::write(&p1.config, three).expect("written");
    p1.restart().await;
    let took = until(LIMIT, "a copy of the bucket on each server", || async {
        copies() == 3
    })
    .await;
    eprintln!("three copies {took:?} after p1 asked for them");
    cluster.wait_held_by(0).await;
    assert_eq!(cluster.read(1).await.0, 200);
    // p0 reconnects to NATS as any process may: it finds three copies and leaves them. (Its
    // gateway comes back to it or, through the balancer, to p1.)
    cluster.portals[0].kill().await;
    cluster.portals[0].restart().await;
    until(
        LIMIT,
        "the lift read through both processes again",
        || async { cluster.read(0).await.0 == 200 && cluster.read(1).await.0 == 200 },
    )
    .await;
    assert_eq!(copies(), 3, "p0 asked for one and left three");
    cluster.stop().await;
}

/// NATS with a user and password and TLS that verifies its clients (the processes' CA for it is
/// not the portals'): the processes reach it with the credentials of their `nats` URL and the
/// client certificate, a lift held by p0 is read through p1; p1 started again with a wrong
/// password serves no lift held elsewhere, and says why in `/healthz`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_with_a_password_and_tls() {
    let nats_dir = testkit::scratch();
    let pki = testkit::pki::pki(nats_dir.path());
    let path = |p: &std::path::Path| p.to_str().expect("UTF-8").to_owned();
    // The configuration docs/CLUSTER.md §Securing NATS shows.
    let conf = nats_dir.path().join("nats.conf");
    let text = format!(
        "authorization {{\n  user: canlift\n  password: \"s3cr:t@x\"\n}}\n\
         tls {{\n  cert_file: \"{}\"\n  key_file: \"{}\"\n  ca_file: \"{}\"\n  verify: true\n}}\n",
        path(&pki.cert),
        path(&pki.key),
        path(&pki.ca)
    );
    std::fs::write(&conf, text).expect("written");
    let conf = path(&conf);
    let options = ["-c", conf.as_str()];
    let Some(nats) = Nats::start_with(&options) else {
        return;
    };
    // The server asks for both (its INFO, sent before TLS).
    let mut info = String::new();
    let stream = std::net::TcpStream::connect(("127.0.0.1", nats.port())).expect("NATS listens");
    std::io::BufRead::read_line(&mut std::io::BufReader::new(stream), &mut info).expect("INFO");
    for asked in [r#""auth_required":true"#, r#""tls_verify":true"#] {
        assert!(info.contains(asked), "{info}");
    }
    let url = format!("tls://canlift:s3cr%3At%40x@127.0.0.1:{}", nats.port());
    let client = format!(
        "nats_ca = \"{}\"\nnats_cert = \"{}\"\nnats_key = \"{}\"\n",
        path(&pki.ca),
        path(&pki.client_cert),
        path(&pki.client_key)
    );
    let Some(mut cluster) =
        Cluster::start_on(vec![nats], &url, "cluster_secured", 2, 6, &client).await
    else {
        return;
    };
    let (status, answer) = cluster.read(1).await;
    assert_eq!(status, 200, "relayed through a secured NATS: {answer}");
    assert_eq!(
        cluster.call(1, "GET", "/healthz", None).await.1,
        json!("ok\n")
    );

    refused_after_restart(
        &mut cluster,
        |p1| {
            let config = std::fs::read_to_string(&p1.config).expect("p1's configuration");
            let wrong = config.replace("s3cr%3At%40x", "wrong");
            assert_ne!(config, wrong);
            std::fs::write(&p1.config, wrong).expect("written");
        },
        &["wrong", "s3cr"],
    )
    .await;
    cluster.stop().await;
}

/// p1 killed, `change` made to what it reads at start, p1 started again: NATS refuses it, and
/// `/healthz` says why (showing none of `secrets`); p1 answers 503 for the lift p0 holds, which
/// p0 still serves.
async fn refused_after_restart(
    cluster: &mut Cluster,
    change: impl FnOnce(&PortalProcess),
    secrets: &[&str],
) {
    let p1 = &mut cluster.portals[1];
    p1.kill().await;
    change(p1);
    p1.restart().await;
    let took = until(LIMIT, "p1 says why it has no NATS", || async {
        let health = cluster.call(1, "GET", "/healthz", None).await.1;
        health
            .as_str()
            .is_some_and(|h| h.contains("authorization violation"))
    })
    .await;
    let answer = cluster.call(1, "GET", "/healthz", None).await.1;
    let health = answer.as_str().unwrap_or_default();
    eprintln!("p1 degraded after {took:?}: {health}");
    assert!(health.starts_with("degraded: NATS unreachable"), "{health}");
    for secret in secrets {
        assert!(!health.contains(secret), "{health}");
    }
    let (status, answer) = cluster.read(1).await;
    assert_eq!(status, 503, "no NATS, no relay: {answer}");
    assert_eq!(cluster.read(0).await.0, 200, "the holder serves its lift");
}

/// A NATS server started with configuration `conf` (written to a file in `dir`), and its
/// monitoring port.
fn secured_nats(dir: &std::path::Path, conf: &str) -> Option<(Nats, u16)> {
    let conf_file = dir.join("nats.conf");
    std::fs::write(&conf_file, conf).expect("written");
    let conf_file = conf_file.to_str().expect("UTF-8").to_owned();
    let monitor = testkit::free_port().to_string();
    let nats = Nats::start_with(&["-c", conf_file.as_str(), "-m", monitor.as_str()])?;
    Some((nats, monitor.parse().expect("a port")))
}

/// A file `name` in `dir` holding `content`: a NATS user's seed or credentials.
fn user_file(dir: &std::path::Path, name: &str, content: &str) -> std::path::PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, content).expect("written");
    path
}

/// Two processes on a NATS server started with configuration `conf`, each reaching it as the
/// user whose file `name` (with `content`) its `[cluster]` names by `option`; a lift held by p0
/// is read through p1.
async fn cluster_on_secured_nats(
    dir: &std::path::Path,
    conf: &str,
    (name, content, option): (&str, &str, &str),
) -> Option<(Cluster, std::path::PathBuf, u16)> {
    let (nats, monitor) = secured_nats(dir, conf)?;
    let url = nats.url();
    let user_file = user_file(dir, name, content);
    let more = format!("{option} = \"{}\"\n", user_file.display());
    let name = format!("cluster_{option}");
    let cluster = Cluster::start_on(vec![nats], &url, &name, 2, 6, &more).await?;
    let (status, answer) = cluster.read(1).await;
    assert_eq!(status, 200, "relayed through NATS ({option}): {answer}");
    assert_eq!(
        cluster.call(1, "GET", "/healthz", None).await.1,
        json!("ok\n")
    );
    Some((cluster, user_file, monitor))
}

/// The NATS user docs/CLUSTER.md §Securing NATS shows (known by its NKey, allowed what a portal
/// process needs and nothing else), as `public` key.
fn documented_nkey_user(public: &str) -> String {
    let page = std::fs::read_to_string(testkit::workspace().join("docs/CLUSTER.md"))
        .expect("docs/CLUSTER.md");
    let begin = page
        .find("```text\nauthorization {\n  users = [")
        .expect("the NKey user's configuration in docs/CLUSTER.md")
        + "```text\n".len();
    let block = &page[begin..];
    let block = &block[..block.find("```").expect("the block's end")];
    let key = block.find("nkey: \"").expect("an nkey") + "nkey: \"".len();
    let end = key + block[key..].find('"').expect("the key's end");
    format!("{}{public}{}", &block[..key], &block[end..])
}

/// NATS that knows its users by NKey, with the permissions docs/CLUSTER.md §Securing NATS gives
/// the portals' user: the processes sign the server's nonce with the seed `nats_nkey` names, a
/// lift held by p0 is read, watched and written through p1, and neither process was refused
/// anything. The key rotated (a new user in NATS's configuration, its seed in the file, NATS
/// restarted), both processes come back as the new user without restarting; p1 started again
/// with another user's seed is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_with_an_nkey_user() {
    let dir = testkit::scratch();
    let (public, seed) = cloud_cluster::nats::new_user_nkey().expect("an NKey");
    let conf = documented_nkey_user(&public);
    let Some((mut cluster, seed_file, monitor)) =
        cluster_on_secured_nats(dir.path(), &conf, ("portal.nk", &seed, "nats_nkey")).await
    else {
        return;
    };
    let mut watch = cluster.watch_lantern(1).await;
    cluster.write_lantern(3).await;
    assert!(
        pushed(&mut watch, 3).await.is_some(),
        "p0's live event reaches p1's watcher"
    );
    cluster.write_0x502200(1, 4).await;
    for index in 0..2 {
        let health = cluster.call(index, "GET", "/healthz", None).await.1;
        assert_eq!(health, json!("ok\n"), "p{index}");
        assert_eq!(
            cluster.portals[index]
                .metric("canlift_cluster_nats_refused_total")
                .await,
            0,
            "p{index}"
        );
    }
    // The key rotated: NATS's configuration names the new user, the file holds its seed.
    let (second, rotated_seed) = cloud_cluster::nats::new_user_nkey().expect("an NKey");
    std::fs::write(dir.path().join("nats.conf"), documented_nkey_user(&second)).expect("written");
    rotated(
        &mut cluster,
        monitor,
        (&seed_file, &rotated_seed),
        [&public, &second],
    )
    .await;
    let (_, stranger) = cloud_cluster::nats::new_user_nkey().expect("an NKey");
    refused_after_restart(
        &mut cluster,
        |_| std::fs::write(&seed_file, &stranger).expect("written"),
        &[&seed, &rotated_seed, &stranger],
    )
    .await;
    cluster.stop().await;
}

/// The documented NATS user without the subscription to the lifts' subjects: the holder cannot
/// take requests for its lift (the other process gets 503 at once: nobody answers on NATS), and
/// says why in `/healthz` and `/metrics`. The permission granted and NATS's configuration
/// reloaded (the processes stay connected), the holder subscribes again by itself and the lift
/// is read through the other process; neither process was restarted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nats_user_without_a_permission_is_degraded_until_granted() {
    let dir = testkit::scratch();
    let (public, seed) = cloud_cluster::nats::new_user_nkey().expect("an NKey");
    let documented = documented_nkey_user(&public);
    let conf = documented.replace(
        r#"subscribe: ["canlift.lift.>", "_INBOX.>"]"#,
        r#"subscribe: ["_INBOX.>"]"#,
    );
    assert_ne!(conf, documented, "the subscribe permission as documented");
    let Some((nats, _)) = secured_nats(dir.path(), &conf) else {
        return;
    };
    let url = nats.url();
    let more = format!(
        "nats_nkey = \"{}\"\n",
        user_file(dir.path(), "portal.nk", &seed).display()
    );
    let Some(cluster) = Cluster::start_on(vec![nats], &url, "cluster_refused", 2, 6, &more).await
    else {
        return;
    };
    let (status, answer) = cluster.read(1).await;
    assert_eq!(status, 503, "nobody takes requests for p0's lift: {answer}");
    let health = cluster.call(0, "GET", "/healthz", None).await.1;
    let health = health.as_str().unwrap_or_default();
    assert!(
        health.starts_with("degraded: NATS refuses this process: Permissions Violation for Subscription to \"canlift.lift."),
        "{health}"
    );
    assert!(
        cluster.portals[0]
            .metric("canlift_cluster_nats_refused_total")
            .await
            >= 1
    );
    assert_eq!(cluster.read(0).await.0, 200, "the holder serves its lift");

    std::fs::write(dir.path().join("nats.conf"), &documented).expect("written");
    let granted = std::time::Instant::now();
    cluster.nats[0].reload();
    let took = until(LIMIT, "the lift read through p1 once granted", || async {
        cluster.read(1).await.0 == 200
    })
    .await;
    eprintln!("p0's lift read through p1 {took:?} after NATS took the permission");
    for index in 0..2 {
        let health = cluster.call(index, "GET", "/healthz", None).await.1;
        assert_eq!(
            health,
            json!("ok\n"),
            "p{index}, {:?} after",
            granted.elapsed()
        );
    }
    cluster.stop().await;
}

/// The processes' user `users[0]` replaced by `users[1]`: its `file` rewritten with `content`
/// (NATS's configuration already holds the new user, or is rewritten beside it), NATS started
/// again. The processes read the file at each connection, so both come back as the new user
/// (the server's view of its clients: `/connz?auth=true`) without being restarted, and serve.
async fn rotated(
    cluster: &mut Cluster,
    monitor: u16,
    (file, content): (&std::path::Path, &str),
    [before, after]: [&str; 2],
) {
    let users = |user: &str| {
        testkit::nats::monitoring(monitor, "/connz?auth=true")
            .matches(user)
            .count()
    };
    assert_eq!(users(before), 2, "both processes as the first user");
    std::fs::write(file, content).expect("written");
    cluster.nats[0].stop();
    cluster.nats[0].start_again();
    let took = until(LIMIT, "both processes back as the new user", || async {
        users(after) == 2 && users(before) == 0
    })
    .await;
    eprintln!("both processes connected as the new user {took:?} after NATS restarted");
    until(LIMIT, "the lift read through p1 again", || async {
        cluster.read(1).await.0 == 200
    })
    .await;
    for index in 0..2 {
        let health = cluster.call(index, "GET", "/healthz", None).await.1;
        assert_eq!(health, json!("ok\n"), "p{index}");
    }
}

/// NATS in operator mode (JWT authentication, as NGS or a server set up with `nsc`): the
/// processes present the user JWT of the credentials file `nats_creds` names and sign with its
/// seed. The file is read at each connection: replaced (a renewed JWT), it is what the processes
/// present when NATS has them connect again — here a restart of the server, as when it lets an
/// expired JWT go. p1 started again with the credentials of another operator's user is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_with_jwt_credentials() {
    let dir = testkit::scratch();
    let operator = testkit::nats::auth::OperatorMode::new();
    let (creds, first) = operator.user(None);
    let Some((mut cluster, creds_file, monitor)) = cluster_on_secured_nats(
        dir.path(),
        &operator.conf,
        ("portal.creds", &creds, "nats_creds"),
    )
    .await
    else {
        return;
    };
    let (renewed, second) = operator.user(None);
    rotated(
        &mut cluster,
        monitor,
        (&creds_file, &renewed),
        [&first, &second],
    )
    .await;

    let (stranger, _) = testkit::nats::auth::OperatorMode::new().user(None);
    // The JWTs and the seeds: the long lines of the files that are not decoration or prose.
    let secrets: Vec<&str> = [&creds, &renewed, &stranger]
        .into_iter()
        .flat_map(|text| text.lines())
        .filter(|line| line.len() > 40 && !line.starts_with(['-', '*']) && !line.contains(' '))
        .collect();
    assert_eq!(secrets.len(), 6);
    refused_after_restart(
        &mut cluster,
        |_| std::fs::write(&creds_file, &stranger).expect("written"),
        &secrets,
    )
    .await;
    cluster.stop().await;
}

/// A lift-offline alarm raised by the process that held the lift is cleared by the process the
/// gateway comes back to (it reads the lift's active alarms from the database when it takes the
/// lift).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_raised_by_one_process_is_cleared_by_another() {
    let Some(mut cluster) =
        Cluster::start_with("cluster_alarms", 2, 6, "[alarms]\noffline_after_s = 1\n").await
    else {
        return;
    };
    let active = |index: usize| {
        let portal = &cluster.portals[index];
        let key = cluster.key.clone();
        async move {
            let (status, answer) = portal
                .client(&key)
                .call("GET", "/api/v1/alarms", None)
                .await
                .expect("an answer");
            assert_eq!(status, 200, "{answer}");
            answer["alarms"]
                .as_array()
                .map(|list| {
                    list.iter()
                        .filter_map(|a| a["kind"].as_str().map(str::to_owned))
                        .collect::<Vec<_>>()
                })
                .unwrap_or_default()
        }
    };
    cluster.lift.stop_gateway().await;
    until(LIMIT, "p0 raises lift-offline", || async {
        active(1).await == ["lift-offline"]
    })
    .await;
    cluster.balancer.route_to(1);
    cluster.lift.start_gateway(cluster.gateway.clone()).await;
    cluster.wait_held_by(1).await;
    until(LIMIT, "p1 clears the alarm p0 raised", || async {
        active(0).await.is_empty()
    })
    .await;
    cluster.stop().await;
}
