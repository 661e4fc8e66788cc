//! The connector's messages as types (NXg SW003 §5–§7), apart from the state machines that use
//! them: the JSON-RPC 2.0 envelope ([`Incoming`], [`Id`] and the writers), one serde type per
//! method's parameters and answer, the [`Method`] names, and [`ErrorObject`]. Both sides of a
//! connection, the portal's REST API and its web pages read and write these types; the
//! readings of the specification they implement are in docs/PROTOCOL.md.

mod connect;
mod envelope;
mod error;
mod event;
mod object;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

pub use connect::{
    Connack, Connect, ElevateAnswer, ElevateParams, Identity, TokenParams, MAX_FIELD, MAX_TOKEN,
};
pub use envelope::{
    connack, error_response, notification, parse, request, response, Id, Incoming, Rejected,
};
pub use error::ErrorObject;
pub use event::{
    format_time, parse_time, BusState, Event, EventKind, EventNotification, NodeState,
    RegEventParams, UnregEventParams,
};
pub use object::{
    AnswerLang, GetObject, GetParams, Lang, MplexText, NodeId, NodeRef, Notification, ObjectAnswer,
    ObjectData, PutAnswer, PutObject, PutParams, RegParams, UnregParams, Written,
};

/// The NXg API version canlift speaks: 1, NXg SW003 v1.0.0 (§5.2.1). Each side offers its
/// highest; the lower of both is in force. The API numbers are NXg's: canlift's bus events are
/// an extension called by name, not a version (docs/PROTOCOL.md §Events).
pub const API: u32 = 1;

/// The methods of the connector, each listed once (NXg SW003 §5–§7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Method {
    /// Gateway → portal: identify and ask to be served (§5.2).
    Connect,
    /// Portal → gateway: prove the connection alive (§5.3).
    GetHeartbeat,
    /// Portal → gateway: store a new cloud token (§5.4).
    UpdateUniqueToken,
    /// Portal → gateway: read an object with its metadata (§6.1, §6.2, §6.5).
    GetCanopenObject,
    /// Portal → gateway: write an object (§6.3, §6.6).
    PutCanopenObject,
    /// Portal → gateway: elevate the connection's privilege (§6.4).
    ElevatePrivilege,
    /// Portal → gateway: subscribe to object changes (§7.1).
    RegCanopenObject,
    /// Portal → gateway: end subscriptions (§7.2).
    UnregCanopenObject,
    /// Gateway → portal notification: a subscribed object changed (§7.3).
    CanopenObject,
    /// Portal → gateway (canlift's extension): push bus events (docs/PROTOCOL.md §Events).
    RegCanopenEvent,
    /// Portal → gateway (canlift's extension): stop pushing bus events.
    UnregCanopenEvent,
    /// Gateway → portal notification (canlift's extension): a bus event.
    CanopenEvent,
}

impl Method {
    /// Every method.
    pub const ALL: [Method; 12] = [
        Method::Connect,
        Method::GetHeartbeat,
        Method::UpdateUniqueToken,
        Method::GetCanopenObject,
        Method::PutCanopenObject,
        Method::ElevatePrivilege,
        Method::RegCanopenObject,
        Method::UnregCanopenObject,
        Method::CanopenObject,
        Method::RegCanopenEvent,
        Method::UnregCanopenEvent,
        Method::CanopenEvent,
    ];

