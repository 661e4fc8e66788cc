//! People inside an account (docs/PORTAL.md §Users and roles): users with a role and a sign-in
//! secret (an argon2id hash is kept, never the secret), and API keys that belong to a user and
//! act with its role (only their SHA-256 digest is kept: a key is 128 random bits, which a fast
//! digest protects, while a secret a person may choose needs a slow KDF).
//!
//! The key an account was created with stays valid and acts as the account's administrator.
//! Every change that takes rights away (a user disabled, a role lowered, a key revoked) raises
//! the *auth epoch*; each portal process watches it and forgets what it remembered of keys and
//! sessions, so the change takes effect in every process within a second.

use argon2::password_hash::{PasswordHash, PasswordHasher, PasswordVerifier, SaltString};
use argon2::Argon2;
use rand::RngCore;
use sqlx::Row;

use std::collections::HashMap;

use cloud_types::now_ms;
use cloud_types::users::{Account, KeyInfo, Operator, Role, User};

use crate::secrets::{digest, secret};
use crate::{Store, StoreError};

/// Why a user or key change did not happen.
#[derive(Debug, thiserror::Error)]
pub enum UserError {
    /// The database failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// No such account.
    #[error("no account {0:?}")]
    NoAccount(String),
    /// No such user in the account.
    #[error("no user {0:?} in account {1:?}")]
    NoUser(String, String),
    /// The name is taken in the account (user names are unique within their account).
    #[error("the account has a user {0:?}")]
    Taken(String),
    /// No such key in the account.
    #[error("no key {0:?} in account {1:?}")]
    NoKey(String, String),
}

impl From<sqlx::Error> for UserError {
    fn from(e: sqlx::Error) -> Self {
        UserError::Store(StoreError::from(e))
    }
}

/// How long an API key's account is taken from memory before the database is asked again, and
/// how long a remembered key still counts while the database cannot be reached
/// (docs/SECURITY.md §Bounds).
const KEY_FRESH: std::time::Duration = std::time::Duration::from_secs(60);
const KEY_KEPT: std::time::Duration = std::time::Duration::from_secs(3600);
/// Keys remembered at most (a full memory starts over).
const KEY_CACHE_ENTRIES: usize = 10_000;

/// Operators of API keys recently looked up, by the key's digest.
#[derive(Default)]
pub(crate) struct KeyCache(std::sync::Mutex<HashMap<String, (Operator, std::time::Instant)>>);

impl KeyCache {
    /// The operator of `digest` if it was looked up less than `age` ago.
    fn get(&self, digest: &str, age: std::time::Duration) -> Option<Operator> {
        let keys = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        keys.get(digest)
            .filter(|(_, at)| at.elapsed() < age)
            .map(|(account, _)| account.clone())
    }

    fn put(&self, digest: String, operator: Operator) {
        let mut keys = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if keys.len() >= KEY_CACHE_ENTRIES {
            keys.clear();
        }
        keys.insert(digest, (operator, std::time::Instant::now()));
    }

    /// Forget every key (rights were taken away somewhere).
    fn clear(&self) {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clear();
    }
}

/// The `role` column of `row` (an unknown name, written by a later version, counts as the
/// least role).
fn role_of(row: &sqlx::any::AnyRow) -> Result<Role, sqlx::Error> {
    let name: String = row.try_get("role")?;
    Ok(Role::from_name(&name).unwrap_or(Role::Viewer))
}

/// The argon2id hash of `secret` as a PHC string (the crate's default parameters: 19 MiB,
/// two passes, the OWASP recommendation).
fn hash_secret(secret: &str) -> String {
    let mut salt = [0u8; 16];
    rand::rng().fill_bytes(&mut salt);
    SaltString::encode_b64(&salt)
        .and_then(|salt| {
            let hash = Argon2::default().hash_password(secret.as_bytes(), &salt)?;
            Ok(hash.to_string())
        })
        // Only a salt of the wrong length fails, and this one has the recommended 16 bytes.
        .unwrap_or_default()
}

