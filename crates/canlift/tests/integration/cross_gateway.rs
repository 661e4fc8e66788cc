//! The gateway as lift gateways ship it: built for aarch64 and armv7 Linux (`scripts/cross-gateway`,
//! Debian's cross compilers and Rust standard libraries) and run under qemu-user, in front of
//! the simulator on a hub, connected to a portal on this machine: it comes online, answers a
//! get and a put, and pushes a subscribed value.
//!
//! `CANLIFT_CROSS_GATEWAYS` names the list the script writes (`TARGET QEMU BINARY SYSROOT` per
//! line); without it the test is skipped with the reason (CI sets CANLIFT_REQUIRE_CROSS=1).

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use serde_json::json;
use testkit::constants::LIFT;
use testkit::portal::{until, Rig};

/// One cross-built gateway: its target, the qemu-user binary that runs it, and where its C
/// library is.
struct Cross {
    target: String,
    qemu: PathBuf,
    binary: PathBuf,
    sysroot: PathBuf,
}

fn cross_gateways() -> Option<Vec<Cross>> {
    let Some(list) = std::env::var_os("CANLIFT_CROSS_GATEWAYS") else {
        return testkit::unavailable(
            "CANLIFT_REQUIRE_CROSS",
            "cross gateways: CANLIFT_CROSS_GATEWAYS is not set (scripts/cross-gateway builds them)",
        );
    };
    let text = std::fs::read_to_string(&list).expect("the list of cross gateways");
    let gateways: Vec<Cross> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [target, qemu, binary, sysroot] = fields[..] else {
                panic!(
                    "{}: {line:?} is not TARGET QEMU BINARY SYSROOT",
                    Path::new(&list).display()
                );
            };
            Cross {
                target: target.into(),
                qemu: qemu.into(),
                binary: binary.into(),
                sysroot: sysroot.into(),
            }
        })
        .collect();
    assert!(gateways.len() >= 2, "aarch64 and armv7 in {text}");
    Some(gateways)
}

/// The values of `mplex` in the portal's history of the last ten minutes.
async fn history(rig: &Rig, mplex: &str) -> Vec<String> {
    let path = format!(
        "/api/v1/lifts/{LIFT}/objects/{mplex}/history?from={}&points=10000",
        cloud_types::now_ms() - 600_000
    );
    let (_, h) = rig.call("GET", &path, Some(&rig.key), None).await;
    h["points"]
        .as_array()
        .map(|points| {
            points
                .iter()
                .filter_map(|p| Some(p["last"].as_str()?.to_owned()))
                .collect()
        })
        .unwrap_or_default()
}

async fn serves_the_lift(cross: &Cross) {
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let sim = testkit::lift::simulator(&bus).await;
    let rig = Rig::builder().without_lift().start().await;
    let state = rig.dir().join(format!("gateway-{}", cross.target));
    let config = testkit::lift::gateway_config(&rig.ws_url(), &rig.ca, &bus, &state);
    let file = state.join("gateway.toml");
    std::fs::write(&file, toml::to_string_pretty(&config).expect("TOML")).expect("written");
    let mut gateway = tokio::process::Command::new(&cross.qemu)
        .arg("-L")
        .arg(&cross.sysroot)
        .arg(&cross.binary)
        .args(["gateway", "--config"])
        .arg(&file)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .expect("qemu runs the gateway");

    until(
        Duration::from_secs(60),
        "the emulated gateway online",
        || async { rig.registry().online(LIFT) },
    )
    .await;
    let read = format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked");
    let (status, trips) = rig.call("GET", &read, Some(&rig.key), None).await;
    assert_eq!(status, 200, "{}: {trips}", cross.target);
    let subscribe = json!({"mplex": ["0x652001"]});
    let path = format!("/api/v1/lifts/{LIFT}/subscriptions");
    let (status, body) = rig
        .call("POST", &path, Some(&rig.key), Some(subscribe))
        .await;
    assert_eq!(status, 200, "{}: {body}", cross.target);
    let call = json!({"value": "3", "datatype": 7, "physunit": 0});
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x502200");
    let (status, body) = rig.call("PUT", &path, Some(&rig.key), Some(call)).await;
    assert_eq!(status, 200, "{}: {body}", cross.target);
    // The trip the call made, pushed by the emulated gateway as the subscription asked.
    until(Duration::from_secs(60), "the trip pushed", || async {
        history(&rig, "0x652001").await.iter().any(|v| v == "1")
    })
    .await;

    gateway.start_kill().expect("SIGKILL sent");
    let _ = gateway.wait().await;
    rig.stop().await;
    sim.stop().await;
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_arm_gateways_serve_the_lift_under_qemu() {
    let Some(gateways) = cross_gateways() else {
        return;
    };
    for cross in &gateways {
        serves_the_lift(cross).await;
    }
}
