//! The elevator gateway's side of one connection (NXg SW003 §5–§7), sans-IO.
//!
//! [`Session`] takes WebSocket text messages, object values and time, and returns what to send,
//! which dictionary accesses to run ([`Job`]s, by SDO or on a local dictionary — the driver
//! decides) and when to wake it next. Every rule of the protocol lives here: CONNECT and API
//! negotiation, privileges with expiry and lock-out, the checks of `put_canopen_object`,
//! subscriptions with inhibit and threshold, bounded work in flight, the dead-connection timer.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::sync::PoisonError;
use std::time::{Duration, Instant};

use canopen::sdo::abort::AbortCode;
use canopen::types::{self, DataType as CiaType};
use serde_json::value::RawValue;

use super::answer::{self, Form, Langs, Refusal};
use super::lockout::{Failed, LockoutState};
use super::metadata::{bare, Lookup, Target};
use super::settings::Settings;
use super::Context;
use crate::codes::{rpc_codes, ErrorCode};
use crate::digest;
use crate::meta::{Access, DataType, Description, Privilege};
use crate::msg::{
    self, Done, ElevateAnswer, ElevateParams, ErrorObject, EventKind, EventNotification, GetParams,
    Id, Incoming, Method, MplexText, NodeRef, Notification, PutAnswer, PutParams, RegEventParams,
    RegParams, TokenParams, UnregEventParams, UnregParams,
};

/// A dictionary access the driver runs and reports back with [`Session::handle_job`].
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

/// Why a session ended the connection.
#[derive(Debug, Clone, PartialEq)]
pub enum CloseReason {
    /// No CONNACK within the CONNACK timeout.
    NoConnack,
    /// The portal answered CONNECT with an error.
    Refused(ErrorObject),
    /// The portal answered CONNECT with something else than CONNACK.
    UnexpectedConnack(String),
    /// Nothing heard for 2 × heartbeat + 30 s.
    Silent,
}

impl std::fmt::Display for CloseReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CloseReason::NoConnack => write!(f, "no CONNACK in time"),
            CloseReason::Refused(e) => write!(f, "portal refused CONNECT: {e}"),
            CloseReason::UnexpectedConnack(why) => write!(f, "{why}"),
            CloseReason::Silent => write!(f, "connection silent for 2 × heartbeat + 30 s"),
        }
    }
}

/// What the driver must do.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    /// Send this text message.
    Send(String),
    /// Close the connection.
    Close(CloseReason),
    /// Run a job and call [`Session::handle_job`] with its result.
    Start(JobId, Job),
    /// Start feeding [`Session::handle_value`] with changes of this sub-object.
    Watch(Target, u16, u8),
    /// Stop feeding it.
    Unwatch(Target, u16, u8),
    /// The elevation lock-out changed: store it, so that a restart keeps it.
    Lockout(LockoutState),
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

/// The id of our CONNECT (a string, as the specification's samples).
const CONNECT_ID: u64 = 1;

#[derive(Debug)]
enum Waiting {
    Get {
        id: Option<Id>,
        lang: Langs,
        mplex: String,
        description: Box<Description>,
        form: Form,
    },
    Put {
        id: Option<Id>,
        lang: Langs,
        mplex: String,
    },
    Token {
        id: Option<Id>,
        token: String,
    },
}

/// A request waiting for a free slot.
struct Queued {
    id: Option<Id>,
    method: Method,
    params: Option<Box<RawValue>>,
}

#[derive(Debug, Clone)]
struct Subscription {
    inhibit: Duration,
    threshold: f64,
    datatype: CiaType,
    last: Option<String>,
    last_push: Option<Instant>,
    pending: Option<String>,
}

/// What a portal registered with `reg_canopen_event`.
#[derive(Debug, Clone)]
struct EventSubscription {
    kinds: BTreeSet<EventKind>,
    lang: Langs,
}

#[derive(Debug, Clone, Copy)]
struct Grant {
    level: Privilege,
    until: Instant,
}

/// Why a request fails: bad parameters (−32602) or an NXg refusal.
enum Failure {
    Params(String),
    Nxg(Refusal),
}

