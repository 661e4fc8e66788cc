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

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use canbus::{Bus, BusError, BusSender};
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

use crate::driver::{sleep_until, SdoClients};
use crate::emcy::EmcyMessage;
use crate::heartbeat::{HeartbeatConsumer, HeartbeatEvent, NodeState};
use crate::nmt::NmtCommand;
use crate::sdo::client::ClientConfig;

/// What the master hears.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MasterEvent {
    /// A node's heartbeat state changed, it timed out or came back.
    Heartbeat(HeartbeatEvent),
    /// An EMCY from a node.
    Emcy {
        /// Producer.
        node: u8,
        /// The message.
        message: EmcyMessage,
    },
}

/// The master of a CANopen network.
pub struct Master {
    sender: BusSender,
    sdo: SdoClients,
    table: Arc<Mutex<HeartbeatConsumer>>,
    wake: Arc<tokio::sync::Notify>,
    events: broadcast::Sender<MasterEvent>,
    task: JoinHandle<()>,
}

impl Master {
    /// Open the bus at `url` (two endpoints: one for SDO, one for monitoring).
    pub async fn open(url: &str, config: ClientConfig) -> Result<Master, BusError> {
        let sdo = SdoClients::new(Bus::open(url).await?, config);
        let (sender, mut receiver) = Bus::open(url).await?.split();
        let table = Arc::new(Mutex::new(HeartbeatConsumer::new()));
        let wake = Arc::new(tokio::sync::Notify::new());
        let (events, _) = broadcast::channel(1024);
        let task = {
            let (table, wake, events) = (table.clone(), wake.clone(), events.clone());
            tokio::spawn(async move {
                let mut heartbeat = Vec::new();
                loop {
                    let deadline = table
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .poll_timeout();
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
                    {
                        let mut table = table.lock().unwrap_or_else(PoisonError::into_inner);
                        match &frame {
                            Some(f) => table.handle(f, now, &mut heartbeat),
                            None => table.handle_timeout(now, &mut heartbeat),
                        }
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
            sdo,
            table,
            wake,
            events,
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

    /// Monitor `node`'s heartbeat: it counts as offline when none arrives within `timeout`
    /// (zero: track its state without a timeout).
    pub fn monitor(&self, node: u8, timeout: Duration) {
        self.table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .monitor(node, Some(timeout));
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
