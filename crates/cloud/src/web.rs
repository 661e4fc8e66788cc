//! The web UI (issue 7 §4): pages rendered on the server, one small script (`static/app.js`) for
//! live values, local times and the edit dialog, one style sheet, no build step.
//!
//! Signing in with an account's API key opens a session: a random id in an `HttpOnly`, `Secure`,
//! `SameSite=Strict` cookie, kept in memory as its SHA-256 digest. The pages' script calls the
//! REST API with that cookie; changes need the session's CSRF token as well (see
//! [`crate::api::Caller`]). Every page is sent with a Content-Security-Policy that allows only
//! this origin's script and style.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use axum::extract::{Form, FromRequestParts, Path, Query, State};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{Html, IntoResponse, Redirect, Response};
use axum::routing::{get, post};
use axum::Router;
use lift417::meta::{FormType, PhysUnit};
use serde::Deserialize;
use serde_json::Value;

use crate::api::{read_params, App};
use crate::store::{self, Account, LiftRecord, StoreError};

const COOKIE: &str = "canlift_session";
/// A session ends after this long without a request.
const IDLE: Duration = Duration::from_secs(12 * 3600);
/// Sessions kept at most; the oldest go first.
const MAX_SESSIONS: usize = 10_000;
/// How long a page waits for the gateway's metadata before it shows what it has.
const READ_TIMEOUT: Duration = Duration::from_secs(4);

/// A signed-in browser.
#[derive(Clone)]
pub struct Session {
    /// Whose session it is.
    pub account: Account,
    csrf: String,
    last_used: Instant,
}

impl Session {
    /// Whether `token` is this session's CSRF token (compared in constant time).
    pub fn csrf_matches(&self, token: Option<&str>) -> bool {
        token.is_some_and(|t| nxg::gateway::hash_matches(&self.csrf, t))
    }
}

/// The web UI's sessions, by the SHA-256 digest of their cookie.
#[derive(Default)]
pub struct Sessions {
    by_digest: Mutex<HashMap<String, Session>>,
}

fn cookie(headers: &HeaderMap) -> Option<&str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|c| c.trim().split_once('='))
        .find(|(name, _)| *name == COOKIE)
        .map(|(_, value)| value)
}

impl Sessions {
    /// The session the request's cookie names, if it is still open.
    pub fn get(&self, headers: &HeaderMap) -> Option<Session> {
        let digest = store::digest(cookie(headers)?);
        let mut map = self
            .by_digest
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let session = map.get_mut(&digest)?;
        if session.last_used.elapsed() > IDLE {
            map.remove(&digest);
            return None;
        }
        session.last_used = Instant::now();
        Some(session.clone())
    }

    /// Open a session; the cookie value to set.
    fn open(&self, account: Account) -> String {
        let id = store::secret("");
        let mut map = self
            .by_digest
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        map.retain(|_, s| s.last_used.elapsed() <= IDLE);
        if map.len() >= MAX_SESSIONS {
            if let Some(oldest) = map
                .iter()
                .min_by_key(|(_, s)| s.last_used)
                .map(|(k, _)| k.clone())
            {
                map.remove(&oldest);
            }
        }
        let session = Session {
            account,
            csrf: store::secret(""),
            last_used: Instant::now(),
        };
        map.insert(store::digest(&id), session);
        id
    }

    fn close(&self, headers: &HeaderMap) {
        if let Some(id) = cookie(headers) {
            self.by_digest
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .remove(&store::digest(id));
        }
    }
}

