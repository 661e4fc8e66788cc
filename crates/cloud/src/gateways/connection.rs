//! One gateway connection on the portal: the WebSocket, the portal [`Session`] and the steps
//! around it — identify the gateway against the store, admit or refuse it, register it for
//! operators, record its token, pass operator requests and their answers, store and fan out
//! what it pushes, and clean up when it goes.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use axum::extract::ws::{close_code, CloseFrame, Message, WebSocket};
use futures_util::SinkExt;
use nxg::mplex::Mplex;
use nxg::msg::{Connect, Event, Notification};
use nxg::portal::{CloseReason, Failure, Output, RequestId, Session};

use super::mailbox::{Letter, Mailbox};
use super::reports::Report;
use super::telemetry::Dropped;
use super::{dashboard, Calls, Reply, Shared};
use crate::config::BoardhashChange;
use cloud_types::audit::AuditEntry;
use cloud_types::live::LiftEvent;

use cloud_store::{GatewayRecord, TelemetryRow};

use super::admissions::{Admission, Known};
use super::refusals::Reason;
use crate::throttle::TokenBucket;

/// The lift a connection serves, once it is admitted.
struct Admitted {
    lift: String,
    /// Its account's domain token (what a confirmed token's record is written under).
    domain: String,
    /// Tells this connection from a newer one of the same lift.
    serial: u64,
    /// What the lift may still store this hour.
    quota: Quota,
    /// Whether its state object last said it is in service (none before its first value).
    in_service: Option<bool>,
}

/// A lift's storage quota (`[gateways] max_stored_bytes_per_hour`): bytes a bucket of an
/// hour's worth allows, and the values dropped beyond it since the connection began.
struct Quota {
    bytes: TokenBucket,
    dropped: u64,
    /// When the last `OverQuota` report went out.
    reported: Option<Instant>,
}

impl Quota {
    /// How often a lift over its quota is reported at most (the alarm stays while reports
    /// come, and clears an hour after the last).
    const REPORT_EVERY: std::time::Duration = std::time::Duration::from_secs(60);

    fn new(per_hour: u64, now: Instant) -> Quota {
        let per_hour = per_hour as f64;
        Quota {
            bytes: TokenBucket::with_capacity(per_hour / 3600.0, per_hour, now),
            dropped: 0,
            reported: None,
        }
    }

    /// Whether `row` fits the quota (taken from it if so).
    fn take(&mut self, row: &TelemetryRow, now: Instant) -> bool {
        // What a row costs the database roughly: its texts and its two numbers and overhead.
        let cost = row.lift.len() + row.mplex.len() + row.value.len() + 32;
        let fits = self.bytes.take_n(cost as f64, now).is_ok();
        if !fits {
            self.dropped += 1;
        }
        fits
    }

    /// The values dropped so far, when a report of them is due.
    fn report_due(&mut self, now: Instant) -> Option<u64> {
        if self
            .reported
            .is_some_and(|at| now.duration_since(at) < Quota::REPORT_EVERY)
        {
            return None;
        }
        self.reported = Some(now);
        Some(self.dropped)
    }
}

/// One gateway connection.
pub struct Connection {
    socket: WebSocket,
    shared: Arc<Shared>,
    peer: String,
    session: Session,
    /// Operator requests, and the order to close (a newer connection of the lift); handed
    /// to the registry on admission.
    calls: Calls,
    waiting: HashMap<RequestId, Reply>,
    admitted: Option<Admitted>,
    closing: tokio::sync::watch::Receiver<bool>,
    /// The gateway's messages: `[gateways] max_messages_per_s`, bursts of two seconds' worth
    /// (a gateway pushing its subscriptions after CONNACK).
    rate: TokenBucket,
    /// What the gateway sent while its CONNECT was looked up, read then to see whether it had
    /// left (`identify`), handled after.
    early: VecDeque<Message>,
}

/// Serve one gateway connection until it ends.
pub async fn serve(socket: WebSocket, shared: Arc<Shared>, peer: String) {
    // The connection's task lives as long as the gateway stays: its future is what an idle
    // connection costs. The connection is boxed (an `async fn` holds its arguments twice), and
    // the database work of the end is boxed like that of the start (`carry_out`).
    let mut connection = Box::new(Connection::new(socket, shared, peer));
    let cause = connection.run().await;
    Box::pin(connection.finish(cause)).await;
}

impl Drop for Connection {
    /// Requests still waiting learn at once that the gateway is gone, also when the task is
    /// cut short (the portal stopping).
    fn drop(&mut self) {
        self.calls.end();
    }
}

