//! [`LocalNode`]: a CANopen device on a bus. One task owns the sans-IO machines (NMT, SDO
//! server channels, heartbeat producer and consumer, EMCY, SYNC) and drives them from bus frames,
//! dictionary changes and application commands, sleeping until the earliest deadline (never
//! polling: an idle node costs nothing).
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

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use canbus::{Bus, BusSender, Frame};
use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;

use crate::driver::{sleep_until, SharedDictionary};
use crate::emcy::{EmcyMessage, EmcyProducer};
use crate::heartbeat::{timeout_emcy, HeartbeatConsumer, HeartbeatEvent, HeartbeatProducer};
use crate::nmt::{NmtAction, NmtCommand, NmtSlave, NmtState};
use crate::od::{Access, Object, ObjectCode, ObjectDictionary, Variable, VariableHook};
use crate::pdo::{PdoEngine, PdoEvent};
use crate::sdo::abort::AbortCode;
use crate::sdo::server::{server_channels, ServerChannels, ServerConfig};
use crate::sync::{SyncConfig, SyncEvent, SyncProducer};
use crate::types::{DataType, Value};

/// How a node starts.
#[derive(Debug, Clone)]
pub struct NodeConfig {
    /// Node-ID 1–127.
    pub node_id: u8,
    /// 0x1000 device type (CiA 417 lift controllers: 0x000001A1 with their profile bits).
    pub device_type: u32,
    /// 0x1018 vendor-ID, product code, revision number, serial number.
    pub identity: [u32; 4],
    /// 0x100A manufacturer software version.
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
}

