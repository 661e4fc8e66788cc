//! Webhooks (docs/PORTAL.md §Webhooks): every alarm change at or above a receiver's
//! `min_severity` is queued in the database (so a portal restart loses nothing undelivered) and
//! POSTed as JSON, signed as the Standard Webhooks specification says (`webhook-id`,
//! `webhook-timestamp`, `webhook-signature: v1,<base64 HMAC-SHA256 of id.timestamp.body>`): a
//! receiver that refuses deliveries older than a few minutes cannot be fed a recorded one
//! again. A failed attempt (no connection, no 2xx answer in time) is tried again after 1 s,
//! 2 s, 4 s … at most 10 min apart, and given up three days after the change. Every attempt is
//! counted in `/metrics` and written to the audit log under the receiver's name — never its
//! URL, whose credentials and internal host names are no business of the account's viewers.
//!
//! `https://` receivers are checked against the system's roots or the receiver's `ca_file`;
//! `http://` is allowed only to receivers on this host or its network (loopback, private and
//! link-local addresses), where nothing on the way can read or change the notification.

use std::net::IpAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use http_body_util::Full;
use hyper::body::Bytes;
use tokio::net::TcpStream;

use super::service::{Alarms, Counters};
use crate::config::WebhookSection;
use crate::outbound::{Https, Target};
use cloud_types::audit::AuditEntry;

use cloud_store::{OutboxEntry, Store};

/// What is read of a receiver's answer.
const ANSWER_LIMIT: usize = 64 * 1024;
/// How long one attempt may take.
const ATTEMPT: Duration = Duration::from_secs(10);
/// The longest wait between attempts.
const LONGEST_WAIT: Duration = Duration::from_secs(600);
/// After this long a notification is given up.
const GIVE_UP: Duration = Duration::from_secs(3 * 24 * 3600);

/// The signing key of `secret` (Standard Webhooks): a `whsec_` secret is base64 of the key's
/// bytes; any other text is the key's bytes itself.
fn signing_key(secret: &str) -> Vec<u8> {
    use base64::Engine;
    secret
        .strip_prefix("whsec_")
        .and_then(|b| base64::engine::general_purpose::STANDARD.decode(b).ok())
        .unwrap_or_else(|| secret.as_bytes().to_vec())
}

/// The `webhook-signature` of message `id` sent at `timestamp` (s since the epoch) with
/// `body`, under `secret`: `v1,` and the base64 HMAC-SHA256 of `id.timestamp.body`.
pub fn signature(secret: &str, id: &str, timestamp: u64, body: &[u8]) -> String {
    use base64::Engine;
    let key = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, &signing_key(secret));
    let mut context = ring::hmac::Context::with_key(&key);
    context.update(format!("{id}.{timestamp}.").as_bytes());
    context.update(body);
    let tag = context.sign();
    format!(
        "v1,{}",
        base64::engine::general_purpose::STANDARD.encode(tag.as_ref())
    )
}

/// A receiver ready to be posted to.
pub struct Receiver {
    section: WebhookSection,
    /// What the audit log and the logs call it.
    name: String,
    https: Https,
}

