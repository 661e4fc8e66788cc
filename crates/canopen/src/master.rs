//! [`Master`]: the network-side API: NMT commands, SDO to any node, the heartbeat monitoring
//! table with per-node timeouts and change events, and EMCY reception.
//!
//! ```no_run
//! # async fn demo() -> Result<(), Box<dyn std::error::Error>> {
//! use std::time::Duration;
//! use canopen::master::{Master, MasterEvent};
//! use canopen::nmt::NmtCommand;
//!
//! let master = Master::open("socketcand://127.0.0.1:29536/can0", Default::default()).await?;
//! master.monitor(1, Duration::from_millis(1500)); // lift controller, heartbeat 1 s
//! master.nmt(NmtCommand::Start, 0).await?;      // all nodes operational
//! let trips: u32 = master.sdo().read(1, 0x6520, 1).await?;
//! let mut events = master.events();
//! while let Ok(event) = events.recv().await {
//!     if let MasterEvent::Emcy { node, message } = event {
//!         println!("EMCY from node {node}: {:04X}", message.code);
//!     }
//! }
//! # let _ = trips; Ok(()) }
//! ```

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use canbus::{Bus, BusError, BusSender, CanId};
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

use crate::emcy::EmcyMessage;
use crate::heartbeat::{HeartbeatConsumer, HeartbeatEvent, NodeState};
use crate::nmt::NmtCommand;
use crate::pdo::{MapEntry, PdoValues};
use crate::sdo::client::ClientConfig;
use crate::sdo::clients::SdoClients;
use crate::wake::sleep_until;

/// What the master hears.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MasterEvent {
    /// A node's heartbeat state changed, it timed out or came back.
    Heartbeat(HeartbeatEvent),
    /// Node guarding noticed something (lost, recovered, state reported).
    Guarding(crate::guarding::GuardEvent),
    /// An EMCY from a node.
    Emcy {
        /// Producer.
        node: u8,
        /// The message.
        message: EmcyMessage,
    },
}

/// Why an LSS service failed.
#[derive(Debug, thiserror::Error)]
pub enum LssError {
    /// The bus failed.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// No slave answered (none in configuration state, or none selected).
    #[error("no LSS slave answered")]
    NoResponse,
    /// The slave refused with this CiA 305 error code (1: out of range / not supported).
    #[error("LSS slave refused with error code {0}")]
    Refused(u8),
}

/// How long an LSS slave has to answer, unless [`Master::set_lss_timeout`] says otherwise.
const LSS_TIMEOUT: Duration = Duration::from_millis(200);
/// How long each Fastscan step listens. Every step waits this long: several slaves may answer
/// the same step (on a real bus their identical frames merge; on a virtual one they do not), and
/// a late duplicate must not be taken for the answer to the next step.
const FASTSCAN_TIMEOUT: Duration = Duration::from_millis(20);

/// The master of a CANopen network.
pub struct Master {
    sender: BusSender,
    /// Responses on 0x7E4 go here while an LSS service waits for one.
    lss_route: Arc<Mutex<Option<tokio::sync::mpsc::UnboundedSender<canbus::Frame>>>>,
    lss_turn: tokio::sync::Mutex<()>,
    /// How long an LSS slave has to answer a confirmed service.
    lss_timeout: std::sync::atomic::AtomicU64,
    sdo: SdoClients,
    table: Arc<Mutex<HeartbeatConsumer>>,
    guarding: Arc<Mutex<crate::guarding::GuardingMaster>>,
    wake: Arc<tokio::sync::Notify>,
    events: broadcast::Sender<MasterEvent>,
    /// PDOs of other nodes the application consumes, by COB-ID.
    rpdos: Arc<Mutex<HashMap<CanId, RpdoRoute>>>,
    task: JoinHandle<()>,
}

/// One consumed PDO: the mapping it is read with and who gets the values.
struct RpdoRoute {
    mapping: Vec<MapEntry>,
    callback: Box<dyn FnMut(&PdoValues) + Send>,
}

