//! Fault injection against the real processes (docs/SECURITY.md §Faults): a gateway killed with
//! SIGKILL while it stores a new cloud token, a portal killed during telemetry ingest and during
//! a reconnect storm, and connections that never finish a TLS handshake or an HTTP request.
//! Each test is bounded in time and stops what it started.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use testkit::constants::{LIFT, SERNUM};
use testkit::portal::{until as until_async, Rig};
use testkit::scripted;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::process::Child;
use tokio_tungstenite::tungstenite::Message;

use crate::common;
use common::http::{answer_of, tls_to};
use common::{daemon, kill, PortalProcess};
use testkit::free_port;

/// Kill rounds of the token test (the issue's figure).
const TOKEN_ROUNDS: u32 = 200;

/// The token file's whole content for `token` (`None`: no file).
fn token_file(token: Option<&str>) -> Option<String> {
    token.map(|t| format!("{t}\n"))
}

/// A gateway process killed 200 times while it stores the token `update_unique_token` brought
/// (NXg §5.4): half the time right after its answer arrived, half at a spread of points between
/// the request and the answer. The token file always holds the old or the new token, whole; an
/// answered token is the new one; and the next CONNECT carries what the file holds. Two
/// gateways with portals of their own take 100 kills each, side by side.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_killed_while_storing_its_token_keeps_the_old_or_the_new() {
    let (a, b) = tokio::join!(token_kills(0), token_kills(1));
    eprintln!(
        "{TOKEN_ROUNDS} kills: {} after the answer, {} left the new token, {} the old one",
        a.answered + b.answered,
        a.new_kept + b.new_kept,
        a.old_kept + b.old_kept
    );
}

/// What the kills of one gateway left.
#[derive(Default)]
struct Kills {
    answered: u32,
    new_kept: u32,
    old_kept: u32,
}

/// Half of [`TOKEN_ROUNDS`] kills of one gateway (`lane` 0 or 1 takes the even or odd rounds).
async fn token_kills(lane: u32) -> Kills {
    let dir = testkit::scratch();
    let pki = testkit::pki::pki(dir.path());
    let portal = scripted::Portal::start(&pki).await;
    let hub = testkit::hub().await;
    let config = scripted::config(
        &portal.url(),
        &pki,
        &testkit::hub_url(&hub, "can0"),
        dir.path(),
    );
    let token_path = config.state.dir.join("cloudtoken");
    let config_path = dir.path().join("gateway.toml");
    std::fs::write(&config_path, toml::to_string(&config).expect("TOML")).expect("written");

    let mut on_file: Option<String> = None;
    let mut kills = Kills::default();
    let mut answer_time = Duration::from_millis(5);
    let config_arg = config_path.to_str().expect("UTF-8");
    // A gateway process, and its connection once its CONNECT carried the token on file.
    let portal = &portal;
    let connected = |on_file: Option<String>| async move {
        let gateway = daemon(&["gateway", "--config", config_arg]);
        let (mut ws, ..) = portal.accept().await;
        let connect = scripted::connack(&mut ws).await;
        let sent = connect["params"]["identity"]["cloudtoken"].as_str();
        assert_eq!(sent, on_file.as_deref(), "CONNECT carries the stored token");
        (gateway, ws)
    };
    for round in (lane..TOKEN_ROUNDS).step_by(2) {
        let (mut gateway, mut ws) = connected(on_file.clone()).await;
        let new = format!("T-{round:03}-{}", "x".repeat(round as usize % 100));
        scripted::send(
            &mut ws,
            &format!(
                r#"{{"jsonrpc":"2.0","method":"update_unique_token","id":{round},"params":{{"sernum":"{SERNUM}","token":"{new}"}}}}"#
            ),
        )
        .await;
        let sent_at = tokio::time::Instant::now();
        let wait_for_answer = round % 4 < 2;
        if wait_for_answer {
            let answer = scripted::recv(&mut ws).await;
            assert_eq!(answer["result"]["done"], 0, "round {round}: {answer}");
            kills.answered += 1;
            answer_time = sent_at.elapsed();
        } else {
            // Spread over the whole store: from 0 to twice the last time an answer took.
            tokio::time::sleep(answer_time * (round * 37 % 100) / 50).await;
        }
        kill(&mut gateway).await;
        let content = std::fs::read_to_string(&token_path).ok();
        if wait_for_answer {
            assert_eq!(
                content,
                token_file(Some(&new)),
                "round {round}: an answered token is on file"
            );
        } else {
            assert!(
                content == token_file(on_file.as_deref()) || content == token_file(Some(&new)),
                "round {round}: the token file is torn: {content:?} (old {on_file:?}, new {new:?})"
            );
        }
        if content == token_file(Some(&new)) {
            kills.new_kept += 1;
        } else {
            kills.old_kept += 1;
        }
        on_file = content.map(|c| c.trim_end_matches('\n').to_owned());
        // At most the token and one temporary file a kill left behind.
        let files = std::fs::read_dir(&config.state.dir)
            .expect("the state directory")
            .filter_map(Result::ok)
            .filter(|e| e.file_name().to_string_lossy().contains("cloudtoken"))
            .count();
        assert!(files <= 2, "round {round}: {files} token files");
    }
    // The last token is accepted: a gateway started once more sends it.
    let (mut gateway, _ws) = connected(on_file).await;
    kill(&mut gateway).await;
    hub.shutdown().await;
    kills
}