impl Receiver {
    /// Prepare `section`, the `n`th receiver (from 1): its URL must be
    /// `http(s)://[USER:PASSWORD@]HOST[:PORT]/PATH`, its CA file readable.
    pub fn new(section: &WebhookSection, n: usize) -> Result<Receiver, String> {
        let name = section
            .name
            .clone()
            .unwrap_or_else(|| format!("webhook {n}"));
        Target::parse(&section.url).map_err(|e| format!("alarms.webhooks {name}: {e}"))?;
        let https = Https::new(section.ca_file.as_deref())
            .map_err(|e| format!("alarms.webhooks {name}: {e}"))?;
        Ok(Receiver {
            section: section.clone(),
            name,
            https,
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

/// POST `body`, the notification `id`, to the receiver; the HTTP status, or why there is
/// none — in words that name neither the receiver's address nor its URL.
async fn post(receiver: &Receiver, id: i64, body: &str) -> Result<u16, String> {
    let target = Target::parse(&receiver.section.url)?;
    // An http:// receiver is reached straight, and only on this host or its network; an
    // https:// one through HTTPS_PROXY unless NO_PROXY names it.
    let tcp = match target.https {
        true => None,
        false => {
            let addresses: Vec<_> = tokio::net::lookup_host((target.host.as_str(), target.port))
                .await
                .map_err(|e| format!("its host name did not resolve: {e}"))?
                .collect();
            if !addresses.iter().all(|a| nearby(a.ip())) {
                return Err(
                    "http:// only to a receiver on this host or its network; use https://".into(),
                );
            }
            let tcp = TcpStream::connect(&addresses[..])
                .await
                .map_err(|e| format!("no connection: {}", e.kind()))?;
            Some(tcp)
        }
    };
    let message = format!("msg_{id}");
    let timestamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let signature = signature(
        &receiver.section.secret,
        &message,
        timestamp,
        body.as_bytes(),
    );
    let mut request = hyper::Request::post(&target.path)
        .header("host", &target.host)
        .header("content-type", "application/json")
        .header("user-agent", concat!("canlift/", env!("CARGO_PKG_VERSION")))
        .header("webhook-id", &message)
        .header("webhook-timestamp", timestamp.to_string())
        .header("webhook-signature", signature);
    if let Some(basic) = &target.basic {
        request = request.header("authorization", basic);
    }
    let request = request
        .body(Full::new(Bytes::from(body.to_owned())))
        .map_err(|e| e.to_string())?;
    // What a receiver answers beyond its status is read (up to a bound) and dropped.
    let answer = receiver
        .https
        .send(&target, tcp, request, ANSWER_LIMIT)
        .await?;
    Ok(answer.status)
}

/// The wait before attempt `n + 1` after `n` failed ones: 1 s doubling, at most 10 min.
fn backoff(attempts: u32) -> Duration {
    Duration::from_secs(1u64 << attempts.min(10)).min(LONGEST_WAIT)
}

/// One attempt at `entry`, recorded in the outbox, the counters, the attempts' timer and the
/// audit log.
async fn attempt(
    store: &Store,
    counters: &Counters,
    timer: &crate::metrics::Timer,
    receiver: &Receiver,
    entry: &OutboxEntry,
) {
    let started = std::time::Instant::now();
    let result = tokio::time::timeout(ATTEMPT, post(receiver, entry.id, &entry.body))
        .await
        .unwrap_or_else(|_| Err(format!("no answer within {} s", ATTEMPT.as_secs())));
    let delivered = matches!(result, Ok(status) if (200..300).contains(&status));
    timer.observe(
        if delivered { "delivered" } else { "failed" },
        started.elapsed(),
    );
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
                tracing::error!(receiver = %receiver.name, %error, "webhook notification given up");
            } else {
                tracing::warn!(receiver = %receiver.name, %error, attempts = entry.attempts + 1, "webhook attempt failed; will retry");
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
        object: receiver.name.clone(),
        old_value: None,
        new_value: change,
        result: audit,
        address: None,
    };
    if let Err(e) = store.audit(&entry).await {
        tracing::error!(error = %e, "webhook attempt not audited");
    }
}

/// Deliver queued notifications until the portal stops: whenever something was queued, and
/// whenever the next retry is due.
pub async fn deliver(alarms: Arc<Alarms>, receivers: Vec<Receiver>, timer: crate::metrics::Timer) {
    let store = &alarms.store;
    let counters = &alarms.counters;
    loop {
        match store.due_webhooks(cloud_types::now_ms(), 100).await {
            Ok(due) => {
                for entry in &due {
                    match receivers.iter().find(|r| r.section.url == entry.url) {
                        Some(receiver) => attempt(store, counters, &timer, receiver, entry).await,
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
    fn signatures_are_standard_webhooks() {
        // The specification's example (standard-webhooks/spec, its test vectors).
        assert_eq!(
            signature(
                "whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw",
                "msg_p5jXN8AQM9LWM0D4loKWxJek",
                1614265330,
                br#"{"test": 2432232314}"#
            ),
            "v1,g0hM9SsE+OTPJTGt/tmIKtSyZlE3uFJELVlNIOLJ1OE="
        );
        // Any other text is the key's bytes.
        assert_ne!(
            signature("Jefe", "m", 1, b"x"),
            signature("Jefd", "m", 1, b"x")
        );
    }

    #[test]
    fn nearby_receivers_and_backoff() {
        assert!(nearby("10.1.2.3".parse().unwrap()));
        assert!(nearby("fe80::1".parse().unwrap()));
        assert!(!nearby("8.8.8.8".parse().unwrap()));
        assert_eq!(backoff(0), Duration::from_secs(1));
        assert_eq!(backoff(30), LONGEST_WAIT);
    }
}
