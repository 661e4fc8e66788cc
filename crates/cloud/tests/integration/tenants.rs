//! Tenants cannot touch each other and no outsider can lock anyone out (docs/SECURITY.md
//! §Tenants): a gateway squatting another account's lift identity, wrong keys and sign-in
//! floods from other addresses, forged origins and forwarded addresses, look-alike serial
//! numbers, viewers' streams, user names of other accounts.

use std::net::{IpAddr, Ipv4Addr};
use std::time::{Duration, Instant};

use cloud::client::{Body, Client};
use cloud_types::users::Role;
use serde_json::{json, Value};
use testkit::constants::{ACCOUNT, LIFT, SERNUM, WAIT};
use testkit::portal::{until, Rig};
use tokio::io::AsyncReadExt;

/// The passenger call, privilege 0.
const CALL: &str = "0x502200";

/// A client of the rig from loopback address 127.0.0.`n`.
fn from(rig: &Rig, key: Option<&str>, n: u8) -> Client {
    Client::new(&rig.url(), key, Some(&rig.ca))
        .expect("a client")
        .with_source(IpAddr::V4(Ipv4Addr::new(127, 0, 0, n)))
}

/// The web UI's sign-in form posted by `client`: the status.
async fn login(client: Client, form: &[(&str, &str)]) -> u16 {
    client
        .exchange("POST", "/login", Body::Form(form))
        .await
        .expect("an answer")
        .status
}

/// The lifts an account's key sees: (id, online).
async fn lifts(rig: &Rig, key: &str) -> Vec<(String, bool)> {
    let (status, body) = rig.call("GET", "/api/v1/lifts", Some(key), None).await;
    assert_eq!(status, 200, "{body}");
    body.as_array()
        .into_iter()
        .flatten()
        .map(|l| {
            let id = l["id"].as_str().unwrap_or_default().to_owned();
            (id, l["online"] == true)
        })
        .collect()
}

/// A gateway of another account that sends the identity of this account's lift is a lift of
/// its own account: the real lift stays online, keeps answering and is admitted again after
/// a reconnect; each account sees its own lift under the same id, and neither reaches the
/// other's gateway, data or token.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_squatting_gateway_leaves_the_real_lift_online_and_admitted() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let squatter = rig.hand_made_gateway(SERNUM, "OTH").await;
    assert_eq!(lifts(&rig, &rig.key).await, vec![(LIFT.to_owned(), true)]);
    assert_eq!(
        lifts(&rig, &rig.other_key).await,
        vec![(LIFT.to_owned(), true)]
    );
    // The real lift answers its account; the squatter (which answers nothing) its own.
    let read = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
    let (status, body) = rig.call("GET", &read, Some(&rig.key), None).await;
    assert_eq!(status, 200, "{body}");
    let (status, _) = rig.call("GET", &read, Some(&rig.other_key), None).await;
    assert_eq!(
        status, 504,
        "the squatter's own lift, which does not answer"
    );
    // The squatter's account resets its own lift's token: the real one is untouched.
    let token = format!("/api/v1/lifts/{LIFT}/token");
    assert_eq!(
        rig.call("DELETE", &token, Some(&rig.other_key), None)
            .await
            .0,
        204
    );
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    let (status, body) = rig.call("GET", &read, Some(&rig.key), None).await;
    assert_eq!(
        status, 200,
        "the real lift admitted again with its token: {body}"
    );
    // Each account's audit log holds its own account's entries alone.
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    assert!(
        !audit.to_string().contains("token reset"),
        "the other account's reset is not ours: {audit}"
    );
    // The squatter's account retires its lift: the real one stays.
    drop(squatter);
    let lift = format!("/api/v1/lifts/{LIFT}");
    assert_eq!(
        rig.call("DELETE", &lift, Some(&rig.other_key), None)
            .await
            .0,
        204
    );
    assert!(lifts(&rig, &rig.other_key).await.is_empty());
    assert_eq!(lifts(&rig, &rig.key).await, vec![(LIFT.to_owned(), true)]);
    let (_, audit) = rig
        .call("GET", "/api/v1/audit", Some(&rig.other_key), None)
        .await;
    assert!(audit.to_string().contains("lift retired"), "{audit}");
    rig.stop().await;
}

