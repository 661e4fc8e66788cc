//! A client of the operator REST API over HTTPS (for `canlift lifts|get|put|watch` and tests).

use std::path::Path;

use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use serde_json::Value;

use crate::outbound::{Https, OpenError};

/// Why a call failed before an HTTP answer came.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The portal URL is not `https://HOST[:PORT]`.
    #[error("portal URL {0:?}: expected https://HOST[:PORT]")]
    Url(String),
    /// TLS setup or handshake.
    #[error("TLS: {0}")]
    Tls(String),
    /// Connecting or talking HTTP.
    #[error("{0}")]
    Io(String),
}

/// An operator's connection settings.
#[derive(Clone)]
pub struct Client {
    host: String,
    port: u16,
    key: Option<String>,
    /// A web session's `name=value`, sent as `Cookie`.
    cookie: Option<String>,
    /// Further headers sent with every request.
    headers: Vec<(String, String)>,
    /// The local address connections are made from (the system's choice when absent).
    source: Option<std::net::IpAddr>,
    /// Whom it trusts, and how it gets through a proxy.
    https: Https,
}

/// An answer: HTTP status and JSON body (a string when the body is not JSON).
pub type Answer = (u16, Value);

impl Client {
    /// A client for `portal` (`https://HOST[:PORT]`), trusting `ca` (or the system's roots).
    pub fn new(portal: &str, key: Option<&str>, ca: Option<&Path>) -> Result<Client, ClientError> {
        let rest = portal
            .strip_prefix("https://")
            .ok_or_else(|| ClientError::Url(portal.into()))?
            .trim_end_matches('/');
        let (host, port) = match rest.rsplit_once(':') {
            Some((h, p)) => (
                h.to_owned(),
                p.parse().map_err(|_| ClientError::Url(portal.into()))?,
            ),
            None => (rest.to_owned(), 443),
        };
        let https = Https::new(ca).map_err(|e| ClientError::Tls(e.to_string()))?;
        Ok(Client {
            host,
            port,
            key: key.map(str::to_owned),
            cookie: None,
            headers: Vec::new(),
            source: None,
            https,
        })
    }

    /// The same client, sending header `name: value` with every request (an
    /// `Idempotency-Key`, docs/PORTAL.md §Idempotency).
    pub fn with_header(mut self, name: &str, value: &str) -> Client {
        self.headers.push((name.to_owned(), value.to_owned()));
        self
    }

    /// The same client, connecting from local address `source` (a host with several).
    pub fn with_source(mut self, source: std::net::IpAddr) -> Client {
        self.source = Some(source);
        self
    }

    /// The same client, sending `cookie` (`name=value`, as [`Reply::set_cookie`] gives it):
    /// requests in a web session (docs/PORTAL.md §Web UI).
    pub fn with_cookie(mut self, cookie: &str) -> Client {
        self.cookie = Some(cookie.to_owned());
        self
    }

