//! Memory handed back to the system after bursts of connections.
//!
//! A reconnect storm's handshakes, upgrades and admissions free their memory between the
//! long-lived allocations of the connections that stay, and glibc's allocator neither reuses
//! those holes for them nor returns them: after a burst of 18,000 gateways the portal held about
//! 1 KiB per connection more than the same gateways added a few at a time (docs/BENCHMARKS.md
//! §Where an idle gateway connection's memory goes). Once a burst is over — many connections
//! opened or gone since the last trim, few in the last look — the portal asks the allocator to
//! give its free pages back (`malloc_trim`). "Few" is relative: a large fleet always has some
//! gateways reconnecting, and that steady churn must not keep a storm's memory from being given
//! back; on its own, it leads to a trim at most every 16 looks.

use std::time::Duration;

/// How often the portal looks at its connections.
pub(crate) const INTERVAL: Duration = Duration::from_secs(5);

/// Connections opened or gone since the last trim that make a burst worth trimming after.
const BURST: u64 = 256;

/// At most this many in the last look, or a sixteenth of those since the last trim: the burst
/// is over.
const QUIET: u64 = 32;

/// Whether the allocator can be asked to give memory back here (glibc only).
pub(crate) const SUPPORTED: bool = cfg!(all(target_os = "linux", target_env = "gnu"));

/// When to trim (sans-IO): fed every [`INTERVAL`] with the connections opened so far and the
/// gateways online now.
#[derive(Debug, Default)]
pub(crate) struct Bursts {
    last: Option<(u64, usize)>,
    since_trim: u64,
}

impl Bursts {
    /// One look; true when the portal should trim now.
    pub(crate) fn look(&mut self, opened: u64, online: usize) -> bool {
        // A gateway that reconnects opens one connection and leaves the online count alone; one
        // that goes (an outage on its side) only moves the count: both are churn.
        let churn = self.last.replace((opened, online)).map_or(0, |(o, n)| {
            opened.saturating_sub(o) + online.abs_diff(n) as u64
        });
        self.since_trim += churn;
        let trim = self.since_trim >= BURST && churn <= QUIET.max(self.since_trim / 16);
        if trim {
            self.since_trim = 0;
        }
        trim
    }
}

/// Give the allocator's free pages back; the bytes the process's resident set fell by (`None`
/// where the allocator cannot be asked or the resident set cannot be read). Blocks for a few
/// milliseconds with a large heap: call it off the async workers.
pub(crate) fn trim() -> Option<u64> {
    if !SUPPORTED {
        return None;
    }
    let before = resident_bytes()?;
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` takes no pointers; it walks glibc's own arenas under their locks.
    unsafe {
        libc::malloc_trim(0);
    }
    Some(before.saturating_sub(resident_bytes()?))
}

/// The process's resident set (`VmRSS` of /proc/self/status).
fn resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trims_once_after_a_burst_is_over() {
        let mut bursts = Bursts::default();
        assert!(!bursts.look(0, 0), "the first look has nothing to compare");
        assert!(!bursts.look(2_000, 1_500), "during the burst");
        assert!(!bursts.look(4_000, 3_900), "still coming");
        assert!(
            bursts.look(4_010, 3_995),
            "over: 10 opened and 95 came online, few beside 7,900"
        );
        assert!(!bursts.look(4_015, 4_000), "trimmed already");
        assert!(!bursts.look(4_025, 4_000), "quiet");
    }

    #[test]
    fn outages_and_storms_amid_steady_churn_are_trimmed_after() {
        // (connections opened so far, gateways online) before, during and after the burst.
        let cases = [
            (
                "an outage takes 4,000",
                [(10_000, 10_000), (10_000, 6_000), (10_000, 6_000)],
            ),
            (
                "10,000 reconnect at once, then 100 a look as before: more than 32, few beside \
                 10,000",
                [(0, 10_000), (10_000, 10_000), (10_100, 10_000)],
            ),
        ];
        for (what, looks) in cases {
            let mut bursts = Bursts::default();
            let trims = looks.map(|(opened, online)| bursts.look(opened, online));
            assert_eq!(trims, [false, false, true], "{what}");
        }
    }

    #[test]
    fn steady_churn_trims_once_every_sixteen_looks() {
        let mut bursts = Bursts::default();
        bursts.look(0, 5_000);
        let trims: Vec<u64> = (1..=64)
            .filter(|look| bursts.look(look * 40, 5_000))
            .collect();
        // 40 reconnects a look are few once 640 have come since the last trim.
        assert_eq!(trims, [16, 32, 48, 64]);
    }

    #[test]
    fn small_churn_adds_up_to_a_trim_once_quiet() {
        let mut bursts = Bursts::default();
        bursts.look(0, 0);
        for i in 1..=8 {
            // 30 each time: quiet, but the total since the last trim reaches the burst.
            assert_eq!(bursts.look(i * 30, 0), i * 30 >= BURST, "look {i}");
        }
    }

    #[test]
    fn trimming_reports_what_it_gave_back() {
        if !SUPPORTED {
            eprintln!("skipped: the allocator here cannot be asked to give memory back");
            return;
        }
        // Many small blocks freed between a few that stay: the holes a burst leaves.
        let mut kept = Vec::new();
        let mut freed = Vec::new();
        for i in 0..200_000 {
            let block = vec![i as u8; 200];
            if i % 64 == 0 {
                kept.push(block);
            } else {
                freed.push(block);
            }
        }
        drop(freed);
        let gave = trim().expect("glibc on Linux trims and /proc reads");
        assert!(gave > 1 << 20, "gave back {gave} bytes of ~39 MB freed");
        assert_eq!(kept.len(), 3_125);
    }
}
