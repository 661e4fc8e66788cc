use super::*;

#[test]
fn virtual_inputs_round_trip() {
    for floor in 1..=32 {
        for kind in [CallKind::Car, CallKind::HallUp, CallKind::HallDown] {
            for lift in 1..=8 {
                let pressed = virtual_input(lift, floor, kind, true);
                assert_eq!(
                    decode_virtual_input(pressed),
                    Some((1 << (lift - 1), floor, kind))
                );
                assert_eq!(
                    decode_virtual_input(virtual_input(lift, floor, kind, false)),
                    None
                );
            }
        }
    }
    // CiA 417-4 §4.3.1 layout: hall call up at floor 3 for lift 1, door 1, call request.
    assert_eq!(
        virtual_input(1, 3, CallKind::HallUp, true),
        0x01_10_03_01_01_02
    );
    // Defect (10b) and not installed (11b) are no requests; nor is a generic input.
    assert_eq!(decode_virtual_input(0x02_10_03_01_01_02), None);
    assert_eq!(decode_virtual_input(0x01_10_03_01_01_01), None);
}

#[test]
fn buttons_fill_eight_per_group() {
    assert_eq!(button(1, CallKind::HallUp), (0x6100, 1));
    assert_eq!(button(9, CallKind::HallDown), (0x6101, 1));
    assert_eq!(button(32, CallKind::Car), (0x6107, 8));
}

#[test]
fn settings_are_checked() {
    let ok = SimConfig::default();
    assert!(ok.check().is_ok());
    for bad in [
        SimConfig {
            floors: 1,
            ..ok.clone()
        },
        SimConfig {
            floors: 33,
            ..ok.clone()
        },
        SimConfig {
            lifts: 9,
            ..ok.clone()
        },
        SimConfig {
            speed: 0.0,
            ..ok.clone()
        },
        SimConfig {
            io_node: Some(1),
            ..ok.clone()
        },
        SimConfig {
            node_id: 0,
            ..ok.clone()
        },
    ] {
        assert!(bad.check().is_err(), "{bad:?}");
    }
    let no_io = SimConfig {
        io_node: None,
        floors: 100,
        ..ok
    };
    assert!(no_io.check().is_ok());
}

