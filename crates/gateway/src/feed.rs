//! Feeding subscriptions with values: on a local dictionary every change is seen at once; on a
//! bus, the lift controller's TPDOs carry what they map (their layout is read from 1800h/1A00h
//! when a connection starts and again when the controller boots), and everything else is read
//! by SDO every `poll` interval.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use canbus::{BusReceiver, CanId, Filter, Interface};
use canopen::od::SharedDictionary;
use canopen::sdo::clients::SdoClients;
use nxg::gateway::Target;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::access::Objects;

/// A value for the session: which sub-object, and its bytes.
pub type Update = (Target, u16, u8, Vec<u8>);

type Watched = Arc<Mutex<BTreeSet<(Target, u16, u8)>>>;

enum Watching {
    Bus(Watched),
    Local(Target, Arc<LocalSubscriber>),
}

/// The sources of one connection's subscriptions.
pub struct Feed {
    watched: Watching,
    tasks: Vec<JoinHandle<()>>,
}

impl Drop for Feed {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// A TPDO of the lift controller: where each mapped sub-object lies in the frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    /// (index, sub-index, offset, length) in byte order.
    pub entries: Vec<(u16, u8, usize, usize)>,
}

/// Read the TPDO layouts of `node` (1800h–1803h and the first 508 further ones that exist).
pub async fn read_layouts(sdo: &SdoClients, node: u8) -> HashMap<CanId, Layout> {
    let mut layouts = HashMap::new();
    for n in 0..512u16 {
        let Ok(cob) = sdo.read::<u32>(node, 0x1800 + n, 1).await else {
            if n >= 4 {
                break;
            }
            continue;
        };
        let Some(id) = canopen::cob::id_from_parameter(cob) else {
            continue;
        };
        let Ok(count) = sdo.read::<u8>(node, 0x1A00 + n, 0).await else {
            continue;
        };
        let mut entries = Vec::new();
        let mut offset = 0;
        for s in 1..=count.min(64) {
            let Ok(map) = sdo.read::<u32>(node, 0x1A00 + n, s).await else {
                break;
            };
            let len = usize::from((map & 0xFF) as u8 / 8);
            entries.push(((map >> 16) as u16, (map >> 8) as u8, offset, len));
            offset += len;
        }
        layouts.insert(id, Layout { entries });
    }
    layouts
}

impl Feed {
    /// Changes of `od` (embedded mode). The watcher is installed once per dictionary by
    /// [`LocalChanges::install`]; changes coalesce per sub-object, so a controller that changes
    /// values faster than the portal takes them costs no memory, and the latest value wins.
    pub fn local(
        changes: &LocalChanges,
        od: SharedDictionary,
        target: Target,
        tx: mpsc::Sender<Update>,
    ) -> Feed {
        let local = changes.subscribe();
        let sub = local.clone();
        let task = tokio::spawn(async move {
            loop {
                sub.notify.notified().await;
                let keys =
                    std::mem::take(&mut *sub.dirty.lock().unwrap_or_else(PoisonError::into_inner));
                for (index, s) in keys {
                    let bytes = od
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .read(index, s);
                    if let Ok(bytes) = bytes {
                        if tx.send((target, index, s, bytes)).await.is_err() {
                            return;
                        }
                    }
                }
            }
        });
        Feed {
            watched: Watching::Local(target, local),
            tasks: vec![task],
        }
    }

    /// TPDOs of the lift controller on `bus` (an endpoint of its own) and SDO polling
    /// (bus-node mode).
    pub async fn bus(
        objects: Objects,
        sdo: Option<SdoClients>,
        bus: Option<Interface>,
        controller: Target,
        poll: Duration,
        tx: mpsc::Sender<Update>,
    ) -> Feed {
        let watched: Watched = Arc::default();
        let covered: Arc<Mutex<BTreeSet<(u16, u8)>>> = Arc::default();
        let mut tasks = Vec::new();
        if let (Some(sdo), Some(bus)) = (sdo, bus) {
            let (w, c, tx) = (watched.clone(), covered.clone(), tx.clone());
            tasks.push(tokio::spawn(async move {
                pdo_listener(sdo, bus, controller, w, c, tx).await;
            }));
        }
        let (w, c) = (watched.clone(), covered.clone());
        tasks.push(tokio::spawn(async move {
            let mut tick = tokio::time::interval(poll);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tick.tick().await;
                let keys: Vec<_> = w
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .iter()
                    .copied()
                    .collect();
                for (target, index, sub) in keys {
                    let by_pdo = target == controller
                        && c.lock()
                            .unwrap_or_else(PoisonError::into_inner)
                            .contains(&(index, sub));
                    if by_pdo {
                        continue;
                    }
                    if let Ok(bytes) = objects.read(target, index, sub).await {
                        if tx.send((target, index, sub, bytes)).await.is_err() {
                            return;
                        }
                    }
                }
            }
        }));
        Feed {
            watched: Watching::Bus(watched),
            tasks,
        }
    }

    /// Start feeding this sub-object.
    pub fn watch(&self, target: Target, index: u16, sub: u8) {
        match &self.watched {
            Watching::Bus(w) => {
                w.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .insert((target, index, sub));
            }
            Watching::Local(local, s) if *local == target => {
                s.watched
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .insert((index, sub));
            }
            Watching::Local(..) => {}
        }
    }

    /// Stop feeding it.
    pub fn unwatch(&self, target: Target, index: u16, sub: u8) {
        match &self.watched {
            Watching::Bus(w) => {
                w.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .remove(&(target, index, sub));
            }
            Watching::Local(_, s) => {
                s.watched
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .remove(&(index, sub));
            }
        }
    }
}

