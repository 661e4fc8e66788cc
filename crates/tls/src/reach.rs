//! How a TLS client reaches its server: straight, from a chosen local address, or through an
//! HTTP proxy's `CONNECT` tunnel (RFC 9110 §9.3.6) — TLS stays end to end, the proxy sees only
//! where to. Sites whose networks reach the internet only through a proxy set `HTTPS_PROXY`
//! (and `NO_PROXY` for what is reached directly), read with curl's rules (hyper-util's
//! matcher), or name the proxy in their configuration.

use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use hyper_util::client::proxy::matcher::Matcher;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// The longest answer head a proxy may send to `CONNECT`.
const MAX_HEAD: usize = 8 * 1024;

/// How long a proxy may take to answer `CONNECT` (the caller's own bound is the outer one).
const PROXY_ANSWER: Duration = Duration::from_secs(30);

/// An HTTP proxy to tunnel through.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Proxy {
    host: String,
    port: u16,
    /// `Proxy-Authorization`, from the proxy URL's `USER:PASSWORD@`.
    authorization: Option<String>,
}

impl std::fmt::Display for Proxy {
    /// The proxy as the logs name it: host and port, never its credentials.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.host, self.port)
    }
}

/// Where the proxies come from.
#[derive(Debug, Clone, Default)]
pub enum Proxies {
    /// `HTTPS_PROXY`/`https_proxy` (or `ALL_PROXY`) and `NO_PROXY`/`no_proxy`, as curl reads them.
    #[default]
    Environment,
    /// This proxy for every server (`http://[USER:PASSWORD@]HOST:PORT`), whatever the
    /// environment says.
    Configured(String),
}

/// Why no proxy can be used.
#[derive(Debug, thiserror::Error)]
pub enum ProxyError {
    /// The proxy URL is not `http://[USER:PASSWORD@]HOST[:PORT]`.
    #[error("proxy URL: {0}")]
    Url(String),
}

impl Proxies {
    /// The proxy to reach `host:port` (an HTTPS or WSS server) through, if any.
    pub fn for_server(&self, host: &str, port: u16) -> Result<Option<Proxy>, ProxyError> {
        let matcher = match self {
            Proxies::Environment => Matcher::from_env(),
            Proxies::Configured(url) => {
                if !url.starts_with("http://") {
                    return Err(ProxyError::Url(
                        "an http:// proxy (TLS runs through its CONNECT tunnel)".into(),
                    ));
                }
                Matcher::builder().https(url.as_str()).build()
            }
        };
        let authority = if host.contains(':') {
            format!("[{host}]:{port}")
        } else {
            format!("{host}:{port}")
        };
        let server: http::Uri = format!("https://{authority}/")
            .parse()
            .map_err(|e: http::uri::InvalidUri| ProxyError::Url(e.to_string()))?;
        let Some(intercept) = matcher.intercept(&server) else {
            return Ok(None);
        };
        let uri = intercept.uri();
        if uri.scheme_str() != Some("http") {
            return Err(ProxyError::Url(format!(
                "{}: only http:// proxies (TLS runs through their CONNECT tunnel)",
                uri.scheme_str().unwrap_or("?")
            )));
        }
        let host = uri
            .host()
            .ok_or_else(|| ProxyError::Url("no host".into()))?
            .trim_matches(['[', ']'])
            .to_owned();
        Ok(Some(Proxy {
            host,
            port: uri.port_u16().unwrap_or(80),
            authorization: intercept
                .basic_auth()
                .and_then(|v| v.to_str().ok())
                .map(str::to_owned),
        }))
    }
}

/// A TCP connection to `host:port`: through `proxy`'s tunnel when given, else straight; from
/// local address `source` when given (of the server's address family).
pub async fn connect(
    host: &str,
    port: u16,
    source: Option<IpAddr>,
    proxy: Option<&Proxy>,
) -> std::io::Result<TcpStream> {
    match proxy {
        None => direct(host, port, source).await,
        Some(proxy) => {
            let mut tcp = direct(&proxy.host, proxy.port, source)
                .await
                .map_err(|e| with(e, &format!("the proxy {proxy}")))?;
            tokio::time::timeout(PROXY_ANSWER, tunnel(&mut tcp, host, port, proxy))
                .await
                .map_err(|_| {
                    std::io::Error::new(
                        std::io::ErrorKind::TimedOut,
                        format!("the proxy {proxy} did not answer CONNECT"),
                    )
                })??;
            Ok(tcp)
        }
    }
}

fn with(e: std::io::Error, what: &str) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{what}: {e}"))
}