/// A free loopback port for a process the test restarts on the same address.
/// `canlift loadgen`: `gateways` simulated gateways for domain LOAD whose values change every
/// 50 ms, their tokens in `state`.
fn loadgen(portal: &PortalProcess, gateways: usize, state: &Path) -> Child {
    let (url, ca) = (format!("wss://localhost:{}/ws", portal.port), portal.ca());
    let gateways = gateways.to_string();
    daemon(&[
        "loadgen",
        "--portal",
        &url,
        "--ca",
        ca.to_str().expect("UTF-8"),
        "--domain",
        "LOAD",
        "--sources",
        "4",
        "--change-ms",
        "50",
        "--gateways",
        &gateways,
        "--state",
        state.to_str().expect("UTF-8"),
    ])
}

/// A portal killed with SIGKILL while 100 gateways push telemetry, and again while they storm
/// back: every value the portal had counted as stored before the kill is in the database, the
/// database passes `integrity_check`, and every gateway is back online after each restart within
/// its backoff (1 s doubling, fully jittered).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_portal_killed_during_ingest_and_reconnect_loses_nothing_it_stored() {
    const GATEWAYS: usize = 100;
    let dir = testkit::scratch();
    let (mut portal, key) = PortalProcess::start(dir.path(), "").await;
    let mut fleet = loadgen(&portal, GATEWAYS, &dir.path().join("gateways"));
    portal
        .wait_online(&key, GATEWAYS, Duration::from_secs(60))
        .await;

    for kill_round in 1..=3 {
        // Ingest under way: the counter moves.
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        let before = portal.stored().await;
        let ledger = loop {
            tokio::time::sleep(Duration::from_millis(300)).await;
            let now = portal.stored().await;
            if now > before {
                break now;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "round {kill_round}: no telemetry stored in 30 s"
            );
        };
        portal.kill().await;
        let (rows, check) = portal.inspect().await;
        assert_eq!(check, "ok", "round {kill_round}: integrity_check");
        assert!(
            rows >= ledger,
            "round {kill_round}: {rows} rows, but the portal had stored {ledger} before the kill"
        );
        eprintln!("kill {kill_round}: {ledger} values acknowledged, {rows} rows on disk");

        portal.restart().await;
        if kill_round == 2 {
            // Killed again in the middle of the reconnect storm.
            tokio::time::sleep(Duration::from_millis(300)).await;
            portal.kill().await;
            let (_, check) = portal.inspect().await;
            assert_eq!(check, "ok", "killed during the storm: integrity_check");
            portal.restart().await;
        }
        let took = portal
            .wait_online(&key, GATEWAYS, Duration::from_secs(90))
            .await;
        eprintln!("kill {kill_round}: all {GATEWAYS} back online after {took:?}");
    }
    kill(&mut fleet).await;
    portal.kill().await;
}

/// 1,000 TCP connections that never send a TLS hello, a client that sends an HTTP request
/// one byte at a time (slowloris) and one that never sends the body its head declares: gateways
/// still connect and operators are still answered while they hang, and the portal closes every
/// one of them by its timeouts (TLS handshake 10 s, request head 10 s, a small body 10 s).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_and_slow_clients_are_closed_and_block_no_one() {
    let dir = testkit::scratch();
    let (mut portal, key) = PortalProcess::start(dir.path(), "").await;
    let silent = silent_connections(&portal, 1000).await;
    let slow = tokio::spawn(slowloris(portal.port, portal.ca()));
    let slow_body = tokio::spawn(slow_body(portal.port, portal.ca()));
    let begin = tokio::time::Instant::now();
    // While they hang, gateways connect and an operator is answered.
    let mut fleet = loadgen(&portal, 10, &dir.path().join("gateways"));
    portal.wait_online(&key, 10, Duration::from_secs(30)).await;
    assert!(
        begin.elapsed() < Duration::from_secs(10),
        "served before any timeout fired: {:?}",
        begin.elapsed()
    );
    // Every silent connection is closed by the handshake timeout.
    let mut closed = 0;
    for mut tcp in silent {
        let mut byte = [0u8; 1];
        match tokio::time::timeout(Duration::from_secs(30), tcp.read(&mut byte)).await {
            Ok(Ok(0) | Err(_)) => closed += 1,
            Ok(Ok(_)) => panic!("the portal sent something to a client that said nothing"),
            Err(_) => panic!("a silent connection is still open after 30 s"),
        }
    }
    assert_eq!(closed, 1000);
    let slow_lasted = slow.await.expect("the slow client ends");
    assert!(
        slow_lasted < Duration::from_secs(30),
        "the slow request was closed after {slow_lasted:?}"
    );
    let body_lasted = slow_body.await.expect("the client of a missing body ends");
    assert!(
        body_lasted < Duration::from_secs(30),
        "the request without its body was closed after {body_lasted:?}"
    );
    // The gateways stayed.
    assert_eq!(portal.online(&key).await, 10);
    kill(&mut fleet).await;
    portal.kill().await;
}

/// `n` TCP connections to the portal that say nothing (the listen queue takes those it does
/// not accept yet).
async fn silent_connections(portal: &PortalProcess, n: usize) -> Vec<TcpStream> {
    let mut connections = Vec::with_capacity(n);
    for _ in 0..n {
        connections.push(
            TcpStream::connect(("127.0.0.1", portal.port))
                .await
                .expect("a TCP connection"),
        );
    }
    connections
}

