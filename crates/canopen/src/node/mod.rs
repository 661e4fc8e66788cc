//! A CANopen device: the sans-IO [`Node`] core that composes every service of CiA 301 over an
//! object dictionary, the communication objects it adds to the dictionary, and (feature
//! `tokio`) [`LocalNode`], the core running on a bus.
//!
//! ```no_run
//! # async fn demo() -> Result<(), Box<dyn std::error::Error>> {
//! use canopen::node::{LocalNode, NodeConfig};
//! use canopen::od::ObjectDictionary;
//!
//! let bus = canbus::Bus::open("socketcand://127.0.0.1:29536/can0").await?;
//! let config = NodeConfig { heartbeat_ms: 1000, software_version: "01.23.10".into(), ..NodeConfig::new(1) };
//! let node = LocalNode::start(bus, ObjectDictionary::new(), config);
//! node.set_error(0x5000, [0; 5]); // EMCY, error register, 0x1003 history
//! let mut events = node.events();
//! while let Ok(event) = events.recv().await {
//!     println!("{event:?}");
//! }
//! # Ok(()) }
//! ```

mod core;
#[cfg(feature = "tokio")]
mod local;
mod objects;

pub use self::core::{Node, NodeOutput};
#[cfg(feature = "tokio")]
pub use local::{wait_event, LocalNode};
pub use objects::add_communication_objects;

use crate::emcy::EmcyMessage;
use crate::heartbeat::HeartbeatEvent;
use crate::nmt::{NmtCommand, NmtState};
use crate::od::ObjectDictionary;
use crate::sdo::abort::AbortCode;
use crate::sdo::server::ServerConfig;
use crate::sync::SyncEvent;
use crate::types::Value;

/// How a node starts.
#[derive(Debug, Clone)]
pub struct NodeConfig {
    /// Node-ID 1–127.
    pub node_id: u8,
    /// 0x1000 device type (CiA 417 lift controllers: 0x000001A1 with their profile bits).
    pub device_type: u32,
    /// 0x1018 vendor-ID, product code, revision number, serial number.
    pub identity: [u32; 4],
    /// 1008h manufacturer device name.
    pub device_name: String,
    /// 1009h manufacturer hardware version.
    pub hardware_version: String,
    /// 100Ah manufacturer software version.
    pub software_version: String,
    /// 0x1017 producer heartbeat time at start (ms, 0 = off).
    pub heartbeat_ms: u16,
    /// Entries of 0x1016 (consumer heartbeat times).
    pub consumer_entries: u8,
    /// RPDOs and TPDOs the node offers (communication and mapping objects are added).
    pub pdos: (u16, u16),
    /// Where "store parameters" (0x1010) keeps values; `None`: 0x1010/0x1011 are not offered.
    pub storage: Option<std::path::PathBuf>,
    /// SDO server behaviour.
    pub sdo: ServerConfig,
    /// Further SDO server channels (request, response COB-ID), offered as 1201h, 1202h, …
    /// (CiA 301 §7.5.2.33) beside the default one: a client given several of them, like the
    /// gateway, runs as many transfers to this node at once. A client may move one, as that
    /// section has it, only while it is not valid.
    pub sdo_servers: Vec<(canbus::CanId, canbus::CanId)>,
    /// A self-starting device (CiA 302 1F80h bit 2): after every boot — power-on and each NMT
    /// reset — it enters operational by itself instead of waiting for an NMT master.
    pub self_starting: bool,
}

impl NodeConfig {
    /// Defaults for `node_id`.
    pub fn new(node_id: u8) -> Self {
        NodeConfig {
            node_id,
            device_type: 0,
            identity: [0; 4],
            device_name: String::new(),
            hardware_version: String::new(),
            software_version: String::new(),
            heartbeat_ms: 0,
            consumer_entries: 8,
            pdos: (4, 4),
            storage: None,
            sdo: ServerConfig::default(),
            sdo_servers: Vec::new(),
            self_starting: false,
        }
    }
}

