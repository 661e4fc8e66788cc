//! Conformance: a portal (Rust, TLS with a private CA) sends every sample request of NXg SW003
//! verbatim to a gateway in bus-node mode in front of the simulated lift, and checks each answer
//! field by field.

use crate::common;

use std::time::Duration;

use common::*;
use gateway::Gateway;
use serde_json::{json, Value};

const HEARTBEAT: &str = r#"{ "jsonrpc": "2.0", "id": "<ID>", "method": "get_heartbeat" }"#;

const UPDATE_TOKEN: &str = r#"{
  "jsonrpc": "2.0",
  "method": "update_unique_token",
  "id": "<ID>",
  "params": {
    "sernum": "180917010200000102",
    "token": "A token string that is maximum 128 characters long."
  }
}"#;

const GET_TRIP: &str = r#"{
  "jsonrpc": "2.0",
  "id": "<ID>",
  "method": "get_canopen_object",
  "params": {
    "lang": { "preferred_language": "en", "alternate_language": "de" },
    "object": { "mplex": "0x652001", "compact": false, "stripped": false, "naked": false }
  }
}"#;

const GET_COMPACT: &str = r#"{
  "jsonrpc": "2.0",
  "id": "<ID>",
  "method": "get_canopen_object",
  "params": {
    "lang": { "preferred_language": "en", "alternate_language": "de" },
    "object": { "mplex": "0x401001", "compact": true }
  }
}"#;

const PUT_CALL: &str = r#"{
    "jsonrpc": "2.0",
    "method": "put_canopen_object",
"id": "<ID>",
"params": {
  "sernum": "180917010200000102",
  "object": { "mplex": "0x502200", "datatype": 7, "physunit": 0, "value": "4" }
}
}"#;

const ELEVATE: &str = r#"{
  "jsonrpc": "2.0",
  "method": "elevate_privilege",
  "id": "<ID>",
  "params": {
    "sernum": "180917010200000102",
    "privilege": 1,
    "passhash": "<The unsalted SHA1 password hash for the desired priv.>"
  }
}"#;

const GET_OTHER_NODE: &str = r#"{
  "jsonrpc": "2.0",
"id": "<ID>",
"method": "get_canopen_object",
"params": {
  "lang": { "preferred_language": "en", "alternate_language": "de" },
  "node": { "id": 12, "net": 1, "datatype": 25 },
  "object": { "mplex": "0x610001", "compact": false }
}
}"#;

const PUT_OTHER_NODE: &str = r#"{
  "jsonrpc": "2.0",
  "method": "put_canopen_object",
  "id": "<ID>",
  "params": {
    "sernum": "180917010200000102",
    "node": { "id": 12, "net": 1 },
    "object": { "mplex": "0x502200", "datatype": 7, "physunit": 0, "value": "4" }
  }
}"#;

const REG: &str = r#"{
  "jsonrpc": "2.0",
  "method": "reg_canopen_object",
  "id": "<ID>",
  "params": { "mplex": [ "0x652001", "0x652002" ], "inhibit": 1000, "threshold": 1 }
}"#;

const UNREG: &str = r#"{
  "jsonrpc": "2.0",
  "method": "unreg_canopen_object",
  "id": "12345",
  "params": { "mplex": [ "0x652001", "0x652002" ] }
}"#;

