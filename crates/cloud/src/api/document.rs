//! The OpenAPI document of the operator API (docs/PORTAL.md §Operator REST API), generated from
//! the code: each operation from its handler's `#[utoipa::path]` (its parameters and bodies are
//! the handler's own types, their bounds the ones the handler enforces), each schema from the
//! type the portal reads or writes, and the routes registered from the same list
//! ([`super::routes`]), so no route exists without its operation. What every operation answers
//! alike — an unknown key, a role below the operation's, too many requests, a body that is not
//! JSON of the documented shape, the database away — is added here once ([`Refusals`]).

use std::collections::btree_map::Entry;
use std::collections::BTreeMap;

use utoipa::openapi::extensions::Extensions;
use utoipa::openapi::header::HeaderBuilder;
use utoipa::openapi::path::{Operation, ParameterIn};
use utoipa::openapi::security::{ApiKey, ApiKeyValue, HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::{Content, ObjectBuilder, OpenApi, RefOr, Response, ResponseBuilder, Type};
use utoipa::{IntoResponses, Modify, ToSchema};

use nxg::msg::ErrorObject;

/// The document's frame: what the operations do not say themselves.
#[derive(utoipa::OpenApi)]
#[openapi(
    info(
        title = "canlift portal operator API",
        version = "1",
        description = "Operator API of the canlift cloud portal (NXg CANopen-Lift Connector). \
            Authenticate with `Authorization: Bearer API_KEY`. The web UI's session cookie is \
            accepted too; with it, requests other than GET must carry the page's \
            `X-CSRF-Token`. Every operation names the least role that may call it \
            (x-least-role: viewer < technician < engineer < admin); a key or session of a lower \
            role gets 403. The key an account was created with acts as the account's admin. \
            Errors are JSON-RPC error objects: the portal's own refusals carry the HTTP status \
            as their code, a gateway's refusals its CiA 301 abort code or NXg error code."
    ),
    tags(
        (name = "lifts", description = "The account's lifts: list, retire"),
        (name = "objects", description = "Reading and writing a lift's CANopen objects through its gateway (NXg §6), elevation"),
        (name = "history", description = "Stored values of an object over a period"),
        (name = "subscriptions", description = "Subscriptions held by the account and the live event stream (Server-Sent Events)"),
        (name = "tokens", description = "A lift's cloud token: rotate, reset"),
        (name = "alarms", description = "Alarms and the stored bus events of lifts"),
        (name = "audit", description = "Who did what to which lift"),
        (name = "users", description = "The account's users and API keys (administrators)"),
        (name = "reports", description = "Availability and fault figures of the account's lifts over any period, the monthly report, the availability target (docs/PORTAL.md §Availability)"),
    ),
    security(("bearer" = []), ("session" = [])),
    components(schemas(ErrorObject)),
)]
pub(super) struct Frame;

/// The answers every operation may give besides its own, and the ways to authenticate: applied
/// to the whole document, once the operations are in it.
pub(super) struct Refusals;

impl Modify for Refusals {
    fn modify(&self, openapi: &mut OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
        components.add_security_scheme(
            "session",
            SecurityScheme::ApiKey(ApiKey::Cookie(ApiKeyValue::with_description(
                "canlift_session",
                "Web UI session (from POST /login); PUT, POST and DELETE also need the X-CSRF-Token header.",
            ))),
        );
        for item in openapi.paths.paths.values_mut() {
            let operations = [
                &mut item.get,
                &mut item.put,
                &mut item.post,
                &mut item.delete,
            ];
            for operation in operations.into_iter().flatten() {
                add_refusals(operation);
            }
        }
    }
}

/// `operation` with the refusals it shares with every other, where it does not say them itself.
fn add_refusals(operation: &mut Operation) {
    let least = least_role(operation.extensions.as_ref());
    let has_query = operation
        .parameters
        .iter()
        .flatten()
        .any(|p| matches!(p, RefOr::T(p) if p.parameter_in == ParameterIn::Query));
    let has_body = operation.request_body.is_some();
    let mut shared: Vec<(u16, String)> = vec![(
        401,
        "no, an unknown, an expired or a revoked API key or session".into(),
    )];
    if let Some(role) = least.filter(|r| r != "viewer") {
        shared.push((
            403,
            format!("the caller's role does not include this operation (it needs {role})"),
        ));
    }
    if has_query {
        shared.push((
            400,
            "a malformed query: a parameter of the wrong type or beyond its bounds".into(),
        ));
    }
    if has_body {
        shared.push((
            400,
            "a body that is not JSON, or a value beyond a documented bound".into(),
        ));
        shared.push((415, "the body is not application/json".into()));
        shared.push((
            422,
            "the body is JSON of another shape than documented".into(),
        ));
    }
    shared.push((503, "the database is unavailable".into()));
    let responses = &mut operation.responses.responses;
    for (status, text) in shared {
        match responses.entry(status.to_string()) {
            Entry::Vacant(place) => {
                place.insert(refusal(&text));
            }
            // The operation's own meaning of the status first, then the shared one: a 400 is
            // both "no such name" and "a malformed query".
            Entry::Occupied(mut place) => {
                if let RefOr::T(response) = place.get_mut() {
                    if !response.description.contains(&text) {
                        response.description = format!("{}; or {text}", response.description);
                    }
                }
            }
        }
    }
    responses.entry("429".into()).or_insert_with(|| {
        refused("too many requests with this API key ([server] requests_per_key_s), or for this lift's gateway")
            .header(
                "Retry-After",
                HeaderBuilder::new()
                    .schema(Some(ObjectBuilder::new().schema_type(Type::Integer).minimum(Some(1))))
                    .description(Some("seconds to wait"))
                    .build(),
            )
            .build()
            .into()
    });
}

