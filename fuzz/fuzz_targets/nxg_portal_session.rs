//! The portal's session fed arbitrary messages, before and after it accepted the gateway: no
//! panic, and while it serves, an operator request still goes out and its answer comes back.
#![no_main]

use std::time::{Duration, Instant};

use canlift_fuzz::messages;
use libfuzzer_sys::fuzz_target;
use nxg::msg::Method;
use nxg::portal::{Output, Session, Settings};

const CONNECT: &str = r#"{"jsonrpc":"2.0","id":"1","method":"CONNECT","params":{"identity":{"sernum":"180917010200000102","vendorid":1050,"productcode":4096,"liftnum":"1","hardware":"h","software":"s","boardhash":"00","api":2},"domaintoken":"MAS"}}"#;

fuzz_target!(|data: &[u8]| {
    let settings = Settings {
        api: 2,
        connect_timeout: Duration::from_secs(10),
        heartbeat: Duration::from_secs(60),
        request_timeout: Duration::from_secs(5),
        max_in_flight: 4,
        max_queued: 4,
    };
    let mut now = Instant::now();
    let mut session = Session::new(settings, now);
    // The first byte says whether the gateway identifies itself before the input.
    let identify_first = data.first().is_some_and(|b| b & 1 == 1);
    let accept = |session: &mut Session, out: Vec<Output>, now| {
        for o in out {
            if let Output::Identify(connect) = o {
                session.accept(&connect, Some("0123456789ABCDEF".into()), now);
            }
        }
    };
    if identify_first {
        let out = session.handle_text(CONNECT, now);
        accept(&mut session, out, now);
    }
    for text in messages(data.get(1..).unwrap_or_default()) {
        let out = session.handle_text(&text, now);
        accept(&mut session, out, now);
        now += Duration::from_millis(7);
        let _ = session.handle_timeout(now);
    }
    if !session.serving() {
        return;
    }
    let params = serde_json::value::RawValue::from_string(
        r#"{"object":{"mplex":"0x652001","naked":true}}"#.into(),
    )
    .ok();
    let (request, out) = session.request(Method::GetCanopenObject, params, now);
    // The request is sent at once, or queued behind requests the input left open; answer
    // whatever was sent (ids are the portal's counters) and look for this request's answer.
    let mut answered = false;
    let mut to_answer: Vec<String> = Vec::new();
    for o in out {
        match o {
            Output::Send(t) => to_answer.push(t),
            Output::Answer(id, _) if id == request => answered = true,
            _ => {}
        }
    }
    for _ in 0..16 {
        let Some(sent) = to_answer.pop() else { break };
        let Ok(v) = serde_json::from_str::<serde_json::Value>(&sent) else {
            continue;
        };
        let Some(id) = v.get("id") else { continue };
        let reply = format!(
            r#"{{"jsonrpc":"2.0","id":{id},"result":{{"object":{{"mplex":"0x652001","value":["1"]}}}}}}"#
        );
        for o in session.handle_text(&reply, now) {
            match o {
                Output::Send(t) => to_answer.push(t),
                Output::Answer(id, _) if id == request => answered = true,
                _ => {}
            }
        }
    }
    if session.serving() {
        assert!(
            answered,
            "an operator request after the fuzz input was never answered"
        );
    }
});
