//! The client's address behind a load balancer (docs/PORTAL.md §Behind a load balancer): the
//! throttles, the refusals, the audit log and the logs need the address of whoever is on the
//! other end, and behind a load balancer every connection comes from the balancer.
//!
//! Only the peers of `[server] trusted_proxies` are believed, in the two ways HAProxy and its
//! kind say it: a PROXY protocol v2 header sent before anything else on the connection (TCP
//! mode, TLS passed through), or `X-Forwarded-For` on each request (HTTP mode). Anyone else's
//! header is not read — a PROXY header from an untrusted peer is just a failed TLS handshake —
//! and anyone else's `X-Forwarded-For` is ignored.

use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use axum::http::HeaderMap;
use ipnet::IpNet;
use tokio::io::AsyncReadExt;
use tokio::net::TcpStream;

/// The first bytes of a PROXY protocol v2 header (its signature, then version and command).
const SIGNATURE: &[u8] = ppp::v2::PROTOCOL_PREFIX;

/// A PROXY v2 header's fixed part: the signature, version and command, family, length.
const FIXED: usize = 16;

/// The peers whose word on the client's address counts.
#[derive(Debug, Clone, Default)]
pub struct TrustedProxies(Vec<IpNet>);

impl TrustedProxies {
    /// The addresses and CIDR blocks of `[server] trusted_proxies`.
    pub fn parse(list: &[String]) -> Result<TrustedProxies, String> {
        list.iter()
            .map(|text| {
                text.parse::<IpNet>()
                    .or_else(|_| text.parse::<IpAddr>().map(IpNet::from))
                    .map_err(|_| {
                        format!("[server] trusted_proxies: {text:?} is no address or CIDR block")
                    })
            })
            .collect::<Result<_, _>>()
            .map(TrustedProxies)
    }

    /// Whether `ip` is a trusted proxy's (an IPv4 address mapped into IPv6 counts as itself).
    pub fn trusts(&self, ip: IpAddr) -> bool {
        let ip = match ip {
            IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(ip, IpAddr::V4),
            v4 => v4,
        };
        self.0.iter().any(|net| net.contains(&ip))
    }

    /// The client behind connection `tcp` from `peer`: a trusted peer's PROXY v2 header is read
    /// (and taken off the stream) if it sent one first; otherwise, and for anyone else, the
    /// peer. A trusted peer that starts a header and does not finish it within `patience`, or
    /// sends a malformed one, is an error: the connection is closed.
    pub async fn client_of(
        &self,
        tcp: &mut TcpStream,
        peer: SocketAddr,
        patience: Duration,
    ) -> std::io::Result<SocketAddr> {
        if !self.trusts(peer.ip()) {
            return Ok(peer);
        }
        let header = tokio::time::timeout(patience, read_header(tcp))
            .await
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "PROXY header"))??;
        Ok(header.unwrap_or(peer))
    }

    /// The client of a request that came from `peer` with `headers`: from a trusted peer, the
    /// right-most address of `X-Forwarded-For` that is not a trusted proxy's (the addresses
    /// before it are whatever the client chose to send); otherwise the peer.
    pub fn client_of_request(&self, peer: SocketAddr, headers: &HeaderMap) -> SocketAddr {
        if !self.trusts(peer.ip()) {
            return peer;
        }
        let hops: Vec<IpAddr> = headers
            .get_all("x-forwarded-for")
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(','))
            .filter_map(|hop| hop.trim().parse::<IpAddr>().ok())
            .collect();
        hops.into_iter()
            .rev()
            .find(|ip| !self.trusts(*ip))
            .map_or(peer, |ip| SocketAddr::new(ip, 0))
    }
}

