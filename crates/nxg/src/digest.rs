//! Comparing secrets' digests without leaking where they differ: the SHA-1 password hashes of
//! `elevate_privilege` (NXg SW003 §6.4), the SHA-256 digests of cloud tokens and API keys, and
//! CSRF tokens on the portal.

/// Whether two hex digests are equal, case-insensitively and in time independent of where they
/// differ (surrounding white space ignored).
pub fn matches(expected: &str, given: &str) -> bool {
    let (a, b) = (expected.trim().as_bytes(), given.trim().as_bytes());
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| {
        acc | (x.to_ascii_lowercase() ^ y.to_ascii_lowercase())
    }) == 0
}

#[cfg(test)]
mod tests {
    #[test]
    fn compares_case_insensitively() {
        assert!(super::matches("4cf5bc59", "4CF5BC59"));
        assert!(super::matches(" ab ", "AB"));
        assert!(!super::matches("4cf5bc59", "4cf5bc5a"));
        assert!(!super::matches("4cf5bc59", "4cf5bc5"));
        assert!(!super::matches("", "a"));
    }
}
