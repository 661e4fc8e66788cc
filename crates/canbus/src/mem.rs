//! `mem://NAME`: an in-process bus.
//!
//! Every endpoint opened on the same NAME in this process shares one bus. A send delivers the
//! frame, timestamped, to every other endpoint's receive queue at once (and to the sender's own
//! only if it asked for its own frames). Like a SocketCAN socket, a receiver that does not keep
//! up loses frames and is told how many ([`crate::BusEvent::Overrun`]); a slow reader never
//! slows down the bus.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock, PoisonError, Weak};
use std::time::SystemTime;

use crate::bus::{BusError, BusOptions, BusSender, Endpoints, RxFeed, SenderInner};
use crate::frame::Frame;

#[derive(Default)]
struct MemBus {
    endpoints: Endpoints,
}

fn registry() -> &'static Mutex<HashMap<String, Weak<MemBus>>> {
    static REGISTRY: OnceLock<Mutex<HashMap<String, Weak<MemBus>>>> = OnceLock::new();
    REGISTRY.get_or_init(Default::default)
}

/// Sends on a `mem://` bus; never waits.
#[derive(Clone)]
pub(crate) struct MemSender {
    bus: Arc<MemBus>,
    endpoint: u64,
}

impl MemSender {
    pub(crate) fn send(&self, frame: Frame) -> Result<(), BusError> {
        let frame = frame.with_timestamp(SystemTime::now());
        self.bus.endpoints.deliver(Some(self.endpoint), frame);
        Ok(())
    }
}

pub(crate) fn open(name: &str, feed: RxFeed, options: &BusOptions) -> BusSender {
    let bus = {
        let mut registry = registry().lock().unwrap_or_else(PoisonError::into_inner);
        registry.retain(|_, bus| bus.strong_count() > 0);
        match registry.get(name).and_then(Weak::upgrade) {
            Some(bus) => bus,
            None => {
                let bus = Arc::new(MemBus::default());
                registry.insert(name.to_owned(), Arc::downgrade(&bus));
                bus
            }
        }
    };
    let endpoint = bus.endpoints.add(feed, options.receive_own);
    BusSender::new(SenderInner::Mem(MemSender { bus, endpoint }))
}

#[cfg(test)]
mod tests {
    use crate::{Bus, BusEvent, BusOptions, Filter, Frame};

    #[tokio::test]
    async fn frames_reach_others_but_not_the_sender() {
        let mut a = Bus::open("mem://t-basic").await.unwrap();
        let mut b = Bus::open("mem://t-basic").await.unwrap();
        let mut c = Bus::open("mem://t-basic").await.unwrap();
        let mut other_bus = Bus::open("mem://t-basic-2").await.unwrap();
        let f = Frame::standard(0x181, &[1, 2, 3]).unwrap();
        a.send(f).await.unwrap();
        for rx in [&mut b, &mut c] {
            let got = rx.receiver.recv_frame().await.unwrap();
            assert_eq!(got.data(), f.data());
            assert!(got.timestamp().is_some());
        }
        assert!(a.receiver.try_recv().is_none(), "sender got its own frame");
        assert!(
            other_bus.receiver.try_recv().is_none(),
            "buses leak into each other"
        );
    }

    #[tokio::test]
    async fn receive_own_is_opt_in() {
        let options = BusOptions {
            receive_own: true,
            ..Default::default()
        };
        let mut a = Bus::open_with("mem://t-own", options).await.unwrap();
        a.send(Frame::standard(1, &[]).unwrap()).await.unwrap();
        assert_eq!(a.receiver.recv_frame().await.unwrap().id().as_raw(), 1);
    }

    #[tokio::test]
    async fn filters_and_overruns() {
        let a = Bus::open("mem://t-filter").await.unwrap();
        let options = BusOptions {
            rx_queue: 4,
            ..Default::default()
        };
        let mut b = Bus::open_with("mem://t-filter", options).await.unwrap();
        b.receiver.set_filters(&[Filter::standard(0x700, 0x780)]);
        for id in [0x181, 0x701, 0x702, 0x703, 0x704, 0x705, 0x706] {
            a.send(Frame::standard(id, &[]).unwrap()).await.unwrap();
        }
        // Filtered before queueing (as SocketCAN's kernel filters): 0x181 takes no room, the
        // queue holds 4 of the six that pass and 2 are lost.
        assert_eq!(b.recv().await, Some(BusEvent::Overrun { dropped: 2 }));
        let ids: Vec<u32> = std::iter::from_fn(|| match b.receiver.try_recv() {
            Some(BusEvent::Frame(f)) => Some(f.id().as_raw()),
            _ => None,
        })
        .collect();
        assert_eq!(ids, vec![0x701, 0x702, 0x703, 0x704]);
    }

    #[tokio::test]
    async fn a_handled_endpoint_gets_what_was_queued_then_what_comes_in_order() {
        let a = Bus::open("mem://t-handled").await.unwrap();
        let (_, mut receiver) = Bus::open("mem://t-handled").await.unwrap().split();
        receiver.set_filters(&[Filter::standard(0x580, 0x780)]);
        let send = |id| a.send(Frame::standard(id, &[id as u8]).unwrap());
        for id in [0x581, 0x181, 0x582] {
            send(id).await.unwrap();
        }
        let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let handled = {
            let seen = seen.clone();
            receiver.handle_with(move |event| match event {
                BusEvent::Frame(f) => seen.lock().unwrap().push(f.id().as_raw()),
                other => panic!("{other:?}"),
            })
        };
        // Handed over at once, by the sender's own delivery: nothing to wait for.
        for id in [0x583, 0x701, 0x5FF] {
            send(id).await.unwrap();
        }
        assert_eq!(*seen.lock().unwrap(), vec![0x581, 0x582, 0x583, 0x5FF]);
        // Dropping the handle closes the endpoint.
        drop(handled);
        send(0x584).await.unwrap();
        assert_eq!(seen.lock().unwrap().len(), 4);
        let registry = super::registry().lock().unwrap();
        let bus = registry.get("t-handled").and_then(|w| w.upgrade()).unwrap();
        assert_eq!(bus.endpoints.len(), 1);
    }

    #[tokio::test]
    async fn dropped_receivers_are_pruned() {
        let a = Bus::open("mem://t-prune").await.unwrap();
        let b = Bus::open("mem://t-prune").await.unwrap();
        drop(b);
        a.send(Frame::standard(1, &[]).unwrap()).await.unwrap();
        let registry = super::registry().lock().unwrap();
        let bus = registry.get("t-prune").and_then(|w| w.upgrade()).unwrap();
        assert_eq!(bus.endpoints.len(), 1);
    }
}
