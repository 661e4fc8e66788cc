//! Another node's PDOs, configured over SDO: reading their communication (1400h/1800h) and
//! mapping (1600h/1A00h) parameters, and writing them with the CiA 301 §7.3.5 procedure —
//! disable (COB-ID bit 31), set the parameters, clear the mapping count, write the entries,
//! set the count, enable. Every step's abort is reported with the step it came from.

use std::fmt;

use super::MapEntry;
use crate::sdo::abort::AbortCode;
use crate::sdo::clients::{ClientError, SdoClients};

/// Receive or transmit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Direction {
    /// RPDO: 1400h + n communication, 1600h + n mapping.
    Receive,
    /// TPDO: 1800h + n communication, 1A00h + n mapping.
    Transmit,
}

/// One PDO of a node: `TPDO1` … `TPDO512`, `RPDO1` … `RPDO512`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PdoId {
    /// Receive or transmit.
    pub direction: Direction,
    /// 1–512.
    pub number: u16,
}

impl PdoId {
    /// `tpdo1`, `RPDO4` (case-insensitive).
    pub fn parse(text: &str) -> Option<Self> {
        let lower = text.to_ascii_lowercase();
        let (direction, number) = if let Some(n) = lower.strip_prefix("tpdo") {
            (Direction::Transmit, n)
        } else {
            (Direction::Receive, lower.strip_prefix("rpdo")?)
        };
        let number: u16 = number.parse().ok().filter(|n| (1..=512).contains(n))?;
        Some(PdoId { direction, number })
    }

    /// The PDO a communication or mapping parameter index (1400h–1BFFh) belongs to.
    pub fn of_index(index: u16) -> Option<Self> {
        let (receive, number, _) = super::classify(index)?;
        Some(PdoId {
            direction: if receive {
                Direction::Receive
            } else {
                Direction::Transmit
            },
            number: number + 1,
        })
    }

    /// The communication parameter's index.
    pub fn communication(self) -> u16 {
        let base = match self.direction {
            Direction::Receive => 0x1400,
            Direction::Transmit => 0x1800,
        };
        base + self.number - 1
    }

    /// The mapping parameter's index.
    pub fn mapping(self) -> u16 {
        self.communication() + 0x200
    }
}

impl fmt::Display for PdoId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let kind = match self.direction {
            Direction::Receive => "RPDO",
            Direction::Transmit => "TPDO",
        };
        write!(f, "{kind}{}", self.number)
    }
}

/// A PDO's parameters as the node holds them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RemotePdo {
    /// Which PDO.
    pub id: PdoId,
    /// Sub 1: the COB-ID entry (bit 31 set: not valid, the PDO is off; bit 30: no RTR;
    /// bit 29: 29-bit identifier).
    pub cob_id: u32,
    /// Sub 2: transmission type (0 acyclic synchronous, 1–240 every n-th SYNC, 254/255 event).
    pub transmission: u8,
    /// Sub 3 (TPDO): inhibit time in 100 µs, if the node has it.
    pub inhibit_100us: Option<u16>,
    /// Sub 5: event timer (TPDO) or deadline (RPDO) in ms, if the node has it.
    pub event_ms: Option<u16>,
    /// Sub 6 (TPDO): SYNC start value, if the node has it.
    pub sync_start: Option<u8>,
    /// The mapped objects, in order.
    pub mapping: Vec<MapEntry>,
}

impl RemotePdo {
    /// Whether the PDO is on (COB-ID bit 31 clear).
    pub fn enabled(&self) -> bool {
        self.cob_id & 0x8000_0000 == 0
    }

    /// The bits the mapping fills (at most 64).
    pub fn bits(&self) -> u32 {
        self.mapping.iter().map(|m| u32::from(m.bits)).sum()
    }
}

/// A configuration step that failed.
#[derive(Debug, thiserror::Error)]
#[error("{pdo}: {step}: {error}{}", explain(.error))]
pub struct ConfigureError {
    /// The PDO.
    pub pdo: PdoId,
    /// What was being written, e.g. "mapping entry 2 (6520h sub 1, 32 bits)".
    pub step: String,
    /// The transfer's failure (its abort code says why).
    pub error: ClientError,
}

/// Why another node's PDO cannot be consumed.
#[derive(Debug, thiserror::Error)]
pub enum ConsumeError {
    /// The node has no such PDO.
    #[error("node {node} has no {pdo}")]
    Missing {
        /// The node.
        node: u8,
        /// The PDO.
        pdo: PdoId,
    },
    /// The PDO is off (COB-ID bit 31) or its COB-ID is not one.
    #[error("{pdo} of node {node} is off (COB-ID entry 0x{cob_id:08X})")]
    Off {
        /// The node.
        node: u8,
        /// The PDO.
        pdo: PdoId,
        /// Its COB-ID entry.
        cob_id: u32,
    },
    /// Reading its parameters failed.
    #[error(transparent)]
    Sdo(#[from] ClientError),
}

/// What an abort means for PDO configuration, beyond the code's standard text.
fn explain(error: &ClientError) -> &'static str {
    match error.abort_code() {
        AbortCode::NOT_MAPPABLE => " — the object cannot be mapped into a PDO (not PDO-mappable, or no such object)",
        AbortCode::PDO_LENGTH => " — the mapped objects exceed the PDO's 64 bits",
        AbortCode::INVALID_VALUE => " — the node refuses this value (a COB-ID it reserves, or a change while the PDO is valid)",
        AbortCode::NO_OBJECT => " — the node has no such PDO",
        AbortCode::NO_SUB_INDEX => " — the node does not have this parameter",
        _ => "",
    }
}