/// Whether `secret` matches `hash` (a PHC string): argon2id, 19 MiB and tens of milliseconds
/// of one core — the caller runs it where it holds up nothing else.
pub fn secret_matches(secret: &str, hash: &str) -> bool {
    PasswordHash::new(hash).is_ok_and(|h| {
        Argon2::default()
            .verify_password(secret.as_bytes(), &h)
            .is_ok()
    })
}

impl Store {
    /// The operator an API key acts for (found by the key's digest: an index lookup reveals
    /// nothing of a random 128-bit key): the account's administrator for the account's own key,
    /// a user with its role for a user's key.
    ///
    /// A key found is remembered for a minute, so requests do not each cost a query, and while
    /// the database is unreachable a key that was valid within the hour still counts: operators
    /// keep reading lifts, which needs no database, through an outage. What is remembered is
    /// forgotten when the auth epoch rises (a user disabled, a key revoked: see
    /// [`Store::follow_auth_epoch`]).
    pub async fn operator_by_key(&self, key: &str) -> Result<Option<Operator>, StoreError> {
        let digest = digest(key);
        if let Some(operator) = self.keys.get(&digest, KEY_FRESH) {
            return Ok(Some(operator));
        }
        let operator = match self.operator_of_key(&digest).await {
            Ok(operator) => operator,
            Err(e) if e.is_unavailable() => {
                return match self.keys.get(&digest, KEY_KEPT) {
                    Some(operator) => Ok(Some(operator)),
                    None => Err(e),
                };
            }
            Err(e) => return Err(e),
        };
        if let Some(operator) = &operator {
            self.keys.put(digest, operator.clone());
        }
        Ok(operator)
    }

