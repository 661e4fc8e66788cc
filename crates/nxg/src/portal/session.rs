//! The portal's side of one gateway connection (NXg SW003 §5–§7), sans-IO.
//!
//! [`Session`] waits for CONNECT (with a deadline), hands its parameters to the driver to check
//! against its registry ([`Output::Identify`]), answers CONNACK with the negotiated API and, on
//! first contact, issues the cloud token with `update_unique_token`. Afterwards the portal is
//! the JSON-RPC client: operator requests go out with their own ids, answers are matched to
//! them or time out, at most `max_in_flight` are outstanding, `get_heartbeat` keeps the
//! connection proven, and `canopen_object` notifications come out as values.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use serde_json::value::RawValue;

use crate::codes::rpc_codes;
use crate::msg::{
    self, Connect, ErrorObject, Event, EventNotification, Id, Incoming, Method, Notification,
    TokenParams,
};

/// Limits and timers of a portal connection.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Highest API version the portal speaks.
    pub api: u32,
    /// How long a gateway has to send CONNECT.
    pub connect_timeout: Duration,
    /// How often `get_heartbeat` is sent; silence for 2 × this + 30 s ends the connection.
    pub heartbeat: Duration,
    /// How long an operator request may wait for its answer.
    pub request_timeout: Duration,
    /// Operator requests outstanding at once.
    pub max_in_flight: usize,
    /// Operator requests waiting behind them; more are refused as busy.
    pub max_queued: usize,
}

/// Identifies an operator request.
pub type RequestId = u64;

/// Why an operator request failed.
#[derive(Debug, Clone, PartialEq)]
pub enum Failure {
    /// The gateway answered with an error object.
    Error(ErrorObject),
    /// The gateway's answer is not what the method answers (the reason).
    Invalid(String),
    /// No answer within the request timeout.
    Timeout,
    /// Too many requests waiting for this gateway.
    Busy,
    /// The connection ended first.
    Gone,
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Failure::Error(e) => write!(f, "{e}"),
            Failure::Invalid(why) => write!(f, "an answer not as the method answers: {why}"),
            Failure::Timeout => f.write_str("no answer within the request timeout"),
            Failure::Busy => f.write_str("too many requests waiting for the gateway"),
            Failure::Gone => f.write_str("the connection ended first"),
        }
    }
}

/// Why a session ended the connection.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CloseReason {
    /// No CONNECT within the connect timeout.
    NoConnect,
    /// CONNECT's parameters are malformed (what is wrong).
    InvalidConnect(String),
    /// The first message is not JSON-RPC (what is wrong).
    NotJsonRpc(String),
    /// Another message came before the CONNACK.
    BeforeConnack,
    /// The registry refused the gateway (the cause).
    Refused(String),
    /// Nothing heard for 2 × heartbeat + 30 s.
    Silent,
}

impl std::fmt::Display for CloseReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CloseReason::NoConnect => write!(f, "no CONNECT in time"),
            CloseReason::InvalidConnect(why) => write!(f, "invalid CONNECT: {why}"),
            CloseReason::NotJsonRpc(why) => write!(f, "not JSON-RPC before CONNECT: {why}"),
            CloseReason::BeforeConnack => write!(f, "a message other than CONNECT before CONNACK"),
            CloseReason::Refused(cause) => write!(f, "{cause}"),
            CloseReason::Silent => write!(f, "gateway silent for 2 × heartbeat + 30 s"),
        }
    }
}

/// What the driver must do.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    /// Send this text.
    Send(String),
    /// Close the connection without an answer (refusal, misbehaviour, silence).
    Close(CloseReason),
    /// CONNECT arrived: check it and call [`Session::accept`] or [`Session::refuse`].
    Identify(Connect),
    /// The gateway stored this token: keep it (hashed) as the one to expect.
    TokenConfirmed(String),
    /// An operator request finished: the raw JSON of its `result`, or why not.
    Answer(RequestId, Result<String, Failure>),
    /// A `canopen_object` notification.
    Notification(Notification),
    /// A `canopen_event` notification (docs/PROTOCOL.md §Events).
    Event(Event),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    AwaitConnect,
    Identifying,
    Serving,
    Closed,
}

enum Pending {
    Operator(RequestId, Instant),
    Token(String),
    Heartbeat,
}

/// A request waiting for a free slot.
struct Queued {
    request: RequestId,
    method: Method,
    params: Option<Box<RawValue>>,
}

/// One gateway connection, portal side.
pub struct Session {
    settings: Settings,
    phase: Phase,
    started: Instant,
    /// When the peer's last NXg message arrived. WebSocket pings and pongs do not count: a
    /// proxy may answer them for a peer that is gone (NXg §5.3, docs/PROTOCOL.md §Heartbeat).
    last_rx: Instant,
    next_heartbeat: Option<Instant>,
    connect_id: Option<Id>,
    api: u32,
    next_id: u64,
    pending: HashMap<u64, Pending>,
    in_flight: usize,
    queue: VecDeque<Queued>,
    next_request: RequestId,
}

