//! The wire model of the hub's bit-rate mode, sans-IO: which queued frame wins the bus next and
//! when its last bit has passed. The bus thread in `channel.rs` feeds it arrivals and sleeps
//! until each transmission ends; the tests here drive it with made-up instants.

use std::collections::{HashMap, VecDeque};
use std::time::Instant;

use crate::frame::Frame;
use crate::wire;

/// A frame waiting for the bus, with whatever the caller keeps alive until it has left.
struct Pending<T> {
    frame: Frame,
    arrival: Instant,
    token: T,
}

/// One frame on the wire: who sent it, and when its transmission ends (the end of the
/// interframe space, when receivers have it).
pub(super) struct Transmission<T> {
    pub(super) from: u64,
    pub(super) frame: Frame,
    pub(super) ends: Instant,
    pub(super) token: T,
}

/// Each client has a FIFO transmit queue (as a CAN controller's queue); whenever the bus becomes
/// free, the heads of the queues already waiting arbitrate and the lowest arbitration key wins
/// (CiA 301 builds on ISO 11898-1 bitwise arbitration). The winner occupies the bus for its exact
/// wire time including stuff bits.
///
/// Time is kept as the instant the bus becomes free (`free_at`), advanced by each frame's wire
/// time, so a late wake-up of the caller delays one delivery slightly but never accumulates.
pub(super) struct Arbiter<T> {
    bitrate: u32,
    queues: HashMap<u64, VecDeque<Pending<T>>>,
    free_at: Instant,
}

impl<T> Arbiter<T> {
    pub(super) fn new(bitrate: u32, now: Instant) -> Self {
        Arbiter {
            bitrate,
            queues: HashMap::new(),
            free_at: now,
        }
    }

    pub(super) fn is_idle(&self) -> bool {
        self.queues.is_empty()
    }

    /// Queue `frame` from client `from`, which handed it over at `arrival`.
    pub(super) fn push(&mut self, from: u64, frame: Frame, arrival: Instant, token: T) {
        self.queues.entry(from).or_default().push_back(Pending {
            frame,
            arrival,
            token,
        });
    }

    /// The next transmission: the winner among the frames waiting when the bus is next free
    /// (or, on an idle bus, when the earliest frame arrives).
    pub(super) fn next(&mut self) -> Option<Transmission<T>> {
        let earliest = self
            .queues
            .values()
            .filter_map(|q| q.front())
            .map(|p| p.arrival)
            .min()?;
        let start = self.free_at.max(earliest);
        // Only frames already waiting when arbitration starts take part in it.
        let (&from, _) = self
            .queues
            .iter()
            .filter_map(|(client, q)| q.front().map(|head| (client, head)))
            .filter(|(_, head)| head.arrival <= start)
            .min_by_key(|(_, head)| (wire::arbitration_key(&head.frame), head.arrival))?;
        let queue = self.queues.get_mut(&from)?;
        let winner = queue.pop_front()?;
        if queue.is_empty() {
            self.queues.remove(&from);
        }
        self.free_at = start + wire::frame_duration(&winner.frame, self.bitrate);
        Some(Transmission {
            from,
            frame: winner.frame,
            ends: self.free_at,
            token: winner.token,
        })
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    fn frame(id: u16, seed: u64) -> Frame {
        let data = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).to_le_bytes();
        Frame::standard(id, &data).unwrap()
    }

    fn drain(arbiter: &mut Arbiter<()>) -> Vec<Transmission<()>> {
        std::iter::from_fn(|| arbiter.next()).collect()
    }

    #[test]
    fn a_burst_takes_the_sum_of_its_wire_times() {
        for bitrate in [125_000u32, 250_000, 500_000, 1_000_000] {
            let t0 = Instant::now();
            let mut arbiter = Arbiter::new(bitrate, t0);
            let frames: Vec<Frame> = (0..500)
                .map(|i| frame(0x100 + i % 0x100, i.into()))
                .collect();
            for f in &frames {
                arbiter.push(1, *f, t0, ());
            }
            let sent = drain(&mut arbiter);
            assert_eq!(sent.len(), frames.len());
            let mut at = t0;
            for (tx, f) in sent.iter().zip(&frames) {
                at += wire::frame_duration(f, bitrate);
                assert_eq!(tx.frame, *f, "one client's frames leave in order");
                assert_eq!(tx.ends, at);
            }
            assert!(arbiter.is_idle());
        }
    }

    #[test]
    fn an_idle_bus_starts_at_the_arrival() {
        let t0 = Instant::now();
        let mut arbiter = Arbiter::new(500_000, t0);
        let later = t0 + Duration::from_millis(7);
        let f = frame(0x181, 1);
        arbiter.push(3, f, later, ());
        let tx = arbiter.next().unwrap();
        assert_eq!(tx.from, 3);
        assert_eq!(tx.ends, later + wire::frame_duration(&f, 500_000));
        assert!(arbiter.next().is_none());
    }

    #[test]
    fn the_lowest_id_among_waiting_heads_wins() {
        let t0 = Instant::now();
        let mut arbiter = Arbiter::new(125_000, t0);
        arbiter.push(1, frame(0x700, 1), t0, ());
        arbiter.push(1, frame(0x080, 2), t0, ());
        arbiter.push(2, frame(0x200, 3), t0, ());
        arbiter.push(3, frame(0x181, 4), t0, ());
        let ids: Vec<u32> = drain(&mut arbiter)
            .iter()
            .map(|tx| wire::arbitration_key(&tx.frame) >> 21)
            .collect();
        // Client 1's 0x080 waits behind its own 0x700: a controller's queue is FIFO.
        assert_eq!(ids, [0x181, 0x200, 0x700, 0x080]);
    }

    #[test]
    fn a_frame_arriving_during_a_transmission_competes_at_the_next_slot_only() {
        let t0 = Instant::now();
        let mut arbiter = Arbiter::new(125_000, t0);
        let high = frame(0x7FF, 1);
        arbiter.push(1, high, t0, ());
        arbiter.push(1, frame(0x7FE, 2), t0, ());
        // 0x001 arrives while the first frame is on the wire: it wins the second slot.
        let busy = wire::frame_duration(&high, 125_000);
        arbiter.push(2, frame(0x001, 3), t0 + busy / 2, ());
        // 0x002 arrives after the second slot has started: it waits for the third.
        let second_start = t0 + busy;
        arbiter.push(
            3,
            frame(0x002, 4),
            second_start + Duration::from_nanos(1),
            (),
        );
        let order: Vec<u64> = drain(&mut arbiter).iter().map(|tx| tx.from).collect();
        assert_eq!(order, [1, 2, 3, 1]);
    }
}
