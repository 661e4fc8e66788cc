//! Process data objects (CiA 301 §7.2.2), sans-IO.
//!
//! The configuration lives in the object dictionary: RPDO communication 0x1400+n and mapping
//! 0x1600+n, TPDO communication 0x1800+n and mapping 0x1A00+n (n < 512). [`PdoGuard`] makes
//! network writes follow the CiA 301 mapping procedure (invalidate the COB-ID, set the count to
//! 0, write entries, set the count, validate) with CANopenNode's abort codes; [`PdoEngine`] is
//! rebuilt from the dictionary whenever those objects change.
//!
//! Transmission types: 0 (synchronous, acyclic: on the SYNC after an event), 1–240 (every n-th
//! SYNC, with the SYNC start value 0x1800 sub 6), 252 (remote request, sampled at the next SYNC),
//! 253 (remote request, at once), 254/255 (on change, with inhibit time sub 3 and event timer
//! sub 5; they answer remote requests too). Remote requests need COB-ID bit 30 clear, and a bus
//! that carries remote frames (SocketCAN, `mem://`; not socketcand). RPDOs of types 0–240
//! are applied at the next SYNC, 254/255 at once; sub 5 of an RPDO is its receive timeout.
//! Mapping granularity is 8 bits (like CANopenNode).

#[cfg(feature = "tokio")]
pub mod remote;

use std::collections::HashMap;
use std::time::{Duration, Instant};

use canbus::{CanId, Frame};

use crate::cob::{check_parameter_write, COB_INVALID};
use crate::od::{Access, Object, ObjectCode, ObjectDictionary, Variable, WriteGuard};
use crate::sdo::abort::AbortCode;
use crate::types::{DataType, Value};

/// First RPDO communication parameter index.
pub const RPDO_COMM: u16 = 0x1400;
/// First RPDO mapping index.
pub const RPDO_MAP: u16 = 0x1600;
/// First TPDO communication parameter index.
pub const TPDO_COMM: u16 = 0x1800;
/// First TPDO mapping index.
pub const TPDO_MAP: u16 = 0x1A00;
/// PDOs of each direction at most.
pub const MAX_PDOS: u16 = 512;
/// Mapping entries per PDO at most.
pub const MAX_ENTRIES: u8 = 64;

fn u32_var(name: &str, access: Access, value: u32) -> Variable {
    Variable::new(name, DataType::Unsigned32, access).with_value(Value::Uint(value.into()))
}

fn small_var(name: &str, ty: DataType, value: u64) -> Variable {
    Variable::new(name, ty, Access::Rw).with_value(Value::Uint(value))
}

/// Add `rpdos` RPDOs and `tpdos` TPDOs with the pre-defined connection set's COB-IDs
/// (RPDO1–4: 0x200/0x300/0x400/0x500 + node-ID, TPDO1–4: 0x180/0x280/0x380/0x480 + node-ID;
/// later ones start invalid), event-driven, with empty mappings.
pub fn add_pdo_objects(od: &mut ObjectDictionary, node_id: u8, rpdos: u16, tpdos: u16) {
    for (receive, count) in [(true, rpdos.min(MAX_PDOS)), (false, tpdos.min(MAX_PDOS))] {
        for n in 0..count {
            let (comm, map) = if receive {
                (RPDO_COMM + n, RPDO_MAP + n)
            } else {
                (TPDO_COMM + n, TPDO_MAP + n)
            };
            if od.object(comm).is_some() {
                continue;
            }
            let base: u32 = if receive { 0x200 } else { 0x180 };
            let cob = if n < 4 {
                base + 0x100 * u32::from(n) + u32::from(node_id)
            } else {
                COB_INVALID
            };
            let kind = if receive { "RPDO" } else { "TPDO" };
            let mut subs = vec![
                (
                    1u8,
                    u32_var(&format!("COB-ID used by {kind}"), Access::Rw, cob),
                ),
                (2, small_var("Transmission type", DataType::Unsigned8, 254)),
            ];
            if !receive {
                subs.push((3, small_var("Inhibit time", DataType::Unsigned16, 0)));
            }
            subs.push((
                5,
                small_var(
                    if receive {
                        "Event timer (receive timeout)"
                    } else {
                        "Event timer"
                    },
                    DataType::Unsigned16,
                    0,
                ),
            ));
            if !receive {
                subs.push((6, small_var("SYNC start value", DataType::Unsigned8, 0)));
            }
            od.insert(Object::composite(
                comm,
                format!("{kind} communication parameter {}", n + 1),
                ObjectCode::Record,
                subs,
            ));
            let mut mapping = Object::composite(
                map,
                format!("{kind} mapping parameter {}", n + 1),
                ObjectCode::Record,
                (1..=8u8).map(|i| {
                    (
                        i,
                        u32_var(&format!("Application object {i}"), Access::Rw, 0),
                    )
                }),
            );
            if let Some(count) = mapping.subs.get_mut(&0) {
                *count = small_var(
                    "Number of mapped application objects",
                    DataType::Unsigned8,
                    0,
                );
            }
            od.insert(mapping);
        }
    }
}

