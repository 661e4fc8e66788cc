//! The gateway's watch over its networks (docs/PROTOCOL.md §Events): one task per network runs
//! the sans-IO [`Supervisor`] on a bus endpoint of its own — EMCY, NMT states and heartbeat
//! silence of every node, the network's state — reads each newly heard node's heartbeat period
//! (1017h) by SDO, and queues what happened as bus events with their time and the EMCY texts,
//! for the portal that registers for them (docs/PROTOCOL.md §Events).

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use canbus::{Bus, BusEvent as Link, CanId, Filter, ERR_FLAG};
use canopen::sdo::clients::SdoClients;
use canopen::supervisor::{BusCondition, NodeStatus, Supervision, Supervisor};
use canopen::wake::sleep_until;
use nxg::gateway::{BusEvent, EventQueue, Happening};
use nxg::msg::{BusState, NodeId, NodeRef, NodeState};
use tokio::sync::{mpsc, Notify};
use tokio::task::JoinHandle;

/// Where a network's supervision delivers.
#[derive(Clone)]
pub struct Sink {
    /// The gateway's queue of undelivered events.
    pub queue: Arc<Mutex<EventQueue>>,
    /// Woken whenever something was queued.
    pub ready: Arc<Notify>,
}

impl Sink {
    fn push(&self, what: Happening) {
        let time_ms = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX));
        self.queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(BusEvent { time_ms, what });
        self.ready.notify_one();
    }
}

/// One network to watch.
pub struct Network {
    /// Its `net` number.
    pub net: u8,
    /// A bus endpoint of the supervision's own.
    pub bus: Bus,
    /// SDO to read heartbeat periods.
    pub sdo: SdoClients,
    /// The gateway's own node-ID there (0: none).
    pub own: u8,
    /// Heartbeat periods from the configuration (ms; 0: not supervised).
    pub configured: Vec<(u8, u16)>,
}

/// Watch `network` until the task is aborted.
pub fn spawn(network: Network, sink: Sink) -> JoinHandle<()> {
    tokio::spawn(run(network, sink))
}

async fn run(network: Network, sink: Sink) {
    let Network {
        net,
        bus,
        sdo,
        own,
        configured,
    } = network;
    let (_sender, mut receiver) = bus.split();
    // EMCY 081h–0FFh, NMT error control 701h–77Fh, error frames.
    receiver.set_filters(&[
        Filter::standard(0x080, 0x780),
        Filter::standard(0x700, 0x780),
        Filter {
            id: ERR_FLAG,
            mask: ERR_FLAG,
        },
    ]);
    let mut supervisor = Supervisor::new(own, configured);
    let (periods_tx, mut periods) = mpsc::unbounded_channel::<(u8, Option<u16>)>();
    let mut out = Vec::new();
    let mut limit = LogLimit::new();
    loop {
        for s in out.drain(..) {
            match s {
                Supervision::ReadPeriod(node) => {
                    let (sdo, tx) = (sdo.clone(), periods_tx.clone());
                    tokio::spawn(async move {
                        let ms = sdo.read::<u16>(node, 0x1017, 0).await.ok();
                        let _ = tx.send((node, ms));
                    });
                }
                other => {
                    if let Some(what) = happening(net, other) {
                        limit.log(net, &what);
                        sink.push(what);
                    }
                }
            }
        }
        let timer = sleep_until(supervisor.poll_timeout());
        tokio::select! {
            event = receiver.recv() => {
                let now = Instant::now();
                match event {
                    Some(Link::Frame(frame)) => supervisor.handle_frame(&frame, now, &mut out),
                    Some(Link::LinkDown { .. }) => supervisor.link(false, now, &mut out),
                    Some(Link::LinkUp) => supervisor.link(true, now, &mut out),
                    Some(Link::Overrun { .. }) => supervisor.overrun(&mut out),
                    None => return,
                }
            }
            Some((node, ms)) = periods.recv() => supervisor.period(node, ms),
            _ = timer => supervisor.handle_timeout(Instant::now(), &mut out),
        }
    }
}