/// A portal process out of file descriptors: more connections come than it has descriptors
/// left. It warns (once per episode), counts the failed accepts, keeps the gateway it holds, and
/// takes connections again once descriptors are free — the ones that came meanwhile waited in
/// the listen queue (docs/PORTAL.md §Metrics).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_portal_out_of_file_descriptors_serves_again_once_some_are_free() {
    let dir = testkit::scratch();
    let mut portal = PortalProcess::configure(dir.path(), "");
    let key = portal.add_account("load", "LOAD").await;
    // About 20 descriptors are the process's own (database, runtime, listener).
    let mut log = portal.restart_with_files(64).await;
    let mut fleet = loadgen(&portal, 1, &dir.path().join("gateways"));
    portal.wait_online(&key, 1, Duration::from_secs(30)).await;
    let flood = silent_connections(&portal, 100).await;
    let warned = tokio::time::timeout(Duration::from_secs(30), async {
        while let Ok(Some(line)) = log.next_line().await {
            if line.contains("accept failed") {
                return line;
            }
        }
        panic!("the portal's log ended without the accept failure");
    })
    .await
    .expect("the accept failure is logged within 30 s");
    assert!(warned.contains("Too many open files"), "{warned}");
    drop(flood);
    // An operator's connection is taken again, and the gateway kept its connection throughout.
    portal.wait_online(&key, 1, Duration::from_secs(30)).await;
    assert!(portal.metric("canlift_accept_failures_total").await >= 1);
    assert_eq!(portal.metric("canlift_gateway_connections_total").await, 1);
    kill(&mut fleet).await;
    portal.kill().await;
}

/// Open TLS to the portal and send a request head one byte every 500 ms; how long until the
/// portal closed the connection.
async fn slowloris(port: u16, ca: PathBuf) -> Duration {
    let mut stream = tls_to(port, &ca).await;
    let begin = tokio::time::Instant::now();
    let head = b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-Slow: ";
    for byte in head.iter().chain(std::iter::repeat(&b'a')) {
        if stream.write_all(&[*byte]).await.is_err() || stream.flush().await.is_err() {
            break;
        }
        let mut buf = [0u8; 256];
        match tokio::time::timeout(Duration::from_millis(500), stream.read(&mut buf)).await {
            Ok(Ok(0) | Err(_)) => break,
            Ok(Ok(n)) => {
                // hyper answers a timed-out head with 408 before closing.
                let answer = String::from_utf8_lossy(&buf[..n]).into_owned();
                assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
                break;
            }
            Err(_) => {}
        }
        if begin.elapsed() > Duration::from_secs(60) {
            break;
        }
    }
    begin.elapsed()
}

/// Open TLS to the portal and send a request head that declares a body, then no body; how long
/// until the portal answered 408 and closed the connection.
async fn slow_body(port: u16, ca: PathBuf) -> Duration {
    let mut stream = tls_to(port, &ca).await;
    let begin = tokio::time::Instant::now();
    let head =
        "POST /api/v1/lifts/x/privilege HTTP/1.1\r\nHost: localhost\r\nContent-Length: 40\r\n\r\n";
    stream
        .write_all(head.as_bytes())
        .await
        .expect("the head is sent");
    let answer = tokio::time::timeout(Duration::from_secs(60), answer_of(&mut stream))
        .await
        .expect("an answer within a minute");
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    let mut byte = [0u8; 1];
    let closed = tokio::time::timeout(Duration::from_secs(5), stream.read(&mut byte)).await;
    assert!(
        matches!(closed, Ok(Ok(0) | Err(_))),
        "the connection stays open after a body that never came"
    );
    begin.elapsed()
}

/// Requests the portal refuses without looking at their bodies (405 from the router, 401 for
/// no credential, 404 for no route), each body sent 200 ms after its head as a client busy
/// elsewhere may: the answer comes after the body, and the next request on the same connection
/// is answered — the portal does not close a connection because a refusal left a body unread
/// (a client that sent its next request meanwhile would lose it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refusal_leaves_the_connection_usable() {
    let dir = testkit::scratch();
    let (mut portal, _key) = PortalProcess::start(dir.path(), "").await;
    let mut stream = tls_to(portal.port, &portal.ca()).await;
    let body = r#"{"password": "service", "privilege": 1}"#;
    for (method, path, refused) in [
        ("PUT", "/healthz", "405"),
        ("POST", "/api/v1/lifts/x/privilege", "401"),
        ("POST", "/nowhere", "404"),
        ("DELETE", "/api/v1/lifts", "405"),
    ] {
        let head = format!(
            "{method} {path} HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n",
            body.len()
        );
        stream.write_all(head.as_bytes()).await.expect("sent");
        stream.flush().await.expect("sent");
        tokio::time::sleep(Duration::from_millis(200)).await;
        stream.write_all(body.as_bytes()).await.expect("sent");
        stream.flush().await.expect("sent");
        let answer = answer_of(&mut stream).await;
        assert!(
            answer.starts_with(&format!("HTTP/1.1 {refused}")),
            "{method} {path}: {answer}"
        );
        // A closed connection fails the write or gives no answer: both end in the assert.
        let next = b"GET /healthz HTTP/1.1\r\nHost: localhost\r\n\r\n";
        let answer = match stream.write_all(next).await {
            Ok(()) => answer_of(&mut stream).await,
            Err(e) => e.to_string(),
        };
        assert!(
            answer.starts_with("HTTP/1.1 200"),
            "after {method} {path}, the next request on the connection: {answer:?}"
        );
    }
    portal.kill().await;
}

