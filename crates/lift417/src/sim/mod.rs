//! The simulated lift on a CANopen bus: a CiA 417 lift controller whose object dictionary is the
//! [catalog](crate::catalog), running one [`model::Lift`] per lift, and an I/O node with the hall
//! and car buttons as CiA 417 virtual inputs (input groups 6100h…, sent to the controller as
//! 6010h "virtual input mapping" by PDO).
//!
//! The lift model runs on simulated time (`speed` times the wall clock); the CANopen side
//! (heartbeat, SDO, PDO timing) runs on the wall clock. Calls come from 0x5022 (passenger call),
//! from the I/O node's buttons (its 0x2000 "simulated button press", or [`Simulator::press`]),
//! and, when asked, from simulated passengers. Faults come from 0x5030 or the configuration and
//! raise EMCY with the CiA 417 codes of [`model::Fault::emcy_code`]. Counters (0x6520, 0x44xx)
//! are stored in the state directory as they change and survive restarts.

pub mod model;

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant};

use canbus::{Bus, CanId};
use canopen::cob::restricted;
use canopen::eds::{self, DeviceDescription};
use canopen::nmt::NmtState;
use canopen::node::{add_communication_objects, LocalNode, NodeConfig, PdoSetup};
use canopen::od::{ObjectDictionary, VariableHook};
use canopen::sdo::abort::AbortCode;
use canopen::types::Value;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;

use crate::catalog::{Catalog, CatalogError, Device};
use crate::lift::MAX_LIFTS;
use model::{CallKind, Counters, Event, Fault, Lift, Params};
pub use model::{FIRE_SERVICE, INSPECTION};

/// CiA 301 device profile number of CiA 417.
pub const PROFILE_417: u32 = 417;
/// Virtual device type of the lift controller in 1000h (CiA 417-1: call controller).
pub const CONTROLLER_DEVICE: u32 = 1;
/// Virtual device type of the I/O node in 1000h (CiA 417-1: input panel unit, our reading).
pub const IO_DEVICE: u32 = 8;
/// Floors the I/O node's buttons can serve: 4 input groups of 8 for hall calls, 4 for car calls.
pub const MAX_IO_FLOORS: u8 = 32;
/// How often the simulator moves the lifts and publishes their state (wall clock).
pub const TICK: Duration = Duration::from_millis(20);

/// How to run the simulator.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Node-ID of the lift controller.
    pub node_id: u8,
    /// Node-ID of the I/O node, if one is simulated.
    pub io_node: Option<u8>,
    /// Floors per lift (2–254; 32 at most with an I/O node).
    pub floors: u8,
    /// Lifts the controller serves (1–8, CiA 417 offsets).
    pub lifts: u8,
    /// Simulated time runs this many times faster than the wall clock.
    pub speed: f64,
    /// Heartbeat producer time of both nodes (ms).
    pub heartbeat_ms: u16,
    /// Where stored parameters and counters live; none: nothing survives a restart.
    pub state_dir: Option<PathBuf>,
    /// Faults (0x5030 bits) lift 1 starts with.
    pub faults: u8,
    /// Door wear: every lift's door closes this many percent more slowly per simulated hour
    /// (0x4403 shows it), until the closing supervision calls it blocked at twice the nominal
    /// time.
    pub door_wear_percent_per_h: f64,
    /// Simulated passengers press a button about this often (simulated time).
    pub passengers: Option<Duration>,
    /// Enter operational by itself (a self-starting device, CiA 302 0x1F80 bit 2).
    pub autostart: bool,
    /// Seed of the simulated passengers and loads.
    pub seed: u64,
    /// Further SDO server channels of the controller (request, response COB-ID; 1201h ff.),
    /// for a gateway that reads it with several transfers at once.
    pub sdo_servers: Vec<(CanId, CanId)>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            node_id: 1,
            io_node: Some(12),
            floors: 8,
            lifts: 1,
            speed: 1.0,
            heartbeat_ms: 1000,
            state_dir: None,
            faults: 0,
            door_wear_percent_per_h: 0.0,
            passengers: None,
            autostart: true,
            seed: 0x5EED,
            sdo_servers: Vec::new(),
        }
    }
}

