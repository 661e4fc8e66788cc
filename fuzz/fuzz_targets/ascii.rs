//! The CiA 309-3 ASCII gateway's command language, line by line: no panic, every line is
//! answered or becomes a job, and the session still answers `help` afterwards.
#![no_main]

use std::time::Duration;

use canlift_fuzz::messages;
use canopen::ascii::{Session, Step};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut session = Session::new(1, Duration::from_millis(500), "fuzz");
    for text in messages(data) {
        for line in text.lines() {
            if let Step::Reply(reply) = session.handle(line) {
                let _ = reply.to_string();
            }
        }
    }
    assert!(matches!(session.handle("help"), Step::Reply(_)));
});
