//! Bus events over the connector (docs/PROTOCOL.md §Events): the gateway in bus-node
//! mode through the hub in front of the simulated lift and an independent node (a python-canopen
//! LocalNode, 200 ms heartbeat), a scripted portal registering for events.

use crate::common;

use std::time::Duration;

use canbus::Bus;
use canopen::sdo::client::ClientConfig;
use canopen::sdo::clients::SdoClients;
use common::*;
use gateway::Gateway;
use serde_json::{json, Value};
use testkit::script::Script;
use testkit::scripted::{connack_api, recv_within};

/// The independent node.
const PYTHON: u8 = 5;

/// A python-canopen node from the test controller's EDS, heartbeat 200 ms, running once READY.
async fn python_node(python: &std::path::Path, hub: &canbus::hub::HubHandle) -> Script {
    let addr = hub.local_addr();
    let eds = testkit::workspace().join("tests/fixtures/controller.eds");
    let args = [
        "--heartbeat".to_owned(),
        "200".to_owned(),
        addr.ip().to_string(),
        addr.port().to_string(),
        eds.display().to_string(),
        PYTHON.to_string(),
    ];
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let node = Script::start(python, "controller.py", &args);
    node.wait_for("READY", 1, WAIT).await;
    node
}

fn request(id: &str, method: &str, params: Value) -> String {
    json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params}).to_string()
}

fn register(lang: &str) -> String {
    request(
        "reg",
        "reg_canopen_event",
        json!({"events": ["emcy", "state", "bus"],
               "lang": {"preferred_language": lang, "alternate_language": "en"}}),
    )
}

/// Events until one matches `wanted` (within `wait`); all seen on the way, the match last.
async fn until(ws: &mut Ws, wait: Duration, wanted: impl Fn(&Value) -> bool) -> Vec<Value> {
    let deadline = tokio::time::Instant::now() + wait;
    let mut seen = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        let Some(message) = recv_within(ws, left).await else {
            panic!("not seen within {wait:?}; seen: {seen:#?}");
        };
        if message["method"] != "canopen_event" {
            continue;
        }
        let event = message["result"]["event"].clone();
        let done = wanted(&event);
        seen.push(event);
        if done {
            return seen;
        }
    }
}

fn is_state(node: u8, state: &'static str) -> impl Fn(&Value) -> bool {
    move |e| e["type"] == "state" && e["node"]["id"] == node && e["state"] == state
}

