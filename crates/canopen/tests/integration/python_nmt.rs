//! NMT, heartbeat, EMCY and LSS interop with python-canopen through the hub.

use std::process::Stdio;
use std::time::Duration;

use canbus::hub::HubHandle;
use canbus::Bus;
use canopen::heartbeat::{HeartbeatEvent, NodeState};
use canopen::master::{Master, MasterEvent};
use canopen::nmt::NmtState;
use canopen::node::{LocalNode, NodeConfig};
use canopen::od::ObjectDictionary;
use testkit::{interop_script, python};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader, Lines};
use tokio::process::{Child, ChildStdout, Command};

fn spawn(
    python: &std::path::Path,
    script: &str,
    hub: &HubHandle,
    node: u8,
) -> (Child, Lines<BufReader<ChildStdout>>) {
    let addr = hub.local_addr();
    let mut child = Command::new(python)
        .arg(interop_script(script))
        .args([
            addr.ip().to_string(),
            addr.port().to_string(),
            node.to_string(),
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let lines = BufReader::new(child.stdout.take().unwrap()).lines();
    (child, lines)
}

async fn line(lines: &mut Lines<BufReader<ChildStdout>>) -> String {
    tokio::time::timeout(Duration::from_secs(15), lines.next_line())
        .await
        .expect("python answered in time")
        .unwrap()
        .expect("python still running")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_canopen_master_commands_a_canlift_node() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let (mut child, mut lines) = spawn(&python, "nmt_master.py", &hub, 21);
    assert_eq!(line(&mut lines).await, "READY");
    let url = testkit::hub_url(&hub, "can0");
    let config = NodeConfig {
        heartbeat_ms: 50,
        ..NodeConfig::new(21)
    };
    let node = LocalNode::start(
        Bus::open(&url).await.unwrap(),
        ObjectDictionary::new(),
        config,
    );
    assert_eq!(line(&mut lines).await, "BOOTUP");
    assert_eq!(line(&mut lines).await, "HEARTBEAT OPERATIONAL");
    assert_eq!(line(&mut lines).await, "HEARTBEAT STOPPED");
    assert_eq!(line(&mut lines).await, "HEARTBEAT PRE-OPERATIONAL");
    assert_eq!(node.nmt_state(), NmtState::PreOperational);
    assert_eq!(line(&mut lines).await, "WAIT-EMCY");
    node.set_error(0x4210, [0xAA, 0xBB, 0, 0, 0]);
    assert_eq!(line(&mut lines).await, "EMCY 4210 09 aabb000000");
    assert_eq!(line(&mut lines).await, "OK");
    let _ = child.wait().await;
    node.stop().await;
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn canlift_master_hears_a_python_canopen_node() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let master = Master::open(&url, Default::default()).await.unwrap();
    let mut events = master.events();
    let (mut child, mut lines) = spawn(&python, "local_node.py", &hub, 12);
    assert_eq!(line(&mut lines).await, "READY");
    master.monitor(12, Duration::from_millis(500));
    let wait = |events: &mut tokio::sync::broadcast::Receiver<MasterEvent>,
                pred: fn(&MasterEvent) -> bool| {
        let mut events = events.resubscribe();
        async move {
            tokio::time::timeout(Duration::from_secs(5), async {
                loop {
                    if let Ok(e) = events.recv().await {
                        if pred(&e) {
                            return e;
                        }
                    }
                }
            })
            .await
            .expect("event in time")
        }
    };
    let started = wait(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::StateChanged {
                node: 12,
                new: NodeState::Operational,
                ..
            })
        )
    });
    master
        .nmt(canopen::nmt::NmtCommand::Start, 12)
        .await
        .unwrap();
    started.await;
    let emcy = wait(&mut events, |e| {
        matches!(e, MasterEvent::Emcy { node: 12, .. })
    });
    child
        .stdin
        .as_mut()
        .unwrap()
        .write_all(b"emcy 5000\n")
        .await
        .unwrap();
    child.stdin.as_mut().unwrap().flush().await.unwrap();
    let MasterEvent::Emcy { message, .. } = emcy.await else {
        unreachable!()
    };
    assert_eq!(
        (message.code, message.register, message.manufacturer),
        (0x5000, 0x01, [1, 2, 0, 0, 0])
    );
    // The python node goes away: the heartbeat table notices.
    let offline = wait(&mut events, |e| {
        matches!(
            e,
            MasterEvent::Heartbeat(HeartbeatEvent::Timeout { node: 12 })
        )
    });
    drop(child.stdin.take());
    let _ = child.wait().await;
    offline.await;
    assert_eq!(master.node_state(12), NodeState::Offline);
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_canopen_lss_master_configures_a_canlift_node() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let url = testkit::hub_url(&hub, "can0");
    let dir = testkit::scratch();
    let config = |serial: u32| NodeConfig {
        identity: [0x41A, 0x1000, 2, serial],
        storage: Some(dir.path().join(format!("{serial}.params"))),
        ..NodeConfig::new(canopen::lss::UNCONFIGURED)
    };
    let master = Master::open(&url, Default::default()).await.unwrap();
    let mut events = master.events();
    let low = LocalNode::start(
        Bus::open(&url).await.unwrap(),
        ObjectDictionary::new(),
        config(0x0300_0001),
    );
    let high = LocalNode::start(
        Bus::open(&url).await.unwrap(),
        ObjectDictionary::new(),
        config(0x0300_0002),
    );
    let (mut child, mut lines) = spawn(&python, "lss_master.py", &hub, 33);
    assert_eq!(line(&mut lines).await, "READY");
    assert_eq!(
        line(&mut lines).await,
        "FOUND 0000041A 00001000 00000002 03000001"
    );
    assert_eq!(line(&mut lines).await, "OK");
    let booted = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            if let Ok(MasterEvent::Heartbeat(HeartbeatEvent::BootUp { node: 33 })) =
                events.recv().await
            {
                return;
            }
        }
    });
    booted.await.expect("node 33 booted");
    assert_eq!(low.nmt_state(), NmtState::PreOperational);
    assert_eq!(
        high.nmt_state(),
        NmtState::Initialising,
        "the other one still waits"
    );
    assert_eq!(
        master.sdo().read::<u32>(33, 0x1018, 4).await.unwrap(),
        0x0300_0001
    );
    let _ = child.wait().await;
    low.stop().await;
    high.stop().await;
    hub.shutdown().await;
}