/// The same, the other way round: the squatter came first, and the real gateway of the
/// account is admitted all the same.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lift_squatted_before_it_first_connected_is_admitted() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    rig.stop_gateway().await;
    let store = rig.store().await;
    let masora = store.account(ACCOUNT).await.unwrap().unwrap();
    assert!(store.retire(&masora, LIFT, "test").await.unwrap());
    let _squatter = rig.hand_made_gateway(SERNUM, "OTH").await;
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    assert_eq!(lifts(&rig, &rig.key).await, vec![(LIFT.to_owned(), true)]);
    let read = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
    assert_eq!(rig.call("GET", &read, Some(&rig.key), None).await.0, 200);
    rig.stop().await;
}

/// Ten wrong API keys from one address leave the right key from another address signing in;
/// the address that guessed waits, its neighbour does not.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_keys_from_one_address_lock_out_no_one_else() {
    let rig = Rig::builder().without_lift().start().await;
    let sign_in = |n: u8, key: String| {
        let rig = &rig;
        async move { login(from(rig, None, n), &[("key", key.as_str())]).await }
    };
    let mut statuses = Vec::new();
    for i in 0..30 {
        statuses.push(sign_in(20, format!("clk_wrong{i}")).await);
    }
    assert!(
        statuses.contains(&429),
        "the guessing address waits: {statuses:?}"
    );
    assert_eq!(
        sign_in(21, rig.key.clone()).await,
        303,
        "another address signs in"
    );
    assert_eq!(
        sign_in(20, rig.key.clone()).await,
        429,
        "the guessing address still waits"
    );
    rig.stop().await;
}

/// 64 sign-ins at a time, with made-up names from made-up addresses: the password checks queue
/// on their own threads, those beyond the queue are turned away at once (429), and an
/// operator's reads are answered all the while. The reads' latency, calm and flooded, is printed:
/// a figure to read, not a bound to assert on a shared machine (the checks' bounded queue is
/// `auth::passwords`'s unit test).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sign_in_flood_leaves_operator_reads_fast() {
    // The reads as fast as they are answered (no rate per key).
    let rig = Rig::builder()
        .portal(|c| c.server.requests_per_key_s = 0)
        .start()
        .await;
    rig.online().await;
    let reader = Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca)).expect("a client");
    let mut connection = reader.connect().await.expect("a connection");
    let calm = latencies(&mut connection, 100).await;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let attempts = std::sync::Arc::new(Attempts::default());
    // The attacker's side runs on a runtime of its own (as it would on a machine of its own):
    // the portal's workers carry only what the portal does.
    let flood = {
        let (url, ca) = (rig.url(), rig.ca.clone());
        let (stop, attempts) = (stop.clone(), attempts.clone());
        std::thread::spawn(move || {
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(1)
                .enable_all()
                .build()
                .expect("a runtime");
            runtime.block_on(async move {
                let tasks: Vec<_> = (0..64u32)
                    .map(|n| {
                        let (url, ca) = (url.clone(), ca.clone());
                        let (stop, attempts) = (stop.clone(), attempts.clone());
                        tokio::spawn(sign_in_flood(n, url, ca, stop, attempts))
                    })
                    .collect();
                for task in tasks {
                    let _ = task.await;
                }
            });
        })
    };
    tokio::time::sleep(Duration::from_millis(500)).await;
    let before = attempts.answered();
    let flooded = latencies(&mut connection, 300).await;
    let during = attempts.answered() - before;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let _ = tokio::task::spawn_blocking(move || flood.join()).await;
    let p99 = |l: &[Duration]| l[l.len() * 99 / 100 - 1];
    let (calm99, flooded99) = (p99(&calm), p99(&flooded));
    let busy = attempts.busy.load(std::sync::atomic::Ordering::Relaxed);
    eprintln!(
        "operator reads p99: {calm99:?} calm, {flooded99:?} during {during} sign-in attempts \
         (64 at a time; {busy} in all turned away as busy)"
    );
    assert!(during > 0, "the reads were answered while the flood ran");
    assert!(
        busy > 0,
        "sign-ins beyond the checks' queue are turned away, not queued"
    );
    rig.stop().await;
}