fn is_emcy(code: &'static str) -> impl Fn(&Value) -> bool {
    move |e| e["type"] == "emcy" && e["code"] == code
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn faults_and_silence_reach_the_portal_in_order_even_after_a_gap() {
    let Some(python) = testkit::python() else {
        return;
    };
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let sim = testkit::lift::simulator(&bus).await;
    let mut node = python_node(&python, &hub).await;
    let mut config = config(&portal.url(), &pki, &bus, dir.path());
    // The simulator's heartbeat period given, so the gateway does not read node 1's 1017h by
    // SDO while the test's own client below writes to node 1: two clients' frames would mix on
    // node 1's one SDO channel (CiA 301: one client per channel).
    config.bus.nodes.push(gateway::config::NodeSection {
        heartbeat_ms: Some(lift417::sim::SimConfig::default().heartbeat_ms),
        ..gateway::config::NodeSection::new(1)
    });
    let running = spawn(Gateway::bus_node(config).await.unwrap());
    // A direct SDO client for fault injection while the portal is away.
    let sdo = SdoClients::new(Bus::open(&bus).await.unwrap(), ClientConfig::default());

    // NXg api 1 agreed, the events served all the same; they wait for the registration.
    let (mut ws, ..) = portal.accept().await;
    let connect = connack_api(&mut ws, 1).await;
    assert_eq!(connect["params"]["identity"]["api"], 1);
    assert_eq!(
        recv_within(&mut ws, Duration::from_millis(500)).await,
        None,
        "nothing unsolicited"
    );
    let answer = ask(&mut ws, &register("de"), &mut Vec::new()).await;
    assert_eq!(answer["result"], json!({"done": 0}));
    // The nodes heard since the start: the python node is supervised with its 1017h.
    until(&mut ws, WAIT, is_state(PYTHON, "operational")).await;

    // A fault in the simulator (a drive fault): EMCY with code, register and the German text.
    sdo.write(1, 0x5030, 0, 4u8).await.unwrap();
    let seen = until(&mut ws, WAIT, is_emcy("0xF001")).await;
    let emcy = seen.last().unwrap();
    assert_eq!(emcy["node"], json!({"id": 1, "net": 1}));
    assert_eq!(emcy["text"], "Antriebsstörung: Schnellhalt");
    assert!(emcy["register"].as_str().unwrap().starts_with("0x"));
    assert!(nxg::msg::parse_time(emcy["time"].as_str().unwrap()).is_some());
    // English from now on; the fault cleared is the error reset.
    ask(&mut ws, &register("en"), &mut Vec::new()).await;
    sdo.write(1, 0x5030, 0, 0u8).await.unwrap();
    let seen = until(&mut ws, WAIT, is_emcy("0x0000")).await;
    assert_eq!(seen.last().unwrap()["text"], "Error reset or no error");

    // The independent node dies: offline within 2 s (1.5 × 200 ms after its last heartbeat).
    node.kill().await;
    let died = std::time::Instant::now();
    until(&mut ws, WAIT, is_state(PYTHON, "offline")).await;
    assert!(
        died.elapsed() < Duration::from_secs(2),
        "{:?}",
        died.elapsed()
    );
    // It comes back: boot-up.
    let mut node = python_node(&python, &hub).await;
    until(&mut ws, WAIT, is_state(PYTHON, "boot-up")).await;

    // The portal goes away; meanwhile a fault comes and goes and the node dies again.
    drop(ws);
    sdo.write(1, 0x5030, 0, 2u8).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    node.kill().await;
    tokio::time::sleep(Duration::from_millis(600)).await;
    sdo.write(1, 0x5030, 0, 0u8).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    // Back: after the registration, what happened in between, in order.
    let (mut ws, ..) = portal.accept().await;
    connack_api(&mut ws, 1).await;
    ask(&mut ws, &register("en"), &mut Vec::new()).await;
    let seen = until(&mut ws, WAIT, is_emcy("0x0000")).await;
    let position = |wanted: &dyn Fn(&Value) -> bool| seen.iter().position(wanted);
    let overload = position(&is_emcy("0xFF04")).expect("the overload");
    let offline = position(&is_state(PYTHON, "offline")).expect("the node's silence");
    assert!(overload < offline && offline < seen.len() - 1, "{seen:#?}");
    assert_eq!(seen[overload]["text"], "Overload");
    let times: Vec<i64> = seen
        .iter()
        .map(|e| nxg::msg::parse_time(e["time"].as_str().unwrap()).unwrap())
        .collect();
    assert!(times.windows(2).all(|w| w[0] <= w[1]), "{times:?}");

    // An NXg portal that never calls reg_canopen_event sees nothing it did not ask for.
    drop(ws);
    let (mut ws, ..) = portal.accept().await;
    connack_api(&mut ws, 1).await;
    // What the gateway reads of node 1 as a portal connects is done before this test's own
    // client takes node 1's one SDO channel (CiA 301: one client per channel).
    tokio::time::sleep(Duration::from_millis(500)).await;
    sdo.write(1, 0x5030, 0, 1u8).await.unwrap();
    assert_eq!(
        recv_within(&mut ws, Duration::from_millis(800)).await,
        None,
        "a portal that did not register sees no event"
    );
    sdo.write(1, 0x5030, 0, 0u8).await.unwrap();

    running.stop().await;
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_networks_state_from_error_frames_and_the_link() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    // Net 1 through the hub (its link can go down), net 2 in-process (error frames).
    let hub = testkit::hub().await;
    let addr = hub.local_addr();
    let mut config = config(
        &portal.url(),
        &pki,
        &testkit::hub_url(&hub, "can0"),
        dir.path(),
    );
    config.networks.push(gateway::config::NetworkSection {
        net: 2,
        url: "mem://events-net2".into(),
        nodes: Vec::new(),
    });
    let running = spawn(Gateway::bus_node(config).await.unwrap());
    let (mut ws, ..) = portal.accept().await;
    connack_api(&mut ws, 1).await;
    let reg = request("r", "reg_canopen_event", json!({"events": ["bus"]}));
    ask(&mut ws, &reg, &mut Vec::new()).await;
    let is_bus = |net: u8, state: &'static str| {
        move |e: &Value| e["type"] == "bus" && e["net"] == net && e["state"] == state
    };
    // Error frames (SocketCAN classes): error-passive, bus-off, restarted.
    let net2 = Bus::open("mem://events-net2").await.unwrap();
    let passive = canbus::Frame::error(0x04, &[0, 0x10]).unwrap();
    net2.send(passive).await.unwrap();
    until(&mut ws, WAIT, is_bus(2, "error-passive")).await;
    net2.send(canbus::Frame::error(0x40, &[]).unwrap())
        .await
        .unwrap();
    until(&mut ws, WAIT, is_bus(2, "bus-off")).await;
    net2.send(canbus::Frame::error(0x100, &[]).unwrap())
        .await
        .unwrap();
    until(&mut ws, WAIT, is_bus(2, "error-active")).await;
    // The hub goes away and comes back on the same port.
    hub.shutdown().await;
    until(&mut ws, WAIT, is_bus(1, "offline")).await;
    let back = canbus::hub::Hub::bind(canbus::hub::HubConfig {
        listen: addr,
        ..canbus::hub::HubConfig::default()
    })
    .await
    .unwrap()
    .spawn()
    .unwrap();
    until(&mut ws, Duration::from_secs(20), is_bus(1, "error-active")).await;
    running.stop().await;
    back.shutdown().await;
}
