//! HTTP/1.1 over TLS to a portal by hand, for tests that need what a client library hides: a
//! body sent late, a head that never ends, the same connection kept for the next request.

use std::path::Path;
use std::time::Duration;

use tokio::io::AsyncReadExt;
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;
use tokio_rustls::rustls::pki_types::ServerName;

/// A TLS connection to the portal on `port`, trusting `roots`.
pub async fn tls_to(port: u16, roots: &Path) -> TlsStream<TcpStream> {
    let config = tls::client_config(Some(roots), None).expect("a client configuration");
    let tcp = TcpStream::connect(("127.0.0.1", port))
        .await
        .expect("the portal accepts");
    tokio_rustls::TlsConnector::from(config)
        .connect(ServerName::try_from("localhost").expect("a name"), tcp)
        .await
        .expect("a TLS handshake")
}

/// One HTTP/1.1 answer from `stream`, head and body (by its Content-Length; none without),
/// as text; what was read before the connection ended if it ended first (empty: closed).
pub async fn answer_of<S: tokio::io::AsyncRead + Unpin>(stream: &mut S) -> String {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        if let Some(end) = got.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&got[..end]).to_ascii_lowercase();
            let length = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .and_then(|v| v.trim().parse::<usize>().ok())
                .unwrap_or(0);
            if got.len() >= end + 4 + length {
                break;
            }
        }
        match tokio::time::timeout(Duration::from_secs(30), stream.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break,
            Ok(Ok(n)) => got.extend_from_slice(&buf[..n]),
            Err(_) => panic!("no answer within 30 s"),
        }
    }
    String::from_utf8_lossy(&got).into_owned()
}
