//! The dashboard's subscriptions: every gateway is asked, as it connects, to push the objects
//! the portal stores as telemetry and shows live (`[dashboard] live`) and, when it speaks api
//! 2, the bus events the alarms are made of (`[dashboard] events`).

use std::sync::Arc;

use nxg::msg::{Lang, MplexText, RegEventParams, RegParams};
use nxg::portal::Failure;

use super::Registry;
use crate::config::Dashboard;

/// Ask a newly connected gateway to push the dashboard's objects, the way an operator would.
/// `reg_canopen_object` is all or none (NXg §7.1): when one object is missing on this lift the
/// others are registered one by one.
pub(super) async fn subscribe(
    registry: Arc<Registry>,
    lift: String,
    dashboard: Arc<Dashboard>,
    api: u32,
) {
    if api >= 2 && !dashboard.events.is_empty() {
        let events = RegEventParams {
            events: dashboard.events.clone(),
            lang: Some(Lang::new("en", "en")),
        };
        if let Err(e) = registry.call(&lift, &events).await {
            tracing::warn!(%lift, failure = ?e, "bus events not registered");
        }
    }
    if dashboard.live.is_empty() {
        return;
    }
    let params = |mplex: Vec<MplexText>| RegParams {
        mplex,
        inhibit: dashboard.inhibit_ms,
        threshold: 0.0,
        node: None,
    };
    let all = params(dashboard.live.iter().map(|m| (*m).into()).collect());
    match registry.call(&lift, &all).await {
        Ok(_) => return,
        Err(Failure::Error(_)) => {}
        Err(other) => {
            tracing::debug!(%lift, failure = ?other, "dashboard objects not subscribed");
            return;
        }
    }
    for mplex in &dashboard.live {
        if let Err(e) = registry.call(&lift, &params(vec![(*mplex).into()])).await {
            tracing::debug!(%lift, %mplex, failure = ?e, "dashboard object not subscribed");
        }
    }
}
