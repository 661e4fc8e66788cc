//! EDS and DCF import (CiA 306): no panic on any bytes (UTF-8 or not); what an import kept
//! exports to a file that imports to the same objects without a part left out.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(imported) = canopen::eds::import_bytes("fuzz.eds", data, None) else {
        return;
    };
    let description = imported.description;
    for dcf in [false, true] {
        let exported = canopen::eds::export(&description, dcf);
        let again = canopen::eds::import("again.eds", &exported, None)
            .unwrap_or_else(|e| panic!("the export does not import: {e}\n{exported}"));
        let left_out: Vec<_> = again
            .findings
            .iter()
            .filter(|f| f.severity == canopen::eds::Severity::Error)
            .collect();
        assert!(left_out.is_empty(), "the export loses parts: {left_out:?}\n{exported}");
        let again = again.description;
        let indices = |d: &canopen::eds::DeviceDescription| {
            d.od.objects()
                .map(|o| (o.index, o.subs.len()))
                .collect::<Vec<_>>()
        };
        assert_eq!(indices(&again), indices(&description));
    }
});
