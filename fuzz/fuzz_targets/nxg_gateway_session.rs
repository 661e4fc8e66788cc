//! The gateway's session fed arbitrary messages after its CONNACK (jobs answered at once): no
//! panic, and as long as the connection stays open, a valid request is still answered.
#![no_main]

use std::time::{Duration, Instant};

use canlift_fuzz::{gateway_context, gateway_settings, messages};
use libfuzzer_sys::fuzz_target;
use nxg::gateway::{Job, JobResult, Output, Phase, Session};

/// Run the outputs' jobs to completion; the texts sent.
fn settle(session: &mut Session, mut out: Vec<Output>, now: Instant) -> Vec<String> {
    let mut sent = Vec::new();
    for _ in 0..1000 {
        let mut jobs = Vec::new();
        for o in out {
            match o {
                Output::Send(text) => sent.push(text),
                Output::Start(id, job) => jobs.push((id, job)),
                _ => {}
            }
        }
        if jobs.is_empty() {
            return sent;
        }
        out = Vec::new();
        for (id, job) in jobs {
            let result = match job {
                Job::Read { .. } => JobResult::Read(vec![vec![1, 0, 0, 0]]),
                Job::ReadArray { .. } => JobResult::Read(vec![vec![2], vec![3]]),
                Job::Write { .. } | Job::StoreToken(_) => JobResult::Done,
            };
            out.extend(session.handle_job(id, result, now));
        }
    }
    panic!("jobs never end");
}

fuzz_target!(|data: &[u8]| {
    let mut now = Instant::now();
    let mut session = Session::new(gateway_settings(), gateway_context(), None, now);
    let connack = r#"{"jsonrpc":"2.0","id":"1","result":"CONNACK","api":2}"#;
    assert!(session.handle_text(connack, now).is_empty());
    for text in messages(data) {
        let out = session.handle_text(&text, now);
        settle(&mut session, out, now);
        let events = session.deliver_events();
        settle(&mut session, events, now);
        now += Duration::from_millis(7);
        let out = session.handle_timeout(now);
        settle(&mut session, out, now);
    }
    if session.phase() == Phase::Closed {
        return;
    }
    let get = r#"{"jsonrpc":"2.0","id":"fuzz-final","method":"get_canopen_object","params":{"object":{"mplex":"0x652001","naked":true}}}"#;
    let out = session.handle_text(get, now);
    let sent = settle(&mut session, out, now);
    assert!(
        sent.iter().any(|t| t.contains("\"fuzz-final\"")),
        "a valid request after the fuzz input got no answer: {sent:?}"
    );
});
