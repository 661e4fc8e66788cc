use std::sync::{Arc, Mutex};

use super::*;
use crate::cob::restricted;

fn dictionary() -> ObjectDictionary {
    let mut od = ObjectDictionary::new();
    for (index, ty, access) in [
        (0x2000, DataType::Unsigned16, Access::Rw),
        (0x2001, DataType::Unsigned32, Access::Rw),
        (0x2002, DataType::Unsigned8, Access::Ro),
        (0x2003, DataType::Unsigned32, Access::Rw),
    ] {
        let mut v = Variable::new(format!("Object {index:04X}"), ty, access);
        if index != 0x2003 {
            v = v.mappable();
        }
        od.insert(Object::var(index, v));
    }
    add_pdo_objects(&mut od, 5, 4, 4);
    od.guard(Arc::new(PdoGuard));
    od
}

fn w32(od: &mut ObjectDictionary, index: u16, sub: u8, v: u32) -> Result<(), AbortCode> {
    od.write(index, sub, &v.to_le_bytes())
}

fn entry(index: u16, sub: u8, bits: u8) -> u32 {
    MapEntry { index, sub, bits }.to_u32()
}

/// Map `entries` into TPDO `n` (from 0) by the CiA 301 procedure, with transmission type
/// `ttype`, inhibit (100 µs units) and event timer (ms).
fn map_tpdo(
    od: &mut ObjectDictionary,
    n: u16,
    entries: &[u32],
    ttype: u8,
    inhibit: u16,
    timer: u16,
) {
    let cob = od.get_u32(TPDO_COMM + n, 1).unwrap() & 0x7FF;
    w32(od, TPDO_COMM + n, 1, cob | COB_INVALID).unwrap();
    od.write(TPDO_COMM + n, 2, &[ttype]).unwrap();
    od.write(TPDO_COMM + n, 3, &inhibit.to_le_bytes()).unwrap();
    od.write(TPDO_COMM + n, 5, &timer.to_le_bytes()).unwrap();
    od.write(TPDO_MAP + n, 0, &[0]).unwrap();
    for (i, e) in entries.iter().enumerate() {
        w32(od, TPDO_MAP + n, i as u8 + 1, *e).unwrap();
    }
    od.write(TPDO_MAP + n, 0, &[entries.len() as u8]).unwrap();
    w32(od, TPDO_COMM + n, 1, cob).unwrap();
}

/// One identifier, one producer: a TPDO moves onto no other PDO's identifier of its node, an
/// RPDO onto no TPDO's; two RPDOs may consume one frame.
#[test]
fn a_pdo_moves_onto_no_identifier_the_node_produces_or_consumes_otherwise() {
    let mut od = dictionary();
    // TPDO 2 (285h) and RPDO 2 (305h) closed first, as the procedure has it.
    w32(&mut od, TPDO_COMM + 1, 1, COB_INVALID | 0x285).unwrap();
    w32(&mut od, RPDO_COMM + 1, 1, COB_INVALID | 0x305).unwrap();
    let refused = Err(AbortCode::INVALID_VALUE);
    assert_eq!(w32(&mut od, TPDO_COMM + 1, 1, 0x185), refused, "TPDO 1's");
    assert_eq!(w32(&mut od, TPDO_COMM + 1, 1, 0x205), refused, "RPDO 1's");
    assert_eq!(w32(&mut od, RPDO_COMM + 1, 1, 0x185), refused, "TPDO 1's");
    assert_eq!(w32(&mut od, RPDO_COMM + 1, 1, 0x205), Ok(()), "RPDO 1's");
    assert_eq!(w32(&mut od, TPDO_COMM + 1, 1, 0x1A5), Ok(()));
    // A closed PDO holds no identifier.
    w32(&mut od, TPDO_COMM, 1, COB_INVALID | 0x185).unwrap();
    w32(&mut od, TPDO_COMM + 1, 1, COB_INVALID | 0x1A5).unwrap();
    assert_eq!(w32(&mut od, TPDO_COMM + 1, 1, 0x185), Ok(()));
}