/// One mapping entry: object, sub-index and length in bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapEntry {
    /// Object index (0x0001–0x0007: dummy entry of that data type).
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Length in bits (multiple of 8).
    pub bits: u8,
}

impl MapEntry {
    /// Decode a mapping parameter value: index in bits 16–31, sub-index 8–15, length 0–7.
    pub fn from_u32(v: u32) -> Self {
        MapEntry {
            index: (v >> 16) as u16,
            sub: (v >> 8) as u8,
            bits: v as u8,
        }
    }

    /// Encode as a mapping parameter value.
    pub fn to_u32(self) -> u32 {
        u32::from(self.index) << 16 | u32::from(self.sub) << 8 | u32::from(self.bits)
    }

    fn is_dummy(self) -> bool {
        (1..=7).contains(&self.index)
    }
}

/// Which PDO an index belongs to: (receive, number from 0, is mapping object).
fn classify(index: u16) -> Option<(bool, u16, bool)> {
    match index {
        0x1400..=0x15FF => Some((true, index - RPDO_COMM, false)),
        0x1600..=0x17FF => Some((true, index - RPDO_MAP, true)),
        0x1800..=0x19FF => Some((false, index - TPDO_COMM, false)),
        0x1A00..=0x1BFF => Some((false, index - TPDO_MAP, true)),
        _ => None,
    }
}

/// Check that `entry` may be mapped into a PDO of the given direction.
pub fn check_entry(od: &ObjectDictionary, entry: MapEntry, receive: bool) -> Result<(), AbortCode> {
    if entry.bits == 0 || !entry.bits.is_multiple_of(8) {
        return Err(AbortCode::NOT_MAPPABLE);
    }
    if entry.is_dummy() {
        let size = DataType::from_code(entry.index)
            .and_then(DataType::size)
            .ok_or(AbortCode::NOT_MAPPABLE)?;
        return if size * 8 == usize::from(entry.bits) {
            Ok(())
        } else {
            Err(AbortCode::NOT_MAPPABLE)
        };
    }
    let var = od
        .variable(entry.index, entry.sub)
        .map_err(|_| AbortCode::NOT_MAPPABLE)?;
    let direction_ok = if receive {
        var.access.writable()
    } else {
        var.access.readable()
    };
    let size_ok = var
        .data_type
        .size()
        .is_some_and(|s| s * 8 == usize::from(entry.bits));
    if !var.pdo_mappable || !direction_ok || !size_ok {
        return Err(AbortCode::NOT_MAPPABLE);
    }
    Ok(())
}

/// Whether a PDO of this node (`receive`: an RPDO) may not take identifier `id`: one
/// identifier, one producer on the network (CiA 301 §7.3.5) — so not one of the node's SDO
/// channels', a TPDO not another TPDO's, and neither an RPDO's nor a TPDO's the other kind's
/// (the node would produce what it expects from another). Two RPDOs may consume one frame.
fn taken_for_pdo(od: &ObjectDictionary, except: (u16, u8), id: CanId, receive: bool) -> bool {
    crate::cob::used_by_sdo_channel(od, except, id)
        || crate::cob::used_by_tpdo(od, except, id)
        || (!receive && crate::cob::used_by_rpdo(od, except, id))
}

/// Enforces the CiA 301 PDO configuration procedure on network writes.
pub struct PdoGuard;