async fn pdo_listener(
    sdo: SdoClients,
    bus: Interface,
    controller: Target,
    watched: Watched,
    covered: Arc<Mutex<BTreeSet<(u16, u8)>>>,
    tx: mpsc::Sender<Update>,
) {
    let bus = match bus.endpoint() {
        Ok(bus) => bus,
        Err(e) => {
            tracing::warn!(bus = %bus.url(), error = %e, "no PDO feed; subscriptions are polled");
            return;
        }
    };
    let (_, mut rx) = bus.split();
    let boot_up = CanId::Standard(0x700 + u16::from(controller.node));
    // What the controller's TPDOs cover; only their frames and its boot-up reach this endpoint
    // (SDO traffic and other nodes' frames are filtered out before they are queued).
    let learn = |layouts: &HashMap<CanId, Layout>, rx: &mut BusReceiver| {
        let mut c = covered.lock().unwrap_or_else(PoisonError::into_inner);
        c.clear();
        c.extend(
            layouts
                .values()
                .flat_map(|l| l.entries.iter().map(|e| (e.0, e.1))),
        );
        let filters: Vec<Filter> = std::iter::once(boot_up)
            .chain(layouts.keys().copied())
            .map(Filter::exact)
            .collect();
        rx.set_filters(&filters);
    };
    let mut layouts = read_layouts(&sdo, controller.node).await;
    learn(&layouts, &mut rx);
    while let Some(frame) = rx.recv_frame().await {
        if frame.id() == boot_up && frame.data() == [0] {
            // The controller restarted: its PDO configuration may have changed.
            layouts = read_layouts(&sdo, controller.node).await;
            learn(&layouts, &mut rx);
            continue;
        }
        let Some(layout) = layouts.get(&frame.id()) else {
            continue;
        };
        for &(index, sub, offset, len) in &layout.entries {
            let key = (controller, index, sub);
            if !watched
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .contains(&key)
            {
                continue;
            }
            if let Some(bytes) = frame.data().get(offset..offset + len) {
                if tx
                    .send((controller, index, sub, bytes.to_vec()))
                    .await
                    .is_err()
                {
                    return;
                }
            }
        }
    }
}

/// One connection's view of a local dictionary: what it watches and what changed since it last
/// looked.
#[derive(Default)]
pub struct LocalSubscriber {
    watched: Mutex<BTreeSet<(u16, u8)>>,
    dirty: Mutex<BTreeSet<(u16, u8)>>,
    notify: tokio::sync::Notify,
}

type Subscribers = Arc<Mutex<Vec<std::sync::Weak<LocalSubscriber>>>>;

/// Changes of a local dictionary, fanned out to connections.
#[derive(Clone)]
pub struct LocalChanges {
    subscribers: Subscribers,
}

impl LocalChanges {
    /// Install the watcher on `od` (once per dictionary).
    pub fn install(od: &SharedDictionary) -> LocalChanges {
        let changes = LocalChanges {
            subscribers: Arc::default(),
        };
        let subs = changes.subscribers.clone();
        od.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .watch(Arc::new(move |index, sub| {
                subs.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .retain(|weak| {
                        let Some(s) = weak.upgrade() else {
                            return false;
                        };
                        let watched = s
                            .watched
                            .lock()
                            .unwrap_or_else(PoisonError::into_inner)
                            .contains(&(index, sub));
                        if watched {
                            s.dirty
                                .lock()
                                .unwrap_or_else(PoisonError::into_inner)
                                .insert((index, sub));
                            s.notify.notify_one();
                        }
                        true
                    });
            }));
        changes
    }

    fn subscribe(&self) -> Arc<LocalSubscriber> {
        let s = Arc::new(LocalSubscriber::default());
        self.subscribers
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Arc::downgrade(&s));
        s
    }
}
