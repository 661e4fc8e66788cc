//! The API contract holds (docs/PORTAL.md §Operator REST API): requests generated from
//! `/api/v1/openapi.json` itself — valid ones and deliberately broken ones — are sent to a
//! portal with a lift online, and the test fails on any status the document does not list for the
//! operation, any JSON answer that does not match the schema documented for its status, any 5xx,
//! and any schema-valid request the portal refuses as malformed (400, 415, 422 of its own).
//!
//! Each operation's `x-least-role` is held too: a valid request with a key of every lower role
//! is refused with 403 naming the role.
//!
//! Valid values come from the document: a parameter's or body's `examples` where the lift
//! decides what is valid (an object's address, a value for its type), otherwise from the schema
//! (enum, integer and number bounds, `pattern`). A refusal by the lift's gateway (a value a
//! read-only object does not take) is an answer, not a contract breach: it carries the CiA/NXg
//! code, while the portal's own refusals carry the HTTP status as their code.
//!
//! The schema checker below covers the subset of OpenAPI 3.1 (JSON Schema 2020-12) the document
//! uses (`$ref`, `type` as a name or a list of names, `oneOf`, `allOf`, `enum`, `required`,
//! `properties`, `items`, `minimum`, `maximum`); schemathesis checks the rest.

use std::collections::BTreeMap;

use cloud::client::{Body, Client, Reply};
use cloud_types::users::Role;
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::TestRunner;
use serde_json::{json, Value};
use testkit::constants::LIFT;
use testkit::portal::Rig;

/// Requests generated per operation and kind.
const CASES: usize = 12;

/// One request to send and what it is.
#[derive(Debug, Clone)]
struct Request {
    method: String,
    path: String,
    query: Vec<(String, String)>,
    body: Payload,
    /// Whether every part is valid per the document.
    valid: bool,
    /// What was broken, for invalid ones.
    broken: &'static str,
    /// Without the API key.
    anonymous: bool,
}

#[derive(Debug, Clone)]
enum Payload {
    None,
    Json(Value),
    Text(&'static str),
    Form,
}

/// The document, with `$ref`s resolved on demand.
struct Document(Value);

impl Document {
    fn resolve<'a>(&'a self, schema: &'a Value) -> &'a Value {
        match schema.get("$ref").and_then(Value::as_str) {
            Some(r) => {
                let name = r.trim_start_matches("#/components/schemas/");
                &self.0["components"]["schemas"][name]
            }
            None => schema,
        }
    }

    /// Whether `value` matches `schema`; the path to the first mismatch otherwise.
    fn check(&self, schema: &Value, value: &Value, at: &str) -> Result<(), String> {
        let schema = self.resolve(schema);
        if let Some(all) = schema.get("allOf").and_then(Value::as_array) {
            for part in all {
                self.check(part, value, at)?;
            }
        }
        if let Some(options) = schema.get("oneOf").and_then(Value::as_array) {
            let fitting = options
                .iter()
                .filter(|o| self.check(o, value, at).is_ok())
                .count();
            if fitting != 1 {
                return Err(format!("{at}: {value} fits {fitting} of {options:?}"));
            }
        }
        if let Some(options) = schema.get("enum").and_then(Value::as_array) {
            if !options.contains(value) {
                return Err(format!("{at}: {value} is not one of {options:?}"));
            }
        }
        let kinds = types(schema);
        let fits = |kind: &str| match kind {
            "object" => value.is_object(),
            "array" => value.is_array(),
            "string" => value.is_string(),
            "integer" => value.is_i64() || value.is_u64(),
            "number" => value.is_number(),
            "boolean" => value.is_boolean(),
            "null" => value.is_null(),
            _ => true,
        };
        if !kinds.is_empty() && !kinds.iter().any(|k| fits(k)) {
            return Err(format!("{at}: {value} is not of type {kinds:?}"));
        }
        if let Some(n) = value.as_f64() {
            if schema
                .get("minimum")
                .and_then(Value::as_f64)
                .is_some_and(|m| n < m)
                || schema
                    .get("maximum")
                    .and_then(Value::as_f64)
                    .is_some_and(|m| n > m)
            {
                return Err(format!("{at}: {n} out of the documented range"));
            }
        }
        if let Some(object) = value.as_object() {
            for name in schema["required"].as_array().into_iter().flatten() {
                let name = name.as_str().unwrap_or_default();
                if !object.contains_key(name) {
                    return Err(format!("{at}: no {name:?}"));
                }
            }
            if let Some(properties) = schema["properties"].as_object() {
                for (name, v) in object {
                    if let Some(s) = properties.get(name) {
                        self.check(s, v, &format!("{at}.{name}"))?;
                    }
                }
            }
        }
        if let (Some(items), Some(list)) = (schema.get("items"), value.as_array()) {
            for (i, v) in list.iter().enumerate() {
                self.check(items, v, &format!("{at}[{i}]"))?;
            }
        }
        Ok(())
    }

