//! What one portal process knows of the others (docs/CLUSTER.md §Holder entries): the lifts
//! they hold, as their entries in the bucket say, and which of them live, as their leases say.
//! Sans-IO: fed the bucket's entries and the time, it answers who holds a lift and which
//! entries are left of processes that died. An entry is written when a connection is admitted
//! (and when the lift's status changes), never refreshed: it stands while its process's lease
//! is fresh and names the entry's incarnation.

use std::collections::{BTreeSet, HashMap};
use std::time::{Duration, Instant};

use crate::msgs::HolderEntry;

/// A lift another process holds, by its entry.
#[derive(Debug, Clone)]
struct Held {
    entry: HolderEntry,
    /// The entry's revision in the bucket (a sweep deletes only that one).
    revision: u64,
    /// The watch that last delivered it ([`Holders::rewatch`]).
    watch: u64,
    /// Handed to a sweep already: not again.
    swept: bool,
}

/// A process's lease as last written.
#[derive(Debug, Clone, Copy)]
struct Lease {
    incarnation: u64,
    written: Instant,
    watch: u64,
}

impl Lease {
    /// Whether the lease stands at `now`: written less than `ttl` before.
    fn fresh(&self, now: Instant, ttl: Duration) -> bool {
        now.saturating_duration_since(self.written) < ttl
    }
}

/// Whether the process that wrote `entry` lives, by `leases`: its lease is fresh and of the
/// same incarnation.
fn lives(
    leases: &HashMap<String, Lease>,
    entry: &HolderEntry,
    now: Instant,
    ttl: Duration,
) -> bool {
    leases
        .get(&entry.node)
        .is_some_and(|l| l.incarnation == entry.incarnation && l.fresh(now, ttl))
}

/// This process's view of the other processes and the lifts they hold.
#[derive(Debug)]
pub(crate) struct Holders {
    /// This process's node name: its own entries and lease are not kept here.
    node: String,
    /// How long a lease stands unrenewed (`[cluster] holder_ttl_s`).
    ttl: Duration,
    lifts: HashMap<String, Held>,
    leases: HashMap<String, Lease>,
    /// The current watch of the bucket (counted from 1), since when it runs, and whether it
    /// has delivered what the bucket held when it began.
    watch: u64,
    watching_since: Instant,
    caught_up: bool,
}

impl Holders {
    /// An empty view for process `node` whose leases last `ttl`.
    pub(crate) fn new(node: &str, ttl: Duration, now: Instant) -> Holders {
        Holders {
            node: node.to_owned(),
            ttl,
            lifts: HashMap::new(),
            leases: HashMap::new(),
            watch: 0,
            watching_since: now,
            caught_up: false,
        }
    }

    fn alive(&self, entry: &HolderEntry, now: Instant) -> bool {
        lives(&self.leases, entry, now, self.ttl)
    }

    /// The entry of `lift` when another process holds it and lives.
    pub(crate) fn holder(&self, lift: &str, now: Instant) -> Option<&HolderEntry> {
        self.lifts
            .get(lift)
            .map(|e| &e.entry)
            .filter(|h| self.alive(h, now))
    }

    /// How many lifts living processes other than this one hold.
    pub(crate) fn held_elsewhere(&self, now: Instant) -> usize {
        self.lifts
            .values()
            .filter(|e| self.alive(&e.entry, now))
            .count()
    }

    /// How many other processes live.
    pub(crate) fn others_alive(&self, now: Instant) -> usize {
        self.leases
            .values()
            .filter(|l| l.fresh(now, self.ttl))
            .count()
    }

    /// Another process's entry of `lift` at `revision`; returns the one it replaces.
    pub(crate) fn put(
        &mut self,
        lift: &str,
        entry: HolderEntry,
        revision: u64,
    ) -> Option<HolderEntry> {
        let entry = Held {
            entry,
            revision,
            watch: self.watch,
            swept: false,
        };
        self.lifts.insert(lift.to_owned(), entry).map(|e| e.entry)
    }

    /// The entry of `lift` was deleted (or is this process's own).
    pub(crate) fn remove(&mut self, lift: &str) {
        self.lifts.remove(lift);
    }

    /// `node` renewed its lease for `incarnation`; `written` is when (by the entry's age).
    pub(crate) fn lease(&mut self, node: &str, incarnation: u64, written: Instant) {
        if node == self.node {
            return;
        }
        // A lease read from the bucket ([`Holders::suspects`]) may be newer than what a
        // lagging watch delivers after it.
        let written = match self.leases.get(node) {
            Some(known) if known.incarnation == incarnation => written.max(known.written),
            _ => written,
        };
        let lease = Lease {
            incarnation,
            written,
            watch: self.watch,
        };
        self.leases.insert(node.to_owned(), lease);
    }

