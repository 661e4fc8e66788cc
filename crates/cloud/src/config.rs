//! The portal's configuration (docs/PORTAL.md §Configuration): `[server]`, `[state]`,
//! `[database]`, `[gateways]`, `[dashboard]`, `[alarms]`, `[insights]`, `[cluster]`, `[oidc]`.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use nxg::mplex::Mplex;
use nxg::msg::EventKind;
use nxg::portal::Settings;
use serde::{Deserialize, Serialize};

use cloud_cluster::ClusterSection;
use cloud_types::alarms::Severity;
use cloud_types::users::Role;

/// `[server]`: the one TLS port.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerSection {
    /// Address to listen on.
    pub listen: SocketAddr,
    /// PEM certificate chain; with `tls_key` absent a development CA and certificate are
    /// generated into the state directory.
    pub tls_cert: Option<PathBuf>,
    /// PEM private key.
    pub tls_key: Option<PathBuf>,
    /// PEM CA certificates: gateways must present a certificate signed by one of them.
    pub client_ca: Option<PathBuf>,
    /// Requests per second one API key may make, on average (bursts of two seconds' worth);
    /// more are answered 429 with `Retry-After`. 0: no limit.
    pub requests_per_key_s: u32,
    /// Hours between rotations of the TLS session-ticket key (kept in the state directory, so
    /// a restarted portal resumes its gateways' sessions; a ticket counts for at most two
    /// periods). 0: no tickets, every handshake is a full one.
    pub ticket_rotate_h: u32,
    /// Sign-in secrets checked at once (argon2id, 19 MiB each), on threads of their own at a
    /// lower priority; 0: as many as the machine has cores. A few more wait; beyond them a
    /// sign-in is answered 429 (docs/PORTAL.md §Users and roles).
    pub password_checks_at_once: usize,
    /// Load balancers and proxies (addresses or CIDR blocks) whose word on the client's
    /// address counts: the PROXY protocol v2 header they send first, or `X-Forwarded-For`
    /// (docs/PORTAL.md §Behind a load balancer). No one else's is believed.
    pub trusted_proxies: Vec<String>,
    /// `/metrics` on a listener of its own (plain HTTP, for a scraper on the portal's network),
    /// and not on the public port.
    pub metrics_listen: Option<SocketAddr>,
    /// `/metrics` on the public port for requests with `Authorization: Bearer` this token.
    /// Neither set: `/metrics` is not served on the public port.
    pub metrics_token: Option<String>,
}

impl Default for ServerSection {
    fn default() -> Self {
        ServerSection {
            listen: SocketAddr::from(([127, 0, 0, 1], 8443)),
            tls_cert: None,
            tls_key: None,
            client_ca: None,
            requests_per_key_s: 100,
            ticket_rotate_h: 12,
            password_checks_at_once: 0,
            trusted_proxies: Vec::new(),
            metrics_listen: None,
            metrics_token: None,
        }
    }
}

/// `[state]`: the portal's durable state (the SQLite database by default, the development
/// PKI).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StateSection {
    /// Directory for durable state.
    pub dir: PathBuf,
}

impl Default for StateSection {
    fn default() -> Self {
        StateSection {
            dir: "state".into(),
        }
    }
}

/// `[database]`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DatabaseSection {
    /// `sqlite://PATH`; absent: `sqlite://STATE_DIR/canlift.db`.
    pub url: Option<String>,
    /// Days telemetry is kept (older values are deleted every hour); 0 keeps it forever.
    pub telemetry_days: u32,
    /// Days bus events are kept (the same way); 0 keeps them forever.
    pub events_days: u32,
    /// Days the roll-ups of pushed values (per minute and per hour: what charts of long periods
    /// read, docs/PORTAL.md §History) are kept; 0 keeps them forever.
    pub rollup_days: u32,
    /// Pushed values that may wait for the database. When they fill it, a connection waits for
    /// room (at most 2 s; meanwhile it reads nothing from its gateway, which TCP slows down);
    /// while the database is unreachable further values are dropped and counted
    /// (`canlift_telemetry_dropped_total`).
    pub telemetry_queue: usize,
    /// Connections to PostgreSQL this process opens at most (two more write telemetry). In a
    /// cluster every process opens as many: processes × (this + 2) must stay below the
    /// server's `max_connections` minus `superuser_reserved_connections` (100 − 3 by default),
    /// or PostgreSQL refuses connections while the pools grow under load. SQLite takes 4.
    pub connections: u32,
}

