//! How a portal process reaches NATS (docs/CLUSTER.md §Securing NATS): the servers' URLs with the
//! credentials NATS URLs carry — `USER:PASSWORD@` or a `TOKEN@` — or a user's NKey seed or
//! credentials file (JWT), and TLS trusting a CA of its own, with a client certificate for servers
//! that verify their clients.
//!
//! Whoever can publish on NATS can ask any lift's holder for anything an operator may ask, so a
//! NATS reachable beyond one machine needs both. async-nats takes no credentials from the URL
//! (it would connect without them, and NATS would refuse it), so they are taken out here; the
//! URL is shown, in logs, errors and `/healthz`, only without them.

use std::path::{Path, PathBuf};

use async_nats::{Auth, AuthError, ConnectOptions, ServerAddr};

use crate::config::ClusterSection;

/// The NATS servers and how to prove who this process is, checked before the process serves.
pub struct NatsAccess {
    /// The servers, without credentials (async-nats logs them at debug level).
    servers: Vec<ServerAddr>,
    /// Their URLs as they may be shown.
    shown: String,
    credentials: Option<Credentials>,
    tls: Option<rustls::ClientConfig>,
}

/// How this process proves who it is to NATS: one of the ways NATS's authorization offers.
#[derive(PartialEq, Eq)]
enum Credentials {
    /// A NATS URL's `USER:PASSWORD@`.
    UserPassword { user: String, password: String },
    /// A NATS URL's `TOKEN@` (a user part without a password, as NATS's own clients read it).
    Token(String),
    /// `nats_nkey`: a file holding a user's NKey seed, with which the server's nonce is signed;
    /// read again at each connection, as the credentials file is.
    NKey(PathBuf),
    /// `nats_creds`: a credentials file, read again at each connection (a renewed user JWT
    /// is taken up when NATS lets the expired one go), its JWT sent and the server's nonce signed
    /// with its seed (NATS's operator mode).
    Jwt(PathBuf),
}

/// Names the kind of credentials and never a secret.
impl std::fmt::Debug for Credentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Credentials::UserPassword { user, .. } => write!(f, "user {user} with a password"),
            Credentials::Token(_) => f.write_str("a token"),
            Credentials::NKey(file) => write!(f, "NKey seed file {}", file.display()),
            Credentials::Jwt(file) => write!(f, "credentials file {}", file.display()),
        }
    }
}

/// Why `[cluster]` cannot reach NATS as written; the URLs in it are shown without credentials.
#[derive(Debug, thiserror::Error)]
#[error("[cluster] nats = {shown}: {why}")]
pub struct NatsConfigError {
    shown: String,
    why: String,
}

