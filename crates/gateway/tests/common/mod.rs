//! A portal for tests: a private CA made with rcgen, a TLS WebSocket server on loopback that
//! selects a subprotocol, and a gateway configuration pointing at it.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use gateway::config::Config;
use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair, KeyUsagePurpose};
use serde_json::Value;
use tokio::net::{TcpListener, TcpStream};
use tokio_rustls::server::TlsStream;
use tokio_tungstenite::tungstenite::handshake::server::{Request, Response};
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::WebSocketStream;

pub const SERNUM: &str = "180917010200000102";
/// SHA-1 of "service" and "setup".
pub const SERVICE_SHA1: &str = "4cf5bc59bee9e1c44c6254b5f84e7f066bd8e5fe";
pub const SETUP_SHA1: &str = "80437a44a661d141174209119d54125a59a64b2a";
pub const WAIT: Duration = Duration::from_secs(10);

/// A scratch directory removed on drop.
pub struct Scratch(pub PathBuf);

impl Scratch {
    pub fn new(name: &str) -> Scratch {
        let dir = std::env::temp_dir().join(format!("canlift-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Scratch(dir)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A CA and a server certificate for localhost and 127.0.0.1, as PEM files in `dir`.
pub struct TestPki {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
    /// A client certificate signed by the same CA, for mutual TLS.
    pub client_cert: PathBuf,
    pub client_key: PathBuf,
}

pub fn pki(dir: &Path) -> TestPki {
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let ca_key = KeyPair::generate().unwrap();
    let ca_cert = ca_params.self_signed(&ca_key).unwrap();
    let issuer = Issuer::new(ca_params, ca_key);
    let params =
        CertificateParams::new(vec!["localhost".to_owned(), "127.0.0.1".to_owned()]).unwrap();
    let key = KeyPair::generate().unwrap();
    let cert = params.signed_by(&key, &issuer).unwrap();
    let client_params =
        CertificateParams::new(vec!["gateway-180917010200000102".to_owned()]).unwrap();
    let client_key = KeyPair::generate().unwrap();
    let client = client_params.signed_by(&client_key, &issuer).unwrap();
    let pki = TestPki {
        ca: dir.join("ca.pem"),
        cert: dir.join("server.pem"),
        key: dir.join("server.key"),
        client_cert: dir.join("client.pem"),
        client_key: dir.join("client.key"),
    };
    std::fs::write(&pki.client_cert, client.pem()).unwrap();
    std::fs::write(&pki.client_key, client_key.serialize_pem()).unwrap();
    std::fs::write(&pki.ca, ca_cert.pem()).unwrap();
    std::fs::write(&pki.cert, cert.pem()).unwrap();
    std::fs::write(&pki.key, key.serialize_pem()).unwrap();
    pki
}

pub type Ws = WebSocketStream<TlsStream<TcpStream>>;

/// A TLS WebSocket server that answers with `protocol` (or none).
pub struct Portal {
    listener: TcpListener,
    acceptor: tokio_rustls::TlsAcceptor,
    pub protocol: Option<&'static str>,
}

impl Portal {
    pub async fn start(pki: &TestPki) -> Portal {
        Portal::start_with(pki, false).await
    }

    /// A portal that requires a client certificate signed by the test CA.
    pub async fn start_with(pki: &TestPki, client_auth: bool) -> Portal {
        let ca = client_auth.then_some(pki.ca.as_path());
        let config = tls::server_config(&pki.cert, &pki.key, ca).unwrap();
        Portal {
            listener: TcpListener::bind("127.0.0.1:0").await.unwrap(),
            acceptor: tokio_rustls::TlsAcceptor::from(Arc::new(config)),
            protocol: Some("cloud"),
        }
    }

    pub fn url(&self) -> String {
        format!(
            "wss://localhost:{}/ws",
            self.listener.local_addr().unwrap().port()
        )
    }

    /// Accept TCP and try TLS: whether the handshake succeeded.
    pub async fn try_tls(&self) -> bool {
        let (tcp, _) = tokio::time::timeout(WAIT, self.listener.accept())
            .await
            .expect("a gateway connects")
            .unwrap();
        self.acceptor.accept(tcp).await.is_ok()
    }

    /// Accept the next gateway; returns the socket and the request's headers of interest.
    #[allow(clippy::result_large_err)] // the callback's error type is tungstenite's
    pub async fn accept(&self) -> (Ws, Option<String>, Option<String>) {
        let (tcp, _) = tokio::time::timeout(WAIT, self.listener.accept())
            .await
            .expect("a gateway connects")
            .unwrap();
        let tls = self.acceptor.accept(tcp).await.unwrap();
        let protocol = self.protocol;
        let seen = Arc::new(std::sync::Mutex::new((None, None)));
        let seen2 = seen.clone();
        let ws =
            tokio_tungstenite::accept_hdr_async(tls, move |req: &Request, mut resp: Response| {
                let header = |name: &str| {
                    req.headers()
                        .get(name)
                        .and_then(|v| v.to_str().ok())
                        .map(str::to_owned)
                };
                *seen2.lock().unwrap() = (header("Sec-WebSocket-Protocol"), header("Origin"));
                if let Some(p) = protocol {
                    resp.headers_mut()
                        .insert("Sec-WebSocket-Protocol", HeaderValue::from_static(p));
                }
                Ok(resp)
            })
            .await
            .unwrap();
        let (protocols, origin) = seen.lock().unwrap().clone();
        (ws, protocols, origin)
    }
}

/// The next text message as JSON.
pub async fn recv(ws: &mut Ws) -> Value {
    loop {
        let message = tokio::time::timeout(WAIT, ws.next())
            .await
            .expect("a message in time");
        match message {
            Some(Ok(Message::Text(t))) => return serde_json::from_str(t.as_str()).unwrap(),
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
            other => panic!("expected text, got {other:?}"),
        }
    }
}

pub async fn send(ws: &mut Ws, text: &str) {
    ws.send(Message::Text(text.into())).await.unwrap();
}

/// Send a request and return the answer with the same id, collecting notifications on the way.
pub async fn ask(ws: &mut Ws, text: &str, notes: &mut Vec<Value>) -> Value {
    send(ws, text).await;
    let id: Value = serde_json::from_str::<Value>(text)
        .map(|v| v["id"].clone())
        .unwrap_or(Value::Null);
    loop {
        let v = recv(ws).await;
        if v.get("method").is_some() {
            notes.push(v);
        } else if v["id"] == id {
            return v;
        }
    }
}

/// Receive CONNECT and answer it like the specification's sample.
pub async fn connack(ws: &mut Ws) -> Value {
    let connect = recv(ws).await;
    assert_eq!(connect["method"], "CONNECT");
    let answer = format!(
        r#"{{"jsonrpc":"2.0","id":{},"result":"CONNACK","api":1}}"#,
        connect["id"]
    );
    send(ws, &answer).await;
    connect
}

/// A gateway configuration for `portal`, the bus at `bus`, state in `dir`.
pub fn config(portal_url: &str, pki: &TestPki, bus: &str, dir: &Path) -> Config {
    let mut c = Config::default();
    c.identity.sernum = SERNUM.into();
    c.identity.vendorid = 1050;
    c.identity.productcode = 4096;
    c.identity.liftnum = "40/7289/20399-126".into();
    c.identity.hardware = "Thor @ NX-T2".into();
    c.identity.software = "01.23.10".into();
    c.identity.boardhash =
        "2354A687AF6DC79B203E754E8E426A87FE188A62983B7AC48F9D5E195B728112".into();
    c.identity.domaintoken = "MAS".into();
    c.cloud.url = portal_url.into();
    c.cloud.ca_file = Some(pki.ca.clone());
    c.cloud.origin = Some("https://192.168.178.101".into());
    c.state.dir = dir.join("state");
    c.bus.url = bus.into();
    c.bus.sdo_timeout_ms = 300;
    c.bus.poll_ms = 100;
    c.privileges.service_sha1 = Some(SERVICE_SHA1.into());
    c.privileges.setup_sha1 = Some(SETUP_SHA1.into());
    c
}

/// A gateway running in a task.
pub struct Running {
    stop: tokio::sync::watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
}

/// Run `gateway` until [`Running::finish`].
pub fn spawn(gateway: gateway::Gateway) -> Running {
    let (stop, stopped) = tokio::sync::watch::channel(false);
    Running {
        stop,
        task: tokio::spawn(gateway.run(stopped)),
    }
}

impl Running {
    /// Stop the gateway and wait until it has.
    pub async fn finish(self) {
        self.stop.send(true).unwrap();
        tokio::time::timeout(WAIT, self.task)
            .await
            .expect("gateway stops")
            .unwrap();
    }
}
