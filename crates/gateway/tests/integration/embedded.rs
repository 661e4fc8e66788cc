//! Embedded mode: a controller written in Rust hands the gateway its own dictionary; reads and
//! writes are local and changes notify without polling.

use crate::common;

use std::sync::{Arc, Mutex};

use canopen::types::Value as CoValue;
use common::*;
use gateway::Gateway;
use lift417::catalog::{Catalog, Device};
use serde_json::json;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_the_controllers_own_dictionary() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let od = Catalog::builtin()
        .dictionary(Device::Controller, 1, 8)
        .unwrap();
    let od = Arc::new(Mutex::new(od));
    od.lock()
        .unwrap()
        .set_value(0x6520, 1, &CoValue::Uint(2510))
        .unwrap();
    od.lock().unwrap().insert(canopen::od::Object::var(
        0x2F00,
        canopen::od::Variable::new(
            "Door hold time",
            canopen::types::DataType::Unsigned16,
            canopen::od::Access::Rw,
        )
        .with_value(CoValue::Uint(30)),
    ));
    let config = config(&portal.url(), &pki, "mem://unused", dir.path());
    let gateway = Gateway::embedded(config, od.clone()).unwrap();
    let running = spawn(gateway);
    let (mut ws, ..) = portal.accept().await;
    connack(&mut ws).await;
    let mut notes = Vec::new();
    let naked = r#"{"jsonrpc":"2.0","id":1,"method":"get_canopen_object","params":{"object":{"mplex":"0x652001","naked":true}}}"#;
    assert_eq!(
        ask(&mut ws, naked, &mut notes).await["result"],
        json!({"object": {"mplex": "0x652001", "value": ["2510"]}})
    );
    let reg = r#"{"jsonrpc":"2.0","id":2,"method":"reg_canopen_object","params":{"mplex":["0x652001"],"threshold":1}}"#;
    assert_eq!(
        ask(&mut ws, reg, &mut notes).await["result"],
        json!({"done": 0})
    );
    // The baseline push, then the controller counts a trip: pushed at once.
    while notes.is_empty() {
        notes.push(recv(&mut ws).await);
    }
    assert_eq!(
        notes[0]["result"],
        json!({"mplex": "0x652001", "value": "2510"})
    );
    od.lock()
        .unwrap()
        .set_value(0x6520, 1, &CoValue::Uint(2511))
        .unwrap();
    let pushed = recv(&mut ws).await;
    assert_eq!(
        pushed["result"],
        json!({"mplex": "0x652001", "value": "2511"})
    );
    // A put lands in the dictionary.
    let put = format!(
        r#"{{"jsonrpc":"2.0","id":3,"method":"put_canopen_object","params":{{"sernum":"{SERNUM}","object":{{"mplex":"0x502200","datatype":7,"physunit":0,"value":"6"}}}}}}"#
    );
    assert_eq!(
        ask(&mut ws, &put, &mut notes).await["result"]["object"]["mplex"],
        "0x502200"
    );
    assert_eq!(
        od.lock().unwrap().get_value(0x5022, 0),
        Ok(CoValue::Uint(6))
    );
    // The dictionary says what exists: a vendor object of its own is described by its name,
    // a catalog object it lacks does not exist.
    let get = |mplex: &str| {
        format!(
            r#"{{"jsonrpc":"2.0","id":4,"method":"get_canopen_object","params":{{"object":{{"mplex":"{mplex}"}}}}}}"#
        )
    };
    let own = ask(&mut ws, &get("0x2F0000"), &mut notes).await;
    assert_eq!(own["result"]["object"]["name"], "Door hold time", "{own}");
    assert_eq!(own["result"]["object"]["value"], json!(["30"]));
    let lacking = ask(&mut ws, &get("0x6D2001"), &mut notes).await;
    assert_eq!(
        lacking["error"]["code"], 0x0602_0000,
        "lift 2's counter: {lacking}"
    );
    running.stop().await;
}
