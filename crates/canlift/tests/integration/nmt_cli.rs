//! `canlift nmt` against an independent NMT slave: python-canopen's LocalNode, through the hub.

use std::process::Stdio;
use std::time::Duration;

use testkit::{interop_script, python};
use tokio::io::{AsyncBufReadExt, BufReader};

use crate::common;
use common::run;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nmt_commands_reach_a_python_canopen_node() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let addr = hub.local_addr();
    let mut node = tokio::process::Command::new(python)
        .arg(interop_script("local_node.py"))
        .args([addr.ip().to_string(), addr.port().to_string(), "12".into()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(node.stdout.take().unwrap()).lines();
    let ready = tokio::time::timeout(Duration::from_secs(30), lines.next_line())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(ready.as_deref(), Some("READY"));
    let url = testkit::hub_url(&hub, "can0");
    for (command, state) in [
        ("start", "Operational"),
        ("stop", "Stopped"),
        ("preop", "PreOperational"),
    ] {
        let out = run(&["nmt", "--bus", &url, command, "12", "--wait-ms", "3000"]).await;
        assert!(
            out.status.success(),
            "{command}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(
            String::from_utf8_lossy(&out.stdout),
            format!("node 12: {state}\n")
        );
    }
    // A node that does not exist never confirms.
    let out = run(&["nmt", "--bus", &url, "start", "13", "--wait-ms", "500"]).await;
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("did not report Operational"));
    drop(node.stdin.take());
    let _ = tokio::time::timeout(Duration::from_secs(10), node.wait()).await;
    hub.shutdown().await;
}
