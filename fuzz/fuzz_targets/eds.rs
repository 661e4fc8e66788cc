//! EDS and DCF import (CiA 306): no panic; an imported file exports to one that imports to
//! the same objects.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let Ok(description) = canopen::eds::import("fuzz.eds", &text, None) else {
        return;
    };
    for dcf in [false, true] {
        let exported = canopen::eds::export(&description, dcf);
        let again = canopen::eds::import("again.eds", &exported, None)
            .unwrap_or_else(|e| panic!("the export does not import: {e}\n{exported}"));
        let indices = |d: &canopen::eds::DeviceDescription| {
            d.od.objects()
                .map(|o| (o.index, o.subs.len()))
                .collect::<Vec<_>>()
        };
        assert_eq!(indices(&again), indices(&description));
    }
});
