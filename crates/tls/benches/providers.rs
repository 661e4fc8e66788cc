//! The two crypto providers rustls offers, side by side in one run: ring (what canlift's TLS
//! uses) and aws-lc-rs (rustls's default), on the primitives a connection of the connector
//! costs — the X25519 key exchange of every handshake, the server's signature of a full
//! handshake (ECDSA P-256 and the RSA-2048 most operators' certificates have), the gateway's
//! verification of it, the sealing of a 200-byte record (a typical NXg message) with both
//! TLS 1.3 ciphers, and the session ticket the portal seals (AES-256-GCM, docs/BENCHMARKS.md
//! §Crypto providers).
//!
//! `cargo bench -p tls --bench providers`

use criterion::{criterion_group, criterion_main, Criterion};

/// A 2048-bit RSA key (PKCS#8 DER): aws-lc-rs makes it, both load it.
fn rsa_key() -> Vec<u8> {
    use aws_lc_rs::encoding::AsDer;
    let key =
        aws_lc_rs::rsa::KeyPair::generate(aws_lc_rs::rsa::KeySize::Rsa2048).expect("an RSA key");
    AsDer::<aws_lc_rs::encoding::Pkcs8V1Der>::as_der(&key)
        .expect("its PKCS#8 form")
        .as_ref()
        .to_vec()
}

/// The same measurements for a provider whose API is ring's (aws-lc-rs keeps it).
/// `$agree` and `$ecdsa` take the two places where aws-lc-rs's signatures differ: its key
/// agreement names the error value, its ECDSA key loading takes no random source.
macro_rules! primitives {
    ($c:expr, $name:literal, $p:ident, $rsa:expr, $agree:expr, $ecdsa:expr) => {{
        use $p::{aead, agreement, rand, signature};
        let c: &mut Criterion = $c;
        let rng = rand::SystemRandom::new();
        c.bench_function(
            format!("{}/{}", "x25519 exchange (2 keys, 1 agreement)", $name).as_str(),
            |b| {
                b.iter(|| {
                    let ours = agreement::EphemeralPrivateKey::generate(&agreement::X25519, &rng)
                        .expect("a key");
                    let theirs = agreement::EphemeralPrivateKey::generate(&agreement::X25519, &rng)
                        .expect("a key");
                    let public = theirs.compute_public_key().expect("a public key");
                    let peer =
                        agreement::UnparsedPublicKey::new(&agreement::X25519, public.as_ref());
                    $agree(ours, &peer)
                })
            },
        );
        let pkcs8 = signature::EcdsaKeyPair::generate_pkcs8(
            &signature::ECDSA_P256_SHA256_ASN1_SIGNING,
            &rng,
        )
        .expect("a P-256 key");
        let ecdsa: signature::EcdsaKeyPair = $ecdsa(pkcs8.as_ref(), &rng);
        let transcript = [0x5A_u8; 130];
        c.bench_function(format!("{}/{}", "ECDSA P-256 sign", $name).as_str(), |b| {
            b.iter(|| ecdsa.sign(&rng, &transcript).expect("signed"))
        });
        let sig = ecdsa.sign(&rng, &transcript).expect("signed");
        let public = signature::UnparsedPublicKey::new(
            &signature::ECDSA_P256_SHA256_ASN1,
            signature::KeyPair::public_key(&ecdsa).as_ref().to_vec(),
        );
        c.bench_function(
            format!("{}/{}", "ECDSA P-256 verify", $name).as_str(),
            |b| b.iter(|| public.verify(&transcript, sig.as_ref()).expect("valid")),
        );
        let rsa = signature::RsaKeyPair::from_pkcs8($rsa).expect("the RSA key");
        let mut rsa_sig = vec![0; 256];
        c.bench_function(format!("{}/{}", "RSA-2048 PSS sign", $name).as_str(), |b| {
            b.iter(|| {
                rsa.sign(&signature::RSA_PSS_SHA256, &rng, &transcript, &mut rsa_sig)
                    .expect("signed")
            })
        });
        for (algorithm, label) in [
            (&aead::AES_128_GCM, "seal 200 B AES-128-GCM"),
            (&aead::CHACHA20_POLY1305, "seal 200 B ChaCha20-Poly1305"),
            (&aead::AES_256_GCM, "seal session ticket 120 B AES-256-GCM"),
        ] {
            let key = aead::LessSafeKey::new(
                aead::UnboundKey::new(algorithm, &vec![7; algorithm.key_len()]).expect("a key"),
            );
            let len = if label.contains("ticket") { 120 } else { 200 };
            let mut record = vec![0x42_u8; len];
            c.bench_function(format!("{}/{}", label, $name).as_str(), |b| {
                b.iter(|| {
                    record.truncate(len);
                    let nonce = aead::Nonce::assume_unique_for_key([1; 12]);
                    key.seal_in_place_append_tag(nonce, aead::Aad::from([23, 3, 3]), &mut record)
                        .expect("sealed")
                })
            });
        }
    }};
}

fn providers(c: &mut Criterion) {
    let rsa = rsa_key();
    primitives!(
        c,
        "ring",
        ring,
        &rsa,
        |ours, peer| ring::agreement::agree_ephemeral(ours, peer, |secret| secret[0])
            .expect("agreed"),
        |pkcs8, rng| {
            ring::signature::EcdsaKeyPair::from_pkcs8(
                &ring::signature::ECDSA_P256_SHA256_ASN1_SIGNING,
                pkcs8,
                rng,
            )
            .expect("loaded")
        }
    );
    primitives!(
        c,
        "aws-lc-rs",
        aws_lc_rs,
        &rsa,
        |ours, peer| {
            aws_lc_rs::agreement::agree_ephemeral(ours, peer, (), |secret| Ok(secret[0]))
                .expect("agreed")
        },
        |pkcs8, _| {
            aws_lc_rs::signature::EcdsaKeyPair::from_pkcs8(
                &aws_lc_rs::signature::ECDSA_P256_SHA256_ASN1_SIGNING,
                pkcs8,
            )
            .expect("loaded")
        }
    );
}

criterion_group!(benches, providers);
criterion_main!(benches);
