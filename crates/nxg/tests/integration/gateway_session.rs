//! The gateway session against the specification's samples, with the CiA 417 catalog as the
//! lift controller's metadata (an integration test: the catalog crate depends on this one).

use std::sync::Arc;
use std::time::{Duration, Instant};

use canopen::sdo::abort::AbortCode;
use lift417::catalog::Catalog;
use nxg::codes::rpc_codes;
use nxg::gateway::{
    BusEvent, CloseReason, Context, Happening, Identity, Job, JobResult, LevelState, Lookup,
    Metadata, Output, Phase, Policy, Session, Settings, Target,
};
use nxg::meta::Texts;
use nxg::msg::{BusState, NodeId, NodeRef, NodeState};
use serde_json::{json, Value};

const SERNUM: &str = "180917010200000102";
/// SHA-1 of "service" and "setup".
const SERVICE_SHA1: &str = "4cf5bc59bee9e1c44c6254b5f84e7f066bd8e5fe";
const SETUP_SHA1: &str = "80437a44a661d141174209119d54125a59a64b2a";

fn settings() -> Settings {
    Settings {
        identity: Identity {
            sernum: SERNUM.into(),
            vendorid: 1050,
            productcode: 4096,
            liftnum: "40/7289/20399-126".into(),
            hardware: "Thor @ NX-T2".into(),
            software: "01.23.10".into(),
            boardhash: "2354A687AF6DC79B203E754E8E426A87FE188A62983B7AC48F9D5E195B728112".into(),
            domaintoken: "MAS".into(),
            api: 1,
        },
        service_sha1: Some(SERVICE_SHA1.into()),
        setup_sha1: Some(SETUP_SHA1.to_uppercase()),
        privilege_duration: Duration::from_secs(300),
        max_in_flight: 2,
        max_queued: 2,
        max_subscriptions: 4,
        heartbeat: Duration::from_secs(300),
        connack_timeout: Duration::from_secs(30),
        lift_controller: 1,
        nets: vec![1],
        policy: Policy::default(),
    }
}

/// The catalog for the lift controller (node 1) and for node 13 (as if its EDS had been merged
/// with the catalog), nothing for other nodes.
struct ControllerCatalog;

impl Metadata for ControllerCatalog {
    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup {
        if target.net == 1 && matches!(target.node, 1 | 13) {
            Catalog::builtin().describe(None, index, sub)
        } else {
            Lookup::Unknown
        }
    }

    fn object_texts(&self, _: Target, index: u16) -> Option<(Texts, Texts)> {
        Catalog::builtin().object_texts(None, index)
    }

    fn text<'a>(&'a self, texts: &'a Texts, p: &str, a: &str) -> Option<(&'a str, &'a str)> {
        Catalog::builtin().text(texts, p, a)
    }
}

fn metadata() -> Context {
    Context::new(Arc::new(ControllerCatalog))
}

struct Portal {
    session: Session,
    now: Instant,
}

impl Portal {
    fn connected() -> Portal {
        Portal::connected_with(settings(), metadata())
    }

    /// A session in service with `settings`, sharing `context` (a reconnection shares it).
    fn connected_with(settings: Settings, context: Context) -> Portal {
        Portal::connected_at(settings, context, 1)
    }

