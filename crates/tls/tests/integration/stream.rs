//! `tls::stream::ServerStream` against rustls's buffered client (`tokio-rustls`, what the
//! gateway uses): data both ways in every size and split, close_notify, resumption, key
//! updates in order, push-back, no buffer held while idle, and the failures.

use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use proptest::prelude::*;
use rustls::pki_types::ServerName;
use rustls::{ClientConfig, HandshakeKind, ServerConfig};
use tls::stream::{Acceptor, ServerStream, WRITE_BACKLOG};
use tls::tickets::TicketKeys;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, DuplexStream, ReadBuf};
use tokio_rustls::client::TlsStream;
use tokio_rustls::TlsConnector;

struct Pki {
    server: Arc<ServerConfig>,
    client: Arc<ClientConfig>,
    /// The CA's certificate (PEM): the files go with the function's directory.
    ca: Vec<u8>,
}

/// The server and client configurations the crate makes (as the portal and the gateway use
/// them) for the test PKI, with session tickets under the crate's own ticket keys.
fn pki() -> Pki {
    let dir = tempfile::tempdir().unwrap();
    let files = testkit::pki::pki(dir.path());
    let mut server = tls::server_config(&files.cert, &files.key, None).unwrap();
    let keys = TicketKeys::open(&dir.path().join("tickets"), Duration::from_secs(3600)).unwrap();
    server.ticketer = Arc::new(keys);
    server.send_tls13_tickets = 1;
    Pki {
        server: Arc::new(server),
        client: tls::client_config(Some(&files.ca), None).unwrap(),
        ca: std::fs::read(&files.ca).unwrap(),
    }
}

/// A connected pair over an in-memory pipe of `capacity` bytes each way.
async fn pair(pki: &Pki, capacity: usize) -> (ServerStream<DuplexStream>, TlsStream<DuplexStream>) {
    let (near, far) = tokio::io::duplex(capacity);
    let acceptor = Acceptor::new(pki.server.clone());
    let connector = TlsConnector::from(pki.client.clone());
    let name = ServerName::try_from("localhost").unwrap();
    let (server, client) = tokio::join!(acceptor.accept(near), connector.connect(name, far));
    (server.unwrap(), client.unwrap())
}

fn message(len: usize, seed: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed))
        .collect()
}

#[tokio::test]
async fn data_goes_both_ways_and_close_notify_ends_it() {
    let pki = pki();
    let (mut server, mut client) = pair(&pki, 64 * 1024).await;
    assert_eq!(server.handshake_kind(), Some(HandshakeKind::Full));
    // tls::provider's first choice (SHA-256 in its key schedule).
    assert_eq!(
        client
            .get_ref()
            .1
            .negotiated_cipher_suite()
            .map(|s| s.suite()),
        Some(rustls::CipherSuite::TLS13_AES_128_GCM_SHA256)
    );
    for (i, len) in [1usize, 150, 4096, 16_384, 16_385, 100_000]
        .into_iter()
        .enumerate()
    {
        let up = message(len, i as u8);
        let down = message(len, 100 + i as u8);
        let (from_client, from_server) = tokio::join!(
            async {
                client.write_all(&up).await.unwrap();
                client.flush().await.unwrap();
                let mut got = vec![0; len];
                client.read_exact(&mut got).await.unwrap();
                got
            },
            async {
                let mut got = vec![0; len];
                server.read_exact(&mut got).await.unwrap();
                server.write_all(&down).await.unwrap();
                server.flush().await.unwrap();
                got
            }
        );
        assert!(from_server == up, "{len} bytes up");
        assert!(from_client == down, "{len} bytes down");
        assert_eq!(server.buffered(), 0, "idle after {len} bytes: nothing kept");
    }
    server.shutdown().await.unwrap();
    let mut rest = Vec::new();
    client.read_to_end(&mut rest).await.unwrap();
    assert!(rest.is_empty());
    client.shutdown().await.unwrap();
    let mut rest = Vec::new();
    assert_eq!(server.read_to_end(&mut rest).await.unwrap(), 0);
}

#[tokio::test]
async fn a_second_connection_resumes_the_session() {
    let pki = pki();
    let (mut server, mut client) = pair(&pki, 8192).await;
    // The ticket comes after the handshake; the client takes it with the first answer.
    client.write_all(b"ping").await.unwrap();
    let mut got = [0; 4];
    server.read_exact(&mut got).await.unwrap();
    server.write_all(b"pong").await.unwrap();
    server.flush().await.unwrap();
    client.read_exact(&mut got).await.unwrap();
    let (server, _client) = pair(&pki, 8192).await;
    assert_eq!(server.handshake_kind(), Some(HandshakeKind::Resumed));
}

