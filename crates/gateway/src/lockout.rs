//! The elevation lock-out kept across restarts (docs/PROTOCOL.md §Privileges): the failure
//! counts and the rest of a lock per level, in `STATE_DIR/elevation.json`, written atomically
//! whenever they change. A damaged file is reported and read as "no failures".

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use nxg::gateway::{Lockout, LockoutState};

/// Where the lock-out lives.
#[derive(Debug, Clone)]
pub struct LockoutStore {
    path: PathBuf,
    first_lock: Duration,
}

impl LockoutStore {
    /// The file in `dir`; the third wrong hash locks for `first_lock`.
    pub fn new(dir: &Path, first_lock: Duration) -> LockoutStore {
        LockoutStore {
            path: dir.join("elevation.json"),
            first_lock,
        }
    }

    /// The stored lock-out, counted from now.
    pub fn load(&self) -> Lockout {
        let state = match std::fs::read_to_string(&self.path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(LockoutState::default()),
            read => read
                .map_err(|e| e.to_string())
                .and_then(|text| serde_json::from_str(&text).map_err(|e| e.to_string())),
        }
        .unwrap_or_else(|error| {
            tracing::error!(path = %self.path.display(), error, "elevation lock-out unreadable; starting without");
            LockoutState::default()
        });
        Lockout::restore(state, self.first_lock, Instant::now())
    }

    /// Store `state`.
    pub fn store(&self, state: &LockoutState) -> std::io::Result<()> {
        let text = serde_json::to_string(state).map_err(std::io::Error::other)?;
        canopen::storage::write_atomically(&self.path, &format!("{text}\n"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nxg::gateway::LevelState;
    use nxg::meta::Privilege;

    #[test]
    fn survives_a_restart_and_a_damaged_file_means_none() {
        let dir = tempfile::tempdir().unwrap();
        let store = LockoutStore::new(dir.path(), nxg::gateway::FIRST_LOCK);
        assert_eq!(store.load(), Lockout::default());
        let state = LockoutState {
            service: LevelState {
                failures: 3,
                locked_s: 30,
            },
            setup: LevelState::default(),
        };
        store.store(&state).unwrap();
        let restored = store.load();
        assert!(restored
            .locked(Privilege::Service, Instant::now())
            .is_some());
        std::fs::write(dir.path().join("elevation.json"), "{broken").unwrap();
        assert_eq!(store.load(), Lockout::default());
    }
}
