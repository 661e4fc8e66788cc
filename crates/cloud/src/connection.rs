//! One HTTP/1.1 connection of the portal, served by hyper with two bounds between its requests
//! (docs/SECURITY.md §Bounds): a request head must be in whole within [`HEAD_TIMEOUT`] of its
//! first byte (of the connection's start, for the first request), and a connection waits at
//! most [`IDLE_TIMEOUT`] for its next request.
//!
//! hyper has one timer for both (`header_read_timeout` runs from the end of an answer to the
//! end of the next head), so the few seconds a slow client must meet also closed every idle
//! keep-alive connection after those seconds: a client reusing one just then (one polling at
//! that period) lost its request ("Remote end closed connection without response"). Here hyper's
//! timer is the idle bound and the stream bounds the head from its first byte. The stream knows
//! where the connection is from the service, which sees each request come and its answer's
//! body go; an upgraded connection (a gateway's WebSocket) is the WebSocket's from then on.

use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::http::{Request, Response, StatusCode};
use hyper::body::{Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Instant, Sleep};

/// How long a request head may take, from its first byte (for a connection's first request,
/// from the end of its TLS handshake): a client that sends its head slowly (slowloris) or not at
/// all is closed. The TLS handshake has the same bound (`server::HANDSHAKE_TIMEOUT`).
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(10);

/// How long a connection may wait idle for its next request. Longer than the keep-alive of the
/// balancers and proxies put in front of portals (60 s for nginx's upstream connections and
/// AWS's ALB), so that they close an idle connection before the portal does and never send a
/// request into one the portal is closing; nginx's own clients get 75 s too.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(75);

/// Serve `service` on `io` until the client closes, a bound is reached, or an upgrade takes the
/// connection over.
pub async fn serve<I, S>(io: I, service: S) -> Result<(), hyper::Error>
where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    S: tower::Service<Request<Incoming>, Response = Response<Body>, Error = Infallible>
        + Clone
        + Send
        + 'static,
    S::Future: Send + 'static,
{
    let phase = Phase::default();
    let io = Bounded {
        inner: io,
        phase: phase.clone(),
        head_by: Some(Box::pin(tokio::time::sleep(HEAD_TIMEOUT))),
    };
    let arrived = phase.clone();
    let service = tower::ServiceBuilder::new()
        .map_request(move |request: Request<Incoming>| {
            arrived.set(IN_REQUEST);
            request
        })
        .map_response(move |response| phase.answered(response))
        .service(service);
    // hyper bounds the wait only when it has a timer.
    hyper::server::conn::http1::Builder::new()
        .timer(TokioTimer::new())
        .header_read_timeout(IDLE_TIMEOUT)
        .serve_connection(TokioIo::new(io), TowerToHyperService::new(service))
        .with_upgrades()
        .await
}

/// Waiting for a request head: the first, or one whose first byte has come.
const HEAD: u8 = 0;
/// From a head's end until its answer's body is gone.
const IN_REQUEST: u8 = 1;
/// Between an answer and the next head's first byte.
const IDLE: u8 = 2;
/// Taken over by an upgrade: no bounds of HTTP's.
const UPGRADED: u8 = 3;

/// Where the connection is, shared by its stream and its service (both run in the connection's
/// task; atomic only to be `Send`).
#[derive(Clone, Default)]
struct Phase(Arc<AtomicU8>);

impl Phase {
    fn get(&self) -> u8 {
        self.0.load(Ordering::Relaxed)
    }

    fn set(&self, phase: u8) {
        self.0.store(phase, Ordering::Relaxed);
    }

    /// The connection is idle once `response`'s body is gone (hyper drops it when written
    /// whole, or when the connection fails); a 101 hands it to the upgrade.
    fn answered(&self, response: Response<Body>) -> Response<Body> {
        if response.status() == StatusCode::SWITCHING_PROTOCOLS {
            self.set(UPGRADED);
            return response;
        }
        let phase = self.clone();
        response.map(|body| Body::new(Answer { body, phase }))
    }
}

/// An answer's body that marks the connection idle when dropped.
struct Answer {
    body: Body,
    phase: Phase,
}

impl hyper::body::Body for Answer {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

impl Drop for Answer {
    fn drop(&mut self) {
        // hyper reads the next head only once this answer is done (HTTP/1.1 answers in order).
        self.phase.set(IDLE);
    }
}

/// The connection's stream, failing its reads once a head has taken longer than
/// [`HEAD_TIMEOUT`] (hyper then closes the connection).
struct Bounded<I> {
    inner: I,
    phase: Phase,
    /// When the head being waited for must be in: reset at the first byte after an idle wait;
    /// dropped once the connection is upgraded (a gateway's lasts for days).
    head_by: Option<Pin<Box<Sleep>>>,
}

impl<I: AsyncRead + Unpin> AsyncRead for Bounded<I> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        match this.phase.get() {
            HEAD => {
                let late = this
                    .head_by
                    .as_mut()
                    .is_some_and(|t| t.as_mut().poll(cx).is_ready());
                if late {
                    return Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        "the request head did not come in time",
                    )));
                }
                Pin::new(&mut this.inner).poll_read(cx, buf)
            }
            IDLE => {
                let before = buf.filled().len();
                let read = Pin::new(&mut this.inner).poll_read(cx, buf);
                if matches!(read, Poll::Ready(Ok(()))) && buf.filled().len() > before {
                    this.phase.set(HEAD);
                    // Always there: only an upgrade drops it, and nothing comes after that.
                    if let Some(timer) = &mut this.head_by {
                        timer.as_mut().reset(Instant::now() + HEAD_TIMEOUT);
                    }
                }
                read
            }
            UPGRADED => {
                this.head_by = None;
                Pin::new(&mut this.inner).poll_read(cx, buf)
            }
            _ => Pin::new(&mut this.inner).poll_read(cx, buf),
        }
    }
}

