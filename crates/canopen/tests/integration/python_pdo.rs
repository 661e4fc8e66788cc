//! PDOs configured by python-canopen's PDO API (over SDO, from an EDS canlift exports) on a
//! canlift LocalNode: it receives our TPDOs (event-driven and SYNC-driven), we consume its RPDO.

use std::process::Stdio;
use std::time::Duration;

use canbus::Bus;
use canopen::eds::{export, DeviceDescription};
use canopen::node::{LocalNode, NodeConfig};
use canopen::od::{Access, Object, ObjectDictionary, Variable};
use canopen::types::{DataType, Value};
use testkit::{interop_script, python};
use tokio::io::{AsyncBufReadExt, BufReader};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_canopen_configures_and_uses_our_pdos() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let addr = hub.local_addr();
    let url = testkit::hub_url(&hub, "can0");
    let mut od = ObjectDictionary::new();
    for (index, name, ty) in [
        (0x2000, "Car position", DataType::Unsigned16),
        (0x2001, "Trip counter", DataType::Unsigned32),
        (0x2100, "Setpoint", DataType::Unsigned16),
    ] {
        od.insert(Object::var(
            index,
            Variable::new(name, ty, Access::Rw).mappable(),
        ));
    }
    let node = LocalNode::start(Bus::open(&url).await.unwrap(), od, NodeConfig::new(10));
    // python-canopen needs the node's dictionary: export it as an EDS.
    let dir = testkit::scratch();
    let eds = dir.path().join("node10.eds");
    let description = DeviceDescription {
        od: node.od().lock().unwrap().clone(),
        ..DeviceDescription::default()
    };
    std::fs::write(&eds, export(&description, false)).unwrap();

    let mut child = tokio::process::Command::new(python)
        .arg(interop_script("pdo_master.py"))
        .args([addr.ip().to_string(), addr.port().to_string(), "10".into()])
        .arg(&eds)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    macro_rules! next {
        () => {
            match tokio::time::timeout(Duration::from_secs(15), lines.next_line()).await {
                Ok(Ok(Some(line))) => line,
                other => panic!("python stopped early: {other:?}"),
            }
        };
    }
    assert_eq!(next!(), "CONFIGURED");
    node.set_value(0x2001, 0, &Value::Uint(777)).unwrap();
    node.set_value(0x2000, 0, &Value::Uint(1234)).unwrap();
    assert_eq!(next!(), "TPDO1 1234");
    assert_eq!(next!(), "RPDO-SENT");
    let mut stored = Value::Uint(0);
    // Up to 5 s: on a loaded CI machine python, the hub and the node share two cores.
    for _ in 0..250 {
        stored = node.value(0x2100, 0).unwrap();
        if stored == Value::Uint(4321) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(stored, Value::Uint(4321), "RPDO stored in the dictionary");
    assert_eq!(next!(), "TPDO2 777");
    assert_eq!(next!(), "OK");
    let _ = child.wait().await;
    node.stop().await;
    hub.shutdown().await;
}
