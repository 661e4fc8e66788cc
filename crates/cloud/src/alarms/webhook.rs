//! Webhooks (docs/PORTAL.md §Webhooks): every alarm change at or above a receiver's
//! `min_severity` is queued in the database (so a portal restart loses nothing undelivered) and
//! POSTed as JSON with `X-Canlift-Signature: sha256=<hex HMAC-SHA256 of the body>` — the scheme
//! receivers know from code-hosting webhooks. A failed attempt (no connection, no 2xx answer in
//! time) is tried again after 1 s, 2 s, 4 s … at most 10 min apart, and given up three days
//! after the change. Every attempt is counted in `/metrics` and written to the audit log.
//!
//! `https://` receivers are checked against the system's roots or the receiver's `ca_file`;
//! `http://` is allowed only to receivers on this host or its network (loopback, private and
//! link-local addresses), where nothing on the way can read or change the notification.

use std::net::IpAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use tokio::net::TcpStream;

use super::service::{Alarms, Counters};
use crate::config::WebhookSection;
use cloud_types::audit::AuditEntry;

use cloud_store::{OutboxEntry, Store};

/// How long one attempt may take.
const ATTEMPT: Duration = Duration::from_secs(10);
/// The longest wait between attempts.
const LONGEST_WAIT: Duration = Duration::from_secs(600);
/// After this long a notification is given up.
const GIVE_UP: Duration = Duration::from_secs(3 * 24 * 3600);

/// The signature header's value for `body` under `secret`.
pub fn signature(secret: &str, body: &[u8]) -> String {
    let key = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, secret.as_bytes());
    format!("sha256={}", hex::encode(ring::hmac::sign(&key, body)))
}

/// A receiver ready to be posted to.
pub struct Receiver {
    section: WebhookSection,
    tls: tokio_rustls::TlsConnector,
}

impl Receiver {
    /// Prepare `section`: its URL must be `http(s)://HOST[:PORT]/PATH`, its CA file readable.
    pub fn new(section: &WebhookSection) -> Result<Receiver, String> {
        Target::parse(&section.url)?;
        let tls = tls::client_config(section.ca_file.as_deref(), None)
            .map_err(|e| format!("alarms.webhooks {}: {e}", section.url))?;
        let mut tls = Arc::unwrap_or_clone(tls);
        tls.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(Receiver {
            section: section.clone(),
            tls: tokio_rustls::TlsConnector::from(Arc::new(tls)),
        })
    }
}

/// Where a URL points.
struct Target {
    https: bool,
    host: String,
    port: u16,
    path: String,
}

impl Target {
    fn parse(url: &str) -> Result<Target, String> {
        let uri: hyper::Uri = url
            .parse()
            .map_err(|e| format!("webhook URL {url:?}: {e}"))?;
        let https = match uri.scheme_str() {
            Some("https") => true,
            Some("http") => false,
            _ => return Err(format!("webhook URL {url:?}: http:// or https://")),
        };
        let host = uri
            .host()
            .ok_or_else(|| format!("webhook URL {url:?}: no host"))?
            .trim_matches(['[', ']'])
            .to_owned();
        Ok(Target {
            https,
            port: uri.port_u16().unwrap_or(if https { 443 } else { 80 }),
            path: uri
                .path_and_query()
                .map_or_else(|| "/".to_owned(), |p| p.as_str().to_owned()),
            host,
        })
    }
}

/// Whether `ip` is on this host or its network.
fn nearby(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => v4.is_loopback() || v4.is_private() || v4.is_link_local(),
        IpAddr::V6(v6) => {
            v6.is_loopback()
                || (v6.segments()[0] & 0xFE00) == 0xFC00
                || (v6.segments()[0] & 0xFFC0) == 0xFE80
        }
    }
}

/// POST `body` to the receiver; the HTTP status, or why there is none.
async fn post(receiver: &Receiver, id: i64, body: &str) -> Result<u16, String> {
    let target = Target::parse(&receiver.section.url)?;
    let addresses: Vec<_> = tokio::net::lookup_host((target.host.as_str(), target.port))
        .await
        .map_err(|e| format!("{}: {e}", target.host))?
        .collect();
    if !target.https && !addresses.iter().all(|a| nearby(a.ip())) {
        return Err(format!(
            "{}: http:// only to a receiver on this host or its network; use https://",
            target.host
        ));
    }
    let tcp = TcpStream::connect(&addresses[..])
        .await
        .map_err(|e| format!("{}:{}: {e}", target.host, target.port))?;
    let _ = tcp.set_nodelay(true);
    let request = hyper::Request::post(&target.path)
        .header("host", &target.host)
        .header("content-type", "application/json")
        .header("user-agent", concat!("canlift/", env!("CARGO_PKG_VERSION")))
        .header(
            "x-canlift-signature",
            signature(&receiver.section.secret, body.as_bytes()),
        )
        .header("x-canlift-delivery", id.to_string())
        .body(Full::new(Bytes::from(body.to_owned())))
        .map_err(|e| e.to_string())?;
    if target.https {
        let name = rustls::pki_types::ServerName::try_from(target.host.clone())
            .map_err(|e| e.to_string())?;
        let tls = receiver
            .tls
            .connect(name, tcp)
            .await
            .map_err(|e| format!("TLS with {}: {e}", target.host))?;
        send(tls, request).await
    } else {
        send(tcp, request).await
    }
}

