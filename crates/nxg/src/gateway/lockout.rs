//! Wrong password hashes lock elevation out (NXg §6.4; docs/PROTOCOL.md §Privileges): per
//! privilege level, after the third wrong hash for 30 s (`[privileges] lockout_s`), doubling
//! with each further one up to an hour. The state belongs to the gateway, not to a connection — a portal that reconnects
//! finds the lock where it left it — and survives restarts through [`LockoutState`], which the
//! driver stores. Only a correct hash for the level ends its count.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::meta::Privilege;

/// Failures before the first lock.
const LOCKOUT_AFTER: u32 = 3;
/// The first lock unless configured.
pub const FIRST_LOCK: Duration = Duration::from_secs(30);
/// The longest lock (or the first, if that is longer).
const LONGEST_LOCK: Duration = Duration::from_secs(3600);

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Level {
    failures: u32,
    locked_until: Option<Instant>,
}

/// The failure counts and locks of the grantable levels (service, setup).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Lockout {
    levels: [Level; 2],
    first_lock: Duration,
}

impl Default for Lockout {
    fn default() -> Self {
        Lockout::new(FIRST_LOCK)
    }
}

/// What a wrong hash did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failed {
    /// Counted; not locked (yet).
    Counted(u32),
    /// The level is locked now, for this long.
    Locked(Duration),
}

/// One level's count and remaining lock, as stored between runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LevelState {
    /// Wrong hashes since the last correct one.
    pub failures: u32,
    /// Seconds of lock left (0: not locked).
    pub locked_s: u64,
}

/// The lock-out as the driver stores it (in the state directory).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct LockoutState {
    /// Service level.
    pub service: LevelState,
    /// Setup level.
    pub setup: LevelState,
}

fn slot(level: Privilege) -> Option<usize> {
    match level {
        Privilege::Service => Some(0),
        Privilege::Setup => Some(1),
        _ => None,
    }
}

impl Lockout {
    /// No failures yet; the third wrong hash locks for `first_lock`.
    pub fn new(first_lock: Duration) -> Lockout {
        Lockout {
            levels: [Level::default(); 2],
            first_lock,
        }
    }

    /// How long `level` is still locked, if it is.
    pub fn locked(&self, level: Privilege, now: Instant) -> Option<Duration> {
        let l = self.levels[slot(level)?];
        l.locked_until
            .filter(|u| now < *u)
            .map(|u| u.duration_since(now))
    }

    /// A wrong hash for `level`.
    pub fn failure(&mut self, level: Privilege, now: Instant) -> Failed {
        let Some(i) = slot(level) else {
            return Failed::Counted(0);
        };
        let l = &mut self.levels[i];
        l.failures = l.failures.saturating_add(1);
        if l.failures < LOCKOUT_AFTER {
            return Failed::Counted(l.failures);
        }
        // 2^16 takes any first lock of a second or more past the longest.
        let exponent = (l.failures - LOCKOUT_AFTER).min(16);
        let lock = self
            .first_lock
            .checked_mul(1 << exponent)
            .map_or(LONGEST_LOCK, |lock| lock.min(LONGEST_LOCK))
            .max(self.first_lock);
        l.locked_until = Some(now + lock);
        Failed::Locked(lock)
    }

    /// A correct hash for `level`: its count starts again.
    pub fn success(&mut self, level: Privilege) {
        if let Some(i) = slot(level) {
            self.levels[i] = Level::default();
        }
    }

    /// The state to store.
    pub fn state(&self, now: Instant) -> LockoutState {
        let level = |l: &Level| LevelState {
            failures: l.failures,
            locked_s: l
                .locked_until
                .filter(|u| now < *u)
                .map_or(0, |u| u.duration_since(now).as_secs().max(1)),
        };
        LockoutState {
            service: level(&self.levels[0]),
            setup: level(&self.levels[1]),
        }
    }

    /// The lock-out of a stored state, counted from `now`.
    pub fn restore(state: LockoutState, first_lock: Duration, now: Instant) -> Lockout {
        let level = |s: LevelState| Level {
            failures: s.failures,
            locked_until: (s.locked_s > 0).then(|| now + Duration::from_secs(s.locked_s)),
        };
        Lockout {
            levels: [level(state.service), level(state.setup)],
            first_lock,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locks_grow_and_only_success_ends_them() {
        let now = Instant::now();
        let mut l = Lockout::default();
        assert_eq!(l.failure(Privilege::Service, now), Failed::Counted(1));
        assert_eq!(l.failure(Privilege::Service, now), Failed::Counted(2));
        assert_eq!(
            l.failure(Privilege::Service, now),
            Failed::Locked(Duration::from_secs(30))
        );
        assert_eq!(
            l.locked(Privilege::Service, now),
            Some(Duration::from_secs(30))
        );
        assert_eq!(l.locked(Privilege::Setup, now), None, "per level");
        let later = now + Duration::from_secs(31);
        assert_eq!(l.locked(Privilege::Service, later), None);
        assert_eq!(
            l.failure(Privilege::Service, later),
            Failed::Locked(Duration::from_secs(60))
        );
        // Stored and restored: the count and the rest of the lock survive.
        let state = l.state(later + Duration::from_secs(20));
        assert_eq!(
            state.service,
            LevelState {
                failures: 4,
                locked_s: 40
            }
        );
        let restored = Lockout::restore(state, FIRST_LOCK, later);
        assert_eq!(
            restored.locked(Privilege::Service, later),
            Some(Duration::from_secs(40))
        );
        l.success(Privilege::Service);
        assert_eq!(l.state(later).service, LevelState::default());
        // User and engineer-on-site have no count.
        assert_eq!(l.failure(Privilege::User, now), Failed::Counted(0));
    }

    #[test]
    fn the_first_lock_is_configurable_and_the_longest_is_an_hour() {
        let now = Instant::now();
        let mut l = Lockout::new(Duration::from_secs(5));
        for _ in 0..2 {
            l.failure(Privilege::Setup, now);
        }
        assert_eq!(
            l.failure(Privilege::Setup, now),
            Failed::Locked(Duration::from_secs(5))
        );
        for _ in 0..20 {
            l.failure(Privilege::Setup, now);
        }
        assert_eq!(
            l.failure(Privilege::Setup, now),
            Failed::Locked(LONGEST_LOCK)
        );
    }
}