/// HTML-escape text for element content and quoted attributes.
fn esc(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Milliseconds since the epoch as `YYYY-MM-DD HH:MM:SS UTC` (the script shows local time).
fn utc(ms: i64) -> String {
    let Ok(t) = time::OffsetDateTime::from_unix_timestamp(ms.div_euclid(1000)) else {
        return format!("{ms} ms");
    };
    format!(
        "{:04}-{:02}-{:02} {:02}:{:02}:{:02} UTC",
        t.year(),
        u8::from(t.month()),
        t.day(),
        t.hour(),
        t.minute(),
        t.second()
    )
}

fn time(ms: i64) -> String {
    if ms <= 0 {
        return "never".into();
    }
    format!("<time data-ms=\"{ms}\">{}</time>", utc(ms))
}

/// A whole page. `session` absent: the sign-in page (no navigation).
fn page_html(title: &str, session: Option<&Session>, lift: Option<&str>, body: &str) -> Response {
    let nav = session.map_or_else(String::new, |s| {
        format!(
            "<nav><a href=\"/\">Fleet</a><a href=\"/audit\">Audit</a><span class=\"who\">{}</span>\
             <form method=\"post\" action=\"/logout\"><input type=\"hidden\" name=\"csrf\" value=\"{}\">\
             <button>Sign out</button></form></nav>",
            esc(&s.account.name),
            esc(&s.csrf)
        )
    });
    let csrf = session.map_or_else(String::new, |s| {
        format!("<meta name=\"csrf\" content=\"{}\">", esc(&s.csrf))
    });
    let lift = lift.map_or_else(String::new, |l| format!(" data-lift=\"{}\"", esc(l)));
    let html = format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">{csrf}\
         <title>{} · canlift</title><link rel=\"stylesheet\" href=\"/static/style.css\">\
         <script src=\"/static/app.js\" defer></script></head>\
         <body{lift}><header><a class=\"brand\" href=\"/\">canlift</a>{nav}</header><main>{body}</main></body></html>\n",
        esc(title)
    );
    Html(html).into_response()
}

/// A page that says what went wrong.
fn problem(status: StatusCode, session: Option<&Session>, message: &str) -> Response {
    let body = format!(
        "<h1>{}</h1><p class=\"error\">{}</p>",
        status.as_u16(),
        esc(message)
    );
    (status, page_html(status.as_str(), session, None, &body)).into_response()
}

impl From<StoreError> for Response {
    fn from(e: StoreError) -> Response {
        tracing::error!(error = %e, "web page failed on the database");
        problem(
            StatusCode::INTERNAL_SERVER_ERROR,
            None,
            "The database is unavailable.",
        )
    }
}

/// A page's signed-in browser; without a session, the page redirects to the sign-in form.
struct SignedIn(Session);

impl FromRequestParts<Arc<App>> for SignedIn {
    type Rejection = Redirect;

    async fn from_request_parts(parts: &mut Parts, app: &Arc<App>) -> Result<Self, Redirect> {
        app.sessions
            .get(&parts.headers)
            .map(SignedIn)
            .ok_or_else(|| Redirect::to("/login"))
    }
}

async fn login_page() -> Response {
    login_form(None)
}

fn login_form(error: Option<&str>) -> Response {
    let error = error.map_or_else(String::new, |e| {
        format!("<p class=\"error\">{}</p>", esc(e))
    });
    let body = format!(
        "<h1>Sign in</h1>{error}<form class=\"login\" method=\"post\" action=\"/login\">\
         <label>API key <input type=\"password\" name=\"key\" autocomplete=\"current-password\" required autofocus></label>\
         <button>Sign in</button></form>\
         <p class=\"hint\">The key was printed once by <code>canlift cloud account add</code> (or by <code>canlift demo</code>).</p>"
    );
    page_html("Sign in", None, None, &body)
}

#[derive(Deserialize)]
struct LoginForm {
    key: String,
}

async fn login(State(app): State<Arc<App>>, Form(form): Form<LoginForm>) -> Response {
    match app.store.account_by_key(form.key.trim()).await {
        Ok(Some(account)) => {
            tracing::info!(account = %account.name, "web sign-in");
            let id = app.sessions.open(account);
            let cookie = format!(
                "{COOKIE}={id}; Path=/; HttpOnly; Secure; SameSite=Strict; Max-Age={}",
                IDLE.as_secs()
            );
            let mut response = Redirect::to("/").into_response();
            if let Ok(v) = HeaderValue::from_str(&cookie) {
                response.headers_mut().insert(header::SET_COOKIE, v);
            }
            response
        }
        Ok(None) => (
            StatusCode::UNAUTHORIZED,
            login_form(Some("Unknown API key.")),
        )
            .into_response(),
        Err(e) => e.into(),
    }
}

#[derive(Deserialize)]
struct LogoutForm {
    csrf: String,
}

async fn logout(
    State(app): State<Arc<App>>,
    headers: HeaderMap,
    Form(form): Form<LogoutForm>,
) -> Response {
    if let Some(session) = app.sessions.get(&headers) {
        if !session.csrf_matches(Some(&form.csrf)) {
            return problem(StatusCode::FORBIDDEN, Some(&session), "Wrong CSRF token.");
        }
        app.sessions.close(&headers);
    }
    let mut response = Redirect::to("/login").into_response();
    response.headers_mut().insert(
        header::SET_COOKIE,
        HeaderValue::from_static(
            "canlift_session=; Path=/; HttpOnly; Secure; SameSite=Strict; Max-Age=0",
        ),
    );
    response
}

