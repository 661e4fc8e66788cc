//! What the portal's operator-facing parts share: the REST API ([`crate::api`]) and the web UI
//! ([`crate::web`]) are handlers of one [`AppState`], and neither depends on the other.

use std::sync::Arc;

use cloud_store::Store;
use nxg::names::ObjectNames;

use crate::alarms::Alarms;
use crate::audit::AuditTrail;
use crate::auth::Auth;
use crate::config::Dashboard;
use crate::gateways::subscriptions::Subscriptions;
use crate::gateways::Registry;

/// What the API's handlers and the web UI's pages share.
pub struct AppState {
    /// The database.
    pub store: Store,
    /// Live gateways.
    pub registry: Arc<Registry>,
    /// Who may do what: sessions, throttles, elevations.
    pub auth: Auth,
    /// The audit log, written before a lift is asked.
    pub audit: AuditTrail,
    /// What the web UI shows.
    pub dashboard: Arc<Dashboard>,
    /// Who holds which subscriptions.
    pub subscriptions: Arc<Subscriptions>,
    /// Alarms.
    pub alarms: Arc<Alarms>,
    /// Object names operators may use instead of an mplex (`?name=`, path, web forms).
    pub names: Arc<ObjectNames>,
    /// What lift insights read.
    pub insights: Arc<crate::config::Insights>,
    /// The fleet's availability over the last days, per account.
    pub recent: crate::insights::Recent,
}

impl crate::auth::AuthState for AppState {
    fn auth(&self) -> &Auth {
        &self.auth
    }

    fn store(&self) -> &Store {
        &self.store
    }
}
