//! SYNC (CiA 301 §7.2.5): producer and consumer, with COB-ID 0x1005, communication cycle period
//! 0x1006, synchronous window length 0x1007 and the counter overflow value 0x1019.

use std::time::{Duration, Instant};

use canbus::{CanId, Frame};

/// SYNC parameters of a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SyncConfig {
    /// 0x1005: identifier (bit 30: this node produces SYNC; bit 29: 29-bit identifier).
    pub cob_id: u32,
    /// 0x1006: period in µs (0: no SYNC produced).
    pub period_us: u32,
    /// 0x1007: synchronous window in µs (0: no window).
    pub window_us: u32,
    /// 0x1019: counter overflow value (0: no counter; 2–240).
    pub counter_overflow: u8,
}

impl Default for SyncConfig {
    fn default() -> Self {
        SyncConfig {
            cob_id: 0x80,
            period_us: 0,
            window_us: 0,
            counter_overflow: 0,
        }
    }
}

impl SyncConfig {
    fn id(&self) -> Option<CanId> {
        // Bit 31 of 0x1005 is "don't care" for SYNC; only bit 29 selects the format.
        crate::cob::id_from_parameter(self.cob_id & 0x7FFF_FFFF)
    }

    /// Whether this node is the SYNC producer.
    pub fn produces(&self) -> bool {
        self.cob_id & 0x4000_0000 != 0 && self.period_us > 0
    }
}

/// The SYNC producer: frames at the period, on a fixed grid (no drift), with the counter when
/// 0x1019 enables it.
#[derive(Debug, Clone)]
pub struct SyncProducer {
    config: SyncConfig,
    next: Option<Instant>,
    counter: u8,
}

impl SyncProducer {
    /// A producer with `config`, first SYNC one period after `now`.
    pub fn new(config: SyncConfig, now: Instant) -> Self {
        let mut p = SyncProducer {
            config,
            next: None,
            counter: 1,
        };
        p.reconfigure(config, now);
        p
    }

    /// Apply new parameters (e.g. after SDO writes to 0x1005/0x1006/0x1019).
    pub fn reconfigure(&mut self, config: SyncConfig, now: Instant) {
        self.config = config;
        self.counter = 1;
        self.next = config
            .produces()
            .then(|| now + Duration::from_micros(config.period_us.into()));
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.next
    }

    /// Send the SYNC if one is due.
    pub fn handle_timeout(&mut self, now: Instant, out: &mut Vec<Frame>) {
        let Some(next) = self.next.filter(|n| now >= *n) else {
            return;
        };
        let period = Duration::from_micros(self.config.period_us.into());
        self.next = Some(crate::tick::next_tick(next, period, now));
        let Some(id) = self.config.id() else {
            return;
        };
        let frame = if self.config.counter_overflow >= 2 {
            let counter = self.counter;
            self.counter = if counter >= self.config.counter_overflow {
                1
            } else {
                counter + 1
            };
            Frame::new(id, &[counter])
        } else {
            Frame::new(id, &[])
        };
        out.extend(frame.ok());
    }
}

/// A SYNC received: its counter (if the producer sends one) and when the synchronous window
/// closes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SyncEvent {
    /// The counter, 1 to the overflow value.
    pub counter: Option<u8>,
    /// Synchronous PDOs must be sent before this instant (`None`: no window).
    pub window_ends: Option<Instant>,
}

/// Recognise a SYNC frame under `config` received at `now`.
pub fn receive(config: &SyncConfig, frame: &Frame, now: Instant) -> Option<SyncEvent> {
    if Some(frame.id()) != config.id() || frame.data().len() > 1 || frame.is_remote() {
        return None;
    }
    Some(SyncEvent {
        counter: frame.data().first().copied(),
        window_ends: (config.window_us > 0)
            .then(|| now + Duration::from_micros(config.window_us.into())),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn due(p: &mut SyncProducer, now: Instant) -> Option<Frame> {
        let mut out = Vec::new();
        p.handle_timeout(now, &mut out);
        out.pop()
    }

    #[test]
    fn producer_period_counter_and_grid() {
        let t0 = Instant::now();
        let us = Duration::from_micros;
        let config = SyncConfig {
            cob_id: 0x4000_0080,
            period_us: 1000,
            window_us: 0,
            counter_overflow: 3,
        };
        let mut p = SyncProducer::new(config, t0);
        assert_eq!(p.poll_timeout(), Some(t0 + us(1000)));
        assert_eq!(due(&mut p, t0 + us(999)), None);
        let counters: Vec<u8> = (1..=5)
            .map(|k| due(&mut p, t0 + us(1000 * k + 300)).unwrap().data()[0])
            .collect();
        assert_eq!(counters, vec![1, 2, 3, 1, 2]);
        assert_eq!(
            p.poll_timeout(),
            Some(t0 + us(6000)),
            "late calls keep the grid"
        );
        p.reconfigure(
            SyncConfig {
                counter_overflow: 0,
                ..config
            },
            t0 + us(6000),
        );
        assert_eq!(due(&mut p, t0 + us(7000)).unwrap().data(), &[] as &[u8]);
        p.reconfigure(
            SyncConfig {
                cob_id: 0x80,
                ..config
            },
            t0,
        );
        assert_eq!(p.poll_timeout(), None, "bit 30 clear: consumer only");
    }

    #[test]
    fn consumer_recognises_sync_and_window() {
        let now = Instant::now();
        let config = SyncConfig {
            window_us: 500,
            ..SyncConfig::default()
        };
        let event = receive(&config, &Frame::standard(0x80, &[7]).unwrap(), now).unwrap();
        assert_eq!(event.counter, Some(7));
        assert_eq!(event.window_ends, Some(now + Duration::from_micros(500)));
        assert!(receive(&config, &Frame::standard(0x81, &[]).unwrap(), now).is_none());
        assert!(receive(&config, &Frame::standard(0x80, &[1, 2]).unwrap(), now).is_none());
        assert_eq!(
            receive(
                &SyncConfig::default(),
                &Frame::standard(0x80, &[]).unwrap(),
                now
            )
            .unwrap()
            .window_ends,
            None
        );
    }
}