impl Connection {
    fn new(socket: WebSocket, shared: Arc<Shared>, peer: String) -> Connection {
        let session = Session::new(shared.policy.settings.clone(), Instant::now());
        let calls = Calls::new(Mailbox::new(
            shared.policy.settings.max_queued.max(1) + shared.policy.settings.max_in_flight,
        ));
        let closing = shared.closing.clone();
        let rate = TokenBucket::new(shared.policy.max_messages_per_s, Instant::now());
        Connection {
            socket,
            shared,
            peer,
            session,
            calls,
            waiting: HashMap::new(),
            admitted: None,
            closing,
            rate,
            early: VecDeque::new(),
        }
    }

    /// Serve until the connection is over; the cause.
    async fn run(&mut self) -> String {
        let mut outputs = Vec::new();
        loop {
            if let Err(cause) = self.carry_out(outputs).await {
                return cause;
            }
            outputs = match self.next().await {
                Ok(out) => out,
                Err(cause) => return cause,
            };
        }
    }

    /// Do what the session asks; handling an output may produce more (Identify → CONNACK,
    /// token), so until none is left. `Err`: the connection is over, with the cause.
    async fn carry_out(&mut self, mut outputs: Vec<Output>) -> Result<(), String> {
        let mut unflushed = false;
        while !outputs.is_empty() {
            for output in std::mem::take(&mut outputs) {
                match output {
                    // Written together, flushed once below: one TLS write for all.
                    Output::Send(text) => {
                        if self.socket.feed(Message::Text(text.into())).await.is_err() {
                            return Err("sending failed".into());
                        }
                        unflushed = true;
                    }
                    Output::Close(reason) => {
                        if let CloseReason::InvalidConnect(why) = &reason {
                            self.shared.refusals.invalid(&self.peer, why);
                        }
                        let _ = self.socket.send(Message::Close(None)).await;
                        return Err(reason.to_string());
                    }
                    // Database work happens once per connection or rarely: boxed, its futures
                    // live only while it runs instead of sizing the connection's task for good
                    // (an idle connection's memory is mostly that task).
                    Output::Identify(connect) => {
                        outputs.extend(Box::pin(self.identify(connect)).await?);
                    }
                    Output::TokenConfirmed(token) => Box::pin(self.token_confirmed(&token)).await,
                    Output::Answer(request, answer) => self.answer(request, answer),
                    // A full queue: wait for room, reading nothing more from this gateway
                    // meanwhile (push-back); boxed, as the wait is the exception.
                    Output::Notification(n) => {
                        if let Err(row) = self.notification(n) {
                            Box::pin(self.shared.telemetry.wait(row)).await;
                        }
                    }
                    Output::Event(event) => self.event(event),
                }
            }
        }
        if unflushed && self.socket.flush().await.is_err() {
            return Err("sending failed".into());
        }
        Ok(())
    }

    /// Wait for the next thing to happen: a message, an operator request, replacement by a
    /// newer connection, or the session's timer.
    async fn next(&mut self) -> Result<Vec<Output>, String> {
        if let Some(message) = self.early.pop_front() {
            return self.received(Some(Ok(message))).await;
        }
        let deadline = self.session.poll_timeout();
        tokio::select! {
            message = self.socket.recv() => self.received(message).await,
            letter = self.calls.next() => match letter {
                Letter::Item(call) => {
                    // The requests that came together (a lift page asks for all its objects
                    // at once) leave together.
                    let now = Instant::now();
                    let mut out = Vec::new();
                    let mut call = Some(call);
                    while let Some(c) = call {
                        let (request, sent) = self.session.request(c.method, c.params, now);
                        self.waiting.insert(request, c.reply);
                        out.extend(sent);
                        call = self.calls.try_item();
                    }
                    Ok(out)
                }
                Letter::Close => {
                    let _ = self.socket.send(Message::Close(None)).await;
                    Err("replaced by a newer connection".into())
                }
            },
            _ = self.closing.changed() => {
                let _ = self.socket.send(Message::Close(None)).await;
                Err("the portal is shutting down".into())
            }
            _ = tokio::time::sleep_until(deadline.unwrap_or_else(Instant::now).into()), if deadline.is_some() => {
                Ok(self.session.handle_timeout(Instant::now()))
            }
        }
    }