async fn send<S>(stream: S, request: hyper::Request<Full<Bytes>>) -> Result<u16, String>
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
    // The answer's body is read and dropped, up to where the connection closes.
    let _ = response.into_body().collect().await;
    Ok(status)
}

/// The wait before attempt `n + 1` after `n` failed ones: 1 s doubling, at most 10 min.
fn backoff(attempts: u32) -> Duration {
    Duration::from_secs(1u64 << attempts.min(10)).min(LONGEST_WAIT)
}

/// One attempt at `entry`, recorded in the outbox, the counters and the audit log.
async fn attempt(store: &Store, counters: &Counters, receiver: &Receiver, entry: &OutboxEntry) {
    let result = tokio::time::timeout(ATTEMPT, post(receiver, entry.id, &entry.body))
        .await
        .unwrap_or_else(|_| Err(format!("no answer within {} s", ATTEMPT.as_secs())));
    let now = cloud_types::now_ms();
    let (outcome, audit) = match &result {
        Ok(status) if (200..300).contains(status) => {
            counters.webhooks_delivered.fetch_add(1, Ordering::Relaxed);
            (Ok(()), format!("ok {status}"))
        }
        failed => {
            let error = match failed {
                Ok(status) => format!("HTTP {status}"),
                Err(e) => e.clone(),
            };
            counters.webhooks_failed.fetch_add(1, Ordering::Relaxed);
            let next = now + i64::try_from(backoff(entry.attempts).as_millis()).unwrap_or(i64::MAX);
            let expired =
                now - entry.created > i64::try_from(GIVE_UP.as_millis()).unwrap_or(i64::MAX);
            if expired {
                counters.webhooks_given_up.fetch_add(1, Ordering::Relaxed);
                tracing::error!(url = %receiver.section.url, %error, "webhook notification given up");
            } else {
                tracing::warn!(url = %receiver.section.url, %error, attempts = entry.attempts + 1, "webhook attempt failed; will retry");
            }
            let outcome = Err((error.clone(), (!expired).then_some(next)));
            (outcome, error)
        }
    };
    let outcome = match &outcome {
        Ok(()) => Ok(()),
        Err((e, next)) => Err((e.as_str(), *next)),
    };
    if let Err(e) = store.webhook_attempt(entry.id, now, outcome).await {
        tracing::error!(error = %e, "webhook attempt not recorded");
    }
    let change = serde_json::from_str::<cloud_types::alarms::AlarmChange>(&entry.body)
        .map(|c| format!("{} alarm {}", c.change.name(), c.alarm.id))
        .unwrap_or_default();
    let entry = AuditEntry {
        at: now,
        account: "portal".into(),
        lift: entry.lift.clone(),
        action: "webhook".into(),
        object: receiver.section.url.clone(),
        old_value: None,
        new_value: change,
        result: audit,
    };
    if let Err(e) = store.audit(&entry).await {
        tracing::error!(error = %e, "webhook attempt not audited");
    }
}

/// Deliver queued notifications until the portal stops: whenever something was queued, and
/// whenever the next retry is due.
pub async fn deliver(alarms: Arc<Alarms>, receivers: Vec<Receiver>) {
    let store = &alarms.store;
    let counters = &alarms.counters;
    loop {
        match store.due_webhooks(cloud_types::now_ms(), 100).await {
            Ok(due) => {
                for entry in &due {
                    match receivers.iter().find(|r| r.section.url == entry.url) {
                        Some(receiver) => attempt(store, counters, receiver, entry).await,
                        None => {
                            // The receiver left the configuration: nothing to deliver to.
                            let gone = Err(("receiver no longer configured", None));
                            let _ = store
                                .webhook_attempt(entry.id, cloud_types::now_ms(), gone)
                                .await;
                        }
                    }
                }
            }
            Err(e) => tracing::error!(error = %e, "webhook outbox unreadable"),
        }
        if let Ok(pending) = store.pending_webhooks().await {
            counters
                .webhooks_pending
                .store(u64::try_from(pending).unwrap_or(0), Ordering::Relaxed);
        }
        let wait = match store.next_webhook_due().await {
            Ok(Some(at)) => {
                Duration::from_millis(u64::try_from(at - cloud_types::now_ms()).unwrap_or(0))
            }
            _ => LONGEST_WAIT,
        };
        tokio::select! {
            _ = alarms.outbox.notified() => {}
            _ = tokio::time::sleep(wait.min(LONGEST_WAIT)) => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signatures_are_hmac_sha256_of_the_body() {
        // RFC 4231 test case 2.
        assert_eq!(
            signature("Jefe", b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }

    #[test]
    fn urls_and_nearby_receivers() {
        let t = Target::parse("http://127.0.0.1:9000/hook?x=1").unwrap();
        assert_eq!(
            (t.https, t.port, t.path.as_str()),
            (false, 9000, "/hook?x=1")
        );
        assert_eq!(Target::parse("https://example.com").unwrap().port, 443);
        assert!(Target::parse("ftp://x/").is_err());
        assert!(nearby("10.1.2.3".parse().unwrap()));
        assert!(nearby("fe80::1".parse().unwrap()));
        assert!(!nearby("8.8.8.8".parse().unwrap()));
        assert_eq!(backoff(0), Duration::from_secs(1));
        assert_eq!(backoff(30), LONGEST_WAIT);
    }
}
