//! The daemons under a service manager (docs/OPERATIONS.md §systemd), as systemd would run
//! them: readiness, reloads and stops told on `NOTIFY_SOCKET`; SIGHUP reading the portal's
//! certificate again without dropping a connection and the gateway's CA for its next one; the
//! package's example configurations read as they are installed.

use std::path::{Path, PathBuf};
use std::time::Duration;

use rustls::pki_types::CertificateDer;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, UnixDatagram};
use tokio_rustls::client::TlsStream;

use super::common::http::{answer_of, tls_to};
use super::common::{canlift, send_signal, PortalProcess};

/// What a service manager hears on its `NOTIFY_SOCKET` (sd_notify(3): one datagram of
/// `KEY=VALUE` lines per call).
struct Notifications {
    socket: UnixDatagram,
    path: PathBuf,
}

impl Notifications {
    fn bind(dir: &Path) -> Notifications {
        let path = dir.join("notify");
        Notifications {
            socket: UnixDatagram::bind(&path).expect("a datagram socket"),
            path,
        }
    }

    /// The next datagram, within 30 s.
    async fn next(&self) -> String {
        let mut buf = vec![0; 4096];
        let n = tokio::time::timeout(Duration::from_secs(30), self.socket.recv(&mut buf))
            .await
            .expect("a notification within 30 s")
            .expect("received");
        String::from_utf8(buf[..n].to_vec()).expect("UTF-8")
    }

    /// Whether a datagram arrives within `wait`.
    async fn quiet_for(&self, wait: Duration) -> bool {
        let mut buf = vec![0; 4096];
        tokio::time::timeout(wait, self.socket.recv(&mut buf))
            .await
            .is_err()
    }
}

fn lines(message: &str) -> Vec<&str> {
    message.lines().collect()
}

fn presented(stream: &TlsStream<TcpStream>) -> CertificateDer<'static> {
    stream
        .get_ref()
        .1
        .peer_certificates()
        .expect("a certificate")[0]
        .clone()
}

fn leaf(file: &Path) -> CertificateDer<'static> {
    tls::certificates(file).expect("a certificate")[0].clone()
}

/// `GET /healthz` on a kept-alive connection: the status line.
async fn healthz(stream: &mut TlsStream<TcpStream>) -> String {
    stream
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\n\r\n")
        .await
        .expect("sent");
    let answer = answer_of(stream).await;
    assert!(!answer.is_empty(), "the portal closed the connection");
    answer.lines().next().unwrap_or_default().to_owned()
}

/// A test PKI of its own in `dir`.
fn pki_in(dir: &Path) -> testkit::pki::TestPki {
    std::fs::create_dir_all(dir).expect("a directory");
    testkit::pki::pki(dir)
}

fn copy_pair(cert: &Path, key: &Path, to: &Path) {
    std::fs::copy(cert, to.join("portal.crt")).expect("certificate copied");
    std::fs::copy(key, to.join("portal.key")).expect("key copied");
}

/// The portal says READY=1 once it accepts, with its address in STATUS; SIGHUP makes it read
/// a renewed certificate (RELOADING=1, READY=1) that new handshakes get while a connection made
/// before goes on; a key that is not the certificate's, or a half-written one, is refused and
/// the certificate in use stays; SIGTERM says STOPPING=1.
#[tokio::test]
async fn the_portal_tells_its_state_and_takes_a_renewed_certificate_on_sighup() {
    let dir = testkit::scratch();
    let (first, renewed) = (
        pki_in(&dir.path().join("first")),
        pki_in(&dir.path().join("renewed")),
    );
    let files = dir.path().join("tls");
    std::fs::create_dir_all(&files).expect("a directory");
    copy_pair(&first.cert, &first.key, &files);
    let roots = dir.path().join("both-cas.pem");
    let mut both = std::fs::read(&first.ca).expect("CA");
    both.extend(std::fs::read(&renewed.ca).expect("CA"));
    std::fs::write(&roots, both).expect("written");
    let portal = PortalProcess::configure(
        dir.path(),
        &format!(
            "tls_cert = \"{}\"\ntls_key = \"{}\"\n",
            files.join("portal.crt").display(),
            files.join("portal.key").display()
        ),
    );
    let notifications = Notifications::bind(dir.path());
    let mut child = canlift()
        .args(["cloud", "--config", portal.config.to_str().expect("UTF-8")])
        .env("NOTIFY_SOCKET", &notifications.path)
        .env("RUST_LOG", "info")
        .spawn()
        .expect("canlift starts");
    let mut log = tokio::io::BufReader::new(child.stderr.take().expect("stderr")).lines();

    let ready = notifications.next().await;
    assert_eq!(
        lines(&ready),
        [
            "READY=1",
            &format!("STATUS=serving on 127.0.0.1:{}", portal.port)
        ],
        "{ready}"
    );
    // Ready means serving: the first connection after it is answered, no retry.
    let mut before = tls_to(portal.port, &roots).await;
    assert_eq!(presented(&before), leaf(&first.cert));
    assert_eq!(healthz(&mut before).await, "HTTP/1.1 200 OK");

    copy_pair(&renewed.cert, &renewed.key, &files);
    send_signal(&child, "HUP");
    assert_eq!(lines(&notifications.next().await), ["RELOADING=1"]);
    assert_eq!(lines(&notifications.next().await), ["READY=1"]);
    let mut after = tls_to(portal.port, &roots).await;
    assert_eq!(presented(&after), leaf(&renewed.cert), "the renewed one");
    assert_eq!(healthz(&mut after).await, "HTTP/1.1 200 OK");
    assert_eq!(
        healthz(&mut before).await,
        "HTTP/1.1 200 OK",
        "the connection made before the reload goes on"
    );
    assert_eq!(presented(&before), leaf(&first.cert));

    // An administrator's mistakes: the new certificate with the old key, then a key cut short.
    std::fs::copy(&first.key, files.join("portal.key")).expect("copied");
    let half = std::fs::read(&renewed.key).expect("key");
    for (key, what) in [
        (None, "a key that is not the certificate's"),
        (Some(half), "half a key"),
    ] {
        if let Some(key) = key {
            std::fs::write(files.join("portal.key"), &key[..key.len() / 2]).expect("written");
        }
        send_signal(&child, "HUP");
        assert_eq!(lines(&notifications.next().await), ["RELOADING=1"]);
        assert_eq!(lines(&notifications.next().await), ["READY=1"]);
        let refusal = tokio::time::timeout(Duration::from_secs(10), async {
            loop {
                let line = log.next_line().await.expect("stderr").expect("a line");
                if line.contains("not reloaded") {
                    return line;
                }
            }
        })
        .await
        .unwrap_or_else(|_| panic!("{what}: the refusal is logged"));
        assert!(refusal.contains("ERROR"), "{what}: {refusal}");
        let mut still = tls_to(portal.port, &roots).await;
        assert_eq!(presented(&still), leaf(&renewed.cert), "{what}: kept");
        assert_eq!(healthz(&mut still).await, "HTTP/1.1 200 OK");
    }

    send_signal(&child, "TERM");
    assert_eq!(lines(&notifications.next().await), ["STOPPING=1"]);
    let status = tokio::time::timeout(Duration::from_secs(30), child.wait())
        .await
        .expect("it stops")
        .expect("a status");
    assert!(status.success(), "{status}");
}

