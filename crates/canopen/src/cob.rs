//! The pre-defined connection set (CiA 301 §7.3.5): which COB-ID carries which service.

use canbus::CanId;

use crate::od::ObjectDictionary;
use crate::sdo::abort::AbortCode;

/// Bit 31 of a COB-ID parameter (PDO communication, SDO server and client parameters): set,
/// the object does not exist.
pub const COB_INVALID: u32 = 0x8000_0000;

/// A network write of a COB-ID parameter whose bit 31 says whether its object exists — a PDO's
/// (CiA 301 §7.5.2.35–36, sub 1) or a further SDO channel's (§7.5.2.33, subs 1 and 2) — from
/// `old` to `new`: while the object exists only that bit may change (so a channel or PDO in use
/// never moves under its peer: invalidate, change, validate), and a valid identifier must be a
/// CAN identifier that the pre-defined connection set leaves free ([`restricted`]) and that the
/// node does not use otherwise (`in_use`: one identifier, one producer, §7.3.5).
pub fn check_parameter_write(
    old: u32,
    new: u32,
    in_use: impl Fn(CanId) -> bool,
) -> Result<(), AbortCode> {
    let exists = old & COB_INVALID == 0;
    if exists && new & COB_INVALID == 0 && (new ^ old) & 0x3FFF_FFFF != 0 {
        return Err(AbortCode::INVALID_VALUE);
    }
    if new & COB_INVALID == 0 {
        match id_from_parameter(new) {
            None => return Err(AbortCode::INVALID_VALUE),
            Some(CanId::Standard(id)) if restricted(id) => return Err(AbortCode::INVALID_VALUE),
            Some(id) if in_use(id) => return Err(AbortCode::INVALID_VALUE),
            Some(_) => {}
        }
    }
    Ok(())
}

/// Whether `id` is a valid identifier of one of the node's further SDO server channels
/// (1201h–127Fh, request or response) other than the parameter `except` (index, sub).
pub fn used_by_sdo_channel(od: &ObjectDictionary, except: (u16, u8), id: CanId) -> bool {
    let entries = (0x1201..=0x127F).flat_map(|i| [(i, 1), (i, 2)]);
    used_by(od, entries, except, id)
}

/// Whether `id` is the identifier of one of the node's valid TPDOs (1800h–19FFh sub 1) other
/// than the parameter `except` (index, sub).
pub fn used_by_tpdo(od: &ObjectDictionary, except: (u16, u8), id: CanId) -> bool {
    used_by(od, (0x1800..=0x19FF).map(|i| (i, 1)), except, id)
}

/// Whether `id` is the identifier of one of the node's valid RPDOs (1400h–15FFh sub 1) other
/// than the parameter `except` (index, sub).
pub fn used_by_rpdo(od: &ObjectDictionary, except: (u16, u8), id: CanId) -> bool {
    used_by(od, (0x1400..=0x15FF).map(|i| (i, 1)), except, id)
}

fn used_by(
    od: &ObjectDictionary,
    entries: impl Iterator<Item = (u16, u8)>,
    except: (u16, u8),
    id: CanId,
) -> bool {
    entries
        .filter(|&entry| entry != except)
        .filter_map(|(i, s)| od.get_u32(i, s))
        .filter_map(id_from_parameter)
        .any(|other| other == id)
}

/// The identifier in a COB-ID parameter value (0x1005, 0x1014, 0x1200…, 0x1400…): bit 31 set
/// means not valid (`None`), bit 29 selects a 29-bit identifier; bit 30 (RTR / producer flag)
/// is the caller's business.
pub fn id_from_parameter(value: u32) -> Option<CanId> {
    if value & COB_INVALID != 0 {
        None
    } else if value & 0x2000_0000 != 0 {
        CanId::extended(value & 0x1FFF_FFFF).ok()
    } else {
        CanId::standard((value & 0x7FF) as u16).ok()
    }
}

/// The COB-ID parameter value of a valid identifier: bit 29 set for a 29-bit one (the inverse of
/// [`id_from_parameter`]).
pub fn parameter_from_id(id: CanId) -> u32 {
    match id {
        CanId::Standard(id) => u32::from(id),
        CanId::Extended(id) => id | 0x2000_0000,
    }
}

