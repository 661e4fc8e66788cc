//! The SDO server fed arbitrary request frames and time steps (every transfer type and every
//! abort path): no panic, and after the transfer timeout a fresh upload is answered.
#![no_main]

use std::time::{Duration, Instant};

use canlift_fuzz::sample_dictionary;
use canopen::sdo::server::{SdoServer, ServerConfig};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let config = ServerConfig::default();
    let timeout = config.timeout;
    let mut od = sample_dictionary();
    let mut server = SdoServer::new(config);
    let mut now = Instant::now();
    let mut out = Vec::new();
    for step in data.chunks_exact(9) {
        let (control, payload) = step.split_at(1);
        let payload: [u8; 8] = payload.try_into().expect("8 bytes");
        now += Duration::from_millis(u64::from(control[0]) * 16);
        server.handle_timeout(now, &mut out);
        server.handle(&mut od, &payload, now, &mut out);
        assert!(out.len() <= 128, "{} responses queued", out.len());
        out.clear();
    }
    now += timeout + Duration::from_secs(1);
    server.handle_timeout(now, &mut out);
    out.clear();
    // Initiate upload of 1000h sub 0 (CiA 301 §7.2.4.3.3).
    server.handle(&mut od, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0], now, &mut out);
    let response = out.last().expect("the server answers a fresh upload");
    assert_eq!(
        response[0] & 0xE0,
        0x40,
        "an upload response, not {response:02X?}"
    );
});
