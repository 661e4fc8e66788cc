//! The elevator gateway's side of one connection (NXg SW003 §5–§7), sans-IO.
//!
//! [`Session`] takes WebSocket text messages, object values and time, and returns what to send,
//! which dictionary accesses to run ([`Job`]s, by SDO or on a local dictionary — the driver
//! decides) and when to wake it next. Every rule of the protocol lives here: CONNECT and API
//! negotiation, privileges with expiry and lock-out, the checks of `put_canopen_object`,
//! subscriptions with inhibit and threshold, bounded work in flight, the dead-connection timer.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::time::{Duration, Instant};

use canopen::sdo::abort::AbortCode;
use canopen::types::{self, DataType, Value as CoValue};
use lift417::catalog::{Bound, Catalog, Entry, Texts};
use lift417::meta::{Access, FormType, NxgDataType, Privilege};
use serde_json::{json, Map, Value};

use crate::errors::{self, rpc_codes, NxgError};
use crate::mplex::Mplex;
use crate::rpc::{self, Incoming};

/// What the gateway says about itself in CONNECT (NXg SW003 §5.2.1); also the `[identity]`
/// section of the gateway's configuration.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Identity {
    /// Serial number (unique per vendor).
    pub sernum: String,
    /// CiA vendor-ID.
    pub vendorid: u32,
    /// Product code.
    pub productcode: u32,
    /// Lift number as the owner knows it.
    pub liftnum: String,
    /// Hardware description.
    pub hardware: String,
    /// Software version.
    pub software: String,
    /// Hash identifying the board.
    pub boardhash: String,
    /// Which account the unit belongs to.
    pub domaintoken: String,
    /// Highest API version supported.
    pub api: u32,
}

impl Default for Identity {
    fn default() -> Self {
        Identity {
            sernum: String::new(),
            vendorid: 0,
            productcode: 0,
            liftnum: String::new(),
            hardware: String::new(),
            software: format!("canlift {}", env!("CARGO_PKG_VERSION")),
            boardhash: String::new(),
            domaintoken: String::new(),
            api: 1,
        }
    }
}

/// The settings of a session.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Who we are.
    pub identity: Identity,
    /// SHA-1 (hex) of the service password; `None`: service rights cannot be granted.
    pub service_sha1: Option<String>,
    /// SHA-1 (hex) of the setup password.
    pub setup_sha1: Option<String>,
    /// How long an elevation lasts.
    pub privilege_duration: Duration,
    /// Requests that may wait for the bus at once.
    pub max_in_flight: usize,
    /// Requests that may queue behind them before new ones are refused as busy.
    pub max_queued: usize,
    /// Subscriptions at most.
    pub max_subscriptions: usize,
    /// The portal's heartbeat interval: silence for 2 × this + 30 s ends the connection.
    pub heartbeat: Duration,
    /// How long to wait for CONNACK.
    pub connect_timeout: Duration,
    /// Node-ID of the lift controller on net 1 (requests without `node`).
    pub lift_controller: u8,
    /// The CAN networks configured (1 is the bus of `[bus]`).
    pub nets: Vec<u8>,
}

/// Which node and network a request is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Target {
    /// CAN network (1 = the gateway's own bus).
    pub net: u8,
    /// Node-ID.
    pub node: u8,
}

/// What the session knows of an entry.
#[derive(Debug, Clone, PartialEq)]
pub enum Lookup {
    /// Metadata of the entry.
    Entry(Box<Entry>),
    /// The object exists, the sub-index does not.
    NoSub,
    /// The object does not exist.
    NoObject,
    /// No metadata for this node: the request's `datatype` must do.
    Unknown,
}

/// Where metadata comes from: the catalog for the lift controller, EDS files for other nodes.
pub trait Metadata: Send + Sync {
    /// The metadata of (`index`, `sub`) on `target`.
    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup;

    /// The name and hint of the whole object, for a `compact` read of an array.
    fn object_texts(&self, _target: Target, _index: u16) -> Option<(Texts, Texts)> {
        None
    }
}

/// A dictionary access the driver runs and reports back with [`Session::complete`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Job {
    /// Read one sub-object.
    Read {
        /// Where.
        target: Target,
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// Read sub-index 0 (the count) and then sub-indices 1..=count (`compact`).
    ReadArray {
        /// Where.
        target: Target,
        /// Index.
        index: u16,
    },
    /// Write one sub-object.
    Write {
        /// Where.
        target: Target,
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The encoded value.
        data: Vec<u8>,
    },
    /// Store the cloud token durably (write, fsync, rename).
    StoreToken(String),
}

/// The outcome of a [`Job`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum JobResult {
    /// The bytes read (one entry for `Read`, the elements for `ReadArray`).
    Read(Vec<Vec<u8>>),
    /// Written or stored.
    Done,
    /// Refused, with the abort code (SDO timeout 0x05040000, …).
    Failed(AbortCode),
}

/// Identifies a job.
pub type JobId = u64;

/// What the driver must do.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    /// Send this text message.
    Send(String),
    /// Close the connection (the cause is logged).
    Close(String),
    /// Run a job and call [`Session::complete`] with its result.
    Start(JobId, Job),
    /// Start feeding [`Session::value`] with changes of this sub-object.
    Watch(Target, u16, u8),
    /// Stop feeding it.
    Unwatch(Target, u16, u8),
}

