//! `canlift lss` against unconfigured canlift nodes on a hub. Fastscan steps are timed: under
//! cargo-nextest these tests run with no other beside them (.config/nextest.toml). Each step
//! listens 60 ms: a hub round trip takes well under a millisecond, the margin is for a loaded
//! machine.

use std::time::Duration;

use canbus::Bus;
use canopen::node::{LocalNode, NodeConfig};

use crate::common;
use common::{run, stderr};

/// Read `node`'s serial number (1018h sub 4) with `canlift sdo`, waiting for it to boot.
async fn serial_of(bus: &str, node: u8) -> String {
    for _ in 0..25 {
        let out = run(&[
            "sdo",
            "--bus",
            bus,
            "read",
            &node.to_string(),
            "0x1018",
            "4",
            "x32",
        ])
        .await;
        if out.status.success() {
            return String::from_utf8_lossy(&out.stdout).trim().to_owned();
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    panic!("node {node} never answered");
}

/// `canlift lss --bus BUS ARGS`.
async fn lss(bus: &str, args: &[&str]) -> std::process::Output {
    let mut all = vec!["lss", "--bus", bus, "--timeout-ms", "1000"];
    all.extend_from_slice(args);
    run(&all).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lss_from_the_command_line() {
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let dir = testkit::scratch();
    let mut nodes = Vec::new();
    for (product, serial) in [(0x77u32, 0x31u32), (0x77, 0x32), (0x78, 0x33), (0x78, 0x34)] {
        let config = NodeConfig {
            identity: [0x41A, product, 2, serial],
            storage: Some(dir.path().join(format!("node-{serial:x}.params"))),
            ..NodeConfig::new(canopen::lss::UNCONFIGURED)
        };
        let node_bus = Bus::open(&bus).await.expect("the hub");
        nodes.push(LocalNode::start(
            node_bus,
            canopen::od::ObjectDictionary::new(),
            config,
        ));
    }
    let ok = |out: std::process::Output| {
        assert!(out.status.success(), "{}", stderr(&out));
        String::from_utf8_lossy(&out.stdout).into_owned()
    };

    // One by hand: find, inquire, give an ID, store, back to waiting.
    let found = ok(lss(&bus, &["fastscan", "--step-ms", "60"]).await);
    assert_eq!(found, "0x0000041A 0x00000077 0x00000002 0x00000031\n");
    let inquired = ok(lss(&bus, &["inquire"]).await);
    assert_eq!(
        inquired,
        "0x0000041A 0x00000077 0x00000002 0x00000031\n255\n"
    );
    assert_eq!(ok(lss(&bus, &["set-node", "20"]).await), "OK\n");
    let refused = lss(&bus, &["set-bitrate", "5"]).await;
    assert!(!refused.status.success());
    assert!(
        stderr(&refused).contains("ERROR: 503"),
        "{}",
        stderr(&refused)
    );
    assert_eq!(ok(lss(&bus, &["store"]).await), "OK\n");
    assert_eq!(ok(lss(&bus, &["switch-global", "off"]).await), "OK\n");
    assert_eq!(serial_of(&bus, 20).await, "0x00000031");

    // Only one product (matched in one step), revisions not looked at.
    let product = [
        "fastscan",
        "--assign",
        "30",
        "--store",
        "--step-ms",
        "60",
        "--product",
        "0x77",
        "--skip-revision",
    ];
    assert_eq!(
        ok(lss(&bus, &product).await),
        "# node 30: 0x0000041A 0x00000077 0x00000000 0x00000032\n# 1 node(s) configured\n"
    );
    // The rest in one go.
    let assigned = ok(lss(
        &bus,
        &["fastscan", "--assign", "31", "--store", "--step-ms", "60"],
    )
    .await);
    assert_eq!(
        assigned,
        "# node 31: 0x0000041A 0x00000078 0x00000002 0x00000033\n\
         # node 32: 0x0000041A 0x00000078 0x00000002 0x00000034\n\
         # 2 node(s) configured\n"
    );
    assert_eq!(serial_of(&bus, 32).await, "0x00000034");
    assert_eq!(serial_of(&bus, 30).await, "0x00000032");
    assert_eq!(serial_of(&bus, 31).await, "0x00000033");
    let none = lss(&bus, &["fastscan", "--step-ms", "60"]).await;
    assert!(!none.status.success());
    assert!(stderr(&none).contains("ERROR: 103"), "{}", stderr(&none));

    // Selective switch by address, then a change that applies at reset communication.
    assert_eq!(
        ok(lss(&bus, &["switch-selective", "0x41A", "0x78", "2", "0x33"]).await),
        "OK\n"
    );
    assert_eq!(ok(lss(&bus, &["set-node", "40"]).await), "OK\n");
    assert_eq!(ok(lss(&bus, &["switch-global", "off"]).await), "OK\n");
    ok(run(&["nmt", "--bus", &bus, "reset-comm", "31"]).await);
    assert_eq!(serial_of(&bus, 40).await, "0x00000033");
    drop(nodes);
    hub.shutdown().await;
}
