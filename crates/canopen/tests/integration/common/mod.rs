//! Helpers shared by the node and master integration tests.

use std::time::Duration;

use canopen::master::MasterEvent;
use canopen::sdo::client::ClientConfig;
use tokio::sync::broadcast;

/// How long a test waits for an event.
pub const WAIT: Duration = Duration::from_secs(3);

/// The next master event matching `pred`, within [`WAIT`].
pub async fn master_event(
    events: &mut broadcast::Receiver<MasterEvent>,
    pred: impl Fn(&MasterEvent) -> bool,
) -> MasterEvent {
    tokio::time::timeout(WAIT, async {
        loop {
            if let Ok(e) = events.recv().await {
                if pred(&e) {
                    return e;
                }
            }
        }
    })
    .await
    .expect("event in time")
}

/// An SDO client configuration with a short timeout, for tests that expect timeouts.
pub fn client_config() -> ClientConfig {
    ClientConfig {
        timeout: Duration::from_millis(300),
        ..ClientConfig::default()
    }
}