impl NatsAccess {
    /// Read `[cluster] nats` (one URL, or the URLs of a NATS cluster separated by commas),
    /// `nats_creds` or `nats_nkey`, `nats_ca`, `nats_cert` and `nats_key`: the files are read and
    /// the credentials parsed now, so that a wrong one stops the process at start instead of
    /// failing every reconnection.
    pub fn from_config(
        section: &ClusterSection,
        urls: &str,
    ) -> Result<NatsAccess, NatsConfigError> {
        let refuse = |shown: &str, why: String| NatsConfigError {
            shown: shown.to_owned(),
            why,
        };
        let given = urls
            .split(',')
            .map(|url| url.trim().parse::<ServerAddr>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| refuse("(not shown)", e.to_string()))?;
        let servers: Vec<ServerAddr> = given.iter().map(without_credentials).collect();
        let shown = servers
            .iter()
            .map(ServerAddr::as_url_str)
            .collect::<Vec<_>>()
            .join(",");
        if given.iter().any(ServerAddr::is_websocket) {
            return Err(refuse(
                &shown,
                "use nats:// or tls:// (not WebSocket)".into(),
            ));
        }
        let decoded = |part: &str| {
            percent_encoding::percent_decode_str(part)
                .decode_utf8()
                .map(|text| text.into_owned())
                .map_err(|_| refuse(&shown, "the credentials are not UTF-8".into()))
        };
        let mut credentials = None;
        for server in &given {
            let these = match (server.username(), server.password()) {
                (Some(user), Some(password)) => Credentials::UserPassword {
                    user: decoded(user)?,
                    password: decoded(password)?,
                },
                (Some(token), None) => Credentials::Token(decoded(token)?),
                (None, Some(_)) => return Err(refuse(&shown, "a password needs a user".into())),
                (None, None) => continue,
            };
            // One client, one CONNECT: the servers of a NATS cluster share their users.
            match &credentials {
                Some(first) if *first != these => {
                    return Err(refuse(
                        &shown,
                        "the URLs carry different credentials".into(),
                    ))
                }
                _ => credentials = Some(these),
            }
        }
        let mut from_files = Vec::new();
        for (kind, file) in [
            (KeyFile::NKey, &section.nats_nkey),
            (KeyFile::Creds, &section.nats_creds),
        ] {
            let Some(file) = file else { continue };
            let fault = |why: String| refuse(&shown, kind.fault(file, why));
            let text = std::fs::read_to_string(file).map_err(|e| fault(e.to_string()))?;
            kind.key(&text).map_err(fault)?;
            from_files.push(match kind {
                KeyFile::NKey => Credentials::NKey(file.clone()),
                KeyFile::Creds => Credentials::Jwt(file.clone()),
            });
        }
        if from_files.len() + usize::from(credentials.is_some()) > 1 {
            return Err(refuse(
                &shown,
                "one way to authenticate: credentials in the URL, nats_creds or nats_nkey".into(),
            ));
        }
        let credentials = credentials.or(from_files.pop());
        let identity = match (&section.nats_cert, &section.nats_key) {
            (Some(cert), Some(key)) => Some(tls::Identity { cert, key }),
            (None, None) => None,
            _ => return Err(refuse(&shown, "nats_cert and nats_key go together".into())),
        };
        let tls = if given.iter().any(ServerAddr::tls_required)
            || section.nats_ca.is_some()
            || identity.is_some()
        {
            let config = tls::client_config(section.nats_ca.as_deref(), identity)
                .map_err(|e| refuse(&shown, e.to_string()))?;
            Some(std::sync::Arc::unwrap_or_clone(config))
        } else {
            None
        };
        Ok(NatsAccess {
            servers,
            shown,
            credentials,
            tls,
        })
    }

    /// The servers' URLs as they may be shown: without credentials.
    pub fn shown(&self) -> &str {
        &self.shown
    }

    /// An error about these servers (shown without credentials).
    pub(crate) fn error(&self, why: String) -> NatsConfigError {
        NatsConfigError {
            shown: self.shown().to_owned(),
            why,
        }
    }

    /// The servers to connect to.
    pub fn servers(&self) -> Vec<ServerAddr> {
        self.servers.clone()
    }

    /// The client's options: the credentials and, where asked for, TLS required with canlift's
    /// TLS configuration (the CA of `nats_ca`, else the system's roots; the client certificate).
    pub fn options(&self) -> ConnectOptions {
        let options = match &self.credentials {
            Some(Credentials::UserPassword { user, password }) => {
                ConnectOptions::with_user_and_password(user.clone(), password.clone())
            }
            Some(Credentials::Token(token)) => ConnectOptions::with_token(token.clone()),
            Some(Credentials::NKey(file)) => signing_with(KeyFile::NKey, file),
            Some(Credentials::Jwt(file)) => signing_with(KeyFile::Creds, file),
            None => ConnectOptions::new(),
        };
        match &self.tls {
            Some(config) => options.require_tls(true).tls_client_config(config.clone()),
            None => options,
        }
    }
}

/// Which kind of file holds the key that signs a connection.
#[derive(Clone, Copy)]
enum KeyFile {
    /// `nats_nkey`: the seed alone.
    NKey,
    /// `nats_creds`: the user's JWT and its seed.
    Creds,
}

impl KeyFile {
    /// What is wrong with `file`, named by the `[cluster]` option that names it (never its
    /// content).
    fn fault(self, file: &Path, why: String) -> String {
        let option = match self {
            KeyFile::NKey => "nats_nkey",
            KeyFile::Creds => "nats_creds",
        };
        format!("{option} {}: {why}", file.display())
    }