/// Sign-in attempt after attempt with made-up names, each from another made-up address of
/// 127.0.0.0/8, until `stop`.
async fn sign_in_flood(
    n: u32,
    url: String,
    ca: std::path::PathBuf,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    attempts: std::sync::Arc<Attempts>,
) {
    let mut i = 0u32;
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        let source = Ipv4Addr::new(
            127,
            1 + (n % 200) as u8,
            (i % 250) as u8,
            1 + (n % 250) as u8,
        );
        let client = Client::new(&url, None, Some(&ca))
            .expect("a client")
            .with_source(IpAddr::V4(source));
        let user = format!("nobody{n}x{i}");
        let form = [
            ("account", "masora"),
            ("user", user.as_str()),
            ("secret", "cls_guess"),
        ];
        let reply = client.exchange("POST", "/login", Body::Form(&form)).await;
        let counter = match reply {
            Ok(reply) if reply.status == 429 => &attempts.busy,
            _ => &attempts.other,
        };
        counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        i += 1;
    }
}

/// The flood's sign-in attempts by answer: busy (429) and any other.
#[derive(Default)]
struct Attempts {
    busy: std::sync::atomic::AtomicU64,
    other: std::sync::atomic::AtomicU64,
}

impl Attempts {
    fn answered(&self) -> u64 {
        self.busy.load(std::sync::atomic::Ordering::Relaxed)
            + self.other.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// `n` reads of the lift's car position, their latencies sorted.
async fn latencies(connection: &mut cloud::client::Connection, n: usize) -> Vec<Duration> {
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
    let mut times = Vec::with_capacity(n);
    for _ in 0..n {
        let begin = Instant::now();
        let (status, body) = connection
            .call("GET", &path, None)
            .await
            .expect("an answer");
        assert_eq!(status, 200, "{body}");
        times.push(begin.elapsed());
    }
    times.sort();
    times
}

/// Another site's form cannot sign a browser in (login CSRF): a foreign `Origin`, or without
/// one a foreign `Referer`, is 403; the portal's own origin signs in.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sign_in_from_another_origin_is_refused() {
    let rig = Rig::builder().without_lift().start().await;
    let ours = format!(
        "https://localhost:{}",
        rig.url().rsplit(':').next().unwrap_or_default()
    );
    let form = [("key", rig.key.as_str())];
    let post = |name: &'static str, value: String| {
        let client = Client::new(&rig.url(), None, Some(&rig.ca))
            .expect("a client")
            .with_header(name, &value);
        login(client, &form)
    };
    assert_eq!(post("origin", "https://evil.example".into()).await, 403);
    assert_eq!(post("referer", "https://evil.example/x".into()).await, 403);
    assert_eq!(post("referer", format!("{ours}.evil.example/")).await, 403);
    assert_eq!(post("origin", ours.clone()).await, 303);
    assert_eq!(post("referer", format!("{ours}/login")).await, 303);
    rig.stop().await;
}

/// A serial number with a zero-width space looks like the real one and is another: refused,
/// as are format, private-use and decomposed texts, and counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn look_alike_identities_are_refused() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    for sernum in [
        format!("{SERNUM}\u{200b}"),
        format!("\u{202e}{SERNUM}"),
        format!("{SERNUM}\u{e000}"),
    ] {
        let refused = rig.try_hand_made_gateway(&sernum, "MAS").await;
        assert!(refused.is_err(), "{sernum:?} admitted");
    }
    assert_eq!(lifts(&rig, &rig.key).await.len(), 1);
    let token = Some(testkit::constants::METRICS_TOKEN);
    let (_, metrics) = rig.call("GET", "/metrics", token, None).await;
    let metrics = metrics.as_str().unwrap_or_default().to_owned();
    assert!(
        metrics.contains("canlift_gateways_refused_total{reason=\"identity\"} 3"),
        "{metrics}"
    );
    rig.stop().await;
}

