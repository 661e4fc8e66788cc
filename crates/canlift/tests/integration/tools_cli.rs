//! The integrator's tools (`canlift scan`, `canlift lss`, `canlift sync|time|emcy`) against the
//! simulator, a python-canopen LocalNode and canlift nodes on one hub, and their help texts.

use std::time::Duration;

use canbus::Bus;
use canopen::node::{LocalNode, NodeConfig};
use serde_json::Value;
use testkit::python;
use tokio::io::{AsyncBufReadExt, BufReader};

use crate::common;
use common::{python_node, run, snapshot, stderr};

#[tokio::test]
async fn help_texts() {
    for command in [
        "ascii", "scan", "sdo", "lss", "pdo", "dcf", "sync", "time", "emcy",
    ] {
        let out = run(&[command, "--help"]).await;
        assert!(out.status.success(), "{}", stderr(&out));
        snapshot(
            &format!("{command}-help.txt"),
            &String::from_utf8_lossy(&out.stdout),
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scan_finds_every_node_with_its_identity() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let _sim = testkit::lift::simulator(&bus).await;
    let mut node5 = python_node(&python, &hub, "local_node.py", 5).await.0;
    // Node 9 sends no heartbeat: only probing finds it.
    let node9 = LocalNode::start(
        Bus::open(&bus).await.expect("the hub"),
        testkit::sample::dictionary(),
        NodeConfig::new(9),
    );

    let out = run(&["scan", "--bus", &bus, "--json"]).await;
    assert!(out.status.success(), "{}", stderr(&out));
    let found: Vec<Value> = serde_json::from_slice(&out.stdout).expect("JSON");
    let ids: Vec<u64> = found.iter().filter_map(|f| f["node"].as_u64()).collect();
    assert_eq!(ids, [1, 5, 12], "{found:?}");
    let controller = &found[0];
    assert_eq!(controller["name"], "canlift simulated lift controller");
    assert!(controller["profile"]
        .as_str()
        .unwrap_or_default()
        .starts_with("417 "));
    assert!(controller["software"]
        .as_str()
        .unwrap_or_default()
        .starts_with("canlift "));
    for key in ["device_type", "vendor", "product", "revision", "serial"] {
        assert!(
            controller[key]
                .as_str()
                .unwrap_or_default()
                .starts_with("0x"),
            "{key}: {controller}"
        );
    }
    assert_eq!(found[1]["name"], "python-canopen");
    assert_eq!(found[1]["state"], "pre-operational");
    assert_eq!(
        found[1]["vendor"],
        Value::Null,
        "python's node has no 1018h"
    );
    assert_eq!(found[2]["name"], "canlift simulated I/O node");

    let out = run(&["scan", "--bus", &bus, "--probe", "--listen-ms", "1200"]).await;
    assert!(out.status.success(), "{}", stderr(&out));
    let table = String::from_utf8_lossy(&out.stdout);
    let rows: Vec<&str> = table.lines().collect();
    assert!(rows[0].starts_with("node  state"), "{table}");
    let nine = rows
        .iter()
        .find(|r| r.starts_with("9 "))
        .unwrap_or_else(|| panic!("probing finds node 9:\n{table}"));
    assert!(nine.contains("unknown"), "{nine}");
    assert!(nine.contains("417 lift control"), "{nine}");
    assert!(nine.contains("lift controller"), "{nine}");
    assert_eq!(rows.len(), 5, "{table}");

    drop(node9);
    drop(node5.stdin.take());
    let _ = tokio::time::timeout(Duration::from_secs(10), node5.wait()).await;
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sync_time_and_emcy_on_the_wire() {
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let mut listener = Bus::open(&bus).await.expect("the hub");

    // SYNC with the counter, counting 1…4.
    let out = run(&[
        "sync",
        "--bus",
        &bus,
        "--period-ms",
        "5",
        "--counter",
        "4",
        "--count",
        "6",
    ])
    .await;
    assert!(out.status.success(), "{}", stderr(&out));
    let mut counters = Vec::new();
    while counters.len() < 6 {
        let frame = tokio::time::timeout(Duration::from_secs(10), listener.receiver.recv_frame())
            .await
            .expect("a SYNC")
            .expect("the bus");
        assert_eq!(frame.id(), canbus::CanId::Standard(0x80));
        counters.push(frame.data()[0]);
    }
    assert_eq!(counters, [1, 2, 3, 4, 1, 2]);
    let refused = run(&["sync", "--bus", &bus, "--counter", "1", "--count", "1"]).await;
    assert!(stderr(&refused).contains("2–240"), "{}", stderr(&refused));

    // TIME at a given instant.
    let out = run(&["time", "--bus", &bus, "--at", "2026-11-23T10:11:12.345"]).await;
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(
        String::from_utf8_lossy(&out.stdout),
        "TIME 2026-11-23T10:11:12.345 UTC\n"
    );
    let frame = tokio::time::timeout(Duration::from_secs(10), listener.receiver.recv_frame())
        .await
        .expect("TIME")
        .expect("the bus");
    assert_eq!(frame.id(), canbus::CanId::Standard(0x100));
    let t = canopen::time::TimeOfDay::parse(frame.data()).expect("a time stamp");
    assert_eq!(t.ms, ((10 * 60 + 11) * 60 + 12) * 1000 + 345);

    // EMCY: one process watches, another sends.
    let mut watch = common::canlift()
        .args(["emcy", "--bus", &bus, "watch", "--count", "2"])
        .spawn()
        .expect("canlift runs");
    let mut err = BufReader::new(watch.stderr.take().expect("stderr")).lines();
    let ready = tokio::time::timeout(Duration::from_secs(20), err.next_line())
        .await
        .expect("watching")
        .expect("stderr");
    assert!(ready.is_some_and(|l| l.starts_with("watching EMCY")));
    let sent = run(&[
        "emcy",
        "--bus",
        &bus,
        "send",
        "5",
        "0xFF01",
        "--register",
        "0x21",
        "--data",
        "01 02",
    ])
    .await;
    assert!(sent.status.success(), "{}", stderr(&sent));
    let reset = run(&["emcy", "--bus", &bus, "send", "5", "0"]).await;
    assert!(reset.status.success(), "{}", stderr(&reset));
    let out = tokio::time::timeout(Duration::from_secs(20), watch.wait_with_output())
        .await
        .expect("watch ends after 2")
        .expect("its output");
    assert_eq!(
        String::from_utf8_lossy(&out.stdout),
        "node 5   FF01  Door blocked  register 0x21  data 01 02 00 00 00\n\
         node 5   0000  Error reset or no error  register 0x01  data 00 00 00 00 00\n"
    );
    let frame = tokio::time::timeout(Duration::from_secs(10), listener.receiver.recv_frame())
        .await
        .expect("the EMCY")
        .expect("the bus");
    assert_eq!(frame.id(), canbus::CanId::Standard(0x85));
    assert_eq!(frame.data(), [0x01, 0xFF, 0x21, 0x01, 0x02, 0, 0, 0]);
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pdo_set_then_show_against_python_canopen() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let (mut node, mut stdout) = python_node(&python, &hub, "pdo_node.py", 6).await;
    let mut stdin = node.stdin.take().expect("stdin");

    let out = run(&["pdo", "--bus", &bus, "show", "6", "--all"]).await;
    assert!(out.status.success(), "{}", stderr(&out));
    let before = String::from_utf8_lossy(&out.stdout).into_owned();
    snapshot("pdo-show-before.txt", &before);

    let out = run(&[
        "pdo",
        "--bus",
        &bus,
        "set",
        "6",
        "tpdo1",
        "--cob-id",
        "0x186",
        "--type",
        "254",
        "--inhibit",
        "10",
        "--event",
        "100",
        "--map",
        "0x2001:0:32,0x2002:0:16",
    ])
    .await;
    assert!(out.status.success(), "{}", stderr(&out));
    let set = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(set.starts_with("TPDO1   COB-ID 0x186  type 254"), "{set}");

    // python-canopen decodes what it received against its own dictionary.
    use tokio::io::AsyncWriteExt;
    stdin.write_all(b"check\n").await.expect("check");
    let line = tokio::time::timeout(Duration::from_secs(20), stdout.next_line())
        .await
        .expect("an answer")
        .expect("stdout")
        .expect("a line");
    let seen: Value = serde_json::from_str(&line).expect("JSON");
    assert_eq!(seen["cob_id"], 0x186);
    assert_eq!(seen["enabled"], true);
    assert_eq!(seen["trans_type"], 254);
    assert_eq!(seen["inhibit_time"], 10);
    assert_eq!(seen["event_timer"], 100);
    assert_eq!(
        seen["map"],
        serde_json::json!([[0x2001, 0, 32], [0x2002, 0, 16]])
    );

    let out = run(&["pdo", "--bus", &bus, "show", "6"]).await;
    assert!(out.status.success(), "{}", stderr(&out));
    snapshot("pdo-show-after.txt", &String::from_utf8_lossy(&out.stdout));

    // An application consumes the PDO by the node's own configuration.
    let master = canopen::master::Master::open(&bus, Default::default())
        .await
        .expect("the hub");
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let consumed = master
        .on_remote_tpdo(6, 1, move |values| {
            let _ = tx.send(values.clone());
        })
        .await
        .expect("TPDO1 is on");
    assert_eq!(consumed.mapping.len(), 2);
    stdin
        .write_all(b"send 0x12345678 -3\n")
        .await
        .expect("send");
    let values = tokio::time::timeout(Duration::from_secs(20), rx.recv())
        .await
        .expect("the TPDO")
        .expect("values");
    assert_eq!(values.cob_id, canbus::CanId::Standard(0x186));
    assert_eq!(values.value::<u32>(0x2001, 0), Some(0x1234_5678));
    assert_eq!(values.value::<i16>(0x2002, 0), Some(-3));
    assert!(matches!(
        master.on_remote_tpdo(6, 2, |_| {}).await,
        Err(canopen::pdo::remote::ConsumeError::Missing { .. })
    ));
    drop(master);

    // A node that checks mappings (canlift's) refuses a bad one: the step and the abort are
    // named. python-canopen's LocalNode takes any mapping.
    let node9 = LocalNode::start(
        Bus::open(&bus).await.expect("the hub"),
        testkit::sample::dictionary(),
        NodeConfig::new(9),
    );
    let out = run(&[
        "pdo",
        "--bus",
        &bus,
        "set",
        "9",
        "tpdo1",
        "--map",
        "0x1008:0:8",
    ])
    .await;
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("TPDO1: mapping entry 1 (1008h sub 0, 8 bits)") && err.contains("06040041"),
        "{err}"
    );
    assert!(err.contains("cannot be mapped"), "{err}");
    drop(node9);
    let out = run(&["pdo", "--bus", &bus, "set", "6", "tpdo2"]).await;
    assert!(
        stderr(&out).contains("node 6 has no TPDO2"),
        "{}",
        stderr(&out)
    );

    drop(stdin);
    let _ = tokio::time::timeout(Duration::from_secs(10), node.wait()).await;
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dcf_read_then_apply_and_a_wrong_identity_refused() {
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let sim = testkit::lift::simulator(&bus).await;
    let dir = testkit::scratch();
    let eds = dir.path().join("io.eds");
    let config = lift417::sim::SimConfig {
        speed: 20.0,
        ..lift417::sim::SimConfig::default()
    };
    let text = lift417::sim::export_eds(&config, lift417::catalog::Device::Io).expect("the EDS");
    std::fs::write(&eds, text).expect("written");

    // Read the I/O node's values into a DCF.
    let eds_arg = eds.to_string_lossy().into_owned();
    let out = run(&["dcf", "--bus", &bus, "read", "12", &eds_arg]).await;
    assert!(out.status.success(), "{}", stderr(&out));
    let dcf = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(dcf.contains("[DeviceComissioning]"), "a DCF");
    let heartbeat = dcf.find("[1017]").expect("1017h in the DCF");
    assert!(
        dcf[heartbeat..].contains("ParameterValue=1000"),
        "{}",
        &dcf[heartbeat..heartbeat + 300]
    );

    // Change the heartbeat time and TPDO1's event timer, apply, read back.
    let changed = dcf.replacen("ParameterValue=1000", "ParameterValue=700", 1);
    let dcf_path = dir.path().join("io.dcf");
    std::fs::write(&dcf_path, &changed).expect("written");
    let dcf_arg = dcf_path.to_string_lossy().into_owned();
    let out = run(&["dcf", "--bus", &bus, "apply", "12", &dcf_arg]).await;
    let report = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "{}\n{report}", stderr(&out));
    assert!(report.contains("1017h sub 0    700  OK"), "{report}");
    assert!(report.contains("TPDO1  COB-ID"), "{report}");
    let out = run(&["sdo", "--bus", &bus, "read", "12", "0x1017", "0", "u16"]).await;
    assert_eq!(String::from_utf8_lossy(&out.stdout), "700\n");

    // Another device's DCF is refused before anything is written.
    let other = changed
        .replacen("ParameterValue=700", "ParameterValue=900", 1)
        .replace("ProductNumber=", "ProductNumber=0x7777\n;was ");
    std::fs::write(&dcf_path, other).expect("written");
    let out = run(&["dcf", "--bus", &bus, "apply", "12", &dcf_arg]).await;
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("is not the device this DCF describes"),
        "{}",
        stderr(&out)
    );
    assert!(
        stderr(&out).contains("ProductNumber: the DCF says 0x00007777"),
        "{}",
        stderr(&out)
    );
    let out = run(&["sdo", "--bus", &bus, "read", "12", "0x1017", "0", "u16"]).await;
    assert_eq!(
        String::from_utf8_lossy(&out.stdout),
        "700\n",
        "nothing written"
    );
    drop(sim);
    hub.shutdown().await;
}

/// `canlift eds check` on files with the defects found in public device descriptions: every
/// defect with its file, line and severity, in text and JSON; exit 1 while a file has an error,
/// 0 when only warnings are left.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn eds_check_lists_each_defect_with_its_line() {
    let dir = testkit::workspace().join("tests/fixtures/eds-defects");
    let file = |name: &str| dir.join(name).display().to_string();
    let names = [
        "visible-string-default.eds",
        "object-count.eds",
        "domain-default.eds",
        "subnumber-type.eds",
        "sub7.dcf",
        "windows-1252.eds",
    ];
    let mut args = vec!["eds".to_owned(), "check".to_owned(), "--json".to_owned()];
    args.extend(names.iter().map(|n| file(n)));
    let out = crate::common::canlift()
        .args(&args)
        .output()
        .await
        .expect("runs");
    assert_eq!(out.status.code(), Some(1), "two files have errors");
    let checked: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let mut found = Vec::new();
    for c in checked.as_array().expect("per file") {
        let name = c["file"]
            .as_str()
            .and_then(|f| f.rsplit('/').next())
            .unwrap_or_default();
        assert_eq!(
            c["objects"],
            4 - u64::from(name == "object-count.eds"),
            "{c}"
        );
        for f in c["findings"].as_array().expect("findings") {
            found.push((
                name.to_owned(),
                f["line"].as_u64().unwrap_or(0),
                f["severity"].as_str().unwrap_or_default().to_owned(),
            ));
        }
    }
    let expected = [
        ("visible-string-default.eds", 56, "warning"),
        ("object-count.eds", 24, "warning"),
        ("object-count.eds", 26, "error"),
        ("domain-default.eds", 56, "warning"),
        ("subnumber-type.eds", 55, "warning"),
        ("subnumber-type.eds", 92, "error"),
        ("sub7.dcf", 56, "warning"),
        ("sub7.dcf", 59, "warning"),
        ("windows-1252.eds", 52, "warning"),
    ]
    .map(|(n, l, s)| (n.to_owned(), l, s.to_owned()));
    assert_eq!(found, expected);
    // The line a finding names is the defect's.
    let text = std::fs::read_to_string(dir.join("subnumber-type.eds")).expect("fixture");
    assert_eq!(text.lines().nth(91), Some("DataType=0x0040"));
    // Text for people, one line per finding; warnings alone pass.
    let out = crate::common::canlift()
        .args([
            "eds",
            "check",
            &file("domain-default.eds"),
            &file("sub7.dcf"),
        ])
        .output()
        .await
        .expect("runs");
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains(&format!(
            "{}:56: warning: DefaultValue \"@ABCD\" is not a valid DOMAIN",
            file("domain-default.eds")
        )),
        "{text}"
    );
}
