use super::*;
use serde_json::{json, Value};

const CONNECT: &str = r#"{"jsonrpc":"2.0","method":"CONNECT","id":"c1","params":{"identity":{
  "sernum":"180917010200000102","vendorid":1050,"productcode":4096,"liftnum":"40/7289/20399-126",
  "hardware":"Thor @ NX-T2","software":"01.23.10","api":3,"boardhash":"2354A6"},"domaintoken":"MAS"}}"#;

fn settings() -> Settings {
    Settings {
        api: 2,
        connect_timeout: Duration::from_secs(10),
        heartbeat: Duration::from_secs(300),
        request_timeout: Duration::from_secs(10),
        max_in_flight: 2,
        max_queued: 1,
    }
}

fn sent(out: &[Output]) -> Vec<Value> {
    out.iter()
        .filter_map(|o| match o {
            Output::Send(t) => Some(serde_json::from_str(t).unwrap()),
            _ => None,
        })
        .collect()
}

/// A session that has accepted the sample gateway (without issuing a token).
fn serving(now: Instant) -> Session {
    let mut s = Session::new(settings(), now);
    let out = s.handle_text(CONNECT, now);
    let [Output::Identify(hello)] = &out[..] else {
        panic!("{out:?}")
    };
    s.accept(&hello.clone(), None, now);
    s
}

#[test]
fn connect_identify_connack_and_token() {
    let now = Instant::now();
    let mut s = Session::new(settings(), now);
    let out = s.handle_text(CONNECT, now);
    let [Output::Identify(hello)] = &out[..] else {
        panic!("{out:?}")
    };
    assert_eq!(hello.identity.sernum, "180917010200000102");
    assert_eq!(
        (hello.identity.vendorid, hello.identity.productcode),
        (1050, 4096)
    );
    assert_eq!(hello.domaintoken, "MAS");
    assert_eq!(hello.identity.api, 3);
    assert_eq!(hello.identity.cloudtoken, None);
    let out = s.accept(&hello.clone(), Some("T0K3N".into()), now);
    let messages = sent(&out);
    // CONNACK as docs/PROTOCOL.md reads the sample, with the lower of both APIs.
    assert_eq!(
        messages[0],
        json!({"jsonrpc":"2.0","id":"c1","result":"CONNACK","api":2})
    );
    assert_eq!(messages[1]["method"], "update_unique_token");
    assert_eq!(
        messages[1]["params"],
        json!({"sernum":"180917010200000102","token":"T0K3N"})
    );
    assert_eq!(s.api(), 2);
    let answer = format!(
        r#"{{"jsonrpc":"2.0","id":{},"result":{{"done":0}}}}"#,
        messages[1]["id"]
    );
    assert_eq!(
        s.handle_text(&answer, now),
        [Output::TokenConfirmed("T0K3N".into())]
    );
}