    /// Open one keep-alive connection (TCP, TLS, HTTP/1.1) for many requests.
    pub async fn connect(&self) -> Result<Connection, ClientError> {
        let io = |e: &dyn std::fmt::Display| {
            ClientError::Io(format!("{}:{}: {e}", self.host, self.port))
        };
        // Through HTTPS_PROXY unless NO_PROXY names the portal.
        let tls = self
            .https
            .open(&self.host, self.port, self.source)
            .await
            .map_err(|e| match e {
                OpenError::Proxy(e) => io(&e),
                OpenError::Connect(e) => io(&e),
                OpenError::Tls(e) => ClientError::Tls(e),
            })?;
        let (sender, conn) =
            hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(tls))
                .await
                .map_err(|e| io(&e))?;
        Ok(Connection {
            sender,
            conn: Some(Box::new(conn)),
            // RFC 9110 §7.2: the port too, unless it is HTTPS's own.
            host: match self.port {
                443 => self.host.clone(),
                port => format!("{}:{port}", self.host),
            },
            key: self.key.clone(),
            cookie: self.cookie.clone(),
            headers: self.headers.clone(),
        })
    }

    /// One request with a JSON answer, on a connection of its own.
    pub async fn call(
        &self,
        method: &str,
        path: &str,
        body: Option<Value>,
    ) -> Result<Answer, ClientError> {
        self.connect().await?.call(method, path, body).await
    }

    /// One counter or gauge of the portal's `/metrics` (Prometheus text): the sum of its
    /// samples whatever their labels, or with `name{label="…"}` that sample alone; `None` when
    /// the answer is not 200 or has no such line.
    pub async fn metric(&self, name: &str) -> Result<Option<f64>, ClientError> {
        let (status, text) = self.call("GET", "/metrics", None).await?;
        let text = text.as_str().filter(|_| status == 200);
        Ok(text.and_then(|t| sample_sum(t, name)))
    }

    /// One request with its whole answer (status, `Retry-After`, body), on a connection of its
    /// own: a JSON body, or with `form` an `application/x-www-form-urlencoded` one (the web UI's
    /// forms).
    pub async fn exchange(
        &self,
        method: &str,
        path: &str,
        body: Body<'_>,
    ) -> Result<Reply, ClientError> {
        let mut connection = self.connect().await?;
        let request = connection.request(method, path, body)?;
        connection
            .driven(|sender| async move {
                let response = send(sender, request).await?;
                let retry_after = response
                    .headers()
                    .get(hyper::header::RETRY_AFTER)
                    .and_then(|v| v.to_str().ok())
                    .and_then(|v| v.parse().ok());
                let set_cookie = response
                    .headers()
                    .get(hyper::header::SET_COOKIE)
                    .and_then(|v| v.to_str().ok())
                    .and_then(|v| v.split(';').next())
                    .map(str::to_owned);
                let media = response
                    .headers()
                    .get(hyper::header::CONTENT_TYPE)
                    .and_then(|v| v.to_str().ok())
                    .and_then(|v| v.split(';').next())
                    .map(|v| v.trim().to_owned());
                let (status, body) = answer(response).await?;
                Ok(Reply {
                    status,
                    retry_after,
                    body,
                    set_cookie,
                    media,
                })
            })
            .await
    }

    /// Open the Server-Sent Events at `path` (the portal subscribes before answering, so
    /// nothing published after this returns is missed). `Err` carries a status other than 200.
    pub async fn events(&self, path: &str) -> Result<Result<EventStream, Answer>, ClientError> {
        let mut connection = self.connect().await?;
        let request = connection.request("GET", path, Body::Empty)?;
        // The stream outlives this call: its connection is driven by a task of its own.
        if let Some(conn) = connection.conn.take() {
            tokio::spawn(conn);
        }
        let response = send(&mut connection.sender, request)
            .await
            .map_err(|e| at(&self.host, e))?;
        if response.status() != 200 {
            return Ok(Err(answer(response).await?));
        }
        Ok(Ok(EventStream {
            body: response.into_body(),
            parser: crate::sse::SseParser::default(),
            ready: std::collections::VecDeque::new(),
        }))
    }
}

/// hyper's end of an HTTP/1.1 connection, driven by whoever awaits a call on it.
type Conn = hyper::client::conn::http1::Connection<
    hyper_util::rt::TokioIo<tokio_rustls::client::TlsStream<tokio::net::TcpStream>>,
    Full<Bytes>,
>;

/// One kept-alive connection to the portal: requests go one after another.
pub struct Connection {
    sender: hyper::client::conn::http1::SendRequest<Full<Bytes>>,
    /// The connection's I/O, polled within each call rather than in a task of its own: a
    /// spawned one is woken for every request and wakes the caller for every answer, often
    /// across threads — more than twice the client's CPU per request in the portal benchmark
    /// (docs/BENCHMARKS.md §"What the portal adds to an operator read"). `None` once it ended
    /// or was handed to a task (an event stream's); boxed, as it is a kilobyte and more.
    conn: Option<Box<Conn>>,
    host: String,
    key: Option<String>,
    cookie: Option<String>,
    headers: Vec<(String, String)>,
}