/// A renewed certificate (the portal's SIGHUP): handshakes from then on present it, a
/// connection made before goes on as it was, and a client resumes the session it had.
#[tokio::test]
async fn a_replaced_configuration_serves_new_handshakes_and_spares_the_old_ones() {
    let pki = pki();
    let (mut before, mut client) = pair(&pki, 8192).await;
    client.write_all(b"ping").await.unwrap();
    let mut got = [0; 4];
    before.read_exact(&mut got).await.unwrap();
    let first = client.get_ref().1.peer_certificates().unwrap()[0].clone();

    let acceptor = Acceptor::new(pki.server.clone());
    let dir = tempfile::tempdir().unwrap();
    let renewed = testkit::pki::pki(dir.path());
    let mut config = tls::server_config(&renewed.cert, &renewed.key, None).unwrap();
    config.ticketer = pki.server.ticketer.clone();
    acceptor.replace(config);

    let roots = dir.path().join("both.pem");
    let mut both = std::fs::read(&renewed.ca).unwrap();
    both.extend_from_slice(&pki.ca);
    std::fs::write(&roots, both).unwrap();
    let client_config = tls::client_config(Some(&roots), None).unwrap();
    let connect = |config: Arc<ClientConfig>| {
        let acceptor = acceptor.clone();
        async move {
            let (near, far) = tokio::io::duplex(8192);
            let name = ServerName::try_from("localhost").unwrap();
            let (server, client) = tokio::join!(
                acceptor.accept(near),
                TlsConnector::from(config).connect(name, far)
            );
            (server.unwrap(), client.unwrap())
        }
    };
    let (_after, fresh) = connect(client_config).await;
    let second = fresh.get_ref().1.peer_certificates().unwrap()[0].clone();
    assert_ne!(first, second, "the renewed certificate is presented");

    // The connection made before still carries data both ways.
    before.write_all(b"pong").await.unwrap();
    before.flush().await.unwrap();
    client.read_exact(&mut got).await.unwrap();
    assert_eq!(&got, b"pong");
    // Its client took a ticket with the answer: it resumes against the new configuration.
    let (resumed, _client) = connect(pki.client.clone()).await;
    assert_eq!(resumed.handshake_kind(), Some(HandshakeKind::Resumed));
}

/// The client asks for new keys every few messages (RFC 8446 §4.6.3, `update_requested`): the
/// server answers with a KeyUpdate of its own, sealed and sent before its next records, which
/// the client then opens with the server's new keys.
#[tokio::test]
async fn keys_are_updated_when_the_client_asks() {
    let pki = pki();
    let (mut server, mut client) = pair(&pki, 4096).await;
    for i in 0..60u8 {
        if i % 7 == 3 {
            client.get_mut().1.refresh_traffic_keys().unwrap();
        }
        let up = message(200, i);
        let down = message(300, i);
        client.write_all(&up).await.unwrap();
        client.flush().await.unwrap();
        let mut got = vec![0; up.len()];
        server.read_exact(&mut got).await.unwrap();
        assert_eq!(got, up, "message {i} up");
        server.write_all(&down).await.unwrap();
        server.flush().await.unwrap();
        let mut got = vec![0; down.len()];
        client.read_exact(&mut got).await.unwrap();
        assert_eq!(got, down, "message {i} down");
    }
}

#[tokio::test]
async fn a_peer_that_stops_reading_makes_the_writer_wait() {
    let pki = pki();
    let (mut server, mut client) = pair(&pki, 4096).await;
    let big = message(1 << 20, 7);
    // Write until the stream stops taking data: the pipe (4 KiB) and the stream's backlog fill.
    let mut accepted = 0;
    while let Ok(n) =
        tokio::time::timeout(Duration::from_millis(100), server.write(&big[accepted..])).await
    {
        accepted += n.unwrap();
        assert!(accepted < big.len(), "1 MiB went into a pipe nobody reads");
    }
    // At most the backlog and one more record are queued (the allocation at most twice that).
    assert!(
        accepted <= WRITE_BACKLOG + 16_384 + 4096,
        "took {accepted} bytes"
    );
    assert!(
        server.buffered() <= 2 * (WRITE_BACKLOG + 16_384 + 256),
        "holds {} bytes",
        server.buffered()
    );
    let ((), read) = tokio::join!(
        async {
            server.write_all(&big[accepted..]).await.unwrap();
            server.flush().await.unwrap();
        },
        async {
            let mut got = vec![0; big.len()];
            client.read_exact(&mut got).await.unwrap();
            got
        }
    );
    assert!(read == big);
    assert_eq!(server.buffered(), 0);
}