/// Where the connection stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// CONNECT sent, waiting for CONNACK.
    Connecting,
    /// Serving the portal with this API version.
    Connected(u32),
    /// Closed.
    Closed,
}

const CONNECT_ID: u64 = 1;
const MAX_TOKEN: usize = 128;

#[derive(Debug, Clone)]
struct Lang {
    preferred: String,
    alternate: String,
}

impl Lang {
    fn english() -> Self {
        Lang {
            preferred: "en".into(),
            alternate: "en".into(),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Form {
    Full,
    Stripped,
    Naked,
}

#[derive(Debug)]
enum Waiting {
    Get {
        id: Value,
        lang: Lang,
        mplex: String,
        entry: Box<Entry>,
        form: Form,
    },
    Put {
        id: Value,
        lang: Lang,
        mplex: String,
    },
    Token {
        id: Value,
        token: String,
    },
    Baseline(Target, u16, u8),
}

#[derive(Debug, Clone)]
struct Subscription {
    inhibit: Duration,
    threshold: f64,
    datatype: DataType,
    last: Option<String>,
    last_push: Option<Instant>,
    pending: Option<String>,
}

#[derive(Debug, Clone, Copy)]
struct Grant {
    level: Privilege,
    until: Instant,
}

/// One connection's protocol state.
pub struct Session {
    settings: Settings,
    metadata: std::sync::Arc<dyn Metadata>,
    token: Option<String>,
    phase: Phase,
    started: Instant,
    last_rx: Instant,
    next_job: JobId,
    waiting: HashMap<JobId, Waiting>,
    in_flight: usize,
    queue: VecDeque<(Value, String, Value)>,
    grant: Option<Grant>,
    failures: u32,
    locked_until: Option<Instant>,
    subscriptions: BTreeMap<(Target, u16, u8), Subscription>,
}

impl Session {
    /// A session that will CONNECT with `token` (the stored cloud token, if any).
    pub fn new(
        settings: Settings,
        metadata: std::sync::Arc<dyn Metadata>,
        token: Option<String>,
        now: Instant,
    ) -> Self {
        Session {
            settings,
            metadata,
            token,
            phase: Phase::Connecting,
            started: now,
            last_rx: now,
            next_job: 1,
            waiting: HashMap::new(),
            in_flight: 0,
            queue: VecDeque::new(),
            grant: None,
            failures: 0,
            locked_until: None,
            subscriptions: BTreeMap::new(),
        }
    }

    /// Where the connection stands.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The CONNECT request to send first (NXg SW003 §5.2.1).
    pub fn connect(&self) -> Output {
        let id = &self.settings.identity;
        let mut identity = json!({
            "sernum": id.sernum,
            "vendorid": id.vendorid,
            "productcode": id.productcode,
            "liftnum": id.liftnum,
            "hardware": id.hardware,
            "software": id.software,
            "api": id.api,
            "boardhash": id.boardhash,
        });
        if let Some(token) = &self.token {
            identity["cloudtoken"] = json!(token);
        }
        let params = json!({"identity": identity, "domaintoken": id.domaintoken});
        Output::Send(rpc::request(&json!(CONNECT_ID), "CONNECT", params))
    }

    /// Subscriptions in force.
    pub fn subscription_count(&self) -> usize {
        self.subscriptions.len()
    }

    /// When to call [`Session::timeout`] next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.phase == Phase::Closed {
            return None;
        }
        let silence = match self.phase {
            Phase::Connecting => self.started + self.settings.connect_timeout,
            _ => self.last_rx + self.settings.heartbeat * 2 + Duration::from_secs(30),
        };
        let pushes = self
            .subscriptions
            .values()
            .filter(|s| s.pending.is_some())
            .filter_map(|s| s.last_push.map(|t| t + s.inhibit));
        pushes.chain([silence]).min()
    }

    /// Something arrived (a text, a ping or pong): the connection is alive.
    pub fn activity(&mut self, now: Instant) {
        self.last_rx = now;
    }

    /// Time passed: pushes whose inhibit gap ended, or the end of a silent connection.
    pub fn timeout(&mut self, now: Instant) -> Vec<Output> {
        let mut out = Vec::new();
        match self.phase {
            Phase::Closed => return out,
            Phase::Connecting if now >= self.started + self.settings.connect_timeout => {
                return self.close("no CONNACK in time".into());
            }
            Phase::Connected(_)
                if now >= self.last_rx + self.settings.heartbeat * 2 + Duration::from_secs(30) =>
            {
                return self.close("connection silent for 2 × heartbeat + 30 s".into());
            }
            _ => {}
        }
        let controller = self.settings.lift_controller;
        for (key, sub) in self.subscriptions.iter_mut() {
            let due = sub.last_push.is_none_or(|t| now >= t + sub.inhibit);
            if due {
                if let Some(value) = sub.pending.take() {
                    out.push(push(key, sub, value, now, controller));
                }
            }
        }
        out
    }

    fn close(&mut self, cause: String) -> Vec<Output> {
        self.phase = Phase::Closed;
        vec![Output::Close(cause)]
    }

    /// A text message from the portal.
    pub fn text(&mut self, text: &str, now: Instant) -> Vec<Output> {
        self.last_rx = now;
        let message = match rpc::parse(text) {
            Ok(m) => m,
            Err(rejected) => {
                return vec![Output::Send(rpc::error(
                    &rejected.id,
                    rejected.code,
                    &rejected.message,
                    None,
                ))]
            }
        };
        match (self.phase, message) {
            (Phase::Closed, _) => Vec::new(),
            (
                Phase::Connecting,
                Incoming::Response {
                    id,
                    result,
                    error,
                    rest,
                },
            ) => {
                if id != json!(CONNECT_ID) {
                    return Vec::new();
                }
                self.connack(result, error, rest)
            }
            (Phase::Connecting, Incoming::Request { id, .. }) => vec![Output::Send(rpc::error(
                &id,
                rpc_codes::INVALID_REQUEST,
                "not connected: CONNACK first",
                None,
            ))],
            (Phase::Connected(_), Incoming::Request { id, method, params }) => {
                self.request(id, method, params, now)
            }
            // Responses to nothing we asked and notifications from the portal: nothing to do.
            _ => Vec::new(),
        }
    }

    fn connack(
        &mut self,
        result: Option<Value>,
        error: Option<Value>,
        rest: Map<String, Value>,
    ) -> Vec<Output> {
        if let Some(error) = error {
            return self.close(format!("portal refused CONNECT: {error}"));
        }
        // DESIGN.md §4: "CONNACK" with `api` beside it, or {"connack": …, "api": N}; no api → 1.
        let (ok, api) = match &result {
            Some(Value::String(s)) => (s.eq_ignore_ascii_case("CONNACK"), rest.get("api")),
            Some(Value::Object(o)) => (
                o.contains_key("connack") || o.contains_key("CONNACK"),
                o.get("api").or_else(|| rest.get("api")),
            ),
            _ => (false, None),
        };
        if !ok {
            return self.close(format!("unexpected CONNECT answer: {result:?}"));
        }
        let theirs = api.and_then(Value::as_u64).unwrap_or(1);
        let agreed = theirs.min(u64::from(self.settings.identity.api)).max(1) as u32;
        self.phase = Phase::Connected(agreed);
        Vec::new()
    }

    fn request(&mut self, id: Value, method: String, params: Value, now: Instant) -> Vec<Output> {
        let needs_bus = matches!(
            method.as_str(),
            "get_canopen_object"
                | "put_canopen_object"
                | "update_unique_token"
                | "reg_canopen_object"
        );
        if needs_bus && self.in_flight >= self.settings.max_in_flight {
            if self.queue.len() >= self.settings.max_queued {
                return vec![Output::Send(rpc::error(
                    &id,
                    rpc_codes::BUSY,
                    "too many requests waiting; try again later",
                    None,
                ))];
            }
            self.queue.push_back((id, method, params));
            return Vec::new();
        }
        self.dispatch(id, method, params, now)
    }

    fn dispatch(&mut self, id: Value, method: String, params: Value, now: Instant) -> Vec<Output> {
        let lang = language(&params);
        let result = match method.as_str() {
            "get_heartbeat" => Ok(vec![Output::Send(rpc::result(&id, json!({"done": 0})))]),
            "update_unique_token" => self.update_token(&id, &params),
            "get_canopen_object" => self.get(&id, &params, &lang),
            "put_canopen_object" => self.put(&id, &params, &lang, now),
            "elevate_privilege" => self.elevate(&id, &params, now),
            "reg_canopen_object" => self.register(&id, &params),
            "unreg_canopen_object" => self.unregister(&id, &params),
            _ => {
                return vec![Output::Send(rpc::error(
                    &id,
                    rpc_codes::METHOD_NOT_FOUND,
                    &format!("unknown method {method:?}"),
                    None,
                ))]
            }
        };
        match result {
            Ok(out) => out,
            Err(Failure::Params(why)) => vec![Output::Send(rpc::error(
                &id,
                rpc_codes::INVALID_PARAMS,
                &why,
                None,
            ))],
            Err(Failure::Nxg(e)) => vec![Output::Send(nxg_error(&id, &e, &lang))],
        }
    }

    fn start(&mut self, job: Job, waiting: Waiting) -> Output {
        let id = self.next_job;
        self.next_job += 1;
        self.in_flight += 1;
        self.waiting.insert(id, waiting);
        Output::Start(id, job)
    }

    fn check_sernum(&self, params: &Value) -> Result<(), Failure> {
        let sernum = params
            .get("sernum")
            .and_then(Value::as_str)
            .ok_or_else(|| Failure::Params("sernum (string) is missing".into()))?;
        if sernum != self.settings.identity.sernum {
            return Err(Failure::Nxg(NxgError {
                code: errors::IDENTITY,
                data: sernum.chars().take(64).collect(),
                detail: Some("The serial number does not match.".into()),
            }));
        }
        Ok(())
    }

    fn update_token(&mut self, id: &Value, params: &Value) -> Result<Vec<Output>, Failure> {
        self.check_sernum(params)?;
        let token = params
            .get("token")
            .and_then(Value::as_str)
            .ok_or_else(|| Failure::Params("token (string) is missing".into()))?;
        if token.chars().count() > MAX_TOKEN {
            return Err(Failure::Nxg(NxgError::new(errors::TOO_LONG, "token")));
        }
        if token.is_empty() || token.chars().any(char::is_control) {
            return Err(Failure::Nxg(NxgError::new(
                AbortCode::INVALID_VALUE,
                "token",
            )));
        }
        let waiting = Waiting::Token {
            id: id.clone(),
            token: token.to_owned(),
        };
        Ok(vec![self.start(Job::StoreToken(token.to_owned()), waiting)])
    }

    fn target(&self, params: &Value) -> Result<(Target, bool), Failure> {
        match params.get("node") {
            None | Some(Value::Null) => Ok((
                Target {
                    net: 1,
                    node: self.settings.lift_controller,
                },
                false,
            )),
            Some(node) => {
                let id = node
                    .get("id")
                    .and_then(Value::as_u64)
                    .filter(|n| (1..=127).contains(n))
                    .ok_or_else(|| Failure::Params("node.id must be 1–127".into()))?;
                let net = match node.get("net") {
                    None | Some(Value::Null) => 1,
                    Some(n) => n
                        .as_u64()
                        .and_then(|n| u8::try_from(n).ok())
                        .ok_or_else(|| Failure::Params("node.net must be a number".into()))?,
                };
                if !self.settings.nets.contains(&net) {
                    return Err(Failure::Params(format!("net {net} is not configured")));
                }
                let target = Target {
                    net,
                    node: id as u8,
                };
                let other = target
                    != Target {
                        net: 1,
                        node: self.settings.lift_controller,
                    };
                Ok((target, other))
            }
        }
    }

    /// The entry for a request, from metadata or, for nodes without it, the given datatype.
    fn entry(
        &self,
        target: Target,
        m: Mplex,
        mplex: &str,
        datatype: Option<&Value>,
    ) -> Result<Entry, Failure> {
        match self.metadata.lookup(target, m.index, m.sub) {
            Lookup::Entry(e) => Ok(*e),
            Lookup::NoSub => Err(Failure::Nxg(NxgError::new(AbortCode::NO_SUB_INDEX, mplex))),
            Lookup::NoObject => Err(Failure::Nxg(NxgError::new(AbortCode::NO_OBJECT, mplex))),
            Lookup::Unknown => {
                let code = datatype.and_then(Value::as_u64).ok_or_else(|| {
                    Failure::Params("node.datatype is needed for a node without metadata".into())
                })?;
                let datatype = NxgDataType::from_code(code as u32)
                    .map_err(|e| Failure::Params(e.to_string()))?;
                Ok(bare_entry(m, datatype))
            }
        }
    }

    fn get(&mut self, id: &Value, params: &Value, lang: &Lang) -> Result<Vec<Output>, Failure> {
        let object = params
            .get("object")
            .ok_or_else(|| Failure::Params("object is missing".into()))?;
        let mplex = object
            .get("mplex")
            .and_then(Value::as_str)
            .ok_or_else(|| Failure::Params("object.mplex (string) is missing".into()))?;
        let m = Mplex::parse(mplex).map_err(|e| Failure::Params(e.to_string()))?;
        let flag = |name: &str| object.get(name).and_then(Value::as_bool).unwrap_or(false);
        let form = if flag("naked") {
            Form::Naked
        } else if flag("stripped") {
            Form::Stripped
        } else {
            Form::Full
        };
        let (target, _) = self.target(params)?;
        let datatype = params.get("node").and_then(|n| n.get("datatype"));
        let entry = self.entry(target, m, mplex, datatype)?;
        if entry.access == Access::Wo {
            return Err(Failure::Nxg(NxgError::new(AbortCode::WRITE_ONLY, mplex)));
        }
        let compact = flag("compact") && m.sub == 1;
        let mut entry = entry;
        if compact {
            if let Some((name, hint)) = self.metadata.object_texts(target, m.index) {
                entry.name = name;
                entry.hint = hint;
            }
        }
        let job = if compact {
            Job::ReadArray {
                target,
                index: m.index,
            }
        } else {
            Job::Read {
                target,
                index: m.index,
                sub: m.sub,
            }
        };
        let waiting = Waiting::Get {
            id: id.clone(),
            lang: lang.clone(),
            mplex: mplex.to_owned(),
            entry: Box::new(entry),
            form,
        };
        Ok(vec![self.start(job, waiting)])
    }

    fn privilege(&self, now: Instant) -> Privilege {
        self.grant
            .filter(|g| now < g.until)
            .map_or(Privilege::User, |g| g.level)
    }

    fn put(
        &mut self,
        id: &Value,
        params: &Value,
        lang: &Lang,
        now: Instant,
    ) -> Result<Vec<Output>, Failure> {
        self.check_sernum(params)?;
        let object = params
            .get("object")
            .ok_or_else(|| Failure::Params("object is missing".into()))?;
        let text = |name: &str| {
            object
                .get(name)
                .and_then(Value::as_str)
                .ok_or_else(|| Failure::Params(format!("object.{name} (string) is missing")))
        };
        let number = |name: &str| {
            object
                .get(name)
                .and_then(Value::as_u64)
                .ok_or_else(|| Failure::Params(format!("object.{name} (number) is missing")))
        };
        let mplex = text("mplex")?;
        let value = text("value")?;
        let datatype = number("datatype")?;
        let physunit = number("physunit")?;
        let m = Mplex::parse(mplex).map_err(|e| Failure::Params(e.to_string()))?;
        let (target, other_node) = self.target(params)?;
        let entry = self.entry(target, m, mplex, object.get("datatype"))?;
        let fail = |code: AbortCode| Err(Failure::Nxg(NxgError::new(code, mplex)));
        if !entry.access.writable() {
            return fail(AbortCode::READ_ONLY);
        }
        let needed = if other_node {
            entry.privilege.max(Privilege::Setup)
        } else {
            entry.privilege
        };
        if needed == Privilege::EngineerOnSite || self.privilege(now) < needed {
            return fail(errors::PRIVILEGE);
        }
        if u64::from(entry.datatype.code()) != datatype
            || u64::from(entry.physunit.code()) != physunit
        {
            return fail(errors::TYPE_MISMATCH);
        }
        let ty = entry.value_type();
        let parsed = types::from_text(ty, value)
            .map_err(|_| Failure::Nxg(NxgError::new(AbortCode::INVALID_VALUE, mplex)))?;
        check_range(&entry, &parsed).map_err(|code| Failure::Nxg(NxgError::new(code, mplex)))?;
        let data = types::encode(ty, &parsed)
            .map_err(|_| Failure::Nxg(NxgError::new(AbortCode::INVALID_VALUE, mplex)))?;
        let job = Job::Write {
            target,
            index: m.index,
            sub: m.sub,
            data,
        };
        let waiting = Waiting::Put {
            id: id.clone(),
            lang: lang.clone(),
            mplex: mplex.to_owned(),
        };
        Ok(vec![self.start(job, waiting)])
    }

    fn elevate(
        &mut self,
        id: &Value,
        params: &Value,
        now: Instant,
    ) -> Result<Vec<Output>, Failure> {
        self.check_sernum(params)?;
        let level = params
            .get("privilege")
            .and_then(Value::as_u64)
            .ok_or_else(|| Failure::Params("privilege (number) is missing".into()))?;
        let level =
            Privilege::from_code(level as u32).map_err(|e| Failure::Params(e.to_string()))?;
        let data = level.code().to_string();
        if !level.grantable_remotely() {
            return Err(Failure::Nxg(NxgError {
                code: errors::PRIVILEGE,
                data,
                detail: Some("Engineer-on-site rights cannot be granted remotely.".into()),
            }));
        }
        if let Some(until) = self.locked_until.filter(|u| now < *u) {
            return Err(Failure::Nxg(NxgError {
                code: errors::IDENTITY,
                data,
                detail: Some(format!(
                    "Too many wrong password hashes; elevation is locked for {} s.",
                    until.duration_since(now).as_secs().max(1)
                )),
            }));
        }
        let passhash = params
            .get("passhash")
            .and_then(Value::as_str)
            .ok_or_else(|| Failure::Params("passhash (string) is missing".into()))?;
        let expected = match level {
            Privilege::User => None,
            Privilege::Service => self.settings.service_sha1.as_deref(),
            _ => self.settings.setup_sha1.as_deref(),
        };
        let ok = level == Privilege::User || expected.is_some_and(|e| hash_matches(e, passhash));
        if !ok {
            self.failures += 1;
            if self.failures >= LOCKOUT_AFTER {
                // 30 s after the third failure, doubling with each further one, up to an hour.
                let exponent = (self.failures - LOCKOUT_AFTER).min(7);
                let lock = (LOCKOUT_BASE * 2u32.pow(exponent)).min(LOCKOUT_CAP);
                self.locked_until = Some(now + lock);
            }
            return Err(Failure::Nxg(NxgError {
                code: errors::IDENTITY,
                data,
                detail: Some("The password hash does not match.".into()),
            }));
        }
        self.failures = 0;
        self.locked_until = None;
        let duration = self.settings.privilege_duration;
        self.grant = Some(Grant {
            level,
            until: now + duration,
        });
        Ok(vec![Output::Send(rpc::result(
            id,
            json!({"duration": duration.as_secs()}),
        ))])
    }

    fn mplex_list(params: &Value) -> Result<Vec<(String, Mplex)>, Failure> {
        let list = params
            .get("mplex")
            .and_then(Value::as_array)
            .ok_or_else(|| Failure::Params("mplex (array of strings) is missing".into()))?;
        list.iter()
            .map(|v| {
                let text = v
                    .as_str()
                    .ok_or_else(|| Failure::Params("mplex entries are strings".into()))?;
                let m = Mplex::parse(text).map_err(|e| Failure::Params(e.to_string()))?;
                Ok((text.to_owned(), m))
            })
            .collect()
    }

    fn register(&mut self, id: &Value, params: &Value) -> Result<Vec<Output>, Failure> {
        let list = Self::mplex_list(params)?;
        let inhibit = params.get("inhibit").map_or(Some(0), Value::as_u64);
        let inhibit = inhibit.ok_or_else(|| Failure::Params("inhibit is a number of ms".into()))?;
        let threshold = params.get("threshold").map_or(Some(0.0), Value::as_f64);
        let threshold = threshold
            .filter(|t| *t >= 0.0)
            .ok_or_else(|| Failure::Params("threshold is a number ≥ 0".into()))?;
        let (target, _) = self.target(params)?;
        let datatype = params.get("node").and_then(|n| n.get("datatype"));
        // All or none: every mplex is checked before any is registered.
        let mut checked = Vec::with_capacity(list.len());
        for (text, m) in &list {
            let entry = self.entry(target, *m, text, datatype)?;
            if entry.access == Access::Wo {
                return Err(Failure::Nxg(NxgError::new(
                    AbortCode::WRITE_ONLY,
                    text.as_str(),
                )));
            }
            checked.push((*m, entry.value_type()));
        }
        let new = checked
            .iter()
            .filter(|(m, _)| !self.subscriptions.contains_key(&(target, m.index, m.sub)))
            .count();
        if self.subscriptions.len() + new > self.settings.max_subscriptions {
            return Err(Failure::Nxg(NxgError {
                code: AbortCode::OUT_OF_MEMORY,
                data: list.first().map(|l| l.0.clone()).unwrap_or_default(),
                detail: Some(format!(
                    "At most {} subscriptions per connection.",
                    self.settings.max_subscriptions
                )),
            }));
        }
        let mut out = vec![Output::Send(rpc::result(id, json!({"done": 0})))];
        for (m, datatype) in checked {
            let key = (target, m.index, m.sub);
            let fresh = !self.subscriptions.contains_key(&key);
            let sub = self.subscriptions.entry(key).or_insert(Subscription {
                inhibit: Duration::ZERO,
                threshold: 0.0,
                datatype,
                last: None,
                last_push: None,
                pending: None,
            });
            sub.inhibit = Duration::from_millis(inhibit);
            sub.threshold = threshold;
            // A registration starts the subscription afresh: the baseline read below is pushed.
            sub.last = None;
            sub.last_push = None;
            sub.pending = None;
            if fresh {
                out.push(Output::Watch(target, m.index, m.sub));
            }
            // The current value is the first push and the baseline for the threshold — after a
            // repeated registration too, so that whoever registered learns where it stands.
            let job = Job::Read {
                target,
                index: m.index,
                sub: m.sub,
            };
            let id = self.next_job;
            self.next_job += 1;
            self.waiting
                .insert(id, Waiting::Baseline(target, m.index, m.sub));
            out.push(Output::Start(id, job));
        }
        Ok(out)
    }

    fn unregister(&mut self, id: &Value, params: &Value) -> Result<Vec<Output>, Failure> {
        let list = Self::mplex_list(params)?;
        let (target, _) = self.target(params)?;
        let mut out = vec![Output::Send(rpc::result(id, json!({"done": 0})))];
        for (_, m) in list {
            if self
                .subscriptions
                .remove(&(target, m.index, m.sub))
                .is_some()
            {
                out.push(Output::Unwatch(target, m.index, m.sub));
            }
        }
        Ok(out)
    }

    /// A job finished.
    pub fn complete(&mut self, job: JobId, result: JobResult, now: Instant) -> Vec<Output> {
        let Some(waiting) = self.waiting.remove(&job) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        match waiting {
            Waiting::Baseline(target, index, sub) => {
                if let JobResult::Read(values) = result {
                    if let Some(bytes) = values.first() {
                        out.extend(self.bytes(target, index, sub, bytes, now));
                    }
                }
                return out;
            }
            Waiting::Get {
                id,
                lang,
                mplex,
                entry,
                form,
            } => {
                self.in_flight -= 1;
                out.push(Output::Send(match result {
                    JobResult::Read(values) => {
                        get_answer(&id, &lang, &mplex, &entry, form, &values)
                    }
                    JobResult::Failed(code) => nxg_error(&id, &NxgError::new(code, mplex), &lang),
                    JobResult::Done => {
                        rpc::error(&id, i64::from(AbortCode::GENERAL.0), "no value", None)
                    }
                }));
            }
            Waiting::Put { id, lang, mplex } => {
                self.in_flight -= 1;
                out.push(Output::Send(match result {
                    JobResult::Failed(code) => nxg_error(&id, &NxgError::new(code, mplex), &lang),
                    _ => rpc::result(&id, json!({"object": {"mplex": mplex}})),
                }));
            }
            Waiting::Token { id, token } => {
                self.in_flight -= 1;
                out.push(Output::Send(match result {
                    JobResult::Failed(code) => {
                        nxg_error(&id, &NxgError::new(code, "token"), &Lang::english())
                    }
                    _ => {
                        self.token = Some(token);
                        rpc::result(&id, json!({"done": 0}))
                    }
                }));
            }
        }
        while self.in_flight < self.settings.max_in_flight {
            let Some((id, method, params)) = self.queue.pop_front() else {
                break;
            };
            out.extend(self.dispatch(id, method, params, now));
        }
        out
    }

    /// The raw bytes of a watched sub-object (read or received in a PDO).
    pub fn bytes(
        &mut self,
        target: Target,
        index: u16,
        sub: u8,
        bytes: &[u8],
        now: Instant,
    ) -> Vec<Output> {
        let Some(s) = self.subscriptions.get(&(target, index, sub)) else {
            return Vec::new();
        };
        match types::decode(s.datatype, bytes) {
            Ok(v) => {
                let text = types::to_text(s.datatype, &v);
                self.value(target, index, sub, text, now)
            }
            Err(_) => Vec::new(),
        }
    }

    /// A watched sub-object has this value now (text form).
    pub fn value(
        &mut self,
        target: Target,
        index: u16,
        sub: u8,
        text: String,
        now: Instant,
    ) -> Vec<Output> {
        let key = (target, index, sub);
        let controller = self.settings.lift_controller;
        let Some(s) = self.subscriptions.get_mut(&key) else {
            return Vec::new();
        };
        let passes = match (&s.last, s.datatype.is_numeric()) {
            (None, _) => true,
            (Some(last), _) if *last == text => false,
            (Some(last), true) => match (last.parse::<f64>(), text.parse::<f64>()) {
                (Ok(a), Ok(b)) => (a - b).abs() >= s.threshold.max(f64::MIN_POSITIVE),
                _ => true,
            },
            (Some(_), false) => true,
        };
        if !passes {
            // Back within the threshold of what the portal has: nothing is owed.
            s.pending = None;
            return Vec::new();
        }
        let free = s.last_push.is_none_or(|t| now >= t + s.inhibit);
        if free {
            s.pending = None;
            vec![push(&key, s, text, now, controller)]
        } else {
            s.pending = Some(text);
            Vec::new()
        }
    }
}

const LOCKOUT_AFTER: u32 = 3;
const LOCKOUT_BASE: Duration = Duration::from_secs(30);
const LOCKOUT_CAP: Duration = Duration::from_secs(3600);

enum Failure {
    Params(String),
    Nxg(NxgError),
}

/// A notification; pushes of nodes other than the lift controller say which node they are from.
fn push(
    key: &(Target, u16, u8),
    s: &mut Subscription,
    text: String,
    now: Instant,
    controller: u8,
) -> Output {
    s.last_push = Some(now);
    s.last = Some(text.clone());
    let (target, index, sub) = *key;
    let mut payload = json!({"mplex": Mplex { index, sub }.to_string(), "value": text});
    if target.net != 1 || target.node != controller {
        payload["node"] = json!({"id": target.node, "net": target.net});
    }
    Output::Send(rpc::notification("canopen_object", payload))
}

/// Compare hex digests (SHA-1 password hashes, SHA-256 of tokens and keys) case-insensitively,
/// in time independent of where they differ.
pub fn hash_matches(expected: &str, given: &str) -> bool {
    let (a, b) = (expected.trim().as_bytes(), given.trim().as_bytes());
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| {
        acc | (x.to_ascii_lowercase() ^ y.to_ascii_lowercase())
    }) == 0
}