/// A viewer's event stream never makes the gateway hold a subscription: with `mplex` it is
/// 403 (holding is a technician's), without it the stream is the viewer's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewers_stream_holds_no_subscription() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    let store = rig.store().await;
    store.add_user(ACCOUNT, "vic", Role::Viewer).await.unwrap();
    let (_, viewer) = store.add_key(ACCOUNT, "vic", None).await.unwrap();
    let client = Client::new(&rig.url(), Some(&viewer), Some(&rig.ca)).expect("a client");
    let held = format!("/api/v1/lifts/{LIFT}/events?mplex=0x2001");
    match client.events(&held).await.expect("an answer") {
        Err((status, body)) => {
            assert_eq!(status, 403, "{body}");
            assert!(body.to_string().contains("technician"), "{body}");
        }
        Ok(_) => panic!("a viewer's stream with mplex was opened"),
    }
    let watched = format!("/api/v1/lifts/{LIFT}/events");
    assert!(client.events(&watched).await.expect("an answer").is_ok());
    rig.stop().await;
}

/// User names belong to their account: another account's administrator adds a user of a name
/// this account has, and learns nothing; each signs in to their own account.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn user_names_are_the_accounts_own() {
    let rig = Rig::builder().without_lift().start().await;
    let ann = || Some(json!({"name": "ann", "role": "viewer"}));
    let users = "/api/v1/users";
    let (status, ours) = rig.call("POST", users, Some(&rig.key), ann()).await;
    assert_eq!(status, 201, "{ours}");
    let (status, theirs) = rig.call("POST", users, Some(&rig.other_key), ann()).await;
    assert_eq!(status, 201, "another account's ann: {theirs}");
    let (status, again) = rig.call("POST", users, Some(&rig.key), ann()).await;
    assert_eq!(status, 409, "{again}");
    let sign_in = |account: &'static str, secret: String| {
        let client = Client::new(&rig.url(), None, Some(&rig.ca)).expect("a client");
        async move {
            let form = [
                ("account", account),
                ("user", "ann"),
                ("secret", secret.as_str()),
            ];
            client
                .exchange("POST", "/login", Body::Form(&form))
                .await
                .expect("an answer")
                .status
        }
    };
    let secret = |v: &Value| v["secret"].as_str().unwrap_or_default().to_owned();
    assert_eq!(sign_in(ACCOUNT, secret(&ours)).await, 303);
    assert_eq!(sign_in("someone", secret(&theirs)).await, 303);
    assert_eq!(sign_in("someone", secret(&ours)).await, 401);
    rig.stop().await;
}

/// Behind a trusted load balancer the audit log names the client `X-Forwarded-For` gives;
/// from anyone else the header is not believed and the peer is named.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_audit_names_the_forwarded_client_only_behind_a_trusted_proxy() {
    for (trusted, expected) in [(true, "203.0.113.7"), (false, "127.0.0.1")] {
        let rig = Rig::builder()
            .portal(move |c| {
                if trusted {
                    c.server.trusted_proxies = vec!["127.0.0.1/32".into()];
                }
            })
            .start()
            .await;
        rig.online().await;
        let client = Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca))
            .expect("a client")
            .with_header("x-forwarded-for", "198.51.100.1, 203.0.113.7");
        let path = format!("/api/v1/lifts/{LIFT}/objects/{CALL}");
        let body = json!({"value": "3", "datatype": 7, "physunit": 0});
        let (status, answer) = client
            .call("PUT", &path, Some(body))
            .await
            .expect("an answer");
        assert_eq!(status, 200, "{answer}");
        let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
        let put = audit
            .as_array()
            .and_then(|a| a.iter().find(|e| e["action"] == "put"))
            .cloned()
            .unwrap_or_default();
        assert_eq!(put["address"], expected, "trusted {trusted}: {audit}");
        rig.stop().await;
    }
}

/// Behind a trusted load balancer in TCP mode the PROXY protocol v2 header names the client:
/// the audit log has its address; the same header from an untrusted peer is no TLS at all.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trusted_proxy_header_names_the_client() {
    let rig = Rig::builder()
        .portal(|c| c.server.trusted_proxies = vec!["127.0.0.1".into()])
        .start()
        .await;
    rig.online().await;
    let client: std::net::SocketAddr = "203.0.113.9:40000".parse().unwrap();
    let body = json!({"value": "4", "datatype": 7, "physunit": 0});
    let status = put_through_proxy_header(&rig, client, 1, &body).await;
    assert_eq!(status, Some(200));
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    let put = audit
        .as_array()
        .and_then(|a| a.iter().find(|e| e["action"] == "put"))
        .cloned()
        .unwrap_or_default();
    assert_eq!(put["address"], "203.0.113.9", "{audit}");
    // From 127.0.0.2, which is not trusted, the header is not read: the handshake fails.
    assert_eq!(put_through_proxy_header(&rig, client, 2, &body).await, None);
    rig.stop().await;
}

