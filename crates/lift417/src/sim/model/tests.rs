use super::*;

fn lift() -> Lift {
    Lift::new(Params::with_floors(8), Counters::default(), 7)
}

/// (time s, position mm, speed mm/s, acceleration mm/s²).
type Sample = (f64, f64, f64, f64);

/// Run until `done` holds, recording (time, position, speed, acceleration) every step.
fn run_until(
    lift: &mut Lift,
    limit_s: f64,
    mut done: impl FnMut(&Lift, &[Event]) -> bool,
) -> (Vec<Sample>, Vec<Event>) {
    let mut trace = Vec::new();
    let mut events = Vec::new();
    let mut t = 0.0;
    while t < limit_s {
        lift.advance(STEP);
        t += STEP.as_secs_f64();
        while let Some(e) = lift.poll_event() {
            events.push(e);
        }
        trace.push((
            t,
            lift.position_mm(),
            lift.speed_mm_s(),
            lift.acceleration_mm_s2(),
        ));
        if done(lift, &events) {
            return (trace, events);
        }
    }
    panic!(
        "not done after {limit_s} s: events {events:?}, state {:?}",
        lift.state()
    );
}

fn drain(lift: &mut Lift) -> Vec<Event> {
    std::iter::from_fn(|| lift.poll_event()).collect()
}

#[test]
fn a_call_to_floor_4_travels_cycles_the_doors_and_counts_one_trip() {
    let mut lift = lift();
    let p = lift.params().clone();
    lift.call(4, CallKind::Car).unwrap();
    let (trace, events) = run_until(&mut lift, 60.0, |l, _| {
        l.state() == LiftState::Idle && !l.has_calls() && l.counters().door_cycles == 1
    });
    assert_eq!(
        events,
        [
            Event::Departed { floor: 4 },
            Event::Arrived { floor: 4 },
            Event::DoorsOpen,
            Event::DoorsClosed
        ]
    );
    assert_eq!(lift.counters().trips, 1);
    assert_eq!(lift.counters().starts, 1);
    assert_eq!(lift.position_mm(), 11_500.0, "levelled exactly at floor 4");
    assert_eq!(lift.floor(), 4);
    let travel: Vec<_> = trace.iter().take_while(|s| s.1 < 11_500.0).collect();
    // Plausible curves: position never goes back, speed and acceleration stay within the
    // limits, and the top speed is reached on a 10.5 m run.
    for w in travel.windows(2) {
        assert!(w[1].1 >= w[0].1, "position went back at {:?}", w[1]);
        let jerk = (w[1].3 - w[0].3) / STEP.as_secs_f64();
        assert!(jerk.abs() <= p.jerk + 1e-6, "jerk {jerk} at {:?}", w[1]);
    }
    let top = travel.iter().map(|s| s.2).fold(0.0, f64::max);
    let peak_a = travel.iter().map(|s| s.3.abs()).fold(0.0, f64::max);
    assert!(
        top <= p.speed + 1e-9 && top > 0.95 * p.speed,
        "top speed {top}"
    );
    assert!(
        peak_a <= p.acceleration.max(p.deceleration) + 1e-9,
        "peak acceleration {peak_a}"
    );
    let duration = travel.last().unwrap().0;
    // 10.5 m at 1 m/s with 0.6 m/s² and jerk 1 m/s³: about 13–15 s door to door.
    assert!((11.0..18.0).contains(&duration), "travel took {duration} s");
    // The approach is smooth: the last half metre takes more than a second, not a jump.
    let last_half_metre = travel.iter().filter(|s| s.1 > 11_000.0).count();
    assert!(
        last_half_metre > 100,
        "{last_half_metre} steps in the last 0.5 m"
    );
    assert_eq!(lift.speed_mm_s(), 0.0);
    assert_eq!(lift.door(), DoorState::Closed);
}

#[test]
fn calls_are_served_in_travel_direction() {
    let mut lift = lift();
    lift.call(6, CallKind::Car).unwrap();
    lift.advance(Duration::from_secs(2));
    // While going up: a car call at 3 and a hall call down at 2 come in.
    lift.call(3, CallKind::Car).unwrap();
    lift.call(2, CallKind::HallDown).unwrap();
    lift.call(5, CallKind::HallUp).unwrap();
    let mut arrivals = Vec::new();
    run_until(&mut lift, 200.0, |l, events| {
        arrivals = events
            .iter()
            .filter_map(|e| match e {
                Event::Arrived { floor } => Some(*floor),
                _ => None,
            })
            .collect();
        !l.has_calls() && l.state() == LiftState::Idle
    });
    assert_eq!(
        arrivals,
        [3, 5, 6, 2],
        "up-collective first, then the down call"
    );
    assert_eq!(lift.counters().trips, 4);
}

