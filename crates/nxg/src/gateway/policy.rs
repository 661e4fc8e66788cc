//! The write policy the lift's owner sets (`[policy]` of the gateway's configuration): NXg §6.3
//! lets a gateway limit writes heavily, and for a lift this is the main safety lever.
//!
//! - `remote_writes = "read-only"` refuses every put (06010002h);
//! - `deny` refuses puts to the objects it lists (06010002h; they stay readable);
//! - `hide` makes objects invisible: get, put and registration answer 06020000h;
//! - on nodes other than the lift controller, the communication objects 1000h–1FFFh (PDO
//!   parameters, heartbeat, store/restore, program control) are not written unless `allow`
//!   lists them;
//! - an object without a description (no EDS, catalog or vendor metadata) is never written;
//! - `default_privilege` is what writing an object needs when no metadata says.
//!
//! - the lift-safety interlock: while the lift controller's state object (`lift_state`) holds a
//!   value of `refuse_writes_in` — out of order, fire service, fire brigade service, inspection —
//!   every put is refused with 08000022h and reads go on (docs/GATEWAY.md §Lift-safety interlock).
//!
//! A rule is an index (`"0x5022"`), a range (`"0x1010-0x1FFF"`), or a table with a node:
//! `{ index = "0x1010-0x1FFF", node = 12 }`.

use std::fmt;
use std::ops::RangeInclusive;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use super::metadata::Target;
use crate::codes::ErrorCode;
use crate::meta::Privilege;
use crate::mplex::Mplex;

/// Whether the cloud may write at all.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RemoteWrites {
    /// Writes are checked object by object.
    #[default]
    Allowed,
    /// Every put is refused.
    ReadOnly,
}

/// Objects by index (one or a range), on every node or on one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rule {
    /// The indices.
    pub indices: RangeInclusive<u16>,
    /// Only on this node (any network); every node when absent.
    pub node: Option<u8>,
}

impl Rule {
    fn matches(&self, target: Target, index: u16) -> bool {
        self.indices.contains(&index) && self.node.is_none_or(|n| n == target.node)
    }

    fn parse_indices(text: &str) -> Result<RangeInclusive<u16>, String> {
        let number = |t: &str| {
            let t = t.trim();
            t.strip_prefix("0x")
                .or_else(|| t.strip_prefix("0X"))
                .and_then(|h| u16::from_str_radix(h, 16).ok())
                .ok_or_else(|| format!("{t:?} is not an index (0x and four hex digits)"))
        };
        match text.split_once('-') {
            Some((from, to)) => {
                let (from, to) = (number(from)?, number(to)?);
                if from > to {
                    return Err(format!(
                        "range {text:?}: from {from:04X}h is above to {to:04X}h"
                    ));
                }
                Ok(from..=to)
            }
            None => number(text).map(|i| i..=i),
        }
    }
}

impl fmt::Display for Rule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (from, to) = (self.indices.start(), self.indices.end());
        if from == to {
            write!(f, "0x{from:04X}")?;
        } else {
            write!(f, "0x{from:04X}-0x{to:04X}")?;
        }
        match self.node {
            Some(n) => write!(f, " on node {n}"),
            None => Ok(()),
        }
    }
}

impl<'de> Deserialize<'de> for Rule {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Rule, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Text(String),
            Table { index: String, node: Option<u8> },
        }
        let (text, node) = match Raw::deserialize(d)? {
            Raw::Text(t) => (t, None),
            Raw::Table { index, node } => (index, node),
        };
        if node.is_some_and(|n| !(1..=127).contains(&n)) {
            return Err(serde::de::Error::custom("node is a node-ID 1–127"));
        }
        let indices = Rule::parse_indices(&text).map_err(serde::de::Error::custom)?;
        Ok(Rule { indices, node })
    }
}

impl Serialize for Rule {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let (from, to) = (self.indices.start(), self.indices.end());
        let index = if from == to {
            format!("0x{from:04X}")
        } else {
            format!("0x{from:04X}-0x{to:04X}")
        };
        match self.node {
            None => s.serialize_str(&index),
            Some(node) => {
                let mut map = s.serialize_map(Some(2))?;
                map.serialize_entry("index", &index)?;
                map.serialize_entry("node", &node)?;
                map.end()
            }
        }
    }
}