impl WriteGuard for PdoGuard {
    fn check(
        &self,
        od: &ObjectDictionary,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), AbortCode> {
        let Some((receive, n, is_map)) = classify(index) else {
            return Ok(());
        };
        let comm = if receive { RPDO_COMM } else { TPDO_COMM } + n;
        let valid = od.get_u32(comm, 1).is_some_and(|c| c & COB_INVALID == 0);
        if !is_map {
            return match sub {
                1 => {
                    let new = u32::from_le_bytes(
                        data.try_into().map_err(|_| AbortCode::LENGTH_MISMATCH)?,
                    );
                    let old = od.get_u32(comm, 1).unwrap_or(COB_INVALID);
                    check_parameter_write(old, new, |id| taken_for_pdo(od, (comm, 1), id, receive))
                }
                2 if matches!(data.first(), Some(241..=251)) => Err(AbortCode::INVALID_VALUE),
                // Inhibit time and SYNC start value cannot change while the TPDO exists.
                3 | 6 if !receive && valid => Err(AbortCode::INVALID_VALUE),
                _ => Ok(()),
            };
        }
        if valid {
            return Err(AbortCode::UNSUPPORTED_ACCESS);
        }
        let map = if receive { RPDO_MAP } else { TPDO_MAP } + n;
        if sub == 0 {
            let count = *data.first().ok_or(AbortCode::LENGTH_MISMATCH)?;
            if count > MAX_ENTRIES {
                return Err(AbortCode::PDO_LENGTH);
            }
            let mut bits = 0u32;
            for s in 1..=count {
                let entry = MapEntry::from_u32(od.get_u32(map, s).ok_or(AbortCode::PDO_LENGTH)?);
                check_entry(od, entry, receive)?;
                bits += u32::from(entry.bits);
            }
            return if bits <= 64 {
                Ok(())
            } else {
                Err(AbortCode::PDO_LENGTH)
            };
        }
        if od.get_u32(map, 0) != Some(0) {
            return Err(AbortCode::UNSUPPORTED_ACCESS);
        }
        let value = u32::from_le_bytes(data.try_into().map_err(|_| AbortCode::LENGTH_MISMATCH)?);
        check_entry(od, MapEntry::from_u32(value), receive)
    }
}

/// Something the application should know about (CiA 301 EMCY codes in brackets).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PdoEvent {
    /// An RPDO was shorter than its mapping (0x8210) and was not processed.
    LengthError {
        /// RPDO number from 1.
        rpdo: u16,
    },
    /// An RPDO was longer than its mapping (0x8220); the mapped part was processed.
    LengthExceeded {
        /// RPDO number from 1.
        rpdo: u16,
    },
    /// An RPDO did not arrive within its receive timeout (0x8250).
    Timeout {
        /// RPDO number from 1.
        rpdo: u16,
    },
}

impl PdoEvent {
    /// The emergency error code CiA 301 assigns.
    pub fn emcy_code(self) -> u16 {
        match self {
            PdoEvent::LengthError { .. } => crate::emcy::codes::PDO_LENGTH,
            PdoEvent::LengthExceeded { .. } => crate::emcy::codes::PDO_LENGTH_EXCEEDED,
            PdoEvent::Timeout { .. } => crate::emcy::codes::RPDO_TIMEOUT,
        }
    }
}

#[derive(Debug)]
struct Tpdo {
    number: u16,
    id: CanId,
    /// COB-ID bit 30 clear: remote requests are answered.
    rtr_allowed: bool,
    ttype: u8,
    inhibit: Duration,
    event_timer: Option<Duration>,
    sync_start: u8,
    map: Vec<MapEntry>,
    last_sent: Option<Instant>,
    /// When an event occurred that waits to be sent (inhibit time, or SYNC for type 0).
    pending: Option<Instant>,
    timer_due: Option<Instant>,
    syncs: u32,
    started: bool,
}

#[derive(Debug)]
struct Rpdo {
    number: u16,
    id: CanId,
    ttype: u8,
    map: Vec<MapEntry>,
    timeout: Option<Duration>,
    deadline: Option<Instant>,
    /// Data of a synchronous RPDO, applied at the next SYNC.
    buffered: Option<Vec<u8>>,
}

