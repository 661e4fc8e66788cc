//! Periodic schedules (heartbeat, SYNC): stay on the grid `start + k × period` whatever the
//! wake-up latency, so the mean period is exact; only after a real suspension (a second or a
//! hundred periods behind) start a fresh grid instead of sending a burst of catch-up frames.

use std::time::{Duration, Instant};

/// The deadline after `due` (which has been handled at `now`).
pub(crate) fn next_tick(due: Instant, period: Duration, now: Instant) -> Instant {
    let following = due + period;
    let limit = (period * 100).min(Duration::from_secs(1));
    if now.saturating_duration_since(due) >= limit {
        now + period
    } else {
        following
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn late_wakeups_keep_the_grid_suspensions_restart_it() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        assert_eq!(
            next_tick(t0, ms(1), t0 + ms(2)),
            t0 + ms(1),
            "2 ms late at 1 ms: catch up"
        );
        assert_eq!(next_tick(t0, ms(100), t0 + ms(150)), t0 + ms(100));
        assert_eq!(
            next_tick(t0, ms(100), t0 + ms(1250)),
            t0 + ms(1350),
            "suspended: fresh grid"
        );
        assert_eq!(
            next_tick(t0, ms(1), t0 + ms(100)),
            t0 + ms(101),
            "100 periods behind"
        );
    }
}