#[test]
fn the_mapping_procedure_and_its_aborts() {
    let mut od = dictionary();
    // The PDO is valid: its mapping cannot change, nor its identifier.
    assert_eq!(
        w32(&mut od, TPDO_MAP, 1, entry(0x2000, 0, 16)),
        Err(AbortCode::UNSUPPORTED_ACCESS)
    );
    assert_eq!(
        od.write(TPDO_MAP, 0, &[1]),
        Err(AbortCode::UNSUPPORTED_ACCESS)
    );
    assert_eq!(
        w32(&mut od, TPDO_COMM, 1, 0x190),
        Err(AbortCode::INVALID_VALUE)
    );
    assert_eq!(
        od.write(TPDO_COMM, 2, &[245]),
        Err(AbortCode::INVALID_VALUE)
    );
    w32(&mut od, TPDO_COMM, 1, 0x185 | COB_INVALID).unwrap();
    // Count not 0 yet? It is 0 by default; set a count first to see the rule.
    w32(&mut od, TPDO_MAP, 1, entry(0x2000, 0, 16)).unwrap();
    od.write(TPDO_MAP, 0, &[1]).unwrap();
    assert_eq!(
        w32(&mut od, TPDO_MAP, 2, entry(0x2001, 0, 32)),
        Err(AbortCode::UNSUPPORTED_ACCESS),
        "count must be 0"
    );
    od.write(TPDO_MAP, 0, &[0]).unwrap();
    assert_eq!(
        w32(&mut od, TPDO_MAP, 2, entry(0x2003, 0, 32)),
        Err(AbortCode::NOT_MAPPABLE),
        "not PDO-mappable"
    );
    assert_eq!(
        w32(&mut od, TPDO_MAP, 2, entry(0x2100, 0, 32)),
        Err(AbortCode::NOT_MAPPABLE),
        "no such object"
    );
    assert_eq!(
        w32(&mut od, TPDO_MAP, 2, entry(0x2001, 0, 16)),
        Err(AbortCode::NOT_MAPPABLE),
        "wrong length"
    );
    assert_eq!(
        w32(&mut od, RPDO_MAP, 1, entry(0x2002, 0, 8)),
        Err(AbortCode::UNSUPPORTED_ACCESS),
        "RPDO1 valid"
    );
    w32(&mut od, RPDO_COMM, 1, 0x205 | COB_INVALID).unwrap();
    assert_eq!(
        w32(&mut od, RPDO_MAP, 1, entry(0x2002, 0, 8)),
        Err(AbortCode::NOT_MAPPABLE),
        "read-only into an RPDO"
    );
    w32(&mut od, TPDO_MAP, 2, entry(0x2001, 0, 32)).unwrap();
    w32(&mut od, TPDO_MAP, 3, entry(0x2001, 0, 32)).unwrap();
    assert_eq!(
        od.write(TPDO_MAP, 0, &[3]),
        Err(AbortCode::PDO_LENGTH),
        "80 bits"
    );
    w32(&mut od, TPDO_MAP, 3, entry(0x0005, 0, 8)).unwrap(); // dummy UNSIGNED8
    od.write(TPDO_MAP, 0, &[3]).unwrap();
    w32(&mut od, TPDO_COMM, 1, 0x185).unwrap();
    let engine = PdoEngine::configure(&od, Instant::now());
    assert_eq!(engine.tpdos.len(), 1);
    assert_eq!(engine.tpdos[0].map.len(), 3);
    assert!(
        engine.rpdos.is_empty(),
        "RPDO1 is invalid, the others have no mapping"
    );
}