const ERROR_REGISTER: &str = "0x100100";
const LIFT_STATE: &str = "0x502400";

/// The fault column: the error register's bits (CiA 301 §7.5.2.2) and an out-of-service lift
/// state, from the newest stored values.
fn faults(latest: &HashMap<String, (i64, String)>) -> String {
    const BITS: [&str; 8] = [
        "generic",
        "current",
        "voltage",
        "temperature",
        "communication",
        "device profile",
        "reserved",
        "manufacturer",
    ];
    let register = latest
        .get(ERROR_REGISTER)
        .and_then(|(_, v)| v.parse::<u8>().ok());
    let state = latest
        .get(LIFT_STATE)
        .and_then(|(_, v)| v.parse::<u8>().ok());
    if register.is_none() && state.is_none() {
        return "<span class=\"muted\">no data</span>".into();
    }
    let mut found: Vec<&str> = BITS
        .iter()
        .enumerate()
        .filter(|(i, _)| register.is_some_and(|r| r & (1 << i) != 0))
        .map(|(_, name)| *name)
        .collect();
    if state == Some(4) {
        found.push("out of service");
    }
    if found.is_empty() {
        "<span class=\"ok\">none</span>".into()
    } else {
        format!("<span class=\"fault\">{}</span>", esc(&found.join(", ")))
    }
}

fn online_badge(lift: &str, online: bool) -> String {
    let (class, text) = if online {
        ("online", "online")
    } else {
        ("offline", "offline")
    };
    format!(
        "<span class=\"badge {class}\" data-online=\"{}\">{text}</span>",
        esc(lift)
    )
}

/// Lifts per fleet page.
const PAGE: usize = 100;

#[derive(Deserialize)]
struct FleetQuery {
    /// 1-based page.
    page: Option<usize>,
    /// Part of a lift's id or lift number.
    q: Option<String>,
}

async fn fleet(
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
    Query(query): Query<FleetQuery>,
) -> Response {
    let all = match app.store.lifts(&session.account.domain).await {
        Ok(l) => l,
        Err(e) => return e.into(),
    };
    let total = all.len();
    let online_count = all.iter().filter(|l| app.registry.online(&l.id)).count();
    let needle = query.q.as_deref().unwrap_or("").trim().to_lowercase();
    let lifts: Vec<&LiftRecord> = all
        .iter()
        .filter(|l| {
            needle.is_empty()
                || l.id.to_lowercase().contains(&needle)
                || l.liftnum.to_lowercase().contains(&needle)
        })
        .collect();
    let pages = lifts.len().div_ceil(PAGE).max(1);
    let page = query.page.unwrap_or(1).clamp(1, pages);
    let watched = [ERROR_REGISTER.to_owned(), LIFT_STATE.to_owned()];
    let mut rows = String::new();
    for lift in lifts.iter().skip((page - 1) * PAGE).take(PAGE) {
        let latest = match app.store.latest(&lift.id, &watched).await {
            Ok(l) => l,
            Err(e) => return e.into(),
        };
        let _ = write!(
            rows,
            "<tr><td><a href=\"/lifts/{id}\">{id}</a></td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&lift.liftnum),
            online_badge(&lift.id, app.registry.online(&lift.id)),
            time(lift.last_seen),
            faults(&latest),
            id = esc(&lift.id),
        );
    }
    let link =
        |p: usize, text: &str| format!("<a href=\"/?page={p}&amp;q={}\">{text}</a>", esc(&needle));
    let mut pager = format!("<p class=\"ranges\">page {page} of {pages} ");
    if page > 1 {
        pager.push_str(&link(page - 1, "← previous"));
    }
    if page < pages {
        pager.push_str(&link(page + 1, "next →"));
    }
    pager.push_str("</p>");
    let body = if total == 0 {
        format!(
            "<h1>Fleet</h1><p>No lift of domain <code>{}</code> has connected yet.</p>",
            esc(&session.account.domain)
        )
    } else {
        format!(
            "<h1>Fleet</h1><p class=\"summary\">{online_count} of {total} lifts online</p>\
             <form class=\"read\" method=\"get\"><input name=\"q\" placeholder=\"lift id or number\" value=\"{}\">\
             <button>Find</button></form>\
             <table class=\"fleet\"><thead><tr><th>Lift</th><th>Lift number</th><th>State</th>\
             <th>Last seen</th><th>Active faults</th></tr></thead><tbody>{rows}</tbody></table>{pager}",
            esc(&needle)
        )
    };
    page_html("Fleet", Some(&session), None, &body)
}

