//! An LSS slave (CiA 305) fed arbitrary master frames: no panic, at most one answer per
//! frame, and a global switch back to waiting always works.
#![no_main]

use canbus::Frame;
use canopen::lss::{self, cs, LssSlave, LssState};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut slave = LssSlave::new([0x41A, 0x1000, 0x10002, 0x1234_5678], lss::UNCONFIGURED);
    let mut out: Vec<Frame> = Vec::new();
    for chunk in data.chunks_exact(8) {
        let payload: [u8; 7] = chunk[1..].try_into().expect("7 bytes");
        let _ = slave.handle(&lss::request(chunk[0], payload), &mut out);
        assert!(out.len() <= 1, "{} answers to one frame", out.len());
        out.clear();
    }
    let _ = slave.handle(&lss::request(cs::SWITCH_GLOBAL, [0; 7]), &mut out);
    assert_eq!(slave.state(), LssState::Waiting);
});
