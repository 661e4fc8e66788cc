//! Requests for lifts another process holds: relayed on the lift's own subject to its holder,
//! which answers through its [`crate::Local`].

use std::sync::atomic::Ordering;

use nxg::portal::Failure;

use crate::msgs::{self, Relayed, RelayedAnswer};
use crate::Cluster;

impl Cluster {
    /// Send a request to the process held `lift`, and wait for its answer: no holder (or
    /// no NATS) is [`Failure::Gone`] (503), no answer in time [`Failure::Timeout`].
    pub async fn request(&self, lift: &str, relayed: &Relayed) -> Result<String, Failure> {
        self.counters.relayed.fetch_add(1, Ordering::Relaxed);
        let outcome = self.relay(lift, relayed).await;
        if matches!(outcome, Err(Failure::Gone | Failure::Timeout)) {
            self.counters.relay_failed.fetch_add(1, Ordering::Relaxed);
        }
        outcome
    }

    pub(crate) async fn relay(&self, lift: &str, relayed: &Relayed) -> Result<String, Failure> {
        if !self.connected() {
            return Err(Failure::Gone);
        }
        let payload = serde_json::to_vec(relayed).map_err(|e| Failure::Invalid(e.to_string()))?;
        let request = async_nats::Request::new()
            .payload(payload.into())
            .timeout(Some(self.request_timeout));
        let reply = self
            .client
            .send_request(msgs::rpc_subject(lift), request)
            .await
            .map_err(|e| match e.kind() {
                async_nats::client::RequestErrorKind::TimedOut => Failure::Timeout,
                _ => Failure::Gone,
            })?;
        serde_json::from_slice::<RelayedAnswer>(&reply.payload)
            .map_err(|e| Failure::Invalid(format!("the holder's answer: {e}")))?
            .outcome()
    }
}
