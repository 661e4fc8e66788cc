//! The alarm service: one task takes what the gateway connections report
//! ([`crate::gateways::reports`]: bus events, a lift coming online or going offline) and the
//! acknowledgements of alarms only a person ends, stores the events in batches, applies [`Rules`] to an
//! index of the active alarms (so that an event costs a look-up, and the database is written
//! only when an alarm changes), runs the `lift-offline` timers, and announces every change to
//! the lift's live viewers and to the webhook outbox. It also keeps each lift's status (in
//! service, out of service, offline, unknown: docs/PORTAL.md §Availability), writing its changes
//! with the events, and applies the trend rules' verdicts. [`Alarms`] is the handle the API and
//! the web UI use.

use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, Notify};
use tokio::time::Instant;

use super::rules::{Active, Applied, Rules, Verdict};
use crate::config::WebhookSection;
use crate::gateways::reports::Report;
use crate::gateways::Registry;
use cloud_store::{EventRow, StatusRow, Store, StoreError};
use cloud_types::alarms::{Alarm, AlarmChange, Change, Kind, WebhookBody};
use cloud_types::insights::Status;
use cloud_types::live::LiftEvent;

/// Counts for `/metrics`.
#[derive(Debug, Default)]
pub struct Counters {
    /// Events stored.
    pub events_stored: AtomicU64,
    /// Events lost because the database failed (those the report queue had no room for are
    /// counted by [`crate::gateways::reports::Reports`]).
    pub events_dropped: AtomicU64,
    /// Alarms raised.
    pub raised: AtomicU64,
    /// Alarms cleared.
    pub cleared: AtomicU64,
    /// Webhook notifications delivered.
    pub webhooks_delivered: AtomicU64,
    /// Webhook attempts that failed (each is retried until given up).
    pub webhooks_failed: AtomicU64,
    /// Webhook notifications given up.
    pub webhooks_given_up: AtomicU64,
    /// Webhook notifications waiting (as of the last delivery round).
    pub webhooks_pending: AtomicU64,
}

/// An alarm of `kind` on `lift` that only a person ends was acknowledged.
#[derive(Debug, Clone, PartialEq)]
pub struct Acknowledged {
    /// The lift.
    pub lift: String,
    /// The kind.
    pub kind: Kind,
}

/// What the API, the web UI and the webhook worker share.
pub struct Alarms {
    /// The database.
    pub store: Store,
    /// Live viewers.
    pub registry: Arc<Registry>,
    /// Where acknowledgements that end an alarm go to the service.
    pub acknowledged: mpsc::Sender<Acknowledged>,
    /// Webhook receivers.
    pub webhooks: Vec<WebhookSection>,
    /// Wakes the webhook worker.
    pub outbox: Arc<Notify>,
    /// Counts.
    pub counters: Arc<Counters>,
}

/// Why an acknowledgement did not happen.
#[derive(Debug)]
pub enum AckError {
    /// No such alarm (of the caller's account).
    NotFound,
    /// It was acknowledged before.
    Already(Box<Alarm>),
    /// The database.
    Store(StoreError),
}

impl From<StoreError> for AckError {
    fn from(e: StoreError) -> Self {
        AckError::Store(e)
    }
}

impl Alarms {
    /// Acknowledge alarm `id` of a lift of `domain` for `by`.
    pub async fn acknowledge(
        &self,
        domain: &str,
        id: i64,
        by: &str,
        comment: &str,
    ) -> Result<Alarm, AckError> {
        let done = self
            .store
            .acknowledge_alarm(domain, id, by, comment, cloud_types::now_ms())
            .await?;
        let alarm = self.store.alarm_of(domain, id).await?;
        match (done, alarm) {
            (Some(true), Some(alarm)) => {
                self.announce(Change::Acknowledged, alarm.clone()).await;
                if alarm.kind.cleared_by_acknowledgement() {
                    let lift = alarm.lift.clone();
                    let kind = alarm.kind;
                    let _ = self.acknowledged.send(Acknowledged { lift, kind }).await;
                }
                Ok(alarm)
            }
            (Some(false), Some(alarm)) => Err(AckError::Already(Box::new(alarm))),
            _ => Err(AckError::NotFound),
        }
    }

