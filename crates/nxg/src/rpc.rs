//! JSON-RPC 2.0 envelopes as the connector uses them (NXg SW003 §5–§7, DESIGN.md §4).

use serde_json::{json, Map, Value};

use crate::errors::rpc_codes;

/// A message received.
#[derive(Debug, Clone, PartialEq)]
pub enum Incoming {
    /// A request: it gets exactly one answer with the same `id`.
    Request {
        /// String or number, echoed unchanged.
        id: Value,
        /// Method name.
        method: String,
        /// Parameters (`null` when absent).
        params: Value,
    },
    /// A notification (no `id`): no answer.
    Notification {
        /// Method name.
        method: String,
        /// `params`, or `result` as the connector's own notifications carry it.
        params: Value,
    },
    /// A response to one of our requests; `rest` keeps the other members (the CONNACK's `api`).
    Response {
        /// The id of our request.
        id: Value,
        /// `result`, if successful.
        result: Option<Value>,
        /// `error`, if not.
        error: Option<Value>,
        /// Members beside `result`/`error`.
        rest: Map<String, Value>,
    },
}

/// A message that cannot be handled, with the JSON-RPC error to answer it with.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejected {
    /// The JSON-RPC error code.
    pub code: i64,
    /// Why.
    pub message: String,
    /// The id to answer with (`null` when unknown).
    pub id: Value,
}

fn valid_id(id: &Value) -> bool {
    matches!(id, Value::String(_) | Value::Number(_) | Value::Null)
}

/// Parse one WebSocket text message.
pub fn parse(text: &str) -> Result<Incoming, Rejected> {
    let value: Value = serde_json::from_str(text).map_err(|e| Rejected {
        code: rpc_codes::PARSE,
        message: format!("invalid JSON: {e}"),
        id: Value::Null,
    })?;
    let Value::Object(mut obj) = value else {
        return Err(Rejected {
            code: rpc_codes::INVALID_REQUEST,
            message: "a request is a JSON object (batches are not supported)".into(),
            id: Value::Null,
        });
    };
    let id = obj.remove("id");
    let invalid = |message: &str, id: Option<Value>| Rejected {
        code: rpc_codes::INVALID_REQUEST,
        message: message.into(),
        id: id.filter(valid_id).unwrap_or(Value::Null),
    };
    if obj.get("jsonrpc").and_then(Value::as_str) != Some("2.0") {
        return Err(invalid("jsonrpc must be \"2.0\"", id));
    }
    if id.as_ref().is_some_and(|i| !valid_id(i)) {
        return Err(invalid("id must be a string, a number or null", None));
    }
    match obj.remove("method") {
        Some(Value::String(method)) => {
            let params = obj
                .remove("params")
                .or_else(|| obj.remove("result"))
                .unwrap_or(Value::Null);
            Ok(match id {
                Some(id) => Incoming::Request { id, method, params },
                None => Incoming::Notification { method, params },
            })
        }
        Some(_) => Err(invalid("method must be a string", id)),
        None => {
            let Some(id) = id else {
                return Err(invalid("neither a request nor a response", None));
            };
            let result = obj.remove("result");
            let error = obj.remove("error");
            if result.is_none() == error.is_none() {
                return Err(invalid("a response has either result or error", Some(id)));
            }
            obj.remove("jsonrpc");
            Ok(Incoming::Response {
                id,
                result,
                error,
                rest: obj,
            })
        }
    }
}

/// A successful response.
pub fn result(id: &Value, result: Value) -> String {
    json!({"jsonrpc": "2.0", "id": id, "result": result}).to_string()
}

/// An error response; `code` is a JSON-RPC code or a CiA 301 abort code (as a number).
pub fn error(id: &Value, code: i64, message: &str, data: Option<Value>) -> String {
    let mut error = json!({"code": code, "message": message});
    if let Some(data) = data {
        error["data"] = data;
    }
    json!({"jsonrpc": "2.0", "id": id, "error": error}).to_string()
}

/// A request (without `params` when they are `null`, as the get_heartbeat sample).
pub fn request(id: &Value, method: &str, params: Value) -> String {
    let mut request = json!({"jsonrpc": "2.0", "method": method, "id": id});
    if !params.is_null() {
        request["params"] = params;
    }
    request.to_string()
}

/// A notification carrying its payload under `result`, as NXg SW003 §7.3.1 shows.
pub fn notification(method: &str, payload: Value) -> String {
    json!({"jsonrpc": "2.0", "method": method, "result": payload}).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_notifications_and_responses() {
        let r = parse(r#"{"jsonrpc":"2.0","id":"7","method":"get_heartbeat"}"#).unwrap();
        assert_eq!(
            r,
            Incoming::Request {
                id: json!("7"),
                method: "get_heartbeat".into(),
                params: Value::Null
            }
        );
        let n = parse(r#"{"jsonrpc":"2.0","method":"canopen_object","result":{"v":1}}"#).unwrap();
        assert!(matches!(n, Incoming::Notification { params, .. } if params == json!({"v":1})));
        // The CONNACK of NXg SW003 §5.2.2 with `api` beside `result`.
        let c = parse(r#"{"jsonrpc":"2.0","id":1,"result":"CONNACK","api":1}"#).unwrap();
        let Incoming::Response { result, rest, .. } = c else {
            panic!()
        };
        assert_eq!(result, Some(json!("CONNACK")));
        assert_eq!(rest.get("api"), Some(&json!(1)));
    }

    #[test]
    fn rejects_what_is_not_json_rpc() {
        assert_eq!(parse("{").unwrap_err().code, rpc_codes::PARSE);
        assert_eq!(parse("[]").unwrap_err().code, rpc_codes::INVALID_REQUEST);
        let e = parse(r#"{"jsonrpc":"1.0","id":5,"method":"x"}"#).unwrap_err();
        assert_eq!((e.code, e.id), (rpc_codes::INVALID_REQUEST, json!(5)));
        let e = parse(r#"{"jsonrpc":"2.0","id":{},"method":"x"}"#).unwrap_err();
        assert_eq!((e.code, e.id), (rpc_codes::INVALID_REQUEST, Value::Null));
        let e = parse(r#"{"jsonrpc":"2.0","id":1,"method":3}"#).unwrap_err();
        assert_eq!(e.code, rpc_codes::INVALID_REQUEST);
        let e = parse(r#"{"jsonrpc":"2.0","id":1}"#).unwrap_err();
        assert_eq!(e.code, rpc_codes::INVALID_REQUEST);
    }

    #[test]
    fn builds_answers() {
        assert_eq!(
            result(&json!("a"), json!({"done": 0})),
            r#"{"id":"a","jsonrpc":"2.0","result":{"done":0}}"#
        );
        let e: Value =
            serde_json::from_str(&error(&json!(3), 100794368, "m", Some(json!("0x652099"))))
                .unwrap();
        assert_eq!(e["error"]["code"], json!(100794368));
        assert_eq!(e["error"]["data"], json!("0x652099"));
    }
}
