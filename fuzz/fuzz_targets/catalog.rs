//! The catalog TOML (the built-in CiA 417 catalog's format, also the vendor metadata file of a
//! gateway): no panic in parsing, validating, describing and naming.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lift417::catalog::Catalog;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(catalog) = Catalog::from_toml(text) else {
        return;
    };
    let _ = catalog.validate();
    let _ = catalog.names();
    let indices: Vec<u16> = catalog.objects().map(|o| o.index()).collect();
    for index in indices.into_iter().take(64) {
        for sub in [0, 1, 2, 255] {
            let _ = catalog.describe(None, index, sub);
        }
        let _ = catalog.object_texts(None, index);
    }
});