    /// The same, with the portal's CONNACK offering `api`.
    fn connected_at(settings: Settings, context: Context, api: u32) -> Portal {
        let now = Instant::now();
        let agreed = api.min(settings.identity.api);
        let mut session = Session::new(settings, context, None, now);
        let connack = format!(r#"{{"jsonrpc":"2.0","id":1,"result":"CONNACK","api":{api}}}"#);
        assert!(session.handle_text(&connack, now).is_empty());
        assert_eq!(session.phase(), Phase::Connected(agreed));
        Portal { session, now }
    }

    fn send(&mut self, text: &str) -> Vec<Output> {
        self.session.handle_text(text, self.now)
    }

    /// Send a request and answer its jobs from `values` (bytes per job) or with `done`.
    fn ask(&mut self, text: &str, values: &[&[u8]]) -> Value {
        let mut out = self.send(text);
        let mut values = values.iter();
        loop {
            let job = out.iter().find_map(|o| match o {
                Output::Start(id, job) => Some((*id, job.clone())),
                _ => None,
            });
            if let Some(text) = out.iter().find_map(|o| match o {
                Output::Send(t) => Some(t.clone()),
                _ => None,
            }) {
                return serde_json::from_str(&text).unwrap();
            }
            let (id, job) = job.expect("an answer or a job");
            let result = match job {
                Job::Read { .. } => JobResult::Read(vec![values.next().unwrap().to_vec()]),
                Job::ReadArray { .. } => {
                    JobResult::Read(values.by_ref().map(|v| v.to_vec()).collect())
                }
                Job::Write { .. } | Job::StoreToken(_) => JobResult::Done,
            };
            out = self.session.handle_job(id, result, self.now);
        }
    }

    fn later(&mut self, d: Duration) -> Vec<Output> {
        self.now += d;
        self.session.handle_timeout(self.now)
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

#[test]
fn connect_carries_the_identity_and_the_token_only_when_stored() {
    let now = Instant::now();
    let Output::Send(text) = Session::new(settings(), metadata(), None, now).connect() else {
        panic!()
    };
    let v: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(v["method"], "CONNECT");
    assert_eq!(v["id"], "1", "a string id, as the samples");
    assert_eq!(v["params"]["domaintoken"], "MAS");
    let identity = &v["params"]["identity"];
    assert_eq!(identity["sernum"], SERNUM);
    assert_eq!(identity["vendorid"], 1050);
    assert_eq!(identity["productcode"], 4096);
    assert_eq!(identity["api"], 1);
    assert!(identity.get("cloudtoken").is_none());
    let Output::Send(text) =
        Session::new(settings(), metadata(), Some("2A98765DE230176C".into()), now).connect()
    else {
        panic!()
    };
    let v: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(v["params"]["identity"]["cloudtoken"], "2A98765DE230176C");
}

#[test]
fn connack_forms_and_api_negotiation() {
    let now = Instant::now();
    let mut s = settings();
    s.identity.api = 3;
    for (answer, api) in [
        (r#"{"jsonrpc":"2.0","id":1,"result":"CONNACK","api":2}"#, 2),
        (
            r#"{"jsonrpc":"2.0","id":1,"result":{"connack":true,"api":5}}"#,
            3,
        ),
        (r#"{"jsonrpc":"2.0","id":1,"result":"CONNACK"}"#, 1),
    ] {
        let mut session = Session::new(s.clone(), metadata(), None, now);
        session.handle_text(answer, now);
        assert_eq!(session.phase(), Phase::Connected(api), "{answer}");
    }
    let mut refused = Session::new(s.clone(), metadata(), None, now);
    let out = refused.handle_text(
        r#"{"jsonrpc":"2.0","id":1,"error":{"code":1,"message":"no"}}"#,
        now,
    );
    assert!(matches!(&out[..], [Output::Close(CloseReason::Refused(e))] if e.message == "no"));
    let mut silent = Session::new(s, metadata(), None, now);
    assert_eq!(silent.poll_timeout(), Some(now + Duration::from_secs(30)));
    assert!(silent
        .handle_timeout(now + Duration::from_secs(29))
        .is_empty());
    let out = silent.handle_timeout(now + Duration::from_secs(30));
    assert!(matches!(&out[..], [Output::Close(CloseReason::NoConnack)]));
}

#[test]
fn heartbeat_answers_at_once_even_when_the_bus_is_busy() {
    let mut p = Portal::connected();
    for i in 0..4 {
        p.send(&format!(
            r#"{{"jsonrpc":"2.0","id":{i},"method":"get_canopen_object","params":{{"object":{{"mplex":"0x652001"}}}}}}"#
        ));
    }
    let out = p.send(r#"{"jsonrpc":"2.0","id":"hb","method":"get_heartbeat"}"#);
    assert_eq!(
        sent(&out),
        [json!({"jsonrpc":"2.0","id":"hb","result":{"done":0}})]
    );
    // Two in flight, two queued: the fifth is refused as busy, not buffered without end.
    let out = p.send(r#"{"jsonrpc":"2.0","id":9,"method":"get_canopen_object","params":{"object":{"mplex":"0x652001"}}}"#);
    assert_eq!(sent(&out)[0]["error"]["code"], rpc_codes::BUSY);
}

const GET_TRIP: &str = r#"{
  "jsonrpc": "2.0", "id": "<ID>", "method": "get_canopen_object",
  "params": { "lang": { "preferred_language": "en", "alternate_language": "de" },
    "object": { "mplex": "0x652001", "compact": false, "stripped": false, "naked": false } } }"#;

#[test]
fn get_full_stripped_and_naked_match_the_samples() {
    let mut p = Portal::connected();
    let trips = 2510u32.to_le_bytes();
    let full = p.ask(GET_TRIP, &[&trips]);
    assert_eq!(
        full,
        json!({"jsonrpc":"2.0","id":"<ID>","result":{
            "lang":{"language":"en"},
            "object":{"mplex":"0x652001","objcode":8,"datatype":7,"formtype":10,"physunit":26,
                "access":"ro","privilege":0,"name":"Trip counter [trips]",
                "hint":"This object represents the internal trip counter of the lift controller.",
                "value":["2510"],"min":0,"max":4294967295u64,"zero":false,"list":[]},
            "hints":{"show_off_at_zero":false,"show_unlimited_at_max":false,"show_undefined_at_max":false}}})
    );
    let stripped = p.ask(
        &GET_TRIP.replace(r#""stripped": false"#, r#""stripped": true"#),
        &[&trips],
    );
    assert_eq!(
        stripped["result"],
        json!({"object":{"mplex":"0x652001","objcode":8,"datatype":7,"formtype":10,"physunit":26,
            "access":"ro","privilege":0,"value":["2510"],"min":0,"max":4294967295u64,"zero":false}})
    );
    let naked = p.ask(
        &GET_TRIP.replace(r#""naked": false"#, r#""naked": true"#),
        &[&trips],
    );
    assert_eq!(
        naked["result"],
        json!({"object":{"mplex":"0x652001","value":["2510"]}})
    );
    // German first: name and hint in German, the language says so.
    let de = p.ask(
        &GET_TRIP.replace(
            r#""preferred_language": "en""#,
            r#""preferred_language": "de""#,
        ),
        &[&trips],
    );
    assert_eq!(de["result"]["lang"]["language"], "de");
    assert_eq!(de["result"]["object"]["name"], "Fahrtenzähler [Fahrten]");
}

#[test]
fn list_and_compact_array_match_the_samples() {
    let mut p = Portal::connected();
    let list = p.ask(
        r#"{"jsonrpc":"2.0","id":"1234","method":"get_canopen_object","params":{"lang":{"preferred_language":"en","alternate_language":"de"},"object":{"mplex":"0x411200"}}}"#,
        &[&[0]],
    );
    let object = &list["result"]["object"];
    assert_eq!(
        (
            &object["objcode"],
            &object["datatype"],
            &object["formtype"],
            &object["access"],
            &object["privilege"]
        ),
        (&json!(7), &json!(5), &json!(15), &json!("rw"), &json!(1))
    );
    assert_eq!(object["name"], "Hall lantern options");
    assert_eq!(object["list"].as_array().unwrap().len(), 4);
    assert_eq!(object["list"][3], "off");
    assert_eq!((&object["min"], &object["max"]), (&json!(0), &json!(3)));
    let levels: Vec<Vec<u8>> = [1000i32, 4500, 8000, 11500, 15000, 18500, 22000, 25500]
        .iter()
        .map(|v| v.to_le_bytes().to_vec())
        .collect();
    let refs: Vec<&[u8]> = levels.iter().map(Vec::as_slice).collect();
    let compact = p.ask(
        r#"{"jsonrpc":"2.0","id":"<ID>","method":"get_canopen_object","params":{"lang":{"preferred_language":"en","alternate_language":"de"},"object":{"mplex":"0x401001","compact":true}}}"#,
        &refs,
    );
    let object = &compact["result"]["object"];
    assert_eq!(
        object["value"],
        json!(["1000", "4500", "8000", "11500", "15000", "18500", "22000", "25500"])
    );
    assert_eq!(
        (
            &object["objcode"],
            &object["datatype"],
            &object["formtype"],
            &object["physunit"],
            &object["privilege"]
        ),
        (&json!(8), &json!(4), &json!(26), &json!(15), &json!(1))
    );
    assert_eq!(object["name"], "Floor level positions");
    assert_eq!(object["max"], 2147483647);
}

fn put(mplex: &str, datatype: u32, physunit: u32, value: &str) -> String {
    format!(
        r#"{{"jsonrpc":"2.0","method":"put_canopen_object","id":"p","params":{{"sernum":"{SERNUM}","object":{{"mplex":"{mplex}","datatype":{datatype},"physunit":{physunit},"value":"{value}"}}}}}}"#
    )
}

fn code(v: &Value) -> u64 {
    v["error"]["code"].as_u64().unwrap_or(0)
}

#[test]
fn put_checks_everything_before_writing() {
    let mut p = Portal::connected();
    // The sample: a passenger call to floor 4.
    let out = p.send(&put("0x502200", 7, 0, "4"));
    assert!(
        matches!(&out[..], [Output::Start(_, Job::Write { target: Target { net: 1, node: 1 }, index: 0x5022, sub: 0, data })] if data == &[4, 0, 0, 0])
    );
    let Output::Start(id, _) = out[0] else {
        panic!()
    };
    let answer = sent(&p.session.handle_job(id, JobResult::Done, p.now));
    assert_eq!(
        answer,
        [json!({"jsonrpc":"2.0","id":"p","result":{"object":{"mplex":"0x502200"}}})]
    );
    assert_eq!(
        code(&p.ask(&put("0x652001", 7, 26, "1"), &[])),
        0x0601_0002,
        "read-only"
    );
    assert_eq!(
        code(&p.ask(&put("0x411200", 5, 0, "1"), &[])),
        0x0800_0021,
        "needs service"
    );
    assert_eq!(
        code(&p.ask(&put("0x502200", 6, 0, "4"), &[])),
        0x0607_0010,
        "datatype"
    );
    assert_eq!(
        code(&p.ask(&put("0x502200", 7, 15, "4"), &[])),
        0x0607_0010,
        "physunit"
    );
    assert_eq!(
        code(&p.ask(&put("0x502200", 7, 0, "four"), &[])),
        0x0609_0030
    );
    assert_eq!(
        code(&p.ask(&put("0x502200", 7, 0, "0"), &[])),
        0x0609_0032,
        "below min 1"
    );
    assert_eq!(
        code(&p.ask(&put("0x502200", 7, 0, "255"), &[])),
        0x0609_0031,
        "above max 254"
    );
    assert_eq!(code(&p.ask(&put("0x502299", 7, 0, "1"), &[])), 0x0609_0011);
    assert_eq!(code(&p.ask(&put("0x5FFF00", 7, 0, "1"), &[])), 0x0602_0000);
    let wrong = put("0x502200", 7, 0, "4").replace(SERNUM, "1");
    let e = p.ask(&wrong, &[]);
    assert_eq!(
        (code(&e), &e["error"]["message"]),
        (0x0800_0020, &json!("The serial number does not match."))
    );
    // German messages when German was asked for.
    let de = put("0x652001", 7, 26, "1").replace(
        r#""params":{"#,
        r#""params":{"lang":{"preferred_language":"de"},"#,
    );
    assert_eq!(
        p.ask(&de, &[])["error"]["message"],
        "Versuch, ein nur lesbares Objekt zu schreiben."
    );
    // A refusal from the device comes back with its abort code.
    let out = p.send(&put("0x502200", 7, 0, "4"));
    let Output::Start(id, _) = out[0] else {
        panic!()
    };
    let e = sent(
        &p.session
            .handle_job(id, JobResult::Failed(AbortCode::TIMEOUT), p.now),
    );
    assert_eq!(
        (code(&e[0]), &e[0]["error"]["data"]),
        (0x0504_0000, &json!("0x502200"))
    );
}

fn elevate(level: u8, hash: &str) -> String {
    format!(
        r#"{{"jsonrpc":"2.0","method":"elevate_privilege","id":"e","params":{{"sernum":"{SERNUM}","privilege":{level},"passhash":"{hash}"}}}}"#
    )
}

#[test]
fn privileges_are_granted_expire_and_lock_out() {
    let mut p = Portal::connected();
    let e = p.ask(&elevate(1, "00"), &[]);
    assert_eq!((code(&e), &e["error"]["data"]), (0x0800_0020, &json!("1")));
    assert_eq!(e["error"]["message"], "The password hash does not match.");
    let ok = p.ask(&elevate(1, &SERVICE_SHA1.to_uppercase()), &[]);
    assert_eq!(ok["result"], json!({"duration": 300}));
    assert!(p
        .ask(&put("0x411200", 5, 0, "2"), &[])
        .get("result")
        .is_some());
    assert_eq!(
        code(&p.ask(&put("0x640A00", 7, 19, "1200"), &[])),
        0x0800_0021,
        "engineer on site"
    );
    // Setup rights include service rights; engineer on site is never granted.
    assert!(p.ask(&elevate(2, SETUP_SHA1), &[]).get("result").is_some());
    assert!(p
        .ask(&put("0x411200", 5, 0, "1"), &[])
        .get("result")
        .is_some());
    assert_eq!(
        code(&p.ask(&put("0x640A00", 7, 19, "1200"), &[])),
        0x0800_0021
    );
    assert_eq!(code(&p.ask(&elevate(3, SETUP_SHA1), &[])), 0x0800_0021);
    // The grant ends after its duration.
    p.now += Duration::from_secs(301);
    assert_eq!(
        code(&p.ask(&put("0x411200", 5, 0, "1"), &[])),
        0x0800_0021,
        "expired"
    );
    // Three wrong hashes lock elevation out, even for the right one.
    for _ in 0..3 {
        assert_eq!(code(&p.ask(&elevate(1, "bad"), &[])), 0x0800_0020);
    }
    let locked = p.ask(&elevate(1, SERVICE_SHA1), &[]);
    assert_eq!(code(&locked), 0x0800_0022, "present device state");
    assert!(
        locked["error"]["message"]
            .as_str()
            .unwrap()
            .contains("locked for 30 s"),
        "{locked}"
    );
    p.now += Duration::from_secs(31);
    assert!(p
        .ask(&elevate(1, SERVICE_SHA1), &[])
        .get("result")
        .is_some());
}

#[test]
fn other_nodes_are_read_with_their_datatype_and_written_only_when_described() {
    let mut p = Portal::connected();
    let get = r#"{"jsonrpc":"2.0","id":"<ID>","method":"get_canopen_object","params":{"lang":{"preferred_language":"en","alternate_language":"de"},"node":{"id":12,"net":1,"datatype":25},"object":{"mplex":"0x610001","compact":false}}}"#;
    let out = p.send(get);
    assert!(matches!(
        &out[..],
        [Output::Start(
            _,
            Job::Read {
                target: Target { net: 1, node: 12 },
                index: 0x6100,
                sub: 1
            }
        )]
    ));
    let answer = p.ask(get, &[&[2, 1, 1, 6, 0x10, 0]]);
    assert_eq!(answer["result"]["object"]["value"], json!(["68820205826"]));
    assert_eq!(answer["result"]["object"]["datatype"], 25);
    // The description says what the gateway will do: read it, never write it.
    assert_eq!(answer["result"]["object"]["access"], "ro");
    let put12 = format!(
        r#"{{"jsonrpc":"2.0","method":"put_canopen_object","id":"<ID>","params":{{"sernum":"{SERNUM}","node":{{"id":12,"net":1}},"object":{{"mplex":"0x502200","datatype":7,"physunit":0,"value":"4"}}}}}}"#
    );
    // Node 12 has no description: never written, whatever the caller's rights.
    assert_eq!(code(&p.ask(&put12, &[])), 0x0601_0002, "undescribed");
    // Node 13 is described: writing it needs setup rights.
    let put13 = put12.replace(r#""id":12"#, r#""id":13"#);
    assert_eq!(
        code(&p.ask(&put13, &[])),
        0x0800_0021,
        "setup rights needed"
    );
    p.ask(&elevate(2, SETUP_SHA1), &[]);
    assert!(p.ask(&put13, &[]).get("result").is_some());
    assert_eq!(code(&p.ask(&put12, &[])), 0x0601_0002, "still undescribed");
    let net2 = put13.replace(r#""net":1"#, r#""net":2"#);
    assert_eq!(
        p.ask(&net2, &[])["error"]["code"],
        rpc_codes::INVALID_PARAMS
    );
}

#[test]
fn subscriptions_register_all_or_none_and_respect_inhibit_and_threshold() {
    let mut p = Portal::connected();
    let bad = r#"{"jsonrpc":"2.0","method":"reg_canopen_object","id":"r","params":{"mplex":["0x652001","0x652099"],"inhibit":1000,"threshold":1}}"#;
    let e = p.ask(bad, &[]);
    assert_eq!(
        e["error"],
        json!({"code":101253137u64,"message":"Sub-index does not exist.","data":"0x652099"})
    );
    let missing = bad.replace("0x652099", "0x5FFF01");
    assert_eq!(
        p.ask(&missing, &[])["error"],
        json!({"code":100794368,"message":"Object does not exist in the object dictionary.","data":"0x5FFF01"})
    );
    assert_eq!(p.session.subscription_count(), 0, "none registered");
    let good = r#"{"jsonrpc":"2.0","method":"reg_canopen_object","id":"r","params":{"mplex":["0x652001","0x652002"],"inhibit":1000,"threshold":5}}"#;
    let out = p.send(good);
    assert_eq!(
        sent(&out),
        [json!({"jsonrpc":"2.0","id":"r","result":{"done":0}})]
    );
    assert!(out.contains(&Output::Watch(Target { net: 1, node: 1 }, 0x6520, 1)));
    // The baseline read is the first push.
    let baseline = out.iter().find_map(|o| match o {
        Output::Start(id, Job::Read { sub: 1, .. }) => Some(*id),
        _ => None,
    });
    let pushed = sent(&p.session.handle_job(
        baseline.unwrap(),
        JobResult::Read(vec![100u32.to_le_bytes().to_vec()]),
        p.now,
    ));
    assert_eq!(
        pushed,
        [
            json!({"jsonrpc":"2.0","method":"canopen_object","result":{"mplex":"0x652001","value":"100"}})
        ]
    );
    let t = Target { net: 1, node: 1 };
    let value =
        |p: &mut Portal, v: u32| sent(&p.session.handle_value(t, 0x6520, 1, v.to_string(), p.now));
    // Below the threshold: nothing.
    assert!(value(&mut p, 104).is_empty());
    // Inside the inhibit gap: held back, the latest value goes out when the gap ends.
    p.now += Duration::from_millis(200);
    assert!(value(&mut p, 110).is_empty());
    assert!(value(&mut p, 120).is_empty());
    assert_eq!(
        p.session.poll_timeout(),
        Some(p.now + Duration::from_millis(800))
    );
    assert!(p.later(Duration::from_millis(799)).is_empty());
    let late = sent(&p.later(Duration::from_millis(1)));
    assert_eq!(late[0]["result"]["value"], "120");
    // After the gap a change beyond the threshold goes out at once.
    p.now += Duration::from_millis(1000);
    assert_eq!(value(&mut p, 126)[0]["result"]["value"], "126");
    // A change that returns within the threshold cancels the pending push.
    p.now += Duration::from_millis(100);
    assert!(value(&mut p, 140).is_empty());
    let gap_end = p.now + Duration::from_millis(900);
    assert_eq!(p.session.poll_timeout(), Some(gap_end));
    assert!(value(&mut p, 127).is_empty());
    // Nothing is owed: the only timer left is the connection's own.
    assert!(p.session.poll_timeout() > Some(gap_end));
    assert!(p.later(Duration::from_secs(2)).is_empty());
    // Registering again (a second viewer) pushes the current value once more, although it did
    // not change, and keeps the object watched only once.
    let again = p.send(&good.replace("\"r\"", "\"r2\""));
    assert!(!again.iter().any(|o| matches!(o, Output::Watch(..))));
    let reread = again.iter().find_map(|o| match o {
        Output::Start(id, Job::Read { sub: 1, .. }) => Some(*id),
        _ => None,
    });
    let repeated = sent(&p.session.handle_job(
        reread.unwrap(),
        JobResult::Read(vec![126u32.to_le_bytes().to_vec()]),
        p.now,
    ));
    assert_eq!(repeated[0]["result"]["value"], "126");
    // A value owed when the subscription ends is never pushed, nor timed.
    assert!(value(&mut p, 150).is_empty());
    assert_eq!(
        p.session.poll_timeout(),
        Some(p.now + Duration::from_millis(1000))
    );
    let unreg = r#"{"jsonrpc":"2.0","method":"unreg_canopen_object","id":"12345","params":{"mplex":["0x652001","0x652002"]}}"#;
    let out = p.send(unreg);
    assert_eq!(
        sent(&out),
        [json!({"jsonrpc":"2.0","id":"12345","result":{"done":0}})]
    );
    assert!(out.contains(&Output::Unwatch(t, 0x6520, 1)));
    assert!(p.session.poll_timeout() > Some(p.now + Duration::from_millis(1000)));
    assert!(p.later(Duration::from_secs(2)).is_empty());
    assert!(value(&mut p, 1000).is_empty());
    // At most max_subscriptions (4).
    let many = r#"{"jsonrpc":"2.0","method":"reg_canopen_object","id":"m","params":{"mplex":["0x638301","0x639001","0x639101","0x630101","0x630201"]}}"#;
    assert_eq!(code(&p.ask(many, &[])), 0x0504_0005);
}

#[test]
fn the_token_is_stored_before_it_is_confirmed() {
    let mut p = Portal::connected();
    let req = format!(
        r#"{{"jsonrpc":"2.0","method":"update_unique_token","id":"t","params":{{"sernum":"{SERNUM}","token":"A token string that is maximum 128 characters long."}}}}"#
    );
    let out = p.send(&req);
    let [Output::Start(id, Job::StoreToken(token))] = &out[..] else {
        panic!("{out:?}")
    };
    assert_eq!(token, "A token string that is maximum 128 characters long.");
    assert_eq!(
        sent(&p.session.handle_job(*id, JobResult::Done, p.now)),
        [json!({"jsonrpc":"2.0","id":"t","result":{"done":0}})]
    );
    let long = req.replace("A token string", &"x".repeat(120));
    assert_eq!(code(&p.ask(&long, &[])), 0x0607_0012);
    let wrong = req.replace(SERNUM, "000");
    assert_eq!(
        p.ask(&wrong, &[])["error"]["message"],
        "The serial number does not match."
    );
    let out = p.send(&req);
    let [Output::Start(id, _)] = &out[..] else {
        panic!()
    };
    let failed = sent(&p.session.handle_job(
        *id,
        JobResult::Failed(AbortCode::CANNOT_STORE),
        p.now,
    ));
    assert_eq!(code(&failed[0]), 0x0800_0020);
}

#[test]
fn bad_input_gets_json_rpc_errors_and_the_connection_stays() {
    let mut p = Portal::connected();
    let cases = [
        ("{", rpc_codes::PARSE),
        ("[1,2]", rpc_codes::INVALID_REQUEST),
        (
            r#"{"jsonrpc":"2.0","id":1,"method":"reboot"}"#,
            rpc_codes::METHOD_NOT_FOUND,
        ),
        (
            r#"{"jsonrpc":"2.0","id":1,"method":"get_canopen_object"}"#,
            rpc_codes::INVALID_PARAMS,
        ),
        (
            r#"{"jsonrpc":"2.0","id":1,"method":"get_canopen_object","params":{"object":{"mplex":"652001"}}}"#,
            rpc_codes::INVALID_PARAMS,
        ),
        (
            r#"{"jsonrpc":"2.0","id":1,"method":"reg_canopen_object","params":{"mplex":"0x652001"}}"#,
            rpc_codes::INVALID_PARAMS,
        ),
        (
            r#"{"jsonrpc":"2.0","id":1,"method":"elevate_privilege","params":{"sernum":"180917010200000102","privilege":"1"}}"#,
            rpc_codes::INVALID_PARAMS,
        ),
        (
            r#"{"jsonrpc":"2.0","id":1,"method":"put_canopen_object","params":{"sernum":"180917010200000102","object":{"mplex":"0x502200","value":4}}}"#,
            rpc_codes::INVALID_PARAMS,
        ),
    ];
    for (text, expected) in cases {
        let out = sent(&p.send(text));
        assert_eq!(out.len(), 1, "{text}");
        assert_eq!(out[0]["error"]["code"], expected, "{text}");
    }
    assert_eq!(p.session.phase(), Phase::Connected(1));
    // A notification from the portal needs no answer.
    assert!(p.send(r#"{"jsonrpc":"2.0","method":"hello"}"#).is_empty());
}

#[test]
fn a_silent_connection_is_dropped() {
    let mut p = Portal::connected();
    let limit = Duration::from_secs(630);
    assert_eq!(p.session.poll_timeout(), Some(p.now + limit));
    // Only an NXg message restarts the limit (WebSocket pings never reach the session).
    p.now += Duration::from_secs(300);
    assert_eq!(
        p.send(r#"{"jsonrpc":"2.0","id":"hb","method":"get_heartbeat"}"#)
            .len(),
        1
    );
    assert!(p.later(Duration::from_secs(629)).is_empty());
    let out = p.later(Duration::from_secs(1));
    assert!(matches!(&out[..], [Output::Close(CloseReason::Silent)]));
    assert_eq!(p.session.phase(), Phase::Closed);
}

#[test]
fn never_panics_on_any_text() {
    use proptest::prelude::*;
    let p = std::cell::RefCell::new(Portal::connected());
    proptest!(|(text in ".{0,200}")| {
        let _ = p.borrow_mut().send(&text);
    });
    let methods = [
        "get_canopen_object",
        "put_canopen_object",
        "reg_canopen_object",
        "elevate_privilege",
        "update_unique_token",
    ];
    proptest!(|(m in 0usize..5, params in "[\\[\\]{}\",:0-9a-z ]{0,80}")| {
        let _ = p.borrow_mut().send(&format!(r#"{{"jsonrpc":"2.0","id":1,"method":"{}","params":{params}}}"#, methods[m]));
    });
}

#[test]
fn ids_of_any_kind_are_echoed_and_the_connack_may_use_a_string_id() {
    let now = Instant::now();
    let mut session = Session::new(settings(), metadata(), None, now);
    session.handle_text(
        r#"{"jsonrpc":"2.0","id":"1","result":"CONNACK","api":1}"#,
        now,
    );
    assert_eq!(session.phase(), Phase::Connected(1));
    let mut p = Portal { session, now };
    for id in [r#""abc""#, "17", "-3", "2.5", r#""""#] {
        let answer = p.ask(
            &format!(r#"{{"jsonrpc":"2.0","id":{id},"method":"get_heartbeat"}}"#),
            &[],
        );
        assert_eq!(
            answer["id"],
            serde_json::from_str::<Value>(id).unwrap(),
            "{id}"
        );
    }
}

#[test]
fn put_values_are_decimal_and_out_of_type_range_is_too_high_or_low() {
    let mut p = Portal::connected();
    let write = |p: &mut Portal, value: &str| {
        let out = p.send(&put("0x502200", 7, 0, value));
        match &out[..] {
            [Output::Start(id, Job::Write { data, .. })] => {
                p.session.handle_job(*id, JobResult::Done, p.now);
                Ok(data.clone())
            }
            _ => Err(code(&sent(&out)[0])),
        }
    };
    assert_eq!(
        write(&mut p, "010"),
        Ok(vec![10, 0, 0, 0]),
        "ten, not octal 8"
    );
    assert_eq!(write(&mut p, "08"), Ok(vec![8, 0, 0, 0]));
    assert_eq!(write(&mut p, "0x0A"), Ok(vec![10, 0, 0, 0]));
    assert_eq!(write(&mut p, "4294967296"), Err(0x0609_0031));
    assert_eq!(write(&mut p, "-1"), Err(0x0609_0032));
    assert_eq!(write(&mut p, "1e3"), Err(0x0609_0030));
}

#[test]
fn an_engineer_on_site_object_is_described_in_the_specs_terms() {
    let mut p = Portal::connected();
    // 6001h: rw for an engineer on site only (privilege 3, which NXg §8.4 does not know).
    let get = GET_TRIP.replace("0x652001", "0x600100");
    let answer = p.ask(&get, &[&[1]]);
    let object = &answer["result"]["object"];
    assert_eq!(
        (&object["access"], &object["privilege"]),
        (&json!("ro"), &json!(2)),
        "{answer}"
    );
    // And it is not written remotely, whoever asks.
    p.ask(&elevate(2, SETUP_SHA1), &[]);
    assert_eq!(code(&p.ask(&put("0x600100", 5, 0, "1"), &[])), 0x0800_0021);
}

#[test]
fn errors_are_in_the_last_requested_language() {
    let mut p = Portal::connected();
    // Before any request named a language: English.
    let first = p.ask(&put("0x652001", 7, 26, "1"), &[]);
    assert_eq!(
        first["error"]["message"],
        "Attempt to write a read only object."
    );
    let de = GET_TRIP.replace(
        r#""preferred_language": "en""#,
        r#""preferred_language": "de""#,
    );
    p.ask(&de, &[&2510u32.to_le_bytes()]);
    // NXg §6.3.3: "in the last requested language" — a put without `lang` after a German get
    // is answered in German.
    let after = p.ask(&put("0x652001", 7, 26, "1"), &[]);
    let german = nxg::codes::ErrorCode(0x0601_0002).message("de");
    assert_ne!(german, "Attempt to write a read only object.");
    assert_eq!(after["error"]["message"], german);
    // Until a request names another.
    p.ask(GET_TRIP, &[&2510u32.to_le_bytes()]);
    let english = p.ask(&put("0x652001", 7, 26, "1"), &[]);
    assert_eq!(
        english["error"]["message"],
        "Attempt to write a read only object."
    );
}

#[test]
fn elevation_cannot_be_gamed() {
    let context = metadata();
    let mut p = Portal::connected_with(settings(), context.clone());
    // Two wrong hashes; a grant of privilege 0 does not reset the count.
    for _ in 0..2 {
        assert_eq!(code(&p.ask(&elevate(1, "bad"), &[])), 0x0800_0020);
    }
    assert!(p.ask(&elevate(0, "anything"), &[]).get("result").is_some());
    let out = p.send(&elevate(1, "bad"));
    assert_eq!(code(&sent(&out)[0]), 0x0800_0020);
    // The lock-out is handed out to be stored.
    assert!(out.contains(&Output::Lockout(nxg::gateway::LockoutState {
        service: LevelState {
            failures: 3,
            locked_s: 30
        },
        setup: LevelState::default(),
    })));
    // Locked: even the right hash answers 08000022h, and the setup level is not affected.
    assert_eq!(code(&p.ask(&elevate(1, SERVICE_SHA1), &[])), 0x0800_0022);
    assert!(p.ask(&elevate(2, SETUP_SHA1), &[]).get("result").is_some());
    // A reconnection shares the gateway's lock-out.
    let mut again = Portal::connected_with(settings(), context.clone());
    again.now = p.now;
    let e = again.ask(&elevate(1, SERVICE_SHA1), &[]);
    assert_eq!(code(&e), 0x0800_0022, "{e}");
    // After the lock, the right hash works and ends the count.
    again.now += Duration::from_secs(31);
    assert!(again
        .ask(&elevate(1, SERVICE_SHA1), &[])
        .get("result")
        .is_some());
    assert_eq!(code(&again.ask(&elevate(1, "bad"), &[])), 0x0800_0020);
}

#[test]
fn a_level_without_a_password_is_never_granted_and_says_so() {
    let mut s = settings();
    s.service_sha1 = None;
    let mut p = Portal::connected_with(s, metadata());
    let e = p.ask(&elevate(1, SERVICE_SHA1), &[]);
    assert_eq!(code(&e), 0x0800_0021);
    assert_eq!(
        e["error"]["message"],
        "This gateway grants no service rights."
    );
    // Not a wrong hash: nothing is counted.
    for _ in 0..5 {
        p.ask(&elevate(1, SERVICE_SHA1), &[]);
    }
    assert!(p.ask(&elevate(2, SETUP_SHA1), &[]).get("result").is_some());
}

#[test]
fn the_owners_policy_refuses_and_hides() {
    let policy = |text: &str| -> Policy { nxg::msg::read(text).unwrap() };
    let with = |text: &str| {
        let mut s = settings();
        s.policy = policy(text);
        Portal::connected_with(s, metadata())
    };
    let call = put("0x502200", 7, 0, "4");
    // Read-only: every put refused, reads unaffected.
    let mut p = with(r#"{"remote_writes":"read-only"}"#);
    assert_eq!(code(&p.ask(&call, &[])), 0x0601_0002);
    assert!(p
        .ask(GET_TRIP, &[&7u32.to_le_bytes()])
        .get("result")
        .is_some());
    // Deny: that object only.
    let mut p = with(r#"{"deny":["0x5022"]}"#);
    assert_eq!(code(&p.ask(&call, &[])), 0x0601_0002);
    assert_eq!(
        code(&p.ask(&put("0x411200", 5, 0, "1"), &[])),
        0x0800_0021,
        "other objects pass the policy and meet the usual checks"
    );
    // Hide: get, put and registration answer 06020000h.
    let mut p = with(r#"{"hide":["0x6520"]}"#);
    assert_eq!(code(&p.ask(GET_TRIP, &[])), 0x0602_0000);
    let reg = r#"{"jsonrpc":"2.0","method":"reg_canopen_object","id":"r","params":{"mplex":["0x652001"]}}"#;
    assert_eq!(code(&p.ask(reg, &[])), 0x0602_0000);
    assert!(
        p.ask(&call, &[]).get("result").is_some(),
        "others unaffected"
    );
}

fn node(id: u8) -> NodeRef {
    NodeRef::new(NodeId::new(id).unwrap(), 1)
}

fn event(time_ms: i64, what: Happening) -> BusEvent {
    BusEvent { time_ms, what }
}

fn door_blocked(time_ms: i64) -> BusEvent {
    let text = Texts::from(std::collections::BTreeMap::from([
        ("en".to_owned(), "Door blocked".to_owned()),
        ("de".to_owned(), "Tür blockiert".to_owned()),
    ]));
    event(
        time_ms,
        Happening::Emcy {
            node: node(1),
            code: 0xFF01,
            register: 0x21,
            data: [0; 5],
            text,
        },
    )
}

const REG_EVENTS: &str = r#"{"jsonrpc":"2.0","id":"5","method":"reg_canopen_event","params":{"events":["emcy","state"],"lang":{"preferred_language":"de","alternate_language":"en"}}}"#;

#[test]
fn bus_events_are_served_at_nxg_api_1_wait_for_a_portal_and_keep_their_order() {
    let context = metadata();
    let queue = |e: BusEvent| context.events.lock().unwrap().push(e);
    // Seen while no portal was there.
    queue(door_blocked(1_000));
    queue(event(
        2_000,
        Happening::Bus {
            net: 1,
            state: BusState::BusOff,
        },
    ));
    queue(event(
        3_000,
        Happening::State {
            node: node(12),
            state: NodeState::Offline,
        },
    ));
    // NXg api 1 in force (the only one there is): the events are canlift's extension, called
    // by name; nothing is pushed before a portal registers, then what waited, in order, in
    // German; the bus event was not asked for.
    let s = settings();
    assert_eq!(s.identity.api, 1);
    let mut p = Portal::connected_at(s.clone(), context.clone(), 1);
    assert!(p.session.deliver_events().is_empty(), "nothing unsolicited");
    let out = sent(&p.send(REG_EVENTS));
    assert_eq!(
        out[0],
        json!({"jsonrpc":"2.0","id":"5","result":{"done":0}})
    );
    assert_eq!(
        out[1],
        json!({"jsonrpc":"2.0","method":"canopen_event","result":{"event":{"type":"emcy",
            "node":{"id":1,"net":1},"time":"1970-01-01T00:00:01.000Z","code":"0xFF01",
            "register":"0x21","data":"0000000000","text":"Tür blockiert"}}})
    );
    assert_eq!(
        out[2]["result"]["event"],
        json!({"type":"state","node":{"id":12,"net":1},"time":"1970-01-01T00:00:03.000Z","state":"offline"})
    );
    assert_eq!(out.len(), 3);
    // Live events as they come.
    queue(door_blocked(4_000));
    assert_eq!(sent(&p.session.deliver_events()).len(), 1);
    // Unknown kinds are bad parameters; unregistered, events wait again.
    let bad =
        r#"{"jsonrpc":"2.0","id":"6","method":"reg_canopen_event","params":{"events":["door"]}}"#;
    assert_eq!(p.ask(bad, &[])["error"]["code"], rpc_codes::INVALID_PARAMS);
    let unreg = r#"{"jsonrpc":"2.0","id":"7","method":"unreg_canopen_event","params":{}}"#;
    assert_eq!(p.ask(unreg, &[])["result"], json!({"done":0}));
    queue(door_blocked(5_000));
    assert!(p.session.deliver_events().is_empty());
    // The next portal (a reconnection) gets it.
    let mut again = Portal::connected_at(s, context.clone(), 1);
    let out = sent(&again.send(REG_EVENTS));
    assert_eq!(out.len(), 2);
    assert_eq!(
        out[1]["result"]["event"]["time"],
        "1970-01-01T00:00:05.000Z"
    );
}