    /// A new watch of the bucket begins (after NATS was lost, or the watch broke): what it
    /// delivers replaces what the last one did, once it has delivered all ([`Holders::caught_up`]).
    pub(crate) fn rewatch(&mut self, now: Instant) {
        self.watch += 1;
        self.watching_since = now;
        self.caught_up = false;
    }

    /// The new watch delivered every entry the bucket had: forget the ones it did not (deleted,
    /// or lost with a NATS server that restarted, while this process was not watching).
    pub(crate) fn caught_up(&mut self) {
        let watch = self.watch;
        self.caught_up = true;
        self.lifts.retain(|_, e| e.watch == watch);
        self.leases.retain(|_, l| l.watch == watch);
    }

    /// The processes (name and incarnation) whose entries look left behind to this view (lease
    /// lapsed, or the process started again as another incarnation) — when this process is the
    /// one that sweeps: the first by name of those alive, so that one process deletes them, not
    /// all. Nothing until the watch has delivered the bucket's contents and run for a lease's
    /// time (a lease not yet delivered, or not yet renewed since, is not a lapsed one). A view
    /// can lag the bucket (a watch behind a burst of entries): the suspects' leases are read
    /// from the bucket itself ([`Holders::lease`]) before [`Holders::sweep`] believes it.
    pub(crate) fn suspects(&self, now: Instant) -> Vec<(String, u64)> {
        if !self.caught_up || now.saturating_duration_since(self.watching_since) < self.ttl {
            return Vec::new();
        }
        let sweeper = self
            .leases
            .iter()
            .filter(|(_, l)| l.fresh(now, self.ttl))
            .all(|(other, _)| *other > self.node);
        if !sweeper {
            return Vec::new();
        }
        let suspects: BTreeSet<(&str, u64)> = self
            .lifts
            .values()
            .filter(|e| !e.swept && !self.alive(&e.entry, now))
            .map(|e| (e.entry.node.as_str(), e.entry.incarnation))
            .collect();
        suspects
            .into_iter()
            .map(|(node, incarnation)| (node.to_owned(), incarnation))
            .collect()
    }