fn language(params: &Value) -> Lang {
    let lang = params.get("lang");
    let get = |k: &str| lang.and_then(|l| l.get(k)).and_then(Value::as_str);
    let preferred = get("preferred_language").unwrap_or("en");
    Lang {
        preferred: preferred.chars().take(16).collect(),
        alternate: get("alternate_language")
            .unwrap_or(preferred)
            .chars()
            .take(16)
            .collect(),
    }
}

fn nxg_error(id: &Value, e: &NxgError, lang: &Lang) -> String {
    let message = match (&e.detail, lang.preferred.eq_ignore_ascii_case("de")) {
        (Some(detail), false) => detail.clone(),
        _ => errors::message(e.code, &lang.preferred).to_owned(),
    };
    rpc::error(id, i64::from(e.code.0), &message, Some(json!(e.data)))
}

/// An entry for a node without metadata: the caller's data type, nothing else known.
fn bare_entry(m: Mplex, datatype: NxgDataType) -> Entry {
    let ty = datatype.value_type();
    let (min, max) = match ty.integer_range() {
        Some((lo, hi)) => (Some(Bound::Int(lo)), Some(Bound::Int(hi))),
        None => (None, None),
    };
    Entry {
        index: m.index,
        sub: m.sub,
        objcode: canopen::od::ObjectCode::Var,
        datatype,
        formtype: FormType::Raw,
        physunit: lift417::meta::PhysUnit::None,
        access: Access::Rw,
        privilege: Privilege::Setup,
        name: Texts::default(),
        hint: Texts::default(),
        min,
        max,
        zero: false,
        list: Vec::new(),
        hints: Default::default(),
        default: None,
        pdo: false,
        persist: false,
    }
}