fn mapped_len(map: &[MapEntry]) -> usize {
    map.iter().map(|e| usize::from(e.bits / 8)).sum()
}

/// The PDOs of a node.
#[derive(Debug, Default)]
pub struct PdoEngine {
    tpdos: Vec<Tpdo>,
    rpdos: Vec<Rpdo>,
    /// Objects mapped into event-driven TPDOs → their positions in `tpdos`.
    watched: HashMap<(u16, u8), Vec<usize>>,
}

fn read_map(od: &ObjectDictionary, map_index: u16) -> Vec<MapEntry> {
    let count = od
        .get_u32(map_index, 0)
        .unwrap_or(0)
        .min(u32::from(MAX_ENTRIES)) as u8;
    (1..=count)
        .filter_map(|s| od.get_u32(map_index, s).map(MapEntry::from_u32))
        .collect()
}

impl PdoEngine {
    /// Build the PDOs from the dictionary (call again whenever 0x1400–0x1BFF change).
    pub fn configure(od: &ObjectDictionary, now: Instant) -> Self {
        let mut engine = PdoEngine::default();
        for n in 0..MAX_PDOS {
            if od.object(RPDO_COMM + n).is_some() {
                let cob = od.get_u32(RPDO_COMM + n, 1).unwrap_or(COB_INVALID);
                let map = read_map(od, RPDO_MAP + n);
                if let (Some(id), false) = (crate::cob::id_from_parameter(cob), map.is_empty()) {
                    engine.rpdos.push(Rpdo {
                        number: n + 1,
                        id,
                        ttype: od.get_u32(RPDO_COMM + n, 2).unwrap_or(254) as u8,
                        map,
                        timeout: od
                            .get_u32(RPDO_COMM + n, 5)
                            .filter(|&ms| ms > 0)
                            .map(|ms| Duration::from_millis(ms.into())),
                        deadline: None,
                        buffered: None,
                    });
                }
            }
            if od.object(TPDO_COMM + n).is_some() {
                let cob = od.get_u32(TPDO_COMM + n, 1).unwrap_or(COB_INVALID);
                let map = read_map(od, TPDO_MAP + n);
                if let (Some(id), false) = (crate::cob::id_from_parameter(cob), map.is_empty()) {
                    let ttype = od.get_u32(TPDO_COMM + n, 2).unwrap_or(254) as u8;
                    let event_timer = od
                        .get_u32(TPDO_COMM + n, 5)
                        .filter(|&ms| ms > 0 && ttype >= 254)
                        .map(|ms| Duration::from_millis(ms.into()));
                    let index = engine.tpdos.len();
                    if ttype >= 254 || ttype == 0 {
                        for e in map.iter().filter(|e| !e.is_dummy()) {
                            engine
                                .watched
                                .entry((e.index, e.sub))
                                .or_default()
                                .push(index);
                        }
                    }
                    engine.tpdos.push(Tpdo {
                        number: n + 1,
                        id,
                        rtr_allowed: cob & 0x4000_0000 == 0,
                        ttype,
                        inhibit: Duration::from_micros(
                            u64::from(od.get_u32(TPDO_COMM + n, 3).unwrap_or(0)) * 100,
                        ),
                        event_timer,
                        sync_start: od.get_u32(TPDO_COMM + n, 6).unwrap_or(0) as u8,
                        map,
                        last_sent: None,
                        pending: None,
                        timer_due: event_timer.map(|t| now + t),
                        syncs: 0,
                        started: false,
                    });
                }
            }
        }
        engine
    }

    /// Whether `index` is a PDO configuration object (a change means: configure again).
    pub fn is_config(index: u16) -> bool {
        classify(index).is_some()
    }

    /// The identifiers of the valid RPDOs (for acceptance filters).
    pub fn rpdo_ids(&self) -> Vec<CanId> {
        self.rpdos.iter().map(|r| r.id).collect()
    }

    /// Whether `id` is one of the RPDOs.
    pub fn is_rpdo(&self, id: CanId) -> bool {
        self.rpdos.iter().any(|r| r.id == id)
    }

    /// Mark every event-driven TPDO pending (e.g. on entering operational).
    pub fn trigger_all(&mut self, now: Instant) {
        for t in self.tpdos.iter_mut().filter(|t| t.ttype >= 254) {
            t.pending.get_or_insert(now);
        }
    }

