//! Signed-in browsers: signing in with a user's name and secret, or with an API key, opens a
//! session — a random id in an `HttpOnly`, `Secure`, `SameSite=Strict` cookie, kept only as its
//! SHA-256 digest, in the database (so that every process of a cluster, and the portal after a
//! restart, knows it) and cached in memory; ended after 12 h without a request. Changes through
//! the REST API with the cookie also need the session's CSRF token (see
//! [`crate::auth::Caller`]). When rights change anywhere, or a session is signed out anywhere,
//! the auth epoch rises and each session is checked again before its next request: a disabled
//! user's, a revoked key's or a signed-out session ends on every process.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use axum::http::{header, HeaderMap};

use cloud_types::users::Operator;

use cloud_store::{SessionRecord, Store, StoreError};

/// The cookie's name.
pub const COOKIE: &str = "canlift_session";
/// A session ends after this long without a request.
pub const IDLE: Duration = Duration::from_secs(12 * 3600);
/// How often a session in use has its time of last use written to the database.
const TOUCH: Duration = Duration::from_secs(60);
/// Sessions cached at most; the least recently used go first (they stay in the database).
const MAX_CACHED: usize = 10_000;

/// A signed-in browser.
#[derive(Clone)]
pub struct Session {
    /// Who is signed in.
    pub operator: Operator,
    /// The auth epoch it was last checked in.
    epoch: i64,
    pub(crate) csrf: String,
    last_used: Instant,
    /// When its last use was written to the database.
    touched: Instant,
}

/// What a session was opened with.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Credential {
    /// An API key (its digest).
    Key(String),
    /// A user's name and secret: the user's account and name.
    User {
        /// The user's account.
        account: String,
        /// The user's name within it.
        name: String,
    },
}

impl Session {
    /// Whether `token` is this session's CSRF token (compared in constant time).
    pub fn csrf_matches(&self, token: Option<&str>) -> bool {
        token.is_some_and(|t| nxg::digest::matches(&self.csrf, t))
    }
}

/// The web UI's sessions this process has seen, by the SHA-256 digest of their cookie.
#[derive(Default)]
pub struct Sessions {
    by_digest: Mutex<HashMap<String, Session>>,
}

/// The value of the request's cookie `name`.
pub fn cookie<'a>(headers: &'a HeaderMap, name: &str) -> Option<&'a str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|c| c.trim().split_once('='))
        .find(|(n, _)| *n == name)
        .map(|(_, value)| value)
}

fn idle_ms() -> i64 {
    i64::try_from(IDLE.as_millis()).unwrap_or(i64::MAX)
}

impl Sessions {
    fn cache(&self) -> std::sync::MutexGuard<'_, HashMap<String, Session>> {
        self.by_digest
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// The session the request's cookie names, if it is still open: from this process's
    /// cache, else from the database (opened on another process, or before a restart).
    pub async fn get(
        &self,
        headers: &HeaderMap,
        store: &Store,
    ) -> Result<Option<Session>, StoreError> {
        let Some(id) = cookie(headers, COOKIE) else {
            return Ok(None);
        };
        let digest = cloud_store::digest(id);
        let cached = {
            let mut cache = self.cache();
            match cache.get_mut(&digest) {
                // Idle here may still be in use on another process: the database decides.
                Some(s) if s.last_used.elapsed() > IDLE => {
                    cache.remove(&digest);
                    None
                }
                Some(s) => {
                    s.last_used = Instant::now();
                    let touch = s.touched.elapsed() > TOUCH;
                    if touch {
                        s.touched = s.last_used;
                    }
                    Some((s.clone(), touch))
                }
                None => None,
            }
        };
        if let Some((session, touch)) = cached {
            // The time of last use is worth a write, not a refused request: a database that
            // takes no write (a full disk) leaves it as it was.
            if touch {
                if let Err(e) = store.touch_session(&digest, cloud_types::now_ms()).await {
                    tracing::debug!(error = %e, "session's last use not recorded");
                }
            }
            return Ok(Some(session));
        }
        self.load(&digest, store).await
    }

    /// The session recorded under `digest`, checked against its user or key, and cached.
    async fn load(&self, digest: &str, store: &Store) -> Result<Option<Session>, StoreError> {
        let Some(record) = store.session(digest).await? else {
            return Ok(None);
        };
        let now = cloud_types::now_ms();
        let credential = match (record.key_digest, record.user) {
            (Some(key), _) => Some(Credential::Key(key)),
            (None, Some((account, name))) => Some(Credential::User { account, name }),
            (None, None) => None,
        };
        let epoch = store.seen_auth_epoch();
        let operator = match &credential {
            Some(c) if now.saturating_sub(record.last_used) <= idle_ms() => {
                operator_of(c, store).await?
            }
            _ => None,
        };
        let Some(operator) = operator else {
            store.close_session(digest).await?;
            return Ok(None);
        };
        if let Err(e) = store.touch_session(digest, now).await {
            tracing::debug!(error = %e, "session's last use not recorded");
        }
        Ok(Some(self.keep(digest, operator, epoch, record.csrf)))
    }

