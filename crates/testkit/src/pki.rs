//! A private CA made with rcgen, a server certificate for localhost and 127.0.0.1, and a
//! client certificate for mutual TLS, as PEM files.

use std::path::{Path, PathBuf};

use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair, KeyUsagePurpose};

/// The PEM files of a test PKI.
pub struct TestPki {
    /// The CA certificate.
    pub ca: PathBuf,
    /// The server certificate.
    pub cert: PathBuf,
    /// The server's key.
    pub key: PathBuf,
    /// A client certificate signed by the same CA.
    pub client_cert: PathBuf,
    /// Its key.
    pub client_key: PathBuf,
}

/// Make a PKI in `dir`.
pub fn pki(dir: &Path) -> TestPki {
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).expect("CA parameters");
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let ca_key = KeyPair::generate().expect("CA key");
    let ca_cert = ca_params.self_signed(&ca_key).expect("CA certificate");
    let issuer = Issuer::new(ca_params, ca_key);
    let sign = |names: Vec<String>| {
        let key = KeyPair::generate().expect("a key");
        let cert = CertificateParams::new(names)
            .expect("certificate parameters")
            .signed_by(&key, &issuer)
            .expect("a certificate");
        (cert, key)
    };
    let (cert, key) = sign(vec!["localhost".to_owned(), "127.0.0.1".to_owned()]);
    let (client, client_key) = sign(vec![format!("gateway-{}", crate::constants::SERNUM)]);
    let pki = TestPki {
        ca: dir.join("ca.pem"),
        cert: dir.join("server.pem"),
        key: dir.join("server.key"),
        client_cert: dir.join("client.pem"),
        client_key: dir.join("client.key"),
    };
    let write = |path: &Path, text: String| std::fs::write(path, text).expect("write a PEM file");
    write(&pki.ca, ca_cert.pem());
    write(&pki.cert, cert.pem());
    write(&pki.key, key.serialize_pem());
    write(&pki.client_cert, client.pem());
    write(&pki.client_key, client_key.serialize_pem());
    pki
}