#[tokio::test]
async fn an_end_without_close_notify_is_an_error() {
    let pki = pki();
    let (mut server, client) = pair(&pki, 4096).await;
    drop(client);
    let e = server.read(&mut [0; 16]).await.unwrap_err();
    assert_eq!(e.kind(), std::io::ErrorKind::UnexpectedEof, "{e}");
}

#[tokio::test]
async fn a_peer_that_speaks_no_tls_is_refused() {
    let pki = pki();
    let (near, mut far) = tokio::io::duplex(4096);
    far.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    let e = Acceptor::new(pki.server.clone())
        .accept(near)
        .await
        .err()
        .expect("no TLS, no connection");
    assert_eq!(e.kind(), std::io::ErrorKind::InvalidData, "{e}");
    // The peer is told why (a TLS alert record: content type 21).
    let mut alert = [0u8; 7];
    far.read_exact(&mut alert).await.unwrap();
    assert_eq!(alert[0], 21, "{alert:?}");
}

/// A server that requires a client certificate refuses a client without one with the
/// certificate_required alert (RFC 8446 §4.4.2.4), which the client reads as such at its first
/// read (under TLS 1.3 its side of the handshake is done by then) — not an end of stream without
/// close_notify. The alert is encoded from the records rustls still holds: with none, rustls
/// itself panicked here.
#[tokio::test]
async fn a_client_without_the_required_certificate_is_told_why() {
    let dir = tempfile::tempdir().unwrap();
    let files = testkit::pki::pki(dir.path());
    let server = tls::server_config(&files.cert, &files.key, Some(&files.ca)).unwrap();
    let client = tls::client_config(Some(&files.ca), None).unwrap();
    let (near, far) = tokio::io::duplex(16 * 1024);
    let acceptor = Acceptor::new(Arc::new(server));
    let accept = acceptor.accept(near);
    let name = ServerName::try_from("localhost").unwrap();
    let connect = async {
        let mut stream = TlsConnector::from(client).connect(name, far).await?;
        stream.read(&mut [0; 16]).await
    };
    let (accepted, read) = tokio::join!(accept, connect);
    assert!(accepted.is_err(), "no certificate, no connection");
    let e = read.expect_err("the client learns it was refused");
    let alert = e.get_ref().and_then(|e| e.downcast_ref::<rustls::Error>());
    assert_eq!(
        alert,
        Some(&rustls::Error::AlertReceived(
            rustls::AlertDescription::CertificateRequired
        )),
        "{e}"
    );
}

/// A client that gave up while its connection waited (its ClientHello, then its end of stream,
/// both there before the server looks) is dropped unanswered: no ServerHello, so no key
/// agreement or signature was made for it. A client that waits is answered, its hello whole or
/// in two parts.
#[tokio::test]
async fn a_client_that_gave_up_behind_its_hello_gets_no_handshake() {
    let pki = pki();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let acceptor = Acceptor::new(pki.server.clone());
    let server = tokio::spawn(async move {
        let mut outcomes = Vec::new();
        for _ in 0..3 {
            let (tcp, _) = listener.accept().await.unwrap();
            outcomes.push(
                acceptor
                    .accept(tcp)
                    .await
                    .err()
                    .map(|e| tls::stream::abandoned(&e)),
            );
        }
        outcomes
    });
    let answer = testkit::net::gave_up(addr, &testkit::net::client_hello(&pki.client)).await;
    assert!(answer.is_empty(), "{} bytes answered", answer.len());
    for split in [None, Some(7)] {
        let hello = testkit::net::client_hello(&pki.client);
        let (first, rest) = hello.split_at(split.unwrap_or(hello.len()));
        let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
        tcp.write_all(first).await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
        tcp.write_all(rest).await.unwrap();
        let mut flight = [0u8; 5];
        tcp.read_exact(&mut flight).await.unwrap();
        assert_eq!(
            flight[0], 22,
            "a handshake record (ServerHello): {flight:?}"
        );
    }
    // Given up behind its hello; the others closed later, in the middle of the handshake.
    assert_eq!(
        server.await.unwrap(),
        [Some(true), Some(false), Some(false)]
    );
}

/// A pipe that counts the writes reaching it.
struct Counted {
    pipe: DuplexStream,
    writes: Arc<AtomicUsize>,
}

impl AsyncRead for Counted {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.pipe).poll_read(cx, buf)
    }
}

impl tls::stream::Transport for Counted {}