    /// Cache a session in use now (the least recently used goes when the cache is full).
    fn keep(&self, digest: &str, operator: Operator, epoch: i64, csrf: String) -> Session {
        let session = Session {
            operator,
            epoch,
            csrf,
            last_used: Instant::now(),
            touched: Instant::now(),
        };
        let mut cache = self.cache();
        if cache.len() >= MAX_CACHED {
            if let Some(oldest) = cache
                .iter()
                .min_by_key(|(_, s)| s.last_used)
                .map(|(k, _)| k.clone())
            {
                cache.remove(&oldest);
            }
        }
        cache.insert(digest.to_owned(), session.clone());
        session
    }

    /// The session the request's cookie names, checked again if rights changed (or a session
    /// was signed out) anywhere since it last was (`None` when it ended, or the user or key no
    /// longer counts).
    pub async fn current(
        &self,
        headers: &HeaderMap,
        store: &Store,
    ) -> Result<Option<Session>, StoreError> {
        let Some(session) = self.get(headers, store).await? else {
            return Ok(None);
        };
        if session.epoch == store.seen_auth_epoch() {
            return Ok(Some(session));
        }
        let Some(id) = cookie(headers, COOKIE) else {
            return Ok(None);
        };
        let digest = cloud_store::digest(id);
        self.cache().remove(&digest);
        self.load(&digest, store).await
    }

    /// Open a session for `operator`, signed in with `credential` in auth epoch `epoch`; the
    /// cookie value to set.
    pub async fn open(
        &self,
        operator: Operator,
        credential: Credential,
        epoch: i64,
        store: &Store,
    ) -> Result<String, StoreError> {
        let id = cloud_store::secret("");
        let digest = cloud_store::digest(&id);
        let (key_digest, user) = match &credential {
            Credential::Key(key) => (Some(key.clone()), None),
            Credential::User { account, name } => (None, Some((account.clone(), name.clone()))),
        };
        let now = cloud_types::now_ms();
        let record = SessionRecord {
            key_digest,
            user,
            csrf: cloud_store::secret(""),
            last_used: now,
        };
        // Signing in does not depend on the database taking a write: while it takes none (a
        // full disk), the session lives in this process alone (a cluster's other processes,
        // and this one after a restart, ask for a new sign-in).
        if let Err(e) = store
            .open_session(&digest, &record, now.saturating_sub(idle_ms()))
            .await
        {
            if !e.is_unavailable() {
                return Err(e);
            }
            tracing::warn!(error = %e, "session kept in this process only: the database takes no write");
        }
        self.keep(&digest, operator, epoch, record.csrf);
        Ok(id)
    }

    /// Sign the request's session out, here and (through the database) everywhere.
    pub async fn close(&self, headers: &HeaderMap, store: &Store) -> Result<(), StoreError> {
        if let Some(id) = cookie(headers, COOKIE) {
            let digest = cloud_store::digest(id);
            self.cache().remove(&digest);
            store.close_session(&digest).await?;
        }
        Ok(())
    }
}

/// Who `credential` signs in as now (`None`: the user is disabled, the key revoked).
async fn operator_of(
    credential: &Credential,
    store: &Store,
) -> Result<Option<Operator>, StoreError> {
    match credential {
        Credential::Key(digest) => store.operator_of_key(digest).await,
        Credential::User { account, name } => store.operator(account, name).await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn with_cookie(value: &str) -> HeaderMap {
        let mut headers = HeaderMap::new();
        headers.insert(header::COOKIE, HeaderValue::from_str(value).unwrap());
        headers
    }

    /// A session opened by one process is known to another on the same database (a cluster,
    /// or the portal after a restart); signed out on one, it ends on the other once the
    /// other has seen the auth epoch rise.
    #[tokio::test]
    async fn sessions_live_in_the_database() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        let key = store.add_account("a", "D").await.unwrap();
        let operator = store.operator_by_key(&key).await.unwrap().unwrap();
        let (here, there) = (Sessions::default(), Sessions::default());
        let credential = Credential::Key(cloud_store::digest(&key));
        let epoch = store.seen_auth_epoch();
        let id = here
            .open(operator.clone(), credential, epoch, &store)
            .await
            .unwrap();
        let headers = with_cookie(&format!("theme=dark; {COOKIE}={id}"));
        let session = here.get(&headers, &store).await.unwrap().unwrap();
        assert_eq!(session.operator, operator);
        assert!(session.csrf_matches(Some(&session.csrf.clone())));
        assert!(!session.csrf_matches(Some("nope")));
        assert!(!session.csrf_matches(None));
        let elsewhere = there.current(&headers, &store).await.unwrap().unwrap();
        assert_eq!(elsewhere.operator, operator);
        assert_eq!(
            elsewhere.csrf, session.csrf,
            "one CSRF token for the session"
        );
        here.close(&headers, &store).await.unwrap();
        assert!(here.get(&headers, &store).await.unwrap().is_none());
        // `follow_auth_epoch` does this every second in a portal.
        let follow = tokio::spawn(store.clone().follow_auth_epoch(Duration::from_millis(10)));
        tokio::time::timeout(Duration::from_secs(10), async {
            while store.seen_auth_epoch() == epoch {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        })
        .await
        .expect("the raised epoch is seen");
        follow.abort();
        assert!(there.current(&headers, &store).await.unwrap().is_none());
        let forged = with_cookie("canlift_session=guess");
        assert!(there.get(&forged, &store).await.unwrap().is_none());
    }
}