impl Default for DatabaseSection {
    fn default() -> Self {
        DatabaseSection {
            url: None,
            telemetry_days: 30,
            events_days: 90,
            rollup_days: 400,
            telemetry_queue: 65_536,
            connections: cloud_store::POSTGRES_CONNECTIONS,
        }
    }
}

/// `[gateways]`: how gateways are served.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GatewaysSection {
    /// Seconds between `get_heartbeat` requests.
    pub heartbeat_s: u64,
    /// Seconds a gateway has to send CONNECT.
    pub connect_timeout_s: u64,
    /// Seconds an operator request waits for the gateway's answer.
    pub request_timeout_s: u64,
    /// Operator requests outstanding per gateway.
    pub max_in_flight: usize,
    /// Requests waiting behind them per gateway.
    pub max_queued: usize,
    /// Largest message accepted from a gateway (bytes).
    pub max_message_bytes: usize,
    /// Messages a gateway may send of its own per second (answers to the portal's requests
    /// do not count), on average over two seconds; a connection above it is closed (1008)
    /// without touching the others.
    pub max_messages_per_s: u32,
    /// What a CONNECT with a valid token from another board (`boardhash`) gets.
    pub boardhash_change: BoardhashChange,
    /// Days after which a gateway's token is replaced when it connects (NXg §5.4); 0: never.
    pub token_rotate_days: u32,
    /// Longest value stored (bytes of its text form); a longer one is not stored and counted
    /// (`canlift_telemetry_dropped_total{reason="too_large"}`).
    pub max_value_bytes: usize,
    /// Bytes of values one lift may store per hour (on average: a burst of up to an hour's
    /// worth); beyond it values are not stored, counted (`reason="quota"`), and the lift gets
    /// a `storage-quota` alarm, cleared after an hour within the quota.
    pub max_stored_bytes_per_hour: u64,
    /// Days refused CONNECTs are kept (docs/PORTAL.md §Refused gateways).
    pub refused_keep_days: u32,
    /// Refused CONNECTs kept at most (the newest).
    pub refused_keep_rows: u32,
}

/// What the portal does when a gateway with a valid token reports another `boardhash` than at
/// its first contact: the board was replaced, or the token was copied to another device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BoardhashChange {
    /// Refuse the connection (recorded with the refused attempts) until an administrator
    /// resets the lift's token.
    Refuse,
    /// Accept it, record the new board, audit it and raise a `board-changed` alarm.
    #[default]
    Alarm,
    /// Accept it, record the new board and audit it.
    Accept,
}

impl Default for GatewaysSection {
    fn default() -> Self {
        GatewaysSection {
            heartbeat_s: 300,
            connect_timeout_s: 10,
            request_timeout_s: 10,
            max_in_flight: 16,
            max_queued: 64,
            max_message_bytes: 65536,
            max_messages_per_s: 5000,
            boardhash_change: BoardhashChange::default(),
            token_rotate_days: 0,
            max_value_bytes: 4096,
            max_stored_bytes_per_hour: 8 << 20,
            refused_keep_days: 30,
            refused_keep_rows: 100_000,
        }
    }
}

impl GatewaysSection {
    /// How old a token may be before it is replaced at CONNECT (`None`: never).
    pub fn token_lifetime(&self) -> Option<Duration> {
        (self.token_rotate_days > 0)
            .then(|| Duration::from_secs(u64::from(self.token_rotate_days) * 86_400))
    }

    /// The session settings.
    pub fn settings(&self) -> Settings {
        Settings {
            api: nxg::msg::API,
            connect_timeout: Duration::from_secs(self.connect_timeout_s.max(1)),
            heartbeat: Duration::from_secs(self.heartbeat_s.max(1)),
            request_timeout: Duration::from_secs(self.request_timeout_s.max(1)),
            max_in_flight: self.max_in_flight.max(1),
            max_queued: self.max_queued,
        }
    }
}