/// The body of a request.
#[derive(Debug, Clone, Copy)]
pub enum Body<'a> {
    /// None.
    Empty,
    /// JSON.
    Json(&'a Value),
    /// A form's fields.
    Form(&'a [(&'a str, &'a str)]),
    /// Text sent as JSON as it is, well-formed or not.
    Text(&'a str),
}

/// A whole answer.
#[derive(Debug, Clone, PartialEq)]
pub struct Reply {
    /// The HTTP status.
    pub status: u16,
    /// Seconds to wait before trying again (`Retry-After` of a 429 or 503).
    pub retry_after: Option<u64>,
    /// The body as JSON (a string when it is not JSON).
    pub body: Value,
    /// The `name=value` of a `Set-Cookie` (a sign-in's session).
    pub set_cookie: Option<String>,
    /// The media type of the body (`text/csv`), without its parameters.
    pub media: Option<String>,
}

impl Connection {
    /// A request to `path` with this connection's credentials.
    fn request(
        &self,
        method: &str,
        path: &str,
        body: Body<'_>,
    ) -> Result<hyper::Request<Full<Bytes>>, ClientError> {
        let mut request = hyper::Request::builder()
            .method(method)
            .uri(path)
            .header("host", &self.host);
        if let Some(k) = &self.key {
            request = request.header("authorization", format!("Bearer {k}"));
        }
        if let Some(c) = &self.cookie {
            request = request.header("cookie", c);
        }
        for (name, value) in &self.headers {
            request = request.header(name, value);
        }
        let bytes = match body {
            Body::Json(b) => {
                request = request.header("content-type", "application/json");
                Bytes::from(b.to_string())
            }
            Body::Form(fields) => {
                request = request.header("content-type", "application/x-www-form-urlencoded");
                let text = serde_urlencoded::to_string(fields)
                    .map_err(|e| ClientError::Io(e.to_string()))?;
                Bytes::from(text)
            }
            Body::Text(text) => {
                request = request.header("content-type", "application/json");
                Bytes::from(text.to_owned())
            }
            Body::Empty => Bytes::new(),
        };
        request
            .body(Full::new(bytes))
            .map_err(|e| ClientError::Io(format!("{}: {e}", self.host)))
    }

    /// `exchange` (a request and the reading of its answer) while this task drives the
    /// connection's I/O beside it.
    async fn driven<'a, T, F>(
        &'a mut self,
        exchange: impl FnOnce(&'a mut hyper::client::conn::http1::SendRequest<Full<Bytes>>) -> F,
    ) -> Result<T, ClientError>
    where
        F: std::future::Future<Output = Result<T, ClientError>>,
    {
        let work = exchange(&mut self.sender);
        let located = |e| at(&self.host, e);
        let Some(conn) = &mut self.conn else {
            return work.await.map_err(located);
        };
        let ended = tokio::select! {
            biased;
            done = work => return done.map_err(located),
            ended = conn => ended,
        };
        self.conn = None;
        Err(located(ClientError::Io(match ended {
            Ok(()) => "the connection closed".to_owned(),
            Err(e) => e.to_string(),
        })))
    }

    /// One request with a JSON answer, on this connection.
    pub async fn call(
        &mut self,
        method: &str,
        path: &str,
        body: Option<Value>,
    ) -> Result<Answer, ClientError> {
        let request = self.request(method, path, body.as_ref().map_or(Body::Empty, Body::Json))?;
        self.driven(|sender| async move { answer(send(sender, request).await?).await })
            .await
    }
}

/// The sum of the samples of `name` in the Prometheus text `text` (of every label set, unless
/// `name` names one).
fn sample_sum(text: &str, name: &str) -> Option<f64> {
    let values: Vec<f64> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let rest = l.strip_prefix(name)?;
            let value = match rest.strip_prefix('{') {
                Some(labelled) if !name.contains('{') => labelled.split_once("} ")?.1,
                _ => rest.strip_prefix(' ')?,
            };
            value.trim().parse().ok()
        })
        .collect();
    (!values.is_empty()).then(|| values.iter().sum())
}