impl AsyncWrite for Counted {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        self.writes.fetch_add(1, Ordering::Relaxed);
        Pin::new(&mut self.pipe).poll_write(cx, data)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.pipe).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.pipe).poll_shutdown(cx)
    }
}

/// What a writer writes together (the portal's requests of one lift page) leaves at its flush
/// in one write to the socket, each message its own record; a full record's worth leaves at
/// once.
#[tokio::test]
async fn writes_leave_together_at_the_flush() {
    let pki = pki();
    let (near, far) = tokio::io::duplex(1 << 20);
    let writes = Arc::new(AtomicUsize::new(0));
    let near = Counted {
        pipe: near,
        writes: writes.clone(),
    };
    let acceptor = Acceptor::new(pki.server.clone());
    let connector = TlsConnector::from(pki.client.clone());
    let name = ServerName::try_from("localhost").unwrap();
    let (server, client) = tokio::join!(acceptor.accept(near), connector.connect(name, far));
    let (mut server, mut client) = (server.unwrap(), client.unwrap());
    let before = writes.load(Ordering::Relaxed);
    let messages: Vec<Vec<u8>> = (0..18).map(|k| message(150, k)).collect();
    for m in &messages {
        server.write_all(m).await.unwrap();
    }
    assert_eq!(
        writes.load(Ordering::Relaxed),
        before,
        "nothing left before the flush"
    );
    assert!(server.buffered() > 18 * 150);
    server.flush().await.unwrap();
    assert_eq!(
        writes.load(Ordering::Relaxed),
        before + 1,
        "one write for all"
    );
    assert_eq!(server.buffered(), 0);
    let mut got = vec![0; 18 * 150];
    client.read_exact(&mut got).await.unwrap();
    assert!(got == messages.concat());
    // A record's worth does not wait for the flush.
    server.write_all(&message(40_000, 9)).await.unwrap();
    assert!(writes.load(Ordering::Relaxed) > before + 1);
    assert!(
        server.buffered() < 16_384 + 256,
        "holds {}",
        server.buffered()
    );
}

#[tokio::test]
async fn tcp_and_small_reads() {
    let pki = pki();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let acceptor = Acceptor::new(pki.server.clone());
    let server = tokio::spawn(async move {
        let (tcp, _) = listener.accept().await.unwrap();
        let mut stream = acceptor.accept(tcp).await.unwrap();
        // Read in the 512-byte pieces the portal's WebSocket reads with.
        let mut all = Vec::new();
        let mut piece = [0u8; 512];
        loop {
            let n = stream.read(&mut piece).await.unwrap();
            if n == 0 {
                break;
            }
            all.extend_from_slice(&piece[..n]);
        }
        (all, stream.buffered())
    });
    let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let name = ServerName::try_from("localhost").unwrap();
    let mut client = TlsConnector::from(pki.client.clone())
        .connect(name, tcp)
        .await
        .unwrap();
    let sent = message(50_000, 3);
    for chunk in sent.chunks(777) {
        client.write_all(chunk).await.unwrap();
    }
    client.shutdown().await.unwrap();
    let (received, buffered) = server.await.unwrap();
    assert!(received == sent);
    assert_eq!(buffered, 0);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Any sizes through any pipe: everything arrives, in order, both ways.
    #[test]
    fn any_sizes_through_any_pipe(
        sizes in proptest::collection::vec(1usize..40_000, 1..6),
        capacity in 1usize..9000,
        piece in 1usize..3000,
    ) {
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        runtime.block_on(async {
            let pki = pki();
            let (mut server, mut client) = pair(&pki, capacity).await;
            for (i, &len) in sizes.iter().enumerate() {
                let up = message(len, i as u8);
                let (_, got) = tokio::join!(
                    async {
                        client.write_all(&up).await.unwrap();
                        client.flush().await.unwrap();
                    },
                    async {
                        let mut got = Vec::new();
                        let mut buf = vec![0u8; piece];
                        while got.len() < len {
                            let n = server.read(&mut buf).await.unwrap();
                            got.extend_from_slice(&buf[..n]);
                        }
                        got
                    }
                );
                prop_assert!(got == up);
                let (_, back) = tokio::join!(
                    async {
                        server.write_all(&got).await.unwrap();
                        server.flush().await.unwrap();
                    },
                    async {
                        let mut back = vec![0u8; len];
                        client.read_exact(&mut back).await.unwrap();
                        back
                    }
                );
                prop_assert!(back == up);
            }
            prop_assert_eq!(server.buffered(), 0);
            Ok(())
        })?;
    }
}
