//! Gateways on their WebSocket: one task per connection runs a [`PortalSession`], checks the
//! identity against the [`Store`], issues tokens, answers operator requests through the
//! [`Registry`] and stores and fans out notifications. A second connection with a valid token
//! replaces the first; a gateway that misbehaves is closed without touching the others.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use axum::extract::ws::{Message, WebSocket};
use nxg::portal::{Failure, PortalOutput, PortalSession, PortalSettings, RequestId};
use serde_json::{json, Value};
use tokio::sync::{broadcast, mpsc, oneshot};

use crate::config::DashboardSection;
use crate::store::{self, Admission, Store};

/// An event for live viewers of a lift.
#[derive(Debug, Clone, PartialEq)]
pub enum LiftEvent {
    /// A pushed value: the notification's payload.
    Value(Value),
    /// The gateway came online or went offline.
    Online(bool),
}

/// An operator request on its way to a gateway.
pub struct Call {
    method: String,
    params: Value,
    reply: oneshot::Sender<Result<Value, Failure>>,
}

struct Live {
    calls: mpsc::Sender<Box<Call>>,
    close: oneshot::Sender<()>,
    serial: u64,
    sernum: String,
}

/// The gateways connected now, and the event channels of every lift.
#[derive(Default)]
pub struct Registry {
    live: Mutex<HashMap<String, Live>>,
    events: Mutex<HashMap<String, broadcast::Sender<LiftEvent>>>,
    serial: std::sync::atomic::AtomicU64,
}

impl Registry {
    /// Whether the lift's gateway is connected.
    pub fn online(&self, lift: &str) -> bool {
        self.live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .contains_key(lift)
    }

    /// How many gateways are connected.
    pub fn online_count(&self) -> usize {
        self.live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }

    /// The serial number of a connected gateway (sent with puts and elevations).
    pub fn sernum(&self, lift: &str) -> Option<String> {
        self.live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(lift)
            .map(|l| l.sernum.clone())
    }

    /// Live events of a lift.
    pub fn subscribe(&self, lift: &str) -> broadcast::Receiver<LiftEvent> {
        self.events
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(lift.to_owned())
            .or_insert_with(|| broadcast::channel(1024).0)
            .subscribe()
    }

    /// Hand `event` to the lift's live viewers. A channel exists only while someone watches
    /// (its 1024 slots are allocated up front: one per idle gateway would cost more than the
    /// connection itself).
    fn publish(&self, lift: &str, event: LiftEvent) {
        let mut events = self.events.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(tx) = events.get(lift) {
            if tx.send(event).is_err() {
                events.remove(lift);
            }
        }
    }

    /// Send a request to the lift's gateway and wait for its answer.
    pub async fn call(&self, lift: &str, method: &str, params: Value) -> Result<Value, Failure> {
        let calls = self
            .live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(lift)
            .map(|l| l.calls.clone())
            .ok_or(Failure::Gone)?;
        let (reply, answer) = oneshot::channel();
        // Boxed: the channel's first block of slots is allocated with it, for every idle
        // gateway, and a pointer is an eighth of a call.
        let call = Box::new(Call {
            method: method.to_owned(),
            params,
            reply,
        });
        calls.try_send(call).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => Failure::Busy,
            mpsc::error::TrySendError::Closed(_) => Failure::Gone,
        })?;
        answer.await.map_err(|_| Failure::Gone)?
    }

    fn register(
        &self,
        lift: &str,
        sernum: &str,
        calls: mpsc::Sender<Box<Call>>,
        close: oneshot::Sender<()>,
    ) -> u64 {
        let serial = self
            .serial
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let old = self
            .live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(
                lift.to_owned(),
                Live {
                    calls,
                    close,
                    serial,
                    sernum: sernum.to_owned(),
                },
            );
        if let Some(old) = old {
            tracing::info!(lift, "a new connection replaces the old one");
            let _ = old.close.send(());
        }
        serial
    }

    fn unregister(&self, lift: &str, serial: u64) -> bool {
        let mut live = self.live.lock().unwrap_or_else(PoisonError::into_inner);
        if live.get(lift).is_some_and(|l| l.serial == serial) {
            live.remove(lift);
            return true;
        }
        false
    }
}

/// What a connection task needs.
#[derive(Clone)]
pub struct Shared {
    /// The database.
    pub store: Store,
    /// Live gateways.
    pub registry: Arc<Registry>,
    /// Session settings.
    pub settings: PortalSettings,
    /// Where notifications go to be stored in batches.
    pub telemetry: mpsc::Sender<(String, String, u8, String, i64)>,
    /// Values stored and dropped, for `/metrics`.
    pub counters: Arc<TelemetryCounters>,
    /// What every gateway is asked to push (`live`, `inhibit_ms`), normalized.
    pub dashboard: Arc<DashboardSection>,
}

