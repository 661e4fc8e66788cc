//! What portal processes tell each other over NATS (docs/CLUSTER.md §What lives where): the holder
//! entry of a lift in the KV bucket, an operator request relayed to the holder and its
//! answer, and the names of keys and subjects.

use nxg::msg::{ErrorObject, MplexText};
use nxg::portal::Failure;
use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

use cloud_types::subscriptions::Subscriber;

/// The KV bucket of holder entries (`lift.<token>`, a [`HolderEntry`]) and of the processes'
/// leases (`process.<token>`, an [`Alive`]).
pub const BUCKET: &str = "canlift-holders";

/// The NATS header naming the process that published a lift event (a process skips its own).
pub const ORIGIN: &str = "Canlift-Node";

/// The value of a lift's key in [`BUCKET`]: which process holds its gateway's connection now,
/// and what every process needs to know of a lift it does not hold.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HolderEntry {
    /// The holding process (`[cluster] node`).
    pub node: String,
    /// Which life of that process: the entry stands while the process's lease ([`Alive`])
    /// names the same one, and no longer once it lapsed or the process started again.
    pub incarnation: u64,
    /// The connection's epoch: µs since the Unix epoch when it was admitted, so a newer
    /// connection of the lift has the larger one, whichever process took it.
    pub epoch: u64,
    /// The account's domain token the lift belongs to.
    pub domain: String,
    /// The gateway's serial number (sent with writes and elevations).
    pub sernum: String,
    /// The error register, once pushed (the fleet page's fault column).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_register: Option<u8>,
    /// The lift state, once pushed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lift_state: Option<u8>,
}

impl HolderEntry {
    /// Whether this entry is of a newer connection than `other` (ties: the larger node name,
    /// so that every process decides alike).
    pub fn newer_than(&self, other: &HolderEntry) -> bool {
        (self.epoch, &self.node) > (other.epoch, &other.node)
    }
}

/// The value of a process's key in [`BUCKET`], written every third of `[cluster]
/// holder_ttl_s` while the process lives: the lifts it holds are held while this is fresh
/// (written less than `holder_ttl_s` ago) and names the incarnation their entries name. One
/// lease per process instead of a refresh per lift: holding 100,000 lifts costs the cluster a
/// few writes per second, not tens of thousands.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Alive {
    /// This life of the process: random, chosen when it starts.
    pub incarnation: u64,
}

/// What a key of [`BUCKET`] names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Key {
    /// A lift's holder entry.
    Lift(String),
    /// A process's lease, by node name.
    Process(String),
}

impl Key {
    /// The key as written in the bucket.
    pub fn encode(&self) -> String {
        match self {
            Key::Lift(lift) => format!("lift.{}", token(lift)),
            Key::Process(node) => format!("process.{}", token(node)),
        }
    }

    /// What `key` names; `None` for a key no portal wrote.
    pub fn decode(key: &str) -> Option<Key> {
        match key.split_once('.')? {
            ("lift", rest) => lift_of(rest).map(Key::Lift),
            ("process", rest) => lift_of(rest).map(Key::Process),
            _ => None,
        }
    }
}

/// What another process asks of a lift's holder on [`rpc_subject`]. Externally tagged
/// (`{"call": …}`): a call's raw parameters pass through untouched, which serde's buffering of
/// internally tagged enums would not allow.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Relayed {
    /// An operator request for the gateway.
    Call(RelayedCall),
    /// A holder there asks for subscriptions (docs/PORTAL.md §Subscriptions): the lift's
    /// holder keeps every holder's terms and registers the union with the gateway.
    Hold(RelayedHold),
    /// A holder there lets go of subscriptions.
    Release(RelayedRelease),
    /// Someone there watches the lift's live events: the holder publishes them on
    /// [`events_subject`] for a lease (twice `[cluster] holder_ttl_s`), which the watching
    /// process renews three times per TTL (and at once when the lift moves or NATS comes
    /// back). Unwatched, nothing is published; when the lease of a process lapses (it died, or
    /// lost NATS for longer), the holder also lets go of its watchers' subscriptions. The holder
    /// answers `true` for a lease it renewed, `false` for a new one: then it holds none of the
    /// process's watchers' subscriptions and the process hands them over again.
    Watch(RelayedWatch),
}

/// [`Relayed::Watch`]: which process watches.
#[derive(Debug, Serialize, Deserialize)]
pub struct RelayedWatch {
    /// The watching process's part of its watchers' ids (their upper 32 bits, see
    /// [`Subscriber::Watcher`]).
    pub process: u64,
}

/// An operator request for a lift, relayed to its holder.
#[derive(Debug, Serialize, Deserialize)]
pub struct RelayedCall {
    /// The method's name on the wire (`get_canopen_object`).
    pub method: String,
    /// Its parameters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub params: Option<Box<RawValue>>,
}