#[test]
fn further_sdo_channels_need_free_identifiers() {
    let id = CanId::Standard;
    let with = |channels: &[(u16, u16)]| SimConfig {
        sdo_servers: channels.iter().map(|&(q, r)| (id(q), id(r))).collect(),
        ..SimConfig::default()
    };
    assert!(with(&[(0x6A1, 0x6C1), (0x6A2, 0x6C2)]).check().is_ok());
    for bad in [
        // The I/O node's default channel, and another node's.
        with(&[(0x60C, 0x58C)]),
        with(&[(0x640, 0x5C0)]),
        // Restricted: heartbeats, LSS.
        with(&[(0x705, 0x6C1)]),
        with(&[(0x7E5, 0x6C1)]),
        // A PDO's: lift 1's TPDO 1 of the pre-defined set.
        with(&[(0x181, 0x6C1)]),
        // Twice, or request = response.
        with(&[(0x6A1, 0x6C1), (0x6A2, 0x6C1)]),
        with(&[(0x6A1, 0x6A1)]),
    ] {
        assert!(bad.check().is_err(), "{:?}", bad.sdo_servers);
    }
    // Lift 2's TPDOs are at 680h–682h.
    let two_lifts = SimConfig {
        lifts: 2,
        ..with(&[(0x681, 0x6C1)])
    };
    assert!(two_lifts.check().is_err());
    assert!(SimConfig {
        lifts: 1,
        ..two_lifts
    }
    .check()
    .is_ok());
    let extended = SimConfig {
        sdo_servers: vec![(CanId::Extended(0x1000), id(0x6C1))],
        ..SimConfig::default()
    };
    assert!(extended.check().is_err());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_controller_serves_its_further_sdo_channels() {
    let bus = "mem://sim-sdo-channels";
    let id = CanId::Standard;
    let config = SimConfig {
        sdo_servers: vec![(id(0x6A1), id(0x6C1))],
        ..SimConfig::default()
    };
    let sim = Simulator::start(bus, config).await.unwrap();
    let sdo = canopen::sdo::clients::SdoClients::with_channels(
        Bus::open(bus).await.unwrap(),
        Default::default(),
        &[(1, id(0x6A1), id(0x6C1))],
    );
    // Its 1201h says so, read on the channel itself.
    assert_eq!(sdo.read::<u32>(1, 0x1201, 1).await.unwrap(), 0x6A1);
    assert_eq!(sdo.read::<u32>(1, 0x1201, 2).await.unwrap(), 0x6C1);
    // A client on the default channel moves it (CiA 301 §7.5.2.33): not while it is valid;
    // closed, moved, opened again, it answers on its new identifier only.
    let default = canopen::sdo::clients::SdoClients::new(Bus::open(bus).await.unwrap(), fast());
    assert!(default.write::<u32>(1, 0x1201, 1, 0x6A5).await.is_err());
    default
        .write::<u32>(1, 0x1201, 1, 0x8000_06A1)
        .await
        .unwrap();
    default.write::<u32>(1, 0x1201, 1, 0x6A5).await.unwrap();
    let moved = canopen::sdo::clients::SdoClients::with_channels(
        Bus::open(bus).await.unwrap(),
        fast(),
        &[(1, id(0x6A5), id(0x6C1))],
    );
    assert_eq!(moved.read::<u32>(1, 0x1201, 1).await.unwrap(), 0x6A5);
    let old = canopen::sdo::clients::SdoClients::with_channels(
        Bus::open(bus).await.unwrap(),
        fast(),
        &[(1, id(0x6A1), id(0x6C1))],
    );
    assert!(old.read::<u32>(1, 0x1000, 0).await.is_err(), "closed");
    sim.stop().await;
}

/// A client that gives up on a silent channel after 200 ms.
fn fast() -> canopen::sdo::client::ClientConfig {
    canopen::sdo::client::ClientConfig {
        timeout: Duration::from_millis(200),
        ..Default::default()
    }
}

#[test]
fn the_exported_eds_describes_the_running_dictionary() {
    let config = SimConfig {
        lifts: 2,
        ..SimConfig::default()
    };
    let text = export_eds(&config, Device::Controller).unwrap();
    let imported = canopen::eds::import("sim.eds", &text, Some(1))
        .unwrap()
        .description;
    let od = imported.od;
    assert_eq!(od.get_value(0x1000, 0), Ok(Value::Uint(0x0001_01A1)));
    assert_eq!(od.get_value(0x4010, 4), Ok(Value::Int(11_500)));
    assert!(od.object(0x6D20).is_some(), "lift 2 trip counter");
    assert_eq!(od.variable(0x6520, 1).unwrap().name, "Trip counter [trips]");
    let io = export_eds(&config, Device::Io).unwrap();
    let io = canopen::eds::import("io.eds", &io, Some(12))
        .unwrap()
        .description
        .od;
    assert_eq!(io.get_value(0x1000, 0), Ok(Value::Uint(0x0008_01A1)));
    assert!(io.object(0x2000).is_some());
    // Identity like any real device: 1008h, 1009h, 100Ah.
    for (od, name) in [(&od, CONTROLLER_NAME), (&io, IO_NAME)] {
        assert_eq!(od.get_value(0x1008, 0), Ok(Value::Text(name.into())));
        assert_eq!(
            od.get_value(0x1009, 0),
            Ok(Value::Text("canlift simulator".into()))
        );
        let software = format!("canlift {}", env!("CARGO_PKG_VERSION"));
        assert_eq!(od.get_value(0x100A, 0), Ok(Value::Text(software)));
    }
}