/// `[dashboard]`: what every gateway is asked to push, and what the web UI shows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DashboardSection {
    /// Objects subscribed on every gateway when it connects (`reg_canopen_object`, NXg §7.3):
    /// stored as telemetry, shown live on the lift page; 0x100100 and 0x502400 give the fleet
    /// page its fault column, and what `[insights]` reads must be among them.
    pub live: Vec<String>,
    /// Inhibit time of those subscriptions (ms).
    pub inhibit_ms: u64,
    /// The lift page's parameter table.
    pub parameters: Vec<String>,
    /// Bus event kinds registered on every gateway (docs/PROTOCOL.md §Events; one that does
    /// not have them answers −32601); empty: none.
    pub events: Vec<EventKind>,
}

/// The dashboard as the portal uses it: the objects read once, when the portal starts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Dashboard {
    /// Subscribed on every gateway.
    pub live: Vec<Mplex>,
    /// Their inhibit time (ms).
    pub inhibit_ms: u64,
    /// The lift page's parameter table.
    pub parameters: Vec<Mplex>,
    /// Bus event kinds registered on every gateway.
    pub events: Vec<EventKind>,
}

impl DashboardSection {
    /// The dashboard's objects read; a text that is no mplex is named in the error.
    pub fn dashboard(&self) -> Result<Dashboard, String> {
        let read = |key: &str, list: &[String]| {
            list.iter()
                .map(|m| Mplex::parse(m).map_err(|e| format!("dashboard.{key}: {e}")))
                .collect::<Result<Vec<_>, _>>()
        };
        Ok(Dashboard {
            live: read("live", &self.live)?,
            inhibit_ms: self.inhibit_ms,
            parameters: read("parameters", &self.parameters)?,
            events: self.events.clone(),
        })
    }
}

impl Default for DashboardSection {
    fn default() -> Self {
        let list = |l: &[&str]| l.iter().map(|s| (*s).to_owned()).collect();
        DashboardSection {
            live: list(&[
                "0x652001", "0x652002", "0x638301", "0x639001", "0x630101", "0x648001", "0x502300",
                "0x502400", "0x100100", "0x440001", "0x440004", "0x440301",
            ]),
            inhibit_ms: 500,
            parameters: list(&[
                "0x411300", "0x411400", "0x411500", "0x411200", "0x502200", "0x640801", "0x503000",
            ]),
            events: EventKind::ALL.to_vec(),
        }
    }
}

/// `[[alarms.webhooks]]`: a receiver of alarm changes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebhookSection {
    /// What the audit log and the logs call the receiver (its URL may hold credentials and
    /// internal names); default `webhook N`, its place in the list.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// `https://…` (or `http://` to a receiver on this host or its network); `USER:PASSWORD@`
    /// before the host is sent as Basic authentication.
    pub url: String,
    /// The signing key (Standard Webhooks): `whsec_` and base64 (the key's bytes), or any other
    /// text (its UTF-8 bytes).
    pub secret: String,
    /// Changes of less severe alarms are not sent.
    #[serde(default = "major")]
    pub min_severity: Severity,
    /// PEM CA certificates to trust for this receiver; absent: the system's roots.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
}

fn major() -> Severity {
    Severity::Major
}

/// The severity of each condition (`[alarms.severity]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct Severities {
    /// The gateway is gone.
    pub lift_offline: Severity,
    /// A network is bus-off.
    pub bus_off: Severity,
    /// A network cannot be reached by its gateway.
    pub bus_offline: Severity,
    /// A network is error-passive.
    pub error_passive: Severity,
    /// A node fell silent.
    pub node_offline: Severity,
    /// A node reported an error.
    pub emcy: Severity,
    /// The gateway's board changed under its token.
    pub board_changed: Severity,
    /// The lift pushed more than it may store.
    pub storage_quota: Severity,
    /// A trend rule saw an object's mean rise (`[[insights.trends]]`).
    pub trend: Severity,
}

impl Default for Severities {
    fn default() -> Self {
        Severities {
            lift_offline: Severity::Critical,
            bus_off: Severity::Critical,
            bus_offline: Severity::Critical,
            error_passive: Severity::Minor,
            node_offline: Severity::Major,
            emcy: Severity::Major,
            board_changed: Severity::Major,
            storage_quota: Severity::Major,
            trend: Severity::Minor,
        }
    }
}

