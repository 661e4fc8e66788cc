//! Other nodes and networks, EDS metadata, and mutual TLS.

use crate::common;

use canopen::sdo::client::ClientConfig;
use canopen::sdo::clients::SdoClients;
use common::*;
use gateway::config::{Config, NetworkSection, NodeSection, SdoChannel};
use gateway::Gateway;
use lift417::catalog::Device;
use lift417::sim::{export_eds, SimConfig, Simulator};
use serde_json::json;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn eds_metadata_and_a_second_network() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let sim1 = Simulator::start("mem://nodes-1", SimConfig::default())
        .await
        .unwrap();
    let lifts2 = SimConfig {
        io_node: None,
        lifts: 2,
        ..SimConfig::default()
    };
    let sim2 = Simulator::start("mem://nodes-2", lifts2).await.unwrap();
    let eds = dir.path().join("io-node.eds");
    std::fs::write(&eds, export_eds(&SimConfig::default(), Device::Io).unwrap()).unwrap();
    let mut config = config(&portal.url(), &pki, "mem://nodes-1", dir.path());
    config.bus.nodes = vec![NodeSection::with_eds(12, eds)];
    config.networks = vec![NetworkSection {
        net: 2,
        url: "mem://nodes-2".into(),
        nodes: vec![],
    }];
    let gateway = Gateway::bus_node(config).await.unwrap();
    let running = spawn(gateway);
    let (mut ws, ..) = portal.accept().await;
    connack(&mut ws).await;
    let mut notes = Vec::new();
    // Node 12 has an EDS: no datatype needed, names and access from it.
    let get = r#"{"jsonrpc":"2.0","id":1,"method":"get_canopen_object","params":{"node":{"id":12,"net":1},"object":{"mplex":"0x610001"}}}"#;
    let answer = ask(&mut ws, get, &mut notes).await;
    let object = &answer["result"]["object"];
    assert_eq!(object["name"], "Virtual input 1");
    assert_eq!(object["datatype"], 25);
    assert_eq!(object["access"], "ro");
    let missing = get.replace("0x610001", "0x5FFF00");
    assert_eq!(
        ask(&mut ws, &missing, &mut notes).await["error"]["code"],
        0x0602_0000
    );
    // The EDS says read-only: refused without a bus round trip, even with setup rights.
    let elevate = format!(
        r#"{{"jsonrpc":"2.0","id":2,"method":"elevate_privilege","params":{{"sernum":"{SERNUM}","privilege":2,"passhash":"{SETUP_SHA1}"}}}}"#
    );
    assert_eq!(
        ask(&mut ws, &elevate, &mut notes).await["result"],
        json!({"duration": 300})
    );
    let put = format!(
        r#"{{"jsonrpc":"2.0","id":3,"method":"put_canopen_object","params":{{"sernum":"{SERNUM}","node":{{"id":12,"net":1}},"object":{{"mplex":"0x610001","datatype":25,"physunit":0,"value":"1"}}}}}}"#
    );
    assert_eq!(
        ask(&mut ws, &put, &mut notes).await["error"]["code"],
        0x0601_0002
    );
    // Net 2: the lift-2 trip counter of the second controller (at +800h).
    let net2 = r#"{"jsonrpc":"2.0","id":4,"method":"get_canopen_object","params":{"node":{"id":1,"net":2,"datatype":7},"object":{"mplex":"0x6D2001","naked":true}}}"#;
    assert_eq!(
        ask(&mut ws, net2, &mut notes).await["result"],
        json!({"object": {"mplex": "0x6D2001", "value": ["0"]}})
    );
    // Subscriptions on another node are pushed with the node.
    let reg = r#"{"jsonrpc":"2.0","id":5,"method":"reg_canopen_object","params":{"node":{"id":1,"net":2,"datatype":7},"mplex":["0x6D2001"]}}"#;
    assert_eq!(
        ask(&mut ws, reg, &mut notes).await["result"],
        json!({"done": 0})
    );
    while notes.is_empty() {
        notes.push(recv(&mut ws).await);
    }
    assert_eq!(
        notes[0]["result"],
        json!({"mplex": "0x6D2001", "value": "0", "node": {"id": 1, "net": 2}})
    );
    running.stop().await;
    sim1.stop().await;
    sim2.stop().await;
}

