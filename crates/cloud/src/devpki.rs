//! A development PKI: a private CA and a server certificate for localhost, generated once into a
//! state directory and reused (for `canlift cloud` without certificates, `canlift demo`, the
//! benchmarks). Not for production: any portal's development CA is as good as another's. The
//! CA's key signs the one server certificate and is not kept; the server's key is written for
//! its owner alone.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair, KeyUsagePurpose};

/// The PEM files of a development PKI.
#[derive(Debug, Clone)]
pub struct DevPki {
    /// The CA certificate clients trust.
    pub ca: PathBuf,
    /// The server certificate (localhost, 127.0.0.1).
    pub cert: PathBuf,
    /// The server's private key.
    pub key: PathBuf,
}

/// The PKI in `dir`, generated if it is not there yet.
pub fn ensure(dir: &Path) -> anyhow::Result<DevPki> {
    let pki = DevPki {
        ca: dir.join("dev-ca.pem"),
        cert: dir.join("dev-server.pem"),
        key: dir.join("dev-server.key"),
    };
    if pki.ca.exists() && pki.cert.exists() && pki.key.exists() {
        return Ok(pki);
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut ca_params = CertificateParams::new(Vec::<String>::new())?;
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca_params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "canlift development CA");
    let ca_key = KeyPair::generate()?;
    let ca_cert = ca_params.self_signed(&ca_key)?;
    let issuer = Issuer::new(ca_params, ca_key);
    let mut params = CertificateParams::new(vec!["localhost".to_owned(), "127.0.0.1".to_owned()])?;
    params
        .distinguished_name
        .push(DnType::CommonName, "canlift development portal");
    let key = KeyPair::generate()?;
    let cert = params.signed_by(&key, &issuer)?;
    tls::write_private(&pki.key, &key.serialize_pem())?;
    std::fs::write(&pki.cert, cert.pem())?;
    std::fs::write(&pki.ca, ca_cert.pem())?;
    Ok(pki)
}
