//! What every gateway is asked as it connects: when it speaks api 2, the bus events the alarms
//! are made of (`[dashboard] events`); then every subscription held on its lift — the
//! dashboard's objects (`[dashboard] live`) and whatever accounts and live watchers hold
//! (see `subscriptions`).

use std::sync::Arc;

use nxg::msg::{Lang, RegEventParams};

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
    api: u32,
    subscribed: bool,
) {
    if api >= 2 && !dashboard.events.is_empty() {
        let events = RegEventParams {
            events: dashboard.events.clone(),
            lang: Some(Lang::new("en", "en")),
        };
        if let Err(e) = registry.call(&lift, &events).await {
            tracing::warn!(%lift, failure = %e, "bus events not registered");
        }
    }
    subscriptions.resubscribe(&lift, subscribed).await;
}