/// Check `node`'s configured SDO channels ([`SdoClients::check_channels`]) once it answers on
/// any of them — while it answers on none (not booted yet, switched off) ask again every
/// `retry` — and log each channel it does not serve: every request that lands on one would
/// fail with a timeout. Returns those channels.
pub async fn check_sdo_channels(
    sdo: SdoClients,
    net: u8,
    node: u8,
    retry: std::time::Duration,
) -> Vec<(CanId, CanId)> {
    loop {
        let Ok(answers) = sdo.check_channels(node).await else {
            return Vec::new();
        };
        if answers.iter().all(|(_, answer)| answer.is_err()) {
            tokio::time::sleep(retry).await;
            continue;
        }
        let mut silent = Vec::new();
        for ((request, response), answer) in answers {
            match answer {
                Ok(()) => {
                    tracing::debug!(net, node, %request, %response, "SDO channel answers")
                }
                Err(error) => {
                    tracing::warn!(net, node, %request, %response, %error,
                        "SDO channel does not answer while others do: requests that land on it fail; \
                         check the node's SDO server parameters (1201h ff.) against [[bus.nodes]] sdo_channels");
                    silent.push((request, response));
                }
            }
        }
        return silent;
    }
}

/// A supervision result as an event of network `net`.
fn happening(net: u8, s: Supervision) -> Option<Happening> {
    let node = |id: u8| NodeId::new(id).map(|id| NodeRef::new(id, net));
    Some(match s {
        Supervision::Emcy { node: id, message } => Happening::Emcy {
            node: node(id)?,
            code: message.code,
            register: message.register,
            data: message.manufacturer,
            text: lift417::emcy::text(message.code),
        },
        Supervision::Node { node: id, status } => Happening::State {
            node: node(id)?,
            state: match status {
                NodeStatus::BootUp => NodeState::BootUp,
                NodeStatus::PreOperational => NodeState::PreOperational,
                NodeStatus::Operational => NodeState::Operational,
                NodeStatus::Stopped => NodeState::Stopped,
                NodeStatus::Offline => NodeState::Offline,
            },
        },
        Supervision::Bus(condition) => Happening::Bus {
            net,
            state: match condition {
                BusCondition::ErrorActive => BusState::ErrorActive,
                BusCondition::ErrorPassive => BusState::ErrorPassive,
                BusCondition::BusOff => BusState::BusOff,
                BusCondition::Overrun => BusState::Overrun,
                BusCondition::Offline => BusState::Offline,
            },
        },
        Supervision::ReadPeriod(_) => return None,
    })
}

/// Log lines of events per network and second at most: a node that floods EMCYs must not
/// flood the log (the events themselves still reach the portal).
const LOG_PER_SECOND: u32 = 20;

/// Counts log lines per second and what it left out.
struct LogLimit {
    second: Option<Instant>,
    written: u32,
    left_out: u64,
}

impl LogLimit {
    fn new() -> LogLimit {
        LogLimit {
            second: None,
            written: 0,
            left_out: 0,
        }
    }

    fn log(&mut self, net: u8, what: &Happening) {
        let now = Instant::now();
        if self
            .second
            .is_none_or(|s| now.duration_since(s) >= std::time::Duration::from_secs(1))
        {
            if self.left_out > 0 {
                tracing::warn!(
                    net,
                    left_out = self.left_out,
                    "more bus events than the log shows"
                );
            }
            self.second = Some(now);
            self.written = 0;
            self.left_out = 0;
        }
        if self.written < LOG_PER_SECOND {
            self.written += 1;
            log(what);
        } else {
            self.left_out += 1;
        }
    }
}

fn log(what: &Happening) {
    match what {
        Happening::Emcy {
            node, code, text, ..
        } => {
            let text = text.get("en").unwrap_or_default();
            tracing::warn!(
                node = node.id.get(),
                net = node.net,
                code = format!("{code:04X}h"),
                text,
                "EMCY"
            );
        }
        Happening::State { node, state } => {
            tracing::info!(
                node = node.id.get(),
                net = node.net,
                state = state.name(),
                "node state"
            );
        }
        Happening::Bus { net, state } => tracing::warn!(net, state = state.name(), "network state"),
    }
}