impl From<Refusal> for Failure {
    fn from(r: Refusal) -> Failure {
        Failure::Nxg(r)
    }
}

type Outcome = Result<Vec<Output>, Failure>;

/// One connection's protocol state.
pub struct Session {
    settings: Settings,
    context: Context,
    token: Option<String>,
    phase: Phase,
    started: Instant,
    /// When the peer's last NXg message arrived. WebSocket pings and pongs do not count: a
    /// proxy may answer them for a peer that is gone (NXg §5.3, docs/PROTOCOL.md §Heartbeat).
    last_rx: Instant,
    next_job: JobId,
    waiting: HashMap<JobId, Waiting>,
    /// The first reads of new subscriptions, by job: apart from `waiting`, whose entries are
    /// the size of a request's, because a registration starts hundreds at once.
    baselines: HashMap<JobId, (Target, u16, u8)>,
    in_flight: usize,
    queue: VecDeque<Queued>,
    grant: Option<Grant>,
    subscriptions: BTreeMap<(Target, u16, u8), Subscription>,
    /// The subscriptions holding a value until their inhibit gap ends: timers look at these
    /// only, so holding thousands of quiet subscriptions costs a request nothing.
    owed: BTreeSet<(Target, u16, u8)>,
    events: Option<EventSubscription>,
    /// The languages of the last request that named some (NXg §6.3.3: "in the last requested
    /// language"): what a request without `lang` is answered in.
    last_lang: Option<Langs>,
}

impl Session {
    /// A session that will CONNECT with `token` (the stored cloud token, if any).
    pub fn new(settings: Settings, context: Context, token: Option<String>, now: Instant) -> Self {
        Session {
            settings,
            context,
            token,
            phase: Phase::Connecting,
            started: now,
            last_rx: now,
            next_job: 1,
            waiting: HashMap::new(),
            baselines: HashMap::new(),
            in_flight: 0,
            queue: VecDeque::new(),
            grant: None,
            subscriptions: BTreeMap::new(),
            owed: BTreeSet::new(),
            events: None,
            last_lang: None,
        }
    }

    /// Where the connection stands.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The CONNECT request to send first (NXg SW003 §5.2.1).
    pub fn connect(&self) -> Output {
        let params = self.settings.identity.connect(self.token.clone());
        Output::Send(msg::request(
            &Id::counter(CONNECT_ID),
            Method::Connect,
            Some(&params),
        ))
    }

    /// Subscriptions in force.
    pub fn subscription_count(&self) -> usize {
        self.subscriptions.len()
    }

    fn silence_deadline(&self) -> Instant {
        match self.phase {
            Phase::Connecting => self.started + self.settings.connack_timeout,
            _ => self.last_rx + crate::silence_limit(self.settings.heartbeat),
        }
    }

