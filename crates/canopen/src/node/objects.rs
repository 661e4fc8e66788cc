//! The communication objects a node offers (CiA 301 §7.5.2) where its dictionary does not
//! define them, and moving their node-ID-derived COB-IDs when LSS changes the node-ID.

use std::sync::Arc;

use super::NodeConfig;
use crate::cob::parameter_from_id;
use crate::objects::*;
use crate::od::{Access, Object, ObjectCode, ObjectDictionary, Variable, VariableHook};
use crate::sdo::abort::AbortCode;
use crate::types::{DataType, Value};

/// 0x1003 sub 0 accepts only 0 (clear the history) from the network (CiA 301 §7.5.2.4).
struct HistoryCount;

impl VariableHook for HistoryCount {
    fn on_write(&self, _: u16, _: u8, data: &[u8]) -> Result<(), AbortCode> {
        if data == [0] {
            Ok(())
        } else {
            Err(AbortCode::INVALID_VALUE)
        }
    }
}

fn u32_var(name: &str, access: Access, value: u32) -> Variable {
    Variable::new(name, DataType::Unsigned32, access).with_value(Value::Uint(value.into()))
}

/// Add the communication objects a node needs, where the dictionary does not define them.
pub fn add_communication_objects(od: &mut ObjectDictionary, config: &NodeConfig) {
    let id = u32::from(config.node_id);
    let mut defaults = vec![
        Object::var(
            DEVICE_TYPE,
            u32_var("Device type", Access::Ro, config.device_type),
        ),
        Object::var(
            ERROR_REGISTER,
            Variable::new("Error register", DataType::Unsigned8, Access::Ro).mappable(),
        ),
        Object::var(SYNC_COB_ID, u32_var("COB-ID SYNC", Access::Rw, 0x80)),
        Object::var(
            SYNC_PERIOD,
            u32_var("Communication cycle period", Access::Rw, 0),
        ),
        Object::var(
            SYNC_WINDOW,
            u32_var("Synchronous window length", Access::Rw, 0),
        ),
        Object::var(
            DEVICE_NAME,
            Variable::new(
                "Manufacturer device name",
                DataType::VisibleString,
                Access::Const,
            )
            .with_value(Value::Text(config.device_name.clone())),
        ),
        Object::var(
            HARDWARE_VERSION,
            Variable::new(
                "Manufacturer hardware version",
                DataType::VisibleString,
                Access::Const,
            )
            .with_value(Value::Text(config.hardware_version.clone())),
        ),
        Object::var(
            SOFTWARE_VERSION,
            Variable::new(
                "Manufacturer software version",
                DataType::VisibleString,
                Access::Const,
            )
            .with_value(Value::Text(config.software_version.clone())),
        ),
        Object::var(
            GUARD_TIME,
            Variable::new("Guard time", DataType::Unsigned16, Access::Rw),
        ),
        Object::var(
            LIFE_TIME_FACTOR,
            Variable::new("Life time factor", DataType::Unsigned8, Access::Rw),
        ),
        Object::var(
            TIME_COB_ID,
            u32_var("COB-ID time stamp object", Access::Rw, 0x100),
        ),
        Object::var(EMCY_COB_ID, u32_var("COB-ID EMCY", Access::Rw, 0x80 + id)),
        Object::var(
            EMCY_INHIBIT,
            Variable::new("Inhibit time EMCY", DataType::Unsigned16, Access::Rw),
        ),
        Object::var(
            PRODUCER_HEARTBEAT,
            Variable::new("Producer heartbeat time", DataType::Unsigned16, Access::Rw)
                .with_value(Value::Uint(config.heartbeat_ms.into())),
        ),
        Object::var(
            SYNC_OVERFLOW,
            Variable::new(
                "Synchronous counter overflow value",
                DataType::Unsigned8,
                Access::Rw,
            ),
        ),
        Object::composite(
            IDENTITY,
            "Identity object",
            ObjectCode::Record,
            [
                "Vendor-ID",
                "Product code",
                "Revision number",
                "Serial number",
            ]
            .iter()
            .zip(config.identity)
            .enumerate()
            .map(|(i, (name, v))| (i as u8 + 1, u32_var(name, Access::Ro, v))),
        ),
        Object::composite(
            CONSUMER_HEARTBEAT,
            "Consumer heartbeat time",
            ObjectCode::Array,
            (1..=config.consumer_entries.max(1)).map(|i| {
                (
                    i,
                    u32_var(&format!("Consumer heartbeat time {i}"), Access::Rw, 0),
                )
            }),
        ),
        Object::composite(
            SDO_SERVER,
            "SDO server parameter",
            ObjectCode::Record,
            [
                (
                    1,
                    u32_var("COB-ID client to server", Access::Ro, 0x600 + id),
                ),
                (
                    2,
                    u32_var("COB-ID server to client", Access::Ro, 0x580 + id),
                ),
            ],
        ),
    ];
    for (n, &(request, response)) in (1u16..0x80).zip(&config.sdo_servers) {
        defaults.push(Object::composite(
            SDO_SERVER + n,
            "SDO server parameter",
            ObjectCode::Record,
            [
                // Writable (CiA 301 §7.5.2.33): a client may move or close the channel,
                // under the rule of `SdoServerGuard`.
                (
                    1,
                    u32_var(
                        "COB-ID client to server",
                        Access::Rw,
                        parameter_from_id(request),
                    ),
                ),
                (
                    2,
                    u32_var(
                        "COB-ID server to client",
                        Access::Rw,
                        parameter_from_id(response),
                    ),
                ),
            ],
        ));
    }
    let mut history = Object::composite(
        ERROR_HISTORY,
        "Pre-defined error field",
        ObjectCode::Array,
        (1..=8u8).map(|i| {
            (
                i,
                u32_var(&format!("Standard error field {i}"), Access::Ro, 0),
            )
        }),
    );
    if let Some(count) = history.subs.get_mut(&0) {
        *count = Variable::new("Number of errors", DataType::Unsigned8, Access::Rw)
            .with_hook(Arc::new(HistoryCount));
    }
    defaults.push(history);
    for object in defaults {
        if od.object(object.index).is_none() {
            od.insert(object);
        }
    }
    crate::pdo::add_pdo_objects(od, config.node_id, config.pdos.0, config.pdos.1);
    od.guard(Arc::new(crate::pdo::PdoGuard));
    od.guard(Arc::new(crate::sdo::server::SdoServerGuard));
}

/// Move the default COB-IDs that derive from the node-ID (EMCY, SDO server, PDOs 1–4) from
/// `old` to `new`; identifiers the application set to something else stay.
pub(super) fn renumber(od: &mut ObjectDictionary, old: u8, new: u8) {
    let mut derived = vec![
        (EMCY_COB_ID, 0u8, 0x80u32),
        (SDO_SERVER, 1, 0x600),
        (SDO_SERVER, 2, 0x580),
    ];
    for n in 0..4u16 {
        derived.push((crate::pdo::RPDO_COMM + n, 1, 0x200 + 0x100 * u32::from(n)));
        derived.push((crate::pdo::TPDO_COMM + n, 1, 0x180 + 0x100 * u32::from(n)));
    }
    for (index, sub, base) in derived {
        if let Ok(Value::Uint(v)) = od.get_value(index, sub) {
            let v = v as u32;
            if v & 0x7FF == base + u32::from(old) {
                let renumbered = (v & !0x7FF) | (base + u32::from(new));
                let _ = od.set(index, sub, &renumbered.to_le_bytes());
            }
        }
    }
}