/// A TCP proxy between a gateway and its portal that the test turns hostile: it can stall the
/// connections it carries (stop forwarding without closing: a half-open link), deliver one byte
/// at a time, or reset the connection in the middle of the next message to the gateway.
#[derive(Default)]
struct Proxy {
    /// Connections accepted so far (each gets the next number).
    accepted: AtomicU64,
    /// Connections numbered below this stall for good.
    stalled_below: AtomicU64,
    /// Connections numbered below this are reset in the middle of their next message.
    reset_below: AtomicU64,
    /// Deliver one byte at a time (each written and flushed alone).
    bytewise: AtomicBool,
}

impl Proxy {
    /// Listen on a loopback port and forward each connection to `target`; the listening port.
    fn start(self: &Arc<Proxy>, target: u16) -> u16 {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("a loopback port");
        let port = listener.local_addr().expect("bound").port();
        listener.set_nonblocking(true).expect("non-blocking");
        let proxy = self.clone();
        tokio::spawn(async move {
            let listener = tokio::net::TcpListener::from_std(listener).expect("a tokio listener");
            while let Ok((gateway, _)) = listener.accept().await {
                let number = proxy.accepted.fetch_add(1, Ordering::SeqCst);
                let Ok(portal) = TcpStream::connect(("127.0.0.1", target)).await else {
                    continue;
                };
                tokio::spawn(proxy.clone().carry(number, gateway, portal));
            }
        });
        port
    }

    /// Stall every connection open now; later ones are forwarded.
    fn stall_current(&self) {
        self.stalled_below
            .store(self.accepted.load(Ordering::SeqCst), Ordering::SeqCst);
    }

    /// Reset every connection open now in the middle of its next message to the gateway.
    fn reset_current(&self) {
        self.reset_below
            .store(self.accepted.load(Ordering::SeqCst), Ordering::SeqCst);
    }

    /// Carry one connection both ways until either side closes (or the test breaks it).
    async fn carry(self: Arc<Proxy>, number: u64, mut gateway: TcpStream, mut portal: TcpStream) {
        let (mut up, mut down) = (vec![0u8; 16 * 1024], vec![0u8; 16 * 1024]);
        loop {
            if number < self.stalled_below.load(Ordering::SeqCst) {
                // Half-open: hold both sockets, read nothing, send nothing, close nothing.
                std::future::pending::<()>().await;
            }
            let (n, to_gateway) = tokio::select! {
                n = gateway.read(&mut up) => (n, false),
                n = portal.read(&mut down) => (n, true),
                // Look at the switches again now and then.
                _ = tokio::time::sleep(Duration::from_millis(100)) => continue,
            };
            let Ok(n @ 1..) = n else {
                return;
            };
            if number < self.stalled_below.load(Ordering::SeqCst) {
                continue;
            }
            let (bytes, to) = if to_gateway {
                (&down[..n], &mut gateway)
            } else {
                (&up[..n], &mut portal)
            };
            if to_gateway && number < self.reset_below.load(Ordering::SeqCst) {
                let _ = to.write_all(&bytes[..n / 2]).await;
                // SO_LINGER 0: closing sends RST, not FIN.
                let _ = gateway.set_zero_linger();
                let _ = portal.set_zero_linger();
                return;
            }
            let written = if self.bytewise.load(Ordering::SeqCst) {
                let mut result = Ok(());
                for byte in bytes {
                    result = to.write_all(std::slice::from_ref(byte)).await;
                    if result.is_err() {
                        break;
                    }
                    let _ = to.flush().await;
                }
                result
            } else {
                to.write_all(bytes).await
            };
            if written.is_err() {
                return;
            }
        }
    }
}

/// The portal (in this process) and the simulated lift's gateway, connected through `proxy`.
/// The portal asks for a heartbeat every second and gives a silent link up after 2 × 1 s + 30 s;
/// the gateway expects one every 5 s and gives up after 2 × 5 s + 30 s, so the portal's end of a
/// half-open link is seen before the gateway dials again (a new connection would replace the old
/// one and hide whether the portal noticed the silence by itself).
async fn rig_behind(proxy: &Arc<Proxy>) -> Rig {
    let proxy = proxy.clone();
    Rig::builder()
        .portal(|c| c.gateways.heartbeat_s = 1)
        .gateway(move |c| {
            let port = c
                .cloud
                .url
                .rsplit_once(':')
                .and_then(|(_, rest)| rest.trim_end_matches("/ws").parse().ok())
                .expect("the portal's port");
            c.cloud.url = format!("wss://localhost:{}/ws", proxy.start(port));
            c.cloud.heartbeat_s = GATEWAY_HEARTBEAT.as_secs();
        })
        .start()
        .await
}

/// Trip counter through the portal: the status code.
async fn read_trips(rig: &Rig) -> u16 {
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001");
    rig.call("GET", &path, Some(&rig.key), None).await.0
}

/// Wait until `check` holds, checking every 100 ms, for at most `limit`; how long it took.
async fn until(limit: Duration, what: &str, mut check: impl FnMut() -> bool) -> Duration {
    until_async(limit, what, || std::future::ready(check())).await
}

/// The heartbeat the gateways behind the test proxy expect.
const GATEWAY_HEARTBEAT: Duration = Duration::from_secs(5);

