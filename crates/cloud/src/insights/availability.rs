//! A lift's availability and fault figures over a period, sans-IO (docs/PORTAL.md
//! §Availability): its status timeline integrated with the period's edges cut, its faults,
//! and its counters' increase.

use std::collections::BTreeMap;

use cloud_store::{Edges, Timeline};
use cloud_types::insights::{LiftFigures, Status};

/// How much a counter rose over a period; a counter that went down was reset (a new
/// controller, a cleared memory) and counted again from zero. None unless both ends are known.
pub fn increase(edges: Edges) -> Option<u64> {
    let (start, end) = (edges.start?, edges.end?);
    let rise = if end >= start { end - start } else { end };
    Some(rise.max(0.0).round() as u64)
}

/// The counters a report reads.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Counters {
    /// Trips.
    pub trips: Edges,
    /// Door cycles.
    pub door_cycles: Edges,
    /// Reopenings.
    pub reopenings: Edges,
}

/// Time per status and out-of-service episodes over a period.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Integrated {
    /// Milliseconds per status, in the order of [`Status::ALL`].
    pub ms: [i64; 4],
    /// Out-of-service episodes that overlap the period.
    pub outages: u64,
    /// Those of them that began inside it (failures).
    pub failures: u64,
}

impl Integrated {
    /// Milliseconds in `status`.
    pub fn of(&self, status: Status) -> i64 {
        self.ms[status as usize]
    }

    /// The availability of this time.
    pub fn availability(&self) -> Option<f64> {
        share(
            self.of(Status::InService) as f64,
            self.of(Status::OutOfService) as f64,
        )
    }
}

/// Availability: time in service over in and out of service (offline and unknown count
/// neither way); none when neither was seen.
pub fn share(in_service: f64, out_of_service: f64) -> Option<f64> {
    let seen = in_service + out_of_service;
    (seen > 0.0).then(|| in_service / seen)
}

/// `timeline` from `from` to `to` (ms) as consecutive spans of one status each (start, end,
/// status): before the first status known the lift is unknown; each status lasts until the
/// next change to another; the period's edges cut the first and the last span.
pub fn spans(timeline: &Timeline, from: i64, to: i64) -> Vec<(i64, i64, Status)> {
    let mut out = Vec::new();
    if to <= from {
        return out;
    }
    let mut status = timeline.before.unwrap_or(Status::Unknown);
    let mut since = from;
    for &(at, next) in &timeline.changes {
        let at = at.clamp(from, to);
        if next == status {
            continue;
        }
        if at > since {
            out.push((since, at, status));
        }
        status = next;
        since = at;
    }
    out.push((since, to, status));
    out
}

/// Time per status and out-of-service episodes of `timeline` from `from` to `to` (ms): every
/// out-of-service span is an episode (an outage), a failure when it began after `from`.
pub fn integrate(timeline: &Timeline, from: i64, to: i64) -> Integrated {
    let mut out = Integrated::default();
    for (start, end, status) in spans(timeline, from, to) {
        out.ms[status as usize] += end - start;
        if status == Status::OutOfService {
            out.outages += 1;
            out.failures += u64::from(start > from);
        }
    }
    out
}

/// The figures of `lift` over `from`…`to`.
pub fn figures(
    lift: &str,
    from: i64,
    to: i64,
    timeline: &Timeline,
    faults_by_kind: BTreeMap<String, u64>,
    counters: Counters,
) -> LiftFigures {
    let time = integrate(timeline, from, to);
    let seconds = |status| time.of(status) as f64 / 1000.0;
    let (up, down) = (seconds(Status::InService), seconds(Status::OutOfService));
    let faults = faults_by_kind.values().sum();
    let trips = increase(counters.trips);
    let per = |total: f64, n: u64| (n > 0).then(|| total / n as f64);
    LiftFigures {
        lift: lift.to_owned(),
        availability: share(up, down),
        in_service_s: up,
        out_of_service_s: down,
        offline_s: seconds(Status::Offline),
        unknown_s: seconds(Status::Unknown),
        faults,
        faults_by_kind,
        trips,
        faults_per_1000_trips: trips
            .filter(|t| *t > 0)
            .map(|t| faults as f64 * 1000.0 / t as f64),
        mtbf_s: per(up, time.failures),
        mttr_s: per(down, time.outages),
        door_cycles: increase(counters.door_cycles),
        reopenings: increase(counters.reopenings),
    }
}