/// The portal's `/metrics` read from its own listener (`[server] metrics_listen`, plain HTTP),
/// as a scraper on the portal's network reads it: beside the public port, it answers while
/// that port's queue is full of gateways (docs/PORTAL.md §Metrics).
pub async fn scrape(listen: std::net::SocketAddr) -> Result<Scraped, ClientError> {
    let io = |e: &dyn std::fmt::Display| ClientError::Io(format!("{listen}: {e}"));
    let tcp = tokio::net::TcpStream::connect(listen)
        .await
        .map_err(|e| io(&e))?;
    let (mut sender, conn) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(tcp))
            .await
            .map_err(|e| io(&e))?;
    let request = hyper::Request::get("/metrics")
        .header(hyper::header::HOST, listen.to_string())
        .body(Full::new(Bytes::new()))
        .map_err(|e| io(&e))?;
    let exchange = async {
        let response = send(&mut sender, request).await?;
        let status = response.status();
        let body = response.into_body().collect().await.map_err(|e| io(&e))?;
        if !status.is_success() {
            return Err(io(&format!("/metrics answered {status}")));
        }
        Ok(Scraped(
            String::from_utf8_lossy(&body.to_bytes()).into_owned(),
        ))
    };
    // The connection is driven beside the exchange and dropped with it.
    tokio::select! {
        scraped = exchange => scraped,
        ended = conn => Err(io(&ended.map_or_else(|e| e.to_string(), |()| "closed".into()))),
    }
}

/// A `/metrics` answer (Prometheus text).
#[derive(Debug, Clone)]
pub struct Scraped(pub String);

impl Scraped {
    /// A counter or gauge: the sum of its samples whatever their labels, or with
    /// `name{label="…"}` that sample alone; `None` when there is no such line.
    pub fn sum(&self, name: &str) -> Option<f64> {
        sample_sum(&self.0, name)
    }
}

/// `e`, saying which portal when it is a connection's.
fn at(host: &str, e: ClientError) -> ClientError {
    match e {
        ClientError::Io(e) => ClientError::Io(format!("{host}: {e}")),
        e => e,
    }
}

/// Send `request` once the connection can take it.
async fn send(
    sender: &mut hyper::client::conn::http1::SendRequest<Full<Bytes>>,
    request: hyper::Request<Full<Bytes>>,
) -> Result<hyper::Response<hyper::body::Incoming>, ClientError> {
    sender
        .ready()
        .await
        .map_err(|e| ClientError::Io(e.to_string()))?;
    sender
        .send_request(request)
        .await
        .map_err(|e| ClientError::Io(e.to_string()))
}

/// The status and the whole body of `response`, as JSON (a string when it is not JSON).
async fn answer(response: hyper::Response<hyper::body::Incoming>) -> Result<Answer, ClientError> {
    let status = response.status().as_u16();
    let bytes = response
        .into_body()
        .collect()
        .await
        .map_err(|e| ClientError::Io(e.to_string()))?
        .to_bytes();
    let value = serde_json::from_slice(&bytes)
        .unwrap_or_else(|_| Value::String(String::from_utf8_lossy(&bytes).into_owned()));
    Ok((status, value))
}

/// Server-Sent Events as they arrive (read by [`crate::sse::SseParser`]).
pub struct EventStream {
    body: hyper::body::Incoming,
    parser: crate::sse::SseParser,
    ready: std::collections::VecDeque<crate::sse::SseEvent>,
}

impl EventStream {
    /// The next event: (event name, data); `None` when the stream ends.
    pub async fn next(&mut self) -> Option<Result<(String, String), ClientError>> {
        loop {
            if let Some(e) = self.ready.pop_front() {
                return Some(Ok((e.event, e.data)));
            }
            match self.body.frame().await? {
                Ok(frame) => {
                    if let Ok(data) = frame.into_data() {
                        self.ready.extend(self.parser.feed(&data));
                    }
                }
                Err(e) => return Some(Err(ClientError::Io(e.to_string()))),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_metric_sums_its_label_sets_unless_one_is_named() {
        let text = "# TYPE a counter\na{reason=\"x\"} 2\na{reason=\"y\"} 3\nab 7\nb 1\n";
        assert_eq!(sample_sum(text, "a"), Some(5.0));
        assert_eq!(sample_sum(text, "a{reason=\"y\"}"), Some(3.0));
        assert_eq!(sample_sum(text, "b"), Some(1.0));
        assert_eq!(sample_sum(text, "c"), None);
    }
}
