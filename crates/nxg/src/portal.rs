//! The portal's side of one gateway connection (NXg SW003 §5–§7, DESIGN.md §4), sans-IO.
//!
//! [`PortalSession`] waits for CONNECT (with a deadline), hands the identity to the driver to
//! check against its registry ([`PortalOutput::Identify`]), answers CONNACK with the negotiated
//! API and, on first contact, issues the cloud token with `update_unique_token`. Afterwards the
//! portal is the JSON-RPC client: operator requests go out with their own ids, answers are matched
//! to them or time out, at most `max_in_flight` are outstanding, `get_heartbeat` keeps the
//! connection proven, and `canopen_object` notifications come out as values.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::gateway::Identity;
use crate::rpc::{self, Incoming};

/// Limits and timers of a portal connection.
#[derive(Debug, Clone, PartialEq)]
pub struct PortalSettings {
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

/// What CONNECT said.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Hello {
    /// The gateway's identity (its `api` is the highest it offers).
    pub identity: Identity,
    /// The token the portal gave it earlier, if any.
    pub cloudtoken: Option<String>,
}

/// Identifies an operator request.
pub type RequestId = u64;

/// Why an operator request failed.
#[derive(Debug, Clone, PartialEq)]
pub enum Failure {
    /// The gateway answered with an error object (`code`, `message`, `data`).
    Error(Value),
    /// No answer within the request timeout.
    Timeout,
    /// Too many requests waiting for this gateway.
    Busy,
    /// The connection ended first.
    Gone,
}

/// What the driver must do.
#[derive(Debug, Clone, PartialEq)]
pub enum PortalOutput {
    /// Send this text.
    Send(String),
    /// Close the connection without an answer (refusal, misbehaviour, silence).
    Close(String),
    /// CONNECT arrived: check the identity and call [`PortalSession::accept`] or
    /// [`PortalSession::refuse`].
    Identify(Hello),
    /// The gateway stored this token: keep it (hashed) as the one to expect.
    TokenConfirmed(String),
    /// An operator request finished.
    Answer(RequestId, Result<Value, Failure>),
    /// A `canopen_object` notification's payload (`mplex`, `value`, maybe `node`).
    Notification(Value),
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

/// One gateway connection, portal side.
pub struct PortalSession {
    settings: PortalSettings,
    phase: Phase,
    started: Instant,
    last_rx: Instant,
    next_heartbeat: Option<Instant>,
    connect_id: Value,
    api: u32,
    next_id: u64,
    pending: HashMap<u64, Pending>,
    in_flight: usize,
    queue: VecDeque<(RequestId, String, Value)>,
    next_request: RequestId,
}

const MAX_FIELD: usize = 256;

fn text_field(obj: &Value, name: &str, required: bool) -> Result<String, String> {
    match obj.get(name) {
        Some(Value::String(s)) if s.chars().count() <= MAX_FIELD && !(required && s.is_empty()) => {
            Ok(s.clone())
        }
        None if !required => Ok(String::new()),
        _ => Err(format!(
            "identity.{name} must be a string of at most {MAX_FIELD} characters"
        )),
    }
}

fn number_field(obj: &Value, name: &str) -> Result<u32, String> {
    obj.get(name)
        .and_then(Value::as_u64)
        .and_then(|n| u32::try_from(n).ok())
        .ok_or_else(|| format!("identity.{name} must be a number"))
}

/// Read CONNECT's parameters (NXg SW003 §5.2.1); any malformed field refuses the gateway.
pub fn parse_hello(params: &Value) -> Result<Hello, String> {
    let identity = params.get("identity").ok_or("CONNECT without identity")?;
    let api = match identity.get("api") {
        None | Some(Value::Null) => 1,
        Some(v) => v
            .as_u64()
            .and_then(|n| u32::try_from(n).ok())
            .filter(|n| *n >= 1)
            .ok_or("identity.api must be a number ≥ 1")?,
    };
    let cloudtoken = match identity.get("cloudtoken") {
        None | Some(Value::Null) => None,
        Some(Value::String(t)) if t.chars().count() <= 128 => Some(t.clone()),
        _ => return Err("identity.cloudtoken must be a string of at most 128 characters".into()),
    };
    let domaintoken = match params.get("domaintoken") {
        Some(Value::String(d)) if d.chars().count() <= MAX_FIELD => d.clone(),
        None => String::new(),
        _ => return Err("domaintoken must be a string".into()),
    };
    Ok(Hello {
        identity: Identity {
            sernum: text_field(identity, "sernum", true)?,
            vendorid: number_field(identity, "vendorid")?,
            productcode: number_field(identity, "productcode")?,
            liftnum: text_field(identity, "liftnum", false)?,
            hardware: text_field(identity, "hardware", false)?,
            software: text_field(identity, "software", false)?,
            boardhash: text_field(identity, "boardhash", false)?,
            domaintoken,
            api,
        },
        cloudtoken,
    })
}

impl PortalSession {
    /// A connection that has just been upgraded.
    pub fn new(settings: PortalSettings, now: Instant) -> Self {
        PortalSession {
            settings,
            phase: Phase::AwaitConnect,
            started: now,
            last_rx: now,
            next_heartbeat: None,
            connect_id: Value::Null,
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

    fn close(&mut self, cause: String) -> Vec<PortalOutput> {
        self.phase = Phase::Closed;
        let mut out = vec![PortalOutput::Close(cause)];
        out.extend(self.fail_all());
        out
    }

    fn fail_all(&mut self) -> Vec<PortalOutput> {
        let mut out: Vec<PortalOutput> = self
            .pending
            .drain()
            .filter_map(|(_, p)| match p {
                Pending::Operator(id, _) => Some(PortalOutput::Answer(id, Err(Failure::Gone))),
                _ => None,
            })
            .collect();
        out.extend(
            self.queue
                .drain(..)
                .map(|(id, ..)| PortalOutput::Answer(id, Err(Failure::Gone))),
        );
        self.in_flight = 0;
        out
    }

    /// The connection ended (the driver noticed): every open request fails.
    pub fn ended(&mut self) -> Vec<PortalOutput> {
        self.phase = Phase::Closed;
        self.fail_all()
    }

    /// When to call [`PortalSession::timeout`] next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match self.phase {
            Phase::Closed => None,
            Phase::AwaitConnect | Phase::Identifying => {
                Some(self.started + self.settings.connect_timeout)
            }
            Phase::Serving => {
                let silence = self.last_rx + self.settings.heartbeat * 2 + Duration::from_secs(30);
                let requests = self.pending.values().filter_map(|p| match p {
                    Pending::Operator(_, deadline) => Some(*deadline),
                    _ => None,
                });
                requests.chain(self.next_heartbeat).chain([silence]).min()
            }
        }
    }