fn check_range(entry: &Entry, value: &CoValue) -> Result<(), AbortCode> {
    if let CoValue::Text(t) = value {
        if let Some(Bound::Int(max)) = entry.max {
            if t.chars().count() as i128 > max {
                return Err(errors::TOO_LONG);
            }
        }
        return Ok(());
    }
    let Some(v) = value.as_f64() else {
        return Ok(());
    };
    if entry.zero && v == 0.0 {
        return Ok(());
    }
    if entry.min.is_some_and(|m| v < m.as_f64()) {
        return Err(AbortCode::VALUE_TOO_LOW);
    }
    if entry.max.is_some_and(|m| v > m.as_f64()) {
        return Err(AbortCode::VALUE_TOO_HIGH);
    }
    Ok(())
}

fn bound(b: Option<Bound>) -> Value {
    match b {
        Some(Bound::Int(v)) => i64::try_from(v)
            .map(Value::from)
            .or_else(|_| u64::try_from(v).map(Value::from))
            .unwrap_or(Value::Null),
        Some(Bound::Real(v)) => json!(v),
        None => Value::Null,
    }
}

fn get_answer(
    id: &Value,
    lang: &Lang,
    mplex: &str,
    entry: &Entry,
    form: Form,
    values: &[Vec<u8>],
) -> String {
    let ty = entry.value_type();
    let mut texts = Vec::with_capacity(values.len());
    for bytes in values {
        match types::decode(ty, bytes) {
            Ok(v) => texts.push(Value::String(types::to_text(ty, &v))),
            Err(_) => {
                return nxg_error(id, &NxgError::new(errors::TYPE_MISMATCH, mplex), lang);
            }
        }
    }
    let mut object = Map::new();
    object.insert("mplex".into(), json!(mplex));
    if form != Form::Naked {
        object.insert("objcode".into(), json!(entry.objcode as u8));
        object.insert("datatype".into(), json!(entry.datatype.code()));
        object.insert("formtype".into(), json!(entry.formtype.code()));
        object.insert("physunit".into(), json!(entry.physunit.code()));
        object.insert("access".into(), json!(entry.access.text()));
        object.insert("privilege".into(), json!(entry.privilege.code()));
    }
    let catalog = Catalog::builtin();
    let mut used = "en";
    if form == Form::Full {
        let name = catalog.text(&entry.name, &lang.preferred, &lang.alternate);
        let hint = catalog.text(&entry.hint, &lang.preferred, &lang.alternate);
        used = name.map_or("en", |n| n.0);
        object.insert("name".into(), json!(name.map_or("", |n| n.1)));
        object.insert("hint".into(), json!(hint.map_or("", |h| h.1)));
    }
    object.insert("value".into(), Value::Array(texts));
    if form != Form::Naked {
        object.insert("min".into(), bound(entry.min));
        object.insert("max".into(), bound(entry.max));
        object.insert("zero".into(), json!(entry.zero));
    }
    let mut result = Map::new();
    if form == Form::Full {
        let list: Vec<Value> = entry
            .list
            .iter()
            .map(|t| json!(catalog.text(t, used, &lang.alternate).map_or("", |x| x.1)))
            .collect();
        object.insert("list".into(), Value::Array(list));
        result.insert("lang".into(), json!({"language": used}));
    }
    result.insert("object".into(), Value::Object(object));
    if form == Form::Full {
        result.insert(
            "hints".into(),
            json!({
                "show_off_at_zero": entry.hints.show_off_at_zero,
                "show_unlimited_at_max": entry.hints.show_unlimited_at_max,
                "show_undefined_at_max": entry.hints.show_undefined_at_max,
            }),
        );
    }
    rpc::result(id, Value::Object(result))
}