/// A PROXY v2 header's source address, if the stream begins with one (`None`: it does not,
/// and nothing was read; a header with the LOCAL command — a balancer's own health check —
/// has none either).
async fn read_header(tcp: &mut TcpStream) -> std::io::Result<Option<SocketAddr>> {
    let invalid = |why: String| std::io::Error::new(std::io::ErrorKind::InvalidData, why);
    let mut fixed = [0u8; FIXED];
    // Peeked until the signature is there or cannot be: a TLS ClientHello differs at once.
    loop {
        let n = tcp.peek(&mut fixed).await?;
        if n == 0 || !SIGNATURE.starts_with(&fixed[..n.min(SIGNATURE.len())]) {
            return Ok(None);
        }
        if n == FIXED {
            break;
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let length = usize::from(u16::from_be_bytes([fixed[14], fixed[15]]));
    let mut header = vec![0u8; FIXED + length];
    tcp.read_exact(&mut header).await?;
    let parsed = ppp::v2::Header::try_from(header.as_slice())
        .map_err(|e| invalid(format!("PROXY header: {e}")))?;
    Ok(match parsed.addresses {
        ppp::v2::Addresses::IPv4(a) => {
            Some(SocketAddr::new(a.source_address.into(), a.source_port))
        }
        ppp::v2::Addresses::IPv6(a) => {
            Some(SocketAddr::new(a.source_address.into(), a.source_port))
        }
        ppp::v2::Addresses::Unspecified | ppp::v2::Addresses::Unix(_) => None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn trusted() -> TrustedProxies {
        TrustedProxies::parse(&["10.0.0.0/8".into(), "192.0.2.1".into()]).unwrap()
    }

    #[test]
    fn only_trusted_peers_are_believed_and_only_as_far_as_the_first_untrusted_hop() {
        let proxies = trusted();
        assert!(TrustedProxies::parse(&["10.0.0.0/33".into()]).is_err());
        assert!(proxies.trusts("10.9.8.7".parse().unwrap()));
        assert!(proxies.trusts("::ffff:192.0.2.1".parse().unwrap()));
        assert!(!proxies.trusts("192.0.2.2".parse().unwrap()));
        let mut headers = HeaderMap::new();
        // The client claimed 1.1.1.1; the balancer appended what it saw, 203.0.113.7, and a
        // second proxy of ours its own hop.
        headers.append(
            "x-forwarded-for",
            HeaderValue::from_static("1.1.1.1, 203.0.113.7"),
        );
        headers.append("x-forwarded-for", HeaderValue::from_static("10.1.1.1"));
        let balancer: SocketAddr = "10.0.0.5:4000".parse().unwrap();
        assert_eq!(
            proxies.client_of_request(balancer, &headers).ip(),
            "203.0.113.7".parse::<IpAddr>().unwrap()
        );
        let stranger: SocketAddr = "198.51.100.1:4000".parse().unwrap();
        assert_eq!(proxies.client_of_request(stranger, &headers), stranger);
        assert_eq!(
            proxies.client_of_request(balancer, &HeaderMap::new()),
            balancer
        );
    }

    #[tokio::test]
    async fn a_trusted_peers_proxy_header_names_the_client_and_is_taken_off_the_stream() {
        use tokio::io::AsyncWriteExt;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let client: SocketAddr = "203.0.113.7:51000".parse().unwrap();
        let header = ppp::v2::Builder::with_addresses(
            ppp::v2::Version::Two | ppp::v2::Command::Proxy,
            ppp::v2::Protocol::Stream,
            (client, addr),
        )
        .build()
        .unwrap();
        let send = |bytes: Vec<u8>| async move {
            let mut tcp = TcpStream::connect(addr).await.unwrap();
            tcp.write_all(&bytes).await.unwrap();
            tcp
        };
        let local = TrustedProxies::parse(&["127.0.0.1".into()]).unwrap();
        let patience = Duration::from_secs(5);
        let mut after = header.clone();
        after.extend_from_slice(b"\x16\x03\x01");
        let _sender = send(after).await;
        let (mut tcp, peer) = listener.accept().await.unwrap();
        assert_eq!(
            local.client_of(&mut tcp, peer, patience).await.unwrap(),
            client
        );
        let mut rest = [0u8; 3];
        tcp.read_exact(&mut rest).await.unwrap();
        assert_eq!(&rest, b"\x16\x03\x01", "what follows the header is left");
        // Not trusted: the header is not read, the peer is the client.
        let _sender = send(header.clone()).await;
        let (mut tcp, peer) = listener.accept().await.unwrap();
        let nobody = TrustedProxies::default();
        assert_eq!(
            nobody.client_of(&mut tcp, peer, patience).await.unwrap(),
            peer
        );
        // Trusted, no header (a TLS ClientHello first): the peer, nothing consumed.
        let _sender = send(b"\x16\x03\x01\x02\x00".to_vec()).await;
        let (mut tcp, peer) = listener.accept().await.unwrap();
        assert_eq!(
            local.client_of(&mut tcp, peer, patience).await.unwrap(),
            peer
        );
        // A header begun and never finished: given up after the patience.
        let _sender = send(header[..10].to_vec()).await;
        let (mut tcp, peer) = listener.accept().await.unwrap();
        let short = Duration::from_millis(200);
        assert!(local.client_of(&mut tcp, peer, short).await.is_err());
    }
}
