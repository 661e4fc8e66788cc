//! What an event means for the alarms, sans-IO (docs/PORTAL.md §Alarms):
//!
//! | event | raises | clears |
//! |---|---|---|
//! | `emcy` with a code other than 0000h and a non-zero register | `emcy` (node, code) | — |
//! | `emcy` 0000h (error reset) or a zero error register | — | the node's `emcy` alarms |
//! | `state` `offline` | `node-offline` (node) | — |
//! | `state` `boot-up` | — | the node's `node-offline` and `emcy` alarms (it restarted) |
//! | any other `state` | — | the node's `node-offline` |
//! | `bus` `error-passive`, `bus-off`, `offline` | `bus` (net, state) | the net's other `bus` alarms |
//! | `bus` `error-active` | — | the net's `bus` alarms |
//! | gateway offline for `offline_after_s` | `lift-offline` | — |
//! | gateway back | — | `lift-offline` |
//! | a valid token from another board (`boardhash_change = "alarm"`) | `board-changed` (new hash) | — (its acknowledgement clears it) |
//! | a trend rule's mean rose beyond it (`[[insights.trends]]`) | `trend` (object) | — |
//! | the mean is back within the rule | — | that object's `trend` |
//!
//! `overrun` is stored as an event and raises nothing: frames were lost once, the network is
//! not in a state.

use std::collections::{BTreeMap, HashMap};

use nxg::msg::{BusState, Event, NodeState};

use cloud_types::alarms::{Condition, Kind, Place, Severity};

use crate::config::Severities;

/// What to do with the alarms.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// The condition holds: raise it unless it is already active.
    Raise {
        /// The condition.
        condition: Condition,
        /// How urgent.
        severity: Severity,
        /// What it is, for people.
        text: String,
    },
    /// Active alarms of `kind` at `place` on `lift` are over — all of them, or all but the
    /// one with code `keep`.
    Clear {
        /// The lift.
        lift: String,
        /// The kind.
        kind: Kind,
        /// Where (none: the lift's).
        place: Option<Place>,
        /// A code that stays.
        keep: Option<String>,
    },
    /// The active alarm of exactly this condition, if any, is over.
    End(Condition),
}

/// The rules with their severities.
#[derive(Debug, Clone, Copy, Default)]
pub struct Rules {
    /// Severities per condition.
    pub severities: Severities,
}

impl Rules {
    /// What `event` of `lift` means.
    pub fn event(&self, lift: &str, event: &Event) -> Vec<Verdict> {
        let clear = |kind, place: Place| Verdict::Clear {
            lift: lift.to_owned(),
            kind,
            place: Some(place),
            keep: None,
        };
        let raise = |kind, place: Place, code: String, severity, text| Verdict::Raise {
            condition: Condition {
                lift: lift.to_owned(),
                kind,
                place: Some(place),
                code,
            },
            severity,
            text,
        };
        match event {
            Event::Emcy {
                node,
                code,
                register,
                text,
                ..
            } => {
                let place = Place {
                    id: Some(node.id.get()),
                    net: node.net,
                };
                let reset = code_value(code) == Some(0) || code_value(register) == Some(0);
                if reset {
                    return vec![clear(Kind::Emcy, place)];
                }
                let text = format!(
                    "Node {}: {text} ({})",
                    node.id.get(),
                    code.to_uppercase().replace("0X", "")
                );
                vec![raise(
                    Kind::Emcy,
                    place,
                    normalized_code(code),
                    self.severities.emcy,
                    text,
                )]
            }
            Event::State { node, state, .. } => {
                let place = Place {
                    id: Some(node.id.get()),
                    net: node.net,
                };
                match state {
                    NodeState::Offline => vec![raise(
                        Kind::NodeOffline,
                        place,
                        String::new(),
                        self.severities.node_offline,
                        format!(
                            "Node {} (network {}) is silent: its heartbeat stopped",
                            node.id.get(),
                            node.net
                        ),
                    )],
                    NodeState::BootUp => {
                        vec![clear(Kind::NodeOffline, place), clear(Kind::Emcy, place)]
                    }
                    _ => vec![clear(Kind::NodeOffline, place)],
                }
            }
            Event::Bus { net, state, .. } => {
                let place = Place {
                    id: None,
                    net: *net,
                };
                let (severity, what) = match state {
                    BusState::ErrorActive => return vec![clear(Kind::Bus, place)],
                    BusState::Overrun => return Vec::new(),
                    BusState::ErrorPassive => (self.severities.error_passive, "error-passive"),
                    BusState::BusOff => (self.severities.bus_off, "bus-off"),
                    BusState::Offline => {
                        (self.severities.bus_offline, "unreachable for the gateway")
                    }
                };
                let code = state.name().to_owned();
                vec![
                    Verdict::Clear {
                        lift: lift.to_owned(),
                        kind: Kind::Bus,
                        place: Some(place),
                        keep: Some(code.clone()),
                    },
                    raise(
                        Kind::Bus,
                        place,
                        code,
                        severity,
                        format!("Network {net} is {what}"),
                    ),
                ]
            }
        }
    }