#[test]
fn event_driven_tpdo_with_inhibit_and_event_timer() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut od = dictionary();
    map_tpdo(
        &mut od,
        0,
        &[entry(0x2000, 0, 16), entry(0x2001, 0, 32)],
        254,
        100,
        0,
    ); // 10 ms inhibit
    let mut pdo = PdoEngine::configure(&od, t0);
    let (mut out, mut ev) = (Vec::new(), Vec::new());
    assert_eq!(pdo.poll_timeout(), None, "nothing to do until a change");
    od.set(0x2000, 0, &0x1234u16.to_le_bytes()).unwrap();
    pdo.on_change(0x2000, 0, t0);
    assert_eq!(pdo.poll_timeout(), Some(t0));
    pdo.handle_timeout(&od, t0, &mut out, &mut ev);
    assert_eq!(
        out,
        vec![Frame::standard(0x185, &[0x34, 0x12, 0, 0, 0, 0]).unwrap()]
    );
    out.clear();
    // Two changes inside the inhibit time collapse into one frame with the latest values.
    od.set(0x2001, 0, &7u32.to_le_bytes()).unwrap();
    pdo.on_change(0x2001, 0, t0 + ms(2));
    od.set(0x2001, 0, &8u32.to_le_bytes()).unwrap();
    pdo.on_change(0x2001, 0, t0 + ms(3));
    assert_eq!(pdo.poll_timeout(), Some(t0 + ms(10)));
    pdo.handle_timeout(&od, t0 + ms(9), &mut out, &mut ev);
    assert!(out.is_empty());
    pdo.handle_timeout(&od, t0 + ms(10), &mut out, &mut ev);
    assert_eq!(
        out,
        vec![Frame::standard(0x185, &[0x34, 0x12, 8, 0, 0, 0]).unwrap()]
    );
    out.clear();
    pdo.on_change(0x2003, 0, t0 + ms(11));
    assert_eq!(pdo.poll_timeout(), None, "unmapped objects do not trigger");

    // Event timer 100 ms: sent without changes.
    map_tpdo(&mut od, 1, &[entry(0x2000, 0, 16)], 255, 0, 100);
    let mut pdo = PdoEngine::configure(&od, t0);
    assert_eq!(pdo.poll_timeout(), Some(t0 + ms(100)));
    for k in 1..=3 {
        pdo.handle_timeout(&od, t0 + ms(100 * k), &mut out, &mut ev);
    }
    assert_eq!(out.len(), 3);
    assert!(out.iter().all(|f| f.id() == CanId::Standard(0x285)));
}

#[test]
fn synchronous_tpdos_and_sync_start() {
    let t0 = Instant::now();
    let mut od = dictionary();
    map_tpdo(&mut od, 0, &[entry(0x2000, 0, 16)], 2, 0, 0); // every 2nd SYNC
    assert_eq!(
        od.write(TPDO_COMM, 6, &[3]),
        Err(AbortCode::INVALID_VALUE),
        "valid: start value fixed"
    );
    let cob = 0x185;
    w32(&mut od, TPDO_COMM, 1, cob | COB_INVALID).unwrap();
    od.write(TPDO_COMM, 6, &[3]).unwrap(); // start at SYNC counter 3
    w32(&mut od, TPDO_COMM, 1, cob).unwrap();
    map_tpdo(&mut od, 1, &[entry(0x2000, 0, 16)], 0, 0, 0); // acyclic synchronous
    let mut pdo = PdoEngine::configure(&od, t0);
    let mut out = Vec::new();
    let mut sent = Vec::new();
    for counter in 1..=7u8 {
        if counter == 4 {
            pdo.on_change(0x2000, 0, t0);
        }
        pdo.on_sync(&mut od, Some(counter), t0, &mut out);
        sent.extend(out.drain(..).map(|f| (counter, f.id().as_raw())));
    }
    assert_eq!(sent, vec![(3, 0x185), (4, 0x285), (5, 0x185), (7, 0x185)]);
}

