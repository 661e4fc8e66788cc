//! Whether the database takes writes now (docs/PORTAL.md §Health): the kind of trouble the
//! store's writers and its write probe saw last, cleared by the next write that succeeds.
//! `/healthz` answers 503 naming it while it lasts.

use std::fmt;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::StoreError;

/// Why the database cannot take writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trouble {
    /// The disk (or the database's quota) is full: SQLite's `SQLITE_FULL`, PostgreSQL's
    /// `disk_full` (53100).
    DiskFull,
    /// Another writer holds the database (SQLite's `SQLITE_BUSY`, `SQLITE_LOCKED`) or it has no
    /// resources to spare (PostgreSQL's class 53).
    Busy,
    /// An I/O error on the database's files.
    Io,
    /// The database cannot be reached: down, restarting, or no connection free in time.
    Unreachable,
}

impl fmt::Display for Trouble {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Trouble::DiskFull => "disk full",
            Trouble::Busy => "busy",
            Trouble::Io => "I/O error",
            Trouble::Unreachable => "unreachable",
        })
    }
}

impl Trouble {
    /// The trouble `error` is, if it is one that passes: a statement the database refused
    /// for what it says (a constraint, a syntax) is none.
    pub fn of(error: &sqlx::Error) -> Option<Trouble> {
        match error {
            sqlx::Error::Io(_)
            | sqlx::Error::Tls(_)
            | sqlx::Error::PoolTimedOut
            | sqlx::Error::PoolClosed
            | sqlx::Error::WorkerCrashed
            | sqlx::Error::Protocol(_) => Some(Trouble::Unreachable),
            sqlx::Error::Database(e) => e.code().and_then(|code| Trouble::of_code(&code)),
            _ => None,
        }
    }

    /// The trouble of a database's error code: SQLite's (extended) result codes as numbers,
    /// PostgreSQL's SQLSTATEs.
    fn of_code(code: &str) -> Option<Trouble> {
        // A SQLSTATE has five characters; SQLite's result codes have at most four digits.
        if let Some(sqlite) = code.parse::<i32>().ok().filter(|_| code.len() < 5) {
            // The primary result code is the low byte of an extended one.
            return match sqlite & 0xFF {
                13 => Some(Trouble::DiskFull),
                5 | 6 => Some(Trouble::Busy),
                10 => Some(Trouble::Io),
                _ => None,
            };
        }
        match code {
            "53100" => Some(Trouble::DiskFull),
            "58030" => Some(Trouble::Io),
            // Admin shutdown, crash shutdown, cannot connect now, and the connection
            // exceptions of class 08.
            "57P01" | "57P02" | "57P03" => Some(Trouble::Unreachable),
            c if c.starts_with("08") => Some(Trouble::Unreachable),
            c if c.starts_with("53") => Some(Trouble::Busy),
            _ => None,
        }
    }
}

/// What the store's writers saw last.
#[derive(Default)]
pub struct Health {
    state: Mutex<Option<(Trouble, Instant)>>,
}

impl Health {
    /// Take note of a write's outcome: a success clears the trouble, a failure that is one
    /// notes it (a refusal for what the statement says changes nothing).
    pub fn note<T>(&self, outcome: &Result<T, StoreError>) {
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        match outcome {
            Ok(_) => *state = None,
            Err(e) => {
                if let Some(trouble) = e.trouble() {
                    let since = state.map_or_else(Instant::now, |(_, since)| since);
                    *state = Some((trouble, since));
                }
            }
        }
    }

    /// The trouble now, and for how long it has lasted.
    pub fn trouble(&self) -> Option<(Trouble, Duration)> {
        let state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        state.map(|(trouble, since)| (trouble, since.elapsed()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn database_codes_name_their_trouble() {
        assert_eq!(Trouble::of_code("13"), Some(Trouble::DiskFull));
        assert_eq!(Trouble::of_code("5"), Some(Trouble::Busy));
        // SQLITE_BUSY_SNAPSHOT, SQLITE_IOERR_WRITE: extended codes of the primary ones.
        assert_eq!(Trouble::of_code("517"), Some(Trouble::Busy));
        assert_eq!(Trouble::of_code("778"), Some(Trouble::Io));
        assert_eq!(
            Trouble::of_code("2067"),
            None,
            "a unique constraint is no trouble"
        );
        assert_eq!(Trouble::of_code("53100"), Some(Trouble::DiskFull));
        assert_eq!(Trouble::of_code("57P01"), Some(Trouble::Unreachable));
        assert_eq!(Trouble::of_code("08006"), Some(Trouble::Unreachable));
        assert_eq!(Trouble::of_code("53300"), Some(Trouble::Busy));
        assert_eq!(Trouble::of_code("23505"), None);
        assert_eq!(
            Trouble::of(&sqlx::Error::PoolTimedOut),
            Some(Trouble::Unreachable)
        );
        assert_eq!(Trouble::of(&sqlx::Error::RowNotFound), None);
    }

    #[test]
    fn a_success_clears_what_a_failure_noted() {
        let health = Health::default();
        health.note(&Err::<(), _>(StoreError::from(sqlx::Error::PoolTimedOut)));
        assert_eq!(health.trouble().map(|t| t.0), Some(Trouble::Unreachable));
        health.note(&Err::<(), _>(StoreError::no_row()));
        assert_eq!(
            health.trouble().map(|t| t.0),
            Some(Trouble::Unreachable),
            "a refusal changes nothing"
        );
        health.note(&Ok::<(), StoreError>(()));
        assert_eq!(health.trouble(), None);
    }
}