    /// What the gateway sent, taken by the session.
    async fn received(
        &mut self,
        message: Option<Result<Message, axum::Error>>,
    ) -> Result<Vec<Output>, String> {
        let now = Instant::now();
        if matches!(message, Some(Ok(_))) && self.rate.take(now).is_err() {
            let frame = CloseFrame {
                code: close_code::POLICY,
                reason: "message rate above [gateways] max_messages_per_s".into(),
            };
            let _ = self.socket.send(Message::Close(Some(frame))).await;
            let limit = self.shared.policy.max_messages_per_s;
            return Err(format!("more than {limit} messages/s"));
        }
        match message {
            Some(Ok(Message::Text(text))) => {
                let out = self.session.handle_text(text.as_str(), now);
                // An answer to one of the portal's own requests is not a message the
                // gateway chose to send: those requests are limited where they are
                // made (`max_in_flight`, the API keys' rates), and operators reading a
                // lift at once must not cost the lift its connection.
                if out.iter().any(|o| matches!(o, Output::Answer(..))) {
                    self.rate.give_back();
                }
                Ok(out)
            }
            // Liveness is the gateway's NXg messages alone (NXg §5.3): a proxy may
            // answer pings for a gateway that is gone.
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => Ok(Vec::new()),
            Some(Ok(Message::Binary(_))) => Err("binary message".into()),
            Some(Ok(Message::Close(_))) | None => Err("gateway closed the connection".into()),
            Some(Err(e)) => Err(format!("connection failed: {e}")),
        }
    }

    /// CONNECT came: admit the gateway (CONNACK, a token on first contact or when the one in
    /// use is due for rotation) or refuse it; a valid token from another board is dealt with
    /// per `[gateways] boardhash_change`.
    ///
    /// While the registry is asked, the socket is read: a gateway that gives up waiting (its
    /// CONNACK timeout) and closes ends the connection at once. Otherwise, when look-ups take
    /// long (a reconnect storm on a busy database), every gateway that gave up would keep its
    /// connection's socket open here until its look-up ended — thousands of sockets the
    /// portal's file limit counts, while the same gateways come back on new ones: the portal
    /// ran out of files and accepted nothing more. `Err`: the gateway left.
    async fn identify(&mut self, connect: Connect) -> Result<Vec<Output>, String> {
        let id = cloud_types::lifts::lift_id(&connect.identity);
        let peer = self.peer.clone();
        let (admission, unchanged) = {
            let look_up = look_up(&self.shared, &peer, &id, &connect);
            tokio::pin!(look_up);
            loop {
                tokio::select! {
                    looked_up = &mut look_up => break looked_up,
                    message = self.socket.recv(), if self.early.len() < EARLY => match message {
                        Some(Ok(Message::Close(_)) | Err(_)) | None => {
                            return Err("the gateway left while its CONNECT was looked up".into())
                        }
                        Some(Ok(message)) => self.early.push_back(message),
                    },
                }
            }
        };
        let counters = &self.shared.admissions.counters;
        Ok(match admission {
            Ok(Admission::Refused(reason, cause)) => {
                let refusals = &self.shared.refusals;
                Box::pin(refusals.note(&id, &peer, reason, &cause, &connect.domaintoken)).await;
                self.session.refuse(cause)
            }
            Err(e) => {
                counters.unavailable.fetch_add(1, Ordering::Relaxed);
                tracing::error!(error = %e, "registry unavailable");
                self.session.refuse("registry unavailable".into())
            }
            Ok(admission) => {
                let lift = admission.key().unwrap_or(&id).to_owned();
                counters.admitted.fetch_add(1, Ordering::Relaxed);
                let token = token_to_issue(&self.shared, &lift, &admission).await;
                let out = self.session.accept(&connect, token, Instant::now());
                let api = self.session.api();
                let record = GatewayRecord::connected(&lift, &connect, api);
                if unchanged {
                    self.shared.records.write(record).await;
                } else if let Err(e) = self.shared.records.write_now(record).await {
                    tracing::error!(error = %e, "gateway not recorded");
                }
                // Users' subscriptions are read at CONNACK only where the admission saw some
                // (a first contact's, after a token reset, may have some from before).
                let (subscribed, first) = match &admission {
                    Admission::Known(known) => (known.subscribed, false),
                    Admission::FirstContact { subscribed, .. } => (*subscribed, true),
                    Admission::Refused(..) => (false, false),
                };
                self.register(&lift, &connect, subscribed);
                tracing::info!(%lift, %peer, api, first, "gateway online");
                self.shared.registry.publish(&lift, LiftEvent::Online(true));
                self.shared.reports.report(Report::Online(lift)).await;
                out
            }
        })
    }