    /// An object changed: TPDOs of type 0 and 254/255 mapping it become pending.
    pub fn on_change(&mut self, index: u16, sub: u8, now: Instant) {
        if let Some(list) = self.watched.get(&(index, sub)) {
            for &i in list {
                self.tpdos[i].pending.get_or_insert(now);
            }
        }
    }

    /// Request a TPDO (number from 1) to be sent as soon as its inhibit time allows (or at
    /// the next SYNC for synchronous ones of type 0).
    pub fn request(&mut self, number: u16, now: Instant) {
        if let Some(t) = self.tpdos.iter_mut().find(|t| t.number == number) {
            t.pending.get_or_insert(now);
        }
    }

    fn build(od: &ObjectDictionary, t: &Tpdo) -> Option<Frame> {
        let mut data = Vec::with_capacity(8);
        for e in &t.map {
            let len = usize::from(e.bits / 8);
            if e.is_dummy() {
                data.extend(std::iter::repeat_n(0, len));
                continue;
            }
            let bytes = od.read(e.index, e.sub).ok()?;
            data.extend_from_slice(bytes.get(..len)?);
        }
        Frame::new(t.id, &data).ok()
    }

    /// Handle a frame: an RPDO is written into `od` (owner-side writes: watchers fire).
    /// Returns whether the frame was an RPDO of this node.
    pub fn handle_frame(
        &mut self,
        od: &mut ObjectDictionary,
        frame: &Frame,
        now: Instant,
        events: &mut Vec<PdoEvent>,
    ) -> bool {
        let Some(r) = self.rpdos.iter_mut().find(|r| r.id == frame.id()) else {
            return false;
        };
        if frame.is_remote() {
            return true;
        }
        let need = mapped_len(&r.map);
        let data = frame.data();
        if data.len() < need {
            events.push(PdoEvent::LengthError { rpdo: r.number });
            return true;
        }
        if data.len() > need {
            events.push(PdoEvent::LengthExceeded { rpdo: r.number });
        }
        r.deadline = r.timeout.map(|t| now + t);
        if r.ttype <= 240 {
            r.buffered = Some(data[..need].to_vec());
        } else {
            apply_rpdo(od, &r.map, &data[..need]);
        }
        true
    }

    /// A remote request for one of the TPDOs: type 253 (and event-driven ones) answer at once,
    /// type 252 samples at the next SYNC. Returns whether the frame was such a request.
    pub fn handle_remote(
        &mut self,
        od: &ObjectDictionary,
        frame: &Frame,
        now: Instant,
        out: &mut Vec<Frame>,
    ) -> bool {
        if !frame.is_remote() {
            return false;
        }
        let Some(t) = self.tpdos.iter_mut().find(|t| t.id == frame.id()) else {
            return false;
        };
        if !t.rtr_allowed {
            return true;
        }
        match t.ttype {
            252 => {
                t.pending.get_or_insert(now);
            }
            253..=255 => {
                if let Some(f) = Self::build(od, t) {
                    t.last_sent = Some(now);
                    out.push(f);
                }
            }
            _ => {}
        }
        true
    }

    /// A SYNC: synchronous RPDOs take effect, synchronous TPDOs are sent.
    pub fn on_sync(
        &mut self,
        od: &mut ObjectDictionary,
        counter: Option<u8>,
        now: Instant,
        out: &mut Vec<Frame>,
    ) {
        for r in &mut self.rpdos {
            if let Some(data) = r.buffered.take() {
                apply_rpdo(od, &r.map, &data);
            }
        }
        for t in &mut self.tpdos {
            let send = match t.ttype {
                0 | 252 => t.pending.take().is_some(),
                n @ 1..=240 => {
                    if !t.started {
                        // With a start value and a counter, the first SYNC is the one whose
                        // counter equals the start value.
                        t.started =
                            t.sync_start == 0 || counter.is_none() || counter == Some(t.sync_start);
                        t.syncs = 0;
                    }
                    if t.started {
                        t.syncs += 1;
                    }
                    t.started && (t.syncs - 1) % u32::from(n) == 0
                }
                _ => false,
            };
            if send {
                if let Some(f) = Self::build(od, t) {
                    t.last_sent = Some(now);
                    out.push(f);
                }
            }
        }
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let tx = self.tpdos.iter().filter_map(|t| {
            let inhibit_end = match (t.pending, t.ttype >= 254) {
                (Some(at), true) => Some(t.last_sent.map_or(at, |l| (l + t.inhibit).max(at))),
                _ => None,
            };
            [inhibit_end, t.timer_due].into_iter().flatten().min()
        });
        let rx = self.rpdos.iter().filter_map(|r| r.deadline);
        tx.chain(rx).min()
    }