/// Ask a newly connected gateway to push the dashboard's objects, the way an operator would.
/// `reg_canopen_object` is all or none (NXg §7.3): when one object is missing on this lift the
/// others are registered one by one.
async fn subscribe_live(registry: Arc<Registry>, lift: String, dashboard: Arc<DashboardSection>) {
    let (objects, inhibit) = (&dashboard.live, dashboard.inhibit_ms);
    if objects.is_empty() {
        return;
    }
    let all = json!({"mplex": objects, "inhibit": inhibit, "threshold": 0});
    match registry.call(&lift, "reg_canopen_object", all).await {
        Ok(_) => return,
        Err(Failure::Error(_)) => {}
        Err(other) => {
            tracing::debug!(%lift, failure = ?other, "dashboard objects not subscribed");
            return;
        }
    }
    for mplex in objects {
        let one = json!({"mplex": [mplex], "inhibit": inhibit, "threshold": 0});
        if let Err(e) = registry.call(&lift, "reg_canopen_object", one).await {
            tracing::debug!(%lift, %mplex, failure = ?e, "dashboard object not subscribed");
        }
    }
}

/// Pushed values stored, and dropped because the database could not keep up (the queue in
/// front of it was full) or failed.
#[derive(Debug, Default)]
pub struct TelemetryCounters {
    /// Values written.
    pub stored: AtomicU64,
    /// Values lost.
    pub dropped: AtomicU64,
}

/// Write telemetry in batches (up to 2,000 values or every 200 ms, whichever first).
pub async fn telemetry_writer(
    store: Store,
    mut rx: mpsc::Receiver<(String, String, u8, String, i64)>,
    counters: Arc<TelemetryCounters>,
) {
    const BATCH: usize = 2000;
    let mut batch = Vec::with_capacity(BATCH);
    loop {
        let first = rx.recv().await;
        let Some(first) = first else {
            return;
        };
        batch.push(first);
        let deadline = tokio::time::Instant::now() + std::time::Duration::from_millis(200);
        while batch.len() < BATCH {
            match tokio::time::timeout_at(deadline, rx.recv()).await {
                Ok(Some(v)) => batch.push(v),
                _ => break,
            }
        }
        let counter = match store.telemetry(&batch).await {
            Ok(()) => &counters.stored,
            Err(e) => {
                tracing::error!(error = %e, values = batch.len(), "telemetry not stored");
                &counters.dropped
            }
        };
        counter.fetch_add(batch.len() as u64, Ordering::Relaxed);
        batch.clear();
    }
}

/// Delete telemetry older than `days` once an hour (and at start).
pub async fn telemetry_retention(store: Store, days: u32) {
    if days == 0 {
        return;
    }
    let mut hourly = tokio::time::interval(std::time::Duration::from_secs(3600));
    loop {
        hourly.tick().await;
        let before = store::now_ms() - i64::from(days) * 86_400_000;
        match store.forget_telemetry(before).await {
            Ok(0) => {}
            Ok(n) => tracing::info!(values = n, days, "old telemetry deleted"),
            Err(e) => tracing::error!(error = %e, "old telemetry not deleted"),
        }
    }
}

