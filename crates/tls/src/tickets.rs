//! Stateless TLS 1.3 session tickets (RFC 8446 §4.6.1, §2.2) whose keys outlive the process.
//!
//! A full handshake costs the portal an ECDSA signature and the gateway a certificate chain
//! check; a resumed one costs neither. rustls's own ticketer keeps its keys in memory, so a
//! restarted portal could resume nobody: every gateway it had would come back with a full
//! handshake at once (the reconnect storm of docs/BENCHMARKS.md). [`TicketKeys`] keeps the keys
//! in a file of the state directory (mode 0600) instead, rotates them (a ticket is accepted for
//! at most two rotation periods), and encrypts tickets with AES-256-GCM under a random nonce.
//! Processes of a portal cluster share one set of keys kept by their database instead
//! ([`TicketKeys::shared`], [`TicketKeys::due`]): a gateway resumes its session on whichever
//! process it reaches.
//!
//! Ticket layout: key id (4 bytes) ‖ nonce (12 bytes) ‖ AES-256-GCM(ticket plaintext) ‖ tag.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use ring::aead::{Aad, LessSafeKey, Nonce, UnboundKey, AES_256_GCM, NONCE_LEN};
use ring::rand::{SecureRandom, SystemRandom};

use crate::{file_error, write_private, TlsError};

/// Why a text of keys is none.
#[derive(Debug, thiserror::Error)]
#[error("ticket keys: {0}")]
pub struct BadKeys(&'static str);

impl From<BadKeys> for TlsError {
    fn from(e: BadKeys) -> TlsError {
        TlsError::TicketKeys(e.0)
    }
}

const KEY_LEN: usize = 32;
const ID_LEN: usize = 4;

/// One ticket key: its id (the ticket's first bytes), when it was made, the secret.
struct Key {
    id: [u8; ID_LEN],
    created: u64,
    secret: [u8; KEY_LEN],
}

impl Key {
    fn generate(rng: &SystemRandom, created: u64) -> Option<Key> {
        let mut id = [0u8; ID_LEN];
        let mut secret = [0u8; KEY_LEN];
        rng.fill(&mut id).ok()?;
        rng.fill(&mut secret).ok()?;
        Some(Key {
            id,
            created,
            secret,
        })
    }

    fn aead(&self) -> Option<LessSafeKey> {
        Some(LessSafeKey::new(
            UnboundKey::new(&AES_256_GCM, &self.secret).ok()?,
        ))
    }

    /// `ID CREATED SECRET` in hex and decimal, one line.
    fn line(&self) -> String {
        format!("{} {} {}\n", hex(&self.id), self.created, hex(&self.secret))
    }

    fn parse(line: &str) -> Option<Key> {
        let mut words = line.split_whitespace();
        let id = unhex(words.next()?)?.try_into().ok()?;
        let created = words.next()?.parse().ok()?;
        let secret = unhex(words.next()?)?.try_into().ok()?;
        words.next().is_none().then_some(Key {
            id,
            created,
            secret,
        })
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) || !text.is_ascii() {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).ok())
        .collect()
}

/// The keys in use: tickets are made with `current` and opened with either.
struct Ring {
    current: (Key, LessSafeKey),
    previous: Option<(Key, LessSafeKey)>,
}

/// A key with its cipher, ready for use.
fn keyed(key: Key) -> Option<(Key, LessSafeKey)> {
    let aead = key.aead()?;
    Some((key, aead))
}

impl Ring {
    /// The keys of `text` (as [`Ring::file_text`] writes them): the current key, then the
    /// previous one if there is one.
    fn parse(text: &str) -> Result<Ring, BadKeys> {
        let mut keys = text
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(Key::parse);
        let current = keys.next().flatten().ok_or(BadKeys("no ticket key"))?;
        let previous = keys
            .next()
            .map(|k| k.ok_or(BadKeys("the second line is no ticket key")))
            .transpose()?;
        Ring::from_keys(current, previous).ok_or(BadKeys("unusable ticket key"))
    }

    /// One new key, nothing previous.
    fn fresh(rng: &SystemRandom, now: u64) -> Result<Ring, BadKeys> {
        let key = Key::generate(rng, now).ok_or(BadKeys("no randomness for a ticket key"))?;
        Ring::from_keys(key, None).ok_or(BadKeys("unusable ticket key"))
    }

    /// A new current key when the current one is `rotate` old at `now`: whether it rotated.
    fn rotate_if_due(&mut self, rng: &SystemRandom, rotate: Duration, now: u64) -> bool {
        if now.saturating_sub(self.current.0.created) < rotate.as_secs() {
            return false;
        }
        let Some(next) = Key::generate(rng, now).and_then(keyed) else {
            tracing::error!("no randomness for a new ticket key: the old one stays");
            return false;
        };
        let old = std::mem::replace(&mut self.current, next);
        self.previous = Some(old);
        true
    }

    fn from_keys(current: Key, previous: Option<Key>) -> Option<Ring> {
        let previous = match previous {
            Some(k) => Some(keyed(k)?),
            None => None,
        };
        Some(Ring {
            current: keyed(current)?,
            previous,
        })
    }

