//! Waking async protocol loops (feature `tokio`): at a sans-IO core's next deadline
//! ([`sleep_until`]), and precisely (`PreciseWake`, for the node loops of this crate).
//!
//! A precise wake-up for async protocol loops. tokio's timer has millisecond granularity; a
//! 1 ms SYNC period or a 0.5 ms inhibit time needs better. One small thread per node waits on a
//! condition variable until the requested instant (the OS wakes it within tens of microseconds)
//! and wakes the loop; with no deadline it just waits, costing nothing.

use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::Instant;

use tokio::sync::Notify;

#[derive(Default)]
struct State {
    deadline: Option<Instant>,
    closed: bool,
}

#[derive(Default)]
struct Shared {
    state: Mutex<State>,
    changed: Condvar,
    fired: Notify,
}

/// A one-shot, re-armable precise wake-up; dropping it stops its thread.
pub(crate) struct PreciseWake {
    shared: Arc<Shared>,
}

impl PreciseWake {
    /// Start the alarm's thread.
    pub(crate) fn new(name: &str) -> std::io::Result<Self> {
        let shared = Arc::new(Shared::default());
        let worker = shared.clone();
        std::thread::Builder::new()
            .name(name.to_owned())
            .spawn(move || run(&worker))?;
        Ok(PreciseWake { shared })
    }

    /// Wake the loop at `deadline` (replacing the previous one); `None` disarms.
    pub(crate) fn set(&self, deadline: Option<Instant>) {
        let mut state = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if state.deadline != deadline {
            state.deadline = deadline;
            self.shared.changed.notify_one();
        }
    }

    /// Resolves when the armed deadline has passed.
    pub(crate) async fn fired(&self) {
        self.shared.fired.notified().await;
    }
}

impl Drop for PreciseWake {
    fn drop(&mut self) {
        let mut state = self
            .shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        state.closed = true;
        self.shared.changed.notify_one();
    }
}

fn run(shared: &Shared) {
    let mut state = shared.state.lock().unwrap_or_else(PoisonError::into_inner);
    loop {
        if state.closed {
            return;
        }
        state = match state.deadline {
            None => shared
                .changed
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner),
            Some(deadline) => {
                let now = Instant::now();
                if now >= deadline {
                    state.deadline = None;
                    shared.fired.notify_one();
                    continue;
                }
                shared
                    .changed
                    .wait_timeout(state, deadline - now)
                    .unwrap_or_else(PoisonError::into_inner)
                    .0
            }
        };
    }
}

/// Sleep until `deadline`, or forever without one: the timer arm of a driver's `select!` over a
/// sans-IO core's `poll_timeout()`.
pub async fn sleep_until(deadline: Option<impl Into<tokio::time::Instant>>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d.into()).await,
        None => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn fires_at_the_deadline_with_sub_millisecond_precision() {
        let wake = PreciseWake::new("wake-test").unwrap();
        let mut worst = Duration::ZERO;
        for _ in 0..20 {
            let deadline = Instant::now() + Duration::from_micros(700);
            wake.set(Some(deadline));
            wake.fired().await;
            let now = Instant::now();
            assert!(now >= deadline, "never early");
            worst = worst.max(now - deadline);
        }
        // Informational: precision depends on the machine's load.
        println!("worst lateness {worst:?}");
        wake.set(Some(Instant::now() + Duration::from_secs(3600)));
        wake.set(None);
        let quiet = tokio::time::timeout(Duration::from_millis(20), wake.fired()).await;
        assert!(quiet.is_err(), "a disarmed alarm stays quiet");
    }
}