/// The 11-bit identifiers CiA 301 §7.3.5 reserves for NMT, SYNC/EMCY, TIME, SDO, LSS and
/// error control. 0x180 is among them in CiA 301 but CiA 417 lets lift devices use it for a
/// PDO, so it is allowed here. The
/// configurable objects — PDOs, further SDO channels — must not use the others.
pub fn restricted(id: u16) -> bool {
    matches!(id, 0x000..=0x07F | 0x101..=0x17F | 0x581..=0x5FF | 0x601..=0x67F | 0x6E0..=0x6FF | 0x701..=0x77F | 0x780..=0x7FF)
}

/// A function code: the upper four bits of an 11-bit COB-ID in the pre-defined connection set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Function {
    /// 000h: NMT node control.
    Nmt,
    /// 080h: SYNC.
    Sync,
    /// 081h–0FFh: emergency of node 1–127.
    Emcy(u8),
    /// 100h: TIME stamp.
    Time,
    /// TPDO1–4 (180h/280h/380h/480h + node).
    Tpdo(u8, u8),
    /// RPDO1–4 (200h/300h/400h/500h + node).
    Rpdo(u8, u8),
    /// 580h + node: SDO server → client (response).
    SdoResponse(u8),
    /// 600h + node: SDO client → server (request).
    SdoRequest(u8),
    /// 700h + node: NMT error control (heartbeat, boot-up, node guarding).
    ErrorControl(u8),
    /// 7E4h: LSS slave → master (CiA 305).
    LssResponse,
    /// 7E5h: LSS master → slave (CiA 305).
    LssRequest,
    /// Any other identifier.
    Other,
}

/// Classify an 11-bit COB-ID by the pre-defined connection set.
pub fn classify(cob_id: u16) -> Function {
    let node = (cob_id & 0x7F) as u8;
    match (cob_id, cob_id & 0x780) {
        (0x000, _) => Function::Nmt,
        (0x080, _) => Function::Sync,
        (0x100, _) => Function::Time,
        (0x7E4, _) => Function::LssResponse,
        (0x7E5, _) => Function::LssRequest,
        (_, _) if node == 0 => Function::Other,
        (_, 0x080) => Function::Emcy(node),
        (_, 0x180) => Function::Tpdo(1, node),
        (_, 0x200) => Function::Rpdo(1, node),
        (_, 0x280) => Function::Tpdo(2, node),
        (_, 0x300) => Function::Rpdo(2, node),
        (_, 0x380) => Function::Tpdo(3, node),
        (_, 0x400) => Function::Rpdo(3, node),
        (_, 0x480) => Function::Tpdo(4, node),
        (_, 0x500) => Function::Rpdo(4, node),
        (_, 0x580) => Function::SdoResponse(node),
        (_, 0x600) => Function::SdoRequest(node),
        (_, 0x700) => Function::ErrorControl(node),
        _ => Function::Other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cob_id_parameters() {
        assert_eq!(id_from_parameter(0x0000_0181), Some(CanId::Standard(0x181)));
        assert_eq!(
            id_from_parameter(0x4000_0080),
            Some(CanId::Standard(0x80)),
            "producer bit ignored"
        );
        assert_eq!(id_from_parameter(0x2000_0181), Some(CanId::Extended(0x181)));
        assert_eq!(id_from_parameter(0x8000_0181), None);
    }

    #[test]
    fn predefined_connection_set() {
        assert_eq!(classify(0x000), Function::Nmt);
        assert_eq!(classify(0x080), Function::Sync);
        assert_eq!(classify(0x081), Function::Emcy(1));
        assert_eq!(classify(0x100), Function::Time);
        assert_eq!(classify(0x18C), Function::Tpdo(1, 12));
        assert_eq!(classify(0x4FF), Function::Tpdo(4, 127));
        assert_eq!(classify(0x209), Function::Rpdo(1, 9));
        assert_eq!(classify(0x581), Function::SdoResponse(1));
        assert_eq!(classify(0x67F), Function::SdoRequest(127));
        assert_eq!(classify(0x701), Function::ErrorControl(1));
        assert_eq!(classify(0x7E5), Function::LssRequest);
        assert_eq!(classify(0x180), Function::Other, "node 0 is not a node");
        assert_eq!(classify(0x766), Function::ErrorControl(0x66));
        assert_eq!(classify(0x7E6), Function::Other);
    }
}