/// What the gateway says about one object (the result of a full `get_canopen_object`, with
/// its `object` and `hints`), or why it could not.
struct Object {
    mplex: String,
    answer: Result<Value, String>,
    stored: Option<(i64, String)>,
}

impl Object {
    /// The object's metadata and value.
    fn meta(&self) -> Option<&Value> {
        self.answer.as_ref().ok().map(|a| &a["object"])
    }

    fn name(&self) -> String {
        self.meta()
            .and_then(|m| m["name"].as_str())
            .map_or_else(|| self.mplex.clone(), str::to_owned)
    }

    /// The current value: the gateway's answer, else the newest stored one.
    fn raw(&self) -> String {
        let live = self.meta().and_then(|m| match &m["value"] {
            Value::Array(items) => Some(
                items
                    .iter()
                    .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_owned))
                    .collect::<Vec<_>>()
                    .join(", "),
            ),
            _ => None,
        });
        live.or_else(|| self.stored.as_ref().map(|(_, v)| v.clone()))
            .unwrap_or_default()
    }

    fn number(&self, key: &str) -> Option<i64> {
        self.meta().and_then(|m| m[key].as_i64())
    }

    /// The `data-…` attributes the script formats values and fills the edit dialog with.
    fn attributes(&self) -> String {
        let meta = self.meta();
        let get = |k: &str| meta.map_or(Value::Null, |m| m[k].clone());
        let hints = self
            .answer
            .as_ref()
            .map_or(Value::Null, |a| a["hints"].clone());
        let plain = |v: Value| match v {
            Value::Null => String::new(),
            Value::String(s) => s,
            other => other.to_string(),
        };
        let unit = self
            .number("physunit")
            .and_then(|u| PhysUnit::from_code(u as u32).ok())
            .map_or("", PhysUnit::text);
        format!(
            " data-mplex=\"{}\" data-name=\"{}\" data-raw=\"{}\" data-datatype=\"{}\" data-physunit=\"{}\" \
             data-form=\"{}\" data-min=\"{}\" data-max=\"{}\" data-privilege=\"{}\" data-unit=\"{}\" \
             data-list=\"{}\" data-hints=\"{}\"",
            esc(&self.mplex),
            esc(&self.name()),
            esc(&self.raw()),
            esc(&plain(get("datatype"))),
            esc(&plain(get("physunit"))),
            esc(&plain(get("formtype"))),
            esc(&plain(get("min"))),
            esc(&plain(get("max"))),
            esc(&plain(get("privilege"))),
            esc(unit),
            esc(&get("list").to_string()),
            esc(&hints.to_string()),
        )
    }

    fn writable(&self) -> bool {
        self.meta()
            .is_some_and(|m| matches!(m["access"].as_str(), Some("rw" | "wo")))
    }

    fn numeric(&self) -> bool {
        let form = self
            .number("formtype")
            .and_then(|f| FormType::from_code(f as u32).ok());
        match form {
            Some(f) => matches!(
                f,
                FormType::Number | FormType::Real | FormType::Duration | FormType::Choice
            ),
            None => self.raw().parse::<f64>().is_ok(),
        }
    }

    fn history_link(&self, lift: &str) -> String {
        if !self.numeric() {
            return String::new();
        }
        format!(
            "<a class=\"chart\" href=\"/lifts/{}/history?mplex={}\">chart</a>",
            esc(lift),
            esc(&self.mplex)
        )
    }

    fn card(&self, lift: &str) -> String {
        let note = match &self.answer {
            Err(e) if self.stored.is_none() => format!("<p class=\"error\">{}</p>", esc(e)),
            _ => String::new(),
        };
        format!(
            "<div class=\"card\"{}><h3>{}</h3><p><span class=\"v\">{}</span> <span class=\"u\"></span></p>{note}{}</div>",
            self.attributes(),
            esc(&self.name()),
            esc(&self.raw()),
            self.history_link(lift)
        )
    }

    fn row(&self, lift: &str) -> String {
        let meta = self.meta();
        let range = match (self.number("min"), self.number("max")) {
            (Some(lo), Some(hi)) => format!("{lo} … {hi}"),
            _ => String::new(),
        };
        let access = meta
            .and_then(|m| m["access"].as_str())
            .unwrap_or_default()
            .to_owned();
        let privilege = self
            .number("privilege")
            .and_then(|p| lift417::meta::Privilege::from_code(p as u32).ok())
            .map_or("", lift417::meta::Privilege::text);
        let action = if self.writable() {
            "<button class=\"edit\" type=\"button\">Edit</button>".to_owned()
        } else {
            String::new()
        };
        let value = match &self.answer {
            Err(e) => format!("<span class=\"error\">{}</span>", esc(e)),
            Ok(_) => format!(
                "<span class=\"v\">{}</span> <span class=\"u\"></span>",
                esc(&self.raw())
            ),
        };
        let hint = meta
            .and_then(|m| m["hint"].as_str())
            .unwrap_or_default()
            .to_owned();
        format!(
            "<tr{}><td><code>{}</code></td><td title=\"{}\">{}</td><td>{value}</td><td>{}</td>\
             <td>{}</td><td>{}</td><td>{action} {}</td></tr>",
            self.attributes(),
            esc(&self.mplex),
            esc(&hint),
            esc(&self.name()),
            esc(&range),
            esc(&access),
            esc(privilege),
            self.history_link(lift),
        )
    }
}