/// Ask `proxy` on `tcp` for a tunnel to `host:port`; `Ok` once it answered 2xx.
async fn tunnel(tcp: &mut TcpStream, host: &str, port: u16, proxy: &Proxy) -> std::io::Result<()> {
    let authority = if host.contains(':') {
        format!("[{host}]:{port}")
    } else {
        format!("{host}:{port}")
    };
    let mut request = format!("CONNECT {authority} HTTP/1.1\r\nHost: {authority}\r\n");
    if let Some(authorization) = &proxy.authorization {
        request.push_str(&format!("Proxy-Authorization: {authorization}\r\n"));
    }
    request.push_str("\r\n");
    tcp.write_all(request.as_bytes()).await?;
    // Read to the end of the answer's head and not a byte further: what follows is the
    // server's (a few dozen reads of one byte, once per connection).
    let mut head = Vec::with_capacity(128);
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        if head.len() > MAX_HEAD {
            return Err(refused(proxy, "an answer head over 8 KiB"));
        }
        if tcp.read(&mut byte).await? == 0 {
            return Err(refused(proxy, "closed the connection instead of answering"));
        }
        head.push(byte[0]);
    }
    let status_line = String::from_utf8_lossy(&head);
    let status_line = status_line.lines().next().unwrap_or_default();
    let status = status_line
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse::<u16>().ok());
    match status {
        Some(200..=299) => Ok(()),
        _ => Err(refused(proxy, &format!("answered {status_line:?}"))),
    }
}

fn refused(proxy: &Proxy, why: &str) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::ConnectionRefused,
        format!("the proxy {proxy} {why}"),
    )
}

/// A straight TCP connection, from `source` when given.
async fn direct(host: &str, port: u16, source: Option<IpAddr>) -> std::io::Result<TcpStream> {
    let Some(source) = source else {
        return TcpStream::connect((host, port)).await;
    };
    let mut last = None;
    for addr in tokio::net::lookup_host((host, port)).await? {
        if addr.is_ipv4() != source.is_ipv4() {
            continue;
        }
        let socket = if addr.is_ipv4() {
            TcpSocket::new_v4()?
        } else {
            TcpSocket::new_v6()?
        };
        socket.bind(SocketAddr::new(source, 0))?;
        match socket.connect(addr).await {
            Ok(stream) => return Ok(stream),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::AddrNotAvailable,
            format!("{host} has no address of the family of {source}"),
        )
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configured_proxies_and_their_credentials() {
        let p = Proxies::Configured("http://site:s3cret@proxy.example:3128".into())
            .for_server("portal.example", 443)
            .unwrap()
            .unwrap();
        assert_eq!(p.to_string(), "proxy.example:3128", "no credentials shown");
        // base64("site:s3cret")
        assert_eq!(p.authorization.as_deref(), Some("Basic c2l0ZTpzM2NyZXQ="));
        assert!(Proxies::Configured("https://proxy.example:3128".into())
            .for_server("portal.example", 443)
            .is_err());
    }

    /// A tunnel through a stand-in proxy: the CONNECT line and credentials go first, the
    /// answer head is consumed, and what follows is the server's; a refusal is an error.
    #[tokio::test]
    async fn a_tunnel_is_asked_for_and_refusals_are_errors() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let proxy = Proxy {
            host: "127.0.0.1".into(),
            port,
            authorization: Some("Basic eDp5".into()),
        };
        let stand_in = tokio::spawn(async move {
            let mut asked = Vec::new();
            for answer in [
                &b"HTTP/1.1 200 Connection established\r\n\r\n"[..],
                b"HTTP/1.1 407 Proxy Authentication Required\r\n\r\n",
            ] {
                let (mut tcp, _) = listener.accept().await.unwrap();
                let mut request = vec![0u8; 1024];
                let n = tcp.read(&mut request).await.unwrap();
                asked.push(String::from_utf8_lossy(&request[..n]).into_owned());
                tcp.write_all(answer).await.unwrap();
                tcp.write_all(b"server bytes").await.unwrap();
            }
            asked
        });
        let mut tcp = connect("portal.example", 8443, None, Some(&proxy))
            .await
            .unwrap();
        let mut first = [0u8; 12];
        tcp.read_exact(&mut first).await.unwrap();
        assert_eq!(&first, b"server bytes");
        let refused = connect("portal.example", 8443, None, Some(&proxy))
            .await
            .unwrap_err();
        assert!(refused.to_string().contains("407"), "{refused}");
        let asked = stand_in.await.unwrap();
        assert!(
            asked[0].starts_with("CONNECT portal.example:8443 HTTP/1.1\r\n"),
            "{}",
            asked[0]
        );
        assert!(asked[0].contains("Proxy-Authorization: Basic eDp5\r\n"));
    }
}