    /// Tell the lift's live viewers and queue the webhook notifications.
    async fn announce(&self, change: Change, alarm: Alarm) {
        let lift = alarm.lift.clone();
        let severity = alarm.severity;
        let change = AlarmChange { change, alarm };
        self.registry
            .publish(&lift, LiftEvent::Alarm(change.clone()));
        let hooks: Vec<(usize, &WebhookSection)> = self
            .webhooks
            .iter()
            .enumerate()
            .filter(|(_, h)| severity >= h.min_severity)
            .collect();
        if hooks.is_empty() {
            return;
        }
        let account = match self.store.account_of(&lift).await {
            Ok(account) => account.unwrap_or_default(),
            Err(e) => {
                tracing::error!(error = %e, %lift, "webhook notifications not queued");
                return;
            }
        };
        let mut shown = change;
        shown.alarm.lift = cloud_types::lifts::shown_id(&lift).to_owned();
        let body = WebhookBody {
            change: shown,
            account,
        };
        let body = serde_json::to_string(&body).unwrap_or_default();
        let mut queued = false;
        for (n, hook) in hooks {
            match self
                .store
                .enqueue_webhook(&hook.url, &lift, &body, cloud_types::now_ms())
                .await
            {
                Ok(()) => queued = true,
                Err(e) => {
                    let receiver = hook
                        .name
                        .clone()
                        .unwrap_or_else(|| format!("webhook {}", n + 1));
                    tracing::error!(error = %e, %receiver, "webhook notification not queued")
                }
            }
        }
        if queued {
            self.outbox.notify_one();
        }
    }
}

/// How long a lift must stay within its storage quota (no report of it over) before its
/// `storage-quota` alarm clears.
const QUOTA_KEPT_FOR: Duration = Duration::from_secs(3600);

/// Events written at once at most, and the longest an event waits for its batch.
const BATCH: usize = 1000;
const BATCH_WAIT: Duration = Duration::from_millis(200);

/// The `lift-offline` timers, earliest first: the service asks for the next one on every
/// input, so it must not scan every offline lift of a large fleet to find it.
#[derive(Default)]
struct OfflineTimers {
    by_lift: HashMap<String, Instant>,
    by_time: BTreeSet<(Instant, String)>,
}

impl OfflineTimers {
    /// `lift` gets its alarm at `at` (replacing an earlier timer).
    fn start(&mut self, lift: String, at: Instant) {
        if let Some(old) = self.by_lift.insert(lift.clone(), at) {
            self.by_time.remove(&(old, lift.clone()));
        }
        self.by_time.insert((at, lift));
    }

    /// `lift` is back.
    fn stop(&mut self, lift: &str) {
        if let Some(at) = self.by_lift.remove(lift) {
            self.by_time.remove(&(at, lift.to_owned()));
        }
    }

    fn next(&self) -> Option<Instant> {
        self.by_time.first().map(|(at, _)| *at)
    }

    /// The lifts whose timer ran out by `now`, in order; their timers end.
    fn due(&mut self, now: Instant) -> Vec<String> {
        let mut due = Vec::new();
        while self.by_time.first().is_some_and(|(at, _)| *at <= now) {
            if let Some((_, lift)) = self.by_time.pop_first() {
                self.by_lift.remove(&lift);
                due.push(lift);
            }
        }
        due
    }
}

/// The service's state.
struct Service {
    alarms: Arc<Alarms>,
    rules: Rules,
    offline_after: Duration,
    active: Active,
    /// Lifts offline, with when they become `lift-offline`.
    offline: OfflineTimers,
    /// Lifts over their storage quota, with when their `storage-quota` alarm clears (an hour
    /// after the last report).
    over_quota: OfflineTimers,
    batch: Vec<EventRow>,
    /// Each lift's status as last written by this process, and the changes not written yet.
    statuses: HashMap<String, Status>,
    status_changes: Vec<StatusRow>,
    /// Alarms raised and cleared (id, when) since the last write.
    raised: Vec<Alarm>,
    cleared: Vec<(i64, i64)>,
    flush_at: Option<Instant>,
}

/// Run the service until every reporting connection is gone. At start it learns the active alarms and
/// starts the `lift-offline` timer of every known lift (a lift that does not come back within
/// `offline_after` of the portal's start has the alarm).
pub async fn run(
    alarms: Arc<Alarms>,
    rules: Rules,
    offline_after: Duration,
    mut reports: mpsc::Receiver<Report>,
    mut acknowledged: mpsc::Receiver<Acknowledged>,
    mut trends: mpsc::Receiver<Vec<Verdict>>,
) {
    let mut active = Active::default();
    match alarms.store.active_alarms().await {
        Ok(list) => {
            for (condition, id) in list {
                active.insert(condition, id);
            }
        }
        Err(e) => tracing::error!(error = %e, "active alarms not loaded"),
    }
    let deadline = Instant::now() + offline_after;
    let mut offline = OfflineTimers::default();
    match alarms.store.lift_ids().await {
        Ok(ids) => {
            for id in ids.into_iter().filter(|id| !alarms.registry.online(id)) {
                offline.start(id, deadline);
            }
        }
        Err(e) => tracing::error!(error = %e, "lifts not loaded for the offline alarms"),
    }
    let mut service = Service {
        alarms,
        rules,
        offline_after,
        active,
        offline,
        over_quota: OfflineTimers::default(),
        batch: Vec::with_capacity(BATCH),
        statuses: HashMap::new(),
        status_changes: Vec::new(),
        raised: Vec::new(),
        cleared: Vec::new(),
        flush_at: None,
    };
    let mut received = Vec::with_capacity(BATCH);
    loop {
        let next = service
            .offline
            .next()
            .into_iter()
            .chain(service.over_quota.next())
            .chain(service.flush_at)
            .min();
        tokio::select! {
            n = reports.recv_many(&mut received, BATCH) => {
                if n == 0 {
                    service.flush().await;
                    return;
                }
                service.reports(&mut received).await;
            },
            Some(Acknowledged { lift, kind }) = acknowledged.recv() => {
                let verdict = service.rules.acknowledged(&lift, kind);
                service.apply(vec![verdict]);
            }
            Some(verdicts) = trends.recv() => service.apply(verdicts),
            _ = tokio::time::sleep_until(next.unwrap_or_else(Instant::now)), if next.is_some() => {
                service.timers().await
            }
        }
    }
}

