//! Elevation per person (docs/PORTAL.md §Users and roles). A gateway grants a privilege to its
//! connection (NXg §6.4), and every operator's request to a lift travels on that one
//! connection, so the gateway alone cannot tell who elevated. The portal keeps it: the grant of
//! a lift belongs to the user who entered the password, for the duration the gateway answered
//! and for the connection it was granted on. A put above privilege 0 by anyone else, after the
//! grant ran out, or after the gateway reconnected (the grant died with the connection) is
//! refused by the portal before it reaches the gateway. Grants are kept in the database, so
//! every process of a cluster knows them.

use std::time::Duration;

use cloud_store::{ElevationGrant, Store, StoreError};

/// Why a put above privilege 0 is refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    /// No one elevated on this connection, or the grant ran out.
    #[error("elevate first: privilege {0} is needed to write this object")]
    NotElevated(u32),
    /// Another user holds the lift's grant.
    #[error("the lift's privilege was elevated by {0}, not by you: elevate yourself first")]
    ByAnother(String),
    /// The grant is for a lower privilege than the object needs.
    #[error("privilege {needed} is needed to write this object; you elevated to {held}")]
    Lower {
        /// What the object needs.
        needed: u32,
        /// What was granted.
        held: u32,
    },
}

/// The grants of every lift, kept in the database: in a cluster the engineer may elevate
/// through one process and write through another (the connection is named by its epoch, the
/// same on every process: docs/CLUSTER.md §Holder entries).
#[derive(Clone)]
pub struct Elevations {
    store: Store,
}

impl Elevations {
    /// The grants in `store`.
    pub fn new(store: Store) -> Elevations {
        Elevations { store }
    }

    /// The gateway granted `privilege` for `duration` to `user`'s request on `lift`'s
    /// connection `connection` at `now` (ms; replacing any other user's grant: the connection
    /// has only one). Privilege 0 drops the grant.
    pub async fn granted(
        &self,
        lift: &str,
        user: &str,
        privilege: u32,
        duration: Duration,
        connection: u64,
        now: i64,
    ) -> Result<(), StoreError> {
        if privilege == 0 {
            return self.store.drop_grant(lift).await;
        }
        let grant = ElevationGrant {
            user: user.to_owned(),
            privilege,
            until: now.saturating_add(i64::try_from(duration.as_millis()).unwrap_or(i64::MAX)),
            connection,
        };
        self.store.set_grant(lift, &grant).await
    }

    /// Whether `user` may write an object that needs `needed` on `lift`, whose gateway is on
    /// connection `connection` now (`now` in ms). A grant that ran out or whose connection
    /// ended is dropped.
    pub async fn check(
        &self,
        lift: &str,
        user: &str,
        needed: u32,
        connection: Option<u64>,
        now: i64,
    ) -> Result<Result<(), Refusal>, StoreError> {
        if needed == 0 {
            return Ok(Ok(()));
        }
        let grant = self.store.grant(lift).await?;
        let verdict = decide(grant.as_ref(), user, needed, connection, now);
        if grant.is_some_and(|g| stale(&g, connection, now)) {
            self.store.drop_grant(lift).await?;
        }
        Ok(verdict)
    }
}

/// Whether `grant` ran out at `now` or belongs to another connection than `connection`.
fn stale(grant: &ElevationGrant, connection: Option<u64>, now: i64) -> bool {
    grant.until <= now || Some(grant.connection) != connection
}

/// The verdict on a put by `user` that needs `needed`, given the lift's `grant`.
fn decide(
    grant: Option<&ElevationGrant>,
    user: &str,
    needed: u32,
    connection: Option<u64>,
    now: i64,
) -> Result<(), Refusal> {
    if needed == 0 {
        return Ok(());
    }
    let Some(grant) = grant.filter(|g| !stale(g, connection, now)) else {
        return Err(Refusal::NotElevated(needed));
    };
    if grant.user != user {
        return Err(Refusal::ByAnother(grant.user.clone()));
    }
    if grant.privilege < needed {
        return Err(Refusal::Lower {
            needed,
            held: grant.privilege,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_grant_is_one_users_on_one_connection_for_its_duration() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        let e = Elevations::new(store.clone());
        let check = |user: &'static str, needed, connection, now| {
            let e = e.clone();
            async move {
                e.check("L", user, needed, Some(connection), now)
                    .await
                    .unwrap()
            }
        };
        let (t0, minute) = (1_000_000, Duration::from_secs(60));
        assert_eq!(check("ann", 0, 1, t0).await, Ok(()));
        assert_eq!(check("ann", 1, 1, t0).await, Err(Refusal::NotElevated(1)));
        e.granted("L", "ann", 1, minute, 1, t0).await.unwrap();
        assert_eq!(check("ann", 1, 1, t0).await, Ok(()));
        assert_eq!(
            check("bob", 1, 1, t0).await,
            Err(Refusal::ByAnother("ann".into()))
        );
        assert_eq!(
            check("ann", 2, 1, t0).await,
            Err(Refusal::Lower { needed: 2, held: 1 })
        );
        assert_eq!(
            e.check("M", "ann", 1, Some(1), t0).await.unwrap(),
            Err(Refusal::NotElevated(1))
        );
        // Bob elevates: the connection is his now.
        e.granted("L", "bob", 2, minute, 1, t0).await.unwrap();
        assert_eq!(
            check("ann", 1, 1, t0).await,
            Err(Refusal::ByAnother("bob".into()))
        );
        // The gateway reconnected: the grant died with the old connection.
        assert_eq!(check("bob", 1, 2, t0).await, Err(Refusal::NotElevated(1)));
        assert_eq!(store.grant("L").await.unwrap(), None);
        // It runs out.
        e.granted("L", "bob", 2, minute, 2, t0).await.unwrap();
        assert_eq!(
            check("bob", 2, 2, t0 + 60_000).await,
            Err(Refusal::NotElevated(2))
        );
        // Privilege 0 drops it.
        e.granted("L", "bob", 2, minute, 2, t0).await.unwrap();
        e.granted("L", "bob", 0, minute, 2, t0).await.unwrap();
        assert_eq!(store.grant("L").await.unwrap(), None);
    }
}
