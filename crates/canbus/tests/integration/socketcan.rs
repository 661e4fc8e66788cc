//! SocketCAN backend against a real (virtual) interface. Needs AF_CAN and a `vcan0` interface
//! (`ip link add vcan0 type vcan && ip link set vcan0 up`); skips with the reason otherwise.

use std::time::Duration;

use canbus::{Bus, CanId, Frame};
use testkit::skip;

#[tokio::test]
async fn vcan_loopback_between_two_endpoints() {
    if let Err(reason) = canbus::socketcan::af_can_available() {
        skip(&format!("socketcan: {reason}"));
        return;
    }
    let mut a = match Bus::open("socketcan://vcan0").await {
        Ok(bus) => bus,
        Err(e) => {
            skip(&format!("socketcan: no usable vcan0 interface ({e})"));
            return;
        }
    };
    let mut b = Bus::open("socketcan://vcan0").await.unwrap();
    let frames = [
        Frame::standard(0x181, &[1, 2, 3]).unwrap(),
        Frame::new(CanId::Extended(0x1ABC_DEF0), &[0; 8]).unwrap(),
        Frame::remote(CanId::Standard(0x701), 1).unwrap(),
    ];
    for f in frames {
        a.send(f).await.unwrap();
        let got = tokio::time::timeout(Duration::from_secs(2), b.receiver.recv_frame())
            .await
            .unwrap()
            .unwrap();
        assert_eq!(
            (got.id(), got.kind(), got.data()),
            (f.id(), f.kind(), f.data())
        );
    }
    // A sender does not receive its own frames by default.
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert!(a.receiver.try_recv().is_none());
}
