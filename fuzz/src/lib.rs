//! What the fuzz targets share: splitting one input into several messages, the CiA 417 catalog
//! as a gateway's metadata, a gateway's and a portal's settings, a sample object dictionary.

use std::sync::{Arc, OnceLock};
use std::time::Duration;

use lift417::catalog::Catalog;
use nxg::gateway::{Context, Identity, Lookup, Metadata, Policy, Settings, Target};
use nxg::meta::Texts;

/// The messages of one input: its parts between NUL bytes (at most 64), as text.
pub fn messages(data: &[u8]) -> impl Iterator<Item = String> + '_ {
    data.split(|b| *b == 0)
        .take(64)
        .map(|m| String::from_utf8_lossy(m).into_owned())
}

/// The catalog describing the lift controller (node 1), as the gateway's tests have it.
struct ControllerCatalog;

impl Metadata for ControllerCatalog {
    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup {
        if target.net == 1 && target.node == 1 {
            Catalog::builtin().describe(None, index, sub)
        } else {
            Lookup::Unknown
        }
    }

    fn object_texts(&self, _: Target, index: u16) -> Option<(Texts, Texts)> {
        Catalog::builtin().object_texts(None, index)
    }

    fn text<'a>(&'a self, texts: &'a Texts, p: &str, a: &str) -> Option<(&'a str, &'a str)> {
        Catalog::builtin().text(texts, p, a)
    }
}

/// A gateway's context with the catalog as metadata.
pub fn gateway_context() -> Context {
    Context::new(Arc::new(ControllerCatalog))
}

/// A gateway with service password "service" and setup password "setup", small limits.
pub fn gateway_settings() -> Settings {
    Settings {
        identity: Identity {
            sernum: "180917010200000102".into(),
            vendorid: 1050,
            productcode: 4096,
            liftnum: "40/7289/20399-126".into(),
            hardware: "fuzz".into(),
            software: "0".into(),
            boardhash: "00".into(),
            domaintoken: "MAS".into(),
            api: 2,
        },
        service_sha1: Some("4cf5bc59bee9e1c44c6254b5f84e7f066bd8e5fe".into()),
        setup_sha1: Some("80437a44a661d141174209119d54125a59a64b2a".into()),
        privilege_duration: Duration::from_secs(300),
        max_in_flight: 4,
        max_queued: 4,
        max_subscriptions: 16,
        heartbeat: Duration::from_secs(300),
        connack_timeout: Duration::from_secs(30),
        lift_controller: 1,
        nets: vec![1],
        policy: Policy::default(),
    }
}

/// The test fixtures' lift controller dictionary (imported once, a fresh copy each call).
pub fn sample_dictionary() -> canopen::od::ObjectDictionary {
    static SAMPLE: OnceLock<canopen::od::ObjectDictionary> = OnceLock::new();
    SAMPLE
        .get_or_init(|| {
            let text = include_str!("../../tests/fixtures/controller.eds");
            match canopen::eds::import("controller.eds", text, Some(1)) {
                Ok(d) => d.description.od,
                Err(e) => panic!("the fixture EDS is broken: {e}"),
            }
        })
        .clone()
}
