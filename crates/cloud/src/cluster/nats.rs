//! How a portal process reaches NATS (docs/CLUSTER.md §Securing NATS): the servers' URLs with the
//! credentials NATS URLs carry — `USER:PASSWORD@` or a `TOKEN@` — and TLS trusting a CA of its
//! own, with a client certificate for servers that verify their clients.
//!
//! Whoever can publish on NATS can ask any lift's holder for anything an operator may ask, so a
//! NATS reachable beyond one machine needs both. async-nats takes no credentials from the URL
//! (it would connect without them, and NATS would refuse it), so they are taken out here; the
//! URL is shown, in logs, errors and `/healthz`, only without them.

use async_nats::{ConnectOptions, ServerAddr};

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

/// What a NATS URL's user part means: `USER:PASSWORD`, or a token alone (as NATS's own clients
/// read it).
#[derive(Debug, PartialEq, Eq)]
enum Credentials {
    UserPassword { user: String, password: String },
    Token(String),
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
    /// `nats_ca`, `nats_cert` and `nats_key`: the files are read now, so that a wrong one stops
    /// the process at start instead of failing every reconnection.
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

    /// `options` with the credentials and, where asked for, TLS required with canlift's TLS
    /// configuration (the CA of `nats_ca`, else the system's roots; the client certificate).
    pub fn apply(&self, options: ConnectOptions) -> ConnectOptions {
        let options = match &self.credentials {
            Some(Credentials::UserPassword { user, password }) => {
                options.user_and_password(user.clone(), password.clone())
            }
            Some(Credentials::Token(token)) => options.token(token.clone()),
            None => options,
        };
        match &self.tls {
            Some(config) => options.require_tls(true).tls_client_config(config.clone()),
            None => options,
        }
    }
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
