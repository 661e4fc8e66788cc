//! Value text (NXg values, CiA 309 ASCII) and the CiA 301 encoding of every data type: no
//! panic; text → value → text → value is stable, and value → bytes → value is the identity.
#![no_main]

use canopen::types::{self, ALL_TYPES};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    let ty = ALL_TYPES[usize::from(which) % ALL_TYPES.len()];
    // As bytes off the bus.
    if let Ok(value) = types::decode(ty, rest) {
        let text = types::to_text(ty, &value);
        if let Ok(bytes) = types::encode(ty, &value) {
            let again = types::decode(ty, &bytes).expect("encoded bytes decode");
            assert_eq!(types::to_text(ty, &again), text, "{ty:?}");
        }
    }
    // As text from the portal or an operator.
    let Ok(text) = std::str::from_utf8(rest) else {
        return;
    };
    let _ = types::parse_integer(text);
    let _ = types::parse_text_integer(text);
    if let Ok(value) = types::from_text(ty, text) {
        let shown = types::to_text(ty, &value);
        let reread = types::from_text(ty, &shown)
            .unwrap_or_else(|e| panic!("{ty:?}: {text:?} → {shown:?} does not parse: {e}"));
        assert_eq!(types::to_text(ty, &reread), shown, "{ty:?}: {text:?}");
        if let Ok(bytes) = types::encode(ty, &value) {
            let decoded = types::decode(ty, &bytes).expect("encoded bytes decode");
            assert_eq!(types::to_text(ty, &decoded), shown, "{ty:?}");
        }
    }
});