/// `[policy]`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Policy {
    /// `"allowed"` or `"read-only"`.
    pub remote_writes: RemoteWrites,
    /// Objects never written remotely (they stay readable).
    pub deny: Vec<Rule>,
    /// Objects written although the defaults protect them (communication objects of other
    /// nodes).
    pub allow: Vec<Rule>,
    /// Objects the connector does not show at all.
    pub hide: Vec<Rule>,
    /// The privilege writing needs where no metadata says (0 user, 1 service, 2 setup, 3 never).
    pub default_privilege: u8,
    /// The lift controller's state object read before every put (the lift-safety interlock);
    /// `""`: no interlock. Default 0x502400, the lift state of canlift's controller
    /// (docs/SIMULATOR.md).
    #[serde(with = "optional_mplex")]
    pub lift_state: Option<Mplex>,
    /// The values of `lift_state` in which every put is refused with 08000022h. Default: 4 out
    /// of order, 6 fire service, 7 fire brigade service, 8 inspection.
    pub refuse_writes_in: Vec<u64>,
    /// Objects the interlock lets through in any state. Default 0x5030, the simulator's fault
    /// and special-operation switches (lift 1): they stand for what is switched on site.
    pub interlock_exempt: Vec<Rule>,
}

/// The interlock's default values of the lift state: out of order, fire service, fire brigade
/// service, inspection (canlift's 0x5024, docs/SIMULATOR.md).
pub const REFUSE_WRITES_IN: [u64; 4] = [4, 6, 7, 8];

/// `lift_state` as the configuration writes it: an mplex, or `""` for none.
mod optional_mplex {
    use serde::{Deserialize, Deserializer, Serializer};

    use crate::mplex::Mplex;