/// A link that stops forwarding without closing: the portal marks the lift offline and the
/// gateway dials again, each within its silence limit (2 × heartbeat + 30 s); the new connection
/// serves requests.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_half_open_link_is_given_up_by_both_sides() {
    let proxy = Arc::new(Proxy::default());
    let rig = rig_behind(&proxy).await;
    rig.online().await;
    assert_eq!(read_trips(&rig).await, 200);
    // The gateway's limit, then a reconnection delay of at most 2 s (backoff after at most one
    // failed attempt), with room for a loaded machine.
    let window = nxg::silence_limit(GATEWAY_HEARTBEAT) + Duration::from_secs(10);
    proxy.stall_current();
    let (mut portal_gave_up, mut gateway_gave_up) = (None, None);
    let begin = tokio::time::Instant::now();
    until(window, "both sides give the silent link up", || {
        if portal_gave_up.is_none() && !rig.registry().online(LIFT) {
            portal_gave_up = Some(begin.elapsed());
        }
        if gateway_gave_up.is_none() && proxy.accepted.load(Ordering::SeqCst) >= 2 {
            gateway_gave_up = Some(begin.elapsed());
        }
        portal_gave_up.is_some() && gateway_gave_up.is_some()
    })
    .await;
    eprintln!("half-open link: portal gave up after {portal_gave_up:?}, gateway after {gateway_gave_up:?}");
    let portal = portal_gave_up.expect("until returns once both gave up");
    let gateway = gateway_gave_up.expect("until returns once both gave up");
    assert!(
        portal <= nxg::silence_limit(Duration::from_secs(1)) + Duration::from_secs(5),
        "the portal ends a silent link at its own limit: {portal:?}"
    );
    assert!(
        gateway >= nxg::silence_limit(GATEWAY_HEARTBEAT) - Duration::from_secs(1),
        "the gateway waits for its own limit: {gateway:?}"
    );
    rig.online().await;
    assert_eq!(read_trips(&rig).await, 200);
    rig.stop().await;
}

/// A link that delivers one byte at a time still carries the connector (CONNECT, requests,
/// answers); one reset in the middle of a message to the gateway costs the request in flight an
/// error answer, and the gateway is back at once with its token.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trickling_link_works_and_a_reset_one_reconnects() {
    let proxy = Arc::new(Proxy::default());
    proxy.bytewise.store(true, Ordering::SeqCst);
    let rig = rig_behind(&proxy).await;
    rig.online().await;
    assert_eq!(read_trips(&rig).await, 200, "one byte at a time");
    proxy.bytewise.store(false, Ordering::SeqCst);

    proxy.reset_current();
    let status = read_trips(&rig).await;
    assert!(
        (502..=504).contains(&status),
        "the request whose message was cut: {status}"
    );
    until(Duration::from_secs(10), "the gateway dials again", || {
        proxy.accepted.load(Ordering::SeqCst) >= 2
    })
    .await;
    rig.online().await;
    assert_eq!(read_trips(&rig).await, 200);
    // Still the same lift, known by its token: one lift, no refused attempt.
    let (_, lifts) = rig.call("GET", "/api/v1/lifts", Some(&rig.key), None).await;
    assert_eq!(lifts.as_array().map(Vec::len), Some(1), "{lifts}");
    rig.stop().await;
}

/// A portal whose database takes values more slowly than its gateways push them (a queue of one
/// value in front of the writer, every change pushed): each connection waits for room instead of
/// dropping what it received, reading nothing more from its gateway meanwhile, so TCP slows the
/// gateways down. Nothing is dropped, the gateways stay connected and operators' reads are
/// answered throughout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_overloaded_portal_pushes_back_instead_of_dropping() {
    const GATEWAYS: usize = 20;
    let dir = testkit::scratch();
    let extra = "[database]\ntelemetry_queue = 1\n[dashboard]\ninhibit_ms = 0\n";
    let (portal, key) = PortalProcess::start(dir.path(), extra).await;
    let mut fleet = loadgen(&portal, GATEWAYS, &dir.path().join("gateways"));
    portal
        .wait_online(&key, GATEWAYS, Duration::from_secs(60))
        .await;
    let stored_before = portal.stored().await;
    let path = "/api/v1/lifts/1050-4097-LOAD-000001/objects/0x652001";
    let begin = tokio::time::Instant::now();
    let mut reads = 0;
    while begin.elapsed() < Duration::from_secs(5) {
        let answer = portal.client(&key).call("GET", path, None).await;
        assert_eq!(answer.expect("an answer").0, 200, "a read under push-back");
        reads += 1;
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let stored = portal.stored().await - stored_before;
    let waits = portal.metric("canlift_telemetry_waits_total").await;
    let dropped = portal.metric("canlift_telemetry_dropped_total").await;
    eprintln!("push-back: {stored} stored, {waits} waits, {dropped} dropped, {reads} reads");
    assert!(waits > 0, "the queue was full at times: connections waited");
    assert_eq!(dropped, 0, "nothing is dropped while the database keeps up");
    assert!(stored > 0, "values are stored");
    assert_eq!(
        portal.metric("canlift_gateways_online").await,
        GATEWAYS as u64,
        "the gateways stay connected"
    );
    kill(&mut fleet).await;
    let mut portal = portal;
    portal.kill().await;
}