    /// Check the auth epoch every `period` for as long as the store lives: when it rose, the
    /// keys remembered are forgotten and sessions are checked again (docs/PORTAL.md §Users and
    /// roles). Run by the portal.
    pub async fn follow_auth_epoch(self, period: std::time::Duration) {
        let mut ticks = tokio::time::interval(period);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticks.tick().await;
            match self.auth_epoch().await {
                Ok(epoch) => {
                    let seen = self.epoch.swap(epoch, std::sync::atomic::Ordering::SeqCst);
                    if seen != epoch {
                        self.keys.clear();
                    }
                }
                Err(e) => tracing::debug!(error = %e, "auth epoch not read"),
            }
        }
    }

    /// The auth epoch this process has seen.
    pub fn seen_auth_epoch(&self) -> i64 {
        self.epoch.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Add user `name` to `account` with `role`; its sign-in secret (shown only now).
    pub async fn add_user(
        &self,
        account: &str,
        name: &str,
        role: Role,
    ) -> Result<String, UserError> {
        self.account_named(account).await?;
        let secret = secret("cls_");
        let done = sqlx::query(
            "INSERT INTO users (name, account, role, secret_hash, disabled, created) VALUES ($1, $2, $3, $4, NULL, $5)",
        )
        .bind(name)
        .bind(account)
        .bind(role.name())
        .bind(hash_secret(&secret))
        .bind(now_ms())
        .execute(&self.pool)
        .await;
        match done {
            Ok(_) => Ok(secret),
            Err(sqlx::Error::Database(e)) if e.is_unique_violation() => {
                Err(UserError::Taken(name.to_owned()))
            }
            Err(e) => Err(e.into()),
        }
    }

    /// A user the account's OpenID provider signed on (docs/PORTAL.md §Single sign-on), found
    /// by `subject` (`ISSUER SUB`, which never changes for them) and given `role`, which their
    /// groups decide at every sign-on; made with `name` the first time, without a secret of
    /// their own (no secret matches it). `None` for a user an administrator disabled: the
    /// provider's word does not enable them again. A name another user of the account has is
    /// [`UserError::Taken`]: a local user is never taken over by a provider's name.
    pub async fn signed_on_user(
        &self,
        account: &str,
        subject: &str,
        name: &str,
        role: Role,
    ) -> Result<Option<Operator>, UserError> {
        self.account_named(account).await?;
        for _ in 0..2 {
            let found = sqlx::query(
                "SELECT name, role, disabled FROM users WHERE account = $1 AND sso_subject = $2",
            )
            .bind(account)
            .bind(subject)
            .fetch_optional(&self.pool)
            .await?;
            if let Some(row) = found {
                let known: String = row.try_get("name")?;
                if row.try_get::<Option<i64>, _>("disabled")?.is_some() {
                    return Ok(None);
                }
                if role_of(&row)? != role {
                    self.set_role(account, &known, role).await?;
                }
                return Ok(self.operator(account, &known).await?);
            }
            let made = sqlx::query(
                "INSERT INTO users (name, account, role, secret_hash, disabled, created, sso_subject) VALUES ($1, $2, $3, $4, NULL, $5, $6)",
            )
            .bind(name)
            .bind(account)
            .bind(role.name())
            .bind(NO_SECRET)
            .bind(now_ms())
            .bind(subject)
            .execute(&self.pool)
            .await;
            match made {
                Ok(_) => return Ok(self.operator(account, name).await?),
                // Another process made them a moment ago (then they are found), or the name
                // is another user's.
                Err(sqlx::Error::Database(e)) if e.is_unique_violation() => continue,
                Err(e) => return Err(e.into()),
            }
        }
        Err(UserError::Taken(name.to_owned()))
    }

    /// The users of `account`, by name.
    pub async fn users(&self, account: &str) -> Result<Vec<User>, UserError> {
        self.account_named(account).await?;
        let rows = sqlx::query(
            "SELECT name, account, role, disabled FROM users WHERE account = $1 ORDER BY name",
        )
        .bind(account)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(User {
                    name: r.try_get("name")?,
                    account: r.try_get("account")?,
                    role: role_of(r)?,
                    disabled: r.try_get::<Option<i64>, _>("disabled")?.is_some(),
                })
            })
            .collect()
    }

    /// Disable user `name` of `account`: its keys and sessions stop working (within a second in
    /// every portal process).
    pub async fn disable_user(&self, account: &str, name: &str) -> Result<(), UserError> {
        self.change_user(
            account,
            name,
            sqlx::query("UPDATE users SET disabled = $1 WHERE name = $2 AND account = $3")
                .bind(now_ms()),
        )
        .await
    }

    /// A new sign-in secret for user `name` of `account` (shown only now) and the user's role;
    /// the old secret and the user's sessions stop working. A disabled user stays disabled.
    pub async fn reset_user(&self, account: &str, name: &str) -> Result<(String, Role), UserError> {
        let secret = secret("cls_");
        self.change_user(
            account,
            name,
            sqlx::query("UPDATE users SET secret_hash = $1 WHERE name = $2 AND account = $3")
                .bind(hash_secret(&secret)),
        )
        .await?;
        let row = sqlx::query("SELECT role FROM users WHERE name = $1 AND account = $2")
            .bind(name)
            .bind(account)
            .fetch_one(&self.pool)
            .await?;
        Ok((secret, role_of(&row)?))
    }

    /// Give user `name` of `account` another role.
    pub async fn set_role(&self, account: &str, name: &str, role: Role) -> Result<(), UserError> {
        self.change_user(
            account,
            name,
            sqlx::query("UPDATE users SET role = $1 WHERE name = $2 AND account = $3")
                .bind(role.name()),
        )
        .await
    }

    /// Run `update` (its first parameter bound, `$2` the name, `$3` the account) on one user and
    /// raise the auth epoch.
    async fn change_user<'q>(
        &self,
        account: &'q str,
        name: &'q str,
        update: sqlx::query::Query<'q, sqlx::Any, sqlx::any::AnyArguments<'q>>,
    ) -> Result<(), UserError> {
        let done = update.bind(name).bind(account).execute(&self.pool).await?;
        if done.rows_affected() == 0 {
            return Err(UserError::NoUser(name.to_owned(), account.to_owned()));
        }
        self.raise_auth_epoch().await?;
        Ok(())
    }

    /// A new API key for user `user` of `account`, valid until `expires` (ms since the epoch)
    /// if given: (its id, the key — shown only now).
    pub async fn add_key(
        &self,
        account: &str,
        user: &str,
        expires: Option<i64>,
    ) -> Result<(String, String), UserError> {
        let found = sqlx::query("SELECT COUNT(*) AS n FROM users WHERE name = $1 AND account = $2")
            .bind(user)
            .bind(account)
            .fetch_one(&self.pool)
            .await?
            .try_get::<i64, _>("n")?;
        if found == 0 {
            return Err(UserError::NoUser(user.to_owned(), account.to_owned()));
        }
        let key = secret("clk_");
        let id = secret("")[..12].to_owned();
        sqlx::query(
            "INSERT INTO api_keys (id, key_hash, user_name, account, created, expires, revoked) VALUES ($1, $2, $3, $4, $5, $6, NULL)",
        )
        .bind(&id)
        .bind(digest(&key))
        .bind(user)
        .bind(account)
        .bind(now_ms())
        .bind(expires)
        .execute(&self.pool)
        .await?;
        Ok((id, key))
    }

    /// The API keys of `account`'s users.
    pub async fn keys(&self, account: &str) -> Result<Vec<KeyInfo>, UserError> {
        self.account_named(account).await?;
        let rows = sqlx::query(
            "SELECT id, user_name, expires, revoked FROM api_keys WHERE account = $1 ORDER BY created",
        )
        .bind(account)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(KeyInfo {
                    id: r.try_get("id")?,
                    user: r.try_get("user_name")?,
                    expires: r.try_get("expires")?,
                    revoked: r.try_get::<Option<i64>, _>("revoked")?.is_some(),
                })
            })
            .collect()
    }

    /// Revoke key `id` of `account`: it stops working (within a second in every process).
    pub async fn revoke_key(&self, account: &str, id: &str) -> Result<(), UserError> {
        let done = sqlx::query("UPDATE api_keys SET revoked = $1 WHERE id = $2 AND account = $3")
            .bind(now_ms())
            .bind(id)
            .bind(account)
            .execute(&self.pool)
            .await?;
        if done.rows_affected() == 0 {
            return Err(UserError::NoKey(id.to_owned(), account.to_owned()));
        }
        self.raise_auth_epoch().await?;
        Ok(())
    }

    /// The argon2id hash of the secret of enabled user `name` of `account`, for a sign-in to
    /// check with [`secret_matches`] (on a thread of its own: it takes 19 MiB and tens of
    /// milliseconds); absent, a hash no secret matches, so that an unknown name costs as much
    /// as a wrong secret and a response time tells no one which names exist.
    pub async fn secret_hash(&self, account: &str, name: &str) -> Result<String, StoreError> {
        let row = sqlx::query(
            "SELECT secret_hash FROM users WHERE account = $1 AND name = $2 AND disabled IS NULL",
        )
        .bind(account)
        .bind(name)
        .fetch_optional(&self.pool)
        .await?;
        match row {
            Some(row) => Ok(row.try_get("secret_hash")?),
            None => Ok(DUMMY_HASH.clone()),
        }
    }

    /// User `name` of `account` as an operator, if it exists and is enabled.
    pub async fn operator(
        &self,
        account: &str,
        name: &str,
    ) -> Result<Option<Operator>, StoreError> {
        let row = sqlx::query(
            "SELECT u.role, a.name AS account, a.domain FROM users u JOIN accounts a ON a.name = u.account WHERE u.account = $1 AND u.name = $2 AND u.disabled IS NULL",
        )
        .bind(account)
        .bind(name)
        .fetch_optional(&self.pool)
        .await?;
        row.map(|r| -> Result<Operator, sqlx::Error> {
            Ok(Operator {
                account: Account {
                    name: r.try_get("account")?,
                    domain: r.try_get("domain")?,
                },
                user: name.to_owned(),
                role: role_of(&r)?,
            })
        })
        .transpose()
        .map_err(StoreError::from)
    }

    /// The operator a key acts for, looked up in the database: the account's own key (its
    /// administrator), or a user's key that is neither revoked nor expired, of an enabled user.
    pub async fn operator_of_key(&self, digest: &str) -> Result<Option<Operator>, StoreError> {
        let account = sqlx::query("SELECT name, domain FROM accounts WHERE key_hash = $1")
            .bind(digest)
            .fetch_optional(&self.pool)
            .await?;
        if let Some(r) = account {
            let name: String = r.try_get("name")?;
            return Ok(Some(Operator {
                user: name.clone(),
                account: Account {
                    name,
                    domain: r.try_get("domain")?,
                },
                role: Role::Admin,
            }));
        }
        let key = sqlx::query(
            "SELECT user_name, account FROM api_keys WHERE key_hash = $1 AND revoked IS NULL AND (expires IS NULL OR expires > $2)",
        )
        .bind(digest)
        .bind(now_ms())
        .fetch_optional(&self.pool)
        .await?;
        match key {
            Some(r) => {
                let account: String = r.try_get("account")?;
                self.operator(&account, &r.try_get::<String, _>("user_name")?)
                    .await
            }
            None => Ok(None),
        }
    }

    async fn account_named(&self, account: &str) -> Result<(), UserError> {
        let n = sqlx::query("SELECT COUNT(*) AS n FROM accounts WHERE name = $1")
            .bind(account)
            .fetch_one(&self.pool)
            .await?
            .try_get::<i64, _>("n")?;
        if n == 0 {
            return Err(UserError::NoAccount(account.to_owned()));
        }
        Ok(())
    }

    /// Raise the auth epoch: every process forgets the keys and sessions it remembered.
    pub(crate) async fn raise_auth_epoch(&self) -> Result<(), StoreError> {
        sqlx::query("UPDATE auth_epoch SET epoch = epoch + 1 WHERE id = 1")
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// The auth epoch in the database.
    pub async fn auth_epoch(&self) -> Result<i64, StoreError> {
        let row = sqlx::query("SELECT epoch FROM auth_epoch WHERE id = 1")
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get("epoch")?)
    }
}

