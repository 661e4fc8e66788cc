//! SDO interop with python-canopen (an independent implementation) through the hub:
//! its client against a canlift server, and canlift's client against its LocalNode.

use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use canbus::hub::HubHandle;
use canbus::Bus;
use canopen::sdo::abort::AbortCode;
use canopen::sdo::client::{ClientConfig, Transfer};
use canopen::sdo::clients::{SdoClients, TransferOptions};
use canopen::sdo::serve::serve_sdo;
use canopen::sdo::server::ServerConfig;
use testkit::{interop_script, python};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::Command;

fn script(python: &std::path::Path, name: &str, hub: &HubHandle, node: u8) -> Command {
    let addr = hub.local_addr();
    let mut cmd = Command::new(python);
    cmd.arg(interop_script(name))
        .args([
            addr.ip().to_string(),
            addr.port().to_string(),
            node.to_string(),
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    cmd
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_canopen_client_against_canlift_server() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let od = testkit::sample::dictionary();
    let url = testkit::hub_url(&hub, "can0");
    let server = serve_sdo(
        Bus::open(&url).await.unwrap(),
        Arc::new(Mutex::new(od)),
        9,
        ServerConfig::default(),
    );
    let out = tokio::time::timeout(
        Duration::from_secs(180),
        script(&python, "sdo_client.py", &hub, 9).output(),
    )
    .await
    .expect("python-canopen finished in time")
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && stdout.contains("OK"),
        "python-canopen client failed: {}\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("size 65536: ok"), "{stdout}");
    server.abort();
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn canlift_client_against_python_canopen_local_node() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let mut child = script(&python, "local_node.py", &hub, 12).spawn().unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let ready = tokio::time::timeout(Duration::from_secs(30), lines.next_line())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(ready.as_deref(), Some("READY"));
    let url = testkit::hub_url(&hub, "can0");
    let config = ClientConfig {
        timeout: Duration::from_secs(2),
        ..ClientConfig::default()
    };
    let sdo = SdoClients::new(Bus::open(&url).await.unwrap(), config);

    assert_eq!(
        sdo.read::<String>(12, 0x1008, 0).await.unwrap(),
        "python-canopen"
    );
    sdo.write(12, 0x2001, 0, 0xDEAD_BEEFu32).await.unwrap();
    assert_eq!(sdo.read::<u32>(12, 0x2001, 0).await.unwrap(), 0xDEAD_BEEF);
    sdo.write(12, 0x2002, 0, -1234i16).await.unwrap();
    assert_eq!(sdo.read::<i16>(12, 0x2002, 0).await.unwrap(), -1234);
    for n in [1usize, 4, 5, 7, 8, 100, 889, 4096, 65536] {
        let data: Vec<u8> = (0..n).map(|i| (i * 31 + n) as u8).collect();
        for how in [Transfer::Normal, Transfer::Segmented] {
            let options = TransferOptions {
                how,
                ..TransferOptions::default()
            };
            sdo.write_with(12, 0x2000, 0, data.clone(), options)
                .await
                .unwrap();
            let back = sdo.read_with(12, 0x2000, 0, options).await.unwrap();
            assert_eq!(back, data, "{n} bytes {how:?}");
        }
    }
    let err = sdo.read_raw(12, 0x3000, 0).await.unwrap_err();
    assert_eq!(err.abort_code(), AbortCode::NO_OBJECT);
    let err = sdo.write(12, 0x1008, 0, 1u8).await.unwrap_err();
    assert_eq!(err.abort_code(), AbortCode::READ_ONLY);
    drop(child.stdin.take());
    let _ = tokio::time::timeout(Duration::from_secs(10), child.wait()).await;
    hub.shutdown().await;
}

#[test]
fn python_canopen_imports_our_exported_eds() {
    let Some(python) = python() else { return };
    let fixture =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/eds/canopennode-style.eds");
    let description = canopen::eds::import_file(&fixture, Some(5))
        .unwrap()
        .description;
    let dir = testkit::scratch();
    let exported = dir.path().join("exported.eds");
    std::fs::write(&exported, canopen::eds::export(&description, false)).unwrap();
    let out = std::process::Command::new(python)
        .arg(interop_script("read_eds.py"))
        .arg(&exported)
        .args([
            "5", "1014:00", "1200:01", "1200:02", "1018:01", "1017:00", "1008:00",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let expected = [
        "1014:00 COB-ID EMCY 133",
        "1200:01 COB-ID client to server (rx) 1541",
        "1200:02 COB-ID server to client (tx) 1413",
        "1018:01 Vendor-ID 1050",
        "1017:00 Producer heartbeat time 1000",
        "1008:00 Manufacturer device name canlift lift controller",
    ];
    assert_eq!(stdout.lines().collect::<Vec<_>>(), expected);
}
