//! The SDO client fed arbitrary response frames during an upload or a download (normal,
//! segmented or block): no panic, what an upload returns is bounded by the bytes that came,
//! and after a transfer ends the next one starts.
#![no_main]

use std::time::{Duration, Instant};

use canopen::sdo::client::{ClientConfig, SdoClient, Transfer};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&mode, frames)) = data.split_first() else {
        return;
    };
    let how = match mode % 3 {
        0 => Transfer::Normal,
        1 => Transfer::Segmented,
        _ => Transfer::Block,
    };
    let mut client = SdoClient::new(ClientConfig::default());
    let mut now = Instant::now();
    let mut out = Vec::new();
    let upload = mode & 0x80 == 0;
    let started = if upload {
        client.start_upload(0x1008, 0, how, now, &mut out)
    } else {
        let data = vec![0x5A; usize::from(mode & 0x3F) * 11];
        client.start_download(0x1008, 0, data, how, now, &mut out)
    };
    started.expect("an idle client starts");
    let mut fed = 0usize;
    for response in frames.chunks_exact(8) {
        let response: [u8; 8] = response.try_into().expect("8 bytes");
        fed += 1;
        now += Duration::from_millis(3);
        out.clear();
        if let Some(outcome) = client.handle(&response, now, &mut out) {
            if let (true, Ok(bytes)) = (upload, &outcome) {
                assert!(
                    bytes.len() <= 7 * fed,
                    "{} bytes from {fed} frames",
                    bytes.len()
                );
            }
            break;
        }
    }
    if client.is_busy() {
        now += Duration::from_secs(60);
        out.clear();
        assert!(
            client.handle_timeout(now, &mut out).is_some(),
            "a silent server times out"
        );
    }
    assert!(!client.is_busy());
    out.clear();
    client
        .start_upload(0x1000, 0, Transfer::Normal, now, &mut out)
        .expect("the next transfer starts");
});
