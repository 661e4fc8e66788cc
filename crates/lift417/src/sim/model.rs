//! The simulated lift itself, sans-IO: calls, a collective-selective dispatcher, a jerk-limited
//! drive, the door sequence with light barrier, load, faults and counters. It knows nothing of
//! CANopen or clocks: [`Lift::advance`] moves it on by simulated time and [`Lift::poll_event`]
//! says what happened, so tests run whole journeys in microseconds.

use std::collections::{BTreeSet, VecDeque};
use std::time::Duration;

/// The simulation step: every [`Lift::advance`] is cut into steps of at most this.
pub const STEP: Duration = Duration::from_millis(10);

/// Door open/close time (s) and stroke (mm) of the simulated car door.
const DOOR_TIME_S: f64 = 2.5;
const DOOR_WIDTH_MM: f64 = 900.0;
/// Door closing supervision: a closing that would take this many times the nominal time means
/// a door that cannot close (a blocked-door fault), as a door controller's closing timeout.
const CLOSING_LIMIT: f64 = 2.0;
/// Closings the door timing's mean is taken over.
const TIMING_CLOSINGS: usize = 16;
/// Closings the light barrier may interrupt before the door counts as blocked.
const REOPEN_LIMIT: u32 = 3;
/// Stop accuracy: the car snaps onto the floor within this distance at creeping speed.
const LEVELLING_MM: f64 = 0.5;
/// Time constant of the final exponential approach to the floor (s).
const FINAL_APPROACH_S: f64 = 0.8;
/// Levelling speed: the slowest the car moves before it stands (mm/s).
const CREEP_MM_S: f64 = 10.0;

/// Faults the simulator can be told to have (bits of 0x5030).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Fault {
    /// Something stands in the light barrier: the door cannot close.
    DoorBlocked,
    /// The car holds more than the overload limit (0x6483 sub 4).
    Overload,
    /// The drive has failed; a moving car makes a fast stop.
    DriveFault,
}

impl Fault {
    /// All faults, in bit order.
    pub const ALL: [Fault; 3] = [Fault::DoorBlocked, Fault::Overload, Fault::DriveFault];

    /// The bit in 0x5030.
    pub fn bit(self) -> u8 {
        match self {
            Fault::DoorBlocked => 1,
            Fault::Overload => 2,
            Fault::DriveFault => 4,
        }
    }

    /// The EMCY error code, from the CANopen-Lift additions to CiA 417-1 (§8.4): FF01h light
    /// barrier defect for a blocked door, FF04h application error for an overloaded car (the
    /// profile has no load code), F001h fast stop for a drive fault.
    pub fn emcy_code(self) -> u16 {
        match self {
            Fault::DoorBlocked => 0xFF01,
            Fault::Overload => 0xFF04,
            Fault::DriveFault => 0xF001,
        }
    }

    /// Index into the fault counters of 0x4401 (sub-index − 1).
    pub fn counter(self) -> usize {
        match self {
            Fault::DoorBlocked => 0,
            Fault::Overload => 1,
            Fault::DriveFault => 2,
        }
    }
}

/// Where a call comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CallKind {
    /// A car call (button in the car, 0x5022).
    Car,
    /// A hall call to go up.
    HallUp,
    /// A hall call to go down.
    HallDown,
}

/// A refused call.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CallError {
    /// The floor does not exist.
    #[error("floor {0} does not exist")]
    NoSuchFloor(u8),
    /// Hall up at the top floor or hall down at the bottom.
    #[error("no hall call in that direction at floor {0}")]
    NoDirection(u8),
    /// In fire service or inspection the lift takes no call.
    #[error("no calls in {0}")]
    SpecialOperation(&'static str),
}

/// 0x5030 bit 4: fire service — the fire alarm input or the fire service key switch (CiA 417's
/// virtual input functions 0Bh/0Ch): every call is cancelled, the car is recalled to the lowest
/// floor, opens its doors there, and takes no further call.
pub const FIRE_SERVICE: u8 = 0x10;
/// 0x5030 bit 5: inspection operation — the inspection switch on the car roof: every call is
/// cancelled, the car stops after its travel and takes no call.
pub const INSPECTION: u8 = 0x20;