    /// When to call [`Session::handle_timeout`] next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.phase == Phase::Closed {
            return None;
        }
        let pushes = self
            .owed
            .iter()
            .filter_map(|key| self.subscriptions.get(key))
            .filter_map(|s| s.last_push.map(|t| t + s.inhibit));
        pushes.chain([self.silence_deadline()]).min()
    }

    /// Time passed: pushes whose inhibit gap ended, or the end of a silent connection.
    pub fn handle_timeout(&mut self, now: Instant) -> Vec<Output> {
        match self.phase {
            Phase::Closed => return Vec::new(),
            Phase::Connecting if now >= self.silence_deadline() => {
                return self.close(CloseReason::NoConnack);
            }
            Phase::Connected(_) if now >= self.silence_deadline() => {
                return self.close(CloseReason::Silent);
            }
            _ => {}
        }
        let mut out = Vec::new();
        let controller = self.controller();
        let subscriptions = &mut self.subscriptions;
        self.owed.retain(|key| {
            let Some(sub) = subscriptions.get_mut(key) else {
                return false;
            };
            if sub.last_push.is_some_and(|t| now < t + sub.inhibit) {
                return true;
            }
            if let Some(value) = sub.pending.take() {
                out.push(push(key, sub, value, now, controller));
            }
            false
        });
        out
    }

    fn close(&mut self, reason: CloseReason) -> Vec<Output> {
        self.phase = Phase::Closed;
        vec![Output::Close(reason)]
    }

    fn controller(&self) -> Target {
        Target {
            net: 1,
            node: self.settings.lift_controller,
        }
    }

    /// A text message from the portal.
    pub fn handle_text(&mut self, text: &str, now: Instant) -> Vec<Output> {
        self.last_rx = now;
        let message = match msg::parse(text) {
            Ok(m) => m,
            Err(rejected) => {
                let error = ErrorObject::rpc(rejected.code, rejected.message);
                return vec![Output::Send(msg::error_response(
                    rejected.id.as_ref(),
                    &error,
                ))];
            }
        };
        match (self.phase, message) {
            (Phase::Closed, _) => Vec::new(),
            (Phase::Connecting, Incoming::Response { id, outcome, api }) => {
                if id.and_then(|i| i.counter_value()) != Some(CONNECT_ID) {
                    return Vec::new();
                }
                match outcome {
                    Err(error) => self.close(CloseReason::Refused(error)),
                    Ok(result) => match msg::Connack::read(result, api) {
                        Ok(connack) => {
                            let agreed = connack.api.min(self.settings.identity.api).max(1);
                            self.phase = Phase::Connected(agreed);
                            Vec::new()
                        }
                        Err(why) => self.close(CloseReason::UnexpectedConnack(why)),
                    },
                }
            }
            (Phase::Connecting, Incoming::Request { id, .. }) => {
                let error =
                    ErrorObject::rpc(rpc_codes::INVALID_REQUEST, "not connected: CONNACK first");
                vec![Output::Send(msg::error_response(id.as_ref(), &error))]
            }
            (Phase::Connected(_), Incoming::Request { id, method, params }) => {
                // The bus events are served to any portal that calls them, whatever the api:
                // they are canlift's extension, not a version of NXg (docs/PROTOCOL.md §Events).
                let Some(method) = Method::from_name(&method) else {
                    let error = ErrorObject::rpc(
                        rpc_codes::METHOD_NOT_FOUND,
                        format!("unknown method {method:?}"),
                    );
                    return vec![Output::Send(msg::error_response(id.as_ref(), &error))];
                };
                self.request(id, method, params, now)
            }
            // Responses to nothing we asked and notifications from the portal: nothing to do.
            _ => Vec::new(),
        }
    }

    fn request(
        &mut self,
        id: Option<Id>,
        method: Method,
        params: Option<&RawValue>,
        now: Instant,
    ) -> Vec<Output> {
        let needs_bus = matches!(
            method,
            Method::GetCanopenObject
                | Method::PutCanopenObject
                | Method::UpdateUniqueToken
                | Method::RegCanopenObject
        );
        if needs_bus && self.in_flight >= self.settings.max_in_flight {
            if self.queue.len() >= self.settings.max_queued {
                let error = ErrorObject::rpc(
                    rpc_codes::BUSY,
                    "too many requests waiting; try again later",
                );
                return vec![Output::Send(msg::error_response(id.as_ref(), &error))];
            }
            self.queue.push_back(Queued {
                id,
                method,
                params: params.map(ToOwned::to_owned),
            });
            return Vec::new();
        }
        self.dispatch(id, method, params, now)
    }

    /// A request's languages, kept for the requests after it that name none (NXg §6.3.3: an
    /// error is worded "in the last requested language"); English before any.
    fn languages(&mut self, lang: Option<msg::Lang>) -> Langs {
        match lang.and_then(Langs::of) {
            Some(asked) => {
                self.last_lang = Some(asked.clone());
                asked
            }
            None => self.last_lang.clone().unwrap_or_default(),
        }
    }

    fn dispatch(
        &mut self,
        id: Option<Id>,
        method: Method,
        params: Option<&RawValue>,
        now: Instant,
    ) -> Vec<Output> {
        // Refusals before the parameters are read are in the last requested language.
        let mut lang = self.last_lang.clone().unwrap_or_default();
        let result = match method {
            Method::GetHeartbeat => Ok(vec![Output::Send(msg::response(id.as_ref(), &Done::OK))]),
            Method::UpdateUniqueToken => msg::params(params)
                .map_err(Failure::Params)
                .and_then(|p| self.update_token(&id, p)),
            Method::GetCanopenObject => msg::params::<GetParams>(params)
                .map_err(Failure::Params)
                .and_then(|mut p| {
                    lang = self.languages(p.lang.take());
                    self.get(&id, p, &lang)
                }),
            Method::PutCanopenObject => msg::params::<PutParams>(params)
                .map_err(Failure::Params)
                .and_then(|mut p| {
                    lang = self.languages(p.lang.take());
                    let (node, mplex) = (p.node.map(|n| n.id.get()), p.object.mplex.text.clone());
                    self.put(&id, p, &lang, now).inspect_err(|f| {
                        if let Failure::Nxg(r) = f {
                            let why = r.detail.as_deref().unwrap_or(r.code.message("en"));
                            tracing::info!(?id, ?node, %mplex, code = %r.code, why, "put refused");
                        }
                    })
                }),
            Method::ElevatePrivilege => msg::params(params)
                .map_err(Failure::Params)
                .and_then(|p| self.elevate(&id, p, now)),
            Method::RegCanopenObject => msg::params(params)
                .map_err(Failure::Params)
                .and_then(|p| self.register(&id, p)),
            Method::UnregCanopenObject => msg::params(params)
                .map_err(Failure::Params)
                .and_then(|p| self.unregister(&id, p)),
            Method::RegCanopenEvent => msg::params::<RegEventParams>(params)
                .map_err(Failure::Params)
                .map(|p| self.register_events(&id, p)),
            Method::UnregCanopenEvent => params
                .map_or(Ok(UnregEventParams::default()), |p| msg::read(p.get()))
                .map_err(Failure::Params)
                .map(|p| self.unregister_events(&id, p)),
            Method::Connect | Method::CanopenObject | Method::CanopenEvent => {
                let error = ErrorObject::rpc(
                    rpc_codes::METHOD_NOT_FOUND,
                    format!("{method} is not a request a gateway serves"),
                );
                return vec![Output::Send(msg::error_response(id.as_ref(), &error))];
            }
        };
        match result {
            Ok(out) => out,
            Err(Failure::Params(why)) => {
                let error = ErrorObject::rpc(rpc_codes::INVALID_PARAMS, why);
                vec![Output::Send(msg::error_response(id.as_ref(), &error))]
            }
            Err(Failure::Nxg(refusal)) => vec![Output::Send(msg::error_response(
                id.as_ref(),
                &refusal.to_error(&lang),
            ))],
        }
    }

    /// `reg_canopen_event`: the kinds are added to those registered, and what waited
    /// for a portal follows the answer.
    fn register_events(&mut self, id: &Option<Id>, mut p: RegEventParams) -> Vec<Output> {
        let lang = self.languages(p.lang.take());
        let subscription = self.events.get_or_insert_with(|| EventSubscription {
            kinds: BTreeSet::new(),
            lang: lang.clone(),
        });
        subscription.kinds.extend(p.events);
        subscription.lang = lang;
        let mut out = vec![Output::Send(msg::response(id.as_ref(), &Done::OK))];
        out.extend(self.deliver_events());
        out
    }

    /// `unreg_canopen_event`: the kinds named, or all.
    fn unregister_events(&mut self, id: &Option<Id>, p: UnregEventParams) -> Vec<Output> {
        match (p.events, self.events.as_mut()) {
            (Some(kinds), Some(subscription)) => {
                for kind in kinds {
                    subscription.kinds.remove(&kind);
                }
                if subscription.kinds.is_empty() {
                    self.events = None;
                }
            }
            (None, _) => self.events = None,
            (Some(_), None) => {}
        }
        vec![Output::Send(msg::response(id.as_ref(), &Done::OK))]
    }

    /// Bus events waiting in the gateway's queue, as `canopen_event` notifications — once a
    /// portal has registered (until then they wait; kinds it did not register are dropped).
    /// The driver calls this whenever it has queued events.
    pub fn deliver_events(&mut self) -> Vec<Output> {
        let Some(subscription) = &self.events else {
            return Vec::new();
        };
        if !matches!(self.phase, Phase::Connected(_)) {
            return Vec::new();
        }
        let (events, dropped) = self
            .context
            .events
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if dropped > 0 {
            tracing::warn!(
                dropped,
                "bus events lost while no portal took them (queue full)"
            );
        }
        let metadata = self.context.metadata.as_ref();
        let lang = &subscription.lang;
        events
            .iter()
            .filter(|e| subscription.kinds.contains(&e.kind()))
            .map(|e| {
                let payload = EventNotification {
                    event: e.to_wire(metadata, &lang.preferred, &lang.alternate),
                };
                Output::Send(msg::notification(Method::CanopenEvent, &payload))
            })
            .collect()
    }

    fn start(&mut self, job: Job, waiting: Waiting) -> Output {
        let id = self.next_job;
        self.next_job += 1;
        self.in_flight += 1;
        self.waiting.insert(id, waiting);
        Output::Start(id, job)
    }

    fn check_sernum(&self, sernum: &str) -> Result<(), Failure> {
        if sernum != self.settings.identity.sernum {
            return Err(Refusal::detailed(
                ErrorCode::IDENTITY,
                sernum.chars().take(64).collect::<String>(),
                "The serial number does not match.",
            )
            .into());
        }
        Ok(())
    }

    fn update_token(&mut self, id: &Option<Id>, p: TokenParams) -> Outcome {
        self.check_sernum(&p.sernum)?;
        if p.token.chars().count() > msg::MAX_TOKEN {
            return Err(Refusal::new(ErrorCode::TOO_LONG, "token").into());
        }
        if p.token.is_empty() || p.token.chars().any(char::is_control) {
            return Err(Refusal::new(ErrorCode::INVALID_VALUE, "token").into());
        }
        let waiting = Waiting::Token {
            id: id.clone(),
            token: p.token.clone(),
        };
        Ok(vec![self.start(Job::StoreToken(p.token), waiting)])
    }

    /// The node a request is for, and whether it is another one than the lift controller.
    fn target(&self, node: Option<&NodeRef>) -> Result<(Target, bool), Failure> {
        let Some(node) = node else {
            return Ok((self.controller(), false));
        };
        if !self.settings.nets.contains(&node.net) {
            return Err(Failure::Params(format!(
                "node.net: net {} is not configured",
                node.net
            )));
        }
        let target = Target {
            net: node.net,
            node: node.id.get(),
        };
        Ok((target, target != self.controller()))
    }

    /// The description for a request, from metadata or, for nodes without it, the request's
    /// data type.
    fn describe(
        &self,
        target: Target,
        m: &MplexText,
        datatype: Option<u32>,
    ) -> Result<Description, Failure> {
        if self.settings.policy.hidden(target, m.mplex.index) {
            return Err(Refusal::new(ErrorCode::NO_OBJECT, m.text.as_str()).into());
        }
        match self
            .context
            .metadata
            .lookup(target, m.mplex.index, m.mplex.sub)
        {
            Lookup::Found(d) => Ok(*d),
            Lookup::NoSub => Err(Refusal::new(ErrorCode::NO_SUB_INDEX, m.text.as_str()).into()),
            Lookup::NoObject => Err(Refusal::new(ErrorCode::NO_OBJECT, m.text.as_str()).into()),
            Lookup::Unknown => {
                let code = datatype.ok_or_else(|| {
                    Failure::Params("node.datatype is needed for a node without metadata".into())
                })?;
                let datatype = DataType::from_code(code)
                    .map_err(|e| Failure::Params(format!("node.datatype: {e}")))?;
                // What the gateway does with it: reads it, never writes an object nothing
                // describes (the policy refuses it), so it says read-only.
                let mut d = bare(datatype);
                d.access = crate::meta::Access::Ro;
                Ok(d)
            }
        }
    }

    fn get(&mut self, id: &Option<Id>, p: GetParams, lang: &Langs) -> Outcome {
        let object = p.object;
        let form = if object.naked {
            Form::Naked
        } else if object.stripped {
            Form::Stripped
        } else {
            Form::Full
        };
        let (target, _) = self.target(p.node.as_ref())?;
        let datatype = p.node.and_then(|n| n.datatype);
        let mut description = self.describe(target, &object.mplex, datatype)?;
        if description.access == Access::Wo {
            return Err(Refusal::new(ErrorCode::WRITE_ONLY, object.mplex.text).into());
        }
        let m = object.mplex.mplex;
        let compact = object.compact && m.sub == 1;
        let job = if compact {
            if let Some((name, hint)) = self.context.metadata.object_texts(target, m.index) {
                description.name = name;
                description.hint = hint;
            }
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
            mplex: object.mplex.text,
            description: Box::new(description),
            form,
        };
        Ok(vec![self.start(job, waiting)])
    }

    fn privilege(&self, now: Instant) -> Privilege {
        self.grant
            .filter(|g| now < g.until)
            .map_or(Privilege::User, |g| g.level)
    }

    fn put(&mut self, id: &Option<Id>, p: PutParams, lang: &Langs, now: Instant) -> Outcome {
        self.check_sernum(&p.sernum)?;
        let object = p.object;
        let mplex = object.mplex.text.as_str();
        let (target, other_node) = self.target(p.node.as_ref())?;
        let index = object.mplex.mplex.index;
        let described = !matches!(
            self.context
                .metadata
                .lookup(target, index, object.mplex.mplex.sub),
            Lookup::Unknown
        );
        let d = self.describe(target, &object.mplex, Some(object.datatype))?;
        let controller = self.controller();
        if let Err((code, why)) = self
            .settings
            .policy
            .check_write(target, controller, index, described)
        {
            return Err(Refusal::detailed(code, mplex, why).into());
        }
        let refuse = |code: ErrorCode| Err(Refusal::new(code, mplex).into());
        if !d.access.writable() {
            return refuse(ErrorCode::READ_ONLY);
        }
        let needed = if other_node {
            d.privilege.max(Privilege::Setup)
        } else {
            d.privilege
        };
        if needed == Privilege::EngineerOnSite || self.privilege(now) < needed {
            return refuse(ErrorCode::PRIVILEGE);
        }
        if u32::from(d.datatype.code()) != object.datatype
            || u32::from(d.physunit.code()) != object.physunit
        {
            return refuse(ErrorCode::TYPE_MISMATCH);
        }
        let data = match answer::value_to_write(&d, &object.value) {
            Ok(data) => data,
            Err(code) => return refuse(code),
        };
        let m = object.mplex.mplex;
        let job = Job::Write {
            target,
            index: m.index,
            sub: m.sub,
            data,
        };
        let waiting = Waiting::Put {
            id: id.clone(),
            lang: lang.clone(),
            mplex: object.mplex.text,
        };
        Ok(vec![self.start(job, waiting)])
    }

    fn elevate(&mut self, id: &Option<Id>, p: ElevateParams, now: Instant) -> Outcome {
        self.check_sernum(&p.sernum)?;
        let level = Privilege::from_code(p.privilege)
            .map_err(|e| Failure::Params(format!("privilege: {e}")))?;
        let data = level.code().to_string();
        if !level.grantable_remotely() {
            return Err(Refusal::detailed(
                ErrorCode::PRIVILEGE,
                data,
                "Engineer-on-site rights cannot be granted remotely.",
            )
            .into());
        }
        let duration = self.settings.privilege_duration;
        let grant = |session: &mut Session| {
            session.grant = Some(Grant {
                level,
                until: now + duration,
            });
            let answer = ElevateAnswer {
                duration: duration.as_secs(),
            };
            Output::Send(msg::response(id.as_ref(), &answer))
        };
        if level == Privilege::User {
            // Back to user rights; the failure counts stay as they are.
            return Ok(vec![grant(self)]);
        }
        let expected = match level {
            Privilege::Service => self.settings.service_sha1.clone(),
            _ => self.settings.setup_sha1.clone(),
        };
        let Some(expected) = expected else {
            return Err(Refusal::detailed(
                ErrorCode::PRIVILEGE,
                data,
                format!("This gateway grants no {} rights.", level.text()),
            )
            .into());
        };
        let lockout = self.context.lockout.clone();
        let mut lockout = lockout.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(left) = lockout.locked(level, now) {
            let seconds = left.as_secs().max(1);
            tracing::warn!(
                level = level.text(),
                seconds,
                "elevation refused: locked out"
            );
            return Err(Refusal::detailed(
                ErrorCode::DEVICE_STATE,
                data,
                format!(
                    "Elevation to {} rights is locked for {seconds} s after wrong password hashes.",
                    level.text()
                ),
            )
            .into());
        }
        if !digest::matches(&expected, &p.passhash) {
            match lockout.failure(level, now) {
                Failed::Counted(n) => {
                    tracing::warn!(
                        level = level.text(),
                        failures = n,
                        "elevation refused: wrong password hash"
                    )
                }
                Failed::Locked(lock) => tracing::warn!(
                    level = level.text(),
                    seconds = lock.as_secs(),
                    "elevation refused: wrong password hash; locked out"
                ),
            }
            let state = lockout.state(now);
            let refusal = Refusal::detailed(
                ErrorCode::IDENTITY,
                data,
                "The password hash does not match.",
            );
            let out = Output::Send(msg::error_response(
                id.as_ref(),
                &refusal.to_error(&Langs::default()),
            ));
            return Ok(vec![out, Output::Lockout(state)]);
        }
        lockout.success(level);
        let state = lockout.state(now);
        drop(lockout);
        tracing::info!(
            level = level.text(),
            seconds = duration.as_secs(),
            "privilege granted"
        );
        Ok(vec![grant(self), Output::Lockout(state)])
    }

    fn register(&mut self, id: &Option<Id>, p: RegParams) -> Outcome {
        let (target, _) = self.target(p.node.as_ref())?;
        let datatype = p.node.and_then(|n| n.datatype);
        // All or none: every mplex is checked before any is registered.
        let mut checked = Vec::with_capacity(p.mplex.len());
        for m in &p.mplex {
            let d = self.describe(target, m, datatype)?;
            if d.access == Access::Wo {
                return Err(Refusal::new(ErrorCode::WRITE_ONLY, m.text.as_str()).into());
            }
            checked.push((m.mplex, d.datatype.value_type()));
        }
        let new = checked
            .iter()
            .filter(|(m, _)| !self.subscriptions.contains_key(&(target, m.index, m.sub)))
            .count();
        if self.subscriptions.len() + new > self.settings.max_subscriptions {
            return Err(Refusal::detailed(
                ErrorCode::OUT_OF_MEMORY,
                p.mplex.first().map(|m| m.text.clone()).unwrap_or_default(),
                format!(
                    "At most {} subscriptions per connection.",
                    self.settings.max_subscriptions
                ),
            )
            .into());
        }
        let inhibit = Duration::from_millis(p.inhibit);
        let mut out = vec![Output::Send(msg::response(id.as_ref(), &Done::OK))];
        for (m, datatype) in checked {
            let key = (target, m.index, m.sub);
            if !self.subscriptions.contains_key(&key) {
                out.push(Output::Watch(target, m.index, m.sub));
            }
            // A registration starts the subscription afresh: the baseline read below is the
            // first push and the base of the threshold — after a repeated registration too, so
            // that whoever registered learns where the value stands.
            self.subscriptions.insert(
                key,
                Subscription {
                    inhibit,
                    threshold: p.threshold,
                    datatype,
                    last: None,
                    last_push: None,
                    pending: None,
                },
            );
            let job = Job::Read {
                target,
                index: m.index,
                sub: m.sub,
            };
            let id = self.next_job;
            self.next_job += 1;
            self.baselines.insert(id, (target, m.index, m.sub));
            out.push(Output::Start(id, job));
        }
        Ok(out)
    }

    fn unregister(&mut self, id: &Option<Id>, p: UnregParams) -> Outcome {
        let (target, _) = self.target(p.node.as_ref())?;
        let mut out = vec![Output::Send(msg::response(id.as_ref(), &Done::OK))];
        for m in p.mplex {
            let key = (target, m.mplex.index, m.mplex.sub);
            if self.subscriptions.remove(&key).is_some() {
                self.owed.remove(&key);
                out.push(Output::Unwatch(target, m.mplex.index, m.mplex.sub));
            }
        }
        Ok(out)
    }

    /// A job finished.
    pub fn handle_job(&mut self, job: JobId, result: JobResult, now: Instant) -> Vec<Output> {
        if let Some((target, index, sub)) = self.baselines.remove(&job) {
            // A burst of registrations does not keep its table for the rest of the connection.
            if self.baselines.is_empty() && self.baselines.capacity() > 64 {
                self.baselines.shrink_to(64);
            }
            return match result {
                JobResult::Read(values) => values
                    .first()
                    .map(|bytes| self.handle_bytes(target, index, sub, bytes, now))
                    .unwrap_or_default(),
                _ => Vec::new(),
            };
        }
        let Some(waiting) = self.waiting.remove(&job) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        let send_error = |id: &Option<Id>, refusal: Refusal, lang: &Langs| {
            Output::Send(msg::error_response(id.as_ref(), &refusal.to_error(lang)))
        };
        match waiting {
            Waiting::Get {
                id,
                lang,
                mplex,
                description,
                form,
            } => {
                self.in_flight -= 1;
                let answer = match result {
                    JobResult::Read(values) => {
                        let metadata = &*self.context.metadata;
                        answer::object(metadata, &description, form, &lang, &mplex, &values)
                            .map_err(|code| Refusal::new(code, mplex.as_str()))
                    }
                    JobResult::Failed(code) => Err(Refusal::new(code, mplex.as_str())),
                    JobResult::Done => Err(Refusal::new(ErrorCode::GENERAL, mplex.as_str())),
                };
                out.push(match answer {
                    Ok(a) => Output::Send(msg::response(id.as_ref(), &a)),
                    Err(refusal) => send_error(&id, refusal, &lang),
                });
            }
            Waiting::Put { id, lang, mplex } => {
                self.in_flight -= 1;
                out.push(match result {
                    JobResult::Failed(code) => send_error(&id, Refusal::new(code, mplex), &lang),
                    _ => Output::Send(msg::response(id.as_ref(), &PutAnswer::new(&mplex))),
                });
            }
            Waiting::Token { id, token } => {
                self.in_flight -= 1;
                out.push(match result {
                    JobResult::Failed(code) => {
                        send_error(&id, Refusal::new(code, "token"), &Langs::default())
                    }
                    _ => {
                        self.token = Some(token);
                        Output::Send(msg::response(id.as_ref(), &Done::OK))
                    }
                });
            }
        }
        while self.in_flight < self.settings.max_in_flight {
            let Some(q) = self.queue.pop_front() else {
                break;
            };
            out.extend(self.dispatch(q.id, q.method, q.params.as_deref(), now));
        }
        out
    }

    /// The raw bytes of a watched sub-object (read or received in a PDO).
    pub fn handle_bytes(
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
                self.handle_value(target, index, sub, text, now)
            }
            Err(_) => Vec::new(),
        }
    }

    /// A watched sub-object has this value now (text form).
    pub fn handle_value(
        &mut self,
        target: Target,
        index: u16,
        sub: u8,
        text: String,
        now: Instant,
    ) -> Vec<Output> {
        let key = (target, index, sub);
        let controller = self.controller();
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
            self.owed.remove(&key);
            return Vec::new();
        }
        let free = s.last_push.is_none_or(|t| now >= t + s.inhibit);
        if free {
            s.pending = None;
            self.owed.remove(&key);
            vec![push(&key, s, text, now, controller)]
        } else {
            s.pending = Some(text);
            self.owed.insert(key);
            Vec::new()
        }
    }
}

/// A notification; pushes of nodes other than the lift controller say which node they are from.
fn push(
    key: &(Target, u16, u8),
    s: &mut Subscription,
    text: String,
    now: Instant,
    controller: Target,
) -> Output {
    s.last_push = Some(now);
    s.last = Some(text.clone());
    let (target, index, sub) = *key;
    let node = (target != controller)
        .then(|| msg::NodeId::new(target.node).map(|id| NodeRef::new(id, target.net)))
        .flatten();
    let payload = Notification {
        mplex: crate::mplex::Mplex { index, sub }.to_string(),
        value: text,
        node,
    };
    Output::Send(msg::notification(Method::CanopenObject, &payload))
}