/// The secret hash of a user of single sign-on: not a PHC string, so no secret matches it.
const NO_SECRET: &str = "!sso";

/// A hash to compare against when there is no user, so that an unknown name costs as much time
/// as a wrong secret.
static DUMMY_HASH: std::sync::LazyLock<String> =
    std::sync::LazyLock::new(|| hash_secret("no user has this secret"));

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A sign-in as the portal makes it: the hash, checked, then the operator.
    async fn sign_in(store: &Store, account: &str, name: &str, secret: &str) -> Option<Operator> {
        let hash = store.secret_hash(account, name).await.unwrap();
        if !secret_matches(secret, &hash) {
            return None;
        }
        store.operator(account, name).await.unwrap()
    }

    /// Run by the store's tests on SQLite and PostgreSQL, after [`users_keys_and_the_epoch`]
    /// (which made ann, a local user of `masora`).
    pub(crate) async fn users_of_single_sign_on(store: &Store) {
        const VIC: &str = "https://id.example 248289761001";
        let vic = store
            .signed_on_user("masora", VIC, "vic", Role::Viewer)
            .await
            .unwrap()
            .unwrap();
        assert_eq!((vic.user.as_str(), vic.role), ("vic", Role::Viewer));
        // No secret signs them in.
        for secret in ["", "!sso", "cls_"] {
            assert!(sign_in(store, "masora", "vic", secret).await.is_none());
        }
        // The role follows their groups; the name they were made with stays theirs.
        let epoch = store.auth_epoch().await.unwrap();
        let again = store
            .signed_on_user("masora", VIC, "vic.renamed", Role::Engineer)
            .await
            .unwrap()
            .unwrap();
        assert_eq!((again.user.as_str(), again.role), ("vic", Role::Engineer));
        assert!(
            store.auth_epoch().await.unwrap() > epoch,
            "a role change raises the epoch"
        );
        // Nobody takes over a local user by the name the provider gives.
        assert!(matches!(
            store
                .signed_on_user("masora", "https://id.example 9", "ann", Role::Admin)
                .await,
            Err(UserError::Taken(_))
        ));
        // A disabled user stays disabled whatever the provider says.
        store.disable_user("masora", "vic").await.unwrap();
        assert!(store
            .signed_on_user("masora", VIC, "vic", Role::Admin)
            .await
            .unwrap()
            .is_none());
        // The same subject in another account is another user there.
        let theirs = store
            .signed_on_user("other", VIC, "vic", Role::Viewer)
            .await
            .unwrap()
            .unwrap();
        assert_eq!(theirs.account.name, "other");
        assert!(matches!(
            store
                .signed_on_user("nobody", VIC, "vic", Role::Viewer)
                .await,
            Err(UserError::NoAccount(_))
        ));
    }

    /// Run by the store's tests on SQLite and PostgreSQL, with account `masora` (domain MAS)
    /// and `other` made.
    pub(crate) async fn users_keys_and_the_epoch(store: &Store) {
        let epoch = store.auth_epoch().await.unwrap();
        let secret = store
            .add_user("masora", "ann", Role::Engineer)
            .await
            .unwrap();
        assert!(secret.starts_with("cls_"));
        assert!(matches!(
            store.add_user("masora", "ann", Role::Viewer).await,
            Err(UserError::Taken(_))
        ));
        // Another account's ann is another person: her name tells nothing of this one.
        let other_ann = store.add_user("other", "ann", Role::Viewer).await.unwrap();
        assert!(matches!(
            store.add_user("nobody", "bob", Role::Viewer).await,
            Err(UserError::NoAccount(_))
        ));
        store.add_user("masora", "bob", Role::Viewer).await.unwrap();
        // Sign-in: the right secret only, the hash is argon2id.
        let ann = sign_in(store, "masora", "ann", &secret).await.unwrap();
        assert_eq!(
            (ann.role, ann.account.domain.as_str()),
            (Role::Engineer, "MAS")
        );
        assert!(sign_in(store, "masora", "ann", "cls_wrong").await.is_none());
        assert!(sign_in(store, "masora", "carl", &secret).await.is_none());
        assert!(sign_in(store, "other", "ann", &secret).await.is_none());
        let theirs = sign_in(store, "other", "ann", &other_ann).await.unwrap();
        assert_eq!(
            (theirs.account.name.as_str(), theirs.role),
            ("other", Role::Viewer)
        );
        let hash: String = sqlx::query("SELECT secret_hash FROM users WHERE name = 'ann'")
            .fetch_one(&store.pool)
            .await
            .unwrap()
            .get("secret_hash");
        assert!(hash.starts_with("$argon2id$"), "{hash}");
        // Keys act with the user's role, until revoked or expired.
        let (id, key) = store.add_key("masora", "bob", None).await.unwrap();
        let bob = store.operator_by_key(&key).await.unwrap().unwrap();
        assert_eq!((bob.user.as_str(), bob.role), ("bob", Role::Viewer));
        assert!(matches!(
            store.add_key("other", "bob", None).await,
            Err(UserError::NoUser(..))
        ));
        let (_, old) = store
            .add_key("masora", "ann", Some(now_ms() - 1))
            .await
            .unwrap();
        assert!(
            store.operator_by_key(&old).await.unwrap().is_none(),
            "expired"
        );
        assert_eq!(store.keys("masora").await.unwrap().len(), 2);
        assert!(matches!(
            store.revoke_key("other", &id).await,
            Err(UserError::NoKey(..))
        ));
        store.revoke_key("masora", &id).await.unwrap();
        assert!(store
            .operator_of_key(&digest(&key))
            .await
            .unwrap()
            .is_none());
        // Role changes, reset and disable raise the epoch.
        store
            .set_role("masora", "bob", Role::Technician)
            .await
            .unwrap();
        assert_eq!(
            store.operator("masora", "bob").await.unwrap().unwrap().role,
            Role::Technician
        );
        let (again, role) = store.reset_user("masora", "ann").await.unwrap();
        assert_eq!(role, Role::Engineer);
        assert!(sign_in(store, "masora", "ann", &secret).await.is_none());
        assert!(sign_in(store, "masora", "ann", &again).await.is_some());
        store.disable_user("masora", "ann").await.unwrap();
        assert!(sign_in(store, "masora", "ann", &again).await.is_none());
        assert!(store.operator("masora", "ann").await.unwrap().is_none());
        assert!(store.operator("other", "ann").await.unwrap().is_some());
        assert!(matches!(
            store.disable_user("other", "bob").await,
            Err(UserError::NoUser(..))
        ));
        assert_eq!(store.auth_epoch().await.unwrap(), epoch + 4);
        let users = store.users("masora").await.unwrap();
        let listed: Vec<(&str, Role, bool)> = users
            .iter()
            .map(|u| (u.name.as_str(), u.role, u.disabled))
            .collect();
        assert_eq!(
            listed,
            [
                ("ann", Role::Engineer, true),
                ("bob", Role::Technician, false)
            ]
        );
    }
}