    /// The name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            Method::Connect => "CONNECT",
            Method::GetHeartbeat => "get_heartbeat",
            Method::UpdateUniqueToken => "update_unique_token",
            Method::GetCanopenObject => "get_canopen_object",
            Method::PutCanopenObject => "put_canopen_object",
            Method::ElevatePrivilege => "elevate_privilege",
            Method::RegCanopenObject => "reg_canopen_object",
            Method::UnregCanopenObject => "unreg_canopen_object",
            Method::CanopenObject => "canopen_object",
            Method::RegCanopenEvent => "reg_canopen_event",
            Method::UnregCanopenEvent => "unreg_canopen_event",
            Method::CanopenEvent => "canopen_event",
        }
    }

    /// The method called `name`, if the connector has one.
    pub fn from_name(name: &str) -> Option<Method> {
        Method::ALL.into_iter().find(|m| m.name() == name)
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The answer `{"done": 0}` of heartbeats, tokens and subscriptions (NXg SW003 §5.3.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Done {
    /// Always 0.
    #[cfg_attr(feature = "openapi", schema(minimum = 0, maximum = 0))]
    pub done: u32,
}

impl Done {
    /// `{"done": 0}`.
    pub const OK: Done = Done { done: 0 };
}

/// A request the portal sends to a gateway: its method and the type of the answer.
pub trait Call: Serialize {
    /// The method.
    const METHOD: Method;
    /// What the gateway answers.
    type Answer: DeserializeOwned;
}

/// `get_heartbeat` has no parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Heartbeat;

/// Each request type with its method and answer.
macro_rules! calls {
    ($($params:ty => $method:ident, $answer:ty;)*) => {
        $(impl Call for $params {
            const METHOD: Method = Method::$method;
            type Answer = $answer;
        })*
    };
}

calls! {
    Heartbeat => GetHeartbeat, Done;
    GetParams => GetCanopenObject, ObjectAnswer;
    PutParams => PutCanopenObject, PutAnswer;
    ElevateParams => ElevatePrivilege, ElevateAnswer;
    RegParams => RegCanopenObject, Done;
    UnregParams => UnregCanopenObject, Done;
    TokenParams => UpdateUniqueToken, Done;
    RegEventParams => RegCanopenEvent, Done;
    UnregEventParams => UnregCanopenEvent, Done;
}

/// Read a method's parameters; the error names the field at fault (`object.mplex: …`), for a
/// −32602 answer.
pub fn params<T: DeserializeOwned>(raw: Option<&RawValue>) -> Result<T, String> {
    let Some(raw) = raw else {
        return Err("params are missing".into());
    };
    read(raw.get())
}

/// Read `text` as a `T`; the error names the field at fault.
pub fn read<T: DeserializeOwned>(text: &str) -> Result<T, String> {
    // Tracking the path costs a string per member read (a tenth of an embedded gateway's CPU
    // per request), so it is paid only to explain a refusal: the same text read again.
    if let Ok(value) = T::deserialize(&mut serde_json::Deserializer::from_str(text)) {
        return Ok(value);
    }
    let mut json = serde_json::Deserializer::from_str(text);
    serde_path_to_error::deserialize(&mut json).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        if path == "." {
            inner.to_string()
        } else {
            format!("{path}: {inner}")
        }
    })
}

/// JSON text of one of our own messages. Serializing them cannot fail: they hold no maps with
/// non-string keys and no serializer that refuses.
pub(crate) fn to_json<T: Serialize + ?Sized>(value: &T) -> String {
    serde_json::to_string(value).unwrap_or_else(|e| {
        tracing::error!(error = %e, "a message did not serialize");
        String::from("null")
    })
}

/// Text of a JSON string or number: what a lenient reader accepts where the connector writes
/// text (values pushed or read).
pub(crate) mod text {
    use serde::{Deserialize, Deserializer};

    #[derive(Deserialize)]
    #[serde(untagged)]
    enum TextOrNumber {
        Text(String),
        Number(serde_json::Number),
        Bool(bool),
    }

    impl From<TextOrNumber> for String {
        fn from(t: TextOrNumber) -> String {
            match t {
                TextOrNumber::Text(s) => s,
                TextOrNumber::Number(n) => n.to_string(),
                TextOrNumber::Bool(b) => u8::from(b).to_string(),
            }
        }
    }

    pub(crate) fn one<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
        TextOrNumber::deserialize(d).map(String::from)
    }

    pub(crate) fn many<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
        Vec::<TextOrNumber>::deserialize(d).map(|v| v.into_iter().map(String::from).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn method_names_round_trip() {
        for m in Method::ALL {
            assert_eq!(Method::from_name(m.name()), Some(m));
        }
        assert_eq!(Method::from_name("reboot"), None);
    }

    #[test]
    fn parameter_errors_name_the_field() {
        let e = read::<GetParams>(r#"{"object":{"mplex":5}}"#).unwrap_err();
        assert!(e.starts_with("object.mplex: "), "{e}");
        let e = read::<PutParams>(r#"{"sernum":"1","object":{"mplex":"0x502200","value":"4"}}"#)
            .unwrap_err();
        assert!(e.contains("datatype"), "{e}");
        assert_eq!(params::<GetParams>(None).unwrap_err(), "params are missing");
    }
}
