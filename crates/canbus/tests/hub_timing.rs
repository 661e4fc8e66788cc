//! Bit-rate mode timing, in a test binary of its own so that no other test competes for the CPU
//! while the wire time is measured.

mod common;

use std::time::Duration;

use canbus::hub::HubConfig;
use canbus::{wire, Bus, Frame};
use common::{hub, same, url};
use tokio::time::{timeout, Instant};

async fn recv_frame(bus: &mut Bus) -> Frame {
    timeout(Duration::from_secs(10), bus.receiver.recv_frame())
        .await
        .expect("frame within 10 s")
        .expect("bus open")
}

/// The time a burst of `n` frames occupies the bus from the end of the first to the end of the
/// last: what a receiver can measure.
fn burst_wire_time(frames: &[Frame], bitrate: u32) -> Duration {
    frames[1..]
        .iter()
        .map(|f| wire::frame_duration(f, bitrate))
        .sum()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bitrate_mode_takes_the_computed_wire_time() {
    for bitrate in [125_000u32, 250_000, 500_000, 1_000_000] {
        let hub = hub(HubConfig {
            bitrate: Some(bitrate),
            ..HubConfig::default()
        })
        .await;
        let tx = Bus::open(&url(&hub, "can0")).await.unwrap();
        let mut rx = Bus::open(&url(&hub, "can0")).await.unwrap();
        // About 0.4 s of bus time per bit rate; 8-byte frames with varied content so that
        // stuffing differs from frame to frame.
        let n = (bitrate / 300) as usize;
        let frames: Vec<Frame> = (0..n)
            .map(|i| {
                let data = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15).to_le_bytes();
                Frame::standard(0x100 + (i % 0x100) as u16, &data).unwrap()
            })
            .collect();
        let expected = burst_wire_time(&frames, bitrate);
        // Frames are held back briefly after a client enters raw mode; start after that.
        tokio::time::sleep(Duration::from_millis(150)).await;
        let sender = tokio::spawn({
            let frames = frames.clone();
            async move {
                for f in frames {
                    tx.send(f).await.unwrap();
                }
                tx
            }
        });
        let first = recv_frame(&mut rx).await;
        let t0 = Instant::now();
        assert!(same(&first, &frames[0]));
        for f in &frames[1..] {
            assert!(same(&recv_frame(&mut rx).await, f));
        }
        let measured = t0.elapsed();
        drop(sender.await.unwrap());
        let error =
            (measured.as_secs_f64() - expected.as_secs_f64()).abs() / expected.as_secs_f64();
        println!("{bitrate} bit/s: {n} frames, expected {expected:?}, measured {measured:?}");
        assert!(
            error < 0.05,
            "{bitrate} bit/s: {n} frames took {measured:?}, wire time is {expected:?}"
        );
        hub.shutdown().await;
    }
}
