//! `[cluster]` of the portal's configuration (docs/CLUSTER.md).

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// `[cluster]`: several portal processes on one PostgreSQL database and one NATS server
/// (docs/CLUSTER.md). Absent `nats`: a portal of its own.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClusterSection {
    /// The NATS server (with JetStream, `nats-server -js`): `nats://HOST:PORT`, or
    /// `tls://HOST:PORT` to require TLS; credentials as NATS URLs carry them,
    /// `nats://USER:PASSWORD@HOST:PORT` or `nats://TOKEN@HOST:PORT` (docs/CLUSTER.md §Securing NATS;
    /// or `nats_creds`, or `nats_nkey`). The servers of a NATS cluster separated by commas.
    pub nats: Option<String>,
    /// Copies of the holder bucket in a NATS cluster (1 to 5; 3 outlives the loss of a NATS
    /// server). A bucket with fewer is given more; one with more keeps them.
    pub nats_replicas: usize,
    /// The CA certificate (PEM) that signed the NATS server's: TLS to NATS, trusting it alone.
    pub nats_ca: Option<PathBuf>,
    /// A client certificate (PEM) to present to a NATS server that verifies its clients (with
    /// `nats_key`).
    pub nats_cert: Option<PathBuf>,
    /// The private key (PEM) of `nats_cert`.
    pub nats_key: Option<PathBuf>,
    /// A NATS user credentials file (the user's JWT and NKey seed, as `nsc generate creds` writes
    /// it) for a NATS server that authenticates by JWT (operator mode).
    pub nats_creds: Option<PathBuf>,
    /// A file holding a NATS user's NKey seed (`SU…`, as `nk -gen user` writes it) for a NATS
    /// server that lists its users by NKey.
    pub nats_nkey: Option<PathBuf>,
    /// This process's name in the cluster; absent: the host name and the listening port.
    pub node: Option<String>,
    /// Seconds a process's lease stands unrenewed (it renews it every third of this): how
    /// long the lifts of a process that died may still look online.
    pub holder_ttl_s: u64,
}

impl Default for ClusterSection {
    fn default() -> Self {
        ClusterSection {
            nats: None,
            nats_ca: None,
            nats_cert: None,
            nats_key: None,
            nats_creds: None,
            nats_nkey: None,
            nats_replicas: 1,
            node: None,
            holder_ttl_s: 15,
        }
    }
}
