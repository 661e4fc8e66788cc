//! One bus of the hub: its subscribers, fan-out, and (with a bit rate) the wire model.

use std::sync::atomic::Ordering;
use std::sync::{Arc, PoisonError, RwLock, Weak};
use std::time::{Instant, SystemTime};

use tokio::sync::{mpsc, Notify, OwnedSemaphorePermit};

use super::arbiter::Arbiter;
use super::HubStats;
use crate::frame::Frame;

/// What the hub queues for a client's writer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Outgoing {
    /// A frame seen on the bus (timestamped).
    Frame(Frame),
    /// The answer to `< echo >`.
    Echo,
}

pub(super) struct Subscriber {
    pub(super) client: u64,
    pub(super) tx: mpsc::Sender<Outgoing>,
    /// Woken when the hub drops the client (slow reader).
    pub(super) kill: Arc<Notify>,
}

/// A frame waiting for the bus in bit-rate mode.
pub(super) struct Queued {
    pub(super) from: u64,
    pub(super) frame: Frame,
    pub(super) arrival: Instant,
    /// Returned when the frame has left, which bounds each client's transmit queue.
    pub(super) permit: OwnedSemaphorePermit,
}

pub(super) struct Channel {
    pub(super) name: String,
    subscribers: RwLock<Vec<Subscriber>>,
    /// Present in bit-rate mode: frames go through the arbiter instead of straight out.
    arbiter: Option<std::sync::mpsc::Sender<Queued>>,
    stats: Arc<HubStats>,
}

impl Channel {
    pub(super) fn new(name: &str, bitrate: Option<u32>, stats: Arc<HubStats>) -> Arc<Self> {
        Arc::new_cyclic(|weak: &Weak<Channel>| {
            let arbiter = bitrate.and_then(|bitrate| {
                let (tx, rx) = std::sync::mpsc::channel();
                let weak = weak.clone();
                // An OS thread, not a task: tokio's timer has millisecond resolution, a frame at
                // 1 Mbit/s lasts about 0.13 ms, and thread sleeps are precise to microseconds.
                let spawned = std::thread::Builder::new()
                    .name(format!("hub-bus-{name}"))
                    .spawn(move || arbitrate(weak, rx, bitrate));
                match spawned {
                    Ok(_) => Some(tx),
                    Err(e) => {
                        tracing::error!(channel = name, error = %e, "cannot start the bus thread; channel runs unthrottled");
                        None
                    }
                }
            });
            Channel {
                name: name.to_owned(),
                subscribers: RwLock::new(Vec::new()),
                arbiter,
                stats,
            }
        })
    }

    pub(super) fn add(&self, subscriber: Subscriber) {
        self.subscribers
            .write()
            .unwrap_or_else(PoisonError::into_inner)
            .push(subscriber);
    }

    /// Remove a client; returns whether the channel is now empty.
    pub(super) fn remove(&self, client: u64) -> bool {
        let mut subs = self
            .subscribers
            .write()
            .unwrap_or_else(PoisonError::into_inner);
        subs.retain(|s| s.client != client);
        subs.is_empty()
    }

    pub(super) fn is_timed(&self) -> bool {
        self.arbiter.is_some()
    }

    /// Hand a frame from `from` to the bus: straight out, or to the arbiter in bit-rate mode
    /// (then `permit` is held until the frame has left).
    pub(super) fn submit(&self, from: u64, frame: Frame, permit: Option<OwnedSemaphorePermit>) {
        self.stats.frames_in.fetch_add(1, Ordering::Relaxed);
        match (&self.arbiter, permit) {
            (Some(arbiter), Some(permit)) => {
                let queued = Queued {
                    from,
                    frame,
                    arrival: Instant::now(),
                    permit,
                };
                // The arbiter lives as long as the channel; a send error means shutdown.
                let _ = arbiter.send(queued);
            }
            _ => self.broadcast(from, frame),
        }
    }

    /// Deliver `frame` to every subscriber but its sender. A subscriber whose queue is full is
    /// dropped from the bus: memory stays bounded and one stalled reader never holds up others.
    pub(super) fn broadcast(&self, from: u64, frame: Frame) {
        let frame = frame.with_timestamp(SystemTime::now());
        let mut stalled = Vec::new();
        {
            let subs = self
                .subscribers
                .read()
                .unwrap_or_else(PoisonError::into_inner);
            for sub in subs.iter().filter(|s| s.client != from) {
                match sub.tx.try_send(Outgoing::Frame(frame)) {
                    Ok(()) => {
                        self.stats.frames_out.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(mpsc::error::TrySendError::Full(_)) => stalled.push(sub.client),
                    Err(mpsc::error::TrySendError::Closed(_)) => {}
                }
            }
        }
        if stalled.is_empty() {
            return;
        }
        let mut subs = self
            .subscribers
            .write()
            .unwrap_or_else(PoisonError::into_inner);
        subs.retain(|sub| {
            if !stalled.contains(&sub.client) {
                return true;
            }
            tracing::warn!(
                channel = %self.name,
                client = sub.client,
                "client does not keep up reading (queue full); disconnecting it"
            );
            self.stats.clients_dropped.fetch_add(1, Ordering::Relaxed);
            sub.kill.notify_one();
            false
        });
    }
}

/// The bus thread of bit-rate mode: feeds the [`Arbiter`] and delivers each frame when its
/// transmission ends.
fn arbitrate(channel: Weak<Channel>, rx: std::sync::mpsc::Receiver<Queued>, bitrate: u32) {
    let mut arbiter = Arbiter::new(bitrate, Instant::now());
    let enqueue = |arbiter: &mut Arbiter<OwnedSemaphorePermit>, q: Queued| {
        arbiter.push(q.from, q.frame, q.arrival, q.permit);
    };
    loop {
        if arbiter.is_idle() {
            let Ok(q) = rx.recv() else { return };
            enqueue(&mut arbiter, q);
        }
        while let Ok(q) = rx.try_recv() {
            enqueue(&mut arbiter, q);
        }
        let Some(tx) = arbiter.next() else {
            continue;
        };
        let now = Instant::now();
        if tx.ends > now {
            std::thread::sleep(tx.ends - now);
        }
        let Some(channel) = channel.upgrade() else {
            return;
        };
        channel.broadcast(tx.from, tx.frame);
        // The permit goes back now that the frame has left: it bounds each client's queue.
        drop(tx.token);
    }
}