    /// Make the lift reachable for operators and subscribe the dashboard's objects and its bus
    /// events.
    fn register(&mut self, lift: &str, connect: &Connect, subscribed: bool) {
        if self.admitted.is_some() {
            return;
        }
        let registry = &self.shared.registry;
        let serial = registry.register(lift, connect, self.calls.clone());
        self.admitted = Some(Admitted {
            lift: lift.to_owned(),
            domain: connect.domaintoken.clone(),
            serial,
            quota: Quota::new(self.shared.policy.max_stored_bytes_per_hour, Instant::now()),
            in_service: None,
        });
        tokio::spawn(dashboard::subscribe(
            registry.clone(),
            self.shared.subscriptions.clone(),
            lift.to_owned(),
            self.shared.dashboard.clone(),
            subscribed,
        ));
    }

    /// Queued behind the gateway's row; the lift's next admission waits until it is written.
    async fn token_confirmed(&mut self, token: &str) {
        if let Some(a) = &self.admitted {
            let record = GatewayRecord::token(&a.lift, &a.domain, token);
            self.shared.records.write(record).await;
        }
    }

    fn answer(&mut self, request: RequestId, answer: Result<String, Failure>) {
        if let Some(reply) = self.waiting.remove(&request) {
            let _ = reply.send(answer);
        }
    }

    /// A pushed value: checked (an object someone subscribed to, not too long), handed to live
    /// viewers and queued for the store within the lift's hourly quota; `Err` with the value
    /// when the queue has no room now (see [`super::telemetry::Queue`]).
    fn notification(&mut self, n: Notification) -> Result<(), TelemetryRow> {
        let Some(a) = &mut self.admitted else {
            return Ok(());
        };
        let counters = self.shared.telemetry.counters();
        if n.value.len() > self.shared.policy.max_value_bytes {
            counters.count_dropped(Dropped::TooLarge, 1);
            return Ok(());
        }
        // Only what the portal asked for: a gateway pushing objects of its own choosing (or of
        // other nodes) must not fill the disk with them.
        let mplex = Mplex::parse(&n.mplex).ok();
        let wanted =
            n.node.is_none() && mplex.is_some_and(|m| self.shared.subscriptions.wanted(&a.lift, m));
        if !wanted {
            counters.count_dropped(Dropped::Unsubscribed, 1);
            return Ok(());
        }
        let at = cloud_types::now_ms();
        if mplex == Some(self.shared.insights.state) {
            let now = self.shared.insights.in_service(&n.value);
            if a.in_service.replace(now) != Some(now) {
                self.shared.reports.offer(Report::Service {
                    lift: a.lift.clone(),
                    in_service: now,
                    at,
                });
            }
        }
        self.shared.registry.observe(&a.lift, &n, at);
        let row = TelemetryRow {
            lift: a.lift.clone(),
            mplex: nxg::mplex::normalized(&n.mplex),
            node: 0,
            value: n.value.clone(),
            at,
        };
        self.shared.registry.publish(&a.lift, LiftEvent::Value(n));
        if !a.quota.take(&row, Instant::now()) {
            counters.count_dropped(Dropped::Quota, 1);
            if let Some(dropped) = a.quota.report_due(Instant::now()) {
                let report = Report::OverQuota {
                    lift: a.lift.clone(),
                    dropped,
                };
                self.shared.reports.try_report(report);
            }
            return Ok(());
        }
        self.shared.telemetry.offer(row)
    }

    /// A bus event: to live viewers, and reported (the alarm service stores it).
    fn event(&self, event: Event) {
        let Some(a) = &self.admitted else {
            return;
        };
        self.shared
            .registry
            .publish(&a.lift, LiftEvent::Bus(event.clone()));
        self.shared.reports.event(a.lift.clone(), event);
    }

    /// The connection is over: open requests fail, the lift goes offline (unless a newer
    /// connection already serves it).
    async fn finish(&mut self, cause: String) {
        for output in self.session.ended() {
            if let Output::Answer(request, answer) = output {
                self.answer(request, answer);
            }
        }
        let peer = &self.peer;
        let Some(a) = &self.admitted else {
            tracing::info!(%peer, %cause, "connection ended before CONNACK");
            return;
        };
        // In the background: a database that is down must not hold up the lift going offline.
        self.shared
            .records
            .write_later(GatewayRecord::seen(&a.lift));
        if self.shared.registry.unregister(&a.lift, a.serial) {
            self.shared.subscriptions.offline(&a.lift).await;
            self.shared
                .registry
                .publish(&a.lift, LiftEvent::Online(false));
            self.shared
                .reports
                .report(Report::Offline(a.lift.clone()))
                .await;
        }
        tracing::info!(lift = %a.lift, %peer, %cause, "gateway offline");
    }
}

/// Messages a gateway may send before its CONNACK that are kept for after it; beyond them it
/// is not read until then (NXg §5.2: a gateway waits for CONNACK, so there are none).
const EARLY: usize = 16;