impl<I: AsyncWrite + Unpin> AsyncWrite for Bounded<I> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::routing::get;
    use axum::Router;
    use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

    /// A portal-like router on one end of an in-memory connection, the client's end returned.
    fn connected() -> DuplexStream {
        let router = Router::new().route("/", get(|| async { "ok" })).route(
            "/up",
            get(|mut request: axum::extract::Request| async move {
                let upgrade = hyper::upgrade::on(&mut request);
                tokio::spawn(async move {
                    let mut io = TokioIo::new(upgrade.await.expect("upgraded"));
                    let mut echo = [0u8; 4];
                    io.read_exact(&mut echo)
                        .await
                        .expect("read after the upgrade");
                    io.write_all(&echo).await.expect("echoed");
                });
                Response::builder()
                    .status(StatusCode::SWITCHING_PROTOCOLS)
                    .header("connection", "upgrade")
                    .header("upgrade", "echo")
                    .body(Body::empty())
                    .expect("a 101")
            }),
        );
        let (client, server) = tokio::io::duplex(64 * 1024);
        tokio::spawn(serve(server, router));
        client
    }

    const GET: &[u8] = b"GET / HTTP/1.1\r\nhost: portal\r\n\r\n";

    /// The answer to one request, or what ended the connection.
    async fn answer(client: &mut DuplexStream) -> Result<String, String> {
        let mut got = Vec::new();
        let mut chunk = [0u8; 1024];
        loop {
            match client.read(&mut chunk).await {
                Ok(0) => return Err(format!("closed after {:?}", String::from_utf8_lossy(&got))),
                Ok(n) => got.extend_from_slice(&chunk[..n]),
                Err(e) => return Err(e.to_string()),
            }
            let text = String::from_utf8_lossy(&got).into_owned();
            if text.ends_with("\r\n\r\nok") || text.starts_with("HTTP/1.1 101") {
                return Ok(text);
            }
        }
    }

    /// Whether the server has closed the connection (by `within`).
    async fn closed(client: &mut DuplexStream, within: Duration) -> bool {
        let mut byte = [0u8; 1];
        matches!(
            tokio::time::timeout(within, client.read(&mut byte)).await,
            Ok(Ok(0) | Err(_))
        )
    }

    /// A keep-alive connection idle for up to [`IDLE_TIMEOUT`] still carries the next request
    /// (hyper's head bound alone closed it after 10 s), and is closed after it.
    #[tokio::test(start_paused = true)]
    async fn an_idle_connection_is_kept_for_its_idle_bound() {
        let mut client = connected();
        client.write_all(GET).await.unwrap();
        answer(&mut client).await.expect("the first answer");
        tokio::time::sleep(IDLE_TIMEOUT - Duration::from_secs(1)).await;
        client.write_all(GET).await.unwrap();
        answer(&mut client)
            .await
            .expect("answered after an idle wait longer than the head's bound");
        let idle = Instant::now();
        assert!(closed(&mut client, IDLE_TIMEOUT * 2).await);
        assert_eq!(idle.elapsed(), IDLE_TIMEOUT);
    }

    /// A connection that says nothing is closed after the head's bound, as is one that sends a
    /// head slowly — the first, or one after an idle wait, counted from its first byte.
    #[tokio::test(start_paused = true)]
    async fn a_slow_or_missing_head_is_closed_after_its_bound() {
        let mut silent = connected();
        let began = Instant::now();
        assert!(closed(&mut silent, HEAD_TIMEOUT * 2).await);
        assert_eq!(began.elapsed(), HEAD_TIMEOUT);

        let mut slow = connected();
        slow.write_all(GET).await.unwrap();
        answer(&mut slow).await.expect("the first answer");
        tokio::time::sleep(Duration::from_secs(30)).await;
        let began = Instant::now();
        let dripping = tokio::spawn(async move {
            for byte in GET.iter().cycle() {
                if slow.write_all(&[*byte]).await.is_err() {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            slow
        });
        let mut slow = dripping.await.unwrap();
        assert!(closed(&mut slow, Duration::ZERO).await);
        let lasted = began.elapsed();
        assert!(
            lasted >= HEAD_TIMEOUT && lasted <= HEAD_TIMEOUT + Duration::from_secs(1),
            "{lasted:?}"
        );
    }

    /// An upgraded connection is the upgrade's: silent for longer than both bounds, before and
    /// after its first bytes, it still carries what comes.
    #[tokio::test(start_paused = true)]
    async fn an_upgraded_connection_has_no_http_bounds() {
        let mut client = connected();
        client
            .write_all(
                b"GET /up HTTP/1.1\r\nhost: portal\r\nconnection: upgrade\r\nupgrade: echo\r\n\r\n",
            )
            .await
            .unwrap();
        let head = answer(&mut client).await.expect("switched");
        assert!(head.starts_with("HTTP/1.1 101"), "{head}");
        tokio::time::sleep(IDLE_TIMEOUT * 2).await;
        client.write_all(b"pi").await.unwrap();
        tokio::time::sleep(IDLE_TIMEOUT * 2).await;
        client.write_all(b"ng").await.unwrap();
        let mut echo = [0u8; 4];
        client.read_exact(&mut echo).await.expect("the echo");
        assert_eq!(&echo, b"ping");
    }
}