impl Master {
    /// Open the bus at `url` (two endpoints: one for SDO, one for monitoring).
    pub async fn open(url: &str, config: ClientConfig) -> Result<Master, BusError> {
        let sdo = SdoClients::new(Bus::open(url).await?, config);
        let (sender, mut receiver) = Bus::open(url).await?.split();
        let table = Arc::new(Mutex::new(HeartbeatConsumer::new()));
        let guarding = Arc::new(Mutex::new(crate::guarding::GuardingMaster::new()));
        let wake = Arc::new(tokio::sync::Notify::new());
        let (events, _) = broadcast::channel(1024);
        let lss_route: Arc<Mutex<Option<tokio::sync::mpsc::UnboundedSender<canbus::Frame>>>> =
            Arc::default();
        let rpdos: Arc<Mutex<HashMap<CanId, RpdoRoute>>> = Arc::default();
        let task = {
            let rpdos = rpdos.clone();
            let (table, wake, events) = (table.clone(), wake.clone(), events.clone());
            let lss = lss_route.clone();
            let (guarding, guard_sender) = (guarding.clone(), sender.clone());
            tokio::spawn(async move {
                let mut heartbeat = Vec::new();
                let (mut guard_frames, mut guard_events) = (Vec::new(), Vec::new());
                loop {
                    let deadline = [
                        table
                            .lock()
                            .unwrap_or_else(PoisonError::into_inner)
                            .poll_timeout(),
                        guarding
                            .lock()
                            .unwrap_or_else(PoisonError::into_inner)
                            .poll_timeout(),
                    ]
                    .into_iter()
                    .flatten()
                    .min();
                    let frame = tokio::select! {
                        f = receiver.recv_frame() => match f {
                            Some(f) => Some(f),
                            None => return,
                        },
                        _ = sleep_until(deadline) => None,
                        // A new monitoring entry may move the earliest deadline.
                        _ = wake.notified() => continue,
                    };
                    let now = Instant::now();
                    if let Some(f) = frame.as_ref().filter(|f| !f.is_remote()) {
                        let mut routes = rpdos.lock().unwrap_or_else(PoisonError::into_inner);
                        if let Some(route) = routes.get_mut(&f.id()) {
                            match PdoValues::split(f.id(), &route.mapping, f.data()) {
                                Some(values) => (route.callback)(&values),
                                None => {
                                    tracing::debug!(id = %f.id(), len = f.data().len(), "PDO shorter than its mapping")
                                }
                            }
                            continue;
                        }
                    }
                    if let Some(f) = frame.as_ref().filter(|f| f.id() == crate::lss::SLAVE_ID) {
                        if let Some(route) =
                            lss.lock().unwrap_or_else(PoisonError::into_inner).as_ref()
                        {
                            let _ = route.send(*f);
                        }
                        continue;
                    }
                    {
                        let mut table = table.lock().unwrap_or_else(PoisonError::into_inner);
                        let mut guard = guarding.lock().unwrap_or_else(PoisonError::into_inner);
                        match &frame {
                            Some(f) => {
                                table.handle(f, now, &mut heartbeat);
                                guard.handle(f, &mut guard_events);
                            }
                            None => {
                                table.handle_timeout(now, &mut heartbeat);
                                guard.handle_timeout(now, &mut guard_frames, &mut guard_events);
                            }
                        }
                    }
                    for f in guard_frames.drain(..) {
                        if let Err(e) = guard_sender.send(f).await {
                            tracing::warn!(error = %e, "guard request not sent");
                        }
                    }
                    for e in guard_events.drain(..) {
                        let _ = events.send(MasterEvent::Guarding(e));
                    }
                    for e in heartbeat.drain(..) {
                        let _ = events.send(MasterEvent::Heartbeat(e));
                    }
                    if let Some((node, message)) = frame.as_ref().and_then(EmcyMessage::from_frame)
                    {
                        let _ = events.send(MasterEvent::Emcy { node, message });
                    }
                }
            })
        };
        Ok(Master {
            sender,
            guarding,
            lss_route,
            lss_turn: tokio::sync::Mutex::new(()),
            lss_timeout: std::sync::atomic::AtomicU64::new(LSS_TIMEOUT.as_micros() as u64),
            sdo,
            table,
            wake,
            events,
            rpdos,
            task,
        })
    }