impl Session {
    /// A connection that has just been upgraded.
    pub fn new(settings: Settings, now: Instant) -> Self {
        Session {
            settings,
            phase: Phase::AwaitConnect,
            started: now,
            last_rx: now,
            next_heartbeat: None,
            connect_id: None,
            api: 1,
            next_id: 1,
            pending: HashMap::new(),
            in_flight: 0,
            queue: VecDeque::new(),
            next_request: 1,
        }
    }

    /// The API version in force (after CONNACK).
    pub fn api(&self) -> u32 {
        self.api
    }

    /// Whether the gateway has been accepted and is being served.
    pub fn serving(&self) -> bool {
        self.phase == Phase::Serving
    }

    fn close(&mut self, reason: CloseReason) -> Vec<Output> {
        self.phase = Phase::Closed;
        let mut out = vec![Output::Close(reason)];
        out.extend(self.fail_all());
        out
    }

    fn fail_all(&mut self) -> Vec<Output> {
        let mut out: Vec<Output> = self
            .pending
            .drain()
            .filter_map(|(_, p)| match p {
                Pending::Operator(id, _) => Some(Output::Answer(id, Err(Failure::Gone))),
                _ => None,
            })
            .collect();
        out.extend(
            self.queue
                .drain(..)
                .map(|q| Output::Answer(q.request, Err(Failure::Gone))),
        );
        self.in_flight = 0;
        out
    }

    /// The connection ended (the driver noticed): every open request fails.
    pub fn ended(&mut self) -> Vec<Output> {
        self.phase = Phase::Closed;
        self.fail_all()
    }

    fn silence_deadline(&self) -> Instant {
        self.last_rx + crate::silence_limit(self.settings.heartbeat)
    }

