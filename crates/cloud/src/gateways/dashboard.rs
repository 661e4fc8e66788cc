//! What every gateway is asked as it connects: the bus events the alarms are made of
//! (`[dashboard] events`; a gateway that does not know the method has none); then every subscription held on its lift — the
//! dashboard's objects (`[dashboard] live`) and whatever accounts and live watchers hold
//! (see `subscriptions`).

use std::sync::Arc;

use nxg::codes::rpc_codes;
use nxg::msg::{Lang, RegEventParams};
use nxg::portal::Failure;

use super::subscriptions::Subscriptions;
use super::Registry;
use crate::config::Dashboard;

/// Ask a newly connected gateway for the bus events and the subscriptions held on its lift
/// (users' among them when `subscribed`: the admission saw some in the database).
pub(super) async fn subscribe(
    registry: Arc<Registry>,
    subscriptions: Arc<Subscriptions>,
    lift: String,
    dashboard: Arc<Dashboard>,
    subscribed: bool,
) {
    // Both at once: a gateway that leaves the events unanswered does not hold up its values.
    tokio::join!(
        register_events(&registry, &lift, &dashboard),
        subscriptions.resubscribe(&lift, subscribed),
    );
}

/// Bus events are asked for by name, whatever the api in force: an NXg gateway that does not
/// have them answers −32601 like any unknown method (docs/PROTOCOL.md §Events).
async fn register_events(registry: &Registry, lift: &str, dashboard: &Dashboard) {
    if dashboard.events.is_empty() {
        return;
    }
    let events = RegEventParams {
        events: dashboard.events.clone(),
        lang: Some(Lang::new("en", "en")),
    };
    match registry.call(lift, &events).await {
        Ok(_) => {}
        Err(Failure::Error(e)) if e.code == rpc_codes::METHOD_NOT_FOUND => {
            tracing::debug!(%lift, "the gateway offers no bus events");
        }
        Err(e) => tracing::warn!(%lift, failure = %e, "bus events not registered"),
    }
}
