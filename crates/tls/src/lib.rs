//! TLS for the connector (NXg SW003 §5: TLS only, public or private CA) and the portal's
//! operator API: rustls with aws-lc-rs (or ring, [`PROVIDER`]), PEM certificates and keys, the
//! private CA of a file or the system's roots, client configurations (optionally with a client
//! certificate) and server configurations (optionally requiring one). Shared by the gateway, the portal and the
//! operator client, without bringing either side's stack to the other.

#![warn(missing_docs)]

pub mod reach;
pub mod stream;
pub mod tickets;

use std::path::Path;
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::{ClientConfig, RootCertStore, ServerConfig};

/// Why TLS could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A PEM file could not be read or holds nothing usable.
    #[error("{path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// rustls refused the configuration.
    #[error("TLS: {0}")]
    Rustls(#[from] rustls::Error),
    /// Shared session-ticket keys that are none.
    #[error("ticket keys: {0}")]
    TicketKeys(&'static str),
}

pub(crate) fn file_error(path: &Path, reason: impl ToString) -> TlsError {
    TlsError::File {
        path: path.display().to_string(),
        reason: reason.to_string(),
    }
}

/// Write `text` to `path` readable by the owner only (private keys, ticket keys), replacing it
/// whole: a crash leaves the old file or the new one.
pub fn write_private(path: &Path, text: &str) -> Result<(), TlsError> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let temporary = path.with_extension("new");
    let written = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(&temporary)
        .and_then(|mut f| {
            f.write_all(text.as_bytes())?;
            f.sync_all()
        })
        .and_then(|()| std::fs::rename(&temporary, path));
    written.map_err(|e| file_error(path, e))
}

/// Certificates of a PEM file (at least one).
pub fn certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let certs = CertificateDer::pem_file_iter(path)
        .map_err(|e| file_error(path, e))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| file_error(path, e))?;
    if certs.is_empty() {
        return Err(file_error(path, "no certificate in the file"));
    }
    Ok(certs)
}

/// The private key of a PEM file.
pub fn private_key(path: &Path) -> Result<PrivateKeyDer<'static>, TlsError> {
    PrivateKeyDer::from_pem_file(path).map_err(|e| file_error(path, e))
}

/// The crypto provider of this build: `"aws-lc-rs"` (feature `aws-lc-rs`) or `"ring"`.
pub const PROVIDER: &str = if cfg!(feature = "aws-lc-rs") {
    "aws-lc-rs"
} else {
    "ring"
};

/// The provider every canlift TLS endpoint uses ([`PROVIDER`]: aws-lc-rs's where it builds,
/// faster at the key exchange and RSA signatures a full handshake costs, docs/BENCHMARKS.md
/// §Crypto providers; else ring's), with the AES-128-GCM suites first.
///
/// Their key schedule (TLS 1.3) and PRF (TLS 1.2) hash with SHA-256, which both providers
/// compute with the CPU's SHA instructions where it has them (x86 since AMD Zen and Intel Ice
/// Lake, ARMv8), while SHA-384 — rustls's first choice, AES-256-GCM — ran in plain code on AMD
/// with ring: in a reconnect storm SHA-384 was 4 % of a gateway's CPU (docs/BENCHMARKS.md
/// §Reconnect storms). AES-128 also has 10 rounds to AES-256's 14. TLS_AES_128_GCM_SHA256 is the
/// suite every TLS 1.3 endpoint must offer (RFC 8446 §9.1); browsers and Go's TLS prefer it the
/// same way. A server follows the client's order, so peers that prefer another suite still get
/// it.
pub fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    use rustls::CipherSuite::{
        TLS13_AES_128_GCM_SHA256, TLS_ECDHE_ECDSA_WITH_AES_128_GCM_SHA256,
        TLS_ECDHE_RSA_WITH_AES_128_GCM_SHA256,
    };
    #[cfg(feature = "aws-lc-rs")]
    let mut provider = rustls::crypto::aws_lc_rs::default_provider();
    #[cfg(not(feature = "aws-lc-rs"))]
    let mut provider = rustls::crypto::ring::default_provider();
    // Stable: the others keep rustls's order.
    provider.cipher_suites.sort_by_key(|s| {
        !matches!(
            s.suite(),
            TLS13_AES_128_GCM_SHA256
                | TLS_ECDHE_ECDSA_WITH_AES_128_GCM_SHA256
                | TLS_ECDHE_RSA_WITH_AES_128_GCM_SHA256
        )
    });
    Arc::new(provider)
}