/// Read full metadata of `mplexes` from the lift's gateway, all at once, each waiting at most
/// [`READ_TIMEOUT`].
async fn read_all(
    app: &App,
    lift: &str,
    mplexes: &[String],
    lang: &str,
    stored: &HashMap<String, (i64, String)>,
) -> Vec<Object> {
    let online = app.registry.online(lift);
    let reads = mplexes.iter().map(|mplex| async move {
        let answer = if online {
            let call = app.registry.call(
                lift,
                "get_canopen_object",
                read_params(mplex, lang, "en", "full"),
            );
            match tokio::time::timeout(READ_TIMEOUT, call).await {
                Ok(Ok(v)) => Ok(v),
                Ok(Err(nxg::portal::Failure::Error(e))) => Err(nxg::errors::describe(&e)),
                Ok(Err(f)) => Err(format!("{f:?}").to_lowercase()),
                Err(_) => Err("no answer in time".into()),
            }
        } else {
            Err("offline".into())
        };
        Object {
            mplex: mplex.clone(),
            answer,
            stored: stored.get(mplex).cloned(),
        }
    });
    futures_util::future::join_all(reads).await
}

#[derive(Deserialize)]
struct LiftQuery {
    lang: Option<String>,
    read: Option<String>,
}

/// The language of the page: `?lang=`, else the browser's first choice, else English.
fn language(query: Option<&str>, headers: &HeaderMap) -> String {
    let browser = headers
        .get(header::ACCEPT_LANGUAGE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split([',', ';', '-']).next());
    query
        .or(browser)
        .map(str::trim)
        .filter(|l| (2..=8).contains(&l.len()) && l.chars().all(|c| c.is_ascii_alphabetic()))
        .unwrap_or("en")
        .to_ascii_lowercase()
}

async fn owned(app: &App, session: &Session, id: &str) -> Result<LiftRecord, Response> {
    match app.store.lift(&session.account.domain, id).await {
        Ok(Some(l)) => Ok(l),
        Ok(None) => Err(problem(
            StatusCode::NOT_FOUND,
            Some(session),
            "No such lift.",
        )),
        Err(e) => Err(e.into()),
    }
}

