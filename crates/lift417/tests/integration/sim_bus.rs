//! The simulator on a bus, driven as a portal or a service tool would: SDO writes to 0x5022 and
//! 0x5030, buttons on the I/O node, TPDOs and EMCY observed by a master.

// The simulator is the `sim` feature.
#![cfg(feature = "sim")]

use std::time::Duration;

use canbus::Bus;
use canopen::master::{Master, MasterEvent};
use canopen::sdo::client::ClientConfig;
use lift417::sim::{SimConfig, Simulator};

const SPEED: f64 = 25.0;

fn config() -> SimConfig {
    SimConfig {
        speed: SPEED,
        heartbeat_ms: 200,
        ..SimConfig::default()
    }
}

/// Any unsigned value up to 64 bits (UNSIGNED48 included), little-endian on the wire.
async fn read_uint(master: &Master, node: u8, index: u16, sub: u8) -> u64 {
    let bytes = master.sdo().read_raw(node, index, sub).await.unwrap();
    bytes
        .iter()
        .rev()
        .fold(0, |acc, b| acc << 8 | u64::from(*b))
}

async fn read_u32(master: &Master, node: u8, index: u16, sub: u8) -> u32 {
    read_uint(master, node, index, sub).await as u32
}

/// Wait (wall clock, polling by SDO) until `index:sub` of node 1 satisfies `pred`.
async fn until(master: &Master, index: u16, sub: u8, pred: impl Fn(u32) -> bool) -> u32 {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let v = read_u32(master, 1, index, sub).await;
        if pred(v) {
            return v;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{index:04X}:{sub} stuck at {v}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_passenger_call_by_sdo_makes_a_trip_seen_in_tpdos() {
    let url = "mem://sim-call";
    let sim = Simulator::start(url, config()).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    let mut frames = Bus::open(url).await.unwrap();
    // The device type of a CiA 417 call controller.
    assert_eq!(read_u32(&master, 1, 0x1000, 0).await, 0x0001_01A1);
    assert_eq!(read_u32(&master, 1, 0x6520, 1).await, 0);
    master
        .sdo()
        .write_raw(1, 0x5022, 0, &4u32.to_le_bytes())
        .await
        .unwrap();
    // Floor 9 does not exist: value too high.
    let err = master
        .sdo()
        .write_raw(1, 0x5022, 0, &9u32.to_le_bytes())
        .await
        .unwrap_err();
    assert!(err.to_string().contains("06090031"), "{err}");
    // TPDO1 (0x181): position and speed while travelling.
    let mut top_speed = 0i16;
    let mut last_position = 0u32;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while last_position < 11_500 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no arrival in TPDOs"
        );
        let Ok(Some(frame)) =
            tokio::time::timeout(Duration::from_secs(2), frames.receiver.recv_frame()).await
        else {
            continue;
        };
        if frame.raw_id() == 0x181 {
            let d = frame.data();
            let position = u32::from_le_bytes([d[0], d[1], d[2], d[3]]);
            let speed = i16::from_le_bytes([d[4], d[5]]);
            assert!(
                position >= last_position,
                "the car went back: {position} < {last_position}"
            );
            last_position = position;
            top_speed = top_speed.max(speed);
        }
    }
    assert!(top_speed > 500, "top speed {top_speed} mm/s");
    assert_eq!(until(&master, 0x6520, 1, |v| v == 1).await, 1);
    assert_eq!(read_u32(&master, 1, 0x6383, 1).await, 11_500);
    // Doors cycle, then the lift idles.
    until(&master, 0x4400, 1, |cycles| cycles == 1).await;
    assert_eq!(
        master.sdo().read::<u8>(1, 0x5024, 0).await.unwrap(),
        0,
        "idle"
    );
    assert_eq!(master.sdo().read::<u8>(1, 0x5023, 0).await.unwrap(), 4);
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn buttons_on_the_io_node_reach_the_controller_by_pdo() {
    let url = "mem://sim-buttons";
    let sim = Simulator::start(url, config()).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    // Hall call down at floor 6 (kind 2 in bits 8–11), pressed through the I/O node (node 12).
    master
        .sdo()
        .write_raw(12, 0x2000, 0, &0x0206u16.to_le_bytes())
        .await
        .unwrap();
    // The simulator handles the press asynchronously: the input shows the request shortly.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    while read_uint(&master, 12, 0x6100, 6).await >> 40 != 1 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the button was never requested"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    until(&master, 0x6520, 1, |v| v == 1).await;
    assert_eq!(read_u32(&master, 1, 0x6383, 1).await, 18_500);
    // The controller keeps the last virtual input it received.
    let mapped = read_uint(&master, 1, 0x6010, 0).await;
    assert_eq!(mapped & 0xFF, 0x02, "standard hall call");
    sim.stop().await;
}

/// A reset restores what the devices set up at boot: both reset (communication, then the whole
/// node), they start again by themselves, and the I/O node's buttons still reach the controller
/// through the PDO between them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_reset_the_nodes_start_by_themselves_with_their_pdos() {
    use canopen::nmt::NmtCommand;
    let url = "mem://sim-reset";
    let sim = Simulator::start(url, config()).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    for command in [NmtCommand::ResetCommunication, NmtCommand::ResetNode] {
        for node in [1, 12] {
            master.nmt(command, node).await.unwrap();
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        // Operational again (the heartbeat of 200 ms says 05h), the controller's RPDO1 mapped.
        assert_eq!(read_uint(&master, 1, 0x1600, 0).await, 1, "{command:?}");
        assert_eq!(
            read_u32(&master, 1, 0x1600, 1).await >> 16,
            0x6010,
            "{command:?}"
        );
        assert_eq!(read_uint(&master, 12, 0x1A00, 0).await, 1, "{command:?}");
    }
    let operational = canopen::heartbeat::NodeState::Operational;
    assert_eq!(master.node_state(1), operational, "the heartbeat says 05h");
    assert_eq!(master.node_state(12), operational);
    // Car call to floor 3 on the I/O node's button: it reaches the controller, which travels.
    master
        .sdo()
        .write_raw(12, 0x2000, 0, &0x0003u16.to_le_bytes())
        .await
        .unwrap();
    until(&master, 0x6520, 1, |v| v == 1).await;
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_injected_drive_fault_raises_and_clears_emcy() {
    let url = "mem://sim-fault";
    let sim = Simulator::start(url, config()).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    let mut events = master.events();
    master
        .sdo()
        .write_raw(1, 0x5022, 0, &8u32.to_le_bytes())
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    master.sdo().write_raw(1, 0x5030, 0, &[4]).await.unwrap();
    let emcy = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            if let Ok(MasterEvent::Emcy { node: 1, message }) = events.recv().await {
                return message;
            }
        }
    })
    .await
    .expect("EMCY");
    assert_eq!(emcy.code, 0xF001);
    assert_ne!(emcy.register & 1, 0);
    assert_eq!(master.sdo().read::<u8>(1, 0x1001, 0).await.unwrap() & 1, 1);
    // Fast stop, then out of service.
    until(&master, 0x5024, 0, |state| state == 4).await;
    assert_eq!(
        read_u32(&master, 1, 0x4401, 3).await,
        1,
        "drive faults counted"
    );
    assert_eq!(
        master.sdo().read::<u16>(1, 0x4402, 1).await.unwrap(),
        0xF001
    );
    master.sdo().write_raw(1, 0x5030, 0, &[0]).await.unwrap();
    let reset = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            if let Ok(MasterEvent::Emcy { node: 1, message }) = events.recv().await {
                return message;
            }
        }
    })
    .await
    .expect("EMCY error reset");
    assert_eq!(reset.code, 0);
    until(&master, 0x6520, 1, |v| v == 1).await;
    assert_eq!(read_u32(&master, 1, 0x6383, 1).await, 25_500);
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_lifts_live_at_the_cia_417_offsets() {
    let url = "mem://sim-lifts";
    let config = SimConfig {
        lifts: 2,
        ..config()
    };
    let sim = Simulator::start(url, config).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    // Lift 2's passenger call is 0x5022 + 100h; its objects are at +800h.
    master
        .sdo()
        .write_raw(1, 0x5122, 0, &3u32.to_le_bytes())
        .await
        .unwrap();
    until(&master, 0x6D20, 1, |v| v == 1).await;
    assert_eq!(read_u32(&master, 1, 0x6B83, 1).await, 8_000);
    assert_eq!(
        read_u32(&master, 1, 0x6520, 1).await,
        0,
        "lift 1 did not move"
    );
    assert_eq!(read_u32(&master, 1, 0x6383, 1).await, 1_000);
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn counters_survive_a_restart() {
    let scratch = testkit::scratch();
    let dir = scratch.path();
    let url = "mem://sim-restart";
    let config = SimConfig {
        state_dir: Some(dir.to_path_buf()),
        io_node: None,
        ..config()
    };
    let sim = Simulator::start(url, config.clone()).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    master
        .sdo()
        .write_raw(1, 0x5022, 0, &2u32.to_le_bytes())
        .await
        .unwrap();
    until(&master, 0x4400, 1, |cycles| cycles == 1).await;
    sim.stop().await;
    let sim = Simulator::start(url, config).await.unwrap();
    assert_eq!(
        read_u32(&master, 1, 0x6520, 1).await,
        1,
        "trip counter kept"
    );
    assert_eq!(read_u32(&master, 1, 0x4400, 1).await, 1, "door cycles kept");
    assert_eq!(
        read_u32(&master, 1, 0x4400, 3).await,
        1,
        "drive starts kept"
    );
    sim.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fault_given_at_start_is_reported_in_the_error_history() {
    let url = "mem://sim-start-fault";
    let config = SimConfig {
        faults: 2,
        ..config()
    };
    let sim = Simulator::start(url, config).await.unwrap();
    let master = Master::open(url, ClientConfig::default()).await.unwrap();
    until(&master, 0x5024, 0, |state| state == 4).await;
    assert_eq!(master.sdo().read::<u8>(1, 0x5030, 0).await.unwrap(), 2);
    until(&master, 0x1003, 1, |code| code & 0xFFFF == 0xFF04).await;
    // Manufacturer-specific class: bits 0 and 7 of the error register.
    assert_eq!(master.sdo().read::<u8>(1, 0x1001, 0).await.unwrap(), 0x81);
    assert!(
        read_uint(&master, 1, 0x6480, 1).await > 1000,
        "load above the overload limit"
    );
    assert_eq!(
        read_uint(&master, 1, 0x6482, 1).await,
        0b1000,
        "overload signalled"
    );
    sim.stop().await;
}