/// [`Relayed::Hold`]: `holder` asks for `mplex` with these terms.
#[derive(Debug, Serialize, Deserialize)]
pub struct RelayedHold {
    /// Who asks.
    #[serde(rename = "holder")]
    pub subscriber: Subscriber,
    /// The objects.
    pub mplex: Vec<MplexText>,
    /// Minimum gap between two pushes (ms).
    pub inhibit: u64,
    /// Smallest change of a number that is pushed.
    pub threshold: f64,
}

/// [`Relayed::Release`]: `holder` lets go of `mplex` (of all it holds when absent).
#[derive(Debug, Serialize, Deserialize)]
pub struct RelayedRelease {
    /// Who lets go.
    #[serde(rename = "holder")]
    pub subscriber: Subscriber,
    /// The objects.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mplex: Option<Vec<MplexText>>,
}

/// The holder's answer to a [`RelayedCall`]: what the gateway answered, or the same failure a
/// local request would have had (one of the two).
#[derive(Debug, Serialize, Deserialize)]
pub struct RelayedAnswer {
    /// The gateway's `result`, as it sent it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub result: Option<Box<RawValue>>,
    /// Why there is none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<RelayedFailure>,
}

/// A [`Failure`] on the wire between processes.
#[derive(Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum RelayedFailure {
    /// The gateway answered with an error object.
    Error {
        /// As the gateway sent it.
        error: ErrorObject,
    },
    /// The gateway's answer does not fit the method.
    Invalid {
        /// What is wrong.
        why: String,
    },
    /// The gateway did not answer in time.
    Timeout,
    /// Too many requests wait for the gateway.
    Busy,
    /// The holder no longer holds the lift.
    Gone,
}

impl RelayedAnswer {
    /// The answer to send for `outcome`.
    pub fn of(outcome: Result<String, Failure>) -> RelayedAnswer {
        let failure = match outcome {
            Ok(raw) => match RawValue::from_string(raw) {
                Ok(result) => {
                    return RelayedAnswer {
                        result: Some(result),
                        failure: None,
                    }
                }
                Err(e) => RelayedFailure::Invalid { why: e.to_string() },
            },
            Err(Failure::Error(error)) => RelayedFailure::Error { error },
            Err(Failure::Invalid(why)) => RelayedFailure::Invalid { why },
            Err(Failure::Timeout) => RelayedFailure::Timeout,
            Err(Failure::Busy) => RelayedFailure::Busy,
            Err(Failure::Gone) => RelayedFailure::Gone,
        };
        RelayedAnswer {
            result: None,
            failure: Some(failure),
        }
    }

    /// The outcome it carries.
    pub fn outcome(self) -> Result<String, Failure> {
        match (self.result, self.failure) {
            (Some(result), None) => Ok(result.get().to_owned()),
            (None, Some(RelayedFailure::Error { error })) => Err(Failure::Error(error)),
            (None, Some(RelayedFailure::Invalid { why })) => Err(Failure::Invalid(why)),
            (None, Some(RelayedFailure::Timeout)) => Err(Failure::Timeout),
            (None, Some(RelayedFailure::Busy)) => Err(Failure::Busy),
            (None, Some(RelayedFailure::Gone)) => Err(Failure::Gone),
            _ => Err(Failure::Invalid(
                "the holder's answer has neither a result nor a failure".into(),
            )),
        }
    }
}

/// A lift id (or a node name) as one KV key token and one subject token: letters, digits and `-` as they are, every
/// other byte as `_` and two hex digits (a serial number may hold dots, spaces or `*`, which
/// NATS reserves).
pub fn token(lift: &str) -> String {
    let mut out = String::with_capacity(lift.len());
    for byte in lift.bytes() {
        if byte.is_ascii_alphanumeric() || byte == b'-' {
            out.push(char::from(byte));
        } else {
            out.push_str(&format!("_{byte:02X}"));
        }
    }
    out
}

/// The lift id (or node name) of a [`token`]; `None` for a token no portal wrote.
pub fn lift_of(token: &str) -> Option<String> {
    let mut bytes = Vec::with_capacity(token.len());
    let mut rest = token.as_bytes();
    while let Some((&first, tail)) = rest.split_first() {
        if first == b'_' {
            let hex = std::str::from_utf8(tail.get(..2)?).ok()?;
            bytes.push(u8::from_str_radix(hex, 16).ok()?);
            rest = &tail[2..];
        } else {
            bytes.push(first);
            rest = tail;
        }
    }
    String::from_utf8(bytes).ok()
}

/// Where the holder of `lift` answers relayed requests.
pub fn rpc_subject(lift: &str) -> String {
    format!("canlift.lift.{}.rpc", token(lift))
}

