//! A scripted portal: a TLS WebSocket server on loopback with the test PKI's certificate that
//! selects a subprotocol, and helpers to speak JSON-RPC to the gateway that connects to it by
//! hand — for tests that need exact messages and exact error codes (NXg SW003 §5–§7).

use std::path::Path;
use std::sync::Arc;

use futures_util::{SinkExt, StreamExt};
use gateway::config::Config;
use serde_json::Value;
use tokio::net::{TcpListener, TcpStream};
use tokio_rustls::server::TlsStream;
use tokio_tungstenite::tungstenite::handshake::server::{Request, Response};
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::WebSocketStream;

use crate::constants::WAIT;
use crate::pki::TestPki;

/// The gateway's WebSocket as the portal sees it.
pub type Ws = WebSocketStream<TlsStream<TcpStream>>;

/// A TLS WebSocket server that answers with `protocol` (or none).
pub struct Portal {
    listener: TcpListener,
    acceptor: tokio_rustls::TlsAcceptor,
    /// The subprotocol the upgrade answer selects (`None`: none).
    pub protocol: Option<&'static str>,
}

impl Portal {
    /// A portal with the PKI's server certificate, selecting the `cloud` subprotocol.
    pub async fn start(pki: &TestPki) -> Portal {
        Portal::start_with(pki, false).await
    }

    /// A portal that requires a client certificate signed by the test CA.
    pub async fn start_with(pki: &TestPki, client_auth: bool) -> Portal {
        let ca = client_auth.then_some(pki.ca.as_path());
        let config = tls::server_config(&pki.cert, &pki.key, ca).expect("the test certificate");
        Portal {
            listener: TcpListener::bind("127.0.0.1:0")
                .await
                .expect("a loopback port"),
            acceptor: tokio_rustls::TlsAcceptor::from(Arc::new(config)),
            protocol: Some("cloud"),
        }
    }

    /// `wss://localhost:PORT/ws`.
    pub fn url(&self) -> String {
        format!(
            "wss://localhost:{}/ws",
            self.listener.local_addr().expect("bound").port()
        )
    }

    /// Accept TCP and try TLS: whether the handshake succeeded.
    pub async fn try_tls(&self) -> bool {
        let (tcp, _) = tokio::time::timeout(WAIT, self.listener.accept())
            .await
            .expect("a gateway connects")
            .expect("accept");
        self.acceptor.accept(tcp).await.is_ok()
    }

    /// Accept the next gateway; returns the socket and the request's headers of interest.
    #[allow(clippy::result_large_err)] // the callback's error type is tungstenite's
    pub async fn accept(&self) -> (Ws, Option<String>, Option<String>) {
        let (tcp, _) = tokio::time::timeout(WAIT, self.listener.accept())
            .await
            .expect("a gateway connects")
            .expect("accept");
        let tls = self.acceptor.accept(tcp).await.expect("the TLS handshake");
        self.upgrade(tls).await
    }

    /// Accept the next gateway whose TLS handshake succeeds, within `wait`; the ones that
    /// fail before it (a gateway that does not trust the portal yet) are passed over.
    pub async fn accept_trusted(
        &self,
        wait: std::time::Duration,
    ) -> (Ws, Option<String>, Option<String>) {
        let tls = tokio::time::timeout(wait, async {
            loop {
                let (tcp, _) = self.listener.accept().await.expect("accept");
                if let Ok(tls) = self.acceptor.accept(tcp).await {
                    return tls;
                }
            }
        })
        .await
        .expect("a gateway gets through TLS in time");
        self.upgrade(tls).await
    }

    #[allow(clippy::result_large_err)] // the callback's error type is tungstenite's
    async fn upgrade(&self, tls: TlsStream<TcpStream>) -> (Ws, Option<String>, Option<String>) {
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
                *seen2.lock().expect("not poisoned") =
                    (header("Sec-WebSocket-Protocol"), header("Origin"));
                if let Some(p) = protocol {
                    resp.headers_mut()
                        .insert("Sec-WebSocket-Protocol", HeaderValue::from_static(p));
                }
                Ok(resp)
            })
            .await
            .expect("the WebSocket upgrade");
        let (protocols, origin) = seen.lock().expect("not poisoned").clone();
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
            Some(Ok(Message::Text(t))) => return serde_json::from_str(t.as_str()).expect("JSON"),
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
            other => panic!("expected text, got {other:?}"),
        }
    }
}

/// Send `text`.
pub async fn send(ws: &mut Ws, text: &str) {
    ws.send(Message::Text(text.into())).await.expect("sent");
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

/// Receive CONNECT and answer it like the specification's sample (api 1).
pub async fn connack(ws: &mut Ws) -> Value {
    connack_api(ws, 1).await
}

/// Receive CONNECT and answer it with CONNACK offering `api`.
pub async fn connack_api(ws: &mut Ws, api: u32) -> Value {
    let connect = recv(ws).await;
    assert_eq!(connect["method"], "CONNECT");
    let answer = format!(
        r#"{{"jsonrpc":"2.0","id":{},"result":"CONNACK","api":{api}}}"#,
        connect["id"]
    );
    send(ws, &answer).await;
    connect
}

/// The next text message within `wait`, if one comes.
pub async fn recv_within(ws: &mut Ws, wait: std::time::Duration) -> Option<Value> {
    tokio::time::timeout(wait, recv(ws)).await.ok()
}

/// A gateway configuration for `portal`, the bus at `bus`, state in `dir`: the sample
/// identity and passwords, and the sample's `Origin` header.
pub fn config(portal_url: &str, pki: &TestPki, bus: &str, dir: &Path) -> Config {
    let mut c = crate::lift::gateway_config(portal_url, &pki.ca, bus, &dir.join("state"));
    c.cloud.origin = Some("https://192.168.178.101".into());
    c
}