/// PostgreSQL stopped for 20 s under a portal whose gateways push telemetry: the gateways stay
/// connected, operators keep reading lifts (an API key seen before the outage still counts),
/// the values wait in the portal up to `[database] telemetry_queue` and the rest are dropped and
/// counted; when the database is back the portal writes again without a restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_outage_is_ridden_out() {
    const GATEWAYS: usize = 10;
    const QUEUE: u64 = 500;
    let Some(mut database) = testkit::PostgresServer::start() else {
        return;
    };
    let dir = testkit::scratch();
    let extra = format!(
        "[database]\nurl = \"{}\"\ntelemetry_queue = {QUEUE}\n",
        database.url()
    );
    let (portal, key) = PortalProcess::start(dir.path(), &extra).await;
    let mut fleet = loadgen(&portal, GATEWAYS, &dir.path().join("gateways"));
    portal
        .wait_online(&key, GATEWAYS, Duration::from_secs(60))
        .await;
    let lift = "1050-4097-LOAD-000001";
    let read = || async {
        let path = format!("/api/v1/lifts/{lift}/objects/0x652001");
        portal.client(&key).call("GET", &path, None).await
    };
    assert_eq!(read().await.expect("an answer").0, 200);
    let stored_before = portal.stored().await;

    database.stop();
    let begin = tokio::time::Instant::now();
    let mut reads = 0;
    while begin.elapsed() < Duration::from_secs(20) {
        let answer = read().await.expect("an answer");
        assert_eq!(answer.0, 200, "a read during the outage: {answer:?}");
        reads += 1;
        assert_eq!(
            portal.metric("canlift_gateways_online").await,
            GATEWAYS as u64,
            "the gateways stay connected"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    let queued = portal.metric("canlift_telemetry_queued").await;
    let dropped = portal.metric("canlift_telemetry_dropped_total").await;
    eprintln!("outage: {reads} reads answered, {queued} values waiting, {dropped} dropped");
    assert_eq!(queued, QUEUE, "the queue filled to its bound");
    assert!(dropped > 0, "what did not fit is dropped and counted");

    database.start_again();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let stored = portal.stored().await;
        if stored >= stored_before + QUEUE
            && portal.metric("canlift_telemetry_queued").await < QUEUE
        {
            eprintln!("after the outage: {} values stored", stored - stored_before);
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the portal does not write again: {stored} stored"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // The operator API needs the database again for the list of lifts, and has it.
    assert_eq!(portal.online(&key).await, GATEWAYS);
    kill(&mut fleet).await;
    let mut portal = portal;
    portal.kill().await;
}

/// The sample lift (testkit) as processes: the hub, the simulator on it, and a gateway in
/// bus-node mode connected to `portal` as a lift of domain LOAD, once the lift answers reads;
/// returns the hub's port and the three processes.
async fn lift_on_hub(portal: &PortalProcess, key: &str, dir: &Path) -> (u16, Child, Child, Child) {
    let port = free_port();
    let listen = format!("127.0.0.1:{port}");
    let hub = daemon(&["hub", "--listen", &listen]);
    let bus = format!("socketcand://{listen}/can0");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while TcpStream::connect(("127.0.0.1", port)).await.is_err() {
        assert!(tokio::time::Instant::now() < deadline, "the hub listens");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let sim = daemon(&["sim", "--bus", &bus]);
    let ws = format!("wss://localhost:{}/ws", portal.port);
    let mut config = testkit::lift::gateway_config(&ws, &portal.ca(), &bus, &dir.join("gateway"));
    config.identity.domaintoken = "LOAD".into();
    let path = dir.join("gateway.toml");
    std::fs::write(&path, toml::to_string(&config).expect("TOML")).expect("written");
    let gateway = daemon(&["gateway", "--config", path.to_str().expect("UTF-8")]);
    portal.wait_online(key, 1, Duration::from_secs(30)).await;
    let client = portal.client(key);
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001");
    until_async(Duration::from_secs(30), "the lift answers", || async {
        client
            .call("GET", &path, None)
            .await
            .is_ok_and(|a| a.0 == 200)
    })
    .await;
    (port, hub, sim, gateway)
}

/// The hub killed under a connected lift: while it is down the gateway answers reads with the
/// SDO timeout (05040000h, 504 at the portal) and stays connected to the portal; once a hub
/// listens again the simulator and the gateway find it and reads work again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_hub_costs_answers_not_the_connection() {
    let dir = testkit::scratch();
    let (mut portal, key) = PortalProcess::start(dir.path(), "").await;
    let (port, mut hub, mut sim, mut gateway) = lift_on_hub(&portal, &key, dir.path()).await;
    let client = portal.client(&key);
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001");
    let read = || async { client.call("GET", &path, None).await.expect("an answer") };

    kill(&mut hub).await;
    for _ in 0..5 {
        let (status, body) = read().await;
        assert_eq!(status, 504, "{body}");
        assert_eq!(body["code"], 0x0504_0000, "the SDO timeout: {body}");
        assert_eq!(portal.online(&key).await, 1, "the gateway stays connected");
    }

    let mut hub = daemon(&["hub", "--listen", &format!("127.0.0.1:{port}")]);
    let back = until_async(Duration::from_secs(30), "reads work again", || async {
        read().await.0 == 200
    })
    .await;
    eprintln!("hub restarted: reads answered again after {back:?}");
    for child in [&mut hub, &mut sim, &mut gateway] {
        kill(child).await;
    }
    portal.kill().await;
}

/// How long one read of the trip counter through the portal takes.
async fn timed_read(client: &cloud::client::Client) -> Duration {
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001");
    let begin = tokio::time::Instant::now();
    let (status, body) = client.call("GET", &path, None).await.expect("an answer");
    assert_eq!(status, 200, "{body}");
    begin.elapsed()
}

fn median(mut times: Vec<Duration>) -> Duration {
    times.sort();
    times[times.len() / 2]
}

/// 10,000 frames/s of garbage on the lift's bus (identifiers no CiA 301/417 service of the lift
/// uses, 11- and 29-bit, random data): every node must read and drop them, and the gateway keeps
/// answering within twice its normal latency (medians of 30 reads through the portal).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_garbage_flood_on_the_bus_leaves_answers_timely() {
    const RATE: u64 = 10_000;
    let dir = testkit::scratch();
    let (mut portal, key) = PortalProcess::start(dir.path(), "").await;
    let (port, mut hub, mut sim, mut gateway) = lift_on_hub(&portal, &key, dir.path()).await;
    let client = portal.client(&key);
    let bus = canbus::Bus::open(&format!("socketcand://127.0.0.1:{port}/can0"))
        .await
        .expect("the hub");
    // The receiving half stays open (and unread) for as long as the flood lasts.
    let (sender, _receiver) = bus.split();
    let flooding = Arc::new(AtomicBool::new(false));
    let sent = Arc::new(AtomicU64::new(0));
    let flood = tokio::spawn({
        let (flooding, sent) = (flooding.clone(), sent.clone());
        async move {
            let mut seed = 0x2545_F491_4F6C_DD1Du64;
            let mut next = move || {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                seed
            };
            let mut tick = tokio::time::interval(Duration::from_millis(1));
            loop {
                tick.tick().await;
                if !flooding.load(Ordering::SeqCst) {
                    continue;
                }
                for _ in 0..RATE / 1000 {
                    let r = next();
                    let data = r.to_le_bytes();
                    let len = (r >> 60) as usize % 9;
                    let frame = if r & 1 == 0 {
                        // 780h…7DFh: above heartbeats (700h…77Fh), below LSS (7E4h/7E5h).
                        canbus::Frame::standard(0x780 + (r >> 8) as u16 % 0x60, &data[..len])
                    } else {
                        let id = canbus::CanId::extended((r >> 8) as u32 & 0x1FFF_FFFF)
                            .expect("a 29-bit id");
                        canbus::Frame::new(id, &data[..len])
                    };
                    if sender.send(frame.expect("a frame")).await.is_ok() {
                        sent.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
    });
    // Calm and flooded reads take turns, so whatever else the machine does weighs on both.
    let (mut calm, mut flooded) = (Vec::new(), Vec::new());
    let mut flood_time = Duration::ZERO;
    for _ in 0..5 {
        for _ in 0..6 {
            calm.push(timed_read(&client).await);
        }
        flooding.store(true, Ordering::SeqCst);
        let begin = tokio::time::Instant::now();
        tokio::time::sleep(Duration::from_millis(300)).await;
        for _ in 0..6 {
            flooded.push(timed_read(&client).await);
        }
        flooding.store(false, Ordering::SeqCst);
        flood_time += begin.elapsed();
    }
    flood.abort();
    let rate = sent.load(Ordering::Relaxed) as f64 / flood_time.as_secs_f64();
    let (calm, flooded) = (median(calm), median(flooded));
    eprintln!("garbage flood: {rate:.0} frames/s; median read {calm:?} calm, {flooded:?} flooded");
    assert!(
        rate > RATE as f64 * 0.8,
        "the flood reached {rate:.0} frames/s"
    );
    // Twice the calm latency, and 10 ms for the scheduler of a shared 2-core machine running
    // debug builds of five processes.
    assert!(
        flooded <= calm * 2 + Duration::from_millis(10),
        "median read {flooded:?} under the flood, {calm:?} without"
    );
    for child in [&mut hub, &mut sim, &mut gateway] {
        kill(child).await;
    }
    portal.kill().await;
}

/// Answers to the portal's own requests are not a gateway's flood: with a limit of 5 messages/s
/// (bursts of 10) and nothing subscribed as the lift connects, 8 operators reading the lift at
/// once, 200 reads in all, are all answered and the lift stays online. The limit still closes a
/// gateway that sends on its own (`an_abusive_gateway_is_closed_alone`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn answers_to_the_portals_requests_do_not_count_against_the_message_rate() {
    let rig = Rig::builder()
        .portal(|c| {
            c.gateways.max_messages_per_s = 5;
            c.dashboard.live.clear();
            c.dashboard.parameters.clear();
            c.dashboard.events.clear();
        })
        .start()
        .await;
    rig.online().await;
    let client = cloud::client::Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca))
        .expect("a client of the portal");
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
    let mut connections = Vec::new();
    for _ in 0..8 {
        connections.push(client.connect().await.expect("a connection"));
    }
    let begin = tokio::time::Instant::now();
    let answered = futures_util::future::join_all(connections.iter_mut().map(|c| async {
        let mut statuses = Vec::new();
        for _ in 0..25 {
            statuses.push(
                c.call("GET", &path, None)
                    .await
                    .map(|(status, _)| status)
                    .ok(),
            );
        }
        statuses
    }))
    .await;
    let took = begin.elapsed();
    let ok = answered
        .iter()
        .flatten()
        .filter(|s| **s == Some(200))
        .count();
    assert_eq!(ok, 200, "{answered:?}");
    // Unless this took 38 s, more answers than the limit lets a gateway send of its own.
    eprintln!("200 reads in {took:?}");
    assert!(rig.registry().online(LIFT), "the lift stays online");
    rig.stop().await;
}

/// Until the portal closes `ws`: the close code it gave, if any (`None`: closed without one).
async fn closed<S>(ws: &mut S, limit: Duration) -> Option<u16>
where
    S: futures_util::Stream<Item = Result<Message, tokio_tungstenite::tungstenite::Error>> + Unpin,
{
    use futures_util::StreamExt;
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, ws.next()).await {
            Err(_) => panic!("still open after {limit:?}"),
            Ok(Some(Ok(Message::Close(frame)))) => return frame.map(|f| u16::from(f.code)),
            Ok(Some(Ok(_))) => continue,
            Ok(Some(Err(_)) | None) => return None,
        }
    }
}