async fn lift_page(
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
    headers: HeaderMap,
    Path(id): Path<String>,
    Query(q): Query<LiftQuery>,
) -> Response {
    let lift = match owned(&app, &session, &id).await {
        Ok(l) => l,
        Err(r) => return r,
    };
    let lang = language(q.lang.as_deref(), &headers);
    let (live, parameters) = (&app.dashboard.live, &app.dashboard.parameters);
    let read = q
        .read
        .as_deref()
        .map(str::trim)
        .filter(|r| !r.is_empty())
        .map(nxg::mplex::normalized);
    let stored = match app.store.latest(&id, live).await {
        Ok(s) => s,
        Err(e) => return e.into(),
    };
    let mut wanted = live.clone();
    wanted.extend_from_slice(parameters);
    wanted.extend(read.iter().cloned());
    let mut objects = read_all(&app, &id, &wanted, &lang, &stored).await;
    let read_object = read.as_ref().and_then(|_| objects.pop());
    let parameter_objects = objects.split_off(live.len());
    let online = app.registry.online(&id);
    let mut body = format!(
        "<h1>Lift <code>{}</code> {}</h1>\
         <dl class=\"identity\"><dt>Lift number</dt><dd>{}</dd><dt>Vendor-ID</dt><dd>{}</dd>\
         <dt>Product code</dt><dd>{}</dd><dt>Serial number</dt><dd>{}</dd><dt>Hardware</dt><dd>{}</dd>\
         <dt>Software</dt><dd>{}</dd><dt>API</dt><dd>{}</dd><dt>Last seen</dt><dd>{}</dd></dl>",
        esc(&id),
        online_badge(&id, online),
        esc(&lift.liftnum),
        lift.vendorid,
        lift.productcode,
        esc(&lift.sernum),
        esc(&lift.hardware),
        esc(&lift.software),
        lift.api,
        time(lift.last_seen),
    );
    body.push_str("<h2>Live values</h2><div class=\"cards\">");
    for o in &objects {
        body.push_str(&o.card(&id));
    }
    body.push_str("</div>");
    let table_head =
        "<table class=\"objects\"><thead><tr><th>Object</th><th>Name</th><th>Value</th>\
                      <th>Range</th><th>Access</th><th>Privilege</th><th></th></tr></thead><tbody>";
    body.push_str("<h2>Parameters</h2>");
    body.push_str(table_head);
    for o in &parameter_objects {
        body.push_str(&o.row(&id));
    }
    body.push_str("</tbody></table>");
    let _ = write!(
        body,
        "<h2>Read an object</h2><form class=\"read\" method=\"get\">\
         <input name=\"read\" placeholder=\"0x652001\" value=\"{}\" pattern=\"(0[xX])?[0-9A-Fa-f]{{6}}\" required>\
         <input type=\"hidden\" name=\"lang\" value=\"{}\"><button>Read</button></form>",
        esc(read.as_deref().unwrap_or_default()),
        esc(&lang)
    );
    if let Some(o) = read_object {
        body.push_str(table_head);
        body.push_str(&o.row(&id));
        body.push_str("</tbody></table>");
    }
    body.push_str(EDIT_DIALOG);
    page_html(&format!("Lift {id}"), Some(&session), Some(&id), &body)
}

const EDIT_DIALOG: &str = "<dialog id=\"edit\"><form method=\"dialog\">\
    <h2 class=\"title\"></h2><p class=\"hint muted\"></p>\
    <label>New value <span class=\"field\"></span></label><p class=\"range muted\"></p>\
    <fieldset class=\"elevate\" hidden><legend>Privilege needed</legend>\
    <label>Privilege <select name=\"privilege\"><option value=\"1\">service</option><option value=\"2\">setup</option></select></label>\
    <label>Password <input type=\"password\" name=\"password\" autocomplete=\"off\"></label></fieldset>\
    <p class=\"status\" role=\"status\"></p>\
    <menu><button value=\"cancel\" formnovalidate>Cancel</button><button class=\"save\" value=\"save\">Save</button></menu>\
    </form></dialog>";

#[derive(Deserialize)]
struct HistoryQuery {
    mplex: String,
    /// The period shown, ending now.
    minutes: Option<u32>,
}

