//! Requests the portal itself makes to servers outside it: webhook receivers (docs/PORTAL.md
//! §Webhooks) and the OpenID provider of single sign-on (§Single sign-on). HTTP/1.1, one
//! request per connection, `https://` through `HTTPS_PROXY` unless `NO_PROXY` names the host
//! (the proxy's CONNECT tunnel; TLS end to end), trusting the system's roots or a CA file.
//! Redirects are never followed (a server cannot send the portal elsewhere), answers are read
//! up to a bound, and errors name neither the server's address nor its URL, which may hold
//! credentials and internal host names.

use std::net::IpAddr;
use std::path::Path;
use std::sync::Arc;

use http_body_util::{BodyExt, Full, Limited};
use hyper::body::Bytes;
use tokio::net::TcpStream;
use tokio_rustls::client::TlsStream;

/// Where a request goes, read from its URL.
#[derive(Debug, Clone)]
pub struct Target {
    /// `https://` (else `http://`).
    pub https: bool,
    /// The host name or address (IPv6 without brackets).
    pub host: String,
    /// The port.
    pub port: u16,
    /// Path and query.
    pub path: String,
    /// The URL's `USER:PASSWORD@` as `Authorization: Basic …`.
    pub basic: Option<String>,
}

impl Target {
    /// Read `url` (`http(s)://[USER:PASSWORD@]HOST[:PORT]/PATH`). The errors never repeat it.
    pub fn parse(url: &str) -> Result<Target, String> {
        use base64::Engine;
        let uri: hyper::Uri = url.parse().map_err(|e| format!("not a URL: {e}"))?;
        let https = match uri.scheme_str() {
            Some("https") => true,
            Some("http") => false,
            _ => return Err("http:// or https://".into()),
        };
        let host = uri
            .host()
            .ok_or("no host")?
            .trim_matches(['[', ']'])
            .to_owned();
        let basic = uri
            .authority()
            .and_then(|a| a.as_str().rsplit_once('@'))
            .map(|(userinfo, _)| {
                let (user, password) = userinfo.split_once(':').unwrap_or((userinfo, ""));
                let decode = |t: &str| {
                    percent_encoding::percent_decode_str(t)
                        .decode_utf8_lossy()
                        .into_owned()
                };
                let pair = format!("{}:{}", decode(user), decode(password));
                format!(
                    "Basic {}",
                    base64::engine::general_purpose::STANDARD.encode(pair)
                )
            });
        Ok(Target {
            https,
            port: uri.port_u16().unwrap_or(if https { 443 } else { 80 }),
            path: uri
                .path_and_query()
                .map_or_else(|| "/".to_owned(), |p| p.as_str().to_owned()),
            host,
            basic,
        })
    }
}

/// An answer: its status, and its body.
#[derive(Debug)]
pub struct Answer {
    /// The HTTP status.
    pub status: u16,
    /// The body; none when it was longer than the bound asked for or broke off.
    pub body: Option<Bytes>,
}

/// The TLS side of outbound requests: whom they trust.
#[derive(Clone)]
pub struct Https {
    tls: tokio_rustls::TlsConnector,
}

impl Https {
    /// Trusting `ca_file`'s CAs, or the system's roots without one.
    pub fn new(ca_file: Option<&Path>) -> Result<Https, tls::TlsError> {
        let mut config = Arc::unwrap_or_clone(tls::client_config(ca_file, None)?);
        config.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(Https {
            tls: tokio_rustls::TlsConnector::from(Arc::new(config)),
        })
    }

    /// A TLS connection to `host:port` (from local address `source` if given): through
    /// `HTTPS_PROXY` unless `NO_PROXY` names the host (the proxy resolves its name), else
    /// straight. What failed is told apart, for each caller to say in its own words.
    pub async fn open(
        &self,
        host: &str,
        port: u16,
        source: Option<IpAddr>,
    ) -> Result<TlsStream<TcpStream>, OpenError> {
        let proxy = tls::reach::Proxies::Environment
            .for_server(host, port)
            .map_err(OpenError::Proxy)?;
        let tcp = tls::reach::connect(host, port, source, proxy.as_ref())
            .await
            .map_err(OpenError::Connect)?;
        let _ = tcp.set_nodelay(true);
        let name = rustls::pki_types::ServerName::try_from(host.to_owned())
            .map_err(|e| OpenError::Tls(e.to_string()))?;
        self.tls
            .connect(name, tcp)
            .await
            .map_err(|e| OpenError::Tls(e.to_string()))
    }

    /// Send `request` to `target` over a connection of its own (an `http://` target over `tcp`
    /// when the caller made it, having checked where it goes; else straight), reading at most
    /// `limit` bytes of the answer's body.
    pub async fn send(
        &self,
        target: &Target,
        tcp: Option<TcpStream>,
        request: hyper::Request<Full<Bytes>>,
        limit: usize,
    ) -> Result<Answer, String> {
        let no_connection = |e: std::io::Error| format!("no connection: {}", e.kind());
        if !target.https {
            let tcp = match tcp {
                Some(tcp) => tcp,
                None => tls::reach::connect(&target.host, target.port, None, None)
                    .await
                    .map_err(no_connection)?,
            };
            let _ = tcp.set_nodelay(true);
            return exchange(tcp, request, limit).await;
        }
        let tls = self
            .open(&target.host, target.port, None)
            .await
            .map_err(|e| match e {
                OpenError::Proxy(e) => e.to_string(),
                OpenError::Connect(e) => no_connection(e),
                OpenError::Tls(e) => format!("TLS: {e}"),
            })?;
        exchange(tls, request, limit).await
    }
}

/// Why [`Https::open`] made no connection.
#[derive(Debug)]
pub enum OpenError {
    /// `HTTPS_PROXY` is not a proxy URL.
    Proxy(tls::reach::ProxyError),
    /// No TCP connection, straight or through the proxy.
    Connect(std::io::Error),
    /// No TLS session (the handshake failed, or the host is no server name).
    Tls(String),
}

async fn exchange<S>(
    stream: S,
    request: hyper::Request<Full<Bytes>>,
    limit: usize,
) -> Result<Answer, String>
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    let (mut sender, connection) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
            .await
            .map_err(|e| e.to_string())?;
    tokio::spawn(connection);
    let response = sender
        .send_request(request)
        .await
        .map_err(|e| e.to_string())?;
    let status = response.status().as_u16();
    let body = Limited::new(response.into_body(), limit)
        .collect()
        .await
        .ok()
        .map(|b| b.to_bytes());
    Ok(Answer { status, body })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_are_read_without_repeating_them() {
        let t = Target::parse("http://127.0.0.1:9000/hook?x=1").unwrap();
        assert_eq!(
            (t.https, t.port, t.path.as_str()),
            (false, 9000, "/hook?x=1")
        );
        assert_eq!(t.basic, None);
        let t = Target::parse("https://hooks:p%40ss@alerts.example/hook").unwrap();
        assert_eq!(
            (t.host.as_str(), t.path.as_str()),
            ("alerts.example", "/hook")
        );
        // base64 of "hooks:p@ss".
        assert_eq!(t.basic.as_deref(), Some("Basic aG9va3M6cEBzcw=="));
        assert_eq!(Target::parse("http://[::1]/").unwrap().host, "::1");
        let refused = Target::parse("ftp://secret@x/").err().unwrap();
        assert!(!refused.contains("secret"), "{refused}");
        assert_eq!(Target::parse("https://example.com").unwrap().port, 443);
    }
}
