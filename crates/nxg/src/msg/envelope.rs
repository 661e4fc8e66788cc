//! JSON-RPC 2.0 envelopes as the connector uses them (NXg SW003 §5–§7; docs/PROTOCOL.md
//! §Messages): reading one WebSocket text into an [`Incoming`] message whose parameters stay
//! raw JSON until the method's own type reads them, and writing requests, answers and
//! notifications.

use std::borrow::Cow;

use serde::{Deserialize, Deserializer, Serialize};
use serde_json::value::RawValue;

use super::{to_json, ErrorObject, Method};
use crate::codes::rpc_codes;

/// A JSON-RPC id: any string or number, echoed unchanged (docs/PROTOCOL.md §Messages).
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize)]
#[serde(untagged)]
pub enum Id {
    /// A string id, as the specification's samples use.
    Text(String),
    /// A numeric id.
    Number(serde_json::Number),
}

impl Id {
    /// The string id `n` (we send string ids, as the samples do).
    pub fn counter(n: u64) -> Id {
        Id::Text(n.to_string())
    }

    /// The number this id carries, as text or as a number: how a side finds the request an
    /// answer belongs to among those it numbered itself.
    pub fn counter_value(&self) -> Option<u64> {
        match self {
            Id::Text(t) => t.parse().ok(),
            Id::Number(n) => n.as_u64(),
        }
    }
}

/// Read by what the JSON holds (an untagged enum would try a string first and build an error
/// for every numeric id: once per request).
impl<'de> Deserialize<'de> for Id {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Id, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = Id;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a string or a number")
            }
            fn visit_str<E>(self, v: &str) -> Result<Id, E> {
                Ok(Id::Text(v.to_owned()))
            }
            fn visit_string<E>(self, v: String) -> Result<Id, E> {
                Ok(Id::Text(v))
            }
            fn visit_u64<E>(self, v: u64) -> Result<Id, E> {
                Ok(Id::Number(v.into()))
            }
            fn visit_i64<E>(self, v: i64) -> Result<Id, E> {
                Ok(Id::Number(v.into()))
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Id, E> {
                serde_json::Number::from_f64(v)
                    .map(Id::Number)
                    .ok_or_else(|| E::custom("an id must be a finite number"))
            }
        }
        deserializer.deserialize_any(Visitor)
    }
}

impl std::fmt::Display for Id {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Id::Text(t) => write!(f, "{t:?}"),
            Id::Number(n) => write!(f, "{n}"),
        }
    }
}

/// A message received, borrowing from its text.
#[derive(Debug, Clone)]
pub enum Incoming<'a> {
    /// A request: it gets exactly one answer with the same `id` (`None`: the id was `null`).
    Request {
        /// String, number or null, echoed unchanged.
        id: Option<Id>,
        /// Method name (not necessarily one the connector has).
        method: Cow<'a, str>,
        /// `params`, raw.
        params: Option<&'a RawValue>,
    },
    /// A notification (no `id`): no answer.
    Notification {
        /// Method name.
        method: Cow<'a, str>,
        /// `params`, or `result` as the connector's own notifications carry it (NXg §7.3.1).
        params: Option<&'a RawValue>,
    },
    /// A response to one of our requests.
    Response {
        /// The id of our request.
        id: Option<Id>,
        /// `result` (raw) or `error`.
        outcome: Result<&'a RawValue, ErrorObject>,
        /// `api` beside `result`, as the CONNACK sample has it (NXg §5.2.2).
        api: Option<&'a RawValue>,
    },
}

/// A message that cannot be handled, with the JSON-RPC error to answer it with.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejected {
    /// The JSON-RPC error code.
    pub code: i64,
    /// Why.
    pub message: String,
    /// The id to answer with (`None`: `null`, when it is unknown).
    pub id: Option<Id>,
}