impl Service {
    /// `received` in order, a run of lifts coming online at once (a reconnect storm) as one.
    async fn reports(&mut self, received: &mut Vec<Report>) {
        let mut online = Vec::new();
        for report in received.drain(..) {
            match report {
                Report::Online(lift) => online.push(lift),
                other => {
                    self.online(std::mem::take(&mut online)).await;
                    self.report(other).await;
                }
            }
        }
        self.online(online).await;
    }

    async fn online(&mut self, lifts: Vec<String>) {
        if lifts.is_empty() {
            return;
        }
        let now = cloud_types::now_ms();
        for lift in &lifts {
            self.offline.stop(lift);
            self.status(lift, Status::Unknown, now);
        }
        self.refresh_in_cluster(&lifts).await;
        let verdicts = lifts.iter().map(|lift| self.rules.lift_online(lift));
        let verdicts = verdicts.collect();
        self.apply(verdicts);
    }

    async fn report(&mut self, report: Report) {
        match report {
            Report::Event { lift, event } => {
                let verdicts = self.rules.event(&lift, &event);
                self.batch.push(EventRow {
                    at: event.time_ms().unwrap_or_else(cloud_types::now_ms),
                    kind: event.kind().name().to_owned(),
                    body: serde_json::to_string(&event).unwrap_or_default(),
                    lift,
                });
                self.flush_at.get_or_insert(Instant::now() + BATCH_WAIT);
                self.apply(verdicts);
                if self.batch.len() >= BATCH {
                    self.flush().await;
                }
            }
            Report::Online(lift) => self.online(vec![lift]).await,
            Report::Offline(lift) => {
                self.status(&lift, Status::Offline, cloud_types::now_ms());
                self.offline
                    .start(lift, Instant::now() + self.offline_after);
            }
            Report::Service {
                lift,
                in_service,
                at,
            } => {
                let status = if in_service {
                    Status::InService
                } else {
                    Status::OutOfService
                };
                self.status(&lift, status, at);
            }
            Report::BoardChanged { lift, was, now } => {
                let verdict = self.rules.board_changed(&lift, &was, &now);
                self.apply(vec![verdict]);
            }
            Report::OverQuota { lift, dropped } => {
                let verdict = self.rules.storage_quota(&lift, dropped);
                self.over_quota.start(lift, Instant::now() + QUOTA_KEPT_FOR);
                self.apply(vec![verdict]);
            }
        }
    }

    /// `lift` is `status` from `at` on: written with the next batch when it changed.
    fn status(&mut self, lift: &str, status: Status, at: i64) {
        if self.statuses.get(lift) == Some(&status) {
            return;
        }
        self.statuses.insert(lift.to_owned(), status);
        self.status_changes.push(StatusRow {
            lift: lift.to_owned(),
            at,
            status,
        });
        self.flush_at.get_or_insert(Instant::now() + BATCH_WAIT);
    }

    async fn timers(&mut self) {
        let now = Instant::now();
        if self.flush_at.is_some_and(|t| t <= now) {
            self.flush().await;
        }
        for lift in self.offline.due(now) {
            // Online again by now, perhaps on another process of a cluster (whose alarm
            // service saw it come back): no alarm.
            if self.alarms.registry.online(&lift) {
                continue;
            }
            self.refresh_in_cluster(std::slice::from_ref(&lift)).await;
            let verdict = self.rules.lift_offline(&lift, self.offline_after.as_secs());
            self.apply(vec![verdict]);
        }
        for lift in self.over_quota.due(now) {
            let verdict = self.rules.storage_quota_kept(&lift);
            self.apply(vec![verdict]);
        }
    }

