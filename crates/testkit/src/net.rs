//! TCP clients that misbehave on purpose.

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The ClientHello a rustls client of `config` sends first to `localhost`.
pub fn client_hello(config: &Arc<rustls::ClientConfig>) -> Vec<u8> {
    let name = rustls::pki_types::ServerName::try_from("localhost").expect("a name");
    let mut hello = Vec::new();
    rustls::ClientConnection::new(config.clone(), name)
        .expect("a client")
        .write_tls(&mut hello)
        .expect("a ClientHello");
    hello
}

/// A client that gives up on `addr` as a reconnect storm's impatient client does: it sends
/// `hello` (a TLS ClientHello) and closes the connection behind it. Corked (`TCP_CORK`), both
/// leave in one segment, so the server cannot read the one without the other — as when the
/// client gave up long before the server took the connection. Returns what the server answered.
pub async fn gave_up(addr: SocketAddr, hello: &[u8]) -> Vec<u8> {
    let mut socket = tokio::net::TcpStream::connect(addr)
        .await
        .expect("connected");
    socket2::SockRef::from(&socket)
        .set_tcp_cork(true)
        .expect("TCP_CORK");
    socket.write_all(hello).await.expect("sent");
    socket.shutdown().await.expect("closed behind it");
    let mut answer = Vec::new();
    // A server that answered anyway finds the connection closed: reset, or the answer's end.
    let _ = socket.read_to_end(&mut answer).await;
    answer
}