    /// The entries of `checked` processes (suspects whose leases were read from the bucket
    /// since) that are still left behind, each once, to be deleted at their revision.
    pub(crate) fn sweep(&mut self, now: Instant, checked: &[(String, u64)]) -> Vec<(String, u64)> {
        let Holders {
            ttl, lifts, leases, ..
        } = self;
        let mut dead = Vec::new();
        for (lift, entry) in lifts {
            let of = &entry.entry;
            let checked = checked
                .iter()
                .any(|(node, incarnation)| *node == of.node && *incarnation == of.incarnation);
            if !entry.swept && checked && !lives(leases, of, now, *ttl) {
                entry.swept = true;
                dead.push((lift.clone(), entry.revision));
            }
        }
        dead
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TTL: Duration = Duration::from_secs(15);

    fn written(node: &str, incarnation: u64, epoch: u64) -> HolderEntry {
        HolderEntry {
            node: node.into(),
            incarnation,
            epoch,
            domain: "D".into(),
            sernum: "S".into(),
            error_register: None,
            lift_state: None,
        }
    }

    /// A view of `p1` watching since `t0`, which knows `p2` (incarnation 7) alive at `t0`.
    fn holders(t0: Instant) -> Holders {
        let mut holders = Holders::new("p1", TTL, t0);
        holders.rewatch(t0);
        holders.lease("p2", 7, t0);
        holders.caught_up();
        holders
    }

    #[test]
    fn a_lift_is_held_while_its_process_renews_its_lease() {
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let mut holders = holders(t0);
        holders.put("L", written("p2", 7, 1), 1);
        assert_eq!(holders.holder("L", at(14)).map(|h| h.epoch), Some(1));
        assert_eq!(holders.held_elsewhere(at(14)), 1);
        assert!(holders.holder("L", at(15)).is_none(), "the lease lapsed");
        assert_eq!(holders.held_elsewhere(at(15)), 0);
        assert_eq!(holders.others_alive(at(15)), 0);
        holders.lease("p2", 7, at(16));
        assert!(
            holders.holder("L", at(16)).is_some(),
            "renewed late: held again"
        );
        holders.remove("L");
        assert!(holders.holder("L", at(16)).is_none());
    }

    #[test]
    fn a_process_started_again_holds_none_of_its_earlier_lifts() {
        let t0 = Instant::now();
        let mut holders = holders(t0);
        holders.put("old", written("p2", 7, 1), 1);
        holders.lease("p2", 8, t0);
        assert!(holders.holder("old", t0).is_none());
        holders.put("new", written("p2", 8, 2), 2);
        assert!(holders.holder("new", t0).is_some());
        assert_eq!(holders.others_alive(t0), 1);
    }

    #[test]
    fn a_lift_without_a_lease_seen_is_not_held() {
        let t0 = Instant::now();
        let mut holders = holders(t0);
        holders.put("L", written("p3", 1, 1), 1);
        assert!(holders.holder("L", t0).is_none());
        holders.lease("p1", 1, t0);
        assert_eq!(holders.others_alive(t0), 1, "its own lease is not kept");
    }

    /// A sweep whose suspects' leases, read from the bucket, are as the view has them.
    fn swept(holders: &mut Holders, now: Instant) -> Vec<(String, u64)> {
        let suspects = holders.suspects(now);
        holders.sweep(now, &suspects)
    }

    #[test]
    fn a_view_behind_the_bucket_does_not_sweep_a_living_process() {
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let mut holders = holders(t0);
        holders.put("a", written("p2", 7, 1), 11);
        // The watch has not delivered p2's renewals: its lease looks lapsed here.
        assert_eq!(holders.suspects(at(20)), vec![("p2".into(), 7)]);
        // The bucket has p2's lease of 5 s ago: alive, nothing swept, nothing marked.
        holders.lease("p2", 7, at(15));
        assert!(holders.sweep(at(20), &[("p2".into(), 7)]).is_empty());
        assert!(holders.holder("a", at(20)).is_some());
        // The watch delivers an older renewal late: the newer one stands.
        holders.lease("p2", 7, at(3));
        assert!(holders.suspects(at(25)).is_empty());
        // Only suspects whose leases were read are swept.
        assert!(holders.sweep(at(40), &[]).is_empty());
        assert_eq!(
            holders.sweep(at(40), &[("p2".into(), 7)]),
            vec![("a".into(), 11)]
        );
    }

    #[test]
    fn the_first_living_process_by_name_sweeps_the_dead_ones_entries_once() {
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let mut holders = holders(t0);
        holders.lease("p0", 1, t0);
        holders.put("a", written("p2", 7, 1), 11);
        holders.put("b", written("p3", 1, 1), 12);
        holders.put("c", written("p0", 1, 1), 13);
        assert!(
            swept(&mut holders, at(10)).is_empty(),
            "not before a lease's time"
        );
        // p0 lives and comes first: it sweeps, not p1.
        holders.lease("p0", 1, at(14));
        assert!(swept(&mut holders, at(16)).is_empty());
        // p0's lease lapsed too: p1 is the first alive, and p2 and p3 are dead.
        let mut dead = swept(&mut holders, at(30));
        dead.sort();
        assert_eq!(
            dead,
            vec![("a".into(), 11), ("b".into(), 12), ("c".into(), 13)]
        );
        assert!(swept(&mut holders, at(31)).is_empty(), "each once");
        holders.put("a", written("p2", 7, 1), 14);
        assert_eq!(
            swept(&mut holders, at(32)),
            vec![("a".into(), 14)],
            "written again"
        );
        // A new watch sweeps nothing before it has caught up and run for a lease's time.
        holders.rewatch(at(40));
        holders.put("d", written("p2", 7, 1), 15);
        assert!(swept(&mut holders, at(60)).is_empty(), "not caught up");
        holders.caught_up();
        assert!(swept(&mut holders, at(50)).is_empty(), "not a lease's time");
        assert_eq!(swept(&mut holders, at(60)), vec![("d".into(), 15)]);
    }

    #[test]
    fn a_new_watch_replaces_what_the_last_one_delivered_once_caught_up() {
        let t0 = Instant::now();
        let mut holders = holders(t0);
        holders.put("gone", written("p2", 7, 1), 1);
        holders.put("kept", written("p2", 7, 2), 2);
        holders.rewatch(t0);
        assert!(
            holders.holder("gone", t0).is_some(),
            "served until caught up"
        );
        holders.lease("p2", 7, t0);
        holders.put("kept", written("p2", 7, 2), 2);
        holders.caught_up();
        assert!(holders.holder("gone", t0).is_none());
        assert!(
            holders.put("gone", written("p2", 7, 1), 3).is_none(),
            "forgotten"
        );
        holders.remove("gone");
        assert!(holders.holder("kept", t0).is_some());
        holders.rewatch(t0);
        holders.put("kept", written("p2", 7, 2), 2);
        holders.caught_up();
        assert!(
            holders.holder("kept", t0).is_none(),
            "p2's lease was not delivered again"
        );
    }
}
