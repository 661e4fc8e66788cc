//! Object addresses as the REST API's path and `?name=`, the web forms and the tools take
//! them: the mplex, the address forms, and names from the CiA 417 catalog. No panic; a parsed
//! mplex prints and parses back to itself.
#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use nxg::mplex::Mplex;
use nxg::names::ObjectNames;

fuzz_target!(|data: &[u8]| {
    static NAMES: OnceLock<ObjectNames> = OnceLock::new();
    let names = NAMES.get_or_init(|| lift417::catalog::Catalog::builtin().names());
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(m) = Mplex::parse(text) {
        assert_eq!(Mplex::parse(&m.to_string()), Ok(m));
        assert_eq!(
            Mplex::parse_address(text),
            Ok(m),
            "the strict form is an address too"
        );
    }
    if let Ok(m) = Mplex::parse_address(text) {
        assert_eq!(Mplex::parse_address(&m.to_string()), Ok(m));
    }
    if let Ok(m) = names.resolve(text) {
        assert_eq!(names.resolve(&m.to_string()), Ok(m));
    }
    let _ = nxg::mplex::normalized(text);
});