/// Why the simulator cannot run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A setting is out of range.
    #[error("{0}")]
    Config(String),
    /// The catalog could not be turned into a dictionary.
    #[error(transparent)]
    Catalog(#[from] CatalogError),
    /// The bus could not be opened.
    #[error("bus: {0}")]
    Bus(#[from] canbus::BusError),
    /// The controller refused its own PDO configuration.
    #[error("PDO configuration refused: {0}")]
    Pdo(AbortCode),
}

impl SimConfig {
    fn check(&self) -> Result<(), SimError> {
        let bad = |m: String| Err(SimError::Config(m));
        if !(1..=127).contains(&self.node_id) {
            return bad(format!("node-ID {} is not 1–127", self.node_id));
        }
        if let Some(io) = self.io_node {
            if !(1..=127).contains(&io) || io == self.node_id {
                return bad(format!(
                    "I/O node-ID {io} is not 1–127 or equals the controller's"
                ));
            }
            if self.floors > MAX_IO_FLOORS {
                return bad(format!(
                    "{} floors: the I/O node has buttons for {MAX_IO_FLOORS}",
                    self.floors
                ));
            }
        }
        if !(2..=254).contains(&self.floors) {
            return bad(format!("{} floors: 2 to 254 are possible", self.floors));
        }
        if !(1..=MAX_LIFTS).contains(&self.lifts) {
            return bad(format!("{} lifts: 1 to 8 are possible", self.lifts));
        }
        if !(self.speed.is_finite() && self.speed > 0.0 && self.speed <= 1000.0) {
            return bad(format!("speed {}: more than 0, at most 1000", self.speed));
        }
        let wear = self.door_wear_percent_per_h;
        if !(wear.is_finite() && (0.0..=10_000.0).contains(&wear)) {
            return bad(format!("door wear {wear} %/h: 0 to 10000"));
        }
        self.check_sdo_servers()
    }

    /// Further SDO channels need identifiers of their own: 11-bit, not restricted (CiA 301
    /// §7.3.5, which covers every node's default SDO channel), none of the PDOs' (the
    /// pre-defined connection set's 181h–57Fh and the further lifts' TPDOs) and no two alike.
    fn check_sdo_servers(&self) -> Result<(), SimError> {
        if self.sdo_servers.len() > 127 {
            return Err(SimError::Config(format!(
                "{} SDO server channels: 1201h–127Fh hold 127",
                self.sdo_servers.len()
            )));
        }
        let mut taken: Vec<CanId> = (2..=self.lifts)
            .flat_map(|lift| (0..3).map(move |k| lift_tpdo_cob_id(self.node_id, lift, k)))
            .filter_map(|id| u16::try_from(id).ok().map(CanId::Standard))
            .collect();
        for &(request, response) in &self.sdo_servers {
            for id in [request, response] {
                let why = match id {
                    CanId::Standard(raw) if restricted(raw) => "is restricted (CiA 301 §7.3.5)",
                    CanId::Standard(0x181..=0x57F) => "is a PDO's (CiA 301 §7.3.5)",
                    CanId::Standard(_) if taken.contains(&id) => "is used twice or by a PDO",
                    CanId::Standard(_) => {
                        taken.push(id);
                        continue;
                    }
                    CanId::Extended(_) => "is not an 11-bit identifier",
                };
                return Err(SimError::Config(format!(
                    "SDO channel 0x{request}/0x{response}: 0x{id} {why}"
                )));
            }
        }
        Ok(())
    }

    fn node_config(&self, node_id: u8, device: u32, product: u32, name: &str) -> NodeConfig {
        NodeConfig {
            device_type: device << 16 | PROFILE_417,
            identity: [1050, product, 1, u32::from(node_id)],
            device_name: name.into(),
            hardware_version: "canlift simulator".into(),
            software_version: format!("canlift {}", env!("CARGO_PKG_VERSION")),
            heartbeat_ms: self.heartbeat_ms,
            pdos: (4, 3 * u16::from(self.lifts)),
            storage: self
                .state_dir
                .as_ref()
                .map(|d| d.join(format!("node{node_id}.params"))),
            // Self-starting devices: operational after every boot and every reset.
            self_starting: self.autostart,
            ..NodeConfig::new(node_id)
        }
    }

    fn controller_config(&self) -> NodeConfig {
        NodeConfig {
            sdo_servers: self.sdo_servers.clone(),
            ..self.node_config(self.node_id, CONTROLLER_DEVICE, 0x417_0001, CONTROLLER_NAME)
        }
    }

    fn io_config(&self, id: u8) -> NodeConfig {
        NodeConfig {
            pdos: (4, 4),
            ..self.node_config(id, IO_DEVICE, 0x417_0008, IO_NAME)
        }
    }
}

/// 1008h of the simulated controller (and its EDS's ProductName).
const CONTROLLER_NAME: &str = "canlift simulated lift controller";
/// 1008h of the simulated I/O node.
const IO_NAME: &str = "canlift simulated I/O node";

/// The dictionary of the controller as the simulator starts it: the catalog with floor levels.
fn controller_dictionary(config: &SimConfig) -> Result<ObjectDictionary, SimError> {
    let catalog = Catalog::builtin();
    let mut od = catalog.dictionary(Device::Controller, config.lifts, config.floors)?;
    let levels = Params::with_floors(config.floors).levels;
    for lift in 1..=config.lifts {
        let index = manufacturer(0x4010, lift);
        for (i, level) in levels.iter().enumerate() {
            let sub = u8::try_from(i + 1).unwrap_or(u8::MAX);
            set_default(&mut od, index, sub, Value::Int((*level).into()));
        }
    }
    Ok(od)
}

fn io_dictionary(config: &SimConfig) -> Result<ObjectDictionary, SimError> {
    let mut od = Catalog::builtin().dictionary(Device::Io, 1, config.floors)?;
    set_default(&mut od, 0x6000, 1, Value::Uint(IO_DEVICE.into()));
    for floor in 1..=config.floors {
        for kind in [CallKind::Car, CallKind::HallUp] {
            let (index, sub) = button(floor, kind);
            set_default(
                &mut od,
                index,
                sub,
                Value::Uint(virtual_input(1, floor, kind, false)),
            );
        }
    }
    Ok(od)
}

/// Give a sub-object a value that is also its default (exported EDS, restore defaults).
fn set_default(od: &mut ObjectDictionary, index: u16, sub: u8, value: Value) {
    if let Some(object) = od.object_mut(index) {
        if let Some(var) = object.subs.remove(&sub) {
            object.subs.insert(sub, var.with_value(value));
        }
    }
}

/// The index of lift `lift`'s copy of a per-lift manufacturer object.
fn manufacturer(index: u16, lift: u8) -> u16 {
    index + u16::from(lift - 1) * crate::catalog::MANUFACTURER_LIFT_STRIDE
}

/// The index of lift `lift`'s copy of CiA 417 object `index`.
fn profile(index: u16, lift: u8) -> u16 {
    crate::lift::for_lift(index, lift).unwrap_or(index)
}

/// Where the I/O node keeps a button: hall calls in input groups 1–4, car calls in 5–8, eight
/// floors per group.
fn button(floor: u8, kind: CallKind) -> (u16, u8) {
    let group = u16::from((floor - 1) / 8);
    let sub = (floor - 1) % 8 + 1;
    match kind {
        CallKind::Car => (0x6104 + group, sub),
        CallKind::HallUp | CallKind::HallDown => (0x6100 + group, sub),
    }
}

/// A CiA 417-4 §4.3.1 virtual input: basic function, sub function, source lift, source panel,
/// source door, function data (bytes 0–5).
fn virtual_input(lift: u8, floor: u8, kind: CallKind, request: bool) -> u64 {
    let (basic, sub, panel) = match kind {
        // Standard car call request: the sub function is the target stop, the panel the car.
        CallKind::Car => (0x05u64, u64::from(floor), 0u64),
        CallKind::HallUp => (0x02, 0x01, u64::from(floor)),
        CallKind::HallDown => (0x02, 0x02, u64::from(floor)),
    };
    let lift_bit = 1u64 << (lift - 1);
    basic | sub << 8 | lift_bit << 16 | panel << 24 | 0x10 << 32 | u64::from(request) << 40
}

/// A call carried by a virtual input, if it requests one: (lift bits, floor, kind).
fn decode_virtual_input(value: u64) -> Option<(u8, u8, CallKind)> {
    let byte = |n: u32| (value >> (8 * n)) as u8;
    if byte(5) & 0x03 != 0x01 {
        return None;
    }
    let call = match byte(0) {
        0x02..=0x04 if byte(1) & 0x01 != 0 => (byte(3), CallKind::HallUp),
        0x02..=0x04 if byte(1) & 0x02 != 0 => (byte(3), CallKind::HallDown),
        0x05..=0x07 => (byte(1), CallKind::Car),
        _ => return None,
    };
    Some((byte(2), call.0, call.1))
}

enum Input {
    Call(u8, u8, CallKind),
    Inject(u8, u8),
    Mapped6010,
    Press(u8, CallKind, u8),
}

/// A writable object whose writes become simulator inputs: `parse` checks the value (its error
/// refuses the write with that abort code) and says what it means.
struct InputHook<F> {
    tx: mpsc::UnboundedSender<Input>,
    parse: F,
}

impl<F: Fn(&[u8]) -> Result<Input, AbortCode> + Send + Sync> VariableHook for InputHook<F> {
    fn on_write(&self, _: u16, _: u8, data: &[u8]) -> Result<(), AbortCode> {
        let input = (self.parse)(data)?;
        let _ = self.tx.send(input);
        Ok(())
    }
}

fn input_hook(
    tx: &mpsc::UnboundedSender<Input>,
    parse: impl Fn(&[u8]) -> Result<Input, AbortCode> + Send + Sync + 'static,
) -> Arc<dyn VariableHook> {
    Arc::new(InputHook {
        tx: tx.clone(),
        parse,
    })
}

/// 0x5022: a floor within the lift's floors registers a car call.
fn passenger_call(lift: u8, floors: u8, data: &[u8]) -> Result<Input, AbortCode> {
    let floor = data
        .try_into()
        .map(u32::from_le_bytes)
        .map_err(|_| AbortCode::LENGTH_MISMATCH)?;
    let floor = u8::try_from(floor)
        .ok()
        .filter(|f| *f <= floors)
        .ok_or(AbortCode::VALUE_TOO_HIGH)?;
    if floor == 0 {
        return Err(AbortCode::VALUE_TOO_LOW);
    }
    Ok(Input::Call(lift, floor, CallKind::Car))
}

/// 0x5030 bit 3: the I/O node has lost its supply (silent: no heartbeat, no answers).
pub const IO_OFFLINE: u8 = 0x08;

/// 0x5030: fault injection bits (bits 0–2 the lift's faults, bit 3 the I/O node offline, bits 4
/// and 5 fire service and inspection).
fn fault_injection(lift: u8, data: &[u8]) -> Result<Input, AbortCode> {
    let bits = *data.first().ok_or(AbortCode::LENGTH_MISMATCH)?;
    Ok(Input::Inject(lift, bits))
}

/// The I/O node's 0x2000: bits 0–7 floor, 8–11 kind (0 car, 1 hall up, 2 hall down), 12–14
/// lift − 1.
fn button_press(floors: u8, data: &[u8]) -> Result<Input, AbortCode> {
    let value = data
        .try_into()
        .map(u16::from_le_bytes)
        .map_err(|_| AbortCode::LENGTH_MISMATCH)?;
    let floor = (value & 0xFF) as u8;
    let kind = match (value >> 8) & 0x0F {
        0 => CallKind::Car,
        1 => CallKind::HallUp,
        2 => CallKind::HallDown,
        _ => return Err(AbortCode::INVALID_VALUE),
    };
    let lift = ((value >> 12) & 0x07) as u8 + 1;
    if floor == 0 || floor > floors {
        return Err(AbortCode::VALUE_TOO_HIGH);
    }
    Ok(Input::Press(floor, kind, lift))
}

fn hook(od: &mut ObjectDictionary, index: u16, h: Arc<dyn VariableHook>) {
    if let Some(object) = od.object_mut(index) {
        if let Some(var) = object.subs.remove(&0) {
            object.subs.insert(0, var.with_hook(h));
        }
    }
}

/// A running simulator.
pub struct Simulator {
    controller: Arc<LocalNode>,
    io: Option<Arc<LocalNode>>,
    inputs: mpsc::UnboundedSender<Input>,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<()>,
}

impl Simulator {
    /// Start the controller (and the I/O node) on the bus at `url`.
    pub async fn start(url: &str, config: SimConfig) -> Result<Simulator, SimError> {
        config.check()?;
        let (tx, rx) = mpsc::unbounded_channel();
        let mut od = controller_dictionary(&config)?;
        for lift in 1..=config.lifts {
            let floors = config.floors;
            let call = input_hook(&tx, move |d| passenger_call(lift, floors, d));
            hook(&mut od, manufacturer(0x5022, lift), call);
            let fault = input_hook(&tx, move |d| fault_injection(lift, d));
            hook(&mut od, manufacturer(0x5030, lift), fault);
        }
        let watcher_tx = tx.clone();
        od.watch(Arc::new(move |index, _| {
            if index == 0x6010 {
                let _ = watcher_tx.send(Input::Mapped6010);
            }
        }));
        let controller = Arc::new(LocalNode::start(
            Bus::open(url).await?,
            od,
            config.controller_config(),
        ));
        let io = match config.io_node {
            Some(id) => {
                let mut od = io_dictionary(&config)?;
                let floors = config.floors;
                hook(
                    &mut od,
                    0x2000,
                    input_hook(&tx, move |d| button_press(floors, d)),
                );
                let node = LocalNode::start(Bus::open(url).await?, od, config.io_config(id));
                for setup in io_pdos(id) {
                    node.configure_pdo(&setup).map_err(SimError::Pdo)?;
                }
                Some(Arc::new(node))
            }
            None => None,
        };
        for setup in controller_pdos(&config) {
            controller.configure_pdo(&setup).map_err(SimError::Pdo)?;
        }
        if config.autostart {
            // Self-starting devices; the simulator is ready once both are operational, so a
            // button pressed right away is not lost to a controller still pre-operational.
            if let Some(io) = &io {
                io.wait_for_state(NmtState::Operational).await;
            }
            controller.wait_for_state(NmtState::Operational).await;
        }
        let mut runner = Runner::new(config, controller.clone(), io.clone());
        let (stop, stop_rx) = oneshot::channel();
        let task = tokio::spawn(async move { runner.run(rx, stop_rx).await });
        Ok(Simulator {
            controller,
            io,
            inputs: tx,
            stop: Some(stop),
            task,
        })
    }

    /// The lift controller node.
    pub fn controller(&self) -> &LocalNode {
        &self.controller
    }

    /// The I/O node, if simulated.
    pub fn io(&self) -> Option<&LocalNode> {
        self.io.as_deref()
    }

    /// Press a button of the I/O node (or, without one, call the lift directly).
    pub fn press(&self, lift: u8, floor: u8, kind: CallKind) {
        let _ = self.inputs.send(Input::Press(floor, kind, lift));
    }

    /// Set `lift`'s faults and special operations (the 0x5030 bits) as a switch on site does:
    /// what a write of 0x5030 on the bus does, without the bus.
    pub fn set_switches(&self, lift: u8, bits: u8) {
        let _ = self
            .controller
            .set_value(manufacturer(0x5030, lift), 0, &Value::Uint(bits.into()));
        let _ = self.inputs.send(Input::Inject(lift, bits));
    }

    /// Stop the lifts, store the counters and stop both nodes.
    pub async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let _ = (&mut self.task).await;
        drop(self.inputs);
        if let Some(io) = self.io.take().and_then(|n| Arc::try_unwrap(n).ok()) {
            io.stop().await;
        }
        if let Ok(node) = Arc::try_unwrap(self.controller) {
            node.stop().await;
        }
    }
}