/// What happens on and around a node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NodeEvent {
    /// This node's NMT state changed.
    Nmt(NmtState),
    /// The heartbeat consumer noticed something about another node.
    Heartbeat(HeartbeatEvent),
    /// An EMCY from another node.
    Emcy {
        /// Producer.
        node: u8,
        /// The message.
        message: EmcyMessage,
    },
    /// A SYNC was received.
    Sync(SyncEvent),
    /// Life guarding lost or resumed (this node is guarded by a master).
    Guarding(crate::guarding::GuardEvent),
    /// A TIME stamp was received (0x1012 bit 31 set: this node consumes TIME).
    Time(std::time::SystemTime),
}

/// What the application tells its node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NodeCommand {
    /// Send a TIME stamp for this moment (if 1012h makes the node the producer).
    SendTime(std::time::SystemTime),
    /// Raise an error: EMCY, error register 1001h, history 1003h.
    SetError(u16, [u8; 5]),
    /// Clear an error (an error-reset EMCY follows when none is left).
    ClearError(u16),
    /// Change the node's own NMT state as if commanded.
    Nmt(NmtCommand),
    /// Send TPDO n now.
    SendPdo(u16),
    /// These values (index, sub-index, bytes) are the device's own configuration: every reset
    /// restores them, as a device restores what it set up at boot (its PDOs, say).
    Defaults(Vec<(u16, u8, Vec<u8>)>),
}

/// A PDO set up by the application in one call (the PLC style: identifier, objects in byte
/// order, transmission type, inhibit and event time).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PdoSetup {
    /// Transmit (true) or receive PDO.
    pub transmit: bool,
    /// PDO number from 1.
    pub number: u16,
    /// COB-ID value (bit 29 for a 29-bit identifier; bit 31 set disables the PDO).
    pub cob_id: u32,
    /// Mapped objects in byte order: index and sub-index (lengths come from their types).
    pub objects: Vec<(u16, u8)>,
    /// Transmission type (0, 1–240, 254, 255).
    pub transmission_type: u8,
    /// Inhibit time in 100 µs (TPDO).
    pub inhibit_100us: u16,
    /// Event timer in ms (TPDO) or receive timeout in ms (RPDO).
    pub event_ms: u16,
}

/// The communication and mapping parameter objects of the PDO `setup` configures.
pub(crate) fn pdo_objects(setup: &PdoSetup) -> [u16; 2] {
    use crate::pdo::{RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP};
    let n = setup.number.saturating_sub(1);
    if setup.transmit {
        [TPDO_COMM + n, TPDO_MAP + n]
    } else {
        [RPDO_COMM + n, RPDO_MAP + n]
    }
}

/// [`configure_pdo`], and the PDO so configured becomes the default of its objects: a device's
/// description (its EDS) showing the PDOs the device sets up at boot.
pub fn configure_default_pdo(od: &mut ObjectDictionary, setup: &PdoSetup) -> Result<(), AbortCode> {
    configure_pdo(od, setup)?;
    for index in pdo_objects(setup) {
        od.keep_as_defaults(index);
    }
    Ok(())
}

/// Configure a PDO of `od` with the CiA 301 procedure (as an SDO client would, so the same
/// checks apply): invalidate, parameters, mapping, validate.
pub fn configure_pdo(od: &mut ObjectDictionary, setup: &PdoSetup) -> Result<(), AbortCode> {
    use crate::pdo::MapEntry;
    let [comm, map] = pdo_objects(setup);
    if setup.number == 0 {
        return Err(AbortCode::NO_OBJECT);
    }
    let current = match od.get_value(comm, 1)? {
        Value::Uint(v) => v as u32,
        _ => return Err(AbortCode::GENERAL),
    };
    od.write(comm, 1, &(current | 0x8000_0000).to_le_bytes())?;
    od.write(comm, 2, &[setup.transmission_type])?;
    if setup.transmit {
        od.write(comm, 3, &setup.inhibit_100us.to_le_bytes())?;
    }
    od.write(comm, 5, &setup.event_ms.to_le_bytes())?;
    od.write(map, 0, &[0])?;
    for (i, (index, sub)) in setup.objects.iter().enumerate() {
        let bits = od.variable(*index, *sub)?.data_type.size().unwrap_or(0) * 8;
        let entry = MapEntry {
            index: *index,
            sub: *sub,
            bits: bits as u8,
        };
        od.write(map, i as u8 + 1, &entry.to_u32().to_le_bytes())?;
    }
    od.write(map, 0, &[setup.objects.len() as u8])?;
    od.write(comm, 1, &setup.cob_id.to_le_bytes())
}