/// A gateway that sends a 1 MB message, and one that sends 10,000 messages a second, are each
/// closed alone (1008 for the rate); the lift of another account stays online and answers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_abusive_gateway_is_closed_alone() {
    use futures_util::{SinkExt, StreamExt};
    let rig = Rig::builder().start().await;
    rig.online().await;

    let mut big = rig.hand_made_gateway("ABUSE-BIG", "OTH").await;
    let _ = big.send(Message::Text("x".repeat(1 << 20).into())).await;
    closed(&mut big, Duration::from_secs(10)).await;
    assert_eq!(read_trips(&rig).await, 200);

    let ws = rig.hand_made_gateway("ABUSE-FAST", "OTH").await;
    let (mut tx, mut rx) = ws.split();
    let note =
        r#"{"jsonrpc":"2.0","method":"canopen_object","result":{"mplex":"0x652001","value":"1"}}"#;
    let flood = tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(1));
        let mut sent = 0u64;
        loop {
            tick.tick().await;
            for _ in 0..10 {
                if tx.send(Message::Text(note.into())).await.is_err() {
                    return sent;
                }
                sent += 1;
            }
        }
    });
    let begin = tokio::time::Instant::now();
    let code = closed(&mut rx, Duration::from_secs(10)).await;
    let took = begin.elapsed();
    flood.abort();
    eprintln!("10,000 messages/s: closed after {took:?} with {code:?}");
    assert_eq!(code, Some(1008), "policy violation");
    assert_eq!(read_trips(&rig).await, 200);
    assert!(rig.registry().online(LIFT));
    rig.stop().await;
}