/// 6010h travels from the I/O node's TPDO1 to the controller's RPDO1.
fn io_link(io_node: u8) -> PdoSetup {
    PdoSetup {
        transmit: true,
        number: 1,
        cob_id: 0x180 + u32::from(io_node),
        objects: vec![(0x6010, 0)],
        transmission_type: 255,
        inhibit_100us: 0,
        event_ms: 0,
    }
}

/// The PDOs the I/O node sets up at boot: its button TPDO.
fn io_pdos(io_node: u8) -> Vec<PdoSetup> {
    vec![io_link(io_node)]
}

/// The PDOs the controller sets up at boot — what a running simulator maps and what its
/// exported EDS gives as default values, so that a tool reading the file decodes its PDOs. The
/// I/O node's buttons on RPDO1 (with an I/O node); TPDOs per lift: (1) position, speed,
/// acceleration; (2) door status, door position, light barrier, floor, state; (3) trip counter,
/// load, load signal. Lift 1 uses the pre-defined COB-IDs (180h/280h/380h + node-ID); lifts 2–8
/// use 680h + 3 × (lift − 2) + k, a range CiA 301 leaves free (one multi-lift simulator per
/// bus).
fn controller_pdos(config: &SimConfig) -> Vec<PdoSetup> {
    let mut setups: Vec<PdoSetup> = config
        .io_node
        .map(|id| PdoSetup {
            transmit: false,
            ..io_link(id)
        })
        .into_iter()
        .collect();
    for lift in 1..=config.lifts {
        let p = |index| profile(index, lift);
        let m = |index| manufacturer(index, lift);
        let layouts = [
            (
                vec![(p(0x6383), 1), (p(0x6390), 1), (p(0x6391), 1)],
                1000,
                1000,
            ),
            (
                vec![
                    (p(0x6301), 1),
                    (p(0x6302), 1),
                    (p(0x6310), 1),
                    (m(0x5023), 0),
                    (m(0x5024), 0),
                ],
                500,
                1000,
            ),
            (
                vec![(p(0x6520), 1), (p(0x6480), 1), (p(0x6482), 1)],
                0,
                5000,
            ),
        ];
        for (k, (objects, inhibit_100us, event_ms)) in layouts.into_iter().enumerate() {
            let k16 = k as u16;
            setups.push(PdoSetup {
                transmit: true,
                number: 3 * (u16::from(lift) - 1) + k16 + 1,
                cob_id: lift_tpdo_cob_id(config.node_id, lift, k16),
                objects,
                transmission_type: 255,
                inhibit_100us,
                event_ms,
            });
        }
    }
    setups
}