/// `[alarms]`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlarmsSection {
    /// Seconds a gateway may be offline before its lift has a `lift-offline` alarm.
    pub offline_after_s: u64,
    /// `[alarms.severity]`: how urgent each condition is (`minor`, `major`, `critical`).
    pub severity: Severities,
    /// Receivers of alarm changes.
    pub webhooks: Vec<WebhookSection>,
}

impl Default for AlarmsSection {
    fn default() -> Self {
        AlarmsSection {
            offline_after_s: 120,
            severity: Severities::default(),
            webhooks: Vec::new(),
        }
    }
}

/// `[insights]`: what availability reports and trend alarms read (docs/PORTAL.md
/// §Availability, §Trends). The objects are the lift controller's and must be among `[dashboard]
/// live` (the default list has those of the defaults here): insights read what is stored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InsightsSection {
    /// The lift's state object.
    pub state: String,
    /// Its values that mean "out of service"; any other value means in service.
    pub out_of_service: Vec<i64>,
    /// The trip counter.
    pub trips: String,
    /// The door cycle counter.
    pub door_cycles: String,
    /// The reopening counter.
    pub reopenings: String,
    /// The availability an account promises unless it set its own (0–1).
    pub target: f64,
    /// Trend rules.
    pub trends: Vec<TrendRule>,
}

impl Default for InsightsSection {
    fn default() -> Self {
        InsightsSection {
            state: "0x502400".into(),
            out_of_service: vec![4, 5],
            trips: "0x652001".into(),
            door_cycles: "0x440001".into(),
            reopenings: "0x440004".into(),
            target: 0.99,
            trends: vec![TrendRule {
                mplex: "0x440301".into(),
                name: "Door closing time".into(),
                rise_percent: 20.0,
                baseline_h: 24.0 * 7.0,
                window_h: 24.0,
            }],
        }
    }
}

/// `[[insights.trends]]`: a `trend` alarm when an object's mean over the last `window_h` hours
/// exceeds its mean over the `baseline_h` hours before by more than `rise_percent` %; cleared
/// when it no longer does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrendRule {
    /// The object (of the lift controller), a stored numeric one.
    pub mplex: String,
    /// What the alarm calls it.
    pub name: String,
    /// The rise that raises the alarm (%).
    pub rise_percent: f64,
    /// The baseline's length (hours, fractions allowed).
    pub baseline_h: f64,
    /// The recent window's length (hours, fractions allowed).
    pub window_h: f64,
}

/// `[insights]` as the portal uses it: the objects parsed, the rules checked.
#[derive(Debug, Clone, PartialEq)]
pub struct Insights {
    /// The lift's state object.
    pub state: Mplex,
    /// Its out-of-service values.
    pub out_of_service: Vec<i64>,
    /// Trip, door cycle and reopening counters.
    pub trips: Mplex,
    /// Door cycles.
    pub door_cycles: Mplex,
    /// Reopenings.
    pub reopenings: Mplex,
    /// The default availability target.
    pub target: f64,
    /// Trend rules with their object parsed.
    pub trends: Vec<(Mplex, TrendRule)>,
}

impl InsightsSection {
    /// The section checked; what is wrong is named in the error.
    pub fn insights(&self) -> Result<Insights, String> {
        let parse =
            |key: &str, m: &str| Mplex::parse(m).map_err(|e| format!("insights.{key}: {e}"));
        if !(0.0..=1.0).contains(&self.target) {
            return Err(format!("insights.target {}: 0 to 1", self.target));
        }
        let trends = self
            .trends
            .iter()
            .map(|rule| {
                let hours = |h: f64| h.is_finite() && h > 0.0 && h <= 24.0 * 400.0;
                if !(hours(rule.baseline_h) && hours(rule.window_h)) {
                    return Err(format!(
                        "insights.trends {:?}: baseline_h and window_h more than 0, at most 9600",
                        rule.name
                    ));
                }
                if !(rule.rise_percent.is_finite() && rule.rise_percent > 0.0) {
                    return Err(format!(
                        "insights.trends {:?}: rise_percent more than 0",
                        rule.name
                    ));
                }
                Ok((parse("trends.mplex", &rule.mplex)?, rule.clone()))
            })
            .collect::<Result<_, String>>()?;
        Ok(Insights {
            state: parse("state", &self.state)?,
            out_of_service: self.out_of_service.clone(),
            trips: parse("trips", &self.trips)?,
            door_cycles: parse("door_cycles", &self.door_cycles)?,
            reopenings: parse("reopenings", &self.reopenings)?,
            target: self.target,
            trends,
        })
    }
}

