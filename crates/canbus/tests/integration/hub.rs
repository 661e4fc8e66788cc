//! The hub and the socketcand client backend, end to end over loopback TCP.

use crate::common;

use std::sync::atomic::Ordering;
use std::time::Duration;

use canbus::hub::HubConfig;
use canbus::{Bus, BusError, BusEvent, BusOptions, CanId, Filter, Frame, Interface};
use common::{hub, pattern, same, url, RawClient};
use tokio::time::timeout;

const FRAMES: u32 = 10_000;

/// A hub on `addr` (one that was there before comes back).
async fn hub_at(addr: std::net::SocketAddr) -> canbus::hub::HubHandle {
    canbus::hub::Hub::bind(HubConfig {
        listen: addr,
        ..HubConfig::default()
    })
    .await
    .unwrap()
    .spawn()
    .unwrap()
}

async fn recv_frame(bus: &mut Bus) -> Frame {
    timeout(Duration::from_secs(10), bus.receiver.recv_frame())
        .await
        .expect("frame within 10 s")
        .expect("bus open")
}

/// Receive `expected` in order on `bus`, in a task of its own.
fn expect_in_order(mut bus: Bus, expected: Vec<Frame>) -> tokio::task::JoinHandle<Bus> {
    tokio::spawn(async move {
        for (i, want) in expected.iter().enumerate() {
            let got = recv_frame(&mut bus).await;
            assert!(same(&got, want), "frame {i}: {got} != {want}");
            assert!(got.timestamp().is_some());
        }
        bus
    })
}