/// The 0x5030 bits the lift itself acts on: its three faults and the two special operations.
const LIFT_BITS: u8 = 0x07 | FIRE_SERVICE | INSPECTION;

/// What the lift did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// The drive started towards `floor`.
    Departed {
        /// 1-based.
        floor: u8,
    },
    /// A trip ended at `floor` (the trip counter has counted it).
    Arrived {
        /// 1-based.
        floor: u8,
    },
    /// The doors are fully open.
    DoorsOpen,
    /// The doors are closed again (a door cycle was counted).
    DoorsClosed,
    /// A fault began.
    FaultRaised(Fault),
    /// A fault ended.
    FaultCleared(Fault),
}

/// The door's state (door statusword bits 12–15, CiA 417-4 §4.7.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DoorState {
    /// Closed and locked.
    Closed,
    /// Opening.
    Opening,
    /// Fully open.
    Open,
    /// Closing.
    Closing,
    /// Opening again after the light barrier was interrupted while closing.
    Reopening,
}

impl DoorState {
    /// The status field of the door statusword.
    pub fn status_bits(self) -> u16 {
        match self {
            DoorState::Closed => 0x0,
            DoorState::Closing => 0x2,
            DoorState::Open => 0x3,
            DoorState::Opening => 0x5,
            DoorState::Reopening => 0x6,
        }
    }
}

/// What the lift is doing, as 0x5024 reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum LiftState {
    /// Standing with closed doors, nothing to do.
    Idle = 0,
    /// Travelling up.
    Up = 1,
    /// Travelling down.
    Down = 2,
    /// Doors opening, open or closing.
    Doors = 3,
    /// Standing because of a fault.
    OutOfService = 4,
    /// Braking after a drive fault.
    FastStop = 5,
    /// In fire service: recalled to the lowest floor, taking no calls (0x5030 bit 4).
    FireService = 6,
    /// In inspection operation: taking no calls (0x5030 bit 5). Value 7, fire brigade service,
    /// is left for controllers that have it.
    Inspection = 8,
}

/// Settings the controller reads from its dictionary.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Floor levels in mm, lowest first (0x4010).
    pub levels: Vec<i32>,
    /// Travel speed (mm/s, 0x6423).
    pub speed: f64,
    /// Acceleration (mm/s², 0x640B sub 1).
    pub acceleration: f64,
    /// Deceleration (mm/s², 0x640B sub 2).
    pub deceleration: f64,
    /// Jerk (mm/s³, 0x640D sub 1).
    pub jerk: f64,
    /// Fast-stop deceleration (mm/s², 0x640A).
    pub quick_stop: f64,
    /// Door open time (s, 0x4113).
    pub door_open_s: f64,
    /// Overload limit (kg, 0x6483 sub 4).
    pub overload_kg: u16,
    /// Full load limit (kg, 0x6483 sub 3): passengers stop boarding there.
    pub full_kg: u16,
    /// Parking time (s, 0x4114; 0 off) and floor (0x4115).
    pub parking: Option<(f64, u8)>,
}

impl Params {
    /// Defaults for `floors` floors 3.5 m apart starting at 1 m, as in NXg SW003 §6.2.2.
    pub fn with_floors(floors: u8) -> Params {
        Params {
            levels: (0..i32::from(floors.max(2)))
                .map(|f| 1000 + 3500 * f)
                .collect(),
            speed: 1000.0,
            acceleration: 600.0,
            deceleration: 600.0,
            jerk: 1000.0,
            quick_stop: 1500.0,
            door_open_s: 3.0,
            overload_kg: 1000,
            full_kg: 800,
            parking: None,
        }
    }
}

/// Counters of the lift, kept across restarts by the controller.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Counters {
    /// Completed trips (0x6520 sub 1).
    pub trips: u32,
    /// Seconds in operation (0x6520 sub 2 shows whole hours).
    pub operating_s: f64,
    /// Door cycles (0x4400 sub 1).
    pub door_cycles: u32,
    /// Travelled distance in mm (0x4400 sub 2 shows metres).
    pub distance_mm: f64,
    /// Drive starts (0x4400 sub 3).
    pub starts: u32,
    /// Reopenings for the light barrier (0x4400 sub 4).
    pub reopenings: u32,
    /// Faults by kind and in all (0x4401).
    pub faults: [u32; 4],
    /// The last fault: EMCY code and the operating hour it came at (0x4402).
    pub last_fault: Option<(u16, u32)>,
}

