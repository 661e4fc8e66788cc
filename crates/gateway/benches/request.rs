//! Nanoseconds of the connector's own work per request (no I/O, no TLS): a portal's get of
//! 0x652001 in each form read, described by an embedded gateway's metadata (the controller's
//! dictionary as its EDS, the catalog's NXg texts over it), answered and written as JSON.
//! `cargo bench -p gateway`. The process's whole cost, sockets and TLS included, is
//! `canlift-bench gateway --cpu-only` (docs/BENCHMARKS.md).

use std::hint::black_box;
use std::sync::Arc;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use gateway::config::Config;
use gateway::metadata::BusMetadata;
use lift417::catalog::{Catalog, Device};
use nxg::gateway::{Context, JobResult, Output, Phase, Session, Target};

/// A connected session and the bytes of 0x652001 in its controller's dictionary.
fn session(now: Instant) -> (Session, Vec<u8>) {
    let mut config = Config::default();
    config.identity.sernum = "bench".into();
    let od = Catalog::builtin()
        .dictionary(Device::Controller, 1, 8)
        .expect("the catalog makes a controller's dictionary");
    let value = od.read(0x6520, 1).expect("the controller has 0x652001");
    let metadata = BusMetadata::load(&config)
        .expect("no files to read")
        .with_dictionary(Target { net: 1, node: 1 }, Arc::new(od));
    let mut session = Session::new(
        config.settings(),
        Context::new(Arc::new(metadata)),
        None,
        now,
    );
    let connack = r#"{"jsonrpc":"2.0","id":1,"result":"CONNACK","api":1}"#;
    let _ = session.connect();
    let _ = session.handle_text(connack, now);
    assert!(matches!(session.phase(), Phase::Connected(_)));
    (session, value)
}

fn bench(c: &mut Criterion) {
    let now = Instant::now();
    let mut group = c.benchmark_group("gateway session");
    group.throughput(Throughput::Elements(1));
    for (form, flag) in [
        ("naked", r#","naked":true"#),
        ("stripped", r#","stripped":true"#),
        ("full", ""),
    ] {
        let request = format!(
            r#"{{"jsonrpc":"2.0","id":7,"method":"get_canopen_object","params":{{"lang":{{"preferred_language":"en","alternate_language":"de"}},"object":{{"mplex":"0x652001"{flag}}}}}}}"#
        );
        group.bench_function(format!("get 0x652001 {form}: request to answer"), |b| {
            let (mut session, value) = session(now);
            b.iter(|| {
                let mut answer = None;
                for output in session.handle_text(black_box(&request), now) {
                    if let Output::Start(id, _) = output {
                        let read = JobResult::Read(vec![value.clone()]);
                        answer = session.handle_job(id, read, now).into_iter().next();
                    }
                }
                match answer {
                    Some(Output::Send(text)) if text.contains("\"result\"") => black_box(text),
                    other => panic!("no answer: {other:?}"),
                }
            });
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
