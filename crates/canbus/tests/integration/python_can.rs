//! Interop with python-can's `socketcand` interface (an independent implementation) through the
//! hub, in both directions and between two python-can clients.
//!
//! Needs the venv that `scripts/test` creates; without it these tests skip with a printed reason,
//! unless CANLIFT_REQUIRE_INTEROP=1 (as `scripts/test` and CI set), where they fail instead.

use crate::common;

use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

use canbus::hub::HubConfig;
use canbus::{Bus, BusOptions};
use common::{hub, pattern, same, url};
use testkit::{interop_script, python};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::Command;

const FRAMES: u32 = 10_000;

fn script(python: &PathBuf, mode: &str, hub: &canbus::hub::HubHandle, count: u32) -> Command {
    let addr = hub.local_addr();
    let mut cmd = Command::new(python);
    cmd.arg(interop_script("pattern.py"))
        .args([
            mode,
            &addr.ip().to_string(),
            &addr.port().to_string(),
            "can0",
        ])
        .arg(count.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    cmd
}

async fn finish(child: tokio::process::Child) -> String {
    let out = tokio::time::timeout(Duration::from_secs(120), child.wait_with_output())
        .await
        .expect("python finished in time")
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "python failed: {}\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_can_to_canlift() {
    let Some(python) = python() else { return };
    let hub = hub(HubConfig::default()).await;
    let options = BusOptions {
        rx_queue: 1 << 16,
        ..BusOptions::default()
    };
    let mut bus = Bus::open_with(&url(&hub, "can0"), options).await.unwrap();
    let child = script(&python, "send", &hub, FRAMES).spawn().unwrap();
    for i in 0..FRAMES {
        let got = tokio::time::timeout(Duration::from_secs(30), bus.receiver.recv_frame())
            .await
            .expect("frame in time")
            .unwrap();
        assert!(
            same(&got, &pattern(i)),
            "frame {i}: {got} != {}",
            pattern(i)
        );
    }
    assert!(finish(child).await.contains(&format!("OK {FRAMES}")));
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn canlift_to_python_can() {
    let Some(python) = python() else { return };
    let hub = hub(HubConfig::default()).await;
    let bus = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut child = script(&python, "recv", &hub, FRAMES).spawn().unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let ready = tokio::time::timeout(Duration::from_secs(30), lines.next_line())
        .await
        .expect("python connected in time")
        .unwrap();
    assert_eq!(ready.as_deref(), Some("READY"));
    for i in 0..FRAMES {
        bus.send(pattern(i)).await.unwrap();
    }
    let mut rest = String::new();
    while let Some(line) = tokio::time::timeout(Duration::from_secs(60), lines.next_line())
        .await
        .expect("python finished in time")
        .unwrap()
    {
        rest.push_str(&line);
    }
    finish(child).await;
    assert!(rest.contains(&format!("OK {FRAMES}")), "{rest}");
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_can_to_python_can_through_the_hub() {
    let Some(python) = python() else { return };
    let hub = hub(HubConfig::default()).await;
    let out = finish(script(&python, "loop", &hub, FRAMES).spawn().unwrap()).await;
    assert!(out.contains(&format!("OK {FRAMES}")), "{out}");
    hub.shutdown().await;
}
