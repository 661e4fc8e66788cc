//! The gateway's `[policy]` (TOML): no panic; what parses serializes and parses back the same,
//! and its decisions are total.
#![no_main]

use libfuzzer_sys::fuzz_target;
use nxg::gateway::{Policy, Target};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(policy) = toml::from_str::<Policy>(text) else {
        return;
    };
    let written = toml::to_string(&policy).expect("a policy serializes");
    let again: Policy =
        toml::from_str(&written).unwrap_or_else(|e| panic!("{written:?} does not parse back: {e}"));
    assert_eq!(again, policy);
    let controller = Target { net: 1, node: 1 };
    for (node, index) in [(1, 0x1017), (5, 0x1017), (1, 0x6520), (127, 0xFFFF)] {
        let target = Target { net: 1, node };
        let _ = policy.hidden(target, index);
        let _ = policy.check_write(target, controller, index, true);
    }
    let _ = policy.default_privilege();
    let _ = policy.summary();
});
