//! `canlift sim` as a user runs it: an EDS export that python-canopen (an independent
//! implementation) uses to read and drive the running simulator through the hub, and a clean
//! stop that keeps the counters.

use std::time::Duration;

use canbus::Bus;
use canopen::sdo::clients::SdoClients;
use testkit::{interop_script, python};

use crate::common;
use common::{canlift, interrupt};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn export_eds_writes_both_nodes() {
    let scratch = testkit::scratch();
    let dir = scratch.path();
    let eds = dir.join("lift.eds");
    let out = canlift()
        .args(["sim", "--floors", "6", "--export-eds"])
        .arg(&eds)
        .output()
        .await
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let controller = canopen::eds::import_file(&eds, Some(1))
        .unwrap()
        .description
        .od;
    assert_eq!(
        controller.get_value(0x4010, 0),
        Ok(canopen::types::Value::Uint(6))
    );
    let io = canopen::eds::import_file(&dir.join("io-node-12.eds"), Some(12))
        .unwrap()
        .description
        .od;
    assert!(io.object(0x6100).is_some());
    let bad = canlift()
        .args(["sim", "--floors", "40", "--export-eds"])
        .arg(&eds)
        .output()
        .await
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("40 floors"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_canopen_reads_and_calls_the_simulated_lift() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let scratch = testkit::scratch();
    let dir = scratch.path();
    let eds = dir.join("lift.eds");
    common::export_sim_eds(&eds).await;
    let mut sim = canlift()
        .args(["sim", "--bus", &url, "--speed", "20", "--state"])
        .arg(dir.join("state"))
        .spawn()
        .unwrap();
    // Ready once the controller answers SDO.
    let sdo = SdoClients::new(Bus::open(&url).await.unwrap(), Default::default());
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while sdo.read::<u32>(1, 0x1000, 0).await.is_err() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "simulator did not come up"
        );
    }
    let addr = hub.local_addr();
    let out = tokio::time::timeout(
        Duration::from_secs(120),
        tokio::process::Command::new(&python)
            .arg(interop_script("read_sim.py"))
            .args([
                addr.ip().to_string(),
                addr.port().to_string(),
                "can0".into(),
            ])
            .arg(&eds)
            .arg("1")
            .output(),
    )
    .await
    .expect("python-canopen finished in time")
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let facts: std::collections::HashMap<&str, &str> =
        stdout.lines().filter_map(|l| l.split_once(' ')).collect();
    assert_eq!(facts["device_type"], "0x101a1");
    assert_eq!(facts["trip_name"], "Trip counter [trips]");
    assert_eq!(facts["trips_before"], "0");
    assert_eq!(
        facts["floors"],
        "1000,4500,8000,11500,15000,18500,22000,25500"
    );
    assert_eq!(facts["lantern"], "0");
    assert_eq!(facts["trips_after"], "1");
    assert_eq!(facts["position"], "8000");
    assert_eq!(facts["abort"], "0x6090031", "floor 9 is too high");
    // SIGINT, as Ctrl-C would: the simulator stores its counters and exits 0.
    assert!(interrupt(&mut sim, Duration::from_secs(10)).await.success());
    let stored = std::fs::read_to_string(dir.join("state/node1.params")).unwrap();
    assert!(stored.contains("6520:01 01000000"), "{stored}");
}

/// A reader that goes away (`canlift sim --export-eds F | head -1`) ends a printing command
/// quietly, as it ends `cat`: killed by SIGPIPE, no panic message, no exit status 101. The
/// pipe's read end is closed before the command writes, so its first line meets it.
#[test]
fn a_closed_pipe_ends_a_printing_command_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let scratch = testkit::scratch();
    let (reader, writer) = std::io::pipe().expect("a pipe");
    drop(reader);
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_canlift"))
        .args(["sim", "--export-eds"])
        .arg(scratch.path().join("lift.eds"))
        .stdout(writer)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("canlift starts");
    let out = child.wait_with_output().expect("it ends");
    // SIGPIPE is 13 on Linux.
    assert_eq!(out.status.signal(), Some(13), "{:?}", out.status);
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