    /// The lift's gateway has been offline for `seconds`.
    pub fn lift_offline(&self, lift: &str, seconds: u64) -> Verdict {
        Verdict::Raise {
            condition: Condition {
                lift: lift.to_owned(),
                kind: Kind::LiftOffline,
                place: None,
                code: String::new(),
            },
            severity: self.severities.lift_offline,
            text: format!("The gateway has been offline for {}", duration(seconds)),
        }
    }

    /// The lift's gateway connected from another board (`was` → `now`, the boardhashes).
    pub fn board_changed(&self, lift: &str, was: &str, now: &str) -> Verdict {
        Verdict::Raise {
            condition: Condition {
                lift: lift.to_owned(),
                kind: Kind::BoardChanged,
                place: None,
                code: now.to_owned(),
            },
            severity: self.severities.board_changed,
            text: format!("The gateway's board changed: boardhash {now:?}, was {was:?}"),
        }
    }

    /// An alarm of a `kind` that only a person ends was acknowledged: the lift's alarms of
    /// that kind are over.
    pub fn acknowledged(&self, lift: &str, kind: Kind) -> Verdict {
        Verdict::Clear {
            lift: lift.to_owned(),
            kind,
            place: None,
            keep: None,
        }
    }

    /// The lift pushed more than `[gateways] max_stored_bytes_per_hour`: `dropped` values were
    /// not stored since it began.
    pub fn storage_quota(&self, lift: &str, dropped: u64) -> Verdict {
        Verdict::Raise {
            condition: Condition {
                lift: lift.to_owned(),
                kind: Kind::StorageQuota,
                place: None,
                code: String::new(),
            },
            severity: self.severities.storage_quota,
            text: format!(
                "The lift pushes more than it may store per hour: {dropped} values not stored so far"
            ),
        }
    }

    /// A trend rule saw `mplex` of `lift` rise: mean `now` over its window against `base` over
    /// its baseline.
    pub fn trend(
        &self,
        lift: &str,
        mplex: &str,
        rule: &crate::config::TrendRule,
        base: f64,
        now: f64,
    ) -> Verdict {
        let rise = if base > 0.0 {
            (now / base - 1.0) * 100.0
        } else {
            0.0
        };
        Verdict::Raise {
            condition: Condition {
                lift: lift.to_owned(),
                kind: Kind::Trend,
                place: None,
                code: mplex.to_owned(),
            },
            severity: self.severities.trend,
            text: format!(
                "{} ({mplex}) rose {rise:.0} % (rule: {} %): mean {now:.1} over the last {}, {base:.1} over the {} before",
                rule.name,
                rule.rise_percent,
                hours(rule.window_h),
                hours(rule.baseline_h),
            ),
        }
    }

    /// `mplex` of `lift` is back within its trend rule.
    pub fn trend_over(&self, lift: &str, mplex: &str) -> Verdict {
        Verdict::End(Condition {
            lift: lift.to_owned(),
            kind: Kind::Trend,
            place: None,
            code: mplex.to_owned(),
        })
    }

    /// The lift has stayed within its storage quota for an hour.
    pub fn storage_quota_kept(&self, lift: &str) -> Verdict {
        Verdict::Clear {
            lift: lift.to_owned(),
            kind: Kind::StorageQuota,
            place: None,
            keep: None,
        }
    }

    /// The lift's gateway is back.
    pub fn lift_online(&self, lift: &str) -> Verdict {
        Verdict::Clear {
            lift: lift.to_owned(),
            kind: Kind::LiftOffline,
            place: None,
            keep: None,
        }
    }
}

/// `0xFF01` as a number.
fn code_value(text: &str) -> Option<u32> {
    let hex = text
        .strip_prefix("0x")
        .or_else(|| text.strip_prefix("0X"))?;
    u32::from_str_radix(hex, 16).ok()
}

/// A code in one spelling (`0xFF01`), whatever the gateway wrote.
fn normalized_code(text: &str) -> String {
    code_value(text).map_or_else(|| text.to_owned(), |v| format!("0x{v:04X}"))
}