#[test]
fn refuses_floors_and_directions_that_do_not_exist() {
    let mut lift = lift();
    assert_eq!(lift.call(9, CallKind::Car), Err(CallError::NoSuchFloor(9)));
    assert_eq!(lift.call(0, CallKind::Car), Err(CallError::NoSuchFloor(0)));
    assert_eq!(
        lift.call(8, CallKind::HallUp),
        Err(CallError::NoDirection(8))
    );
    assert_eq!(
        lift.call(1, CallKind::HallDown),
        Err(CallError::NoDirection(1))
    );
}

#[test]
fn a_drive_fault_makes_a_fast_stop_and_the_car_resumes_after_repair() {
    let mut lift = lift();
    lift.call(8, CallKind::Car).unwrap();
    lift.advance(Duration::from_secs(5));
    assert_eq!(drain(&mut lift), [Event::Departed { floor: 8 }]);
    assert_eq!(lift.state(), LiftState::Up);
    lift.inject(Fault::DriveFault.bit());
    let (_, events) = run_until(&mut lift, 10.0, |l, _| l.speed_mm_s() == 0.0);
    assert_eq!(events, [Event::FaultRaised(Fault::DriveFault)]);
    assert_eq!(lift.state(), LiftState::OutOfService);
    let stopped_at = lift.position_mm();
    assert!(stopped_at > 1000.0 && stopped_at < 25_500.0);
    lift.advance(Duration::from_secs(5));
    assert_eq!(lift.position_mm(), stopped_at, "stands while faulty");
    assert_eq!(lift.counters().faults, [0, 0, 1, 1]);
    assert_eq!(lift.counters().last_fault.map(|f| f.0), Some(0xF001));
    lift.inject(0);
    let (_, events) = run_until(&mut lift, 60.0, |l, _| l.counters().trips == 1);
    assert_eq!(
        events,
        [
            Event::FaultCleared(Fault::DriveFault),
            Event::Arrived { floor: 8 }
        ]
    );
}

#[test]
fn a_blocked_door_reopens_then_raises_a_fault_until_freed() {
    let mut lift = lift();
    lift.call(2, CallKind::Car).unwrap();
    run_until(&mut lift, 60.0, |l, _| l.door() == DoorState::Open);
    lift.inject(Fault::DoorBlocked.bit());
    assert!(lift.light_barrier());
    let (_, events) = run_until(&mut lift, 120.0, |_, e| {
        e.contains(&Event::FaultRaised(Fault::DoorBlocked))
    });
    assert!(!events.contains(&Event::DoorsClosed));
    assert_eq!(lift.counters().reopenings, 3);
    assert_eq!(lift.door_statusword() >> 12, 0xE, "error indicator");
    assert_eq!(lift.state(), LiftState::OutOfService);
    lift.advance(Duration::from_secs(30));
    assert_eq!(drain(&mut lift), [Event::DoorsOpen], "reopened once more");
    assert_eq!(lift.door(), DoorState::Open, "stays open while blocked");
    lift.inject(0);
    let (_, events) = run_until(&mut lift, 30.0, |l, _| l.door() == DoorState::Closed);
    assert_eq!(
        events,
        [Event::FaultCleared(Fault::DoorBlocked), Event::DoorsClosed]
    );
    assert_eq!(
        lift.door_statusword(),
        0x0001,
        "closed, safety contact made"
    );
}

#[test]
fn an_overloaded_car_keeps_its_doors_open_and_does_not_leave() {
    let mut lift = lift();
    lift.call(2, CallKind::Car).unwrap();
    run_until(&mut lift, 60.0, |l, _| l.door() == DoorState::Open);
    lift.inject(Fault::Overload.bit());
    lift.call(5, CallKind::Car).unwrap();
    lift.advance(Duration::from_secs(30));
    assert_eq!(lift.door(), DoorState::Open);
    assert_eq!(lift.floor(), 2);
    assert!(lift.load_kg() > lift.params().overload_kg);
    assert_eq!(lift.faults().collect::<Vec<_>>(), [Fault::Overload]);
    lift.inject(0);
    run_until(&mut lift, 60.0, |l, _| l.counters().trips == 2);
    assert_eq!(lift.floor(), 5);
    assert!(lift.load_kg() <= lift.params().full_kg);
}

#[test]
fn parks_after_the_parking_time() {
    let mut params = Params::with_floors(4);
    params.parking = Some((20.0, 3));
    let mut lift = Lift::new(params, Counters::default(), 1);
    lift.advance(Duration::from_secs(19));
    assert_eq!(lift.counters().starts, 0);
    run_until(&mut lift, 60.0, |l, _| l.counters().trips == 1);
    assert_eq!(lift.floor(), 3);
}

