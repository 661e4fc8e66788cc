//! Elevation per person (docs/PORTAL.md §Users and roles). A gateway grants a privilege to its
//! connection (NXg §6.4), and every operator's request to a lift travels on that one
//! connection, so the gateway alone cannot tell who elevated. The portal keeps it: the grant of
//! a lift belongs to the user who entered the password, for the duration the gateway answered
//! and for the connection it was granted on. A put above privilege 0 by anyone else, after the
//! grant ran out, or after the gateway reconnected (the grant died with the connection) is
//! refused by the portal before it reaches the gateway.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

/// One lift's grant.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Grant {
    user: String,
    privilege: u32,
    until: Instant,
    connection: u64,
}

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

/// The grants of every lift, by lift id.
#[derive(Debug, Default)]
pub struct Elevations {
    grants: Mutex<HashMap<String, Grant>>,
}

impl Elevations {
    /// The gateway granted `privilege` for `duration` to `user`'s request on `lift`'s
    /// connection `connection` at `now` (replacing any other user's grant: the connection has
    /// only one). Privilege 0 drops the grant.
    pub fn granted(
        &self,
        lift: &str,
        user: &str,
        privilege: u32,
        duration: Duration,
        connection: u64,
        now: Instant,
    ) {
        let mut grants = self.grants.lock().unwrap_or_else(PoisonError::into_inner);
        if privilege == 0 {
            grants.remove(lift);
            return;
        }
        grants.insert(
            lift.to_owned(),
            Grant {
                user: user.to_owned(),
                privilege,
                until: now + duration,
                connection,
            },
        );
    }

    /// Whether `user` may write an object that needs `needed` on `lift`, whose gateway is on
    /// connection `connection` now.
    pub fn check(
        &self,
        lift: &str,
        user: &str,
        needed: u32,
        connection: Option<u64>,
        now: Instant,
    ) -> Result<(), Refusal> {
        if needed == 0 {
            return Ok(());
        }
        let mut grants = self.grants.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(grant) = grants.get(lift) else {
            return Err(Refusal::NotElevated(needed));
        };
        if grant.until <= now || Some(grant.connection) != connection {
            grants.remove(lift);
            return Err(Refusal::NotElevated(needed));
        }
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

    /// Whether no lift has a grant (a lift's grant goes when it is next checked after it ran
    /// out or its connection ended, or when it is replaced).
    #[cfg(test)]
    fn is_empty(&self) -> bool {
        self.grants
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grant_is_one_users_on_one_connection_for_its_duration() {
        let e = Elevations::default();
        let t0 = Instant::now();
        let minute = Duration::from_secs(60);
        assert_eq!(e.check("L", "ann", 0, Some(1), t0), Ok(()));
        assert_eq!(
            e.check("L", "ann", 1, Some(1), t0),
            Err(Refusal::NotElevated(1))
        );
        e.granted("L", "ann", 1, minute, 1, t0);
        assert_eq!(e.check("L", "ann", 1, Some(1), t0), Ok(()));
        assert_eq!(
            e.check("L", "bob", 1, Some(1), t0),
            Err(Refusal::ByAnother("ann".into()))
        );
        assert_eq!(
            e.check("L", "ann", 2, Some(1), t0),
            Err(Refusal::Lower { needed: 2, held: 1 })
        );
        assert_eq!(
            e.check("M", "ann", 1, Some(1), t0),
            Err(Refusal::NotElevated(1))
        );
        // Bob elevates: the connection is his now.
        e.granted("L", "bob", 2, minute, 1, t0);
        assert_eq!(
            e.check("L", "ann", 1, Some(1), t0),
            Err(Refusal::ByAnother("bob".into()))
        );
        // The gateway reconnected: the grant died with the old connection.
        assert_eq!(
            e.check("L", "bob", 1, Some(2), t0),
            Err(Refusal::NotElevated(1))
        );
        assert!(e.is_empty());
        // It runs out.
        e.granted("L", "bob", 2, minute, 2, t0);
        assert_eq!(
            e.check("L", "bob", 2, Some(2), t0 + minute),
            Err(Refusal::NotElevated(2))
        );
        // Privilege 0 drops it.
        e.granted("L", "bob", 2, minute, 2, t0);
        e.granted("L", "bob", 0, minute, 2, t0);
        assert!(e.is_empty());
    }
}
