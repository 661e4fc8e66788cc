//! [`LocalNode`]: the node core on a bus, driven by one tokio task that sleeps until the core's
//! next deadline (never polling: an idle node costs nothing) and wakes for bus frames,
//! dictionary changes and application commands.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use canbus::{Bus, BusSender};
use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;

use super::core::{Node, NodeOutput};
use super::{NodeCommand, NodeConfig, NodeEvent, PdoSetup};
use crate::nmt::{NmtCommand, NmtState};
use crate::od::ObjectDictionary;
use crate::od::SharedDictionary;
use crate::sdo::abort::AbortCode;
use crate::types::Value;
use crate::wake::sleep_until;

/// A CANopen device running on a bus.
pub struct LocalNode {
    od: SharedDictionary,
    commands: mpsc::UnboundedSender<NodeCommand>,
    power: watch::Sender<bool>,
    state: watch::Receiver<NmtState>,
    events: broadcast::Sender<NodeEvent>,
    task: JoinHandle<()>,
    node_id: u8,
}

impl LocalNode {
    /// Add the communication objects to `od`, start the node on `bus` and send its boot-up
    /// message; it enters pre-operational.
    pub fn start(bus: Bus, mut od: ObjectDictionary, config: NodeConfig) -> LocalNode {
        let node = Node::new(&config, &mut od, Instant::now());
        let (change_tx, change_rx) = mpsc::unbounded_channel();
        od.watch(Arc::new(move |index, sub| {
            // Communication parameters steer the node; every other change may trigger a TPDO.
            let _ = change_tx.send((index, sub));
        }));
        let node_id = node.node_id();
        let od = Arc::new(Mutex::new(od));
        let (commands, command_rx) = mpsc::unbounded_channel();
        let (state_tx, state) = watch::channel(NmtState::Initialising);
        let (events, _) = broadcast::channel(1024);
        let (power, power_rx) = watch::channel(true);
        let shell = Shell {
            node,
            od: od.clone(),
            events: events.clone(),
            state: state_tx,
            out: NodeOutput::default(),
            powered: true,
        };
        let task = tokio::spawn(shell.run(bus, command_rx, change_rx, power_rx));
        LocalNode {
            od,
            commands,
            power,
            state,
            events,
            task,
            node_id,
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
        let _ = self.commands.send(NodeCommand::Nmt(command));
    }

    /// Send a TIME stamp for `at`, if 0x1012 makes this node the TIME producer (bit 30).
    pub fn send_time(&self, at: std::time::SystemTime) {
        let _ = self.commands.send(NodeCommand::SendTime(at));
    }

    /// Raise an error: EMCY, error register 0x1001 and history 0x1003.
    pub fn set_error(&self, code: u16, manufacturer: [u8; 5]) {
        let _ = self
            .commands
            .send(NodeCommand::SetError(code, manufacturer));
    }

    /// Clear an error (an error-reset EMCY follows when none is left).
    pub fn clear_error(&self, code: u16) {
        let _ = self.commands.send(NodeCommand::ClearError(code));
    }

    /// Configure a PDO with the CiA 301 procedure (as an SDO client would, so the same checks
    /// apply): invalidate, parameters, mapping, validate.
    pub fn configure_pdo(&self, setup: &PdoSetup) -> Result<(), AbortCode> {
        let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
        super::configure_pdo(&mut od, setup)?;
        // The device's own PDO: every reset restores it, as a device sets up its PDOs again.
        let objects = super::pdo_objects(setup);
        let values = objects
            .iter()
            .filter_map(|&index| od.object(index))
            .flat_map(|o| {
                o.subs
                    .iter()
                    .filter_map(move |(&sub, v)| Some((o.index, sub, v.value_bytes()?.to_vec())))
            })
            .collect();
        let _ = self.commands.send(NodeCommand::Defaults(values));
        Ok(())
    }

    /// Cut or restore the device's supply, as a simulated failure: while off it neither sends
    /// nor hears anything (its heartbeat stops, SDO requests go unanswered); back on, it boots
    /// as at power-on (NMT reset node: boot-up message, pre-operational).
    pub fn set_powered(&self, on: bool) {
        self.power
            .send_if_modified(|p| std::mem::replace(p, on) != on);
    }

    /// Send TPDO `number` now (subject to its inhibit time; types 0–240 at the next SYNC).
    pub fn send_pdo(&self, number: u16) {
        let _ = self.commands.send(NodeCommand::SendPdo(number));
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

/// The task around the core: it owns the core, locks the shared dictionary for each step and
/// hands the output to the bus, the event subscribers and the state watchers.
struct Shell {
    node: Node,
    od: SharedDictionary,
    events: broadcast::Sender<NodeEvent>,
    state: watch::Sender<NmtState>,
    out: NodeOutput,
    /// Off: nothing is sent or heard ([`LocalNode::set_powered`]).
    powered: bool,
}

impl Shell {
    /// Run one step of the core on the dictionary.
    fn step(&mut self, f: impl FnOnce(&mut Node, &mut ObjectDictionary, &mut NodeOutput)) {
        let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
        f(&mut self.node, &mut od, &mut self.out);
    }

    /// Send the frames and publish the events and the state of the steps so far.
    async fn flush(&mut self, sender: &BusSender) -> bool {
        if !self.powered {
            self.out.frames.clear();
        }
        for event in self.out.events.drain(..) {
            let _ = self.events.send(event);
        }
        self.state.send_if_modified(|s| {
            let changed = *s != self.node.state();
            *s = self.node.state();
            changed
        });
        for f in self.out.frames.drain(..) {
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
        mut commands: mpsc::UnboundedReceiver<NodeCommand>,
        mut changes: mpsc::UnboundedReceiver<(u16, u8)>,
        mut power: watch::Receiver<bool>,
    ) {
        let (sender, mut receiver) = bus.split();
        let mut filtered_for = self.node.node_id();
        receiver.set_filters(&self.node.receive_filters());
        // Microsecond wake-ups for SYNC periods and inhibit times; tokio's timer as fallback.
        let alarm =
            crate::wake::PreciseWake::new(&format!("canopen-node-{}", self.node.node_id())).ok();
        self.step(|node, od, out| node.start(od, Instant::now(), out));
        loop {
            // What the last step changed (a communication parameter written by SDO) takes
            // effect before its answer goes out: the writer's next frame finds it in force.
            // Only what is queued now: changes these make wait for the next round.
            for _ in 0..changes.len() {
                let Ok((index, sub)) = changes.try_recv() else {
                    break;
                };
                self.step(|node, od, out| node.handle_change(od, index, sub, Instant::now(), out));
            }
            // A new node-ID (LSS, then a reset) takes its SDO requests in before its boot-up
            // goes out and tells the master it is there.
            if self.node.node_id() != filtered_for {
                filtered_for = self.node.node_id();
                receiver.set_filters(&self.node.receive_filters());
            }
            if !self.flush(&sender).await {
                return;
            }
            let deadline = self.node.poll_timeout();
            let wake = async {
                match &alarm {
                    Some(alarm) => {
                        alarm.set(deadline);
                        alarm.fired().await
                    }
                    None => sleep_until(deadline).await,
                }
            };
            // Time-driven work first so that a busy bus never starves the timers; then what the
            // application asked before a frame came (a PDO it set up is its own before a reset
            // from the bus restores it).
            tokio::select! {
                biased;
                _ = wake => self.step(|node, od, out| node.handle_timeout(od, Instant::now(), out)),
                Some(command) = commands.recv() => {
                    self.step(|node, od, out| node.handle_command(od, command, Instant::now(), out))
                }
                event = receiver.recv() => match event {
                    Some(canbus::BusEvent::Frame(f)) if self.powered => {
                        self.step(|node, od, out| node.handle_frame(od, &f, Instant::now(), out))
                    }
                    Some(_) => {}
                    None => return,
                },
                Some((index, sub)) = changes.recv() => {
                    self.step(|node, od, out| node.handle_change(od, index, sub, Instant::now(), out))
                }
                Ok(()) = power.changed() => {
                    let on = *power.borrow_and_update();
                    if on && !self.powered {
                        let reset = NodeCommand::Nmt(crate::nmt::NmtCommand::ResetNode);
                        self.powered = true;
                        self.step(|node, od, out| node.handle_command(od, reset, Instant::now(), out));
                    }
                    self.powered = on;
                }
            }
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
