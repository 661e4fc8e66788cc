//! The store's digests and secrets: SHA-256 digests of what is kept (API keys, cloud tokens,
//! session cookies), the NXg password hash sent to gateways, and random secrets.

use rand::RngCore;

/// SHA-256 hex of `secret`.
pub fn digest(secret: &str) -> String {
    hex::encode(ring::digest::digest(
        &ring::digest::SHA256,
        secret.as_bytes(),
    ))
}

/// The NXg password hash (NXg §6.4): the unsalted SHA-1 of `password` as upper-case hex, as
/// `elevate_privilege` carries it and the gateway's `[privileges]` keeps it. Only ever sent to
/// the gateway, never stored by the portal.
pub fn passhash(password: &str) -> String {
    let sha1 = ring::digest::digest(&ring::digest::SHA1_FOR_LEGACY_USE_ONLY, password.as_bytes());
    hex::encode_upper(sha1)
}

/// A random secret of 128 bits as 32 hex digits, with a prefix.
pub fn secret(prefix: &str) -> String {
    let mut bytes = [0u8; 16];
    rand::rng().fill_bytes(&mut bytes);
    format!("{prefix}{}", hex::encode(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digests_are_hex_of_the_hash() {
        // FIPS 180-2's SHA-256 example; the SHA-1 of "password" in upper case, as NXg §6.4 carries it.
        assert_eq!(
            digest("abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(
            passhash("password"),
            "5BAA61E4C9B93F3F0682250B6CF8331B7EE68FD8"
        );
        let s = secret("clk_");
        assert!(
            s.len() == 36 && s[4..].bytes().all(|b| b.is_ascii_hexdigit()),
            "{s}"
        );
    }
}