/// The COB-ID of TPDO `k` (0–2) of lift `lift`: lift 1 in the pre-defined connection set, lifts
/// 2–8 at 680h + 3 × (lift − 2) + k.
fn lift_tpdo_cob_id(node_id: u8, lift: u8, k: u16) -> u32 {
    if lift == 1 {
        0x180 + 0x100 * u32::from(k) + u32::from(node_id)
    } else {
        0x680 + 3 * (u32::from(lift) - 2) + u32::from(k)
    }
}

/// The task that moves the lifts.
struct Runner {
    config: SimConfig,
    controller: Arc<LocalNode>,
    io: Option<Arc<LocalNode>>,
    lifts: Vec<Lift>,
    published: HashMap<(u16, u8), Value>,
    active_codes: BTreeMap<u16, usize>,
    counters_dirty: bool,
    last_store: Instant,
    next_passenger: f64,
    sim_s: f64,
    rng: u64,
    /// The I/O node has its supply (0x5030 bit 3 clear).
    io_powered: bool,
}

impl Runner {
    fn new(config: SimConfig, controller: Arc<LocalNode>, io: Option<Arc<LocalNode>>) -> Runner {
        let io_powered = config.faults & IO_OFFLINE == 0;
        let mut lifts = Vec::new();
        for lift in 1..=config.lifts {
            let counters = read_counters(&controller, lift);
            let mut model = Lift::new(
                Params::with_floors(config.floors),
                counters,
                config.seed.wrapping_add(u64::from(lift)),
            );
            model.set_door_wear(config.door_wear_percent_per_h);
            if lift == 1 {
                model.inject(config.faults);
                let _ = controller.set_value(
                    manufacturer(0x5030, 1),
                    0,
                    &Value::Uint(config.faults.into()),
                );
                if let Some(io) = &io {
                    io.set_powered(io_powered);
                }
            }
            lifts.push(model);
        }
        let rng = config.seed | 1;
        Runner {
            config,
            controller,
            io,
            lifts,
            published: HashMap::new(),
            active_codes: BTreeMap::new(),
            counters_dirty: false,
            last_store: Instant::now(),
            next_passenger: 0.0,
            sim_s: 0.0,
            rng,
            io_powered,
        }
    }

