//! `canlift dump` watching a live node: whole SDO transfers and PDOs decoded by mappings it
//! reads over SDO, or by the ones an EDS gives (the simulator's own export).

use std::time::Duration;

use canbus::Bus;
use canopen::nmt::{NmtCommand, NmtState};
use canopen::node::{LocalNode, NodeConfig, PdoSetup};
use canopen::sdo::clients::SdoClients;
use canopen::types::Value;
use testkit::sample::{self, POSITION};
use tokio::io::AsyncReadExt;

use crate::common;
use common::canlift;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dump_shows_transfers_and_learned_pdos() {
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let mut dump = canlift()
        .args(["dump", "--bus", &url, "--read-pdo-mappings"])
        .spawn()
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;

    let od = sample::dictionary();
    let config = NodeConfig {
        heartbeat_ms: 100,
        software_version: "sim 1.0".into(),
        ..NodeConfig::new(6)
    };
    let node = LocalNode::start(Bus::open(&url).await.unwrap(), od, config);
    node.wait_for_state(NmtState::PreOperational).await;
    // dump reads the (still empty) mappings at the boot-up; the TPDO is configured after that.
    tokio::time::sleep(Duration::from_millis(500)).await;
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
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let sdo = SdoClients::new(Bus::open(&url).await.unwrap(), Default::default());
    assert_eq!(sdo.read::<String>(6, 0x100A, 0).await.unwrap(), "sim 1.0");
    // Configured after the boot-up, as a master does: dump reads the mappings again when the
    // node's heartbeat says operational (every 100 ms here), then decodes what follows.
    node.nmt(NmtCommand::Start);
    node.wait_for_state(NmtState::Operational).await;
    tokio::time::sleep(Duration::from_millis(800)).await;
    node.set_value(POSITION, 0, &Value::Uint(1234)).unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;

    let mut stdout = dump.stdout.take().unwrap();
    dump.start_kill().unwrap();
    let mut text = String::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), stdout.read_to_string(&mut text)).await;
    assert!(text.contains("Boot-up node 6"), "{text}");
    assert!(text.contains("Heartbeat node 6: pre-operational"), "{text}");
    assert!(
        text.contains(
            "=> SDO read node 6 100A:00 (segmented) 7 bytes: 73 69 6D 20 31 2E 30 \"sim 1.0\""
        ),
        "{text}"
    );
    assert!(text.contains("TPDO1 node 6: 2000:00=1234"), "{text}");
    node.stop().await;
    hub.shutdown().await;
}

/// The EDS `canlift sim --export-eds` writes gives the PDOs the simulator maps at boot, so
/// `dump --eds` decodes the running simulator's PDOs from the file alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dump_decodes_the_simulators_pdos_by_its_exported_eds() {
    let scratch = testkit::scratch();
    let eds = scratch.path().join("lift.eds");
    common::export_sim_eds(&eds).await;
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let mut dump = canlift()
        .args(["dump", "--bus", &url, "--eds"])
        .arg(format!("1={}", eds.display()))
        .spawn()
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let sim = lift417::sim::Simulator::start(&url, lift417::sim::SimConfig::default())
        .await
        .unwrap();
    // Every TPDO of lift 1 has an event timer of at most 5 s.
    tokio::time::sleep(Duration::from_millis(5500)).await;
    let mut stdout = dump.stdout.take().unwrap();
    dump.start_kill().unwrap();
    let mut text = String::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), stdout.read_to_string(&mut text)).await;
    for decoded in [
        "TPDO1 node 1: 6383:01=",
        "TPDO2 node 1: 6301:01=",
        "5024:00=0",
        "TPDO3 node 1: 6520:01=",
    ] {
        assert!(text.contains(decoded), "{decoded} not in {text}");
    }
    sim.stop().await;
    hub.shutdown().await;
}