/// The members a JSON-RPC message may have, each raw; others are ignored.
#[derive(Deserialize)]
struct Members<'a> {
    #[serde(borrow, default, deserialize_with = "present")]
    jsonrpc: Option<&'a RawValue>,
    #[serde(borrow, default, deserialize_with = "present")]
    id: Option<&'a RawValue>,
    #[serde(borrow, default, deserialize_with = "present")]
    method: Option<&'a RawValue>,
    #[serde(borrow, default, deserialize_with = "present")]
    params: Option<&'a RawValue>,
    #[serde(borrow, default, deserialize_with = "present")]
    result: Option<&'a RawValue>,
    #[serde(borrow, default, deserialize_with = "present")]
    error: Option<&'a RawValue>,
    #[serde(borrow, default, deserialize_with = "present")]
    api: Option<&'a RawValue>,
}

/// A member that is present, even as `null` (serde's `Option` would read `null` as absent).
fn present<'de, D: Deserializer<'de>>(d: D) -> Result<Option<&'de RawValue>, D::Error> {
    <&RawValue>::deserialize(d).map(Some)
}

fn is_null(raw: &RawValue) -> bool {
    raw.get() == "null"
}

/// Parse one WebSocket text message.
pub fn parse(text: &str) -> Result<Incoming<'_>, Rejected> {
    if !text.trim_start().starts_with('{') {
        // An array would read as a positional struct; anything else is no request either.
        let (code, message) = match serde_json::from_str::<serde::de::IgnoredAny>(text) {
            Ok(_) => (
                rpc_codes::INVALID_REQUEST,
                "a request is a JSON object (batches are not supported)".to_owned(),
            ),
            Err(e) => (rpc_codes::PARSE, format!("invalid JSON: {e}")),
        };
        return Err(Rejected {
            code,
            message,
            id: None,
        });
    }
    let members: Members = serde_json::from_str(text).map_err(|e| {
        let (code, message) = if e.is_data() {
            (rpc_codes::INVALID_REQUEST, format!("invalid request: {e}"))
        } else {
            (rpc_codes::PARSE, format!("invalid JSON: {e}"))
        };
        Rejected {
            code,
            message,
            id: None,
        }
    })?;
    // The id first, so that the other refusals can echo it.
    let id = match members.id {
        None => None,
        Some(raw) if is_null(raw) => Some(None),
        Some(raw) => match serde_json::from_str::<Id>(raw.get()) {
            Ok(id) => Some(Some(id)),
            Err(_) => {
                return Err(Rejected {
                    code: rpc_codes::INVALID_REQUEST,
                    message: "id must be a string, a number or null".into(),
                    id: None,
                })
            }
        },
    };
    let echo = id.clone().flatten();
    let invalid = |message: &str| Rejected {
        code: rpc_codes::INVALID_REQUEST,
        message: message.into(),
        id: echo.clone(),
    };
    let version = members
        .jsonrpc
        .and_then(|raw| serde_json::from_str::<Cow<str>>(raw.get()).ok());
    if version.as_deref() != Some("2.0") {
        return Err(invalid("jsonrpc must be \"2.0\""));
    }
    if let Some(raw) = members.method {
        let method = serde_json::from_str::<Cow<str>>(raw.get())
            .map_err(|_| invalid("method must be a string"))?;
        let params = members.params.or(members.result).filter(|p| !is_null(p));
        return Ok(match id {
            Some(id) => Incoming::Request { id, method, params },
            None => Incoming::Notification { method, params },
        });
    }
    let Some(id) = id else {
        return Err(invalid("neither a request nor a response"));
    };
    let outcome = match (members.result, members.error) {
        (Some(result), None) => Ok(result),
        (None, Some(error)) => Err(ErrorObject::read(error.get())),
        _ => return Err(invalid("a response has either result or error")),
    };
    Ok(Incoming::Response {
        id,
        outcome,
        api: members.api,
    })
}

#[derive(Serialize)]
struct Request<'a, P: Serialize + ?Sized> {
    jsonrpc: &'static str,
    method: &'a str,
    id: &'a Id,
    #[serde(skip_serializing_if = "Option::is_none")]
    params: Option<&'a P>,
}