/// Where the holder of `lift` publishes its live events.
pub fn events_subject(lift: &str) -> String {
    format!("canlift.lift.{}.events", token(lift))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn tokens_are_valid_keys_and_subject_tokens() {
        assert_eq!(token("1234-5678-SN 1.2*"), "1234-5678-SN_201_2E2_2A");
        assert_eq!(rpc_subject("a.b"), "canlift.lift.a_2Eb.rpc");
        assert_eq!(lift_of("a_2Eb").as_deref(), Some("a.b"));
        assert_eq!(lift_of("a_2"), None);
        assert_eq!(lift_of("a_ZZ"), None);
    }

    #[test]
    fn keys_name_lifts_and_processes() {
        let lift = Key::Lift("1050-4097-SN 1.2".into());
        assert_eq!(lift.encode(), "lift.1050-4097-SN_201_2E2");
        assert_eq!(Key::decode(&lift.encode()), Some(lift));
        let process = Key::Process("portal.example:8443".into());
        assert_eq!(process.encode(), "process.portal_2Eexample_3A8443");
        assert_eq!(Key::decode(&process.encode()), Some(process));
        assert_eq!(Key::decode("other.x"), None);
        assert_eq!(Key::decode("lift"), None);
    }

    proptest! {
        #[test]
        fn token_round_trips(lift in "\\PC{0,40}") {
            let t = token(&lift);
            prop_assert!(t.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_'));
            prop_assert_eq!(lift_of(&t), Some(lift));
        }
    }

    /// A call's raw parameters pass through byte for byte; holds and releases name their
    /// holder and objects.
    #[test]
    fn relayed_requests_round_trip() {
        let params = RawValue::from_string("{\"mplex\": \"0x652001\"}".into()).unwrap();
        let call = Relayed::Call(RelayedCall {
            method: "get_canopen_object".into(),
            params: Some(params),
        });
        let wire = serde_json::to_string(&call).unwrap();
        let Relayed::Call(back) = serde_json::from_str(&wire).unwrap() else {
            panic!("{wire}");
        };
        assert_eq!(back.params.unwrap().get(), "{\"mplex\": \"0x652001\"}");
        let hold = Relayed::Hold(RelayedHold {
            subscriber: Subscriber::Watcher(7 << 32 | 1),
            mplex: vec![nxg::mplex::Mplex {
                index: 0x6520,
                sub: 1,
            }
            .into()],
            inhibit: 100,
            threshold: 0.5,
        });
        let wire = serde_json::to_string(&hold).unwrap();
        assert_eq!(
            wire,
            "{\"hold\":{\"holder\":{\"watcher\":30064771073},\"mplex\":[\"0x652001\"],\"inhibit\":100,\"threshold\":0.5}}"
        );
        let release = r#"{"release":{"holder":{"user":"masora"}}}"#;
        let Relayed::Release(back) = serde_json::from_str(release).unwrap() else {
            panic!("{release}");
        };
        assert_eq!(back.subscriber, Subscriber::User("masora".into()));
        assert!(back.mplex.is_none());
        let watch = Relayed::Watch(RelayedWatch { process: 7 << 32 });
        let watch = serde_json::to_string(&watch).unwrap();
        assert_eq!(watch, "{\"watch\":{\"process\":30064771072}}");
        assert!(matches!(
            serde_json::from_str(&watch),
            Ok(Relayed::Watch(RelayedWatch {
                process: 30064771072
            }))
        ));
    }

    #[test]
    fn a_relayed_answer_carries_every_outcome() {
        let error = ErrorObject::rpc(-32603, "x");
        for outcome in [
            Ok("{\"done\":0}".to_owned()),
            Err(Failure::Error(error)),
            Err(Failure::Invalid("why".into())),
            Err(Failure::Timeout),
            Err(Failure::Busy),
            Err(Failure::Gone),
        ] {
            let wire = serde_json::to_string(&RelayedAnswer::of(outcome.clone())).unwrap();
            let back: RelayedAnswer = serde_json::from_str(&wire).unwrap();
            assert_eq!(back.outcome(), outcome);
        }
    }

    #[test]
    fn the_newer_holding_wins_everywhere_alike() {
        let a = HolderEntry {
            node: "a".into(),
            incarnation: 1,
            epoch: 5,
            domain: "d".into(),
            sernum: "s".into(),
            error_register: None,
            lift_state: None,
        };
        let b = HolderEntry {
            node: "b".into(),
            ..a.clone()
        };
        assert!(b.newer_than(&a) && !a.newer_than(&b));
        let c = HolderEntry {
            epoch: 6,
            ..a.clone()
        };
        assert!(c.newer_than(&b));
    }
}
