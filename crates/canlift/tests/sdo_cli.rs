//! `canlift sdo` as a user runs it: the binary against a canlift SDO server on a hub.

use std::process::Output;
use std::sync::{Arc, Mutex};

use canbus::Bus;
use canopen::driver::serve_sdo;
use canopen::od::{Access, Object, ObjectDictionary, Variable};
use canopen::sdo::server::ServerConfig;
use canopen::types::{DataType, Value};

async fn canlift(args: &[&str]) -> Output {
    tokio::process::Command::new(env!("CARGO_BIN_EXE_canlift"))
        .args(args)
        .output()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn read_and_write_from_the_command_line() {
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let mut od = ObjectDictionary::new();
    od.insert(Object::var(
        0x1017,
        Variable::new("Producer heartbeat time", DataType::Unsigned16, Access::Rw)
            .with_value(Value::Uint(1000)),
    ));
    od.insert(Object::var(
        0x1008,
        Variable::new("Name", DataType::VisibleString, Access::Ro)
            .with_value(Value::Text("lift controller".into())),
    ));
    od.insert(Object::var(
        0x2000,
        Variable::new("Blob", DataType::Domain, Access::Rw),
    ));
    let od = Arc::new(Mutex::new(od));
    let server = serve_sdo(
        Bus::open(&url).await.unwrap(),
        od.clone(),
        1,
        ServerConfig::default(),
    );

    let out = canlift(&["sdo", "--bus", &url, "read", "1", "0x1017", "0", "u16"]).await;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(String::from_utf8_lossy(&out.stdout), "1000\n");

    let out = canlift(&[
        "sdo", "--bus", &url, "write", "1", "0x1017", "0", "u16", "250",
    ])
    .await;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        od.lock().unwrap().get_value(0x1017, 0).unwrap(),
        Value::Uint(250)
    );

    let out = canlift(&["sdo", "--bus", &url, "read", "1", "0x1008", "0", "str"]).await;
    assert_eq!(String::from_utf8_lossy(&out.stdout), "lift controller\n");

    let dir = std::env::temp_dir().join(format!("canlift-sdo-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (src, dst) = (dir.join("in.bin"), dir.join("out.bin"));
    let blob: Vec<u8> = (0..20_000u32).map(|i| (i % 251) as u8).collect();
    std::fs::write(&src, &blob).unwrap();
    let out = canlift(&[
        "sdo",
        "--bus",
        &url,
        "--block",
        "write",
        "1",
        "0x2000",
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
        "0x2000",
        "0",
        "--file",
        dst.to_str().unwrap(),
    ])
    .await;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(std::fs::read(&dst).unwrap(), blob);
    std::fs::remove_dir_all(&dir).unwrap();

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
        "sdo", "--bus", &url, "write", "1", "0x1017", "0", "u16", "70000",
    ])
    .await;
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("70000 is too high for UNSIGNED16"));

    server.abort();
    hub.shutdown().await;
}