#[derive(Serialize)]
struct Response<'a, R: Serialize + ?Sized> {
    jsonrpc: &'static str,
    id: Option<&'a Id>,
    result: &'a R,
}

#[derive(Serialize)]
struct ErrorResponse<'a> {
    jsonrpc: &'static str,
    id: Option<&'a Id>,
    error: &'a ErrorObject,
}

#[derive(Serialize)]
struct NotificationMessage<'a, P: Serialize + ?Sized> {
    jsonrpc: &'static str,
    method: &'a str,
    result: &'a P,
}

#[derive(Serialize)]
struct ConnackMessage<'a> {
    jsonrpc: &'static str,
    id: Option<&'a Id>,
    result: &'static str,
    api: u32,
}

/// A request (without `params` when there are none, as the get_heartbeat sample).
pub fn request<P: Serialize + ?Sized>(id: &Id, method: Method, params: Option<&P>) -> String {
    to_json(&Request {
        jsonrpc: "2.0",
        method: method.name(),
        id,
        params,
    })
}

/// A successful answer.
pub fn response<R: Serialize + ?Sized>(id: Option<&Id>, result: &R) -> String {
    to_json(&Response {
        jsonrpc: "2.0",
        id,
        result,
    })
}

/// An error answer.
pub fn error_response(id: Option<&Id>, error: &ErrorObject) -> String {
    to_json(&ErrorResponse {
        jsonrpc: "2.0",
        id,
        error,
    })
}

/// A notification carrying its payload under `result`, as NXg SW003 §7.3.1 shows.
pub fn notification<P: Serialize + ?Sized>(method: Method, payload: &P) -> String {
    to_json(&NotificationMessage {
        jsonrpc: "2.0",
        method: method.name(),
        result: payload,
    })
}