    /// Write the events and alarm changes gathered; announce the changes once stored. When the
    /// database fails the events are dropped (counted) and the alarm changes kept for the next
    /// attempt.
    async fn flush(&mut self) {
        self.flush_at = None;
        if self.batch.is_empty()
            && self.status_changes.is_empty()
            && self.raised.is_empty()
            && self.cleared.is_empty()
        {
            return;
        }
        let counters = &self.alarms.counters;
        let written = self
            .alarms
            .store
            .write_alarm_batch(
                &self.batch,
                &self.status_changes,
                &self.raised,
                &self.cleared,
            )
            .await;
        let events = std::mem::take(&mut self.batch).len() as u64;
        let (new, cleared) = match written {
            Ok(written) => written,
            Err(e) => {
                tracing::error!(error = %e, events, "events and alarm changes not stored");
                counters.events_dropped.fetch_add(events, Ordering::Relaxed);
                self.flush_at = Some(Instant::now() + BATCH_WAIT);
                return;
            }
        };
        counters.events_stored.fetch_add(events, Ordering::Relaxed);
        self.cleared.clear();
        self.status_changes.clear();
        let mut raised_elsewhere = Vec::new();
        for (alarm, new) in std::mem::take(&mut self.raised).into_iter().zip(new) {
            if !new {
                // Another process of the cluster raised it first: its alarm is the one.
                raised_elsewhere.push(alarm.lift);
                continue;
            }
            tracing::warn!(lift = %alarm.lift, kind = alarm.kind.name(), code = %alarm.code, severity = %alarm.severity, text = %alarm.text, "alarm raised");
            counters.raised.fetch_add(1, Ordering::Relaxed);
            self.alarms.announce(Change::Raised, alarm).await;
        }
        for alarm in cleared {
            tracing::info!(lift = %alarm.lift, kind = alarm.kind.name(), code = %alarm.code, "alarm cleared");
            counters.cleared.fetch_add(1, Ordering::Relaxed);
            self.alarms.announce(Change::Cleared, alarm).await;
        }
        if !raised_elsewhere.is_empty() {
            self.refresh(&raised_elsewhere).await;
        }
    }

    /// In a cluster, before deciding about `lifts`: their active alarms as the database has
    /// them (another process may have raised or cleared some while it held a lift), with what
    /// is waiting here written first.
    async fn refresh_in_cluster(&mut self, lifts: &[String]) {
        if self.alarms.registry.cluster().is_some() {
            self.flush().await;
            self.refresh(lifts).await;
        }
    }

    async fn refresh(&mut self, lifts: &[String]) {
        match self.alarms.store.active_alarms_of(lifts).await {
            Ok(active) => {
                let mut of: HashMap<&str, Vec<_>> = lifts
                    .iter()
                    .map(|lift| (lift.as_str(), Vec::new()))
                    .collect();
                for (condition, id) in active {
                    if let Some(list) = of.get_mut(condition.lift.as_str()) {
                        list.push((condition, id));
                    }
                }
                for (lift, active) in of {
                    self.active.replace_lift(lift, active);
                }
            }
            Err(e) => {
                tracing::warn!(lifts = lifts.len(), error = %e, "active alarms not read: deciding on what this process knows")
            }
        }
    }

    /// Update the index of active alarms; the changes wait for the next write.
    fn apply(&mut self, verdicts: Vec<Verdict>) {
        let now = cloud_types::now_ms();
        for verdict in verdicts {
            match self.active.apply(verdict, cloud_store::new_id) {
                Applied::Raised {
                    id,
                    condition,
                    severity,
                    text,
                } => {
                    let alarm = Alarm::raised(id, &condition, severity, &text, now);
                    self.raised.push(alarm);
                }
                Applied::Cleared(ids) => self.cleared.extend(ids.into_iter().map(|id| (id, now))),
                Applied::Unchanged => {}
            }
        }
        if !self.raised.is_empty() || !self.cleared.is_empty() {
            self.flush_at.get_or_insert(Instant::now() + BATCH_WAIT);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offline_timers_run_out_in_order_and_stop_when_a_lift_returns() {
        let t0 = Instant::now();
        let s = Duration::from_secs(1);
        let mut timers = OfflineTimers::default();
        assert_eq!(timers.next(), None);
        timers.start("b".into(), t0 + 2 * s);
        timers.start("a".into(), t0 + 3 * s);
        timers.start("c".into(), t0 + s);
        timers.start("a".into(), t0 + s / 2); // restarted: the earlier timer is gone
        assert_eq!(timers.next(), Some(t0 + s / 2));
        timers.stop("c");
        timers.stop("unknown");
        assert_eq!(timers.due(t0), Vec::<String>::new());
        assert_eq!(timers.due(t0 + 5 * s), ["a", "b"]);
        assert_eq!(timers.next(), None);
        assert!(timers.by_lift.is_empty());
    }
}
