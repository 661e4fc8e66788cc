//! Sign-in secrets checked off the async workers (docs/PORTAL.md §Users and roles): an argon2id
//! check takes 19 MiB and tens of milliseconds of a core, and a flood of sign-ins — no
//! credentials needed, from as many addresses as an attacker has — must not take the cores the
//! gateways and operators need. So checks run on `[server] password_checks_at_once` threads of
//! their own, at a lower scheduling priority (nice 10 on Linux: the scheduler gives the
//! workers about nine tenths of a core whenever they want it), with a bounded queue in front:
//! beyond it a sign-in is answered 429 at once instead of waiting behind thousands.

use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};

use tokio::sync::oneshot;

/// Checks waiting per checking thread at most; beyond them a sign-in is refused as busy.
const QUEUE_PER_THREAD: usize = 8;

/// The niceness of the checking threads (0 is the workers'; 19 the lowest priority).
const NICENESS: i32 = 10;

/// A check and where its answer goes.
struct Job {
    secret: String,
    hash: String,
    answer: oneshot::Sender<bool>,
}

/// Too many checks are waiting: the sign-in is refused (429) rather than queued.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("too many sign-ins at once: try again in a moment")]
pub struct Busy;

/// The threads that check secrets and the queue in front of them.
pub struct PasswordChecks {
    jobs: SyncSender<Job>,
}

impl PasswordChecks {
    /// `threads` checking threads (at least one), each with eight checks waiting.
    /// They end when the checker is dropped.
    pub fn start(threads: usize) -> std::io::Result<PasswordChecks> {
        let threads = threads.max(1);
        let (jobs, queue) = sync_channel::<Job>(threads * QUEUE_PER_THREAD);
        let queue = Arc::new(Mutex::new(queue));
        for n in 0..threads {
            let queue = queue.clone();
            std::thread::Builder::new()
                .name(format!("password-check-{n}"))
                .spawn(move || {
                    lower_priority();
                    loop {
                        let job = queue.lock().unwrap_or_else(PoisonError::into_inner).recv();
                        let Ok(job) = job else {
                            return;
                        };
                        // Nobody waits any more (the request was dropped): no check.
                        if job.answer.is_closed() {
                            continue;
                        }
                        let matches = cloud_store::secret_matches(&job.secret, &job.hash);
                        let _ = job.answer.send(matches);
                    }
                })?;
        }
        Ok(PasswordChecks { jobs })
    }

    /// Whether `secret` matches `hash` (a PHC string), or [`Busy`] when the queue is full.
    pub async fn check(&self, secret: &str, hash: String) -> Result<bool, Busy> {
        let (answer, answered) = oneshot::channel();
        let job = Job {
            secret: secret.to_owned(),
            hash,
            answer,
        };
        match self.jobs.try_send(job) {
            Ok(()) => answered.await.map_err(|_| Busy),
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => Err(Busy),
        }
    }
}

/// Run this thread at [`NICENESS`] (Linux: the niceness is a thread's own; elsewhere the
/// threads run at the workers' priority).
fn lower_priority() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: gettid and setpriority take no pointers; they only change this thread's
    // scheduling priority, and a failure (a sandbox refusing it) leaves it as it was.
    unsafe {
        let tid = libc::gettid();
        let _ = libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, NICENESS);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn secrets_are_checked_and_a_full_queue_is_busy() {
        let checks = PasswordChecks::start(1).unwrap();
        let hash = "$argon2id$v=19$m=19456,t=2,p=1$c2FsdHNhbHRzYWx0$Gq0jdYvAhvlVV2dP4sBCr8tP5JG3tCYwmcp/5qASVsI";
        // Not this hash's secret (the check itself is cloud-store's, tested there).
        assert_eq!(checks.check("wrong", hash.into()).await, Ok(false));
        // Far more at once than the queue holds: some are refused at once, none hangs.
        let many = (0..200).map(|_| checks.check("wrong", hash.into()));
        let answers = futures_util::future::join_all(many).await;
        let busy = answers.iter().filter(|a| **a == Err(Busy)).count();
        assert!(busy > 0 && answers.iter().all(|a| *a != Ok(true)), "{busy}");
    }
}