    /// When to call [`Session::handle_timeout`] next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match self.phase {
            Phase::Closed => None,
            Phase::AwaitConnect | Phase::Identifying => {
                Some(self.started + self.settings.connect_timeout)
            }
            Phase::Serving => {
                let requests = self.pending.values().filter_map(|p| match p {
                    Pending::Operator(_, deadline) => Some(*deadline),
                    _ => None,
                });
                requests
                    .chain(self.next_heartbeat)
                    .chain([self.silence_deadline()])
                    .min()
            }
        }
    }

    fn next_id(&mut self) -> Id {
        let id = self.next_id;
        self.next_id += 1;
        Id::counter(id)
    }

    /// Time passed.
    pub fn handle_timeout(&mut self, now: Instant) -> Vec<Output> {
        match self.phase {
            Phase::Closed => Vec::new(),
            Phase::AwaitConnect | Phase::Identifying => {
                if now >= self.started + self.settings.connect_timeout {
                    self.close(CloseReason::NoConnect)
                } else {
                    Vec::new()
                }
            }
            Phase::Serving => {
                if now >= self.silence_deadline() {
                    return self.close(CloseReason::Silent);
                }
                let mut out = Vec::new();
                let expired: Vec<u64> = self
                    .pending
                    .iter()
                    .filter(|(_, p)| matches!(p, Pending::Operator(_, d) if now >= *d))
                    .map(|(k, _)| *k)
                    .collect();
                for key in expired {
                    if let Some(Pending::Operator(id, _)) = self.pending.remove(&key) {
                        self.in_flight -= 1;
                        out.push(Output::Answer(id, Err(Failure::Timeout)));
                    }
                }
                if self.next_heartbeat.is_some_and(|t| now >= t) {
                    self.next_heartbeat = Some(now + self.settings.heartbeat);
                    let id = self.next_id();
                    if let Some(n) = id.counter_value() {
                        self.pending.insert(n, Pending::Heartbeat);
                    }
                    out.push(Output::Send(msg::request::<()>(
                        &id,
                        Method::GetHeartbeat,
                        None,
                    )));
                }
                out.extend(self.drain_queue(now));
                out
            }
        }
    }

    /// A text message from the gateway.
    pub fn handle_text(&mut self, text: &str, now: Instant) -> Vec<Output> {
        self.last_rx = now;
        let message = match msg::parse(text) {
            Ok(m) => m,
            Err(rejected) => {
                if self.phase == Phase::Serving {
                    tracing::debug!(error = %rejected.message, "unparsable message from a gateway");
                    return Vec::new();
                }
                return self.close(CloseReason::NotJsonRpc(rejected.message));
            }
        };
        match (self.phase, message) {
            (Phase::AwaitConnect, Incoming::Request { id, method, params })
                if Method::from_name(&method) == Some(Method::Connect) =>
            {
                let connect = msg::params::<Connect>(params).and_then(|c| c.validate().map(|()| c));
                match connect {
                    Ok(connect) => {
                        self.connect_id = id;
                        self.phase = Phase::Identifying;
                        vec![Output::Identify(connect)]
                    }
                    Err(why) => self.close(CloseReason::InvalidConnect(why)),
                }
            }
            (Phase::AwaitConnect | Phase::Identifying, _) => self.close(CloseReason::BeforeConnack),
            (Phase::Serving, Incoming::Response { id, outcome, .. }) => {
                self.response(id, outcome, now)
            }
            (Phase::Serving, Incoming::Notification { method, params }) => {
                match Method::from_name(&method) {
                    Some(Method::CanopenObject) => match msg::params::<Notification>(params) {
                        Ok(n) => vec![Output::Notification(n)],
                        Err(why) => {
                            tracing::debug!(%why, "malformed canopen_object notification ignored");
                            Vec::new()
                        }
                    },
                    Some(Method::CanopenEvent) => match msg::params::<EventNotification>(params) {
                        Ok(n) => vec![Output::Event(n.event)],
                        Err(why) => {
                            tracing::debug!(%why, "malformed canopen_event notification ignored");
                            Vec::new()
                        }
                    },
                    _ => Vec::new(),
                }
            }
            (Phase::Serving, Incoming::Request { id, .. }) => {
                let error = ErrorObject::rpc(
                    rpc_codes::METHOD_NOT_FOUND,
                    "the portal serves no requests after CONNECT",
                );
                vec![Output::Send(msg::error_response(id.as_ref(), &error))]
            }
            _ => Vec::new(),
        }
    }

    fn response(
        &mut self,
        id: Option<Id>,
        outcome: Result<&RawValue, ErrorObject>,
        now: Instant,
    ) -> Vec<Output> {
        let Some(key) = id.and_then(|i| i.counter_value()) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        match self.pending.remove(&key) {
            Some(Pending::Operator(request, _)) => {
                self.in_flight -= 1;
                let answer = outcome.map(|r| r.get().to_owned()).map_err(Failure::Error);
                out.push(Output::Answer(request, answer));
            }
            Some(Pending::Token(token)) => match outcome {
                Ok(_) => out.push(Output::TokenConfirmed(token)),
                Err(error) => tracing::warn!(%error, "the gateway did not store its token"),
            },
            Some(Pending::Heartbeat) | None => {}
        }
        out.extend(self.drain_queue(now));
        out
    }

    /// The registry accepted the gateway: CONNACK, and `token` (first contact) is issued.
    pub fn accept(
        &mut self,
        connect: &Connect,
        token: Option<String>,
        now: Instant,
    ) -> Vec<Output> {
        if self.phase != Phase::Identifying {
            return Vec::new();
        }
        self.api = connect.identity.api.min(self.settings.api).max(1);
        self.phase = Phase::Serving;
        self.next_heartbeat = Some(now + self.settings.heartbeat);
        let mut out = vec![Output::Send(msg::connack(
            self.connect_id.as_ref(),
            self.api,
        ))];
        if let Some(token) = token {
            let id = self.next_id();
            let params = TokenParams {
                sernum: connect.identity.sernum.clone(),
                token: token.clone(),
            };
            if let Some(n) = id.counter_value() {
                self.pending.insert(n, Pending::Token(token));
            }
            out.push(Output::Send(msg::request(
                &id,
                Method::UpdateUniqueToken,
                Some(&params),
            )));
        }
        out
    }

    /// The registry refused the gateway: the socket is closed without an answer (NXg §5.2).
    pub fn refuse(&mut self, cause: String) -> Vec<Output> {
        self.close(CloseReason::Refused(cause))
    }

    /// Send an operator request; its answer comes as [`Output::Answer`] with the id.
    pub fn request(
        &mut self,
        method: Method,
        params: Option<Box<RawValue>>,
        now: Instant,
    ) -> (RequestId, Vec<Output>) {
        let request = self.next_request;
        self.next_request += 1;
        if self.phase != Phase::Serving {
            return (request, vec![Output::Answer(request, Err(Failure::Gone))]);
        }
        if self.in_flight >= self.settings.max_in_flight {
            if self.queue.len() >= self.settings.max_queued {
                return (request, vec![Output::Answer(request, Err(Failure::Busy))]);
            }
            self.queue.push_back(Queued {
                request,
                method,
                params,
            });
            return (request, Vec::new());
        }
        (
            request,
            vec![self.send_request(request, method, params, now)],
        )
    }

    fn send_request(
        &mut self,
        request: RequestId,
        method: Method,
        params: Option<Box<RawValue>>,
        now: Instant,
    ) -> Output {
        let id = self.next_id();
        self.in_flight += 1;
        if let Some(n) = id.counter_value() {
            self.pending.insert(
                n,
                Pending::Operator(request, now + self.settings.request_timeout),
            );
        }
        Output::Send(msg::request(&id, method, params.as_deref()))
    }

    fn drain_queue(&mut self, now: Instant) -> Vec<Output> {
        let mut out = Vec::new();
        while self.in_flight < self.settings.max_in_flight {
            let Some(q) = self.queue.pop_front() else {
                break;
            };
            out.push(self.send_request(q.request, q.method, q.params, now));
        }
        out
    }
}

#[cfg(test)]
mod tests;