    async fn run(
        &mut self,
        mut inputs: mpsc::UnboundedReceiver<Input>,
        mut stop: oneshot::Receiver<()>,
    ) {
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut last = Instant::now();
        self.schedule_passenger();
        loop {
            tokio::select! {
                _ = &mut stop => break,
                Some(input) = inputs.recv() => self.input(input),
                _ = tick.tick() => {
                    let now = Instant::now();
                    let dt = now.duration_since(last).mul_f64(self.config.speed);
                    last = now;
                    self.tick(dt);
                }
            }
        }
        self.store_counters();
    }

    fn input(&mut self, input: Input) {
        match input {
            Input::Call(lift, floor, kind) => self.call(lift, floor, kind),
            Input::Inject(lift, bits) => {
                if let Some(l) = self.lifts.get_mut(usize::from(lift) - 1) {
                    l.inject(bits);
                }
                if lift == 1 {
                    self.power_io(bits & IO_OFFLINE == 0);
                }
            }
            Input::Mapped6010 => {
                let value = self.controller.value(0x6010, 0);
                if let Ok(Value::Uint(v)) = value {
                    if let Some((lifts, floor, kind)) = decode_virtual_input(v) {
                        for lift in 1..=self.config.lifts {
                            if lifts & (1 << (lift - 1)) != 0 {
                                self.call(lift, floor, kind);
                            }
                        }
                    }
                }
            }
            Input::Press(floor, kind, lift) => self.press(lift, floor, kind),
        }
    }