/// Metadata of the lift controller from the built-in catalog (any lift, by the offset rules).
#[derive(Debug, Clone, Copy, Default)]
pub struct CatalogMetadata;

impl CatalogMetadata {
    /// The catalog's answer for (`index`, `sub`).
    pub fn lookup(index: u16, sub: u8) -> Lookup {
        let catalog = Catalog::builtin();
        match catalog.lookup(index, sub) {
            Some(found) => {
                let mut entry = found.entry.into_owned();
                entry.index = index;
                Lookup::Entry(Box::new(entry))
            }
            None if catalog.object_for(index).is_some() => Lookup::NoSub,
            None => Lookup::NoObject,
        }
    }
}

#[cfg(test)]
mod tests;

/// Metadata for a bus: the catalog for the lift controller, EDS files for other nodes (names,
/// data types, access and limits as the EDS gives them; writing needs setup rights), nothing for
/// nodes without an EDS (requests then bring their `datatype`).
#[derive(Default)]
pub struct BusMetadata {
    /// The lift controller.
    pub controller: Option<Target>,
    /// Dictionaries imported from EDS files, by node.
    pub nodes: HashMap<Target, canopen::od::ObjectDictionary>,
}

impl Metadata for BusMetadata {
    fn object_texts(&self, target: Target, index: u16) -> Option<(Texts, Texts)> {
        if Some(target) == self.controller {
            let (_, object) = Catalog::builtin().object_for(index)?;
            return Some((object.name.clone(), object.hint.clone()));
        }
        let object = self.nodes.get(&target)?.object(index)?;
        Some((Texts::english(&object.name), Texts::default()))
    }

    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup {
        if Some(target) == self.controller {
            return CatalogMetadata::lookup(index, sub);
        }
        let Some(od) = self.nodes.get(&target) else {
            return Lookup::Unknown;
        };
        let Some(object) = od.object(index) else {
            return Lookup::NoObject;
        };
        let Some(var) = object.subs.get(&sub) else {
            return Lookup::NoSub;
        };
        let datatype = NxgDataType::Cia(var.data_type);
        let mut entry = bare_entry(Mplex { index, sub }, datatype);
        entry.objcode = object.code;
        entry.access = Access::of(var.access);
        entry.name = Texts::english(&var.name);
        entry.formtype = match var.data_type {
            DataType::VisibleString | DataType::UnicodeString => FormType::Text,
            DataType::OctetString | DataType::Domain => FormType::Hex,
            DataType::Real32 | DataType::Real64 => FormType::Real,
            _ => FormType::Number,
        };
        let as_bound = |v: &CoValue| match v {
            CoValue::Int(i) => Some(Bound::Int((*i).into())),
            CoValue::Uint(u) => Some(Bound::Int((*u).into())),
            CoValue::Real32(r) => Some(Bound::Real((*r).into())),
            CoValue::Real64(r) => Some(Bound::Real(*r)),
            _ => None,
        };
        if let Some(low) = var.low.as_ref().and_then(as_bound) {
            entry.min = Some(low);
        }
        if let Some(high) = var.high.as_ref().and_then(as_bound) {
            entry.max = Some(high);
        }
        if let Some(len) = var.max_len {
            entry.max = Some(Bound::Int(len as i128));
        }
        Lookup::Entry(Box::new(entry))
    }
}
