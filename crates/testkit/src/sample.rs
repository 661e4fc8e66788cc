//! A small dictionary for tests of the CANopen services and tools: one object of each kind they
//! exercise, at fixed indices.

use canopen::od::{Access, Object, ObjectDictionary, Variable};
use canopen::types::{DataType, Value};

/// UNSIGNED16, read-write, mappable: a car position (PDO tests).
pub const POSITION: u16 = 0x2000;
/// UNSIGNED32, read-write, mappable: a set-point (RPDO tests).
pub const SETPOINT: u16 = 0x2001;
/// DOMAIN, read-write: large transfers (segmented and block SDO).
pub const BLOB: u16 = 0x2002;
/// UNSIGNED32, read-only, kept across restarts: a trip counter (storage tests).
pub const TRIPS: u16 = 0x2003;

/// The sample dictionary: 1000h device type (a CiA 417 lift controller), 1008h device name,
/// and the objects above.
pub fn dictionary() -> ObjectDictionary {
    let mut od = ObjectDictionary::new();
    let var = |index, v: Variable| Object::var(index, v);
    od.insert(var(
        0x1000,
        Variable::new("Device type", DataType::Unsigned32, Access::Ro)
            .with_value(Value::Uint(0x0001_01A1)),
    ));
    od.insert(var(
        0x1008,
        Variable::new(
            "Manufacturer device name",
            DataType::VisibleString,
            Access::Const,
        )
        .with_value(Value::Text("lift controller".into())),
    ));
    od.insert(var(
        POSITION,
        Variable::new("Car position", DataType::Unsigned16, Access::Rw).mappable(),
    ));
    od.insert(var(
        SETPOINT,
        Variable::new("Setpoint", DataType::Unsigned32, Access::Rw).mappable(),
    ));
    od.insert(var(
        BLOB,
        Variable::new("Blob", DataType::Domain, Access::Rw),
    ));
    od.insert(var(
        TRIPS,
        Variable::new("Trip counter", DataType::Unsigned32, Access::Ro).persistent(),
    ));
    od
}