#[test]
fn counters_continue_from_where_they_were() {
    let counters = Counters {
        trips: 2510,
        operating_s: 3600.0 * 12.0,
        ..Counters::default()
    };
    let mut lift = Lift::new(Params::with_floors(8), counters, 3);
    lift.call(3, CallKind::HallUp).unwrap();
    run_until(&mut lift, 60.0, |l, _| l.counters().door_cycles == 1);
    assert_eq!(lift.counters().trips, 2511);
    assert!(lift.counters().operating_s > 3600.0 * 12.0);
    assert!((lift.counters().distance_mm - 7000.0).abs() < 1.0);
}

/// Serve a car call to the floor above or below and return the door's closing time; none when
/// a fault stopped the lift first.
fn one_closing(lift: &mut Lift) -> Option<u32> {
    let floor = if lift.floor() == 1 { 2 } else { 1 };
    let cycles = lift.counters().door_cycles;
    lift.call(floor, CallKind::Car).unwrap();
    run_until(lift, 120.0, |l, _| {
        l.counters().door_cycles > cycles || l.faults().next().is_some()
    });
    (lift.counters().door_cycles > cycles).then(|| lift.door_timing().last_ms())
}

#[test]
fn a_sound_door_closes_in_its_nominal_time() {
    let mut lift = lift();
    for _ in 0..5 {
        let ms = one_closing(&mut lift).unwrap();
        assert!((2490..=2510).contains(&ms), "{ms} ms");
    }
    assert!((2490..=2510).contains(&lift.door_timing().mean_ms()));
    assert!(lift.faults().next().is_none());
}

#[test]
fn a_wearing_door_closes_ever_more_slowly_until_its_supervision_calls_it_blocked() {
    let mut lift = lift();
    // 400 %/h: a closing takes 1 % longer every 9 s of simulated time.
    lift.set_door_wear(400.0);
    let first = one_closing(&mut lift).unwrap();
    let mut last = first;
    let mut closings = 1;
    while let Some(ms) = one_closing(&mut lift) {
        assert!(ms > last, "{ms} ms after {last} ms");
        last = ms;
        closings += 1;
        assert!(closings < 100, "never blocked");
    }
    assert!(last > first * 3 / 2, "{first} → {last} ms before the fault");
    assert_eq!(lift.faults().collect::<Vec<_>>(), [Fault::DoorBlocked]);
    assert!(lift.closing_factor() > CLOSING_LIMIT);
    assert_eq!(lift.state(), LiftState::OutOfService);
}

#[test]
fn fire_service_recalls_the_car_and_refuses_calls_until_it_ends() {
    let mut lift = lift();
    lift.call(6, CallKind::Car).unwrap();
    lift.call(3, CallKind::HallUp).unwrap();
    lift.advance(Duration::from_secs(2));
    lift.inject(FIRE_SERVICE);
    assert_eq!(lift.state(), LiftState::FireService);
    assert!(matches!(
        lift.call(5, CallKind::Car),
        Err(CallError::SpecialOperation("fire service"))
    ));
    // The travel under way ends at its floor; the passengers' calls are gone, and the car
    // comes back to the lowest floor and opens there.
    let (_, events) = run_until(&mut lift, 120.0, |l, events| {
        l.floor() == 1 && events.contains(&Event::DoorsOpen) && !l.has_calls()
    });
    assert!(events.contains(&Event::Arrived { floor: 1 }), "{events:?}");
    assert!(!events.contains(&Event::Arrived { floor: 6 }), "{events:?}");
    lift.advance(Duration::from_secs(60));
    assert_eq!((lift.floor(), lift.state()), (1, LiftState::FireService));
    // Back to normal: calls are taken again.
    lift.inject(0);
    lift.call(4, CallKind::Car).unwrap();
    run_until(&mut lift, 60.0, |l, _| l.floor() == 4);
}

#[test]
fn inspection_stops_taking_calls_and_faults_still_come_first() {
    let mut lift = lift();
    lift.inject(INSPECTION);
    assert_eq!(lift.state(), LiftState::Inspection);
    assert!(matches!(
        lift.call(2, CallKind::HallUp),
        Err(CallError::SpecialOperation("inspection"))
    ));
    lift.advance(Duration::from_secs(30));
    assert_eq!(lift.floor(), 1);
    lift.inject(INSPECTION | Fault::DriveFault.bit());
    lift.advance(Duration::from_secs(1));
    assert_eq!(lift.state(), LiftState::OutOfService);
}