    /// Send what is due (event-driven TPDOs past their inhibit time, expired event timers) and
    /// report RPDO timeouts.
    pub fn handle_timeout(
        &mut self,
        od: &ObjectDictionary,
        now: Instant,
        out: &mut Vec<Frame>,
        events: &mut Vec<PdoEvent>,
    ) {
        for t in &mut self.tpdos {
            if t.ttype < 254 {
                continue;
            }
            let timer_fired = t.timer_due.is_some_and(|d| now >= d);
            let inhibited = t.last_sent.is_some_and(|l| now < l + t.inhibit);
            if (t.pending.is_some() || timer_fired) && !inhibited {
                if let Some(f) = Self::build(od, t) {
                    out.push(f);
                }
                t.pending = None;
                t.last_sent = Some(now);
                t.timer_due = t.event_timer.map(|e| now + e);
            } else if timer_fired {
                // The event timer fired during the inhibit time: send when it ends.
                t.pending.get_or_insert(now);
                t.timer_due = t.event_timer.map(|e| now + e);
            }
        }
        for r in &mut self.rpdos {
            if r.deadline.is_some_and(|d| now >= d) {
                r.deadline = None;
                events.push(PdoEvent::Timeout { rpdo: r.number });
            }
        }
    }
}

fn apply_rpdo(od: &mut ObjectDictionary, map: &[MapEntry], data: &[u8]) {
    for (e, bytes) in split(map, data).into_iter().flatten() {
        if !e.is_dummy() {
            if let Err(code) = od.set(e.index, e.sub, bytes) {
                tracing::warn!(index = e.index, sub = e.sub, %code, "RPDO data not stored");
            }
        }
    }
}

/// A PDO's data split by its mapping (whole bytes per entry, as CiA 301 PDOs of byte-sized
/// objects lay them out, little-endian); `None` when the data is shorter than the mapping.
fn split<'a>(map: &'a [MapEntry], data: &'a [u8]) -> Option<Vec<(MapEntry, &'a [u8])>> {
    let mut pos = 0;
    map.iter()
        .map(|e| {
            let len = usize::from(e.bits / 8);
            let bytes = data.get(pos..pos + len)?;
            pos += len;
            Some((*e, bytes))
        })
        .collect()
}

/// The values a PDO carried, by the mapping the receiver expects: for applications that
/// consume another node's PDOs without a dictionary entry for each
/// (`Master::on_rpdo`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PdoValues {
    /// The COB-ID it came on.
    pub cob_id: CanId,
    /// Each mapped object with its bytes (dummy entries included).
    pub values: Vec<(MapEntry, Vec<u8>)>,
}

impl PdoValues {
    /// Split `data` by `map`; `None` when the data is shorter than the mapping.
    pub fn split(cob_id: CanId, map: &[MapEntry], data: &[u8]) -> Option<Self> {
        Some(PdoValues {
            cob_id,
            values: split(map, data)?
                .into_iter()
                .map(|(e, b)| (e, b.to_vec()))
                .collect(),
        })
    }

    /// The bytes of (`index`, `sub`).
    pub fn get(&self, index: u16, sub: u8) -> Option<&[u8]> {
        self.values
            .iter()
            .find(|(e, _)| e.index == index && e.sub == sub)
            .map(|(_, b)| b.as_slice())
    }

    /// The value of (`index`, `sub`) as `T` (`None` when absent or of another size).
    pub fn value<T: crate::types::CanopenValue>(&self, index: u16, sub: u8) -> Option<T> {
        T::from_bytes(self.get(index, sub)?).ok()
    }
}

#[cfg(test)]
mod tests;