/// An SVG step chart of `points` (ms, value) between `from` and `to`.
fn chart(points: &[(i64, f64)], from: i64, to: i64) -> String {
    const W: f64 = 800.0;
    const H: f64 = 280.0;
    const LEFT: f64 = 70.0;
    const BOTTOM: f64 = 30.0;
    let lo = points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    let hi = points.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if (hi - lo).abs() < f64::EPSILON {
        (lo - 1.0, hi + 1.0)
    } else {
        (lo, hi)
    };
    let x = |t: i64| LEFT + (t - from) as f64 / (to - from).max(1) as f64 * (W - LEFT - 10.0);
    let y = |v: f64| 10.0 + (hi - v) / (hi - lo) * (H - BOTTOM - 10.0);
    let mut path = String::new();
    let mut previous: Option<f64> = None;
    for &(t, v) in points {
        if let Some(p) = previous {
            let _ = write!(path, " {:.1},{:.1}", x(t), y(p));
        }
        let _ = write!(path, " {:.1},{:.1}", x(t), y(v));
        previous = Some(v);
    }
    if let Some(p) = previous {
        let _ = write!(path, " {:.1},{:.1}", x(to), y(p));
    }
    format!(
        "<svg class=\"chart\" viewBox=\"0 0 {W} {H}\" role=\"img\" aria-label=\"history chart\">\
         <line x1=\"{LEFT}\" y1=\"10\" x2=\"{LEFT}\" y2=\"{b}\" class=\"axis\"/>\
         <line x1=\"{LEFT}\" y1=\"{b}\" x2=\"{r}\" y2=\"{b}\" class=\"axis\"/>\
         <text x=\"{tl}\" y=\"16\" class=\"label\" text-anchor=\"end\">{hi}</text>\
         <text x=\"{tl}\" y=\"{b}\" class=\"label\" text-anchor=\"end\">{lo}</text>\
         <text x=\"{LEFT}\" y=\"{tb}\" class=\"label\">{}</text>\
         <text x=\"{r}\" y=\"{tb}\" class=\"label\" text-anchor=\"end\">{}</text>\
         <polyline class=\"line\" points=\"{}\"/></svg>",
        utc(from),
        utc(to),
        path.trim(),
        b = H - BOTTOM,
        r = W - 10.0,
        tl = LEFT - 6.0,
        tb = H - 8.0,
    )
}

async fn history_page(
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
    Path(id): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Response {
    if let Err(r) = owned(&app, &session, &id).await {
        return r;
    }
    let Ok(mplex) = nxg::mplex::Mplex::parse(&q.mplex) else {
        return problem(
            StatusCode::BAD_REQUEST,
            Some(&session),
            "mplex: six hex digits, e.g. 0x652001.",
        );
    };
    let mplex = mplex.to_string();
    let minutes = q.minutes.unwrap_or(60).clamp(1, 31 * 24 * 60);
    let to = store::now_ms();
    let from = to - i64::from(minutes) * 60_000;
    let rows = match app.store.history(&id, &mplex, from, to).await {
        Ok(r) => r,
        Err(e) => return e.into(),
    };
    let points: Vec<(i64, f64)> = rows
        .iter()
        .filter_map(|(at, v)| v.trim().parse::<f64>().ok().map(|v| (*at, v)))
        .collect();
    let ranges: String = [
        (10u32, "10 min"),
        (60, "1 h"),
        (360, "6 h"),
        (1440, "24 h"),
        (10080, "7 d"),
    ]
    .iter()
    .map(|(m, label)| {
        let class = if *m == minutes {
            " class=\"current\""
        } else {
            ""
        };
        format!(
            "<a{class} href=\"/lifts/{}/history?mplex={}&amp;minutes={m}\">{label}</a>",
            esc(&id),
            esc(&mplex)
        )
    })
    .collect();
    let graph = if points.is_empty() {
        "<p class=\"muted\">No stored numeric values in this period. Values are stored while the \
         gateway pushes them (the dashboard's objects, or a subscription).</p>"
            .to_owned()
    } else {
        chart(&points, from, to)
    };
    let body = format!(
        "<h1>History of <code>{}</code> on <a href=\"/lifts/{id}\">{id}</a></h1>\
         <p class=\"ranges\">{ranges}</p><p class=\"summary\">{} values, last {}</p>{graph}",
        esc(&mplex),
        points.len(),
        points
            .last()
            .map_or_else(|| "—".to_owned(), |p| format!("{} at {}", p.1, time(p.0))),
        id = esc(&id),
    );
    page_html(&format!("History {mplex}"), Some(&session), None, &body)
}

async fn audit_page(State(app): State<Arc<App>>, SignedIn(session): SignedIn) -> Response {
    let entries = match app.store.audit_log(&session.account.domain).await {
        Ok(e) => e,
        Err(e) => return e.into(),
    };
    let mut rows = String::new();
    for e in &entries {
        let _ = write!(
            rows,
            "<tr><td>{}</td><td>{}</td><td><a href=\"/lifts/{lift}\">{lift}</a></td><td>{}</td>\
             <td><code>{}</code></td><td>{}</td><td>{}</td><td class=\"{}\">{}</td></tr>",
            time(e.at),
            esc(&e.account),
            esc(&e.action),
            esc(&e.object),
            esc(e.old_value.as_deref().unwrap_or("")),
            esc(&e.new_value),
            if e.result == "ok" { "ok" } else { "fault" },
            esc(&e.result),
            lift = esc(&e.lift),
        );
    }
    let body = format!(
        "<h1>Audit</h1><p class=\"summary\">Every change and privilege elevation, newest first.</p>\
         <table class=\"audit\"><thead><tr><th>When</th><th>Who</th><th>Lift</th><th>Action</th>\
         <th>Object</th><th>Before</th><th>After</th><th>Result</th></tr></thead><tbody>{rows}</tbody></table>"
    );
    page_html("Audit", Some(&session), None, &body)
}

const APP_JS: &str = include_str!("web/app.js");
const STYLE_CSS: &str = include_str!("web/style.css");

fn asset(kind: &'static str, text: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, kind),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        text,
    )
        .into_response()
}