#[test]
fn rpdos_write_the_dictionary_buffer_for_sync_and_time_out() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut od = dictionary();
    let seen = Arc::new(Mutex::new(Vec::new()));
    let log = seen.clone();
    od.watch(Arc::new(move |i, s| log.lock().unwrap().push((i, s))));
    // RPDO1: async, 0x2000 + 0x2001, 250 ms timeout. RPDO2: synchronous, 0x2001.
    w32(&mut od, RPDO_COMM, 1, 0x205 | COB_INVALID).unwrap();
    od.write(RPDO_COMM, 5, &250u16.to_le_bytes()).unwrap();
    w32(&mut od, RPDO_MAP, 1, entry(0x2000, 0, 16)).unwrap();
    w32(&mut od, RPDO_MAP, 2, entry(0x0005, 0, 8)).unwrap();
    w32(&mut od, RPDO_MAP, 3, entry(0x2001, 0, 32)).unwrap();
    od.write(RPDO_MAP, 0, &[3]).unwrap();
    w32(&mut od, RPDO_COMM, 1, 0x205).unwrap();
    w32(&mut od, RPDO_COMM + 1, 1, 0x305 | COB_INVALID).unwrap();
    od.write(RPDO_COMM + 1, 2, &[1]).unwrap();
    w32(&mut od, RPDO_MAP + 1, 1, entry(0x2001, 0, 32)).unwrap();
    od.write(RPDO_MAP + 1, 0, &[1]).unwrap();
    w32(&mut od, RPDO_COMM + 1, 1, 0x305).unwrap();
    let mut pdo = PdoEngine::configure(&od, t0);
    assert_eq!(
        pdo.rpdo_ids(),
        vec![CanId::Standard(0x205), CanId::Standard(0x305)]
    );
    assert!(pdo.is_rpdo(CanId::Standard(0x305)) && !pdo.is_rpdo(CanId::Standard(0x405)));
    seen.lock().unwrap().clear();
    let mut ev = Vec::new();
    let f = Frame::standard(0x205, &[0x10, 0x27, 0xFF, 1, 0, 0, 0]).unwrap();
    assert!(pdo.handle_frame(&mut od, &f, t0, &mut ev));
    assert_eq!(od.get_value(0x2000, 0).unwrap(), Value::Uint(10_000));
    assert_eq!(od.get_value(0x2001, 0).unwrap(), Value::Uint(1));
    assert_eq!(
        *seen.lock().unwrap(),
        vec![(0x2000, 0), (0x2001, 0)],
        "watchers fire"
    );
    // Too short: not processed; too long: processed and reported.
    assert!(pdo.handle_frame(
        &mut od,
        &Frame::standard(0x205, &[1, 2]).unwrap(),
        t0,
        &mut ev
    ));
    assert!(pdo.handle_frame(
        &mut od,
        &Frame::standard(0x205, &[1, 0, 0, 2, 0, 0, 0, 9]).unwrap(),
        t0,
        &mut ev
    ));
    assert_eq!(
        ev,
        vec![
            PdoEvent::LengthError { rpdo: 1 },
            PdoEvent::LengthExceeded { rpdo: 1 }
        ]
    );
    assert_eq!(od.get_value(0x2001, 0).unwrap(), Value::Uint(2));
    ev.clear();
    // Synchronous RPDO: stored at the next SYNC.
    pdo.handle_frame(
        &mut od,
        &Frame::standard(0x305, &[9, 0, 0, 0]).unwrap(),
        t0,
        &mut ev,
    );
    assert_eq!(od.get_value(0x2001, 0).unwrap(), Value::Uint(2));
    pdo.on_sync(&mut od, None, t0, &mut Vec::new());
    assert_eq!(od.get_value(0x2001, 0).unwrap(), Value::Uint(9));
    // Receive timeout 250 ms after the last RPDO1.
    assert_eq!(pdo.poll_timeout(), Some(t0 + ms(250)));
    pdo.handle_timeout(&od, t0 + ms(250), &mut Vec::new(), &mut ev);
    assert_eq!(ev, vec![PdoEvent::Timeout { rpdo: 1 }]);
    assert_eq!(PdoEvent::Timeout { rpdo: 1 }.emcy_code(), 0x8250);
    assert_eq!(pdo.poll_timeout(), None, "one report per silence");
    assert!(!pdo.handle_frame(
        &mut od,
        &Frame::standard(0x206, &[0; 8]).unwrap(),
        t0,
        &mut ev
    ));
}