/// Serve one gateway connection until it ends.
pub async fn serve(mut socket: WebSocket, shared: Shared, peer: String) {
    let mut session = PortalSession::new(shared.settings.clone(), Instant::now());
    let (calls_tx, mut calls_rx) = mpsc::channel::<Box<Call>>(
        shared.settings.max_queued.max(1) + shared.settings.max_in_flight,
    );
    let (close_tx, mut close_rx) = oneshot::channel::<()>();
    let mut close_tx = Some(close_tx);
    let mut waiting: HashMap<RequestId, oneshot::Sender<Result<Value, Failure>>> = HashMap::new();
    let mut lift: Option<(String, u64)> = None;
    let mut outputs = Vec::new();
    let cause = loop {
        let mut end = None;
        // Handling an output may produce more (Identify → CONNACK, token): drain them all.
        while end.is_none() && !outputs.is_empty() {
            for output in std::mem::take(&mut outputs) {
                match output {
                    PortalOutput::Send(text) => {
                        if socket.send(Message::Text(text.into())).await.is_err() {
                            end = Some("sending failed".to_owned());
                        }
                    }
                    PortalOutput::Close(cause) => {
                        let _ = socket.send(Message::Close(None)).await;
                        end = Some(cause);
                    }
                    PortalOutput::Identify(hello) => {
                        let id = store::lift_id(&hello.identity);
                        let admission = shared
                            .store
                            .admit(&hello.identity, hello.cloudtoken.as_deref())
                            .await;
                        let next = match admission {
                            Ok(Admission::Refused(cause)) => {
                                tracing::warn!(lift = %id, %peer, %cause, "gateway refused");
                                let _ = shared.store.refused(&id, &peer, &cause).await;
                                session.refuse(cause)
                            }
                            Err(e) => {
                                tracing::error!(error = %e, "registry unavailable");
                                session.refuse("registry unavailable".into())
                            }
                            Ok(admission) => {
                                let token = (admission == Admission::FirstContact)
                                    .then(|| store::secret(""));
                                let out = session.accept(&hello, token, Instant::now());
                                if let Err(e) = shared
                                    .store
                                    .upsert_gateway(&hello.identity, session.api())
                                    .await
                                {
                                    tracing::error!(error = %e, "gateway not recorded");
                                }
                                if let Some(close) = close_tx.take() {
                                    let serial = shared.registry.register(
                                        &id,
                                        &hello.identity.sernum,
                                        calls_tx.clone(),
                                        close,
                                    );
                                    lift = Some((id.clone(), serial));
                                    tokio::spawn(subscribe_live(
                                        shared.registry.clone(),
                                        id.clone(),
                                        shared.dashboard.clone(),
                                    ));
                                }
                                tracing::info!(lift = %id, %peer, api = session.api(), first = ?admission, "gateway online");
                                shared.registry.publish(&id, LiftEvent::Online(true));
                                out
                            }
                        };
                        outputs.extend(next);
                    }
                    PortalOutput::TokenConfirmed(token) => {
                        if let Some((id, _)) = &lift {
                            if let Err(e) = shared.store.set_token(id, &token).await {
                                tracing::error!(error = %e, lift = %id, "token not recorded");
                            }
                        }
                    }
                    PortalOutput::Answer(request, answer) => {
                        if let Some(reply) = waiting.remove(&request) {
                            let _ = reply.send(answer);
                        }
                    }
                    PortalOutput::Notification(payload) => {
                        if let Some((id, _)) = &lift {
                            let mplex = nxg::mplex::normalized(
                                payload["mplex"].as_str().unwrap_or_default(),
                            );
                            let value = match &payload["value"] {
                                Value::String(s) => s.clone(),
                                other => other.to_string(),
                            };
                            let node = payload["node"]["id"].as_u64().unwrap_or(0) as u8;
                            let queued = shared.telemetry.try_send((
                                id.clone(),
                                mplex,
                                node,
                                value,
                                store::now_ms(),
                            ));
                            if queued.is_err() {
                                shared.counters.dropped.fetch_add(1, Ordering::Relaxed);
                            }
                            shared.registry.publish(id, LiftEvent::Value(payload));
                        }
                    }
                }
            }
        }
        if let Some(cause) = end {
            break cause;
        }
        let deadline = session.poll_timeout().map(tokio::time::Instant::from_std);
        let timer = async {
            match deadline {
                Some(d) => tokio::time::sleep_until(d).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            message = socket.recv() => {
                let now = Instant::now();
                match message {
                    Some(Ok(Message::Text(text))) => outputs = session.text(text.as_str(), now),
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => session.activity(now),
                    Some(Ok(Message::Binary(_))) => break "binary message".to_owned(),
                    Some(Ok(Message::Close(_))) | None => break "gateway closed the connection".to_owned(),
                    Some(Err(e)) => break format!("connection failed: {e}"),
                }
            }
            Some(call) = calls_rx.recv() => {
                let (request, out) = session.request(&call.method, call.params, Instant::now());
                waiting.insert(request, call.reply);
                outputs = out;
            }
            _ = &mut close_rx => {
                let _ = socket.send(Message::Close(None)).await;
                break "replaced by a newer connection".to_owned();
            }
            _ = timer => outputs = session.timeout(Instant::now()),
        }
    };
    for output in session.ended() {
        if let PortalOutput::Answer(request, answer) = output {
            if let Some(reply) = waiting.remove(&request) {
                let _ = reply.send(answer);
            }
        }
    }
    if let Some((id, serial)) = lift {
        let _ = shared.store.seen(&id).await;
        if shared.registry.unregister(&id, serial) {
            shared.registry.publish(&id, LiftEvent::Online(false));
        }
        tracing::info!(lift = %id, %peer, %cause, "gateway offline");
    } else {
        tracing::info!(%peer, %cause, "connection ended before CONNACK");
    }
}

/// The JSON of an event for Server-Sent Events.
pub fn event_json(lift: &str, event: &LiftEvent) -> (String, String) {
    match event {
        LiftEvent::Value(v) => (
            "value".into(),
            json!({"lift": lift, "object": v}).to_string(),
        ),
        LiftEvent::Online(o) => (
            "online".into(),
            json!({"lift": lift, "online": o}).to_string(),
        ),
    }
}