    /// The user's key in `text` (the file's content), with the user's JWT for a credentials
    /// file.
    fn key(self, text: &str) -> Result<(nkeys::KeyPair, Option<String>), String> {
        match self {
            KeyFile::NKey => Ok((user_seed(text)?, None)),
            KeyFile::Creds => user_credentials(text).map(|(jwt, key)| (key, Some(jwt))),
        }
    }
}

/// Options whose every connection reads `file` again and signs the server's nonce with its key,
/// as NATS's own clients do: a replaced file (a renewed JWT, a rotated seed) is taken up at the
/// next connection, without restarting the process.
fn signing_with(kind: KeyFile, file: &Path) -> ConnectOptions {
    let file = file.to_owned();
    ConnectOptions::with_auth_callback(move |nonce| {
        let file = file.clone();
        async move { signed_in(kind, &file, &nonce).await.map_err(AuthError::new) }
    })
}

/// What a connection presents from `file`, read now: the server's `nonce` signed with its seed,
/// with the user's public key (an NKey seed file) or its JWT (a credentials file).
async fn signed_in(kind: KeyFile, file: &Path, nonce: &[u8]) -> Result<Auth, String> {
    let text = tokio::fs::read_to_string(file)
        .await
        .map_err(|e| kind.fault(file, e.to_string()))?;
    let (key, jwt) = kind.key(&text).map_err(|why| kind.fault(file, why))?;
    let mut auth = Auth::new();
    // A JWT names its user; a seed alone, by its public key.
    match jwt {
        Some(jwt) => auth.jwt = Some(jwt),
        None => auth.nkey = Some(key.public_key()),
    }
    auth.signature = Some(key.sign(nonce).map_err(|e| e.to_string())?);
    Ok(auth)
}

/// The key of an NKey seed file: a user's (`SU…`).
fn user_seed(text: &str) -> Result<nkeys::KeyPair, String> {
    let key =
        nkeys::KeyPair::from_seed(text.trim()).map_err(|e| format!("not an NKey seed ({e})"))?;
    if key.key_pair_type() != nkeys::KeyPairType::User {
        return Err("the seed of another kind of key than a user's (SU…)".into());
    }
    Ok(key)
}

/// The user JWT and the key of a NATS credentials file (as `nsc generate creds` writes it): the
/// first two decorated blocks, `-----BEGIN NATS USER JWT-----` and `-----BEGIN USER NKEY
/// SEED-----`, each a line of dashes followed by its value.
fn user_credentials(text: &str) -> Result<(String, nkeys::KeyPair), String> {
    let mut lines = text.lines().map(str::trim);
    let mut blocks = Vec::new();
    while let Some(line) = lines.next() {
        if line.starts_with("---") && line.contains("BEGIN") {
            blocks.extend(lines.next());
        }
    }
    let [jwt, seed, ..] = blocks[..] else {
        return Err("not a credentials file (a user JWT and its seed)".into());
    };
    let key = nkeys::KeyPair::from_seed(seed).map_err(|e| format!("not an NKey seed ({e})"))?;
    if key.key_pair_type() != nkeys::KeyPairType::User || jwt.split('.').count() != 3 {
        return Err("not a user's credentials".into());
    }
    Ok((jwt.to_owned(), key))
}

/// A new NATS user NKey (`canlift cloud nats-nkey`): its public key (`U…`, what the NATS server's
/// configuration lists) and its seed (`SU…`, what `[cluster] nats_nkey` names).
pub fn new_user_nkey() -> Result<(String, String), nkeys::error::Error> {
    let pair = nkeys::KeyPair::new_user();
    Ok((pair.public_key(), pair.seed()?))
}

