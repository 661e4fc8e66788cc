//! `canlift sdo` as a user runs it: the binary against a canlift SDO server on a hub.

use std::sync::{Arc, Mutex};

use canbus::Bus;
use canopen::sdo::serve::serve_sdo;
use canopen::sdo::server::ServerConfig;
use canopen::types::Value;
use testkit::sample::{self, BLOB, POSITION};

use crate::common;
use common::run as canlift;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn read_and_write_from_the_command_line() {
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let mut od = sample::dictionary();
    od.set_value(POSITION, 0, &Value::Uint(1000)).unwrap();
    let od = Arc::new(Mutex::new(od));
    let server = serve_sdo(
        Bus::open(&url).await.unwrap(),
        od.clone(),
        1,
        ServerConfig::default(),
    );

    let out = canlift(&["sdo", "--bus", &url, "read", "1", "0x2000", "0", "u16"]).await;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(String::from_utf8_lossy(&out.stdout), "1000\n");

    let out = canlift(&[
        "sdo", "--bus", &url, "write", "1", "0x2000", "0", "u16", "250",
    ])
    .await;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        od.lock().unwrap().get_value(POSITION, 0).unwrap(),
        Value::Uint(250)
    );

    let out = canlift(&["sdo", "--bus", &url, "read", "1", "0x1008", "0", "str"]).await;
    assert_eq!(String::from_utf8_lossy(&out.stdout), "lift controller\n");

    // Readable addresses: other forms, names from an EDS, the type from it too, mnemonics.
    let dir = testkit::scratch();
    let eds = dir.path().join("sample.eds");
    let description = canopen::eds::DeviceDescription {
        od: sample::dictionary(),
        ..Default::default()
    };
    std::fs::write(&eds, canopen::eds::export(&description, false)).unwrap();
    let eds = eds.to_str().unwrap();
    for object in [
        &["0x2000:0"][..],
        &["2000sub0"],
        &["0x200000"],
        &["car position"],
        &["Car pos"],
    ] {
        let mut args = vec!["sdo", "--bus", &url, "read", "1"];
        args.extend_from_slice(object);
        args.extend_from_slice(&["--eds", eds]);
        let out = canlift(&args).await;
        assert!(out.status.success(), "{object:?}: {out:?}");
        assert_eq!(String::from_utf8_lossy(&out.stdout), "250\n", "{object:?}");
    }
    let out = canlift(&[
        "sdo", "--bus", &url, "write", "1", "Setpoint", "0x1234", "--eds", eds,
    ])
    .await;
    assert!(out.status.success(), "{out:?}");
    let out = canlift(&[
        "sdo", "--bus", &url, "read", "1", "setpoint", "x32", "--eds", eds,
    ])
    .await;
    assert_eq!(String::from_utf8_lossy(&out.stdout), "0x00001234\n");
    let out = canlift(&["sdo", "--bus", &url, "read", "1", "0x1008:0", "vs"]).await;
    assert_eq!(
        String::from_utf8_lossy(&out.stdout),
        "\"lift controller\"\n"
    );
    let out = canlift(&["sdo", "--bus", &url, "write", "1", "0x2001:0", "7"]).await;
    assert!(!out.status.success(), "no type known without an EDS");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("give the TYPE"),
        "{out:?}"
    );
    let out = canlift(&["sdo", "--bus", &url, "read", "1", "Cheese"]).await;
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("neither an object address"),
        "{out:?}"
    );

    let (src, dst) = (dir.path().join("in.bin"), dir.path().join("out.bin"));
    let blob: Vec<u8> = (0..20_000u32).map(|i| (i % 251) as u8).collect();
    std::fs::write(&src, &blob).unwrap();
    let out = canlift(&[
        "sdo",
        "--bus",
        &url,
        "--block",
        "write",
        "1",
        "0x2002",
        "0",
        "--file",
        src.to_str().unwrap(),
    ])
    .await;
    assert!(out.status.success(), "{out:?}");
    let out = canlift(&[
        "sdo",
        "--bus",
        &url,
        "--block",
        "read",
        "1",
        "0x2002",
        "0",
        "--file",
        dst.to_str().unwrap(),
    ])
    .await;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(std::fs::read(&dst).unwrap(), blob);
    assert_eq!(
        od.lock().unwrap().get_value(BLOB, 0).unwrap(),
        Value::Bytes(blob)
    );

    // Errors name the object, node and CiA abort code, and fail the command.
    let out = canlift(&[
        "sdo", "--bus", &url, "write", "1", "0x1008", "0", "str", "x",
    ])
    .await;
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("1008:00 on node 1") && err.contains("06010002"),
        "{err}"
    );
    let out = canlift(&[
        "sdo", "--bus", &url, "write", "1", "0x2000", "0", "u16", "70000",
    ])
    .await;
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("70000 is too high for UNSIGNED16"));

    server.abort();
    hub.shutdown().await;
}