    /// The I/O node loses or regains its supply (0x5030 bit 3). Back on it boots, and — a
    /// self-starting device, as after every boot — goes operational by itself.
    fn power_io(&mut self, on: bool) {
        let Some(io) = self.io.clone() else {
            return;
        };
        if on == self.io_powered {
            return;
        }
        self.io_powered = on;
        tracing::warn!(node = io.node_id(), on, "I/O node supply");
        // Back on it boots, and (self-starting) goes operational by itself.
        io.set_powered(on);
    }

    fn call(&mut self, lift: u8, floor: u8, kind: CallKind) {
        if let Some(l) = self.lifts.get_mut(usize::from(lift.max(1)) - 1) {
            if let Err(e) = l.call(floor, kind) {
                tracing::info!(lift, error = %e, "call refused");
            }
        }
    }

    /// A button on the I/O node: its input group entry and 6010h change, and 6010h travels to
    /// the controller by PDO. Without an I/O node the call goes straight to the lift.
    fn press(&mut self, lift: u8, floor: u8, kind: CallKind) {
        let Some(io) = &self.io else {
            self.call(lift, floor, kind);
            return;
        };
        let value = Value::Uint(virtual_input(lift, floor, kind, true));
        let (index, sub) = button(floor, kind);
        let _ = io.set_value(index, sub, &value);
        // Every set of 6010h (even to the same value) makes its event-driven TPDO pending.
        let _ = io.set_value(0x6010, 0, &value);
    }

    fn random(&mut self) -> u64 {
        self.rng ^= self.rng << 13;
        self.rng ^= self.rng >> 7;
        self.rng ^= self.rng << 17;
        self.rng
    }

    fn schedule_passenger(&mut self) {
        if let Some(every) = self.config.passengers {
            // Between half and one and a half times the mean interval.
            let jitter = 0.5 + (self.random() % 1000) as f64 / 1000.0;
            self.next_passenger = self.sim_s + every.as_secs_f64() * jitter;
        }
    }

    fn passenger(&mut self) {
        let floors = u64::from(self.config.floors);
        let lift = (self.random() % u64::from(self.config.lifts)) as u8 + 1;
        let floor = (self.random() % floors) as u8 + 1;
        let kind = match self.random() % 3 {
            0 => CallKind::Car,
            _ if floor == 1 => CallKind::HallUp,
            _ if u64::from(floor) == floors => CallKind::HallDown,
            1 => CallKind::HallUp,
            _ => CallKind::HallDown,
        };
        self.press(lift, floor, kind);
    }

    fn tick(&mut self, dt: Duration) {
        self.sim_s += dt.as_secs_f64();
        if self.config.passengers.is_some() && self.sim_s >= self.next_passenger {
            self.passenger();
            self.schedule_passenger();
        }
        for i in 0..self.lifts.len() {
            let lift = i as u8 + 1;
            let params = read_params(&self.controller, lift, self.config.floors);
            if let Some(params) = params.filter(|p| p != self.lifts[i].params()) {
                self.lifts[i].set_params(params);
            }
            self.lifts[i].advance(dt);
            while let Some(event) = self.lifts[i].poll_event() {
                self.event(lift, event);
            }
        }
        self.publish();
        if self.counters_dirty && self.last_store.elapsed() >= Duration::from_secs(2) {
            self.store_counters();
        }
    }