impl NodeConfig {
    /// Defaults for `node_id`.
    pub fn new(node_id: u8) -> Self {
        NodeConfig {
            node_id,
            device_type: 0,
            identity: [0; 4],
            software_version: String::new(),
            heartbeat_ms: 0,
            consumer_entries: 8,
            pdos: (4, 4),
            storage: None,
            sdo: ServerConfig::default(),
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

enum Command {
    SendTime(std::time::SystemTime),
    SetError(u16, [u8; 5]),
    ClearError(u16),
    Nmt(NmtCommand),
    SendPdo(u16),
}

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
            0x1000,
            u32_var("Device type", Access::Ro, config.device_type),
        ),
        Object::var(
            0x1001,
            Variable::new("Error register", DataType::Unsigned8, Access::Ro).mappable(),
        ),
        Object::var(0x1005, u32_var("COB-ID SYNC", Access::Rw, 0x80)),
        Object::var(0x1006, u32_var("Communication cycle period", Access::Rw, 0)),
        Object::var(0x1007, u32_var("Synchronous window length", Access::Rw, 0)),
        Object::var(
            0x100A,
            Variable::new(
                "Manufacturer software version",
                DataType::VisibleString,
                Access::Const,
            )
            .with_value(Value::Text(config.software_version.clone())),
        ),
        Object::var(
            0x100C,
            Variable::new("Guard time", DataType::Unsigned16, Access::Rw),
        ),
        Object::var(
            0x100D,
            Variable::new("Life time factor", DataType::Unsigned8, Access::Rw),
        ),
        Object::var(
            0x1012,
            u32_var("COB-ID time stamp object", Access::Rw, 0x100),
        ),
        Object::var(0x1014, u32_var("COB-ID EMCY", Access::Rw, 0x80 + id)),
        Object::var(
            0x1015,
            Variable::new("Inhibit time EMCY", DataType::Unsigned16, Access::Rw),
        ),
        Object::var(
            0x1017,
            Variable::new("Producer heartbeat time", DataType::Unsigned16, Access::Rw)
                .with_value(Value::Uint(config.heartbeat_ms.into())),
        ),
        Object::var(
            0x1019,
            Variable::new(
                "Synchronous counter overflow value",
                DataType::Unsigned8,
                Access::Rw,
            ),
        ),
        Object::composite(
            0x1018,
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
            0x1016,
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
            0x1200,
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
    let mut history = Object::composite(
        0x1003,
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

/// A CANopen device running on a bus.
pub struct LocalNode {
    od: SharedDictionary,
    commands: mpsc::UnboundedSender<Command>,
    state: watch::Receiver<NmtState>,
    events: broadcast::Sender<NodeEvent>,
    task: JoinHandle<()>,
    node_id: u8,
}

impl LocalNode {
    /// Add the communication objects to `od`, start the node on `bus` and send its boot-up
    /// message; it enters pre-operational.
    pub fn start(bus: Bus, mut od: ObjectDictionary, mut config: NodeConfig) -> LocalNode {
        // A node-ID stored by LSS replaces the configured one.
        if let Some(id) = config.storage.as_deref().and_then(stored_node_id) {
            config.node_id = id;
        }
        add_communication_objects(&mut od, &config);
        if let Some(path) = &config.storage {
            crate::storage::add_storage_objects(&mut od, path.clone());
        }
        let (change_tx, change_rx) = mpsc::unbounded_channel();
        od.watch(Arc::new(move |index, sub| {
            // Communication parameters steer the node; every other change may trigger a TPDO.
            let _ = change_tx.send((index, sub));
        }));
        // The defaults, for resets; stored values come on top of them.
        let initial = od.clone();
        if let Some(path) = &config.storage {
            apply_stored(&mut od, path, 0x0000..=0xFFFF);
        }
        let od = Arc::new(Mutex::new(od));
        let (commands, command_rx) = mpsc::unbounded_channel();
        let (state_tx, state) = watch::channel(NmtState::Initialising);
        let (events, _) = broadcast::channel(1024);
        let driver = Driver::new(&config, od.clone(), initial, events.clone(), state_tx);
        let task = tokio::spawn(driver.run(bus, command_rx, change_rx));
        LocalNode {
            od,
            commands,
            state,
            events,
            task,
            node_id: config.node_id,
        }
    }

    /// The node-ID.
    pub fn node_id(&self) -> u8 {
        self.node_id
    }

    /// The object dictionary, shared with the node task (lock it briefly).
    pub fn od(&self) -> &SharedDictionary {
        &self.od
    }

    /// Set a value as the application (no access check); watchers and the node see it.
    pub fn set_value(&self, index: u16, sub: u8, value: &Value) -> Result<(), AbortCode> {
        self.od
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .set_value(index, sub, value)
    }

    /// Read a value as the application.
    pub fn value(&self, index: u16, sub: u8) -> Result<Value, AbortCode> {
        self.od
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get_value(index, sub)
    }

    /// The node's NMT state.
    pub fn nmt_state(&self) -> NmtState {
        *self.state.borrow()
    }

    /// Wait until the node is in `state`.
    pub async fn wait_for_state(&self, state: NmtState) {
        let mut rx = self.state.clone();
        let _ = rx.wait_for(|s| *s == state).await;
    }

    /// Change the node's own NMT state as if commanded (e.g. a device that starts itself).
    pub fn nmt(&self, command: NmtCommand) {
        let _ = self.commands.send(Command::Nmt(command));
    }

    /// Send a TIME stamp for `at`, if 0x1012 makes this node the TIME producer (bit 30).
    pub fn send_time(&self, at: std::time::SystemTime) {
        let _ = self.commands.send(Command::SendTime(at));
    }

    /// Raise an error: EMCY, error register 0x1001 and history 0x1003.
    pub fn set_error(&self, code: u16, manufacturer: [u8; 5]) {
        let _ = self.commands.send(Command::SetError(code, manufacturer));
    }

    /// Clear an error (an error-reset EMCY follows when none is left).
    pub fn clear_error(&self, code: u16) {
        let _ = self.commands.send(Command::ClearError(code));
    }

    /// Configure a PDO with the CiA 301 procedure (as an SDO client would, so the same checks
    /// apply): invalidate, parameters, mapping, validate.
    pub fn configure_pdo(&self, setup: &PdoSetup) -> Result<(), AbortCode> {
        use crate::pdo::{MapEntry, RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP};
        let n = setup.number.checked_sub(1).ok_or(AbortCode::NO_OBJECT)?;
        let (comm, map) = if setup.transmit {
            (TPDO_COMM + n, TPDO_MAP + n)
        } else {
            (RPDO_COMM + n, RPDO_MAP + n)
        };
        let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
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

    /// Send TPDO `number` now (subject to its inhibit time; types 0–240 at the next SYNC).
    pub fn send_pdo(&self, number: u16) {
        let _ = self.commands.send(Command::SendPdo(number));
    }

    /// Subscribe to the node's events.
    pub fn events(&self) -> broadcast::Receiver<NodeEvent> {
        self.events.subscribe()
    }

    /// Stop the node task.
    pub async fn stop(self) {
        self.task.abort();
        let _ = self.task.await;
    }
}

/// Where LSS "store configuration" keeps the node-ID and bit timing: beside the parameters.
fn lss_path(storage: &std::path::Path) -> std::path::PathBuf {
    storage.with_extension("lss")
}

/// The node-ID stored by LSS, if any.
fn stored_node_id(storage: &std::path::Path) -> Option<u8> {
    let text = std::fs::read_to_string(lss_path(storage)).ok()?;
    let id: u8 = text.split_whitespace().next()?.parse().ok()?;
    (1..=127).contains(&id).then_some(id)
}

/// Move the default COB-IDs that derive from the node-ID (EMCY, SDO server, PDOs 1–4) from
/// `old` to `new`; identifiers the application set to something else stay.
fn renumber(od: &mut ObjectDictionary, old: u8, new: u8) {
    let mut derived = vec![
        (0x1014u16, 0u8, 0x80u32),
        (0x1200, 1, 0x600),
        (0x1200, 2, 0x580),
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

/// Put the stored values of `range` from `path` into `od`; a damaged file is reported and
/// ignored (the node starts with its defaults rather than not at all).
fn apply_stored(
    od: &mut ObjectDictionary,
    path: &std::path::Path,
    range: std::ops::RangeInclusive<u16>,
) {
    match crate::storage::load(path) {
        Ok(entries) => {
            let entries: Vec<_> = entries
                .into_iter()
                .filter(|(i, _, _)| range.contains(i))
                .collect();
            crate::storage::apply(od, &entries);
        }
        Err(e) => tracing::error!(error = %e, "stored parameters not loaded"),
    }
}

struct Driver {
    node_id: u8,
    storage: Option<std::path::PathBuf>,
    lss: crate::lss::LssSlave,
    sdo_config: ServerConfig,
    od: SharedDictionary,
    initial: ObjectDictionary,
    events: broadcast::Sender<NodeEvent>,
    state: watch::Sender<NmtState>,
    nmt: NmtSlave,
    sdo: ServerChannels,
    producer: HeartbeatProducer,
    consumer: HeartbeatConsumer,
    guarding: crate::guarding::GuardingSlave,
    emcy: EmcyProducer,
    sync_config: SyncConfig,
    sync: SyncProducer,
    /// 0x1012: the TIME COB-ID, consumer (bit 31) and producer (bit 30).
    time: (Option<canbus::CanId>, bool, bool),
    pdo: PdoEngine,
    out: Vec<Frame>,
}

fn u32_value(od: &ObjectDictionary, index: u16, sub: u8) -> u32 {
    match od.get_value(index, sub) {
        Ok(Value::Uint(v)) => u32::try_from(v).unwrap_or(0),
        _ => 0,
    }
}

impl Driver {
    fn new(
        config: &NodeConfig,
        od: SharedDictionary,
        initial: ObjectDictionary,
        events: broadcast::Sender<NodeEvent>,
        state: watch::Sender<NmtState>,
    ) -> Self {
        let now = Instant::now();
        let sdo = {
            let guard = od.lock().unwrap_or_else(PoisonError::into_inner);
            ServerChannels::new(server_channels(&guard, config.node_id), &config.sdo)
        };
        let mut driver = Driver {
            node_id: config.node_id,
            storage: config.storage.clone(),
            lss: crate::lss::LssSlave::new(config.identity, config.node_id),
            sdo_config: config.sdo.clone(),
            od,
            initial,
            events,
            state,
            nmt: NmtSlave::new(config.node_id),
            sdo,
            producer: HeartbeatProducer::new(config.node_id),
            consumer: HeartbeatConsumer::new(),
            guarding: crate::guarding::GuardingSlave::new(config.node_id),
            emcy: EmcyProducer::new(config.node_id),
            sync_config: SyncConfig::default(),
            sync: SyncProducer::new(SyncConfig::default(), now),
            time: (None, false, false),
            pdo: PdoEngine::default(),
            out: Vec::new(),
        };
        driver.load_communication(now);
        driver
    }

    /// (Re)read every communication parameter from the dictionary.
    fn load_communication(&mut self, now: Instant) {
        for index in [0x1005, 0x100C, 0x1012, 0x1014, 0x1015, 0x1016, 0x1017] {
            self.apply(index, 0, now);
        }
        let od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
        self.sdo = ServerChannels::new(server_channels(&od, self.node_id), &self.sdo_config);
        self.pdo = PdoEngine::configure(&od, now);
    }

    /// React to a change of a communication parameter.
    fn apply(&mut self, index: u16, sub: u8, now: Instant) {
        let od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
        match index {
            // Writing 0 to 0x1003 sub 0 clears the history (our own mirror writes never
            // write 0 while a history exists).
            0x1003
                if sub == 0
                    && od.get_value(0x1003, 0) == Ok(Value::Uint(0))
                    && self.emcy.history().next().is_some() =>
            {
                self.emcy.clear_history();
                drop(od);
                self.write_history();
            }
            0x1005 | 0x1006 | 0x1007 | 0x1019 => {
                self.sync_config = SyncConfig {
                    cob_id: u32_value(&od, 0x1005, 0),
                    period_us: u32_value(&od, 0x1006, 0),
                    window_us: u32_value(&od, 0x1007, 0),
                    counter_overflow: u32_value(&od, 0x1019, 0) as u8,
                };
                self.sync.reconfigure(self.sync_config, now);
            }
            0x100C | 0x100D => self.guarding.configure(
                u32_value(&od, 0x100C, 0) as u16,
                u32_value(&od, 0x100D, 0) as u8,
            ),
            0x1012 => {
                let value = u32_value(&od, 0x1012, 0);
                let id = crate::cob::id_from_parameter(value & 0x3FFF_FFFF);
                self.time = (id, value & 0x8000_0000 != 0, value & 0x4000_0000 != 0);
            }
            0x1014 => self.emcy.set_cob_id(u32_value(&od, 0x1014, 0)),
            0x1015 => self
                .emcy
                .set_inhibit_100us(u32_value(&od, 0x1015, 0) as u16),
            0x1016 => {
                // Re-target monitoring; the table keeps what it knows about every node.
                let known: Vec<u8> = self.consumer.table().map(|(n, _)| n).collect();
                for node in known {
                    self.consumer.monitor(node, None);
                }
                let entries = od.object(0x1016).map(|o| o.subs.len()).unwrap_or(0);
                for s in 1..entries as u8 {
                    self.consumer.monitor_entry(u32_value(&od, 0x1016, s));
                }
            }
            0x1017 => self
                .producer
                .set_period_ms(u32_value(&od, 0x1017, 0) as u16, now),
            _ if PdoEngine::is_config(index) => self.pdo = PdoEngine::configure(&od, now),
            _ => self.pdo.on_change(index, sub, now),
        }
    }

    /// Mirror the EMCY producer's register and history into 0x1001 and 0x1003.
    fn write_history(&mut self) {
        let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
        let _ = od.set(0x1001, 0, &[self.emcy.error_register()]);
        let slots = od
            .object(0x1003)
            .map(|o| o.subs.len().saturating_sub(1))
            .unwrap_or(0);
        let history: Vec<u32> = self.emcy.history().take(slots).collect();
        for s in 1..=slots {
            let v = history.get(s - 1).copied().unwrap_or(0);
            let _ = od.set(0x1003, s as u8, &v.to_le_bytes());
        }
        let _ = od.set(0x1003, 0, &[history.len() as u8]);
    }

    fn enter(&mut self, state: NmtState) {
        if state == NmtState::Operational {
            // Event-driven TPDOs announce their current values on entering operational.
            self.pdo.trigger_all(Instant::now());
        }
        let _ = self.state.send(state);
        let _ = self.events.send(NodeEvent::Nmt(state));
    }

    fn boot(&mut self, now: Instant) {
        let frame = self.nmt.boot();
        self.out.push(frame);
        self.load_communication(now);
        self.enter(NmtState::PreOperational);
    }

    /// Take the node-ID configured by LSS (CiA 305: at reset communication, or at once for a
    /// node that had none).
    fn change_node_id(&mut self, new: u8) {
        let old = self.node_id;
        tracing::info!(old, new, "node-ID changed by LSS");
        renumber(&mut self.initial, old, new);
        renumber(
            &mut self.od.lock().unwrap_or_else(PoisonError::into_inner),
            old,
            new,
        );
        self.node_id = new;
        self.nmt = NmtSlave::new(new);
        self.producer = HeartbeatProducer::new(new);
        self.guarding = crate::guarding::GuardingSlave::new(new);
        self.emcy = EmcyProducer::new(new);
        self.lss.set_active_node_id(new);
    }

    fn lss_frame(&mut self, frame: &Frame, now: Instant) {
        use crate::lss::{LssAction, LssState, UNCONFIGURED};
        let (reply, action) = self.lss.handle(frame);
        self.out.extend(reply);
        match action {
            Some(LssAction::Store) => {
                let result = match &self.storage {
                    None => 1,
                    Some(path) => {
                        let text = format!(
                            "{} {}\n",
                            self.lss.pending_node_id(),
                            self.lss
                                .pending_bit_timing()
                                .map_or(String::from("-"), |b| b.to_string())
                        );
                        match crate::storage::write_atomically(&lss_path(path), &text) {
                            Ok(()) => 0,
                            Err(e) => {
                                tracing::error!(error = %e, "LSS store failed");
                                2
                            }
                        }
                    }
                };
                self.out.push(self.lss.store_result(result));
            }
            Some(LssAction::ActivateBitTiming { delay_ms }) => {
                // A virtual bus has no bit timing to switch; a SocketCAN deployment does it
                // with `ip link` outside this process.
                tracing::info!(delay_ms, bit_timing = ?self.lss.pending_bit_timing(), "LSS activate bit timing");
            }
            Some(LssAction::StateChanged(LssState::Waiting)) => {
                let pending = self.lss.pending_node_id();
                if self.node_id == UNCONFIGURED && (1..=127).contains(&pending) {
                    self.change_node_id(pending);
                    self.boot(now);
                }
            }
            Some(LssAction::StateChanged(LssState::Configuration)) | None => {}
        }
    }

    /// Reset: restore the values of `range` from the start-up dictionary, then boot again.
    fn reset(&mut self, range: std::ops::RangeInclusive<u16>, now: Instant) {
        let pending = self.lss.pending_node_id();
        if pending != self.node_id && (1..=127).contains(&pending) {
            self.change_node_id(pending);
        }
        {
            let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
            for object in self.initial.objects().filter(|o| range.contains(&o.index)) {
                for (sub, var) in &object.subs {
                    if let Some(bytes) = var.value_bytes() {
                        let _ = od.set(object.index, *sub, bytes);
                    }
                }
            }
            if let Some(path) = &self.storage {
                apply_stored(&mut od, path, range);
            }
        }
        self.emcy = EmcyProducer::new(self.node_id);
        self.enter(NmtState::Initialising);
        self.boot(now);
    }

    fn nmt_action(&mut self, action: NmtAction, now: Instant) {
        match action {
            NmtAction::Entered(state) => self.enter(state),
            NmtAction::ResetCommunication => self.reset(0x1000..=0x1FFF, now),
            NmtAction::ResetNode => self.reset(0x0000..=0xFFFF, now),
        }
    }

    fn frame(&mut self, frame: &Frame, now: Instant) {
        if frame.id() == crate::lss::MASTER_ID {
            self.lss_frame(frame, now);
            return;
        }
        if self.nmt.state() == NmtState::Initialising {
            // No node-ID yet (waiting for LSS): nothing else is served.
            return;
        }
        if let Some(action) = self.nmt.handle(frame) {
            self.nmt_action(action, now);
            return;
        }
        if frame.is_remote() && self.nmt.state().allows_pdo() {
            let od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
            let answered = self.pdo.handle_remote(&od, frame, now, &mut self.out);
            drop(od);
            if answered {
                return;
            }
        }
        if frame.is_remote() {
            let mut events = Vec::new();
            if let Some(reply) = self
                .guarding
                .handle(frame, self.nmt.state(), now, &mut events)
            {
                self.out.push(reply);
            }
            self.guard_events(events);
            return;
        }
        let state = self.nmt.state();
        if state.allows_sdo() && self.sdo.serves(frame.id()) {
            let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
            self.sdo.handle(&mut od, frame, now, &mut self.out);
            return;
        }
        let mut heartbeat = Vec::new();
        self.consumer.handle(frame, now, &mut heartbeat);
        self.heartbeat_events(heartbeat);
        if let Some((node, message)) = EmcyMessage::from_frame(frame) {
            if node != self.node_id {
                let _ = self.events.send(NodeEvent::Emcy { node, message });
            }
        }
        if state.allows_pdo() && self.pdo.is_rpdo(frame.id()) {
            let mut pdo_events = Vec::new();
            let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
            let was_pdo = self.pdo.handle_frame(&mut od, frame, now, &mut pdo_events);
            drop(od);
            if was_pdo && pdo_events.is_empty() {
                // A correct RPDO ends the length and timeout errors it may have raised.
                let active = [0x8210, 0x8220, 0x8250]
                    .into_iter()
                    .filter(|c| self.emcy.is_active(*c));
                let cleared: Vec<u16> = active.collect();
                for code in &cleared {
                    self.emcy.clear_error(*code);
                }
                if !cleared.is_empty() {
                    self.write_history();
                }
            }
            self.pdo_events(pdo_events);
            if was_pdo {
                return;
            }
        }
        if state.allows_sdo() {
            let (time_id, consumes, _) = self.time;
            if consumes && Some(frame.id()) == time_id {
                if let Some(stamp) = crate::time::TimeOfDay::parse(frame.data()) {
                    let _ = self.events.send(NodeEvent::Time(stamp.to_system()));
                }
                return;
            }
            if let Some(event) = crate::sync::receive(&self.sync_config, frame, now) {
                if state.allows_pdo() {
                    let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
                    self.pdo.on_sync(&mut od, event.counter, now, &mut self.out);
                }
                let _ = self.events.send(NodeEvent::Sync(event));
            }
        }
    }

    fn pdo_events(&mut self, events: Vec<PdoEvent>) {
        if events.is_empty() {
            return;
        }
        for e in events {
            let number = match e {
                PdoEvent::LengthError { rpdo }
                | PdoEvent::LengthExceeded { rpdo }
                | PdoEvent::Timeout { rpdo } => rpdo,
            };
            let n = number.to_le_bytes();
            self.emcy.set_error(e.emcy_code(), [n[0], n[1], 0, 0, 0]);
        }
        self.write_history();
    }

    fn send_time(&mut self, at: std::time::SystemTime) {
        let (id, _, produces) = self.time;
        match (id, produces, crate::time::TimeOfDay::from_system(at)) {
            (Some(id), true, Some(stamp)) if self.nmt.state().allows_sdo() => {
                self.out.push(stamp.frame(id))
            }
            (_, false, _) => tracing::debug!("TIME not sent: 0x1012 bit 30 (producer) is clear"),
            _ => tracing::debug!("TIME not sent: not representable or not allowed in this state"),
        }
    }

    fn guard_events(&mut self, events: Vec<crate::guarding::GuardEvent>) {
        use crate::guarding::GuardEvent;
        for event in events {
            match event {
                GuardEvent::LifeGuardingLost => self.emcy.set_error(0x8130, [0; 5]),
                GuardEvent::LifeGuardingResumed => self.emcy.clear_error(0x8130),
                _ => {}
            }
            self.write_history();
            let _ = self.events.send(NodeEvent::Guarding(event));
        }
    }

    fn heartbeat_events(&mut self, events: Vec<HeartbeatEvent>) {
        let mut history_changed = false;
        for event in events {
            match event {
                HeartbeatEvent::Timeout { node } => {
                    let (code, data) = timeout_emcy(node);
                    // One 0x8130 per node: the node-ID is in the manufacturer field.
                    self.emcy.set_error(code, data);
                    history_changed = true;
                }
                HeartbeatEvent::Recovered { .. } => {
                    self.emcy.clear_error(0x8130);
                    history_changed = true;
                }
                HeartbeatEvent::StateChanged { .. } | HeartbeatEvent::BootUp { .. } => {}
            }
            let _ = self.events.send(NodeEvent::Heartbeat(event));
        }
        if history_changed {
            self.write_history();
        }
    }

    fn deadline(&self) -> Option<Instant> {
        [
            self.producer.poll_timeout(),
            self.consumer.poll_timeout(),
            self.guarding.poll_timeout(),
            self.emcy.poll_timeout(),
            self.sync.poll_timeout(),
            self.sdo.poll_timeout(),
            self.pdo
                .poll_timeout()
                .filter(|_| self.nmt.state().allows_pdo()),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    fn timers(&mut self, now: Instant) {
        let state = self.nmt.state();
        if state != NmtState::Initialising {
            if let Some(f) = self.producer.handle_timeout(now, state) {
                self.out.push(f);
            }
        }
        let mut heartbeat = Vec::new();
        self.consumer.handle_timeout(now, &mut heartbeat);
        self.heartbeat_events(heartbeat);
        let mut guard = Vec::new();
        self.guarding.handle_timeout(now, &mut guard);
        self.guard_events(guard);
        self.sdo.handle_timeout(now, &mut self.out);
        if state.allows_sdo() {
            while let Some(f) = self.emcy.poll_transmit(now) {
                self.out.push(f);
            }
            if let Some(f) = self.sync.handle_timeout(now) {
                // This node's own SYNC drives its synchronous PDOs too.
                if state.allows_pdo() {
                    let counter = f.data().first().copied();
                    let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
                    self.out.push(f);
                    self.pdo.on_sync(&mut od, counter, now, &mut self.out);
                } else {
                    self.out.push(f);
                }
            }
        }
        if state.allows_pdo() {
            let mut pdo_events = Vec::new();
            let od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
            self.pdo
                .handle_timeout(&od, now, &mut self.out, &mut pdo_events);
            drop(od);
            self.pdo_events(pdo_events);
        }
        if !state.allows_sdo() && self.sync.poll_timeout().is_some_and(|d| d <= now) {
            // SYNC is not produced while stopped; keep the schedule moving.
            let _ = self.sync.handle_timeout(now);
        }
    }

    async fn flush(&mut self, sender: &BusSender) -> bool {
        for f in self.out.drain(..) {
            match sender.send(f).await {
                Ok(()) => {}
                Err(canbus::BusError::Offline { .. }) => {}
                Err(_) => return false,
            }
        }
        true
    }

    async fn run(
        mut self,
        bus: Bus,
        mut commands: mpsc::UnboundedReceiver<Command>,
        mut changes: mpsc::UnboundedReceiver<(u16, u8)>,
    ) {
        let (sender, mut receiver) = bus.split();
        // Microsecond wake-ups for SYNC periods and inhibit times; tokio's timer as fallback.
        let alarm = crate::alarm::Alarm::new(&format!("canopen-node-{}", self.node_id)).ok();
        if self.node_id != crate::lss::UNCONFIGURED {
            self.boot(Instant::now());
        }
        loop {
            if !self.flush(&sender).await {
                return;
            }
            // Time-driven work first so that a busy bus never starves the timers.
            let deadline = self.deadline();
            let wake = async {
                match &alarm {
                    Some(alarm) => {
                        alarm.set(deadline);
                        alarm.fired().await
                    }
                    None => sleep_until(deadline).await,
                }
            };
            tokio::select! {
                biased;
                _ = wake => self.timers(Instant::now()),
                event = receiver.recv() => match event {
                    Some(canbus::BusEvent::Frame(f)) => self.frame(&f, Instant::now()),
                    Some(_) => {}
                    None => return,
                },
                Some((index, sub)) = changes.recv() => self.apply(index, sub, Instant::now()),
                Some(command) = commands.recv() => {
                    match command {
                        Command::SetError(code, data) => self.emcy.set_error(code, data),
                        Command::ClearError(code) => self.emcy.clear_error(code),
                        Command::Nmt(c) => {
                            if let Some(action) = self.nmt.handle(&c.frame(self.node_id)) {
                                self.nmt_action(action, Instant::now());
                            }
                        }
                        Command::SendPdo(n) => self.pdo.request(n, Instant::now()),
                        Command::SendTime(at) => self.send_time(at),
                    }
                    self.write_history();
                }
            }
            // Zero-delay work (EMCY ready to go, SDO responses) goes out on this turn.
            self.timers(Instant::now());
        }
    }
}

/// Wait for a node's next event matching `pred`, up to `limit`.
pub async fn wait_event(
    events: &mut broadcast::Receiver<NodeEvent>,
    limit: Duration,
    pred: impl Fn(&NodeEvent) -> bool,
) -> Option<NodeEvent> {
    tokio::time::timeout(limit, async {
        loop {
            match events.recv().await {
                Ok(e) if pred(&e) => return Some(e),
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => return None,
            }
        }
    })
    .await
    .ok()
    .flatten()
}