    /// Send an NMT command to `node` (0 = all nodes).
    pub async fn nmt(&self, command: NmtCommand, node: u8) -> Result<(), BusError> {
        self.sender.send(command.frame(node)).await?;
        self.sender.flush().await
    }

    /// SDO reads and writes to any node.
    pub fn sdo(&self) -> &SdoClients {
        &self.sdo
    }

    /// Read a PDO's communication and mapping parameters from `node` (`None`: it has no such
    /// PDO).
    pub async fn read_remote_pdo(
        &self,
        node: u8,
        id: crate::pdo::remote::PdoId,
    ) -> Result<Option<crate::pdo::remote::RemotePdo>, crate::sdo::clients::ClientError> {
        crate::pdo::remote::read(&self.sdo, node, id).await
    }

    /// Consume the PDO on `cob_id` read with `mapping`: `callback` gets each one's values (in
    /// the master's receive task: keep it short, hand work elsewhere). A second call for the
    /// same COB-ID replaces the first.
    pub fn on_rpdo(
        &self,
        cob_id: CanId,
        mapping: Vec<MapEntry>,
        callback: impl FnMut(&PdoValues) + Send + 'static,
    ) {
        self.rpdos
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(
                cob_id,
                RpdoRoute {
                    mapping,
                    callback: Box::new(callback),
                },
            );
    }

    /// Stop consuming the PDO on `cob_id`.
    pub fn off_rpdo(&self, cob_id: CanId) {
        self.rpdos
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(&cob_id);
    }

    /// Consume TPDO `number` of `node` with the COB-ID and mapping the node has (read by SDO);
    /// returns what was read.
    pub async fn on_remote_tpdo(
        &self,
        node: u8,
        number: u16,
        callback: impl FnMut(&PdoValues) + Send + 'static,
    ) -> Result<crate::pdo::remote::RemotePdo, crate::pdo::remote::ConsumeError> {
        use crate::pdo::remote::{ConsumeError, Direction, PdoId};
        let pdo = PdoId {
            direction: Direction::Transmit,
            number,
        };
        let found = self
            .read_remote_pdo(node, pdo)
            .await?
            .ok_or(ConsumeError::Missing { node, pdo })?;
        let cob_id = crate::cob::id_from_parameter(found.cob_id & 0x3FFF_FFFF)
            .filter(|_| found.enabled())
            .ok_or(ConsumeError::Off {
                node,
                pdo,
                cob_id: found.cob_id,
            })?;
        self.on_rpdo(cob_id, found.mapping.clone(), callback);
        Ok(found)
    }

    /// Configure a PDO of `node` with the CiA 301 §7.3.5 mapping procedure.
    pub async fn configure_remote_pdo(
        &self,
        node: u8,
        pdo: &crate::pdo::remote::RemotePdo,
    ) -> Result<(), crate::pdo::remote::ConfigureError> {
        crate::pdo::remote::configure(&self.sdo, node, pdo).await
    }

    /// Monitor `node`'s heartbeat: it counts as offline when none arrives within `timeout`
    /// (zero: track its state without a timeout).
    pub fn monitor(&self, node: u8, timeout: Duration) {
        self.table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .monitor(node, Some(timeout));
        self.wake.notify_one();
    }

    /// Guard `node` with remote frames every `guard_time`; lost after `factor` unanswered
    /// requests (`factor` 0 stops guarding it). Needs remote frames: SocketCAN or `mem://`.
    pub fn guard(&self, node: u8, guard_time: Duration, factor: u8) {
        self.guarding
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .guard(node, guard_time, factor, Instant::now());
        self.wake.notify_one();
    }

    /// The state of `node` as last heard.
    pub fn node_state(&self, node: u8) -> NodeState {
        self.table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .state(node)
    }

    /// Every node heard or monitored, with its state.
    pub fn nodes(&self) -> Vec<(u8, NodeState)> {
        self.table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .table()
            .collect()
    }