/// `canlift cloud backup` while 50 gateways push telemetry: the backup is a whole database
/// (integrity_check, every lift, the values committed when it began); `restore` refuses while
/// the portal runs, puts the backup back once it is stopped, and the gateways come back online
/// with the tokens they hold.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backup_under_load_is_whole_and_restores() {
    const GATEWAYS: usize = 50;
    let dir = testkit::scratch();
    let (mut portal, key) = PortalProcess::start(dir.path(), "").await;
    let mut fleet = loadgen(&portal, GATEWAYS, &dir.path().join("gateways"));
    portal
        .wait_online(&key, GATEWAYS, Duration::from_secs(60))
        .await;
    until_async(Duration::from_secs(30), "telemetry stored", || async {
        portal.stored().await > 1_000
    })
    .await;

    let config = portal.config.to_str().expect("UTF-8").to_owned();
    let file = dir.path().join("backup.db");
    let file_arg = file.to_str().expect("UTF-8");
    let before = portal.stored().await;
    let out = common::run(&["cloud", "backup", file_arg, "--config", &config]).await;
    assert!(out.status.success(), "{}", common::stderr(&out));
    let after = portal.stored().await;
    let said = String::from_utf8_lossy(&out.stdout).into_owned();
    eprintln!("{said}");
    let (lifts, values) = backup_contents(&said);
    assert_eq!(lifts, GATEWAYS as u64, "{said}");
    assert!(
        (before..=after).contains(&values),
        "{values} values backed up, {before} stored before and {after} after: {said}"
    );
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(&file)
        .expect("the backup")
        .permissions()
        .mode();
    assert_eq!(mode & 0o777, 0o600, "the backup is for its owner alone");
    let again = common::run(&["cloud", "backup", file_arg, "--config", &config]).await;
    assert!(!again.status.success(), "a backup never overwrites a file");

    let running = common::run(&["cloud", "restore", file_arg, "--config", &config]).await;
    assert!(
        !running.status.success(),
        "restore refused while the portal runs"
    );
    assert!(
        common::stderr(&running).contains("stop it before restoring"),
        "{}",
        common::stderr(&running)
    );

    interrupt_portal(&mut portal).await;
    let out = common::run(&["cloud", "restore", file_arg, "--config", &config]).await;
    assert!(out.status.success(), "{}", common::stderr(&out));
    let (rows, check) = portal.inspect().await;
    assert_eq!(check, "ok");
    assert_eq!(
        rows, values,
        "the restored database holds the backup's values"
    );

    portal.restart().await;
    let took = portal
        .wait_online(&key, GATEWAYS, Duration::from_secs(90))
        .await;
    eprintln!("all {GATEWAYS} back online {took:?} after the restore");
    kill(&mut fleet).await;
    portal.kill().await;
}

/// Lifts and values from `backup`'s line "FILE: N lifts, M values, taken in S s".
fn backup_contents(said: &str) -> (u64, u64) {
    let number_before = |word: &str| -> u64 {
        let at = said
            .find(word)
            .unwrap_or_else(|| panic!("{word} in {said}"));
        said[..at]
            .split_whitespace()
            .last()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("a number before {word} in {said}"))
    };
    (number_before(" lifts"), number_before(" values"))
}

/// Stop the portal as its service manager would (SIGINT, a clean shutdown).
async fn interrupt_portal(portal: &mut PortalProcess) {
    if let Some(mut child) = portal.child.take() {
        let status = common::interrupt(&mut child, Duration::from_secs(30)).await;
        assert!(status.success(), "the portal stops cleanly: {status}");
    }
}