    pub fn serialize<S: Serializer>(value: &Option<Mplex>, s: S) -> Result<S::Ok, S::Error> {
        match value {
            Some(m) => s.collect_str(m),
            None => s.serialize_str(""),
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Mplex>, D::Error> {
        let text = String::deserialize(d)?;
        if text.is_empty() {
            return Ok(None);
        }
        Mplex::parse(&text)
            .map(Some)
            .map_err(serde::de::Error::custom)
    }
}

impl Default for Policy {
    fn default() -> Self {
        Policy {
            remote_writes: RemoteWrites::Allowed,
            deny: Vec::new(),
            allow: Vec::new(),
            hide: Vec::new(),
            default_privilege: Privilege::Setup.code(),
            lift_state: Some(Mplex {
                index: 0x5024,
                sub: 0,
            }),
            refuse_writes_in: REFUSE_WRITES_IN.to_vec(),
            interlock_exempt: vec![Rule {
                indices: 0x5030..=0x5030,
                node: None,
            }],
        }
    }
}

/// The communication profile area (CiA 301 §7.5.2).
const COMMUNICATION: RangeInclusive<u16> = 0x1000..=0x1FFF;

impl Policy {
    /// Whether the connector hides `index` of `target`.
    pub fn hidden(&self, target: Target, index: u16) -> bool {
        self.hide.iter().any(|r| r.matches(target, index))
    }

    /// The privilege writing needs where no metadata says.
    pub fn default_privilege(&self) -> Privilege {
        Privilege::from_code(u32::from(self.default_privilege)).unwrap_or(Privilege::Setup)
    }

    /// Whether a put of `index` on `target` may go ahead (`controller`: the lift controller;
    /// `described`: some metadata describes the object). The refusal says why, for the log.
    pub fn check_write(
        &self,
        target: Target,
        controller: Target,
        index: u16,
        described: bool,
    ) -> Result<(), (ErrorCode, String)> {
        let refuse = |why: String| Err((ErrorCode::READ_ONLY, why));
        if self.remote_writes == RemoteWrites::ReadOnly {
            return refuse("remote writes are off (policy remote_writes = read-only)".into());
        }
        if let Some(rule) = self.deny.iter().find(|r| r.matches(target, index)) {
            return refuse(format!("denied by policy rule {rule}"));
        }
        if !described {
            return refuse("no description of the object: never written remotely".into());
        }
        let allowed = self.allow.iter().any(|r| r.matches(target, index));
        if target != controller && COMMUNICATION.contains(&index) && !allowed {
            return refuse(format!(
                "communication object of node {}: not written unless the policy allows it",
                target.node
            ));
        }
        Ok(())
    }

    /// Whether the lift-safety interlock guards a put of `index` on `target` (then the lift
    /// state is read first).
    pub fn guarded(&self, target: Target, index: u16) -> bool {
        self.lift_state.is_some()
            && !self
                .interlock_exempt
                .iter()
                .any(|r| r.matches(target, index))
    }

    /// Whether the lift-safety interlock refuses writes while the lift state is `state`.
    pub fn interlocked(&self, state: u64) -> bool {
        self.lift_state.is_some() && self.refuse_writes_in.contains(&state)
    }

    /// The `allow` rules that can never take effect, each with why (logged as warnings at
    /// start): one whose every object a `deny` rule covers (allow never overrides deny), or one
    /// outside the communication objects (1000h–1FFFh), the only protection it lifts.
    pub fn ineffective(&self) -> Vec<String> {
        self.allow
            .iter()
            .filter_map(|rule| {
                if !rule.indices.clone().any(|i| COMMUNICATION.contains(&i)) {
                    return Some(format!(
                        "allow {rule} never takes effect: it lifts only the protection of other \
                         nodes' communication objects (0x1000-0x1FFF)"
                    ));
                }
                let covered = |index: u16| {
                    self.deny.iter().find(|d| {
                        d.indices.contains(&index) && d.node.is_none_or(|n| Some(n) == rule.node)
                    })
                };
                let by: Vec<String> = rule
                    .indices
                    .clone()
                    .map(|i| covered(i).map(ToString::to_string))
                    .collect::<Option<Vec<_>>>()?;
                let mut by = by;
                by.dedup();
                Some(format!(
                    "allow {rule} never takes effect: deny {} covers it (allow never overrides deny)",
                    by.join(", ")
                ))
            })
            .collect()
    }

    /// A line for the log at start.
    pub fn summary(&self) -> String {
        let list = |rules: &[Rule]| {
            if rules.is_empty() {
                "none".to_owned()
            } else {
                rules
                    .iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        };
        let interlock = match self.lift_state {
            Some(state) => format!(
                "interlock {state} in {:?} (exempt {})",
                self.refuse_writes_in,
                list(&self.interlock_exempt)
            ),
            None => "no interlock".to_owned(),
        };
        format!(
            "remote writes {}; deny {}; allow {}; hide {}; default privilege {}; {interlock}",
            match self.remote_writes {
                RemoteWrites::Allowed => "allowed",
                RemoteWrites::ReadOnly => "read-only",
            },
            list(&self.deny),
            list(&self.allow),
            list(&self.hide),
            self.default_privilege().text()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn policy(text: &str) -> Result<Policy, String> {
        crate::msg::read::<Policy>(text)
    }

    const CONTROLLER: Target = Target { net: 1, node: 1 };
    const IO: Target = Target { net: 1, node: 12 };

    #[test]
    fn the_interlock_is_on_by_default_and_can_be_moved_or_turned_off() {
        let default = Policy::default();
        assert_eq!(
            default.lift_state.map(|m| m.to_string()).as_deref(),
            Some("0x502400")
        );
        for state in REFUSE_WRITES_IN {
            assert!(default.interlocked(state));
        }
        assert!(!default.interlocked(0) && !default.interlocked(5));
        assert!(default.guarded(IO, 0x6200) && default.guarded(CONTROLLER, 0x5022));
        assert!(
            !default.guarded(CONTROLLER, 0x5030),
            "the simulator's switches"
        );
        let vendor = policy(r#"{"lift_state": "0x2100a0", "refuse_writes_in": [17]}"#).unwrap();
        assert_eq!(
            vendor.lift_state,
            Some(Mplex {
                index: 0x2100,
                sub: 0xA0
            })
        );
        assert!(vendor.interlocked(17) && !vendor.interlocked(6));
        let off = policy(r#"{"lift_state": ""}"#).unwrap();
        assert!(off.lift_state.is_none() && !off.interlocked(6));
        assert!(!off.guarded(CONTROLLER, 0x5022));
        assert!(off.summary().ends_with("no interlock"));
        assert!(policy(r#"{"lift_state": "0x5024"}"#).is_err());
        // What --print-config writes reads back the same.
        for p in [default, vendor, off] {
            let text = serde_json::to_string(&p).unwrap();
            assert_eq!(policy(&text).unwrap(), p, "{text}");
        }
    }

    #[test]
    fn an_allow_that_cannot_take_effect_is_named() {
        let p = policy(
            r#"{"deny": ["0x1010-0x1FFF", {"index": "0x1018", "node": 7}],
                "allow": [{"index": "0x1017", "node": 12}, {"index": "0x1018", "node": 7},
                          {"index": "0x1018", "node": 8}, "0x2000"]}"#,
        )
        .unwrap();
        let said = p.ineffective();
        assert_eq!(said.len(), 4, "{said:?}");
        assert!(said[0].contains("deny 0x1010-0x1FFF covers it"), "{said:?}");
        assert!(said[3].contains("communication objects"), "{said:?}");
        let p = policy(
            r#"{"deny": ["0x1010-0x1011", {"index": "0x1018", "node": 7}],
                "allow": [{"index": "0x1017", "node": 12}, {"index": "0x1018", "node": 8}]}"#,
        )
        .unwrap();
        assert!(p.ineffective().is_empty(), "{:?}", p.ineffective());
    }

    #[test]
    fn rules_read_and_check() {
        let p = policy(
            r#"{"deny":["0x5022","0x4100-0x41FF"],"allow":[{"index":"0x1017","node":12}],
               "hide":[{"index":"0x2000-0x20FF","node":1}]}"#,
        )
        .unwrap();
        assert!(p.hidden(CONTROLLER, 0x2010) && !p.hidden(IO, 0x2010));
        let code = |r: Result<(), (ErrorCode, String)>| r.map_err(|e| e.0);
        assert_eq!(
            code(p.check_write(CONTROLLER, CONTROLLER, 0x5022, true)),
            Err(ErrorCode::READ_ONLY)
        );
        assert_eq!(
            code(p.check_write(CONTROLLER, CONTROLLER, 0x4113, true)),
            Err(ErrorCode::READ_ONLY)
        );
        assert_eq!(
            code(p.check_write(CONTROLLER, CONTROLLER, 0x4200, true)),
            Ok(())
        );
        // Communication objects of other nodes only when allowed; the controller's by metadata.
        assert_eq!(
            code(p.check_write(IO, CONTROLLER, 0x1016, true)),
            Err(ErrorCode::READ_ONLY)
        );
        assert_eq!(code(p.check_write(IO, CONTROLLER, 0x1017, true)), Ok(()));
        assert_eq!(
            code(p.check_write(CONTROLLER, CONTROLLER, 0x1017, true)),
            Ok(())
        );
        // Nothing without a description.
        assert_eq!(
            code(p.check_write(IO, CONTROLLER, 0x6200, false)),
            Err(ErrorCode::READ_ONLY)
        );
        let ro = policy(r#"{"remote_writes":"read-only"}"#).unwrap();
        assert_eq!(
            code(ro.check_write(CONTROLLER, CONTROLLER, 0x5022, true)),
            Err(ErrorCode::READ_ONLY)
        );
        assert_eq!(Policy::default().default_privilege(), Privilege::Setup);
        assert!(
            p.summary().contains("deny 0x5022, 0x4100-0x41FF"),
            "{}",
            p.summary()
        );
    }

    #[test]
    fn bad_rules_are_named() {
        let e = policy(r#"{"deny":["0x2000-0x1000"]}"#).unwrap_err();
        assert!(e.contains("deny") && e.contains("above"), "{e}");
        assert!(policy(r#"{"deny":["5022"]}"#).is_err());
        assert!(policy(r#"{"hide":[{"index":"0x2000","node":200}]}"#).is_err());
        assert!(policy(r#"{"colour":"red"}"#).is_err());
        // Rules write back as they read.
        let p = policy(r#"{"allow":[{"index":"0x1017","node":12}],"deny":["0x5022"]}"#).unwrap();
        let again: Policy = crate::msg::read(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(again, p);
    }
}