    /// Send an LSS request and wait up to `timeout` for a response with command `expect`.
    async fn lss_request(
        &self,
        request: canbus::Frame,
        expect: Option<u8>,
        timeout: Duration,
    ) -> Result<Option<canbus::Frame>, BusError> {
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
        *self
            .lss_route
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(tx);
        let sent = async {
            self.sender.send(request).await?;
            self.sender.flush().await
        };
        let result = match sent.await {
            Err(e) => Err(e),
            Ok(()) => match expect {
                None => Ok(None),
                Some(cs) => Ok(tokio::time::timeout(timeout, async {
                    while let Some(f) = rx.recv().await {
                        if f.data().first() == Some(&cs) {
                            return Some(f);
                        }
                    }
                    None
                })
                .await
                .ok()
                .flatten()),
            },
        };
        *self
            .lss_route
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = None;
        result
    }

    /// Send a Fastscan step; whether any slave answered within the whole step time.
    async fn fastscan_step(
        &self,
        request: canbus::Frame,
        step: Duration,
    ) -> Result<bool, BusError> {
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
        *self
            .lss_route
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(tx);
        let sent = async {
            self.sender.send(request).await?;
            self.sender.flush().await
        };
        let result = sent.await;
        tokio::time::sleep(step).await;
        *self
            .lss_route
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = None;
        result?;
        let mut answered = false;
        while let Ok(f) = rx.try_recv() {
            answered |= f.data().first() == Some(&crate::lss::cs::IDENTIFY_RESPONSE);
        }
        Ok(answered)
    }

    async fn lss_confirmed(
        &self,
        command: u8,
        payload: [u8; 7],
    ) -> Result<canbus::Frame, LssError> {
        let _turn = self.lss_turn.lock().await;
        self.lss_request(
            crate::lss::request(command, payload),
            Some(command),
            self.lss_timeout(),
        )
        .await?
        .ok_or(LssError::NoResponse)
    }

    async fn lss_checked(&self, command: u8, payload: [u8; 7]) -> Result<(), LssError> {
        let f = self.lss_confirmed(command, payload).await?;
        match f.data()[1] {
            0 => Ok(()),
            code => Err(LssError::Refused(code)),
        }
    }

    /// How long LSS slaves have to answer (default 200 ms): longer for a slow gateway between
    /// the master and the bus, or a loaded machine.
    pub fn set_lss_timeout(&self, timeout: Duration) {
        let micros = u64::try_from(timeout.as_micros()).unwrap_or(u64::MAX);
        self.lss_timeout
            .store(micros, std::sync::atomic::Ordering::Relaxed);
    }

    fn lss_timeout(&self) -> Duration {
        Duration::from_micros(self.lss_timeout.load(std::sync::atomic::Ordering::Relaxed))
    }

    /// Switch every LSS slave to configuration (`true`) or back to waiting.
    pub async fn lss_switch_global(&self, configuration: bool) -> Result<(), BusError> {
        let _turn = self.lss_turn.lock().await;
        let payload = [u8::from(configuration), 0, 0, 0, 0, 0, 0];
        self.lss_request(
            crate::lss::request(crate::lss::cs::SWITCH_GLOBAL, payload),
            None,
            self.lss_timeout(),
        )
        .await
        .map(drop)
    }

    /// Switch the slave with this LSS address (vendor, product, revision, serial) to
    /// configuration; `false` when none answered.
    pub async fn lss_switch_selective(&self, address: [u32; 4]) -> Result<bool, BusError> {
        use crate::lss::cs;
        let _turn = self.lss_turn.lock().await;
        for (i, part) in address.iter().enumerate() {
            let b = part.to_le_bytes();
            let request = crate::lss::request(
                cs::SWITCH_SELECTIVE_VENDOR + i as u8,
                [b[0], b[1], b[2], b[3], 0, 0, 0],
            );
            let expect = (i == 3).then_some(cs::SWITCH_SELECTIVE_RESPONSE);
            if let Some(reply) = self
                .lss_request(request, expect, self.lss_timeout())
                .await?
            {
                return Ok(reply.data()[0] == cs::SWITCH_SELECTIVE_RESPONSE);
            }
        }
        Ok(false)
    }