#[test]
fn restricted_identifiers_are_refused_except_0x180() {
    let mut od = dictionary();
    w32(&mut od, TPDO_COMM + 1, 1, 0x285 | COB_INVALID).unwrap();
    for id in [
        0x000, 0x07F, 0x101, 0x17F, 0x581, 0x601, 0x6E0, 0x705, 0x7E5,
    ] {
        assert_eq!(
            w32(&mut od, TPDO_COMM + 1, 1, id),
            Err(AbortCode::INVALID_VALUE),
            "{id:X}"
        );
    }
    w32(&mut od, TPDO_COMM + 1, 1, 0x180).unwrap();
    w32(&mut od, TPDO_COMM + 1, 1, 0x180 | COB_INVALID).unwrap();
    w32(&mut od, TPDO_COMM + 1, 1, 0x2000_0601).unwrap();
    assert!(restricted(0x77F) && !restricted(0x180) && !restricted(0x181) && !restricted(0x580));
    assert!(
        !restricted(0x081) && !restricted(0x080) && !restricted(0x100),
        "EMCY, SYNC and TIME are configurable"
    );
}

#[test]
fn remote_requests_for_types_252_and_253() {
    let t0 = Instant::now();
    let mut od = dictionary();
    map_tpdo(&mut od, 0, &[entry(0x2000, 0, 16)], 253, 0, 0);
    map_tpdo(&mut od, 1, &[entry(0x2000, 0, 16)], 252, 0, 0);
    // TPDO3 refuses remote requests (bit 30 set).
    map_tpdo(&mut od, 2, &[entry(0x2000, 0, 16)], 253, 0, 0);
    w32(&mut od, TPDO_COMM + 2, 1, 0x385 | COB_INVALID).unwrap();
    w32(&mut od, TPDO_COMM + 2, 1, 0x385 | 0x4000_0000).unwrap();
    let mut pdo = PdoEngine::configure(&od, t0);
    od.set(0x2000, 0, &7u16.to_le_bytes()).unwrap();
    let mut out = Vec::new();
    let rtr = |id| Frame::remote(CanId::Standard(id), 2).unwrap();
    assert!(pdo.handle_remote(&od, &rtr(0x185), t0, &mut out));
    assert_eq!(
        out,
        vec![Frame::standard(0x185, &[7, 0]).unwrap()],
        "253: at once"
    );
    out.clear();
    assert!(pdo.handle_remote(&od, &rtr(0x285), t0, &mut out));
    assert!(out.is_empty(), "252: waits for SYNC");
    od.set(0x2000, 0, &8u16.to_le_bytes()).unwrap();
    pdo.on_sync(&mut od, None, t0, &mut out);
    assert_eq!(out, vec![Frame::standard(0x285, &[8, 0]).unwrap()]);
    out.clear();
    assert!(pdo.handle_remote(&od, &rtr(0x385), t0, &mut out));
    assert!(out.is_empty(), "remote requests not allowed");
    assert!(
        !pdo.handle_remote(&od, &rtr(0x485), t0, &mut out),
        "not a TPDO of ours"
    );
}

#[test]
fn pdo_values_split_by_the_mapping() {
    let map = [
        MapEntry {
            index: 0x2001,
            sub: 0,
            bits: 32,
        },
        MapEntry {
            index: 0x0005,
            sub: 0,
            bits: 8,
        },
        MapEntry {
            index: 0x2002,
            sub: 0,
            bits: 16,
        },
    ];
    let id = CanId::Standard(0x186);
    let v = PdoValues::split(id, &map, &[0x78, 0x56, 0x34, 0x12, 0xEE, 0xFD, 0xFF]).unwrap();
    assert_eq!(v.value::<u32>(0x2001, 0), Some(0x1234_5678));
    assert_eq!(v.value::<i16>(0x2002, 0), Some(-3));
    assert_eq!(
        v.get(0x0005, 0),
        Some(&[0xEE][..]),
        "dummy entries keep their place"
    );
    assert_eq!(v.value::<u8>(0x2001, 0), None, "another size");
    assert_eq!(v.get(0x2003, 0), None);
    assert_eq!(
        PdoValues::split(id, &map, &[0; 6]),
        None,
        "shorter than the mapping"
    );
}