/// The portal's answer to CONNECT: `"result": "CONNACK"` with `api` beside it (NXg §5.2.2).
pub fn connack(id: Option<&Id>, api: u32) -> String {
    to_json(&ConnackMessage {
        jsonrpc: "2.0",
        id,
        result: "CONNACK",
        api,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::Done;
    use serde_json::{json, Value};

    #[test]
    fn requests_notifications_and_responses() {
        let r = parse(r#"{"jsonrpc":"2.0","id":"7","method":"get_heartbeat"}"#).unwrap();
        assert!(matches!(
            r,
            Incoming::Request { id: Some(Id::Text(ref t)), ref method, params: None }
                if t == "7" && method == "get_heartbeat"
        ));
        let n = parse(r#"{"jsonrpc":"2.0","method":"canopen_object","result":{"v":1}}"#).unwrap();
        assert!(
            matches!(n, Incoming::Notification { params: Some(p), .. } if p.get() == r#"{"v":1}"#)
        );
        // The CONNACK of NXg SW003 §5.2.2 with `api` beside `result`.
        let c = parse(r#"{"jsonrpc":"2.0","id":1,"result":"CONNACK","api":1}"#).unwrap();
        let Incoming::Response {
            id,
            outcome: Ok(result),
            api: Some(api),
        } = c
        else {
            panic!("{c:?}")
        };
        assert_eq!(id.and_then(|i| i.counter_value()), Some(1));
        assert_eq!((result.get(), api.get()), ("\"CONNACK\"", "1"));
        // An id of null is still a request; escapes in the method name are read.
        let r = parse(r#"{"jsonrpc":"2.0","id":null,"method":"get_\u0068eartbeat"}"#).unwrap();
        assert!(
            matches!(r, Incoming::Request { id: None, ref method, .. } if method == "get_heartbeat")
        );
        let e = parse(r#"{"jsonrpc":"2.0","id":"3","error":{"code":"0x08000021","message":"m"}}"#)
            .unwrap();
        let Incoming::Response {
            outcome: Err(error),
            ..
        } = e
        else {
            panic!()
        };
        assert_eq!(error.code, 0x0800_0021);
    }

    #[test]
    fn ids_are_read_as_what_they_are_and_echoed_unchanged() {
        for id in [
            r#""7""#,
            r#""a\"b""#,
            "7",
            "-3",
            "7.5",
            "18446744073709551615",
        ] {
            let text = format!(r#"{{"jsonrpc":"2.0","id":{id},"method":"get_heartbeat"}}"#);
            let Ok(Incoming::Request { id: Some(read), .. }) = parse(&text) else {
                panic!("{text}")
            };
            assert_eq!(serde_json::to_string(&read).unwrap(), id);
        }
        assert!(matches!(
            parse(r#"{"jsonrpc":"2.0","id":"12","method":"x"}"#),
            Ok(Incoming::Request {
                id: Some(Id::Text(_)),
                ..
            })
        ));
        for bad in ["true", "[1]", "{}"] {
            let text = format!(r#"{{"jsonrpc":"2.0","id":{bad},"method":"x"}}"#);
            assert_eq!(
                parse(&text).unwrap_err().code,
                rpc_codes::INVALID_REQUEST,
                "{bad}"
            );
        }
    }

    #[test]
    fn rejects_what_is_not_json_rpc() {
        assert_eq!(parse("{").unwrap_err().code, rpc_codes::PARSE);
        assert_eq!(parse("").unwrap_err().code, rpc_codes::PARSE);
        assert_eq!(parse("[]").unwrap_err().code, rpc_codes::INVALID_REQUEST);
        let e = parse(r#"["2.0", 5, "get_heartbeat"]"#).unwrap_err();
        assert_eq!(e.code, rpc_codes::INVALID_REQUEST);
        assert_eq!(parse("[1,").unwrap_err().code, rpc_codes::PARSE);
        assert_eq!(parse("17").unwrap_err().code, rpc_codes::INVALID_REQUEST);
        let e = parse(r#"{"jsonrpc":"1.0","id":5,"method":"x"}"#).unwrap_err();
        assert_eq!(
            (e.code, e.id),
            (rpc_codes::INVALID_REQUEST, Some(Id::Number(5.into())))
        );
        let e = parse(r#"{"jsonrpc":"2.0","id":{},"method":"x"}"#).unwrap_err();
        assert_eq!((e.code, e.id), (rpc_codes::INVALID_REQUEST, None));
        let e = parse(r#"{"jsonrpc":"2.0","id":1,"method":3}"#).unwrap_err();
        assert_eq!(e.code, rpc_codes::INVALID_REQUEST);
        let e = parse(r#"{"jsonrpc":"2.0","id":1}"#).unwrap_err();
        assert_eq!(e.code, rpc_codes::INVALID_REQUEST);
        let e = parse(r#"{"jsonrpc":"2.0","id":1,"result":1,"error":{}}"#).unwrap_err();
        assert_eq!(e.code, rpc_codes::INVALID_REQUEST);
    }

    #[test]
    fn builds_messages() {
        let id = Id::Text("a".into());
        let v: Value = serde_json::from_str(&response(Some(&id), &Done::OK)).unwrap();
        assert_eq!(v, json!({"jsonrpc":"2.0","id":"a","result":{"done":0}}));
        let e = ErrorObject::new(
            crate::codes::ErrorCode::NO_OBJECT,
            "Object does not exist.".into(),
            Some("0x652099"),
        );
        let v: Value = serde_json::from_str(&error_response(Some(&id), &e)).unwrap();
        assert_eq!(
            v["error"],
            json!({"code":100794368,"message":"Object does not exist.","data":"0x652099"})
        );
        let v: Value =
            serde_json::from_str(&request::<()>(&Id::counter(4), Method::GetHeartbeat, None))
                .unwrap();
        assert_eq!(
            v,
            json!({"jsonrpc":"2.0","method":"get_heartbeat","id":"4"})
        );
        let v: Value = serde_json::from_str(&connack(Some(&id), 2)).unwrap();
        assert_eq!(
            v,
            json!({"jsonrpc":"2.0","id":"a","result":"CONNACK","api":2})
        );
    }
}