    fn event(&mut self, lift: u8, event: Event) {
        tracing::debug!(lift, ?event, "lift");
        match event {
            Event::FaultRaised(fault) => {
                tracing::warn!(
                    lift,
                    ?fault,
                    code = format!("{:04X}h", fault.emcy_code()),
                    "fault"
                );
                let count = self.active_codes.entry(fault.emcy_code()).or_insert(0);
                *count += 1;
                // CiA 417-1 reserves the manufacturer-specific error field.
                self.controller.set_error(fault.emcy_code(), [0; 5]);
            }
            Event::FaultCleared(fault) => {
                tracing::info!(lift, ?fault, "fault cleared");
                let code = fault.emcy_code();
                let left = self.active_codes.get_mut(&code).map(|c| {
                    *c = c.saturating_sub(1);
                    *c
                });
                if left == Some(0) {
                    self.active_codes.remove(&code);
                    self.controller.clear_error(code);
                }
            }
            Event::Arrived { .. } | Event::DoorsClosed => {}
            Event::Departed { .. } | Event::DoorsOpen => return,
        }
        self.counters_dirty = true;
    }

    /// Write the lifts' state into the dictionary, only what changed (each write may send a
    /// PDO).
    fn publish(&mut self) {
        let mut values: Vec<(u16, u8, Value)> = Vec::new();
        for (i, l) in self.lifts.iter().enumerate() {
            let lift = i as u8 + 1;
            let p = |index| profile(index, lift);
            let m = |index| manufacturer(index, lift);
            let c = l.counters();
            let hours = (c.operating_s / 3600.0) as u64;
            let load_signal = load_signal(l);
            let standing = l.speed_mm_s() == 0.0;
            let fault = l.faults().any(|f| f == Fault::DriveFault);
            let drive_status = 0x0027 | u64::from(fault) << 3 | u64::from(standing) << 10;
            values.extend([
                (
                    p(0x6383),
                    1,
                    Value::Uint(l.position_mm().max(0.0).round() as u64),
                ),
                (p(0x6390), 1, Value::Int(clamp_i16(l.speed_mm_s()))),
                (p(0x6391), 1, Value::Int(clamp_i16(l.acceleration_mm_s2()))),
                (p(0x6301), 1, Value::Uint(l.door_statusword().into())),
                (
                    p(0x6302),
                    1,
                    Value::Uint(l.door_position_mm().round() as u64),
                ),
                (p(0x6310), 1, Value::Uint(l.light_barrier().into())),
                (p(0x6480), 1, Value::Uint(l.load_kg().into())),
                (p(0x6482), 1, Value::Uint(load_signal.into())),
                (p(0x6520), 1, Value::Uint(c.trips.into())),
                (p(0x6520), 2, Value::Uint(hours)),
                (p(0x63C8), 0, Value::Uint(hours)),
                (p(0x6401), 0, Value::Uint(drive_status)),
                (p(0x6432), 0, Value::Int(l.speed_mm_s().round() as i64)),
                (p(0x6433), 0, Value::Int(l.speed_mm_s().round() as i64)),
                (m(0x5023), 0, Value::Uint(l.floor().into())),
                (m(0x5024), 0, Value::Uint(l.state() as u64)),
                (m(0x4400), 1, Value::Uint(c.door_cycles.into())),
                (m(0x4400), 2, Value::Uint((c.distance_mm / 1000.0) as u64)),
                (m(0x4400), 3, Value::Uint(c.starts.into())),
                (m(0x4400), 4, Value::Uint(c.reopenings.into())),
                (
                    m(0x4402),
                    1,
                    Value::Uint(c.last_fault.map_or(0, |f| f.0).into()),
                ),
                (
                    m(0x4402),
                    2,
                    Value::Uint(c.last_fault.map_or(0, |f| f.1).into()),
                ),
                (m(0x4402), 3, Value::Bool(l.faults().next().is_some())),
                (m(0x4403), 1, Value::Uint(l.door_timing().last_ms().into())),
                (m(0x4403), 2, Value::Uint(l.door_timing().mean_ms().into())),
            ]);
            for (k, n) in c.faults.iter().enumerate() {
                values.push((m(0x4401), k as u8 + 1, Value::Uint((*n).into())));
            }
        }
        for (index, sub, value) in values {
            if self.published.get(&(index, sub)) == Some(&value) {
                continue;
            }
            if self.controller.set_value(index, sub, &value).is_ok() {
                self.published.insert((index, sub), value);
            }
        }
    }

    fn store_counters(&mut self) {
        self.last_store = Instant::now();
        self.counters_dirty = false;
        let Some(dir) = &self.config.state_dir else {
            return;
        };
        let path = dir.join(format!("node{}.params", self.config.node_id));
        let od = self
            .controller
            .od()
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if let Err(e) = canopen::storage::store_counters(&od, &path) {
            tracing::error!(error = %e, "counters not stored");
        }
    }
}