/// Headers every UI response carries: only this origin's script and style, no framing, no
/// sniffing, no referrer to other sites.
async fn harden(mut response: Response) -> Response {
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
             connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'",
        ),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    response
}

/// The UI's routes.
pub fn routes(app: Arc<App>) -> Router {
    Router::new()
        .route("/", get(fleet))
        .route("/login", get(login_page).post(login))
        .route("/logout", post(logout))
        .route("/lifts/{id}", get(lift_page))
        .route("/lifts/{id}/history", get(history_page))
        .route("/audit", get(audit_page))
        .route(
            "/static/app.js",
            get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }),
        )
        .route(
            "/static/style.css",
            get(|| async { asset("text/css; charset=utf-8", STYLE_CSS) }),
        )
        .layer(axum::middleware::map_response(harden))
        .with_state(app)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escapes_markup() {
        assert_eq!(
            esc("<a href=\"x\">'&'</a>"),
            "&lt;a href=&quot;x&quot;&gt;&#39;&amp;&#39;&lt;/a&gt;"
        );
    }

    #[test]
    fn utc_dates() {
        assert_eq!(utc(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(utc(951_782_400_000), "2000-02-29 00:00:00 UTC");
        assert_eq!(
            utc(1_795_392_000_000 + 3_723_000),
            "2026-11-23 01:02:03 UTC"
        );
    }

    #[test]
    fn fault_column() {
        let mut latest = HashMap::new();
        assert!(faults(&latest).contains("no data"));
        latest.insert(ERROR_REGISTER.to_owned(), (1, "0".to_owned()));
        assert!(faults(&latest).contains("none"));
        latest.insert(ERROR_REGISTER.to_owned(), (1, "129".to_owned()));
        latest.insert(LIFT_STATE.to_owned(), (1, "4".to_owned()));
        assert!(faults(&latest).contains("generic, manufacturer, out of service"));
    }

    #[test]
    fn session_cookie_and_csrf() {
        let sessions = Sessions::default();
        let account = Account {
            name: "a".into(),
            domain: "D".into(),
        };
        let id = sessions.open(account.clone());
        let mut headers = HeaderMap::new();
        headers.insert(
            header::COOKIE,
            HeaderValue::from_str(&format!("theme=dark; {COOKIE}={id}")).unwrap(),
        );
        let session = sessions.get(&headers).unwrap();
        assert_eq!(session.account, account);
        assert!(session.csrf_matches(Some(&session.csrf.clone())));
        assert!(!session.csrf_matches(Some("nope")));
        assert!(!session.csrf_matches(None));
        sessions.close(&headers);
        assert!(sessions.get(&headers).is_none());
        let mut forged = HeaderMap::new();
        forged.insert(
            header::COOKIE,
            HeaderValue::from_static("canlift_session=guess"),
        );
        assert!(sessions.get(&forged).is_none());
    }

    #[test]
    fn page_language() {
        let mut h = HeaderMap::new();
        assert_eq!(language(None, &h), "en");
        h.insert(
            header::ACCEPT_LANGUAGE,
            HeaderValue::from_static("de-DE,de;q=0.9"),
        );
        assert_eq!(language(None, &h), "de");
        assert_eq!(language(Some("FR"), &h), "fr");
        assert_eq!(language(Some("<x>"), &h), "en");
    }

    #[test]
    fn chart_steps_between_values() {
        let svg = chart(&[(0, 1.0), (500, 3.0)], 0, 1000);
        assert!(svg.contains("<polyline"), "{svg}");
        // Three points per change: the old level to the change, then the new one to the end.
        let points = svg
            .split("points=\"")
            .nth(1)
            .unwrap()
            .split('"')
            .next()
            .unwrap();
        assert_eq!(points.split(' ').count(), 4, "{points}");
    }
}