/// `server` without the user part of its URL.
fn without_credentials(server: &ServerAddr) -> ServerAddr {
    let mut url = server.clone().into_inner();
    // Both fail only for URLs without a host, which a NATS address always has; the scheme is
    // the one `server` was parsed with, so `from_url` takes it again.
    let _ = url.set_password(None);
    let _ = url.set_username("");
    ServerAddr::from_url(url).unwrap_or_else(|_| server.clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn access(url: &str) -> Result<NatsAccess, NatsConfigError> {
        NatsAccess::from_config(&ClusterSection::default(), url)
    }

    #[test]
    fn credentials_are_taken_out_of_the_url_and_decoded() {
        let a = access("nats://canlift:s3cr%3At%40x@127.0.0.1:4222").unwrap();
        assert_eq!(
            a.credentials,
            Some(Credentials::UserPassword {
                user: "canlift".into(),
                password: "s3cr:t@x".into()
            })
        );
        assert_eq!(a.shown(), "nats://127.0.0.1:4222");
        assert!(a.tls.is_none());
        let a = access("nats://T0K%2Fen@nats.internal").unwrap();
        assert_eq!(a.credentials, Some(Credentials::Token("T0K/en".into())));
        assert_eq!(a.servers()[0].port(), 4222);
        assert!(access("nats://127.0.0.1:4222")
            .unwrap()
            .credentials
            .is_none());
    }

    #[test]
    fn the_servers_of_a_nats_cluster_share_their_credentials() {
        let a =
            access("nats://u:p@10.0.0.1:4222, nats://10.0.0.2:4222,nats://u:p@10.0.0.3").unwrap();
        assert_eq!(a.servers().len(), 3);
        assert_eq!(
            a.shown(),
            "nats://10.0.0.1:4222,nats://10.0.0.2:4222,nats://10.0.0.3"
        );
        assert_eq!(
            a.credentials,
            Some(Credentials::UserPassword {
                user: "u".into(),
                password: "p".into()
            })
        );
        assert!(access("nats://10.0.0.1,tls://10.0.0.2")
            .unwrap()
            .tls
            .is_some());
        let e = access("nats://u:p@10.0.0.1,nats://u:secret@10.0.0.2")
            .err()
            .unwrap();
        assert!(e.to_string().contains("different credentials"), "{e}");
        assert!(!e.to_string().contains("secret"), "{e}");
    }

    #[test]
    fn refusals_never_show_the_credentials() {
        for (url, section, why) in [
            (
                "nats://:secret@127.0.0.1:4222",
                ClusterSection::default(),
                "a password needs a user",
            ),
            (
                "ws://user:secret@127.0.0.1:4222",
                ClusterSection::default(),
                "not WebSocket",
            ),
            (
                "nats://user:secret@127.0.0.1:4222",
                ClusterSection {
                    nats_cert: Some("client.pem".into()),
                    ..ClusterSection::default()
                },
                "go together",
            ),
            (
                "tls://user:secret@127.0.0.1:4222",
                ClusterSection {
                    nats_ca: Some("/nonexistent/ca.pem".into()),
                    ..ClusterSection::default()
                },
                "/nonexistent/ca.pem",
            ),
            (
                "nats://user:secret@[::1",
                ClusterSection::default(),
                "invalid",
            ),
        ] {
            let e = NatsAccess::from_config(&section, url)
                .err()
                .unwrap()
                .to_string();
            assert!(e.contains(why), "{url}: {e}");
            assert!(!e.contains("secret"), "{url}: {e}");
        }
    }

    #[test]
    fn nkey_seeds_and_credentials_files_are_read_at_start() {
        let dir = tempfile::tempdir().unwrap();
        let file = |name: &str, text: &str| {
            let path = dir.path().join(name);
            std::fs::write(&path, text).unwrap();
            Some(path)
        };
        let url = "nats://127.0.0.1:4222";
        let (_, seed) = new_user_nkey().unwrap();
        let (creds, _) = testkit::nats::auth::OperatorMode::new().user(None);
        let nkey = ClusterSection {
            nats_nkey: file("user.nk", &format!("{seed}\n")),
            ..ClusterSection::default()
        };
        let a = NatsAccess::from_config(&nkey, url).unwrap();
        assert_eq!(
            a.credentials,
            Some(Credentials::NKey(nkey.nats_nkey.clone().unwrap()))
        );
        let shown = format!("{:?}", a.credentials.unwrap());
        assert!(shown.starts_with("NKey seed file ") && shown.ends_with("user.nk"));
        assert!(!shown.contains(&seed));
        let jwt = ClusterSection {
            nats_creds: file("user.creds", &creds),
            ..ClusterSection::default()
        };
        assert!(matches!(
            NatsAccess::from_config(&jwt, url).unwrap().credentials,
            Some(Credentials::Jwt(_))
        ));

        let account_seed = nkeys::KeyPair::new_account().seed().unwrap();
        let both = ClusterSection {
            nats_nkey: nkey.nats_nkey.clone(),
            nats_creds: jwt.nats_creds.clone(),
            ..ClusterSection::default()
        };
        for (section, url, why) in [
            (
                nkey.clone(),
                "nats://user:pw@127.0.0.1",
                "one way to authenticate",
            ),
            (both, url, "one way to authenticate"),
            (
                ClusterSection {
                    nats_nkey: file("account.nk", &account_seed),
                    ..ClusterSection::default()
                },
                url,
                "another kind of key",
            ),
            (
                ClusterSection {
                    nats_nkey: file("garbage.nk", "SUNOTASEED"),
                    ..ClusterSection::default()
                },
                url,
                "garbage.nk: not an NKey seed",
            ),
            (
                ClusterSection {
                    nats_creds: file("half.creds", &creds[..creds.find("IMPORTANT").unwrap()]),
                    ..ClusterSection::default()
                },
                url,
                "half.creds: not a credentials file",
            ),
            (
                ClusterSection {
                    nats_creds: Some(dir.path().join("absent.creds")),
                    ..ClusterSection::default()
                },
                url,
                "absent.creds: No such file",
            ),
        ] {
            let e = NatsAccess::from_config(&section, url)
                .err()
                .unwrap()
                .to_string();
            assert!(e.contains(why), "{e}");
            assert!(!e.contains(&seed) && !e.contains(&account_seed), "{e}");
        }
    }

    #[tokio::test]
    async fn each_connection_signs_with_the_key_file_as_it_is_then() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("user.nk");
        let nonce = b"a server's nonce";
        for _ in 0..2 {
            // The seed rotated between two connections: the second signs with the new key.
            let (public, seed) = new_user_nkey().unwrap();
            std::fs::write(&file, format!("{seed}\n")).unwrap();
            let auth = signed_in(KeyFile::NKey, &file, nonce).await.unwrap();
            assert_eq!(auth.nkey.as_deref(), Some(public.as_str()));
            assert!(auth.jwt.is_none());
            let signature = auth.signature.unwrap();
            nkeys::KeyPair::from_public_key(&public)
                .unwrap()
                .verify(nonce, &signature)
                .unwrap();
        }
        let (creds, public) = testkit::nats::auth::OperatorMode::new().user(None);
        let file = dir.path().join("user.creds");
        std::fs::write(&file, &creds).unwrap();
        let auth = signed_in(KeyFile::Creds, &file, nonce).await.unwrap();
        assert!(auth.jwt.is_some_and(|jwt| creds.contains(&jwt)));
        nkeys::KeyPair::from_public_key(&public)
            .unwrap()
            .verify(nonce, &auth.signature.unwrap())
            .unwrap();
        // A file broken since the start fails that connection, naming the file, not the seed.
        std::fs::write(&file, "SUNOTASEED").unwrap();
        let Err(e) = signed_in(KeyFile::Creds, &file, nonce).await else {
            panic!("a broken file signs")
        };
        assert!(
            e.starts_with("nats_creds ") && e.contains("user.creds"),
            "{e}"
        );
        std::fs::remove_file(&file).unwrap();
        let Err(e) = signed_in(KeyFile::NKey, &file, nonce).await else {
            panic!("a missing file signs")
        };
        assert!(e.starts_with("nats_nkey "), "{e}");
    }

    #[test]
    fn tls_is_required_by_scheme_or_by_a_ca_file() {
        let dir = tempfile::tempdir().unwrap();
        let with_ca = ClusterSection {
            nats_ca: Some(testkit::pki::pki(dir.path()).ca),
            ..ClusterSection::default()
        };
        let a = NatsAccess::from_config(&with_ca, "nats://nats.internal:4222").unwrap();
        assert!(a.tls.is_some());
        let a = NatsAccess::from_config(&with_ca, "tls://nats.internal:4222").unwrap();
        assert!(a.tls.is_some());
        assert!(access("nats://nats.internal:4222").unwrap().tls.is_none());
    }
}