/// Hours as people say them: `24 h`, `90 min`, `20 s`.
fn hours(h: f64) -> String {
    let s = (h * 3600.0).round() as u64;
    if s.is_multiple_of(3600) && s > 0 {
        format!("{} h", s / 3600)
    } else {
        duration(s)
    }
}

fn duration(seconds: u64) -> String {
    match seconds {
        s if s % 60 == 0 && s >= 60 => format!("{} min", s / 60),
        s => format!("{s} s"),
    }
}

/// What applying a verdict changed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Applied {
    /// A new alarm.
    Raised {
        /// Its id.
        id: i64,
        /// Its condition.
        condition: Condition,
        /// How urgent.
        severity: Severity,
        /// What it is.
        text: String,
    },
    /// These alarms are over.
    Cleared(Vec<i64>),
    /// The condition was active already.
    Unchanged,
}

/// The active alarms by condition, per lift: raise once, clear what matches.
#[derive(Debug, Clone, Default)]
pub struct Active {
    lifts: HashMap<String, BTreeMap<Condition, i64>>,
}

impl Active {
    /// The alarm active for `condition`, if any.
    pub fn get(&self, condition: &Condition) -> Option<i64> {
        self.lifts.get(&condition.lift)?.get(condition).copied()
    }

    /// `id` is active for `condition`.
    pub fn insert(&mut self, condition: Condition, id: i64) {
        self.lifts
            .entry(condition.lift.clone())
            .or_default()
            .insert(condition, id);
    }

    /// Remove and return the active alarms a [`Verdict::Clear`] names.
    pub fn take_matching(
        &mut self,
        lift: &str,
        kind: Kind,
        place: Option<Place>,
        keep: Option<&str>,
    ) -> Vec<(Condition, i64)> {
        let Some(active) = self.lifts.get_mut(lift) else {
            return Vec::new();
        };
        let matching: Vec<Condition> = active
            .keys()
            .filter(|c| c.kind == kind && c.place == place && keep != Some(c.code.as_str()))
            .cloned()
            .collect();
        let taken = matching
            .into_iter()
            .filter_map(|c| active.remove(&c).map(|id| (c, id)))
            .collect();
        if active.is_empty() {
            self.lifts.remove(lift);
        }
        taken
    }

    /// Apply `verdict`: a condition not yet active becomes alarm `new_id()`; the alarms a
    /// clear names leave the index.
    pub fn apply(&mut self, verdict: Verdict, new_id: impl FnOnce() -> i64) -> Applied {
        match verdict {
            Verdict::Raise {
                condition,
                severity,
                text,
            } => {
                if self.get(&condition).is_some() {
                    return Applied::Unchanged;
                }
                let id = new_id();
                self.insert(condition.clone(), id);
                Applied::Raised {
                    id,
                    condition,
                    severity,
                    text,
                }
            }
            Verdict::Clear {
                lift,
                kind,
                place,
                keep,
            } => Applied::Cleared(
                self.take_matching(&lift, kind, place, keep.as_deref())
                    .into_iter()
                    .map(|(_, id)| id)
                    .collect(),
            ),
            Verdict::End(condition) => {
                let Some(active) = self.lifts.get_mut(&condition.lift) else {
                    return Applied::Unchanged;
                };
                let ended = active.remove(&condition);
                if active.is_empty() {
                    self.lifts.remove(&condition.lift);
                }
                ended.map_or(Applied::Unchanged, |id| Applied::Cleared(vec![id]))
            }
        }
    }

    /// The lift's active alarms are `active` (as the database has them), whatever was known.
    pub fn replace_lift(&mut self, lift: &str, active: Vec<(Condition, i64)>) {
        self.lifts.remove(lift);
        for (condition, id) in active {
            self.insert(condition, id);
        }
    }

    /// How many are active.
    pub fn len(&self) -> usize {
        self.lifts.values().map(BTreeMap::len).sum()
    }