/// The CA certificates of `ca_file`, or the system's roots when there is none.
pub fn roots(ca_file: Option<&Path>) -> Result<RootCertStore, TlsError> {
    let mut roots = RootCertStore::empty();
    match ca_file {
        Some(path) => {
            for cert in certificates(path)? {
                roots.add(cert).map_err(|e| file_error(path, e))?;
            }
        }
        None => {
            let native = rustls_native_certs::load_native_certs();
            for e in &native.errors {
                tracing::warn!(error = %e, "system root certificates partly unreadable");
            }
            let (added, _) = roots.add_parsable_certificates(native.certs);
            if added == 0 {
                return Err(TlsError::File {
                    path: "system roots".into(),
                    reason: "no usable root certificate; give a CA file".into(),
                });
            }
        }
    }
    Ok(roots)
}

/// A client certificate chain and its key, as PEM files.
#[derive(Debug, Clone, Copy)]
pub struct Identity<'a> {
    /// The certificate chain.
    pub cert: &'a Path,
    /// Its private key.
    pub key: &'a Path,
}

/// A client trusting `ca_file` (or the system's roots), presenting `identity` if given.
pub fn client_config(
    ca_file: Option<&Path>,
    identity: Option<Identity<'_>>,
) -> Result<Arc<ClientConfig>, TlsError> {
    let builder = ClientConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()?
        .with_root_certificates(roots(ca_file)?);
    let config = match identity {
        Some(id) => builder.with_client_auth_cert(certificates(id.cert)?, private_key(id.key)?)?,
        None => builder.with_no_client_auth(),
    };
    Ok(Arc::new(config))
}

/// A server presenting `cert` with `key`; with `client_ca`, clients must present a certificate
/// signed by one of its CAs (mutual TLS).
pub fn server_config(
    cert: &Path,
    key: &Path,
    client_ca: Option<&Path>,
) -> Result<ServerConfig, TlsError> {
    let builder =
        ServerConfig::builder_with_provider(provider()).with_safe_default_protocol_versions()?;
    let builder = match client_ca {
        Some(ca) => {
            let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(
                Arc::new(roots(Some(ca))?),
                provider(),
            )
            .build()
            .map_err(|e| file_error(ca, e))?;
            builder.with_client_cert_verifier(verifier)
        }
        None => builder.with_no_client_auth(),
    };
    Ok(builder.with_single_cert(certificates(cert)?, private_key(key)?)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_are_read_and_bad_ones_named() {
        let dir = tempfile::tempdir().unwrap();
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(vec!["localhost".to_owned()])
            .unwrap()
            .self_signed(&key)
            .unwrap();
        let (cert_path, key_path) = (dir.path().join("c.pem"), dir.path().join("k.pem"));
        std::fs::write(&cert_path, cert.pem()).unwrap();
        std::fs::write(&key_path, key.serialize_pem()).unwrap();
        assert_eq!(certificates(&cert_path).unwrap().len(), 1);
        assert!(server_config(&cert_path, &key_path, Some(&cert_path)).is_ok());
        assert!(client_config(Some(&cert_path), None).is_ok());
        let empty = dir.path().join("empty.pem");
        std::fs::write(&empty, "").unwrap();
        let e = certificates(&empty).unwrap_err().to_string();
        assert!(
            e.contains("empty.pem") && e.contains("no certificate"),
            "{e}"
        );
        assert!(private_key(&dir.path().join("missing.pem")).is_err());
    }
}