/// How long the car door took to close (0x4403): the last closing and the mean of the last
/// sixteen, in ms — what shows a door wearing out before it fails.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DoorTiming {
    recent: VecDeque<u32>,
}

impl DoorTiming {
    fn record(&mut self, ms: u32) {
        if self.recent.len() == TIMING_CLOSINGS {
            self.recent.pop_front();
        }
        self.recent.push_back(ms);
    }

    /// The last closing (ms; 0 before the first).
    pub fn last_ms(&self) -> u32 {
        self.recent.back().copied().unwrap_or(0)
    }

    /// The mean of the recent closings (ms; 0 before the first).
    pub fn mean_ms(&self) -> u32 {
        let n = self.recent.len().max(1) as u64;
        (self.recent.iter().map(|&ms| u64::from(ms)).sum::<u64>() / n) as u32
    }
}

/// One simulated lift.
#[derive(Debug, Clone)]
pub struct Lift {
    params: Params,
    position: f64,
    speed: f64,
    acceleration: f64,
    target: Option<usize>,
    moving_up: Option<bool>,
    car_calls: BTreeSet<usize>,
    hall_up: BTreeSet<usize>,
    hall_down: BTreeSet<usize>,
    door: DoorState,
    door_position: f64,
    door_timer: f64,
    /// Time the current closing has taken (s).
    closing_s: f64,
    timing: DoorTiming,
    /// How much slower closing gets per simulated hour (a fraction: 0.1 is 10 %).
    closing_wear_per_h: f64,
    /// Simulated time since the lift was made (s): what wear grows with.
    age_s: f64,
    reopen_tries: u32,
    idle_s: f64,
    load_kg: u16,
    injected: u8,
    active: BTreeSet<Fault>,
    counters: Counters,
    seed: u64,
    events: VecDeque<Event>,
}

impl Lift {
    /// A lift standing at the lowest floor with closed doors.
    pub fn new(params: Params, counters: Counters, seed: u64) -> Lift {
        let position = params.levels.first().copied().map_or(0.0, f64::from);
        Lift {
            params,
            position,
            speed: 0.0,
            acceleration: 0.0,
            target: None,
            moving_up: None,
            car_calls: BTreeSet::new(),
            hall_up: BTreeSet::new(),
            hall_down: BTreeSet::new(),
            door: DoorState::Closed,
            door_position: 0.0,
            door_timer: 0.0,
            closing_s: 0.0,
            timing: DoorTiming::default(),
            closing_wear_per_h: 0.0,
            age_s: 0.0,
            reopen_tries: 0,
            idle_s: 0.0,
            load_kg: 0,
            injected: 0,
            active: BTreeSet::new(),
            counters,
            seed: seed | 1,
            events: VecDeque::new(),
        }
    }

    /// Change the settings (the dictionary was written); a travel in progress keeps its target.
    pub fn set_params(&mut self, params: Params) {
        self.params = params;
    }

    /// The settings in force.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Register a call to 1-based `floor`.
    pub fn call(&mut self, floor: u8, kind: CallKind) -> Result<(), CallError> {
        match self.special_operation() {
            Some(LiftState::FireService) => {
                return Err(CallError::SpecialOperation("fire service"))
            }
            Some(_) => return Err(CallError::SpecialOperation("inspection")),
            None => {}
        }
        let floors = self.params.levels.len();
        let f = usize::from(floor)
            .checked_sub(1)
            .filter(|f| *f < floors)
            .ok_or(CallError::NoSuchFloor(floor))?;
        match kind {
            CallKind::Car => self.car_calls.insert(f),
            CallKind::HallUp if f + 1 < floors => self.hall_up.insert(f),
            CallKind::HallDown if f > 0 => self.hall_down.insert(f),
            _ => return Err(CallError::NoDirection(floor)),
        };
        Ok(())
    }

