//! `LocalNode` and `Master` together on an in-process bus.

use std::time::Duration;

use canbus::{Bus, CanId};
use canopen::heartbeat::{HeartbeatEvent, NodeState};
use canopen::master::{Master, MasterEvent};
use canopen::nmt::{NmtCommand, NmtState};
use canopen::node::{wait_event, LocalNode, NodeConfig, NodeEvent};
use canopen::od::ObjectDictionary;
use canopen::sdo::abort::AbortCode;
use canopen::types::Value;
use testkit::sample::{self, POSITION, SETPOINT, TRIPS};
use tokio::sync::broadcast;

use crate::common;

use common::{client_config, master_event, WAIT};

async fn setup(url: &str, node_id: u8) -> (Master, broadcast::Receiver<MasterEvent>, LocalNode) {
    let master = Master::open(url, client_config()).await.unwrap();
    let events = master.events();
    let config = NodeConfig {
        heartbeat_ms: 50,
        software_version: "01.23.10".into(),
        identity: [0x41A, 0x1000, 1, 0x0001_0203],
        ..NodeConfig::new(node_id)
    };
    let node = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        config,
    );
    (master, events, node)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn boot_nmt_heartbeat_and_sdo_gating() {
    let (master, mut events, node) = setup("mem://node-nmt", 1).await;
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 1,
                new: NodeState::BootUp,
                ..
            })
        )
    })
    .await;
    node.wait_for_state(NmtState::PreOperational).await;
    let sdo = master.sdo();
    assert_eq!(sdo.read::<String>(1, 0x100A, 0).await.unwrap(), "01.23.10");
    assert_eq!(sdo.read::<u32>(1, 0x1018, 4).await.unwrap(), 0x0001_0203);
    assert_eq!(sdo.read::<u32>(1, 0x1200, 1).await.unwrap(), 0x601);

    master.nmt(NmtCommand::Start, 1).await.unwrap();
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 1,
                new: NodeState::Operational,
                ..
            })
        )
    })
    .await;
    assert_eq!(node.nmt_state(), NmtState::Operational);

    // Stopped: SDO is not served (the client times out), heartbeat goes on.
    master.nmt(NmtCommand::Stop, 0).await.unwrap();
    node.wait_for_state(NmtState::Stopped).await;
    let err = sdo.read_raw(1, 0x1000, 0).await.unwrap_err();
    assert_eq!(err.abort_code(), AbortCode::TIMEOUT);
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 1,
                new: NodeState::Stopped,
                ..
            })
        )
    })
    .await;

    // Reset communication restores 0x1017 and boots again.
    master
        .nmt(NmtCommand::EnterPreOperational, 1)
        .await
        .unwrap();
    node.wait_for_state(NmtState::PreOperational).await;
    sdo.write(1, 0x1017, 0, 20u16).await.unwrap();
    master.nmt(NmtCommand::ResetCommunication, 1).await.unwrap();
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 1,
                new: NodeState::BootUp,
                ..
            })
        )
    })
    .await;
    node.wait_for_state(NmtState::PreOperational).await;
    assert_eq!(sdo.read::<u16>(1, 0x1017, 0).await.unwrap(), 50);

    // Heartbeat monitoring: the node disappears, the master notices within its timeout.
    master.monitor(1, Duration::from_millis(200));
    node.stop().await;
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::Timeout { node: 1 })
        )
    })
    .await;
    assert_eq!(master.node_state(1), NodeState::Offline);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn emcy_register_and_history() {
    let (master, mut events, node) = setup("mem://node-emcy", 2).await;
    node.wait_for_state(NmtState::PreOperational).await;
    node.set_error(0x4210, [1, 2, 3, 4, 5]);
    let e = master_event(&mut events, |e| {
        matches!(e, MasterEvent::Emcy { node: 2, .. })
    })
    .await;
    let MasterEvent::Emcy { message, .. } = e else {
        unreachable!()
    };
    assert_eq!(
        (message.code, message.register, message.manufacturer),
        (0x4210, 0x09, [1, 2, 3, 4, 5])
    );
    let sdo = master.sdo();
    assert_eq!(sdo.read::<u8>(2, 0x1001, 0).await.unwrap(), 0x09);
    assert_eq!(sdo.read::<u8>(2, 0x1003, 0).await.unwrap(), 1);
    assert_eq!(sdo.read::<u32>(2, 0x1003, 1).await.unwrap(), 0x0201_4210);
    node.clear_error(0x4210);
    let e = master_event(&mut events, |e| {
        matches!(e, MasterEvent::Emcy { node: 2, .. })
    })
    .await;
    let MasterEvent::Emcy { message, .. } = e else {
        unreachable!()
    };
    assert_eq!((message.code, message.register), (0, 0), "error reset");
    assert_eq!(sdo.read::<u8>(2, 0x1001, 0).await.unwrap(), 0);
    // The history stays until cleared by writing 0; other values are refused.
    assert_eq!(sdo.read::<u8>(2, 0x1003, 0).await.unwrap(), 1);
    let err = sdo.write(2, 0x1003, 0, 1u8).await.unwrap_err();
    assert_eq!(err.abort_code(), AbortCode::INVALID_VALUE);
    sdo.write(2, 0x1003, 0, 0u8).await.unwrap();
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(sdo.read::<u32>(2, 0x1003, 1).await.unwrap(), 0);
    // Inhibit time from 0x1015: two errors 100 ms apart at least.
    sdo.write(2, 0x1015, 0, 1000u16).await.unwrap();
    let mut raw = Bus::open("mem://node-emcy").await.unwrap();
    raw.receiver
        .set_filters(&[canbus::Filter::standard(0x82, 0x7FF)]);
    node.set_error(0x1000, [0; 5]);
    node.set_error(0x2000, [0; 5]);
    let first = raw.receiver.recv_frame().await.unwrap();
    let second = raw.receiver.recv_frame().await.unwrap();
    let gap = second
        .timestamp()
        .unwrap()
        .duration_since(first.timestamp().unwrap())
        .unwrap();
    assert!(
        gap >= Duration::from_millis(95),
        "inhibit time respected: {gap:?}"
    );
    node.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn node_consumes_heartbeats_and_raises_8130() {
    let url = "mem://node-consumer";
    let (master, mut events, watcher) = setup(url, 3).await;
    let mut watcher_events = watcher.events();
    watcher.wait_for_state(NmtState::PreOperational).await;
    // Node 3 monitors node 7 with 150 ms through 0x1016 sub 1.
    master
        .sdo()
        .write(3, 0x1016, 1, 0x0007_0096u32)
        .await
        .unwrap();
    let config = NodeConfig {
        heartbeat_ms: 50,
        ..NodeConfig::new(7)
    };
    let seven = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        config,
    );
    wait_event(&mut watcher_events, WAIT, |e| {
        matches!(
            e,
            NodeEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 7,
                new: NodeState::PreOperational,
                ..
            })
        )
    })
    .await
    .expect("node 7 seen");
    seven.stop().await;
    let e = master_event(&mut events, |e| {
        matches!(e, MasterEvent::Emcy { node: 3, .. })
    })
    .await;
    let MasterEvent::Emcy { message, .. } = e else {
        unreachable!()
    };
    assert_eq!(
        (message.code, message.manufacturer),
        (0x8130, [0, 7, 0, 0, 0])
    );
    assert_eq!(watcher.value(0x1001, 0).unwrap(), Value::Uint(0x11));
    // Node 7 comes back: the error is cleared.
    let seven = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        NodeConfig {
            heartbeat_ms: 50,
            ..NodeConfig::new(7)
        },
    );
    let e = master_event(&mut events, |e| {
        matches!(e, MasterEvent::Emcy { node: 3, .. })
    })
    .await;
    let MasterEvent::Emcy { message, .. } = e else {
        unreachable!()
    };
    assert_eq!(message.code, 0, "error reset when node 7 is heard again");
    seven.stop().await;
    watcher.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sync_producer_configured_by_sdo() {
    let url = "mem://node-sync";
    let (master, _events, node) = setup(url, 4).await;
    node.wait_for_state(NmtState::PreOperational).await;
    let mut raw = Bus::open(url).await.unwrap();
    raw.receiver
        .set_filters(&[canbus::Filter::standard(0x80, 0x7FF)]);
    let sdo = master.sdo();
    sdo.write(4, 0x1019, 0, 3u8).await.unwrap();
    sdo.write(4, 0x1006, 0, 20_000u32).await.unwrap();
    sdo.write(4, 0x1005, 0, 0x4000_0080u32).await.unwrap();
    let mut counters = Vec::new();
    for _ in 0..5 {
        let f = tokio::time::timeout(WAIT, raw.receiver.recv_frame())
            .await
            .unwrap()
            .unwrap();
        assert_eq!(f.id(), CanId::Standard(0x80));
        counters.push(f.data()[0]);
    }
    // Production starts with the 0x1005 write; the counter runs 1..=3 and wraps.
    assert_eq!(counters, vec![1, 2, 3, 1, 2]);
    node.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn configured_pdos_carry_dictionary_changes() {
    use canopen::node::PdoSetup;
    let url = "mem://node-pdo";
    let od = sample::dictionary();
    let node = LocalNode::start(Bus::open(url).await.unwrap(), od, NodeConfig::new(6));
    node.wait_for_state(NmtState::PreOperational).await;
    node.configure_pdo(&PdoSetup {
        transmit: true,
        number: 1,
        cob_id: 0x186,
        objects: vec![(POSITION, 0)],
        transmission_type: 254,
        inhibit_100us: 0,
        event_ms: 0,
    })
    .unwrap();
    node.configure_pdo(&PdoSetup {
        transmit: false,
        number: 1,
        cob_id: 0x206,
        objects: vec![(SETPOINT, 0)],
        transmission_type: 255,
        inhibit_100us: 0,
        event_ms: 0,
    })
    .unwrap();
    let mut peer = Bus::open(url).await.unwrap();
    peer.receiver
        .set_filters(&[canbus::Filter::standard(0x186, 0x7FF)]);
    node.nmt(NmtCommand::Start);
    node.wait_for_state(NmtState::Operational).await;
    let first = tokio::time::timeout(WAIT, peer.receiver.recv_frame())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(
        first.data(),
        &[0, 0],
        "current value on entering operational"
    );
    node.set_value(POSITION, 0, &Value::Uint(1234)).unwrap();
    let f = tokio::time::timeout(WAIT, peer.receiver.recv_frame())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(f.data(), &1234u16.to_le_bytes());
    peer.send(canbus::Frame::standard(0x206, &4321u32.to_le_bytes()).unwrap())
        .await
        .unwrap();
    let mut stored = Value::Uint(0);
    for _ in 0..500 {
        stored = node.value(SETPOINT, 0).unwrap();
        if stored == Value::Uint(4321) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(stored, Value::Uint(4321));
    node.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stored_parameters_survive_restarts_and_resets() {
    let url = "mem://node-storage";
    let dir = testkit::scratch();
    let path = dir.path().join("node8.params");
    let make = || {
        let od = sample::dictionary();
        let config = NodeConfig {
            storage: Some(path.clone()),
            ..NodeConfig::new(8)
        };
        (od, config)
    };
    let master = Master::open(url, client_config()).await.unwrap();
    let (od, config) = make();
    let node = LocalNode::start(Bus::open(url).await.unwrap(), od, config);
    node.wait_for_state(NmtState::PreOperational).await;
    node.set_value(TRIPS, 0, &Value::Uint(1001)).unwrap();
    master.sdo().write(8, 0x1017, 0, 250u16).await.unwrap();
    let err = master
        .sdo()
        .write(8, 0x1010, 1, 0x1234u32)
        .await
        .unwrap_err();
    assert_eq!(err.abort_code(), AbortCode::CANNOT_STORE, "wrong signature");
    master.sdo().write_raw(8, 0x1010, 1, b"save").await.unwrap();
    assert_eq!(master.sdo().read::<u32>(8, 0x1010, 1).await.unwrap(), 1);
    node.stop().await;

    // Restart: the stored values are back.
    let (od, config) = make();
    let node = LocalNode::start(Bus::open(url).await.unwrap(), od, config);
    node.wait_for_state(NmtState::PreOperational).await;
    assert_eq!(node.value(TRIPS, 0).unwrap(), Value::Uint(1001));
    assert_eq!(master.sdo().read::<u16>(8, 0x1017, 0).await.unwrap(), 250);
    // Reset node returns to the stored values, not to what was changed since.
    // Each reset is over when the node's boot-up is on the bus (CiA 301 §7.2.8.3.3): an SDO
    // request sent before could reach the node while it resets.
    let mut boot_ups = Bus::open(url).await.unwrap();
    boot_ups
        .receiver
        .set_filters(&[canbus::Filter::standard(0x708, 0x7FF)]);
    master.sdo().write(8, 0x1017, 0, 100u16).await.unwrap();
    master.nmt(NmtCommand::ResetNode, 8).await.unwrap();
    booted(&mut boot_ups).await;
    assert_eq!(master.sdo().read::<u16>(8, 0x1017, 0).await.unwrap(), 250);
    // Restore defaults of the communication parameters; they apply at the next reset.
    master.sdo().write_raw(8, 0x1011, 2, b"load").await.unwrap();
    master.nmt(NmtCommand::ResetCommunication, 8).await.unwrap();
    booted(&mut boot_ups).await;
    assert_eq!(master.sdo().read::<u16>(8, 0x1017, 0).await.unwrap(), 0);
    assert_eq!(node.value(TRIPS, 0).unwrap(), Value::Uint(1001));
    node.stop().await;
}

/// Wait for the next boot-up message `bus` receives (its filters pick the node), past the
/// node's heartbeats.
async fn booted(bus: &mut Bus) {
    tokio::time::timeout(WAIT, async {
        while let Some(frame) = bus.receiver.recv_frame().await {
            if frame.data() == [0x00] {
                return;
            }
        }
        panic!("the bus closed");
    })
    .await
    .expect("a boot-up in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn node_guarding_and_life_guarding() {
    use canopen::guarding::GuardEvent;
    let (master, mut events, node) = setup("mem://node-guarding", 9).await;
    let mut node_events = node.events();
    node.wait_for_state(NmtState::PreOperational).await;
    master.sdo().write(9, 0x100C, 0, 50u16).await.unwrap();
    master.sdo().write(9, 0x100D, 0, 3u8).await.unwrap();
    master.guard(9, Duration::from_millis(50), 3);
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Guarding(GuardEvent::StateChanged {
                node: 9,
                state: NmtState::PreOperational
            })
        )
    })
    .await;
    // The master stops guarding: the node's life guarding runs out (150 ms) and raises 0x8130.
    master.guard(9, Duration::ZERO, 0);
    wait_event(&mut node_events, WAIT, |e| {
        matches!(e, NodeEvent::Guarding(GuardEvent::LifeGuardingLost))
    })
    .await
    .expect("life guarding lost");
    let e = master_event(&mut events, |e| {
        matches!(e, MasterEvent::Emcy { node: 9, .. })
    })
    .await;
    let MasterEvent::Emcy { message, .. } = e else {
        unreachable!()
    };
    assert_eq!(message.code, 0x8130);
    // Guarding again: resumed, error reset; then the node disappears and the master notices.
    master.guard(9, Duration::from_millis(50), 3);
    wait_event(&mut node_events, WAIT, |e| {
        matches!(e, NodeEvent::Guarding(GuardEvent::LifeGuardingResumed))
    })
    .await
    .expect("life guarding resumed");
    node.stop().await;
    master_event(&mut events, |e| {
        matches!(e, MasterEvent::Guarding(GuardEvent::NodeLost { node: 9 }))
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn time_producer_and_consumer() {
    let url = "mem://node-time";
    let (master, _events, producer) = setup(url, 11).await;
    let consumer = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        NodeConfig::new(12),
    );
    let mut consumed = consumer.events();
    producer.wait_for_state(NmtState::PreOperational).await;
    consumer.wait_for_state(NmtState::PreOperational).await;
    master
        .sdo()
        .write(11, 0x1012, 0, 0x4000_0100u32)
        .await
        .unwrap(); // producer
    master
        .sdo()
        .write(12, 0x1012, 0, 0x8000_0100u32)
        .await
        .unwrap(); // consumer
    let at = std::time::UNIX_EPOCH + Duration::from_millis(1_704_112_496_789);
    producer.send_time(at);
    let e = wait_event(&mut consumed, WAIT, |e| matches!(e, NodeEvent::Time(_)))
        .await
        .unwrap();
    assert_eq!(e, NodeEvent::Time(at));
    producer.stop().await;
    consumer.stop().await;
}