    /// Whether none is.
    pub fn is_empty(&self) -> bool {
        self.lifts.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(json: serde_json::Value) -> Event {
        serde_json::from_value(json).unwrap()
    }

    const T: &str = "2026-11-23T10:11:12.345Z";

    #[test]
    fn emcy_raises_per_code_and_a_reset_clears_the_node() {
        let rules = Rules::default();
        let fault = event(
            serde_json::json!({"type":"emcy","node":{"id":1,"net":1},"time":T,
            "code":"0xff01","register":"0x21","data":"0000000000","text":"Door blocked"}),
        );
        let verdicts = rules.event("L", &fault);
        let [Verdict::Raise {
            condition,
            severity,
            text,
        }] = &verdicts[..]
        else {
            panic!("{verdicts:?}")
        };
        assert_eq!(condition.code, "0xFF01");
        assert_eq!(
            condition.place,
            Some(Place {
                id: Some(1),
                net: 1
            })
        );
        assert_eq!(*severity, Severity::Major);
        assert_eq!(text, "Node 1: Door blocked (FF01)");
        let reset = event(
            serde_json::json!({"type":"emcy","node":{"id":1,"net":1},"time":T,
            "code":"0x0000","register":"0x00","data":"0000000000","text":"Error reset"}),
        );
        assert!(matches!(
            &rules.event("L", &reset)[..],
            [Verdict::Clear {
                kind: Kind::Emcy,
                place: Some(Place {
                    id: Some(1),
                    net: 1
                }),
                keep: None,
                ..
            }]
        ));
    }

    #[test]
    fn states_and_networks() {
        let rules = Rules::default();
        let offline = event(
            serde_json::json!({"type":"state","node":{"id":12,"net":1},"time":T,"state":"offline"}),
        );
        assert!(matches!(
            &rules.event("L", &offline)[..],
            [Verdict::Raise { condition, severity: Severity::Major, .. }] if condition.kind == Kind::NodeOffline
        ));
        let boot = event(
            serde_json::json!({"type":"state","node":{"id":12,"net":1},"time":T,"state":"boot-up"}),
        );
        assert_eq!(rules.event("L", &boot).len(), 2);
        let off = event(serde_json::json!({"type":"bus","net":2,"time":T,"state":"bus-off"}));
        let verdicts = rules.event("L", &off);
        assert!(matches!(&verdicts[0], Verdict::Clear { keep: Some(k), .. } if k == "bus-off"));
        assert!(matches!(
            &verdicts[1],
            Verdict::Raise {
                severity: Severity::Critical,
                ..
            }
        ));
        let overrun = event(serde_json::json!({"type":"bus","net":2,"time":T,"state":"overrun"}));
        assert!(rules.event("L", &overrun).is_empty());
        assert!(matches!(
            rules.lift_offline("L", 120),
            Verdict::Raise { text, .. } if text == "The gateway has been offline for 2 min"
        ));
    }

    #[test]
    fn the_index_clears_what_matches() {
        let mut active = Active::default();
        let c = |kind, code: &str| Condition {
            lift: "L".into(),
            kind,
            place: Some(Place { id: None, net: 1 }),
            code: code.into(),
        };
        active.insert(c(Kind::Bus, "bus-off"), 1);
        active.insert(c(Kind::Bus, "error-passive"), 2);
        assert_eq!(active.get(&c(Kind::Bus, "bus-off")), Some(1));
        let place = Some(Place { id: None, net: 1 });
        let taken = active.take_matching("L", Kind::Bus, place, Some("bus-off"));
        assert_eq!(taken.iter().map(|t| t.1).collect::<Vec<_>>(), [2]);
        assert_eq!(active.len(), 1);
        assert_eq!(active.take_matching("L", Kind::Bus, place, None).len(), 1);
        assert!(active.is_empty());
    }

    #[test]
    fn a_board_change_stays_until_acknowledged() {
        let rules = Rules::default();
        let mut active = Active::default();
        let mut ids = 10..;
        let mut apply = |v| active.apply(v, || ids.next().unwrap_or_default());
        let raised = apply(rules.board_changed("L", "A1", "B2"));
        assert!(matches!(
            &raised,
            Applied::Raised { condition, text, .. }
                if condition.kind == Kind::BoardChanged && condition.code == "B2"
                    && condition.place.is_none() && text.contains("\"B2\", was \"A1\"")
        ));
        assert_eq!(
            apply(rules.board_changed("L", "A1", "B2")),
            Applied::Unchanged
        );
        // The gateway coming back does not end it; the acknowledgement does.
        assert_eq!(apply(rules.lift_online("L")), Applied::Cleared(Vec::new()));
        assert_eq!(
            apply(rules.acknowledged("L", Kind::BoardChanged)),
            Applied::Cleared(vec![10])
        );
        assert!(Kind::BoardChanged.cleared_by_acknowledgement());
        assert!(!Kind::Emcy.cleared_by_acknowledgement());
        assert_eq!(Kind::from_name("board-changed"), Some(Kind::BoardChanged));
    }
}