    /// Set the injected faults (bits of [`Fault::bit`]); they begin and end as the lift runs.
    pub fn inject(&mut self, bits: u8) {
        let fire_begins = bits & FIRE_SERVICE != 0 && self.injected & FIRE_SERVICE == 0;
        self.injected = bits & LIFT_BITS;
        if fire_begins {
            // The recall: a call of the lift's own that no passenger can make now.
            self.car_calls.insert(0);
        }
    }

    /// The injected fault bits.
    pub fn injected(&self) -> u8 {
        self.injected
    }

    /// The next event, oldest first.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// Car position in mm.
    pub fn position_mm(&self) -> f64 {
        self.position
    }

    /// Car speed in mm/s, positive upwards.
    pub fn speed_mm_s(&self) -> f64 {
        self.speed
    }

    /// Car acceleration in mm/s², positive upwards.
    pub fn acceleration_mm_s2(&self) -> f64 {
        self.acceleration
    }

    /// The door's state.
    pub fn door(&self) -> DoorState {
        self.door
    }

    /// Door opening width in mm.
    pub fn door_position_mm(&self) -> f64 {
        self.door_position
    }

    /// The door statusword (6301h): status in bits 12–15, safety contact (bit 0) when closed.
    pub fn door_statusword(&self) -> u16 {
        let status = if self.active.contains(&Fault::DoorBlocked) {
            0xE
        } else {
            self.door.status_bits()
        };
        (status << 12) | u16::from(self.door == DoorState::Closed)
    }

    /// Whether the light barrier is interrupted.
    pub fn light_barrier(&self) -> bool {
        self.injected & Fault::DoorBlocked.bit() != 0 && self.door != DoorState::Closed
    }

    /// Load in kg.
    pub fn load_kg(&self) -> u16 {
        self.load_kg
    }

    /// The floor (1-based) the car is at or nearest to.
    pub fn floor(&self) -> u8 {
        let nearest = self
            .params
            .levels
            .iter()
            .enumerate()
            .min_by(|(_, a), (_, b)| {
                let da = (f64::from(**a) - self.position).abs();
                let db = (f64::from(**b) - self.position).abs();
                da.total_cmp(&db)
            })
            .map_or(0, |(i, _)| i);
        u8::try_from(nearest + 1).unwrap_or(u8::MAX)
    }

    /// What the lift is doing.
    pub fn state(&self) -> LiftState {
        if self.active.contains(&Fault::DriveFault) {
            return if self.speed != 0.0 {
                LiftState::FastStop
            } else {
                LiftState::OutOfService
            };
        }
        if !self.active.is_empty() {
            return LiftState::OutOfService;
        }
        if let Some(special) = self.special_operation() {
            return special;
        }
        if self.target.is_some() {
            return match self.moving_up {
                Some(false) => LiftState::Down,
                _ => LiftState::Up,
            };
        }
        if self.door != DoorState::Closed {
            return LiftState::Doors;
        }
        LiftState::Idle
    }