/// The simulated controller on `bus`, offering `further` as its SDO server channels 1201h ff.
async fn controller_offering(bus: &str, further: &[SdoChannel]) -> Simulator {
    let config = SimConfig {
        sdo_servers: further.iter().map(SdoChannel::ids).collect(),
        ..SimConfig::default()
    };
    Simulator::start(bus, config).await.unwrap()
}

/// `config` with the controller (node 1) read on `channels`.
fn reading_on(mut config: Config, channels: &[SdoChannel]) -> Config {
    config.bus.nodes = vec![NodeSection {
        sdo_channels: channels.to_vec(),
        ..NodeSection::new(1)
    }];
    config
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_controller_with_further_sdo_channels_is_read_on_all_of_them() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let bus = "mem://nodes-sdo-channels";
    let channel = |request, response| SdoChannel { request, response };
    let channels = [
        channel(0x601, 0x581),
        channel(0x6A1, 0x6C1),
        channel(0x6A2, 0x6C2),
    ];
    let sim = controller_offering(bus, &channels[1..]).await;
    let mut monitor = canbus::Bus::open(bus).await.unwrap();
    let config = reading_on(config(&portal.url(), &pki, bus, dir.path()), &channels);
    let gateway = Gateway::bus_node(config).await.unwrap();
    let running = spawn(gateway);
    let (mut ws, ..) = portal.accept().await;
    connack(&mut ws).await;
    // 24 reads at once of the controller's identity (1018h sub 4 is its node-ID: 1) and
    // device name, every answer checked.
    for i in 0..24 {
        let mplex = if i % 2 == 0 { "0x101804" } else { "0x100800" };
        send(
            &mut ws,
            &format!(
                r#"{{"jsonrpc":"2.0","id":{i},"method":"get_canopen_object","params":{{"object":{{"mplex":"{mplex}","naked":true}}}}}}"#
            ),
        )
        .await;
    }
    let mut answered = 0;
    while answered < 24 {
        let v = recv(&mut ws).await;
        let Some(i) = v["id"].as_u64() else { continue };
        let expected = if i % 2 == 0 {
            json!(["1"])
        } else {
            json!(["canlift simulated lift controller"])
        };
        assert_eq!(v["result"]["object"]["value"], expected, "{v}");
        answered += 1;
    }
    let mut requests = std::collections::BTreeSet::new();
    while let Ok(Some(f)) = tokio::time::timeout(
        std::time::Duration::from_millis(100),
        monitor.receiver.recv_frame(),
    )
    .await
    {
        requests.insert(f.id());
    }
    for (request, _) in channels.iter().map(SdoChannel::ids) {
        assert!(requests.contains(&request), "no request on {request}");
    }
    running.stop().await;
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_channel_closed_on_the_controller_is_set_aside_and_reads_go_on() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let bus = "mem://nodes-sdo-channel-closed";
    let channels = [(0x6A1, 0x6C1), (0x6A2, 0x6C2)]
        .map(|(request, response)| SdoChannel { request, response });
    let sim = controller_offering(bus, &channels).await;
    let mut config = reading_on(config(&portal.url(), &pki, bus, dir.path()), &channels);
    config.bus.sdo_timeout_ms = 100;
    config.bus.sdo_probe_ms = 200;
    let running = spawn(Gateway::bus_node(config).await.unwrap());
    let (mut ws, ..) = portal.accept().await;
    connack(&mut ws).await;
    // The controller's node-ID (1018h sub 4) read through the gateway: whether it answered.
    async fn read(ws: &mut Ws, i: u32) -> bool {
        let request = format!(
            r#"{{"jsonrpc":"2.0","id":{i},"method":"get_canopen_object","params":{{"object":{{"mplex":"0x101804","naked":true}}}}}}"#
        );
        send(ws, &request).await;
        recv(ws).await["result"]["object"]["value"] == json!(["1"])
    }
    assert!(
        read(&mut ws, 0).await && read(&mut ws, 1).await,
        "both channels answer"
    );
    // A service tool on the default channel (the gateway does not use it) closes 1202h as
    // CiA 301 §7.5.2.33 has it.
    let tool = SdoClients::new(
        canbus::Bus::open(bus).await.unwrap(),
        ClientConfig::default(),
    );
    // Twelve reads from `first` on: taken in turn, a channel that closed fails every other
    // one until its third timeout sets it aside.
    async fn set_aside_after_three(ws: &mut Ws, first: u32) {
        let mut answered = Vec::new();
        for i in first..first + 12 {
            answered.push(read(ws, i).await);
        }
        assert_eq!(
            answered.iter().filter(|ok| !**ok).count(),
            3,
            "{answered:?}"
        );
        assert!(answered[6..].iter().all(|ok| *ok), "{answered:?}");
    }
    tool.write::<u32>(1, 0x1202, 1, 0x8000_06A2).await.unwrap();
    set_aside_after_three(&mut ws, 2).await;
    // Opened again, it is asked at the next probe (`sdo_probe_ms`) and back in service; then
    // 1201h closing in turn is set aside too, which needs 1202h serving (a node's last channel
    // in service is never set aside): reads go on.
    tool.write::<u32>(1, 0x1202, 1, 0x06A2).await.unwrap();
    tokio::time::sleep(std::time::Duration::from_secs(2)).await;
    tool.write::<u32>(1, 0x1201, 1, 0x8000_06A1).await.unwrap();
    set_aside_after_three(&mut ws, 14).await;
    running.stop().await;
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_configured_sdo_channel_the_node_does_not_serve_is_named_once_it_answers() {
    let bus = "mem://nodes-sdo-channels-checked";
    let id = canbus::CanId::Standard;
    let config = ClientConfig {
        timeout: std::time::Duration::from_millis(100),
        ..ClientConfig::default()
    };
    let channels = [(0x601, 0x581), (0x6A1, 0x6C1), (0x6A2, 0x6C2)]
        .map(|(request, response)| (1, id(request), id(response)));
    let sdo = SdoClients::with_channels(canbus::Bus::open(bus).await.unwrap(), config, &channels);
    // Nobody answers yet (the controller has not booted): asked again until it does.
    let check = tokio::spawn(gateway::supervision::check_sdo_channels(
        sdo,
        1,
        1,
        std::time::Duration::from_millis(100),
    ));
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    assert!(
        !check.is_finished(),
        "named channels of a node that is not there"
    );
    let offered = SdoChannel {
        request: 0x6A1,
        response: 0x6C1,
    };
    let sim = controller_offering(bus, &[offered]).await;
    let silent = tokio::time::timeout(WAIT, check).await.unwrap().unwrap();
    assert_eq!(silent, vec![(id(0x6A2), id(0x6C2))]);
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_needs_the_client_certificate() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start_with(&pki, true).await;
    let sim = Simulator::start("mem://mtls", SimConfig::default())
        .await
        .unwrap();
    // Without a client certificate the handshake fails.
    let config = config(&portal.url(), &pki, "mem://mtls", dir.path());
    let gateway = Gateway::bus_node(config.clone()).await.unwrap();
    let running = spawn(gateway);
    assert!(!portal.try_tls().await, "no client certificate, no TLS");
    running.stop().await;
    // With it the gateway gets through to CONNECT.
    let mut config = config;
    config.cloud.client_cert = Some(pki.client_cert.clone());
    config.cloud.client_key = Some(pki.client_key.clone());
    let gateway = Gateway::bus_node(config).await.unwrap();
    let running = spawn(gateway);
    let (mut ws, ..) = portal.accept().await;
    connack(&mut ws).await;
    running.stop().await;
    sim.stop().await;
}

/// Device descriptions with the defects found in public files (tests/fixtures/eds-defects):
/// the gateway starts, serves every object they describe well, and answers for what they left
/// out as for an object the node does not have.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn defective_device_descriptions_are_served_where_they_are_well_described() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let portal = Portal::start(&pki).await;
    let bus = "mem://nodes-defects";
    let sim = Simulator::start(bus, SimConfig::default()).await.unwrap();
    let fixtures = testkit::workspace().join("tests/fixtures/eds-defects");
    let files = [
        (20, "visible-string-default.eds"),
        (21, "object-count.eds"),
        (22, "domain-default.eds"),
        (23, "subnumber-type.eds"),
        (24, "sub7.dcf"),
        (25, "windows-1252.eds"),
    ];
    let mut devices = Vec::new();
    let mut config = config(&portal.url(), &pki, bus, dir.path());
    for (id, name) in files {
        let path = fixtures.join(name);
        // The device itself: what the file describes (a real one would have the rest too).
        let od = canopen::eds::import_file(&path, Some(id))
            .unwrap()
            .description
            .od;
        let bus = canbus::Bus::open(bus).await.unwrap();
        devices.push(canopen::node::LocalNode::start(
            bus,
            od,
            canopen::node::NodeConfig::new(id),
        ));
        config.bus.nodes.push(NodeSection::with_eds(id, path));
    }
    let gateway = Gateway::bus_node(config)
        .await
        .expect("the gateway starts with every file");
    let running = spawn(gateway);
    let (mut ws, ..) = portal.accept().await;
    connack(&mut ws).await;
    let mut notes = Vec::new();
    let get = |id: u8, mplex: &str| {
        format!(
            r#"{{"jsonrpc":"2.0","id":1,"method":"get_canopen_object","params":{{"node":{{"id":{id},"net":1}},"object":{{"mplex":"{mplex}"}}}}}}"#
        )
    };
    for (id, _) in files {
        let answer = ask(&mut ws, &get(id, "0x200000"), &mut notes).await;
        let object = &answer["result"]["object"];
        assert_eq!(object["value"], json!(["4660"]), "node {id}: {answer}");
        assert_eq!(object["name"], "Well described", "node {id}");
        assert_eq!(object["access"], "rw", "node {id}");
    }
    // Served although a part of their file was defective.
    for (id, mplex, name) in [
        (20, "0x100800", "Manufacturer device name"),
        (22, "0x210000", "Program data"),
        (23, "0x220002", "Setting 2"),
        (24, "0x1F5107", "Program control 7"),
        (25, "0x240000", "Türzustand – Schließen"),
    ] {
        let answer = ask(&mut ws, &get(id, mplex), &mut notes).await;
        assert_eq!(
            answer["result"]["object"]["name"], name,
            "node {id}: {answer}"
        );
    }
    // NXg §6.1.1: a string's "max" is its count of characters — for the controller's constant
    // 1008h, the characters it holds.
    let name = ask(
        &mut ws,
        r#"{"jsonrpc":"2.0","id":1,"method":"get_canopen_object","params":{"object":{"mplex":"0x100800"}}}"#,
        &mut notes,
    )
    .await;
    let object = &name["result"]["object"];
    let chars = object["value"][0].as_str().map(|v| v.chars().count());
    assert!(chars.is_some_and(|n| n > 0), "{name}");
    assert_eq!(object["max"].as_u64(), chars.map(|n| n as u64), "{name}");
    // Left out: answered as an object the node does not have, never asked on the bus.
    for (id, mplex) in [(21, "0x200100"), (23, "0x230000")] {
        let answer = ask(&mut ws, &get(id, mplex), &mut notes).await;
        assert_eq!(answer["error"]["code"], 0x0602_0000, "node {id}: {answer}");
    }
    running.stop().await;
    sim.stop().await;
}