/// The gateway says READY=1 once it is on the bus, though the portal is out of reach (its CA
/// file names the wrong CA); SIGHUP after the right CA is written makes its next connection
/// reach the portal, without a restart.
#[tokio::test]
async fn the_gateway_is_ready_on_the_bus_and_takes_a_new_ca_on_sighup() {
    use testkit::scripted;
    let dir = testkit::scratch();
    let pki = pki_in(&dir.path().join("portal"));
    let other = pki_in(&dir.path().join("other"));
    let portal = scripted::Portal::start(&pki).await;
    let hub = testkit::hub().await;
    let mut config = scripted::config(
        &portal.url(),
        &pki,
        &testkit::hub_url(&hub, "can0"),
        dir.path(),
    );
    let ca = dir.path().join("portal-ca.pem");
    std::fs::copy(&other.ca, &ca).expect("copied");
    config.cloud.ca_file = Some(ca.clone());
    let path = dir.path().join("gateway.toml");
    std::fs::write(&path, toml::to_string(&config).expect("TOML")).expect("written");

    let notifications = Notifications::bind(dir.path());
    let child = canlift()
        .args(["gateway", "--config", path.to_str().expect("UTF-8")])
        .env("NOTIFY_SOCKET", &notifications.path)
        .env("RUST_LOG", "warn")
        .spawn()
        .expect("canlift starts");
    let ready = notifications.next().await;
    assert_eq!(lines(&ready)[0], "READY=1", "{ready}");
    assert!(
        !portal.try_tls().await,
        "a gateway trusting another CA does not get through"
    );

    std::fs::copy(&pki.ca, &ca).expect("copied");
    send_signal(&child, "HUP");
    assert_eq!(lines(&notifications.next().await), ["RELOADING=1"]);
    assert_eq!(lines(&notifications.next().await), ["READY=1"]);
    // Its next attempt (backoff after a failure or two: a few seconds) gets through.
    let (mut ws, ..) = portal.accept_trusted(Duration::from_secs(30)).await;
    let connect = scripted::connack(&mut ws).await;
    assert!(
        connect.to_string().contains(testkit::constants::SERNUM),
        "{connect}"
    );
    assert!(notifications.quiet_for(Duration::from_millis(200)).await);
}

/// The configurations the package installs in /etc/canlift are read as they are (a typo in
/// a key would stop the service at its first start).
#[tokio::test]
async fn the_packaged_configurations_are_read() {
    let contrib = testkit::workspace().join("contrib/etc");
    for (command, file) in [("cloud", "portal.toml"), ("gateway", "gateway.toml")] {
        let path = contrib.join(file);
        let out = canlift()
            .args([command, "--print-config", "--config"])
            .arg(&path)
            .output()
            .await
            .expect("canlift runs");
        assert!(
            out.status.success(),
            "{file}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let printed: toml::Table =
            toml::from_str(&String::from_utf8_lossy(&out.stdout)).expect("TOML");
        let dir = printed["state"]["dir"].as_str().expect("a state directory");
        assert!(dir.starts_with("/var/lib/canlift-"), "{file}: {dir}");
    }
}
