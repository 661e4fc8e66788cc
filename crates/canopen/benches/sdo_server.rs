//! Nanoseconds per frame in the SDO server state machine (no I/O): `cargo bench -p canopen`.

use std::hint::black_box;
use std::time::Instant;

use canopen::od::{Access, Object, ObjectDictionary, Variable};
use canopen::sdo::server::{SdoServer, ServerConfig};
use canopen::types::{DataType, Value};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

fn dictionary() -> ObjectDictionary {
    let mut od = ObjectDictionary::new();
    od.insert(Object::var(
        0x1000,
        Variable::new("Device type", DataType::Unsigned32, Access::Ro)
            .with_value(Value::Uint(0x0001_01A1)),
    ));
    od.insert(Object::var(
        0x2000,
        Variable::new("Blob", DataType::Domain, Access::Rw),
    ));
    od.insert(Object::var(
        0x2001,
        Variable::new("Setpoint", DataType::Unsigned16, Access::Rw)
            .with_limits(Some(Value::Uint(0)), Some(Value::Uint(1000))),
    ));
    od
}

fn bench(c: &mut Criterion) {
    let now = Instant::now();
    let mut group = c.benchmark_group("sdo_server");
    group.throughput(Throughput::Elements(1));

    group.bench_function("expedited upload (1 request frame)", |b| {
        let mut od = dictionary();
        let mut server = SdoServer::new(ServerConfig::default());
        let mut out = Vec::with_capacity(4);
        let req = [0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0];
        b.iter(|| {
            out.clear();
            server.handle(&mut od, black_box(&req), now, &mut out);
            black_box(&out);
        })
    });

    group.bench_function("expedited download with limit check (1 frame)", |b| {
        let mut od = dictionary();
        let mut server = SdoServer::new(ServerConfig::default());
        let mut out = Vec::with_capacity(4);
        let req = [0x2B, 0x01, 0x20, 0x00, 0xF4, 0x01, 0, 0];
        b.iter(|| {
            out.clear();
            server.handle(&mut od, black_box(&req), now, &mut out);
            black_box(&out);
        })
    });

    // Whole block cycles: initiate + 127 data segments + abort (129 frames in), and initiate +
    // start + 127 segments out + abort.
    group.throughput(Throughput::Elements(129));
    group.bench_function("block download sub-block (129 frames in)", |b| {
        let mut od = dictionary();
        let mut server = SdoServer::new(ServerConfig::default());
        let mut out = Vec::with_capacity(4);
        let segments: Vec<[u8; 8]> = (1..=127u8).map(|seq| [seq, 1, 2, 3, 4, 5, 6, 7]).collect();
        b.iter(|| {
            out.clear();
            server.handle(
                &mut od,
                &[0xC6, 0x00, 0x20, 0x00, 0, 0, 1, 0],
                now,
                &mut out,
            );
            for s in &segments {
                server.handle(&mut od, black_box(s), now, &mut out);
            }
            server.handle(
                &mut od,
                &[0x80, 0x00, 0x20, 0x00, 0, 0, 0, 0],
                now,
                &mut out,
            );
            black_box(&out);
        })
    });
    group.bench_function("block upload sub-block (127 frames out)", |b| {
        let mut od = dictionary();
        od.write(0x2000, 0, &[0x55; 889]).unwrap();
        let mut server = SdoServer::new(ServerConfig::default());
        let mut out = Vec::with_capacity(256);
        b.iter(|| {
            out.clear();
            server.handle(
                &mut od,
                &[0xA4, 0x00, 0x20, 0x00, 127, 0, 0, 0],
                now,
                &mut out,
            );
            server.handle(&mut od, &[0xA3, 0, 0, 0, 0, 0, 0, 0], now, &mut out);
            server.handle(
                &mut od,
                &[0x80, 0x00, 0x20, 0x00, 0, 0, 0, 0],
                now,
                &mut out,
            );
            black_box(&out);
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