/// The `x-least-role` an operation declares.
fn least_role(extensions: Option<&Extensions>) -> Option<String> {
    extensions?.get("x-least-role")?.as_str().map(str::to_owned)
}

/// A refusal: `text` with an error object.
fn refusal(text: &str) -> RefOr<Response> {
    refused(text).build().into()
}

/// A refusal to build on: `text` with an error object.
fn refused(text: &str) -> ResponseBuilder {
    let error = RefOr::Ref(utoipa::openapi::Ref::from_schema_name(ErrorObject::name()));
    ResponseBuilder::new()
        .description(text)
        .content("application/json", Content::new(Some(error)))
}

/// Refusals that several operations share, named once.
macro_rules! refusals {
    ($($(#[$doc:meta])* $name:ident: $($status:literal $text:literal),+;)*) => {$(
        $(#[$doc])*
        pub(super) struct $name;

        impl IntoResponses for $name {
            fn responses() -> BTreeMap<String, RefOr<Response>> {
                BTreeMap::from([$(($status.to_string(), refusal($text))),+])
            }
        }
    )*};
}

refusals! {
    /// The lift is not one of the caller's account.
    NoLift: 404 "no such lift (or not the account's)";
    /// Neither the lift nor, on it, the object.
    NoObject: 404 "no such lift (or not the account's), or no such object on it";
    /// A write the caller may not make.
    WriteRefused: 403 "the caller's role does not include this operation (it needs technician), or the object needs a privilege the caller does not hold: writing above privilege 0 needs the role engineer and an elevation by the same user on the gateway's current connection; also the gateway's own refusal of rights";
    /// A user or key of another account, or none.
    NoSuchUser: 404 "no such user or key in the caller's account";
    /// The lift's gateway could not be asked.
    GatewayAway: 503 "the gateway is offline",
        504 "the gateway did not answer in time";
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use serde_json::Value;

    /// Every `$ref` in `value`.
    fn refs<'a>(value: &'a Value, found: &mut Vec<&'a str>) {
        match value {
            Value::Object(fields) => {
                if let Some(Value::String(r)) = fields.get("$ref") {
                    found.push(r);
                }
                fields.values().for_each(|v| refs(v, found));
            }
            Value::Array(items) => items.iter().for_each(|v| refs(v, found)),
            _ => {}
        }
    }

    #[test]
    fn every_operation_is_named_tagged_and_says_who_may_call_it() {
        let document = serde_json::to_value(super::super::document()).expect("JSON");
        let tags: BTreeSet<&str> = document["tags"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|t| t["name"].as_str())
            .collect();
        let mut ids = BTreeSet::new();
        let mut operations = 0;
        for (path, item) in document["paths"].as_object().expect("paths") {
            for (method, op) in item.as_object().expect("an item") {
                let at = format!("{method} {path}");
                operations += 1;
                let id = op["operationId"].as_str().expect(&at);
                assert!(ids.insert(id.to_owned()), "{at}: {id} twice");
                let tag = op["tags"][0].as_str().expect(&at);
                assert!(
                    tags.contains(tag),
                    "{at}: tag {tag} is not in the document's tags"
                );
                let role = op["x-least-role"].as_str().expect(&at);
                assert!(
                    ["viewer", "technician", "engineer", "admin"].contains(&role),
                    "{at}: {role}"
                );
                let responses = op["responses"].as_object().expect(&at);
                assert!(
                    responses.keys().any(|s| s.starts_with('2')),
                    "{at}: no success"
                );
                for shared in ["401", "429", "503"] {
                    assert!(responses.contains_key(shared), "{at}: no {shared}");
                }
                assert_eq!(
                    responses.contains_key("403"),
                    role != "viewer" || at.contains("/events"),
                    "{at}: 403 documented as its role says"
                );
                if !op["requestBody"].is_null() {
                    for malformed in ["400", "415", "422"] {
                        assert!(responses.contains_key(malformed), "{at}: no {malformed}");
                    }
                }
            }
        }
        assert_eq!(operations, 28, "the operator API's operations");
        let mut found = Vec::new();
        refs(&document, &mut found);
        assert!(
            found.len() > 100,
            "schemas are referenced, not inlined: {}",
            found.len()
        );
        for r in found {
            let name = r.trim_start_matches("#/components/schemas/");
            assert!(
                document["components"]["schemas"].get(name).is_some(),
                "{r} is not in the document"
            );
        }
    }
}
