//! The JSON-RPC envelope and every NXg message type, from arbitrary text: no panic, and a
//! request that parses re-encodes to one that parses the same.
#![no_main]

use libfuzzer_sys::fuzz_target;
use nxg::msg::{self, Incoming, Method};

fn typed(params: &str) {
    let _ = serde_json::from_str::<msg::Connect>(params);
    let _ = serde_json::from_str::<msg::TokenParams>(params);
    let _ = serde_json::from_str::<msg::ElevateParams>(params);
    let _ = serde_json::from_str::<msg::ElevateAnswer>(params);
    let _ = serde_json::from_str::<msg::GetParams>(params);
    let _ = serde_json::from_str::<msg::ObjectAnswer>(params);
    let _ = serde_json::from_str::<msg::PutParams>(params);
    let _ = serde_json::from_str::<msg::PutAnswer>(params);
    let _ = serde_json::from_str::<msg::RegParams>(params);
    let _ = serde_json::from_str::<msg::UnregParams>(params);
    let _ = serde_json::from_str::<msg::Notification>(params);
    let _ = serde_json::from_str::<msg::RegEventParams>(params);
    let _ = serde_json::from_str::<msg::UnregEventParams>(params);
    let _ = serde_json::from_str::<msg::EventNotification>(params);
    let _ = serde_json::from_str::<msg::ErrorObject>(params);
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    typed(text);
    let Ok(incoming) = msg::parse(text) else {
        return;
    };
    if let Incoming::Request {
        id: Some(id),
        method,
        params,
    } = incoming
    {
        if let Some(params) = params {
            typed(params.get());
        }
        let Some(known) = Method::ALL.iter().find(|m| m.name() == method) else {
            return;
        };
        let again = msg::request(&id, *known, params);
        match msg::parse(&again) {
            Ok(Incoming::Request {
                id: Some(id2),
                method: m2,
                params: p2,
            }) => {
                assert_eq!(id, id2);
                assert_eq!(method, m2);
                assert_eq!(params.map(|p| p.get()), p2.map(|p| p.get()));
            }
            other => panic!("{again} re-parsed as {other:?}"),
        }
    }
});