    /// Time passed.
    pub fn timeout(&mut self, now: Instant) -> Vec<PortalOutput> {
        match self.phase {
            Phase::Closed => Vec::new(),
            Phase::AwaitConnect | Phase::Identifying => {
                if now >= self.started + self.settings.connect_timeout {
                    self.close("no CONNECT in time".into())
                } else {
                    Vec::new()
                }
            }
            Phase::Serving => {
                if now >= self.last_rx + self.settings.heartbeat * 2 + Duration::from_secs(30) {
                    return self.close("gateway silent for 2 × heartbeat + 30 s".into());
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
                        out.push(PortalOutput::Answer(id, Err(Failure::Timeout)));
                    }
                }
                if self.next_heartbeat.is_some_and(|t| now >= t) {
                    self.next_heartbeat = Some(now + self.settings.heartbeat);
                    let id = self.next_id;
                    self.next_id += 1;
                    self.pending.insert(id, Pending::Heartbeat);
                    out.push(PortalOutput::Send(rpc::request(
                        &json!(id),
                        "get_heartbeat",
                        Value::Null,
                    )));
                }
                out.extend(self.drain_queue(now));
                out
            }
        }
    }

    /// A WebSocket ping or pong arrived.
    pub fn activity(&mut self, now: Instant) {
        self.last_rx = now;
    }

    /// A text message from the gateway.
    pub fn text(&mut self, text: &str, now: Instant) -> Vec<PortalOutput> {
        self.last_rx = now;
        let message = match rpc::parse(text) {
            Ok(m) => m,
            Err(rejected) => {
                if self.phase == Phase::Serving {
                    tracing::debug!(error = %rejected.message, "unparsable message from a gateway");
                    return Vec::new();
                }
                return self.close(format!("not JSON-RPC before CONNECT: {}", rejected.message));
            }
        };
        match (self.phase, message) {
            (Phase::AwaitConnect, Incoming::Request { id, method, params })
                if method == "CONNECT" =>
            {
                match parse_hello(&params) {
                    Ok(hello) => {
                        self.connect_id = id;
                        self.phase = Phase::Identifying;
                        vec![PortalOutput::Identify(hello)]
                    }
                    Err(why) => self.close(format!("invalid CONNECT: {why}")),
                }
            }
            (Phase::AwaitConnect | Phase::Identifying, _) => {
                self.close("a message other than CONNECT before CONNACK".into())
            }
            (
                Phase::Serving,
                Incoming::Response {
                    id, result, error, ..
                },
            ) => self.response(id, result, error, now),
            (Phase::Serving, Incoming::Notification { method, params })
                if method == "canopen_object" =>
            {
                if params.get("mplex").and_then(Value::as_str).is_some()
                    && params.get("value").is_some()
                {
                    vec![PortalOutput::Notification(params)]
                } else {
                    Vec::new()
                }
            }
            (Phase::Serving, Incoming::Request { id, .. }) => vec![PortalOutput::Send(rpc::error(
                &id,
                crate::errors::rpc_codes::METHOD_NOT_FOUND,
                "the portal serves no requests after CONNECT",
                None,
            ))],
            _ => Vec::new(),
        }
    }

