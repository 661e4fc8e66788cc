//! Interop: the conversation driven by a portal in Python `websockets` over Python's ssl, an
//! independent WebSocket and TLS stack.

use crate::common;

use std::collections::HashMap;
use std::process::Stdio;
use std::time::Duration;

use common::*;
use gateway::Gateway;
use serde_json::{json, Value};
use tokio::io::{AsyncBufReadExt, BufReader};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_python_websockets_portal_talks_to_the_gateway() {
    let Some(python) = testkit::python() else {
        return;
    };
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let mut portal = tokio::process::Command::new(&python)
        .arg(testkit::interop_script("portal.py"))
        .arg(&pki.cert)
        .arg(&pki.key)
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(portal.stdout.take().unwrap()).lines();
    let first = tokio::time::timeout(Duration::from_secs(30), lines.next_line())
        .await
        .expect("the portal starts")
        .unwrap()
        .unwrap();
    let port = first.strip_prefix("PORT ").expect("PORT line");
    let bus = "mem://python-portal";
    let sim = testkit::lift::simulator(bus).await;
    let config = config(&format!("wss://localhost:{port}/ws"), &pki, bus, dir.path());
    let gateway = Gateway::bus_node(config).await.unwrap();
    let running = spawn(gateway);
    let mut answers: HashMap<String, Value> = HashMap::new();
    let mut notes = Vec::new();
    let mut facts = HashMap::new();
    loop {
        let line = tokio::time::timeout(Duration::from_secs(60), lines.next_line())
            .await
            .expect("the conversation goes on")
            .unwrap()
            .expect("the portal printed DONE");
        let (kind, rest) = line.split_once(' ').unwrap_or((line.as_str(), ""));
        match kind {
            "DONE" => break,
            "ANSWER" => {
                let (name, json) = rest.split_once(' ').unwrap();
                answers.insert(name.to_owned(), serde_json::from_str(json).unwrap());
            }
            "NOTE" => notes.push(serde_json::from_str::<Value>(rest).unwrap()),
            _ => {
                facts.insert(kind.to_owned(), rest.to_owned());
            }
        }
    }
    assert_eq!(facts["SUBPROTOCOL"], "cloud");
    assert_eq!(facts["ORIGIN"], "https://192.168.178.101");
    let connect: Value = serde_json::from_str(&facts["CONNECT"]).unwrap();
    assert_eq!(connect["params"]["identity"]["sernum"], SERNUM);
    assert_eq!(
        answers["heartbeat"],
        json!({"jsonrpc": "2.0", "id": "<ID>", "result": {"done": 0}})
    );
    let trip = &answers["trip"]["result"];
    assert_eq!(trip["lang"]["language"], "de");
    assert_eq!(trip["object"]["name"], "Fahrtenzähler [Fahrten]");
    assert_eq!(trip["object"]["value"], json!(["0"]));
    assert_eq!(answers["compact"]["id"], 7);
    assert_eq!(
        answers["compact"]["result"]["object"]["value"],
        json!(["1000", "4500", "8000", "11500", "15000", "18500", "22000", "25500"])
    );
    assert_eq!(answers["register"]["result"], json!({"done": 0}));
    assert_eq!(
        answers["put"]["result"],
        json!({"object": {"mplex": "0x502200"}})
    );
    // NXg §6.3.3: in the last requested language — the portal's get asked for German.
    assert_eq!(
        answers["readonly"]["error"],
        json!({"code": 0x0601_0002, "message": "Versuch, ein nur lesbares Objekt zu schreiben.", "data": "0x652001"})
    );
    assert!(notes.contains(&json!({"jsonrpc": "2.0", "method": "canopen_object", "result": {"mplex": "0x652001", "value": "1"}})));
    assert!(portal.wait().await.unwrap().success());
    running.stop().await;
    sim.stop().await;
}