#[test]
fn refusals_close_without_an_answer() {
    let now = Instant::now();
    let mut s = Session::new(settings(), now);
    let out = s.handle_text(CONNECT, now);
    assert!(matches!(out[0], Output::Identify(_)));
    assert!(
        matches!(&s.refuse("wrong token".into())[..], [Output::Close(CloseReason::Refused(c))] if c == "wrong token")
    );
    // Anything but CONNECT first.
    let mut s = Session::new(settings(), now);
    let out = s.handle_text(r#"{"jsonrpc":"2.0","id":1,"method":"get_heartbeat"}"#, now);
    assert!(matches!(&out[..], [Output::Close(_)]));
    // Garbage first.
    let mut s = Session::new(settings(), now);
    assert!(matches!(
        &s.handle_text("GET / HTTP/1.1", now)[..],
        [Output::Close(_)]
    ));
    // Malformed identity.
    let mut s = Session::new(settings(), now);
    let bad = CONNECT.replace(r#""vendorid":1050"#, r#""vendorid":"1050""#);
    assert!(
        matches!(&s.handle_text(&bad, now)[..], [Output::Close(CloseReason::InvalidConnect(c))] if c.contains("vendorid"))
    );
    let mut s = Session::new(settings(), now);
    let long = CONNECT.replace(
        r#""boardhash":"2354A6""#,
        &format!(r#""cloudtoken":"{}""#, "x".repeat(129)),
    );
    assert!(
        matches!(&s.handle_text(&long, now)[..], [Output::Close(CloseReason::InvalidConnect(c))] if c.contains("cloudtoken"))
    );
    // No CONNECT in time.
    let mut s = Session::new(settings(), now);
    assert_eq!(s.poll_timeout(), Some(now + Duration::from_secs(10)));
    assert!(s.handle_timeout(now + Duration::from_secs(9)).is_empty());
    assert!(matches!(
        &s.handle_timeout(now + Duration::from_secs(10))[..],
        [Output::Close(CloseReason::NoConnect)]
    ));
}

#[test]
fn requests_are_correlated_bounded_and_time_out() {
    let now = Instant::now();
    let mut s = serving(now);
    let params = serde_json::value::to_raw_value(&json!({"object":{"mplex":"0x652001"}})).unwrap();
    let (a, out) = s.request(Method::GetCanopenObject, Some(params), now);
    let first = &sent(&out)[0];
    assert_eq!(first["method"], "get_canopen_object");
    let (b, out) = s.request(Method::GetHeartbeat, None, now);
    let second = &sent(&out)[0];
    assert!(second.get("params").is_none());
    // Two in flight: the third waits, the fourth is refused.
    let (c, out) = s.request(Method::GetHeartbeat, None, now);
    assert!(out.is_empty());
    let (d, out) = s.request(Method::GetHeartbeat, None, now);
    assert_eq!(out, [Output::Answer(d, Err(Failure::Busy))]);
    // Answers in any order; the queued one goes out as soon as a slot frees.
    let answer = format!(
        r#"{{"jsonrpc":"2.0","id":{},"error":{{"code":1,"message":"m"}}}}"#,
        second["id"]
    );
    let out = s.handle_text(&answer, now);
    assert_eq!(
        out[0],
        Output::Answer(b, Err(Failure::Error(ErrorObject::rpc(1, "m"))))
    );
    assert_eq!(sent(&out[1..])[0]["method"], "get_heartbeat");
    let answer = format!(
        r#"{{"jsonrpc":"2.0","id":{},"result":{{"object":{{}}}}}}"#,
        first["id"]
    );
    assert_eq!(
        s.handle_text(&answer, now),
        [Output::Answer(a, Ok(r#"{"object":{}}"#.to_owned()))]
    );
    // The queued one times out.
    let later = now + Duration::from_secs(10);
    assert_eq!(s.poll_timeout(), Some(later));
    assert_eq!(
        s.handle_timeout(later),
        [Output::Answer(c, Err(Failure::Timeout))]
    );
    // Unknown ids and notifications.
    assert!(s
        .handle_text(r#"{"jsonrpc":"2.0","id":999,"result":{}}"#, later)
        .is_empty());
    let note = r#"{"jsonrpc":"2.0","method":"canopen_object","result":{"mplex":"0x652001","value":"2511"}}"#;
    assert_eq!(
        s.handle_text(note, later),
        [Output::Notification(Notification {
            mplex: "0x652001".into(),
            value: "2511".into(),
            node: None
        })]
    );
}

#[test]
fn heartbeats_and_silence() {
    let now = Instant::now();
    let mut s = serving(now);
    assert_eq!(s.poll_timeout(), Some(now + Duration::from_secs(300)));
    let out = s.handle_timeout(now + Duration::from_secs(300));
    assert_eq!(sent(&out)[0]["method"], "get_heartbeat");
    // No frame at all for 630 s: closed, and open requests fail.
    let (r, _) = s.request(Method::GetHeartbeat, None, now + Duration::from_secs(300));
    let out = s.handle_timeout(now + Duration::from_secs(630));
    assert!(matches!(out[0], Output::Close(_)));
    assert!(out.contains(&Output::Answer(r, Err(Failure::Gone))));
    assert_eq!(s.poll_timeout(), None);
}

#[test]
fn string_ids_go_out_and_answers_match_them_by_value() {
    let now = Instant::now();
    let mut s = serving(now);
    let (a, out) = s.request(Method::GetHeartbeat, None, now);
    let id = sent(&out)[0]["id"].clone();
    assert!(id.is_string(), "{id}");
    // A gateway that echoes the id as a number is still understood.
    let number: u64 = id.as_str().unwrap().parse().unwrap();
    let answer = format!(r#"{{"jsonrpc":"2.0","id":{number},"result":{{"done":0}}}}"#);
    assert_eq!(
        s.handle_text(&answer, now),
        [Output::Answer(a, Ok(r#"{"done":0}"#.to_owned()))]
    );
    // Error codes as strings, as §6.3.3 shows them.
    let (b, out) = s.request(Method::GetHeartbeat, None, now);
    let id = &sent(&out)[0]["id"];
    let answer = format!(
        r#"{{"jsonrpc":"2.0","id":{id},"error":{{"code":"0x08000021","message":"m","data":"0x502200"}}}}"#
    );
    let out = s.handle_text(&answer, now);
    let [Output::Answer(r, Err(Failure::Error(e)))] = &out[..] else {
        panic!("{out:?}")
    };
    assert_eq!((*r, e.code), (b, 0x0800_0021));
}