/// A parameter the node may not have (sub-indices 3, 5, 6 are optional).
fn optional<T>(result: Result<T, ClientError>) -> Result<Option<T>, ClientError> {
    match result {
        Ok(v) => Ok(Some(v)),
        Err(e)
            if matches!(
                e.abort_code(),
                AbortCode::NO_SUB_INDEX | AbortCode::NO_OBJECT
            ) =>
        {
            Ok(None)
        }
        Err(e) => Err(e),
    }
}

/// Read `id` of `node`; `None` when the node has no such PDO.
pub async fn read(sdo: &SdoClients, node: u8, id: PdoId) -> Result<Option<RemotePdo>, ClientError> {
    let comm = id.communication();
    let cob_id = match sdo.read::<u32>(node, comm, 1).await {
        Ok(v) => v,
        Err(e) if e.abort_code() == AbortCode::NO_OBJECT => return Ok(None),
        Err(e) => return Err(e),
    };
    let transmission = sdo.read::<u8>(node, comm, 2).await?;
    let transmit = id.direction == Direction::Transmit;
    let inhibit_100us = if transmit {
        optional(sdo.read::<u16>(node, comm, 3).await)?
    } else {
        None
    };
    let event_ms = optional(sdo.read::<u16>(node, comm, 5).await)?;
    let sync_start = if transmit {
        optional(sdo.read::<u8>(node, comm, 6).await)?
    } else {
        None
    };
    let count = sdo.read::<u8>(node, id.mapping(), 0).await?;
    let mut mapping = Vec::with_capacity(usize::from(count));
    for sub in 1..=count {
        mapping.push(MapEntry::from_u32(
            sdo.read::<u32>(node, id.mapping(), sub).await?,
        ));
    }
    Ok(Some(RemotePdo {
        id,
        cob_id,
        transmission,
        inhibit_100us,
        event_ms,
        sync_start,
        mapping,
    }))
}

/// Write `pdo` to `node` with the CiA 301 §7.3.5 procedure. The PDO stays off (bit 31) when
/// `pdo.cob_id` has bit 31 set; parameters that are `None` are left as they are.
pub async fn configure(sdo: &SdoClients, node: u8, pdo: &RemotePdo) -> Result<(), ConfigureError> {
    let id = pdo.id;
    let comm = id.communication();
    let step = |step: String| {
        move |error| ConfigureError {
            pdo: id,
            step,
            error,
        }
    };
    let disabled = pdo.cob_id | 0x8000_0000;
    sdo.write(node, comm, 1, disabled)
        .await
        .map_err(step(format!("disabling (COB-ID 0x{disabled:08X})")))?;
    sdo.write(node, comm, 2, pdo.transmission)
        .await
        .map_err(step(format!("transmission type {}", pdo.transmission)))?;
    if let Some(inhibit) = pdo.inhibit_100us {
        sdo.write(node, comm, 3, inhibit)
            .await
            .map_err(step(format!("inhibit time {inhibit} × 100 µs")))?;
    }
    if let Some(event) = pdo.event_ms {
        sdo.write(node, comm, 5, event)
            .await
            .map_err(step(format!("event timer {event} ms")))?;
    }
    if let Some(start) = pdo.sync_start {
        sdo.write(node, comm, 6, start)
            .await
            .map_err(step(format!("SYNC start value {start}")))?;
    }
    let map = id.mapping();
    sdo.write(node, map, 0, 0u8)
        .await
        .map_err(step("clearing the mapping".into()))?;
    for (i, entry) in pdo.mapping.iter().enumerate() {
        sdo.write(node, map, (i + 1) as u8, entry.to_u32())
            .await
            .map_err(step(format!(
                "mapping entry {} ({:04X}h sub {}, {} bits)",
                i + 1,
                entry.index,
                entry.sub,
                entry.bits
            )))?;
    }
    let count = pdo.mapping.len() as u8;
    sdo.write(node, map, 0, count)
        .await
        .map_err(step(format!("mapping count {count}")))?;
    if pdo.enabled() {
        sdo.write(node, comm, 1, pdo.cob_id)
            .await
            .map_err(step(format!("enabling (COB-ID 0x{:08X})", pdo.cob_id)))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_indices() {
        let t = PdoId::parse("tpdo1").unwrap();
        assert_eq!((t.communication(), t.mapping()), (0x1800, 0x1A00));
        assert_eq!(t.to_string(), "TPDO1");
        let r = PdoId::parse("RPDO512").unwrap();
        assert_eq!((r.communication(), r.mapping()), (0x15FF, 0x17FF));
        assert_eq!(PdoId::parse("tpdo0"), None);
        assert_eq!(PdoId::parse("tpdo513"), None);
        assert_eq!(PdoId::parse("pdo1"), None);
        assert_eq!(PdoId::of_index(0x1A00), Some(t));
        assert_eq!(PdoId::of_index(0x15FF), Some(r));
        assert_eq!(PdoId::of_index(0x17FF), Some(r));
        assert_eq!(PdoId::of_index(0x1C00), None);
    }
}
