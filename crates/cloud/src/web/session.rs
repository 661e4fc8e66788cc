//! Signed-in browsers: signing in with a user's name and secret, or with an API key, opens a
//! session — a random id in an `HttpOnly`, `Secure`, `SameSite=Strict` cookie, kept in memory
//! only as its SHA-256 digest, ended after 12 h without a request. Changes through the REST API
//! with the cookie also need the session's CSRF token (see [`crate::api::Caller`]). When rights
//! change anywhere (the auth epoch rises) a session is checked again before its next request:
//! a disabled user's or revoked key's session ends.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use axum::http::{header, HeaderMap};

use crate::store::{self, Operator, Store, StoreError};

/// The cookie's name.
pub(super) const COOKIE: &str = "canlift_session";
/// A session ends after this long without a request.
pub(super) const IDLE: Duration = Duration::from_secs(12 * 3600);
/// Sessions kept at most; the oldest go first.
const MAX_SESSIONS: usize = 10_000;

/// A signed-in browser.
#[derive(Clone)]
pub struct Session {
    /// Who is signed in.
    pub operator: Operator,
    /// How, to check it again when rights change.
    credential: Credential,
    /// The auth epoch it was last checked in.
    epoch: i64,
    pub(super) csrf: String,
    last_used: Instant,
}

/// What a session was opened with.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Credential {
    /// An API key (its digest).
    Key(String),
    /// A user's name and secret (the name).
    User(String),
}

impl Session {
    /// Whether `token` is this session's CSRF token (compared in constant time).
    pub fn csrf_matches(&self, token: Option<&str>) -> bool {
        token.is_some_and(|t| nxg::digest::matches(&self.csrf, t))
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

    /// The session the request's cookie names, checked again if rights changed since it last
    /// was (`None` when it ended, or the user or key no longer counts).
    pub async fn current(
        &self,
        headers: &HeaderMap,
        store: &Store,
    ) -> Result<Option<Session>, StoreError> {
        let Some(mut session) = self.get(headers) else {
            return Ok(None);
        };
        let epoch = store.seen_auth_epoch();
        if session.epoch == epoch {
            return Ok(Some(session));
        }
        let operator = match &session.credential {
            Credential::Key(digest) => store.operator_of_key(digest).await?,
            Credential::User(name) => store.operator(name).await?,
        };
        let Some(operator) = operator else {
            self.close(headers);
            return Ok(None);
        };
        session.operator = operator;
        session.epoch = epoch;
        if let Some(id) = cookie(headers) {
            let mut map = self
                .by_digest
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            if let Some(kept) = map.get_mut(&store::digest(id)) {
                kept.operator = session.operator.clone();
                kept.epoch = epoch;
            }
        }
        Ok(Some(session))
    }

    /// Open a session for `operator`, signed in with `credential` in auth epoch `epoch`; the
    /// cookie value to set.
    pub(super) fn open(&self, operator: Operator, credential: Credential, epoch: i64) -> String {
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
            operator,
            credential,
            epoch,
            csrf: store::secret(""),
            last_used: Instant::now(),
        };
        map.insert(store::digest(&id), session);
        id
    }

    pub(super) fn close(&self, headers: &HeaderMap) {
        if let Some(id) = cookie(headers) {
            self.by_digest
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .remove(&store::digest(id));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    #[test]
    fn session_cookie_and_csrf() {
        let sessions = Sessions::default();
        let operator = Operator {
            account: store::Account {
                name: "a".into(),
                domain: "D".into(),
            },
            user: "a".into(),
            role: store::Role::Admin,
        };
        let id = sessions.open(operator.clone(), Credential::User("a".into()), 0);
        let mut headers = HeaderMap::new();
        headers.insert(
            header::COOKIE,
            HeaderValue::from_str(&format!("theme=dark; {COOKIE}={id}")).unwrap(),
        );
        let session = sessions.get(&headers).unwrap();
        assert_eq!(session.operator, operator);
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
}