fn done(id: &str) -> Value {
    json!({"jsonrpc": "2.0", "id": id, "result": {"done": 0}})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_sample_of_the_specification() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let bus = "mem://conformance";
    let sim = testkit::lift::simulator(bus).await;
    let config = config(&portal.url(), &pki, bus, dir.path());
    let gateway = Gateway::bus_node(config).await.unwrap();
    let running = spawn(gateway);

    // §5.1: the upgrade offers both subprotocols and sends the configured Origin.
    let (mut ws, protocols, origin) = portal.accept().await;
    assert_eq!(protocols.as_deref(), Some("cloud, lift"));
    assert_eq!(origin.as_deref(), Some("https://192.168.178.101"));
    // §5.2.1: CONNECT with the identity and no cloudtoken yet.
    let connect = connack(&mut ws).await;
    assert_eq!(
        connect["params"],
        json!({"identity": {"sernum": SERNUM, "vendorid": 1050, "productcode": 4096,
            "liftnum": "40/7289/20399-126", "hardware": "Thor @ NX-T2", "software": "01.23.10",
            "api": 1, "boardhash": "2354A687AF6DC79B203E754E8E426A87FE188A62983B7AC48F9D5E195B728112"},
            "domaintoken": "MAS"})
    );
    let mut notes = Vec::new();
    // §5.3
    assert_eq!(ask(&mut ws, HEARTBEAT, &mut notes).await, done("<ID>"));
    // §5.4: stored before confirmed.
    assert_eq!(ask(&mut ws, UPDATE_TOKEN, &mut notes).await, done("<ID>"));
    let stored = std::fs::read_to_string(dir.path().join("state/cloudtoken")).unwrap();
    assert_eq!(
        stored.trim_end(),
        "A token string that is maximum 128 characters long."
    );
    // §6.1.1–6.1.3 on the simulator's trip counter (0 on a fresh lift).
    let full = ask(&mut ws, GET_TRIP, &mut notes).await;
    assert_eq!(
        full,
        json!({"jsonrpc": "2.0", "id": "<ID>", "result": {
            "lang": {"language": "en"},
            "object": {"mplex": "0x652001", "objcode": 8, "datatype": 7, "formtype": 10,
                "physunit": 26, "access": "ro", "privilege": 0, "name": "Trip counter [trips]",
                "hint": "This object represents the internal trip counter of the lift controller.",
                "value": ["0"], "min": 0, "max": 4294967295u64, "zero": false, "list": []},
            "hints": {"show_off_at_zero": false, "show_unlimited_at_max": false,
                "show_undefined_at_max": false}}})
    );
    let stripped = ask(
        &mut ws,
        &GET_TRIP.replace(r#""stripped": false"#, r#""stripped": true"#),
        &mut notes,
    )
    .await;
    assert_eq!(
        stripped["result"],
        json!({"object": {"mplex": "0x652001", "objcode": 8, "datatype": 7, "formtype": 10,
            "physunit": 26, "access": "ro", "privilege": 0, "value": ["0"], "min": 0,
            "max": 4294967295u64, "zero": false}})
    );
    let naked = ask(
        &mut ws,
        &GET_TRIP.replace(r#""naked": false"#, r#""naked": true"#),
        &mut notes,
    )
    .await;
    assert_eq!(
        naked["result"],
        json!({"object": {"mplex": "0x652001", "value": ["0"]}})
    );
    // §6.1.4: a list.
    let lantern = GET_TRIP
        .replace("0x652001", "0x411200")
        .replace(r#""id": "<ID>""#, r#""id": "1234""#);
    let list = ask(&mut ws, &lantern, &mut notes).await;
    assert_eq!(list["id"], "1234");
    let object = &list["result"]["object"];
    assert_eq!(
        [
            &object["mplex"],
            &object["objcode"],
            &object["datatype"],
            &object["formtype"],
            &object["physunit"],
            &object["access"],
            &object["privilege"],
            &object["value"],
            &object["min"],
            &object["max"],
            &object["zero"]
        ],
        [
            &json!("0x411200"),
            &json!(7),
            &json!(5),
            &json!(15),
            &json!(0),
            &json!("rw"),
            &json!(1),
            &json!(["0"]),
            &json!(0),
            &json!(3),
            &json!(false)
        ]
    );
    assert_eq!(object["name"], "Hall lantern options");
    assert_eq!(
        object["list"],
        json!([
            "Turn the hall lantern on, when approaching to the floor",
            "Turn the hall lantern on, after arrival when unlocking the doors.",
            "Turn the hall lantern on, after the car door has been fully opened.",
            "off"
        ])
    );
    // §6.2.2: the compact array, exactly the sample's values.
    let compact = ask(&mut ws, GET_COMPACT, &mut notes).await;
    assert_eq!(
        compact["result"],
        json!({"lang": {"language": "en"},
            "object": {"mplex": "0x401001", "objcode": 8, "datatype": 4, "formtype": 26,
                "physunit": 15, "access": "ro", "privilege": 1, "name": "Floor level positions",
                "hint": "This object holds the floor levels in millimeter.",
                "value": ["1000", "4500", "8000", "11500", "15000", "18500", "22000", "25500"],
                "min": 0, "max": 2147483647, "zero": false, "list": []},
            "hints": {"show_off_at_zero": false, "show_unlimited_at_max": false,
                "show_undefined_at_max": false}})
    );
    // §7.1: subscribe to the trip counter and the operating hours; the current values come first.
    assert_eq!(ask(&mut ws, REG, &mut notes).await, done("<ID>"));
    // §6.3: the passenger call to floor 4 — the car travels and the trip counter rises.
    assert_eq!(
        ask(&mut ws, PUT_CALL, &mut notes).await,
        json!({"jsonrpc": "2.0", "id": "<ID>", "result": {"object": {"mplex": "0x502200"}}})
    );
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    while !notes
        .iter()
        .any(|n| n["result"] == json!({"mplex": "0x652001", "value": "1"}))
    {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no trip counter push: {notes:?}"
        );
        let v = recv(&mut ws).await;
        notes.push(v);
    }
    // §7.3.1: notifications have the sample's shape.
    assert!(
        notes.contains(&json!({"jsonrpc": "2.0", "method": "canopen_object",
        "result": {"mplex": "0x652001", "value": "0"}}))
    );
    assert!(
        notes.contains(&json!({"jsonrpc": "2.0", "method": "canopen_object",
        "result": {"mplex": "0x652002", "value": "0"}}))
    );
    // §7.2
    assert_eq!(ask(&mut ws, UNREG, &mut notes).await, done("12345"));
    // §6.4.3: the sample's placeholder is not the hash of the service password.
    let refused = ask(&mut ws, ELEVATE, &mut notes).await;
    assert_eq!(
        refused["error"],
        json!({"code": 0x0800_0020, "message": "The password hash does not match.", "data": "1"})
    );
    // §6.5.1: another node, by SDO, typed by the request: the I/O node's first hall button.
    let other = ask(&mut ws, GET_OTHER_NODE, &mut notes).await;
    let value: u64 = other["result"]["object"]["value"][0]
        .as_str()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(value & 0xFF, 0x02, "standard hall call");
    assert_eq!((value >> 24) & 0xFF, 1, "floor 1");
    assert_eq!(other["result"]["object"]["datatype"], 25);
    // Described by its EDS, named by the CiA 417 catalog.
    assert_eq!(other["result"]["object"]["name"], "Virtual input 1");
    assert_eq!(other["result"]["object"]["objcode"], 8);
    // §6.6.1: the I/O node's EDS has no 5022h.
    let put12 = ask(&mut ws, PUT_OTHER_NODE, &mut notes).await;
    assert_eq!(
        put12["error"]["code"], 0x0602_0000,
        "the I/O node has no 5022h"
    );
    assert_eq!(put12["error"]["data"], "0x502200");
    // A put to another node needs setup rights: the simulated button press (2000h).
    let press = PUT_OTHER_NODE
        .replace("0x502200", "0x200000")
        .replace(r#""datatype": 7"#, r#""datatype": 6"#);
    let refused = ask(&mut ws, &press, &mut notes).await;
    assert_eq!(refused["error"]["code"], 0x0800_0021);
    // §6.4.2 with the right hash, then the put reaches node 12.
    let elevate = ELEVATE
        .replace(
            "<The unsalted SHA1 password hash for the desired priv.>",
            SETUP_SHA1,
        )
        .replace(r#""privilege": 1"#, r#""privilege": 2"#);
    assert_eq!(
        ask(&mut ws, &elevate, &mut notes).await["result"],
        json!({"duration": 300})
    );
    let pressed = ask(&mut ws, &press, &mut notes).await;
    assert!(pressed.get("error").is_none(), "{pressed}");
    // A node that does not answer: SDO timeout, and nothing else stalls.
    let silent = GET_OTHER_NODE.replace(r#""id": 12"#, r#""id": 33"#);
    send(&mut ws, &silent).await;
    assert_eq!(
        ask(&mut ws, &HEARTBEAT.replace("<ID>", "hb"), &mut notes).await,
        done("hb")
    );
    let timeout = recv(&mut ws).await;
    assert_eq!(timeout["error"]["code"], 0x0504_0000);

    running.stop().await;
    sim.stop().await;
}