    /// Values valid for `schema`, or the `example` or one of the `examples` of `place` (a
    /// parameter or a media type) when the document gives some.
    fn valid(&self, schema: &Value, place: &Value) -> BoxedStrategy<Value> {
        let mut listed: Vec<Value> = place["examples"]
            .as_object()
            .map(|e| e.values().map(|x| x["value"].clone()).collect())
            .unwrap_or_default();
        listed.extend(place.get("example").cloned());
        if !listed.is_empty() {
            return proptest::sample::select(listed).boxed();
        }
        let schema = self.resolve(schema).clone();
        if let Some(options) = schema["enum"].as_array().filter(|o| !o.is_empty()) {
            return proptest::sample::select(options.clone()).boxed();
        }
        let int = |key: &str, default: i64| schema[key].as_i64().unwrap_or(default);
        match types(&schema).into_iter().find(|t| *t != "null") {
            Some("integer") => (int("minimum", 0)..=int("maximum", 1000))
                .prop_map(|n| json!(n))
                .boxed(),
            Some("number") => (0.0..100.0f64).prop_map(|n| json!(n)).boxed(),
            Some("boolean") => any::<bool>().prop_map(|b| json!(b)).boxed(),
            Some("string") => {
                let pattern = schema["pattern"].as_str().unwrap_or("[a-z]{1,8}");
                let pattern = pattern.trim_start_matches('^').trim_end_matches('$');
                proptest::string::string_regex(pattern)
                    .map(|s| s.prop_map(Value::from).boxed())
                    .unwrap_or_else(|_| Just(json!("x")).boxed())
            }
            _ => Just(json!({})).boxed(),
        }
    }
}

/// The type names of `schema`: `type` as one name or a list of them (JSON Schema 2020-12).
fn types(schema: &Value) -> Vec<&str> {
    match &schema["type"] {
        Value::String(one) => vec![one.as_str()],
        Value::Array(many) => many.iter().filter_map(Value::as_str).collect(),
        _ => Vec::new(),
    }
}

/// The document's operations: (method, path template, operation).
fn operations(doc: &Document) -> Vec<(String, String, Value)> {
    let mut all = Vec::new();
    for (path, ops) in doc.0["paths"].as_object().into_iter().flatten() {
        for (method, op) in ops.as_object().into_iter().flatten() {
            all.push((method.to_uppercase(), path.clone(), op.clone()));
        }
    }
    all
}

/// A valid request for `op`.
fn valid_request(
    doc: &Document,
    method: &str,
    template: &str,
    op: &Value,
) -> BoxedStrategy<Request> {
    let mut parts: Vec<BoxedStrategy<(String, String, Value)>> = Vec::new();
    for p in op["parameters"].as_array().into_iter().flatten() {
        let (name, place) = (
            p["name"].as_str().unwrap_or_default(),
            p["in"].as_str().unwrap_or_default(),
        );
        let values = doc.valid(&p["schema"], p);
        let (name, place) = (name.to_owned(), place.to_owned());
        let part = if p["required"] == true || place == "path" {
            values
                .prop_map(move |v| (place.clone(), name.clone(), v))
                .boxed()
        } else {
            // An optional one is left out now and then.
            proptest::option::of(values)
                .prop_map(move |v| (place.clone(), name.clone(), v.unwrap_or(Value::Null)))
                .boxed()
        };
        parts.push(part);
    }
    let media = &op["requestBody"]["content"]["application/json"];
    let body = if media.is_null() {
        Just(Payload::None).boxed()
    } else {
        doc.valid(&media["schema"], media)
            .prop_map(Payload::Json)
            .boxed()
    };
    let (method, template) = (method.to_owned(), template.to_owned());
    (parts, body)
        .prop_map(move |(parts, body)| {
            let mut path = template.clone();
            let mut query = Vec::new();
            for (place, name, value) in parts {
                let text = match &value {
                    Value::Null => continue,
                    Value::String(s) => s.clone(),
                    other => other.to_string(),
                };
                if place == "path" {
                    path = path.replace(&format!("{{{name}}}"), &percent_encoded(&text));
                } else {
                    query.push((name, text));
                }
            }
            Request {
                method: method.clone(),
                path,
                query,
                body,
                valid: true,
                broken: "",
                anonymous: false,
            }
        })
        .boxed()
}

/// `text` as a path segment: every byte but the unreserved ones (RFC 3986 §2.3) as `%XX`.
fn percent_encoded(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' => {
                char::from(b).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// `request` with one part broken as the document says it must not be: one request, or for a
/// body with bounded properties one per property.
fn broken(doc: &Document, request: &Request, op: &Value, which: usize) -> Vec<Request> {
    let mut r = request.clone();
    r.valid = false;
    let has_body = !op["requestBody"].is_null();
    let queries: Vec<&Value> = op["parameters"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|p| p["in"] == "query" && p["schema"]["type"] != "string")
        .collect();
    match which % 8 {
        0 => {
            r.anonymous = true;
            r.broken = "no API key";
        }
        1 if r.path.starts_with("/api/v1/lifts/") => {
            let rest = r.path.trim_start_matches("/api/v1/lifts/");
            let tail = rest
                .split_once('/')
                .map_or(String::new(), |(_, t)| format!("/{t}"));
            r.path = format!("/api/v1/lifts/9-9-NOSUCHLIFT{tail}");
            r.broken = "an unknown lift";
        }
        2 if has_body => {
            r.body = Payload::Text("{\"value\": ");
            r.broken = "a body that is not JSON";
        }
        3 if has_body => {
            r.body = Payload::Json(json!({"unexpected": true}));
            r.broken = "a body without its required fields";
        }
        4 if has_body => {
            r.body = Payload::Json(json!([1, 2, 3]));
            r.broken = "a body of the wrong type";
        }
        5 if !queries.is_empty() => {
            let p = queries[which % queries.len()];
            let name = p["name"].as_str().unwrap_or_default().to_owned();
            r.query.retain(|(n, _)| *n != name);
            r.query.push((name, "not-a-number".into()));
            r.broken = "a query parameter of the wrong type";
        }
        6 if has_body => {
            r.body = Payload::Form;
            r.broken = "a form instead of JSON";
        }
        7 if has_body => {
            let schema = &op["requestBody"]["content"]["application/json"]["schema"];
            let Payload::Json(Value::Object(body)) = &r.body else {
                return Vec::new();
            };
            return out_of_range(doc, doc.resolve(schema))
                .into_iter()
                .map(|(name, value)| {
                    let mut body = body.clone();
                    body.insert(name, value);
                    Request {
                        body: Payload::Json(Value::Object(body)),
                        broken: "a body property out of its documented range",
                        ..r.clone()
                    }
                })
                .collect();
        }
        _ => return Vec::new(),
    }
    vec![r]
}

/// For each documented bound of a property of the object `schema`, the property and a value
/// just past it (bounds beyond what a JSON number holds exactly are left alone).
fn out_of_range(doc: &Document, schema: &Value) -> Vec<(String, Value)> {
    const EXACT: f64 = 9_007_199_254_740_992.0;
    let mut past = Vec::new();
    for (name, property) in schema["properties"].as_object().into_iter().flatten() {
        let property = doc.resolve(property);
        let integer = types(property).contains(&"integer");
        let bounds = [
            property["minimum"].as_f64().map(|min| min - 1.0),
            property["maximum"].as_f64().map(|max| max + 1.0),
        ];
        for value in bounds.into_iter().flatten().filter(|v| v.abs() < EXACT) {
            let value = if integer {
                json!(value as i64)
            } else {
                json!(value)
            };
            past.push((name.clone(), value));
        }
    }
    past
}

async fn send(client: &Client, anonymous: &Client, r: &Request) -> Reply {
    let mut path = r.path.clone();
    if !r.query.is_empty() {
        path.push('?');
        path.push_str(&serde_urlencoded::to_string(&r.query).unwrap_or_default());
    }
    let client = if r.anonymous { anonymous } else { client };
    let body = match &r.body {
        Payload::None => Body::Empty,
        Payload::Json(v) => Body::Json(v),
        Payload::Text(t) => Body::Text(t),
        Payload::Form => Body::Form(&[("value", "1")]),
    };
    client
        .exchange(&r.method, &path, body)
        .await
        .unwrap_or_else(|e| panic!("{r:?}: {e}"))
}

/// Whether an error answer is the portal's own refusal (its code is the HTTP status) rather
/// than the gateway's (a CiA/NXg code).
fn portal_refusal(reply: &Reply) -> bool {
    reply.body["code"].as_i64() == Some(i64::from(reply.status))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_portal_keeps_the_contract_of_its_openapi_document() {
    let rig = Rig::builder()
        .portal(|c| c.server.requests_per_key_s = 0)
        .start()
        .await;
    rig.online().await;
    let (status, document) = rig.call("GET", "/api/v1/openapi.json", None, None).await;
    assert_eq!(status, 200);
    let doc = Document(document);
    let client = Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca)).unwrap();
    let anonymous = Client::new(&rig.url(), None, Some(&rig.ca)).unwrap();
    let mut runner = TestRunner::deterministic();
    let mut sent: BTreeMap<String, usize> = BTreeMap::new();
    let mut failures = Vec::new();
    for (method, template, op) in operations(&doc) {
        let streams = op["responses"]["200"]["content"]
            .get("text/event-stream")
            .is_some();
        let strategy = valid_request(&doc, &method, &template, &op);
        for case in 0..CASES {
            let valid = strategy.new_tree(&mut runner).expect("a request").current();
            let requests = std::iter::once(valid.clone()).chain(broken(&doc, &valid, &op, case));
            for r in requests {
                *sent.entry(format!("{method} {template}")).or_default() += 1;
                let reply = if streams && !r.anonymous && r.path.contains(LIFT) {
                    // An event stream stays open: only its status is checked.
                    match client.events(&with_query(&r)).await.expect("an answer") {
                        Ok(_) => Reply {
                            status: 200,
                            retry_after: None,
                            body: Value::Null,
                            set_cookie: None,
                            media: Some("text/event-stream".into()),
                        },
                        Err((status, body)) => Reply {
                            status,
                            retry_after: None,
                            body,
                            set_cookie: None,
                            media: None,
                        },
                    }
                } else {
                    send(&client, &anonymous, &r).await
                };
                if let Err(why) = judge(&doc, &op, &r, &reply) {
                    failures.push(format!(
                        "{method} {}: {why}\n  request: {r:?}\n  answer: {} {}",
                        r.path, reply.status, reply.body
                    ));
                }
            }
        }
    }
    eprintln!("contract: requests per operation {sent:?}");
    failures.extend(roles_below(&rig, &doc, &mut runner).await);
    assert!(
        sent.len() >= 16,
        "every operation of the document: {sent:?}"
    );
    assert!(
        failures.is_empty(),
        "{} breaches:\n{}",
        failures.len(),
        failures.join("\n")
    );
    rig.stop().await;
}

/// The breaches of the operations' `x-least-role`: a valid request with a key of each lower
/// role must be refused (403, naming the role).
async fn roles_below(rig: &Rig, doc: &Document, runner: &mut TestRunner) -> Vec<String> {
    let mut clients = Vec::new();
    for role in Role::ALL {
        let key = crate::roles::user(rig, &format!("contract-{role}"), role).await;
        let client = Client::new(&rig.url(), Some(&key), Some(&rig.ca)).expect("a client");
        clients.push((role, client));
    }
    let anonymous = Client::new(&rig.url(), None, Some(&rig.ca)).expect("a client");
    let mut failures = Vec::new();
    let mut refused = 0;
    for (method, template, op) in operations(doc) {
        let least = op["x-least-role"]
            .as_str()
            .and_then(Role::from_name)
            .unwrap_or_else(|| panic!("{method} {template}: no x-least-role"));
        let strategy = valid_request(doc, &method, &template, &op);
        for (role, client) in clients.iter().filter(|(role, _)| *role < least) {
            let r = strategy.new_tree(runner).expect("a request").current();
            let reply = send(client, &anonymous, &r).await;
            refused += 1;
            let named = reply.body["message"]
                .as_str()
                .is_some_and(|m| m.contains("role"));
            if reply.status != 403 || !named {
                failures.push(format!(
                    "{method} {}: a {role} (the document says {least} at least) got {} {}",
                    r.path, reply.status, reply.body
                ));
            }
        }
    }
    assert!(refused >= 30, "requests below the least role: {refused}");
    failures
}

fn with_query(r: &Request) -> String {
    if r.query.is_empty() {
        return r.path.clone();
    }
    format!(
        "{}?{}",
        r.path,
        serde_urlencoded::to_string(&r.query).unwrap_or_default()
    )
}

/// The breach `reply` is to `request` under the document, if any.
fn judge(doc: &Document, op: &Value, r: &Request, reply: &Reply) -> Result<(), String> {
    let code = reply.status.to_string();
    let Some(documented) = op["responses"].get(&code) else {
        return Err(format!("status {code} is not documented"));
    };
    if reply.status >= 500 {
        return Err(format!("a server error ({code})"));
    }
    if r.valid && matches!(reply.status, 400 | 415 | 422) && portal_refusal(reply) {
        return Err("a schema-valid request refused as malformed".into());
    }
    if !r.valid && reply.status < 300 {
        return Err(format!("{} accepted", r.broken));
    }
    // The schema of the media type answered (a CSV answer is a string); an event stream's
    // status alone is checked.
    let media = reply.media.as_deref().unwrap_or("application/json");
    let content = &documented["content"];
    if !content.is_null() && content.get(media).is_none() {
        return Err(format!("media type {media} is not documented for {code}"));
    }
    if media == "text/event-stream" {
        return Ok(());
    }
    if let Some(schema) = content[media].get("schema") {
        let body = match media {
            "application/json" => reply.body.clone(),
            _ => Value::String(
                reply
                    .body
                    .as_str()
                    .map(str::to_owned)
                    .unwrap_or_else(|| reply.body.to_string()),
            ),
        };
        doc.check(schema, &body, "body")?;
    }
    Ok(())
}
