//! PDO contents for bus monitors: the layouts of a node's PDOs from its dictionary, and the
//! values in a PDO frame by its layout.

use canbus::CanId;

use super::hex;
use crate::od::ObjectDictionary;
use crate::types::{DataType, Value};

/// What a PDO carries: its mapped objects in order, with types where known.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PdoLayout {
    /// `TPDO1 node 1` and the like.
    pub name: String,
    /// Index, sub-index, length in bytes, and the data type when a dictionary tells it.
    pub entries: Vec<(u16, u8, usize, Option<DataType>)>,
}

/// The layouts of the valid TPDOs and RPDOs configured in `od` (an EDS/DCF of node `node`, or
/// a dictionary read back over SDO).
pub fn pdo_layouts(od: &ObjectDictionary, node: u8) -> Vec<(CanId, PdoLayout)> {
    let mut out = Vec::new();
    for (comm, map, kind) in [
        (crate::pdo::TPDO_COMM, crate::pdo::TPDO_MAP, "TPDO"),
        (crate::pdo::RPDO_COMM, crate::pdo::RPDO_MAP, "RPDO"),
    ] {
        for n in 0..crate::pdo::MAX_PDOS {
            let Ok(Value::Uint(cob)) = od.get_value(comm + n, 1) else {
                continue;
            };
            let Some(id) = crate::cob::id_from_parameter(cob as u32) else {
                continue;
            };
            let count = match od.get_value(map + n, 0) {
                Ok(Value::Uint(c)) => c as u8,
                _ => 0,
            };
            let entries: Vec<_> = (1..=count)
                .filter_map(|s| match od.get_value(map + n, s) {
                    Ok(Value::Uint(v)) => Some(crate::pdo::MapEntry::from_u32(v as u32)),
                    _ => None,
                })
                .map(|e| {
                    let ty = od.variable(e.index, e.sub).ok().map(|v| v.data_type);
                    (e.index, e.sub, usize::from(e.bits / 8), ty)
                })
                .collect();
            if !entries.is_empty() {
                out.push((
                    id,
                    PdoLayout {
                        name: format!("{kind}{} node {node}", n + 1),
                        entries,
                    },
                ));
            }
        }
    }
    out
}

/// The values in a PDO's data, by its layout: `2000:00=1234 2001:00=7`.
pub fn decode_pdo(layout: &PdoLayout, data: &[u8]) -> String {
    let mut pos = 0;
    let mut parts = Vec::new();
    for (index, sub, len, ty) in &layout.entries {
        let Some(bytes) = data.get(pos..pos + len) else {
            parts.push(format!("{index:04X}:{sub:02X}=<missing>"));
            break;
        };
        pos += len;
        if (1..=7).contains(index) {
            continue; // dummy entry
        }
        let text = match ty.and_then(|t| {
            crate::types::decode(t, bytes)
                .ok()
                .map(|v| crate::types::to_text(t, &v))
        }) {
            Some(text) => text,
            None if *len <= 8 => {
                let mut wide = [0u8; 8];
                wide[..*len].copy_from_slice(bytes);
                u64::from_le_bytes(wide).to_string()
            }
            None => hex(bytes),
        };
        parts.push(format!("{index:04X}:{sub:02X}={text}"));
    }
    format!("{}: {}", layout.name, parts.join(" "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_from_a_dictionary_decode_frames() {
        let mut od = ObjectDictionary::new();
        od.insert(crate::od::Object::var(
            0x2000,
            crate::od::Variable::new("Position", DataType::Integer16, crate::od::Access::Rw)
                .mappable(),
        ));
        crate::pdo::add_pdo_objects(&mut od, 1, 1, 1);
        let entries = [(0x2000, 0, 16), (0x0005, 0, 8), (0x2100, 1, 32)];
        for (i, (index, sub, bits)) in entries.into_iter().enumerate() {
            let entry = crate::pdo::MapEntry { index, sub, bits }.to_u32();
            od.set(crate::pdo::TPDO_MAP, i as u8 + 1, &entry.to_le_bytes())
                .unwrap();
        }
        od.set(crate::pdo::TPDO_MAP, 0, &[3]).unwrap();
        let layouts = pdo_layouts(&od, 1);
        assert_eq!(layouts.len(), 1, "the RPDO has no mapping");
        let (id, layout) = &layouts[0];
        assert_eq!(*id, CanId::Standard(0x181));
        assert_eq!(
            decode_pdo(layout, &[0xFE, 0xFF, 9, 1, 0, 0, 0]),
            "TPDO1 node 1: 2000:00=-2 2100:01=1"
        );
        assert_eq!(decode_pdo(layout, &[1]), "TPDO1 node 1: 2000:00=<missing>");
    }
}