/// What the registry says about `connect` of lift `id` from `peer`, and whether its admission
/// changes nothing the next one decides on (its row is then refreshed behind the connection,
/// with others).
async fn look_up(
    shared: &Shared,
    peer: &str,
    id: &str,
    connect: &Connect,
) -> (Result<Admission, cloud_store::StoreError>, bool) {
    // A token its last connection confirmed is on record first (else: a first contact
    // again, its board unchecked).
    shared.records.settled(id, &connect.domaintoken).await;
    match shared.admissions.admit(connect).await {
        Ok(Admission::Known(mut known)) => match known.board_was.take() {
            Some(was) => (
                board_changed(shared, peer, connect, was, known).await,
                false,
            ),
            None => (Ok(Admission::Known(known)), true),
        },
        // A first contact's row is written (and checked) before CONNACK; what the CONNACK
        // agreed then follows behind the connection.
        Ok(Admission::FirstContact { key, subscribed }) => {
            (first_contact(shared, connect, key, subscribed).await, true)
        }
        other => (other, false),
    }
}

/// A first contact of lift `key`: its row is written before CONNACK, and it must be this
/// account's. Two first contacts of one identity from two accounts at once both find the key
/// free; the second's row is not written over the first's, which the write reports
/// (`Store::record_batch`), and it is refused here, to be admitted under a key of its own when
/// it tries again (docs/PORTAL.md §Lifts and accounts).
async fn first_contact(
    shared: &Shared,
    connect: &Connect,
    key: String,
    subscribed: bool,
) -> Result<Admission, cloud_store::StoreError> {
    let record = GatewayRecord::connected(&key, connect, connect.identity.api);
    if shared.records.write_now(record).await? {
        Ok(Admission::FirstContact { key, subscribed })
    } else {
        Ok(Admission::Refused(
            Reason::Taken,
            "another account's lift took this identity's key at the same moment: try again".into(),
        ))
    }
}

/// A valid token came from another board than the one on record (`was`): refuse, or accept
/// (`known`) with an alarm or without; audited either way.
async fn board_changed(
    shared: &Shared,
    peer: &str,
    connect: &Connect,
    was: String,
    known: Known,
) -> Result<Admission, cloud_store::StoreError> {
    let lift = known.key.clone();
    let now = connect.identity.boardhash.clone();
    let policy = shared.policy.boardhash_change;
    let result = match policy {
        BoardhashChange::Refuse => "refused",
        BoardhashChange::Alarm => "accepted, alarm raised",
        BoardhashChange::Accept => "accepted",
    };
    tracing::warn!(%lift, %peer, %was, %now, result, "the gateway's board changed");
    shared
        .store
        .audit(&AuditEntry {
            at: cloud_types::now_ms(),
            account: cloud_types::audit::BY_PORTAL.into(),
            lift: lift.clone(),
            action: "board changed".into(),
            object: "boardhash".into(),
            old_value: Some(was.clone()),
            new_value: now.clone(),
            result: result.into(),
            address: Some(peer.to_owned()),
        })
        .await?;
    if policy == BoardhashChange::Refuse {
        return Ok(Admission::Refused(Reason::Board, format!(
            "boardhash {now:?} differs from the registered {was:?} (boardhash_change = refuse; reset the token to admit the new board)"
        )));
    }
    if policy == BoardhashChange::Alarm {
        let report = Report::BoardChanged { lift, was, now };
        shared.reports.report(report).await;
    }
    Ok(Admission::Known(known))
}

/// The token to send with CONNACK: a first one at first contact, a new one when the one in
/// use is older than `[gateways] token_rotate_days` (recorded as the next token first, so
/// that a lost answer does not lock the gateway out).
async fn token_to_issue(shared: &Shared, lift: &str, admission: &Admission) -> Option<String> {
    match admission {
        Admission::FirstContact { .. } => Some(cloud_store::secret("")),
        Admission::Known(known) => {
            let lifetime = shared.policy.token_lifetime?;
            let age = cloud_types::now_ms().saturating_sub(known.token_set);
            if u128::try_from(age).unwrap_or(0) < lifetime.as_millis() {
                return None;
            }
            let token = cloud_store::secret("");
            match shared.store.set_next_token(lift, &token).await {
                Ok(()) => {
                    tracing::info!(%lift, age_days = age / 86_400_000, "token due: rotating");
                    Some(token)
                }
                Err(e) => {
                    tracing::error!(error = %e, %lift, "token rotation postponed");
                    None
                }
            }
        }
        Admission::Refused(..) => None,
    }
}