    /// Give the slave in configuration state a node-ID (1–127, or 0xFF for none).
    pub async fn lss_configure_node_id(&self, node_id: u8) -> Result<(), LssError> {
        self.lss_checked(
            crate::lss::cs::CONFIGURE_NODE_ID,
            [node_id, 0, 0, 0, 0, 0, 0],
        )
        .await
    }

    /// Set the bit timing (index into the CiA 305 table) of the slave in configuration.
    pub async fn lss_configure_bit_timing(&self, index: u8) -> Result<(), LssError> {
        self.lss_checked(
            crate::lss::cs::CONFIGURE_BIT_TIMING,
            [0, index, 0, 0, 0, 0, 0],
        )
        .await
    }

    /// Tell every slave in configuration to switch to its new bit timing after `delay_ms`.
    pub async fn lss_activate_bit_timing(&self, delay_ms: u16) -> Result<(), BusError> {
        let _turn = self.lss_turn.lock().await;
        let d = delay_ms.to_le_bytes();
        let request = crate::lss::request(
            crate::lss::cs::ACTIVATE_BIT_TIMING,
            [d[0], d[1], 0, 0, 0, 0, 0],
        );
        self.lss_request(request, None, self.lss_timeout())
            .await
            .map(drop)
    }

    /// Make the slave in configuration store its node-ID and bit timing.
    pub async fn lss_store(&self) -> Result<(), LssError> {
        self.lss_checked(crate::lss::cs::STORE, [0; 7]).await
    }

    /// The active node-ID of the slave in configuration.
    pub async fn lss_inquire_node_id(&self) -> Result<u8, LssError> {
        Ok(self
            .lss_confirmed(crate::lss::cs::INQUIRE_NODE_ID, [0; 7])
            .await?
            .data()[1])
    }

    /// The LSS address (vendor, product, revision, serial) of the slave in configuration.
    pub async fn lss_inquire_address(&self) -> Result<[u32; 4], LssError> {
        let mut address = [0u32; 4];
        for (i, part) in address.iter_mut().enumerate() {
            let f = self
                .lss_confirmed(crate::lss::cs::INQUIRE_VENDOR + i as u8, [0; 7])
                .await?;
            let d = f.data();
            *part = u32::from_le_bytes([d[1], d[2], d[3], d[4]]);
        }
        Ok(address)
    }

    /// Fastscan (CiA 305 §6.7): find one slave without a node-ID, bit by bit, and leave it in
    /// configuration state. `None` when no such slave answers.
    pub async fn lss_fastscan(&self) -> Result<Option<[u32; 4]>, BusError> {
        self.lss_fastscan_with_step(FASTSCAN_TIMEOUT).await
    }

    /// [`Self::lss_fastscan`] with another step time: longer for slow slaves or a loaded
    /// machine (a scan takes 133 steps).
    pub async fn lss_fastscan_with_step(
        &self,
        step: Duration,
    ) -> Result<Option<[u32; 4]>, BusError> {
        let all = crate::lss::FastscanMaster::new([crate::lss::FastscanPart::Scan; 4])
            .unwrap_or_else(|_| unreachable!("nothing is skipped"));
        self.lss_fastscan_parts(all, step).await
    }

    /// Fastscan with parts matched or skipped (CiA 309-3 `lss_allnodes` scan types): only
    /// slaves of a known vendor or product, say, and fewer steps.
    pub async fn lss_fastscan_parts(
        &self,
        mut scan: crate::lss::FastscanMaster,
        step: Duration,
    ) -> Result<Option<[u32; 4]>, BusError> {
        use crate::lss::FastscanProgress;
        let _turn = self.lss_turn.lock().await;
        loop {
            let answered = self.fastscan_step(scan.request(), step).await?;
            match scan.answered(answered) {
                FastscanProgress::Continue => {}
                FastscanProgress::Found(address) => return Ok(Some(address)),
                FastscanProgress::NotFound => return Ok(None),
            }
        }
    }

    /// Subscribe to heartbeat and EMCY events.
    pub fn events(&self) -> broadcast::Receiver<MasterEvent> {
        self.events.subscribe()
    }
}

impl Drop for Master {
    fn drop(&mut self) {
        self.task.abort();
    }
}