/// An endpoint whose receive queue holds a whole test's worth of frames, so that a test task
/// being scheduled late never turns into an overrun.
async fn open_big(url: &str) -> Bus {
    let options = BusOptions {
        rx_queue: 1 << 19,
        ..BusOptions::default()
    };
    Bus::open_with(url, options).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_exchange_10000_frames_each_way_in_order() {
    let hub = hub(HubConfig::default()).await;
    let a = open_big(&url(&hub, "can0")).await;
    let b = open_big(&url(&hub, "can0")).await;
    let (a_tx, b_tx) = (a.sender.clone(), b.sender.clone());
    let forward: Vec<Frame> = (0..FRAMES).map(pattern).collect();
    let backward: Vec<Frame> = (0..FRAMES).rev().map(pattern).collect();
    let b_reader = expect_in_order(b, forward.clone());
    let a_reader = expect_in_order(a, backward.clone());
    let send_a = tokio::spawn(async move {
        for f in forward {
            a_tx.send(f).await.unwrap();
        }
    });
    let send_b = tokio::spawn(async move {
        for f in backward {
            b_tx.send(f).await.unwrap();
        }
    });
    send_a.await.unwrap();
    send_b.await.unwrap();
    let mut a = a_reader.await.unwrap();
    let mut b = b_reader.await.unwrap();
    // Nobody got their own frames back, and nothing else is queued.
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert!(a.receiver.try_recv().is_none());
    assert!(b.receiver.try_recv().is_none());
    assert_eq!(
        hub.stats().frames_in.load(Ordering::Relaxed),
        2 * u64::from(FRAMES)
    );
    assert_eq!(hub.stats().clients_dropped.load(Ordering::Relaxed), 0);
    hub.shutdown().await;
}

#[tokio::test]
async fn channels_are_separate_buses() {
    let hub = hub(HubConfig::default()).await;
    let a = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut b = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut other = Bus::open(&url(&hub, "can1")).await.unwrap();
    a.send(Frame::standard(0x123, &[1]).unwrap()).await.unwrap();
    assert_eq!(recv_frame(&mut b).await.id(), CanId::Standard(0x123));
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(other.receiver.try_recv().is_none());
    hub.shutdown().await;
}

#[tokio::test]
async fn handshake_messages_arrive_alone_and_echo_works() {
    let hub = hub(HubConfig::default()).await;
    let mut sender = Bus::open(&url(&hub, "can0")).await.unwrap();
    // A frame in flight while the raw client's handshake completes must not be glued to `< ok >`
    // (RawClient::connect asserts that each reply arrives alone).
    let flood = tokio::spawn({
        let tx = sender.sender.clone();
        async move {
            for i in 0..200u16 {
                let _ = tx.send(Frame::standard(i, &[]).unwrap()).await;
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
    });
    let mut raw = RawClient::connect(&hub, "can0").await;
    flood.await.unwrap();
    raw.write("< echo >").await;
    let mut seen = String::new();
    while !seen.contains("< echo >") {
        seen.push_str(&raw.read_some().await);
    }
    assert!(seen.starts_with("< frame "), "{seen}");
    raw.write("< send 7FF 0  >").await;
    assert_eq!(recv_frame(&mut sender).await.id(), CanId::Standard(0x7FF));
    hub.shutdown().await;
}

#[tokio::test]
async fn commands_before_raw_mode_are_answered() {
    let hub = hub(HubConfig::default()).await;
    let stream = tokio::net::TcpStream::connect(hub.local_addr())
        .await
        .unwrap();
    let mut c = RawClient { stream };
    assert_eq!(c.read_some().await, "< hi >");
    c.write("< rawmode >").await;
    assert_eq!(c.read_some().await, "< error open a channel first >");
    c.write("< isotpmode >").await;
    assert!(c.read_some().await.starts_with("< error "));
    c.write("< open can0 >").await;
    assert_eq!(c.read_some().await, "< ok >");
    c.write("< open can1 >").await;
    assert!(c.read_some().await.starts_with("< error "));
    c.write("< rawmode >").await;
    assert_eq!(c.read_some().await, "< ok >");
    drop(c);
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bitrate_mode_arbitrates_by_can_id() {
    // 2 kbit/s: an 8-byte frame occupies the bus for ~60 ms, so everything sent while the
    // first frame is on the wire is waiting when the bus becomes free.
    let hub = hub(HubConfig {
        bitrate: Some(2_000),
        ..HubConfig::default()
    })
    .await;
    let blocker = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut observer = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut nodes = Vec::new();
    for _ in 0..4 {
        nodes.push(Bus::open(&url(&hub, "can0")).await.unwrap());
    }
    let std = |id| Frame::standard(id, &[]).unwrap();
    let ext = |id| Frame::new(CanId::Extended(id), &[]).unwrap();
    blocker
        .send(Frame::standard(0x7FF, &[0; 8]).unwrap())
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(5)).await;
    // Each node's queue is FIFO (like a controller's); node 3 queues 0x400 before 0x050.
    let queues = [
        vec![std(0x105), std(0x205), std(0x305)],
        vec![std(0x101), std(0x201), ext(0x301 << 18)],
        vec![std(0x103), std(0x203), ext(0x303)],
        vec![std(0x400), std(0x050)],
    ];
    for (node, frames) in nodes.iter().zip(&queues) {
        for f in frames {
            node.send(*f).await.unwrap();
        }
    }
    let mut order = Vec::new();
    for _ in 0..12 {
        let f = recv_frame(&mut observer).await;
        order.push((f.id().is_extended(), f.id().as_raw()));
    }
    // Worked by hand: at every free bus the waiting queue heads compare arbitration fields.
    let expected = vec![
        (false, 0x7FF), // already on the wire
        (false, 0x101),
        (false, 0x103),
        (false, 0x105),
        (false, 0x201),
        (false, 0x203),
        (true, 0x303), // base ID 0: beats every head once it reaches the front of its queue
        (false, 0x205),
        (true, 0x301 << 18), // base ID 0x301 beats 0x305 and 0x400
        (false, 0x305),
        (false, 0x400),
        (false, 0x050), // waited behind 0x400 in its node's queue
    ];
    assert_eq!(order, expected);
    hub.shutdown().await;
}

/// A good sender and receiver keep working while `bad` misbehaves.
async fn good_pair_still_works(hub: &canbus::hub::HubHandle, rx: &mut Bus, tx: &Bus, tag: u8) {
    for i in 0..100u16 {
        tx.send(Frame::standard(i, &[tag]).unwrap()).await.unwrap();
    }
    for i in 0..100u16 {
        let f = recv_frame(rx).await;
        assert_eq!((f.id().as_raw(), f.data()), (u32::from(i), &[tag][..]));
    }
    assert!(hub.stats().clients.load(Ordering::Relaxed) >= 2);
}

#[tokio::test]
async fn garbage_and_invalid_frames_are_dropped() {
    let hub = hub(HubConfig::default()).await;
    let tx = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut rx = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut bad = RawClient::connect(&hub, "can0").await;
    bad.write("\x00\x7f garbage \u{fffd}>>> <<").await;
    bad.write(" >< send 800 1 00 >").await; // 11-bit ID out of range
    bad.write("< send 20000000 0  >").await; // 29-bit ID out of range
    bad.write("< send 123 9 1 2 3 4 5 6 7 8 9 >").await; // DLC > 8
    bad.write("< send 123 2 1 >").await; // fewer bytes than the DLC
    bad.write("< send 123 1 100 >").await; // byte out of range
    bad.write("< send xyz 0  >< bcmmode >< frame 123 1.0 00 >")
        .await;
    bad.write("< send 321 1 AB >").await; // valid: must still get through
    let f = recv_frame(&mut rx).await;
    assert_eq!((f.id(), f.data()), (CanId::Standard(0x321), &[0xAB][..]));
    good_pair_still_works(&hub, &mut rx, &tx, 1).await;
    assert!(hub.stats().bad_messages.load(Ordering::Relaxed) >= 7);
    hub.shutdown().await;
}

#[tokio::test]
async fn oversized_line_disconnects_only_that_client() {
    let hub = hub(HubConfig::default()).await;
    let tx = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut rx = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut bad = RawClient::connect(&hub, "can0").await;
    bad.write(&format!("< send 123 {} >", "1 ".repeat(10_000)))
        .await;
    assert!(bad.closed_within(Duration::from_secs(5)).await);
    good_pair_still_works(&hub, &mut rx, &tx, 2).await;
    hub.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_dropped_and_memory_stays_bounded() {
    let hub = hub(HubConfig {
        client_queue: 1024,
        ..HubConfig::default()
    })
    .await;
    let tx = Bus::open(&url(&hub, "can0")).await.unwrap();
    let mut rx = open_big(&url(&hub, "can0")).await;
    // A client with a tiny receive buffer that never reads after the handshake.
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let stream = socket.connect(hub.local_addr()).await.unwrap();
    let mut stalled = RawClient::handshake(stream, "can0").await;
    let dropped = || hub.stats().clients_dropped.load(Ordering::Relaxed);
    // Send in bursts of 256 and let the good reader take each burst before the next: it keeps up
    // by construction, the stalled client does not read at all.
    let mut i = 0u32;
    while dropped() == 0 {
        assert!(i < 2_000_000, "the stalled client was never dropped");
        for _ in 0..256 {
            tx.send(Frame::standard(0x200, &i.to_le_bytes()).unwrap())
                .await
                .unwrap();
            i += 1;
        }
        for j in i - 256..i {
            assert_eq!(
                recv_frame(&mut rx).await.data(),
                &j.to_le_bytes()[..],
                "frame {j}"
            );
        }
    }
    // Bounded: the stalled client was dropped once its queue (1024 frames) plus what TCP buffers
    // hold had filled, not after memory grew with everything sent.
    println!("stalled client dropped after {i} frames");
    assert_eq!(dropped(), 1);
    assert!(stalled.closed_within(Duration::from_secs(5)).await);
    good_pair_still_works(&hub, &mut rx, &tx, 3).await;
    hub.shutdown().await;
}

#[tokio::test]
async fn link_loss_is_reported_and_the_client_reconnects() {
    let first = hub(HubConfig::default()).await;
    let addr = first.local_addr();
    let mut bus = Bus::open(&url(&first, "can0")).await.unwrap();
    first.shutdown().await;
    let event = timeout(Duration::from_secs(5), bus.recv())
        .await
        .unwrap()
        .unwrap();
    assert!(matches!(event, BusEvent::LinkDown { .. }), "{event:?}");
    let err = bus
        .send(Frame::standard(1, &[]).unwrap())
        .await
        .unwrap_err();
    assert!(matches!(err, BusError::Offline { .. }), "{err}");
    assert!(err.to_string().contains("is down"), "{err}");
    // The hub comes back on the same address.
    let second = hub_at(addr).await;
    let event = timeout(Duration::from_secs(15), bus.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(event, BusEvent::LinkUp);
    let mut peer = Bus::open(&url(&second, "can0")).await.unwrap();
    bus.send(Frame::standard(0x42, &[]).unwrap()).await.unwrap();
    assert_eq!(recv_frame(&mut peer).await.id(), CanId::Standard(0x42));
    second.shutdown().await;
}

/// Endpoints of one [`Interface`] share one connection to the server and see each other's
/// frames as separate connections would; a frame an endpoint's filters refuse is not queued for
/// it; link loss and return reach every endpoint.
#[tokio::test]
async fn endpoints_of_an_interface_share_one_connection() {
    let first = hub(HubConfig::default()).await;
    let addr = first.local_addr();
    let interface = Interface::open(&url(&first, "can0")).await.unwrap();
    let mut a = interface.endpoint().unwrap();
    let mut b = interface.endpoint().unwrap();
    let mut c = interface.endpoint().unwrap();
    c.receiver.set_filters(&[Filter::standard(0x700, 0x780)]);
    let mut outside = Bus::open(&url(&first, "can0")).await.unwrap();
    // Give the hub a moment to count both connections.
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert_eq!(first.stats().clients.load(Ordering::Relaxed), 2);

    a.send(Frame::standard(0x601, &[0x40, 0x00, 0x10, 0x00]).unwrap())
        .await
        .unwrap();
    let looped = recv_frame(&mut b).await;
    assert_eq!(looped.id(), CanId::Standard(0x601));
    assert!(looped.timestamp().is_some());
    assert_eq!(recv_frame(&mut outside).await.id(), CanId::Standard(0x601));
    outside
        .send(Frame::standard(0x701, &[5]).unwrap())
        .await
        .unwrap();
    for endpoint in [&mut a, &mut b, &mut c] {
        assert_eq!(recv_frame(endpoint).await.id(), CanId::Standard(0x701));
    }
    assert!(a.receiver.try_recv().is_none(), "a got its own frame");
    assert!(c.receiver.try_recv().is_none(), "c's filters let 0x601 in");

    first.shutdown().await;
    for endpoint in [&mut a, &mut b, &mut c] {
        let event = timeout(Duration::from_secs(5), endpoint.recv())
            .await
            .unwrap();
        assert!(
            matches!(event, Some(BusEvent::LinkDown { .. })),
            "{event:?}"
        );
    }
    let second = hub_at(addr).await;
    for endpoint in [&mut a, &mut b, &mut c] {
        let event = timeout(Duration::from_secs(15), endpoint.recv())
            .await
            .unwrap();
        assert_eq!(event, Some(BusEvent::LinkUp));
    }
    let mut peer = Bus::open(&url(&second, "can0")).await.unwrap();
    b.send(Frame::standard(0x42, &[]).unwrap()).await.unwrap();
    assert_eq!(recv_frame(&mut peer).await.id(), CanId::Standard(0x42));
    assert_eq!(recv_frame(&mut a).await.id(), CanId::Standard(0x42));
    second.shutdown().await;
}

#[tokio::test]
async fn open_fails_clearly_without_a_server() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    drop(listener);
    let err = Bus::open(&format!("socketcand://{addr}/can0"))
        .await
        .unwrap_err();
    assert!(
        err.to_string().contains("connecting to socketcand"),
        "{err}"
    );
}

#[tokio::test]
async fn remote_frames_are_refused_by_socketcand_links() {
    let hub = hub(HubConfig::default()).await;
    let bus = Bus::open(&url(&hub, "can0")).await.unwrap();
    let rtr = Frame::remote(CanId::Standard(0x701), 1).unwrap();
    assert!(matches!(bus.send(rtr).await, Err(BusError::Unsupported(_))));
    hub.shutdown().await;
}

#[tokio::test]
async fn shutdown_disconnects_everyone() {
    let hub = hub(HubConfig::default()).await;
    let mut raw = RawClient::connect(&hub, "can0").await;
    let _bus = Bus::open(&url(&hub, "can0")).await.unwrap();
    timeout(Duration::from_secs(5), hub.shutdown())
        .await
        .unwrap();
    assert!(raw.closed_within(Duration::from_secs(5)).await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flush_delivers_queued_frames_before_the_process_ends() {
    let hub = hub(HubConfig::default()).await;
    let mut peer = Bus::open(&url(&hub, "can0")).await.unwrap();
    let target = url(&hub, "can0");
    // Like a short-lived command: its own runtime, which ends (killing every task) right after
    // the last send. Without the flush, frames still queued for the socket would be lost.
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async {
            let bus = Bus::open(&target).await.unwrap();
            for i in 0..500u16 {
                bus.send(Frame::standard(0x100, &i.to_le_bytes()).unwrap())
                    .await
                    .unwrap();
            }
            bus.sender.flush().await.unwrap();
        });
        drop(rt);
    })
    .join()
    .unwrap();
    for i in 0..500u16 {
        assert_eq!(recv_frame(&mut peer).await.data(), &i.to_le_bytes());
    }
    hub.shutdown().await;
}

/// A socketcand server that completes the handshake, then reads nothing for a while (a busy
/// server, a slow link): senders' frames fill the socket, wait, and must still arrive whole,
/// each sender's in its order, none lost, and a flush must wait for all of them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_reads_late_gets_every_frame_whole_and_in_order() {
    use canbus::socketcand::codec::{Decoder, Message};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    const SENDERS: u16 = 3;
    const EACH: u32 = 50_000;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let server = tokio::spawn(async move {
        let (mut stream, _) = listener.accept().await.unwrap();
        let mut decoder = Decoder::new();
        let mut buf = vec![0u8; 64 * 1024];
        stream.write_all(b"< hi >").await.unwrap();
        let mut frames = Vec::new();
        let mut quiet_from = None;
        loop {
            while let Some(message) = decoder.next_message() {
                match message.unwrap() {
                    Message::Open(_) | Message::RawMode => {
                        stream.write_all(b"< ok >").await.unwrap()
                    }
                    Message::Echo => {
                        stream.write_all(b"< echo >").await.unwrap();
                        quiet_from = Some(tokio::time::Instant::now());
                    }
                    Message::Send(frame) => frames.push(frame),
                    other => panic!("{other:?}"),
                }
            }
            if frames.len() == usize::from(SENDERS) * EACH as usize {
                break;
            }
            // Raw mode reached: read nothing for a while.
            if let Some(from) = quiet_from.take() {
                tokio::time::sleep_until(from + Duration::from_millis(500)).await;
            }
            let n = stream.read(&mut buf).await.unwrap();
            assert!(n > 0, "the client closed after {} frames", frames.len());
            decoder.feed(&buf[..n]);
        }
        frames
    });
    let interface = Interface::open(&format!("socketcand://{addr}/can0"))
        .await
        .unwrap();
    let mut senders = Vec::new();
    for k in 0..SENDERS {
        let bus = interface.endpoint().unwrap();
        senders.push(tokio::spawn(async move {
            for i in 0..EACH {
                let frame = Frame::standard(0x200 + k, &i.to_le_bytes()).unwrap();
                bus.send(frame).await.unwrap();
            }
            bus.sender.flush().await.unwrap();
        }));
    }
    for sender in senders {
        timeout(Duration::from_secs(30), sender)
            .await
            .expect("sent and flushed within 30 s")
            .unwrap();
    }
    let frames = timeout(Duration::from_secs(30), server)
        .await
        .expect("all frames within 30 s")
        .unwrap();
    let mut next = [0u32; SENDERS as usize];
    for frame in frames {
        let k = usize::from(u16::try_from(frame.id().as_raw() - 0x200).unwrap());
        let i = u32::from_le_bytes(frame.data().try_into().unwrap());
        assert_eq!(
            i, next[k],
            "sender {k}: frame {i} where {} was due",
            next[k]
        );
        next[k] += 1;
    }
    assert_eq!(next, [EACH; SENDERS as usize]);
}