impl Insights {
    /// Whether `value` of the state object means the lift serves passengers (a value that is
    /// no integer is none of its out-of-service values).
    pub fn in_service(&self, value: &str) -> bool {
        value
            .trim()
            .parse::<i64>()
            .map_or(true, |v| !self.out_of_service.contains(&v))
    }

    /// The objects insights read.
    pub fn objects(&self) -> Vec<Mplex> {
        let mut all = vec![self.state, self.trips, self.door_cycles, self.reopenings];
        all.extend(self.trends.iter().map(|(m, _)| *m));
        all
    }
}

/// `[oidc]`: the OpenID provider the web UI signs in with (absent: local users only).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OidcSection {
    /// The provider's issuer URL (`https://…`); its discovery document is
    /// `ISSUER/.well-known/openid-configuration`.
    pub issuer: String,
    /// The portal's client id at the provider.
    pub client_id: String,
    /// The portal's client secret (sent as HTTP Basic authentication to the token endpoint);
    /// absent for a public client, which PKCE alone protects.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_secret: Option<String>,
    /// The portal account whose users sign in this way.
    pub account: String,
    /// The claim that lists the user's groups (a string or an array of strings; a dotted path
    /// such as `realm_access.roles` reaches into an object); default `groups`.
    #[serde(default = "groups")]
    pub roles_claim: String,
    /// Which group gives which role (`{ "lift-engineers" = "engineer" }`); a user in several
    /// gets the highest, one in none is refused.
    pub role_map: BTreeMap<String, Role>,
    /// The claim that names the user in the portal; default `preferred_username` (then
    /// `email`, then the subject).
    #[serde(default = "preferred_username")]
    pub name_claim: String,
    /// The scopes asked for; default `openid profile email` (`openid` is always asked).
    #[serde(default = "default_scopes")]
    pub scopes: Vec<String>,
    /// PEM CA certificates that sign the provider's certificate; absent: the system's roots.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
    /// Where the provider sends the browser back; default `https://HOST/login/sso/callback`
    /// with the host the browser asked for. Register it at the provider.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub redirect_url: Option<String>,
    /// What the sign-in page's button says: "Sign in with LABEL"; default `single sign-on`.
    #[serde(default = "label")]
    pub label: String,
}

fn groups() -> String {
    "groups".into()
}

fn preferred_username() -> String {
    "preferred_username".into()
}

fn default_scopes() -> Vec<String> {
    ["openid", "profile", "email"].map(String::from).to_vec()
}

fn label() -> String {
    "single sign-on".into()
}

/// The whole configuration.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// `[server]`.
    pub server: ServerSection,
    /// `[state]`.
    pub state: StateSection,
    /// `[database]`.
    pub database: DatabaseSection,
    /// `[gateways]`.
    pub gateways: GatewaysSection,
    /// `[dashboard]`.
    pub dashboard: DashboardSection,
    /// `[alarms]`.
    pub alarms: AlarmsSection,
    /// `[insights]`.
    pub insights: InsightsSection,
    /// `[cluster]`.
    pub cluster: ClusterSection,
    /// `[oidc]`: single sign-on (absent: local users and API keys only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oidc: Option<OidcSection>,
}

impl Config {
    /// The cluster node's name (`[cluster] node`, else `HOSTNAME:PORT`).
    pub fn node_name(&self) -> String {
        self.cluster.node.clone().unwrap_or_else(|| {
            let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
                .map(|h| h.trim().to_owned())
                .unwrap_or_else(|_| "portal".into());
            format!("{host}:{}", self.server.listen.port())
        })
    }

    /// The database URL in force.
    pub fn database_url(&self) -> String {
        self.database
            .url
            .clone()
            .unwrap_or_else(|| format!("sqlite://{}", self.state.dir.join("canlift.db").display()))
    }
}