    fn response(
        &mut self,
        id: Value,
        result: Option<Value>,
        error: Option<Value>,
        now: Instant,
    ) -> Vec<PortalOutput> {
        let Some(key) = id.as_u64() else {
            return Vec::new();
        };
        let mut out = Vec::new();
        match self.pending.remove(&key) {
            Some(Pending::Operator(request, _)) => {
                self.in_flight -= 1;
                let answer = match (result, error) {
                    (Some(r), None) => Ok(r),
                    (_, Some(e)) => Err(Failure::Error(e)),
                    _ => Err(Failure::Gone),
                };
                out.push(PortalOutput::Answer(request, answer));
            }
            Some(Pending::Token(token)) => {
                if result.is_some() {
                    out.push(PortalOutput::TokenConfirmed(token));
                } else {
                    tracing::warn!(?error, "the gateway did not store its token");
                }
            }
            Some(Pending::Heartbeat) | None => {}
        }
        out.extend(self.drain_queue(now));
        out
    }

    /// The registry accepted the gateway: CONNACK, and `token` (first contact) is issued.
    pub fn accept(
        &mut self,
        hello: &Hello,
        token: Option<String>,
        now: Instant,
    ) -> Vec<PortalOutput> {
        if self.phase != Phase::Identifying {
            return Vec::new();
        }
        self.api = hello.identity.api.min(self.settings.api).max(1);
        self.phase = Phase::Serving;
        self.next_heartbeat = Some(now + self.settings.heartbeat);
        let connack =
            json!({"jsonrpc": "2.0", "id": self.connect_id, "result": "CONNACK", "api": self.api});
        let mut out = vec![PortalOutput::Send(connack.to_string())];
        if let Some(token) = token {
            let id = self.next_id;
            self.next_id += 1;
            let params = json!({"sernum": hello.identity.sernum, "token": token});
            self.pending.insert(id, Pending::Token(token));
            out.push(PortalOutput::Send(rpc::request(
                &json!(id),
                "update_unique_token",
                params,
            )));
        }
        out
    }

    /// The registry refused the gateway: the socket is closed without an answer (NXg §5.2).
    pub fn refuse(&mut self, cause: String) -> Vec<PortalOutput> {
        self.close(cause)
    }

    /// Send an operator request; its answer comes as [`PortalOutput::Answer`] with the id.
    pub fn request(
        &mut self,
        method: &str,
        params: Value,
        now: Instant,
    ) -> (RequestId, Vec<PortalOutput>) {
        let request = self.next_request;
        self.next_request += 1;
        if self.phase != Phase::Serving {
            return (
                request,
                vec![PortalOutput::Answer(request, Err(Failure::Gone))],
            );
        }
        if self.in_flight >= self.settings.max_in_flight {
            if self.queue.len() >= self.settings.max_queued {
                return (
                    request,
                    vec![PortalOutput::Answer(request, Err(Failure::Busy))],
                );
            }
            self.queue.push_back((request, method.to_owned(), params));
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
        method: &str,
        params: Value,
        now: Instant,
    ) -> PortalOutput {
        let id = self.next_id;
        self.next_id += 1;
        self.in_flight += 1;
        self.pending.insert(
            id,
            Pending::Operator(request, now + self.settings.request_timeout),
        );
        PortalOutput::Send(rpc::request(&json!(id), method, params))
    }

    fn drain_queue(&mut self, now: Instant) -> Vec<PortalOutput> {
        let mut out = Vec::new();
        while self.in_flight < self.settings.max_in_flight {
            let Some((request, method, params)) = self.queue.pop_front() else {
                break;
            };
            out.push(self.send_request(request, &method, params, now));
        }
        out
    }
}

#[cfg(test)]
mod tests;