    /// Active faults.
    pub fn faults(&self) -> impl Iterator<Item = Fault> + '_ {
        self.active.iter().copied()
    }

    /// Wear the door: closing takes `percent_per_h` % longer for every simulated hour from
    /// now on (from the lift's start), until the closing supervision calls the door blocked.
    pub fn set_door_wear(&mut self, percent_per_h: f64) {
        self.closing_wear_per_h = percent_per_h.max(0.0) / 100.0;
    }

    /// How many times the nominal closing time a closing takes now.
    pub fn closing_factor(&self) -> f64 {
        1.0 + self.closing_wear_per_h * self.age_s / 3600.0
    }

    /// The door's timing record.
    pub fn door_timing(&self) -> &DoorTiming {
        &self.timing
    }

    /// The counters.
    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    /// Whether calls are waiting.
    pub fn has_calls(&self) -> bool {
        !(self.car_calls.is_empty() && self.hall_up.is_empty() && self.hall_down.is_empty())
    }

    /// Move on by `dt` of simulated time.
    pub fn advance(&mut self, dt: Duration) {
        let mut left = dt;
        while !left.is_zero() {
            let step = left.min(STEP);
            left -= step;
            self.step(step.as_secs_f64());
        }
    }

    fn level(&self, floor: usize) -> f64 {
        self.params
            .levels
            .get(floor)
            .copied()
            .map_or(0.0, f64::from)
    }

    fn random(&mut self) -> u64 {
        // xorshift64: deterministic per seed, so scenarios repeat exactly.
        self.seed ^= self.seed << 13;
        self.seed ^= self.seed >> 7;
        self.seed ^= self.seed << 17;
        self.seed
    }

    /// Fire service or inspection, if the lift is switched to one (fire service first).
    fn special_operation(&self) -> Option<LiftState> {
        if self.injected & FIRE_SERVICE != 0 {
            Some(LiftState::FireService)
        } else if self.injected & INSPECTION != 0 {
            Some(LiftState::Inspection)
        } else {
            None
        }
    }

    /// In a special operation the passengers' calls are gone; fire service keeps one call of
    /// its own, the recall to the lowest floor (until the car is there).
    fn cancel_calls(&mut self) {
        let Some(special) = self.special_operation() else {
            return;
        };
        self.hall_up.clear();
        self.hall_down.clear();
        let recalled = special == LiftState::FireService && self.car_calls.contains(&0);
        self.car_calls.clear();
        if recalled {
            self.car_calls.insert(0);
        }
    }

    fn step(&mut self, dt: f64) {
        self.counters.operating_s += dt;
        self.age_s += dt;
        self.update_faults();
        self.cancel_calls();
        if self.target.is_some() {
            self.drive(dt);
        } else {
            self.doors(dt);
            if self.door == DoorState::Closed && self.active.is_empty() {
                self.dispatch(dt);
            }
        }
    }

    fn raise(&mut self, fault: Fault) {
        if self.active.insert(fault) {
            let hour = (self.counters.operating_s / 3600.0) as u32;
            self.counters.faults[fault.counter()] += 1;
            self.counters.faults[3] += 1;
            self.counters.last_fault = Some((fault.emcy_code(), hour));
            self.events.push_back(Event::FaultRaised(fault));
        }
    }

    fn clear(&mut self, fault: Fault) {
        if self.active.remove(&fault) {
            self.events.push_back(Event::FaultCleared(fault));
        }
    }

    fn update_faults(&mut self) {
        let bits = self.injected;
        let injected = |f: Fault| bits & f.bit() != 0;
        // Overload: the load cell reads above the limit; it matters when the car stands.
        if injected(Fault::Overload) {
            self.load_kg = self.params.overload_kg.saturating_add(80);
            if self.target.is_none() {
                self.raise(Fault::Overload);
            }
        } else if self.active.contains(&Fault::Overload) {
            self.load_kg = self.params.full_kg / 2;
            self.clear(Fault::Overload);
        }
        if injected(Fault::DriveFault) {
            self.raise(Fault::DriveFault);
        } else {
            self.clear(Fault::DriveFault);
        }
        // A worn door would take longer than its supervision allows: it counts as blocked.
        let worn_out = self.closing_factor() > CLOSING_LIMIT;
        if worn_out {
            self.raise(Fault::DoorBlocked);
        } else if !injected(Fault::DoorBlocked) {
            self.reopen_tries = 0;
            self.clear(Fault::DoorBlocked);
        }
    }

    /// Collective selective control: keep the direction while calls lie ahead, then turn.
    fn dispatch(&mut self, dt: f64) {
        let here = usize::from(self.floor()) - 1;
        let at_floor = (self.position - self.level(here)).abs() < LEVELLING_MM;
        if at_floor && (self.car_calls.contains(&here) || self.hall_call_here(here)) {
            self.serve(here);
            return;
        }
        let next = match self.moving_up {
            Some(true) => self.call_above(here).or_else(|| self.call_below(here)),
            _ => self.call_below(here).or_else(|| self.call_above(here)),
        };
        match next {
            Some(floor) => self.depart(floor),
            None => self.park(here, dt),
        }
    }

    fn hall_call_here(&self, here: usize) -> bool {
        match self.moving_up {
            Some(true) => {
                self.hall_up.contains(&here)
                    || self.nothing_above(here) && self.hall_down.contains(&here)
            }
            Some(false) => {
                self.hall_down.contains(&here)
                    || self.nothing_below(here) && self.hall_up.contains(&here)
            }
            None => self.hall_up.contains(&here) || self.hall_down.contains(&here),
        }
    }

    fn nothing_above(&self, here: usize) -> bool {
        self.call_above(here).is_none()
    }

    fn nothing_below(&self, here: usize) -> bool {
        self.call_below(here).is_none()
    }

    fn call_above(&self, here: usize) -> Option<usize> {
        let lowest = |s: &BTreeSet<usize>| s.range(here + 1..).next().copied();
        [
            lowest(&self.car_calls),
            lowest(&self.hall_up),
            lowest(&self.hall_down),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    fn call_below(&self, here: usize) -> Option<usize> {
        let highest = |s: &BTreeSet<usize>| s.range(..here).next_back().copied();
        [
            highest(&self.car_calls),
            highest(&self.hall_up),
            highest(&self.hall_down),
        ]
        .into_iter()
        .flatten()
        .max()
    }

    fn park(&mut self, here: usize, dt: f64) {
        if self.special_operation().is_some() {
            return;
        }
        self.idle_s += dt;
        if let Some((after, floor)) = self.params.parking {
            let park = usize::from(floor.max(1)) - 1;
            if self.idle_s >= after && park != here && park < self.params.levels.len() {
                self.idle_s = 0.0;
                self.depart(park);
            }
        }
    }

    fn depart(&mut self, floor: usize) {
        self.idle_s = 0.0;
        self.moving_up = Some(self.level(floor) > self.position);
        self.target = Some(floor);
        self.counters.starts += 1;
        self.events.push_back(Event::Departed {
            floor: u8::try_from(floor + 1).unwrap_or(u8::MAX),
        });
    }

    /// The distance the car needs to stop from its speed and acceleration with the jerk limit.
    fn stopping_distance(&self) -> f64 {
        let v = self.speed.abs();
        let decel = self.params.deceleration;
        // Time to take the current acceleration back to −decel, plus the braking itself.
        let lag = decel / self.params.jerk;
        v * v / (2.0 * decel) + v * lag
    }

    /// Take a call ahead on the way if the car can still stop there comfortably.
    fn intercept(&mut self) {
        let (Some(target), Some(up)) = (self.target, self.moving_up) else {
            return;
        };
        let braking = self.stopping_distance() + 50.0;
        let candidates =
            self.car_calls
                .iter()
                .chain(if up { &self.hall_up } else { &self.hall_down });
        let mut best = target;
        for &f in candidates {
            let d = self.level(f) - self.position;
            let ahead = if up { d } else { -d };
            let closer = if up { f < best } else { f > best };
            if ahead > braking && closer {
                best = f;
            }
        }
        self.target = Some(best);
    }

    fn drive(&mut self, dt: f64) {
        let Some(target) = self.target else {
            return;
        };
        let p = self.params.clone();
        let direction = if self.moving_up == Some(false) {
            -1.0
        } else {
            1.0
        };
        let mut v = self.speed * direction;
        let mut a = self.acceleration * direction;
        if self.active.contains(&Fault::DriveFault) {
            // Fast stop: brake at the quick-stop deceleration, then stand until repaired.
            v = (v - p.quick_stop * dt).max(0.0);
            a = if v > 0.0 { -p.quick_stop } else { 0.0 };
            self.advance_car(v, a, direction, dt);
            return;
        }
        self.intercept();
        let target = self.target.unwrap_or(target);
        let remaining = (self.level(target) - self.position) * direction;
        if remaining <= LEVELLING_MM && v.abs() <= 2.0 * CREEP_MM_S || remaining < 0.0 {
            self.arrive(target);
            return;
        }
        // The wanted speed: the speed from which a comfortable deceleration (¾ of the limit,
        // leaving room for the jerk limit) stops at the floor, aimed a tracking delay ahead,
        // and for the last centimetres an exponential approach, so deceleration fades out
        // instead of ending in a jolt.
        let tracking = 0.25;
        let comfortable = 0.75 * p.deceleration;
        let ahead = (remaining - v * tracking).max(0.0);
        let v_brake = (2.0 * comfortable * ahead)
            .sqrt()
            .min(remaining / FINAL_APPROACH_S);
        let v_want = p.speed.min(v_brake).max(CREEP_MM_S);
        let a_want = ((v_want - v) / tracking).clamp(-p.deceleration, p.acceleration);
        let da = (a_want - a).clamp(-p.jerk * dt, p.jerk * dt);
        a += da;
        v = (v + a * dt).clamp(0.0, p.speed);
        // Never run past the floor within one step.
        let v = v.min(remaining.max(0.0) / dt);
        self.advance_car(v, a, direction, dt);
    }

    fn advance_car(&mut self, v: f64, a: f64, direction: f64, dt: f64) {
        self.position += v * dt * direction;
        self.counters.distance_mm += v * dt;
        self.speed = v * direction;
        self.acceleration = if v == 0.0 { 0.0 } else { a * direction };
    }

    fn arrive(&mut self, floor: usize) {
        self.position = self.level(floor);
        self.speed = 0.0;
        self.acceleration = 0.0;
        self.target = None;
        self.counters.trips += 1;
        self.events.push_back(Event::Arrived {
            floor: u8::try_from(floor + 1).unwrap_or(u8::MAX),
        });
        self.serve(floor);
    }

    /// Clear the calls answered at `floor` and open the doors.
    fn serve(&mut self, floor: usize) {
        self.car_calls.remove(&floor);
        let up = match self.moving_up {
            Some(true) => !self.nothing_above(floor) || !self.hall_down.contains(&floor),
            Some(false) => self.nothing_below(floor) && self.hall_up.contains(&floor),
            None => self.hall_up.contains(&floor),
        };
        if up {
            self.hall_up.remove(&floor);
        } else {
            self.hall_down.remove(&floor);
        }
        if self.door == DoorState::Closed {
            self.door = DoorState::Opening;
        } else {
            self.door_timer = 0.0;
        }
    }

    fn doors(&mut self, dt: f64) {
        let rate = DOOR_WIDTH_MM / DOOR_TIME_S;
        match self.door {
            DoorState::Closed => {}
            DoorState::Opening | DoorState::Reopening => {
                self.door_position = (self.door_position + rate * dt).min(DOOR_WIDTH_MM);
                if self.door_position >= DOOR_WIDTH_MM {
                    self.door = DoorState::Open;
                    self.door_timer = 0.0;
                    self.exchange_passengers();
                    self.events.push_back(Event::DoorsOpen);
                }
            }
            DoorState::Open => {
                self.door_timer += dt;
                let blocked = self.active.contains(&Fault::DoorBlocked);
                let overloaded = self.active.contains(&Fault::Overload);
                if self.door_timer >= self.params.door_open_s && !blocked && !overloaded {
                    self.door = DoorState::Closing;
                    self.closing_s = 0.0;
                }
            }
            DoorState::Closing => {
                if self.light_barrier() {
                    self.reopen_tries += 1;
                    self.counters.reopenings += 1;
                    if self.reopen_tries >= REOPEN_LIMIT {
                        self.raise(Fault::DoorBlocked);
                    }
                    self.door = DoorState::Reopening;
                    return;
                }
                self.closing_s += dt;
                let rate = rate / self.closing_factor();
                self.door_position = (self.door_position - rate * dt).max(0.0);
                if self.door_position <= 0.0 {
                    self.timing.record((self.closing_s * 1000.0).round() as u32);
                    self.door = DoorState::Closed;
                    self.reopen_tries = 0;
                    self.counters.door_cycles += 1;
                    self.events.push_back(Event::DoorsClosed);
                }
            }
        }
    }

    /// Passengers leave and board: the load changes by a plausible amount.
    fn exchange_passengers(&mut self) {
        if self.active.contains(&Fault::Overload) {
            return;
        }
        let leaving = (self.random() % 4) as u16 * 75;
        let boarding = (self.random() % 4) as u16 * 75;
        let load = self
            .load_kg
            .saturating_sub(leaving)
            .saturating_add(boarding);
        self.load_kg = load.min(self.params.full_kg);
    }
}

#[cfg(test)]
mod tests;