    fn file_text(&self) -> String {
        let mut text = self.current.0.line();
        if let Some((previous, _)) = &self.previous {
            text.push_str(&previous.line());
        }
        text
    }
}

/// Session-ticket keys kept in a file (or by a cluster's database), for
/// [`rustls::ServerConfig::ticketer`].
pub struct TicketKeys {
    /// The file; `None`: shared keys, rotated by whoever keeps them and [installed] here.
    ///
    /// [installed]: TicketKeys::install
    path: Option<PathBuf>,
    rotate: Duration,
    rng: SystemRandom,
    keys: Mutex<Ring>,
}

impl fmt::Debug for TicketKeys {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Never the secrets.
        f.debug_struct("TicketKeys")
            .field("path", &self.path)
            .field("rotate", &self.rotate)
            .finish_non_exhaustive()
    }
}

fn now_s() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

impl TicketKeys {
    /// The keys of `path`, made (and the file written) when it does not exist yet; rotated when
    /// the current key is older than `rotate`. A file that cannot be read as keys is an error,
    /// not silently replaced: it may be another process's.
    pub fn open(path: &Path, rotate: Duration) -> Result<TicketKeys, TlsError> {
        let rng = SystemRandom::new();
        let ring = match std::fs::read_to_string(path) {
            Ok(text) => Ring::parse(&text).map_err(|e| file_error(path, e.0))?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                let ring = Ring::fresh(&rng, now_s()).map_err(|e| file_error(path, e.0))?;
                write_private(path, &ring.file_text())?;
                ring
            }
            Err(e) => return Err(file_error(path, e)),
        };
        let keys = TicketKeys {
            path: Some(path.to_owned()),
            rotate: rotate.max(Duration::from_secs(1)),
            rng,
            keys: Mutex::new(ring),
        };
        keys.rotate_if_due(&mut keys.lock(), now_s());
        Ok(keys)
    }

    /// Keys kept elsewhere (a portal cluster's database) as `text`, which [`TicketKeys::due`]
    /// made: not rotated here, replaced by [`TicketKeys::install`].
    pub fn shared(text: &str, rotate: Duration) -> Result<TicketKeys, BadKeys> {
        Ok(TicketKeys {
            path: None,
            rotate: rotate.max(Duration::from_secs(1)),
            rng: SystemRandom::new(),
            keys: Mutex::new(Ring::parse(text)?),
        })
    }

    /// Use the keys of `text` from now on.
    pub fn install(&self, text: &str) -> Result<(), BadKeys> {
        *self.lock() = Ring::parse(text)?;
        Ok(())
    }

    /// The keys that should replace `text` at `now` (s since the Unix epoch): new ones when
    /// there are none, a rotation when the current key is `rotate` old; `None` while `text` is
    /// still good.
    pub fn due(text: Option<&str>, rotate: Duration, now: u64) -> Result<Option<String>, BadKeys> {
        let rng = SystemRandom::new();
        let Some(text) = text else {
            return Ring::fresh(&rng, now).map(|ring| Some(ring.file_text()));
        };
        let mut ring = Ring::parse(text)?;
        let rotate = rotate.max(Duration::from_secs(1));
        Ok(ring
            .rotate_if_due(&rng, rotate, now)
            .then(|| ring.file_text()))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Ring> {
        self.keys.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A new current key when the current one is older than the rotation period; the file
    /// follows (a failure to write it costs restarts their resumption, not this process's).
    /// Shared keys are rotated by their keeper.
    fn rotate_if_due(&self, ring: &mut Ring, now: u64) {
        let Some(path) = &self.path else {
            return;
        };
        if !ring.rotate_if_due(&self.rng, self.rotate, now) {
            return;
        }
        if let Err(e) = write_private(path, &ring.file_text()) {
            tracing::error!(error = %e, "ticket keys not written: a restart will not resume sessions");
        }
    }
}

impl rustls::server::ProducesTickets for TicketKeys {
    fn enabled(&self) -> bool {
        true
    }

    /// Tickets made now are accepted until the key after the next rotation replaces theirs.
    fn lifetime(&self) -> u32 {
        u32::try_from(self.rotate.as_secs().saturating_mul(2)).unwrap_or(u32::MAX)
    }

    fn encrypt(&self, plain: &[u8]) -> Option<Vec<u8>> {
        let mut nonce = [0u8; NONCE_LEN];
        self.rng.fill(&mut nonce).ok()?;
        let mut ring = self.lock();
        self.rotate_if_due(&mut ring, now_s());
        let (key, aead) = &ring.current;
        let mut ticket = Vec::with_capacity(ID_LEN + NONCE_LEN + plain.len() + 16);
        ticket.extend_from_slice(&key.id);
        ticket.extend_from_slice(&nonce);
        ticket.extend_from_slice(plain);
        let (head, body) = ticket.split_at_mut(ID_LEN + NONCE_LEN);
        let tag = aead
            .seal_in_place_separate_tag(
                Nonce::assume_unique_for_key(nonce),
                Aad::from(&head[..ID_LEN]),
                body,
            )
            .ok()?;
        ticket.extend_from_slice(tag.as_ref());
        Some(ticket)
    }

    fn decrypt(&self, cipher: &[u8]) -> Option<Vec<u8>> {
        let (id, rest) = cipher.split_at_checked(ID_LEN)?;
        let (nonce, sealed) = rest.split_at_checked(NONCE_LEN)?;
        let nonce = Nonce::try_assume_unique_for_key(nonce).ok()?;
        let ring = self.lock();
        let (_, aead) = std::iter::once(&ring.current)
            .chain(ring.previous.as_ref())
            .find(|(key, _)| key.id == id)?;
        let mut plain = sealed.to_vec();
        let len = aead
            .open_in_place(nonce, Aad::from(id), &mut plain)
            .ok()?
            .len();
        plain.truncate(len);
        Some(plain)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rustls::server::ProducesTickets;

    #[test]
    fn a_ticket_opens_after_a_restart_and_not_after_two_rotations() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tickets");
        let day = Duration::from_secs(86_400);
        let keys = TicketKeys::open(&path, day).unwrap();
        let ticket = keys.encrypt(b"session state").unwrap();
        assert_eq!(keys.decrypt(&ticket).unwrap(), b"session state");
        assert_eq!(keys.lifetime(), 2 * 86_400);

        // Another process on the same state directory.
        let restarted = TicketKeys::open(&path, day).unwrap();
        assert_eq!(restarted.decrypt(&ticket).unwrap(), b"session state");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&path).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600);

        // One rotation: still opened by the previous key; two: gone.
        let now = now_s();
        restarted.rotate_if_due(&mut restarted.lock(), now + 86_400);
        assert_eq!(restarted.decrypt(&ticket).unwrap(), b"session state");
        let fresh = restarted.encrypt(b"new").unwrap();
        assert_ne!(fresh[..ID_LEN], ticket[..ID_LEN]);
        restarted.rotate_if_due(&mut restarted.lock(), now + 2 * 86_400);
        assert!(restarted.decrypt(&ticket).is_none());
        assert_eq!(restarted.decrypt(&fresh).unwrap(), b"new");
        // The rotation is on disk: a third process opens the newest ticket.
        let third = TicketKeys::open(&path, day).unwrap();
        assert_eq!(third.decrypt(&fresh).unwrap(), b"new");
    }

    #[test]
    fn forged_and_truncated_tickets_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let keys = TicketKeys::open(&dir.path().join("t"), Duration::from_secs(3600)).unwrap();
        let ticket = keys.encrypt(b"abc").unwrap();
        for cut in 0..ticket.len() {
            assert!(keys.decrypt(&ticket[..cut]).is_none(), "cut at {cut}");
        }
        for i in 0..ticket.len() {
            let mut forged = ticket.clone();
            forged[i] ^= 1;
            assert!(keys.decrypt(&forged).is_none(), "bit flipped in byte {i}");
        }
        let other = TicketKeys::open(&dir.path().join("u"), Duration::from_secs(3600)).unwrap();
        assert!(other.decrypt(&ticket).is_none());
    }

    /// Two processes on one shared text open each other's tickets; a rotation made by one
    /// and installed by the other keeps the previous key's tickets open.
    #[test]
    fn shared_keys_are_rotated_by_their_keeper_and_installed() {
        let hour = Duration::from_secs(3600);
        let now = now_s();
        let text = TicketKeys::due(None, hour, now).unwrap().unwrap();
        assert_eq!(TicketKeys::due(Some(&text), hour, now + 10).unwrap(), None);
        let (a, b) = (
            TicketKeys::shared(&text, hour).unwrap(),
            TicketKeys::shared(&text, hour).unwrap(),
        );
        let ticket = a.encrypt(b"state").unwrap();
        assert_eq!(b.decrypt(&ticket).unwrap(), b"state");
        // Shared keys do not rotate by themselves, even long after.
        b.rotate_if_due(&mut b.lock(), now + 10 * 3600);
        assert_eq!(b.decrypt(&ticket).unwrap(), b"state");
        let rotated = TicketKeys::due(Some(&text), hour, now + 3600)
            .unwrap()
            .unwrap();
        a.install(&rotated).unwrap();
        b.install(&rotated).unwrap();
        let fresh = b.encrypt(b"new").unwrap();
        assert_ne!(fresh[..ID_LEN], ticket[..ID_LEN]);
        assert_eq!(a.decrypt(&ticket).unwrap(), b"state");
        assert_eq!(a.decrypt(&fresh).unwrap(), b"new");
        assert!(a.install("damaged").is_err());
        assert_eq!(
            a.decrypt(&fresh).unwrap(),
            b"new",
            "a damaged text changes nothing"
        );
        assert!(TicketKeys::due(Some("damaged"), hour, now).is_err());
    }

    #[test]
    fn a_damaged_key_file_is_an_error_not_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tickets");
        std::fs::write(&path, "not a key\n").unwrap();
        let e = TicketKeys::open(&path, Duration::from_secs(60)).unwrap_err();
        assert!(e.to_string().contains("no ticket key"), "{e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "not a key\n");
    }
}