/// A put of the call, from 127.0.0.`n`, on a connection that begins with a PROXY v2 header
/// naming `client`: the status, or `None` when no HTTPS exchange came about.
async fn put_through_proxy_header(
    rig: &Rig,
    client: std::net::SocketAddr,
    n: u8,
    body: &Value,
) -> Option<u16> {
    use http_body_util::{BodyExt, Full};
    use tokio::io::AsyncWriteExt;
    let portal: std::net::SocketAddr = format!("127.0.0.1:{}", rig.url().rsplit(':').next()?)
        .parse()
        .ok()?;
    let socket = tokio::net::TcpSocket::new_v4().ok()?;
    socket.bind(format!("127.0.0.{n}:0").parse().ok()?).ok()?;
    let mut tcp = socket.connect(portal).await.ok()?;
    let header = ppp::v2::Builder::with_addresses(
        ppp::v2::Version::Two | ppp::v2::Command::Proxy,
        ppp::v2::Protocol::Stream,
        (client, portal),
    )
    .build()
    .ok()?;
    tcp.write_all(&header).await.ok()?;
    let config = tls::client_config(Some(&rig.ca), None).ok()?;
    let name = rustls::pki_types::ServerName::try_from("localhost").ok()?;
    let tls = tokio_rustls::TlsConnector::from(config)
        .connect(name, tcp)
        .await
        .ok()?;
    let (mut sender, connection) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(tls))
            .await
            .ok()?;
    tokio::spawn(connection);
    let request = hyper::Request::put(format!("/api/v1/lifts/{LIFT}/objects/{CALL}"))
        .header("host", format!("localhost:{}", portal.port()))
        .header("authorization", format!("Bearer {}", rig.key))
        .header("content-type", "application/json")
        .body(Full::new(hyper::body::Bytes::from(body.to_string())))
        .ok()?;
    let response = sender.send_request(request).await.ok()?;
    let status = response.status().as_u16();
    let _ = response.into_body().collect().await;
    Some(status)
}

/// The documented public `/metrics` needs its token; without a configured token it is not
/// served on the public port at all.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_are_for_their_token_alone() {
    let rig = Rig::builder().without_lift().start().await;
    assert_eq!(rig.call("GET", "/metrics", None, None).await.0, 401);
    assert_eq!(
        rig.call("GET", "/metrics", Some(&rig.key), None).await.0,
        401
    );
    let token = Some(testkit::constants::METRICS_TOKEN);
    assert_eq!(rig.call("GET", "/metrics", token, None).await.0, 200);
    rig.stop().await;
    let listen = std::net::SocketAddr::from(([127, 0, 0, 1], testkit::free_port()));
    let rig = Rig::builder()
        .without_lift()
        .portal(move |c| {
            c.server.metrics_token = None;
            c.server.metrics_listen = Some(listen);
        })
        .start()
        .await;
    assert_eq!(rig.call("GET", "/metrics", None, None).await.0, 404);
    let scraped = until(WAIT, "the metrics listener answers", || async {
        cloud::client::scrape(listen)
            .await
            .is_ok_and(|m| m.sum("canlift_gateways_online").is_some())
    })
    .await;
    eprintln!("metrics listener answered after {scraped:?}");
    // It has the public port's bounds: a connection that says nothing is closed after the
    // head's (docs/SECURITY.md §Bounds), not held for ever.
    let mut silent = tokio::net::TcpStream::connect(listen)
        .await
        .expect("connected");
    let mut byte = [0u8; 1];
    let read = tokio::time::timeout(Duration::from_secs(30), silent.read(&mut byte)).await;
    assert!(
        matches!(read, Ok(Ok(0) | Err(_))),
        "a silent connection to the metrics listener: {read:?}"
    );
    rig.stop().await;
}