fn clamp_i16(v: f64) -> i64 {
    v.round().clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i64
}

/// 6482h sub 1: bit 0 zero load, 1 normal, 2 full, 3 overload (limits 6483h).
fn load_signal(l: &Lift) -> u8 {
    let load = l.load_kg();
    let p = l.params();
    if load > p.overload_kg {
        0b1000
    } else if load >= p.full_kg {
        0b0100
    } else if load <= 20 {
        0b0001
    } else {
        0b0010
    }
}

fn uint(node: &LocalNode, index: u16, sub: u8) -> Option<u64> {
    match node.value(index, sub) {
        Ok(Value::Uint(v)) => Some(v),
        _ => None,
    }
}

fn read_counters(node: &LocalNode, lift: u8) -> Counters {
    let p = |index| profile(index, lift);
    let m = |index| manufacturer(index, lift);
    let u32_of = |index, sub| uint(node, index, sub).map_or(0, |v| v as u32);
    let code = uint(node, m(0x4402), 1).unwrap_or(0);
    Counters {
        trips: u32_of(p(0x6520), 1),
        operating_s: f64::from(u32_of(p(0x6520), 2)) * 3600.0,
        door_cycles: u32_of(m(0x4400), 1),
        distance_mm: f64::from(u32_of(m(0x4400), 2)) * 1000.0,
        starts: u32_of(m(0x4400), 3),
        reopenings: u32_of(m(0x4400), 4),
        faults: [1, 2, 3, 4].map(|sub| u32_of(m(0x4401), sub)),
        last_fault: (code != 0).then(|| (code as u16, u32_of(m(0x4402), 2))),
    }
}

/// The lift's settings from the dictionary (None while a value is unreadable).
fn read_params(node: &LocalNode, lift: u8, floors: u8) -> Option<Params> {
    let od = node.od().lock().unwrap_or_else(PoisonError::into_inner);
    let u = |index: u16, sub: u8| match od.get_value(index, sub) {
        Ok(Value::Uint(v)) => Some(v as f64),
        _ => None,
    };
    let p = |index| profile(index, lift);
    let m = |index| manufacturer(index, lift);
    let mut levels = Vec::with_capacity(usize::from(floors));
    for floor in 1..=floors {
        match od.get_value(m(0x4010), floor) {
            Ok(Value::Int(v)) => levels.push(i32::try_from(v).ok()?),
            _ => return None,
        }
    }
    let parking_s = u(m(0x4114), 0)?;
    Some(Params {
        levels,
        speed: u(p(0x6423), 0)?,
        acceleration: u(p(0x640B), 1)?,
        deceleration: u(p(0x640B), 2)?,
        jerk: u(p(0x640D), 1)?,
        quick_stop: u(p(0x640A), 0)?.max(100.0),
        door_open_s: u(m(0x4113), 0)?,
        overload_kg: u(p(0x6483), 4)? as u16,
        full_kg: u(p(0x6483), 3)? as u16,
        parking: (parking_s > 0.0).then(|| (parking_s, u(m(0x4115), 0).unwrap_or(1.0) as u8)),
    })
}

/// The EDS of the simulated `device` as [`Simulator::start`] would run it.
pub fn export_eds(config: &SimConfig, device: Device) -> Result<String, SimError> {
    config.check()?;
    let (mut od, node, product, pdos) = match device {
        Device::Controller => (
            controller_dictionary(config)?,
            config.controller_config(),
            CONTROLLER_NAME,
            controller_pdos(config),
        ),
        Device::Io => {
            let id = config.io_node.unwrap_or(12);
            (
                io_dictionary(config)?,
                config.io_config(id),
                IO_NAME,
                io_pdos(id),
            )
        }
    };
    add_communication_objects(&mut od, &node);
    // The PDOs as the device sets them up at boot are the file's defaults.
    for setup in &pdos {
        canopen::node::configure_default_pdo(&mut od, setup).map_err(SimError::Pdo)?;
    }
    if let Some(path) = node.storage.clone() {
        canopen::storage::add_storage_objects(&mut od, path);
    }
    let description = DeviceDescription {
        device_info: vec![
            ("VendorName".into(), "canlift".into()),
            ("VendorNumber".into(), format!("0x{:08X}", node.identity[0])),
            ("ProductName".into(), product.into()),
            (
                "ProductNumber".into(),
                format!("0x{:08X}", node.identity[1]),
            ),
            (
                "RevisionNumber".into(),
                format!("0x{:08X}", node.identity[2]),
            ),
            ("BaudRate_250".into(), "1".into()),
            ("SimpleBootUpSlave".into(), "1".into()),
            ("NrOfRXPDO".into(), node.pdos.0.to_string()),
            ("NrOfTXPDO".into(), node.pdos.1.to_string()),
            ("LSS_Supported".into(), "1".into()),
        ],
        od,
        ..DeviceDescription::default()
    };
    Ok(eds::export(&description, false))
}

#[cfg(test)]
mod tests;
