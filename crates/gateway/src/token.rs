//! The cloud token, kept durably (NXg §5.4; docs/PROTOCOL.md §Tokens): written to a temporary file, fsynced and renamed
//! over the old one, so a crash leaves the old or the new token, never a broken one.

use std::path::{Path, PathBuf};

/// Where the token lives.
#[derive(Debug, Clone)]
pub struct TokenStore {
    path: PathBuf,
}

impl TokenStore {
    /// The token file in `dir`.
    pub fn new(dir: &Path) -> TokenStore {
        TokenStore {
            path: dir.join("cloudtoken"),
        }
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The stored token, if any (an unreadable or empty file counts as none, and is logged).
    pub fn load(&self) -> Option<String> {
        match std::fs::read_to_string(&self.path) {
            Ok(text) => {
                let token = text.trim_end_matches('\n');
                (!token.is_empty() && token.chars().count() <= 128).then(|| token.to_owned())
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => {
                tracing::error!(path = %self.path.display(), error = %e, "cloud token unreadable");
                None
            }
        }
    }

    /// Store `token` atomically.
    pub fn store(&self, token: &str) -> std::io::Result<()> {
        canopen::storage::write_private_atomically(&self.path, &format!("{token}\n"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stores_and_loads() {
        let dir = tempfile::tempdir().unwrap();
        let store = TokenStore::new(dir.path());
        assert_eq!(store.load(), None);
        store.store("2A98765DE230176C").unwrap();
        assert_eq!(store.load().as_deref(), Some("2A98765DE230176C"));
        store.store("second").unwrap();
        assert_eq!(store.load().as_deref(), Some("second"));
        // No temporary file is left behind.
        let files: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(files.len(), 1);
        // The token is a secret: its owner's alone.
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(store.path())
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);
    }

    #[test]
    fn a_crash_between_write_and_rename_leaves_the_old_token() {
        let dir = tempfile::tempdir().unwrap();
        let store = TokenStore::new(dir.path());
        store.store("old-token").unwrap();
        // What a kill during `store` leaves: a half-written temporary file beside the token.
        std::fs::write(dir.path().join(".cloudtoken.tmp"), "new-to").unwrap();
        assert_eq!(store.load().as_deref(), Some("old-token"));
        // The next store replaces the leftover (of another mode) and the token.
        use std::os::unix::fs::PermissionsExt;
        let leftover = dir.path().join(".cloudtoken.tmp");
        std::fs::set_permissions(&leftover, std::fs::Permissions::from_mode(0o644)).unwrap();
        store.store("new-token").unwrap();
        let mode = std::fs::metadata(store.path())
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "not the leftover's mode");
        assert_eq!(store.load().as_deref(), Some("new-token"));
        assert!(!dir.path().join(".cloudtoken.tmp").exists());
    }
}
