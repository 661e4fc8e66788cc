//! LSS between `Master` and `LocalNode`s. Fastscan steps are timed: under cargo-nextest these
//! tests run with no other beside them (.config/nextest.toml).

use std::time::Duration;

use canbus::Bus;
use canopen::heartbeat::{HeartbeatEvent, NodeState};
use canopen::master::{Master, MasterEvent};
use canopen::nmt::{NmtCommand, NmtState};
use canopen::node::{LocalNode, NodeConfig};
use canopen::od::ObjectDictionary;

use crate::common;

use common::{client_config, master_event};

/// Fastscan step time for the test: an in-process bus answers in well under a millisecond, but
/// a loaded machine may not run the nodes' tasks for tens of milliseconds, and a late answer
/// is taken for no answer. Every scan of the test uses it.
const STEP: Duration = Duration::from_millis(50);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lss_fastscan_configures_unconfigured_nodes() {
    let url = "mem://node-lss";
    let dir = testkit::scratch();
    let storage = |serial: u32| dir.path().join(format!("node-{serial}.params"));
    let config = |serial: u32| NodeConfig {
        identity: [0x41A, 0x1000, 1, serial],
        storage: Some(storage(serial)),
        ..NodeConfig::new(canopen::lss::UNCONFIGURED)
    };
    let master = Master::open(url, client_config()).await.unwrap();
    let mut events = master.events();
    let a = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        config(0x500),
    );
    let b = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        config(0x400),
    );
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(
        a.nmt_state(),
        NmtState::Initialising,
        "silent without a node-ID"
    );

    for (serial, id) in [(0x400u32, 20u8), (0x500, 21)] {
        let found = master
            .lss_fastscan_with_step(STEP)
            .await
            .unwrap()
            .expect("an unconfigured node");
        assert_eq!(found, [0x41A, 0x1000, 1, serial], "lowest address first");
        assert_eq!(
            master.lss_inquire_node_id().await.unwrap(),
            canopen::lss::UNCONFIGURED
        );
        master.lss_configure_node_id(id).await.unwrap();
        master.lss_store().await.unwrap();
        master.lss_switch_global(false).await.unwrap();
        master_event(&mut events, |e| {
            matches!(e, MasterEvent::Heartbeat(HeartbeatEvent::StateChanged { node, new: NodeState::BootUp, .. }) if *node == id)
        })
        .await;
    }
    assert_eq!(
        master.lss_fastscan_with_step(STEP).await.unwrap(),
        None,
        "everyone configured"
    );
    assert_eq!(
        master.sdo().read::<u32>(20, 0x1018, 4).await.unwrap(),
        0x400
    );
    assert_eq!(
        master.sdo().read::<u32>(21, 0x1014, 0).await.unwrap(),
        0x80 + 21,
        "COB-IDs follow"
    );

    // Selective switch, a refused node-ID, then a change that applies at reset communication.
    assert!(master
        .lss_switch_selective([0x41A, 0x1000, 1, 0x500])
        .await
        .unwrap());
    assert_eq!(
        master.lss_inquire_address().await.unwrap(),
        [0x41A, 0x1000, 1, 0x500]
    );
    assert!(matches!(
        master.lss_configure_node_id(0x80).await,
        Err(canopen::master::LssError::Refused(1))
    ));
    master.lss_configure_node_id(30).await.unwrap();
    master.lss_switch_global(false).await.unwrap();
    assert_eq!(
        master
            .lss_inquire_node_id()
            .await
            .map_err(|e| e.to_string()),
        Err("no LSS slave answered".into())
    );
    master
        .nmt(NmtCommand::ResetCommunication, 21)
        .await
        .unwrap();
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 30,
                new: NodeState::BootUp,
                ..
            })
        )
    })
    .await;
    assert_eq!(
        master.sdo().read::<u32>(30, 0x1200, 1).await.unwrap(),
        0x600 + 30
    );
    // Not stored: after a restart the node is 21 again (its stored node-ID).
    a.stop().await;
    let a = LocalNode::start(
        Bus::open(url).await.unwrap(),
        ObjectDictionary::new(),
        config(0x500),
    );
    master_event(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::BootUp { node: 21 })
        )
    })
    .await;
    a.stop().await;
    b.stop().await;
}