/// The availability of several lifts together: their seconds in service over in and out of
/// service (none when neither was seen).
pub fn combined<'a>(lifts: impl IntoIterator<Item = &'a LiftFigures>) -> Option<f64> {
    let (up, down) = lifts.into_iter().fold((0.0, 0.0), |(u, d), l| {
        (u + l.in_service_s, d + l.out_of_service_s)
    });
    share(up, down)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use Status::*;

    const H: i64 = 3_600_000;

    fn timeline(before: Option<Status>, changes: &[(i64, Status)]) -> Timeline {
        Timeline {
            before,
            changes: changes.to_vec(),
        }
    }

    #[test]
    fn a_day_with_an_outage_and_a_gateway_outage_adds_up_by_hand() {
        // 0–2 h unknown (nothing known), 2–10 h in service, 10–11.5 h out of service,
        // 11.5–20 h in service, 20–21 h offline, 21–22 h unknown, 22–24 h in service.
        let t = timeline(
            None,
            &[
                (2 * H, InService),
                (10 * H, OutOfService),
                (23 * H / 2, InService),
                (20 * H, Offline),
                (21 * H, Unknown),
                (22 * H, InService),
            ],
        );
        let mut faults = BTreeMap::new();
        faults.insert("0xFF01".to_owned(), 2);
        let counters = Counters {
            trips: Edges {
                start: Some(1000.0),
                end: Some(1400.0),
            },
            door_cycles: Edges {
                start: Some(10.0),
                end: Some(3.0),
            },
            reopenings: Edges {
                start: None,
                end: Some(3.0),
            },
        };
        let f = figures("L", 0, 24 * H, &t, faults, counters);
        assert_eq!(f.in_service_s, (8.0 + 8.5 + 2.0) * 3600.0);
        assert_eq!(f.out_of_service_s, 1.5 * 3600.0);
        assert_eq!(f.offline_s, 3600.0);
        assert_eq!(f.unknown_s, 3.0 * 3600.0);
        assert_eq!(f.availability, Some(18.5 / 20.0));
        assert_eq!(f.faults, 2);
        assert_eq!(f.trips, Some(400));
        assert_eq!(f.faults_per_1000_trips, Some(5.0));
        assert_eq!(f.mtbf_s, Some(18.5 * 3600.0));
        assert_eq!(f.mttr_s, Some(1.5 * 3600.0));
        assert_eq!(f.door_cycles, Some(3), "a counter that went down was reset");
        assert_eq!(f.reopenings, None);
    }

    #[test]
    fn the_edges_cut_what_began_before_and_what_goes_on_after() {
        // Out of service since before the period, back at 1 h, out again at 3 h until after.
        let t = timeline(Some(OutOfService), &[(H, InService), (3 * H, OutOfService)]);
        let f = figures("L", 0, 4 * H, &t, BTreeMap::new(), Counters::default());
        assert_eq!(f.out_of_service_s, 2.0 * 3600.0);
        assert_eq!(f.in_service_s, 2.0 * 3600.0);
        assert_eq!(f.mttr_s, Some(3600.0), "two episodes overlap the period");
        assert_eq!(f.mtbf_s, Some(2.0 * 3600.0), "one began in it");
        assert_eq!(f.faults_per_1000_trips, None);
        let nothing = figures(
            "L",
            0,
            H,
            &Timeline::default(),
            BTreeMap::new(),
            Counters::default(),
        );
        assert_eq!((nothing.unknown_s, nothing.availability), (3600.0, None));
        assert_eq!((nothing.mtbf_s, nothing.mttr_s), (None, None));
    }

    #[test]
    fn repeated_statuses_are_one_episode() {
        let t = timeline(
            Some(InService),
            &[(H, OutOfService), (2 * H, OutOfService), (3 * H, InService)],
        );
        let time = integrate(&t, 0, 4 * H);
        assert_eq!((time.outages, time.failures), (1, 1));
        assert_eq!(time.of(OutOfService), 2 * H);
    }

    fn status() -> impl Strategy<Value = Status> {
        prop::sample::select(Status::ALL.to_vec())
    }

    proptest! {
        #[test]
        fn every_moment_counts_once(
            before in prop::option::of(status()),
            mut changes in prop::collection::vec((0i64..100_000, status()), 0..20),
            from in 0i64..50_000,
            len in 0i64..60_000,
        ) {
            changes.sort_by_key(|c| c.0);
            let changes: Vec<_> = changes.into_iter().filter(|c| c.0 > from && c.0 < from + len).collect();
            let time = integrate(&timeline(before, &changes), from, from + len);
            prop_assert_eq!(time.ms.iter().sum::<i64>(), len.max(0));
            prop_assert!(time.failures <= time.outages);
            prop_assert!(time.ms.iter().all(|ms| *ms >= 0));
        }
    }
}
