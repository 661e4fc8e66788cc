//! Helpers shared by the integration tests.

use std::time::Duration;

use canbus::hub::HubHandle;
use canbus::{CanId, Frame};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Frame number `i` of the interop pattern: every third frame 29-bit, lengths 0–8 cycling.
/// `tests/interop/pattern.py` computes the same sequence.
pub fn pattern(i: u32) -> Frame {
    let len = (i % 9) as usize;
    let data: Vec<u8> = (0..len).map(|k| (i as usize * 31 + k * 7) as u8).collect();
    if i.is_multiple_of(3) {
        Frame::new(
            CanId::Extended(i.wrapping_mul(2_654_435_761) & 0x1FFF_FFFF),
            &data,
        )
        .unwrap()
    } else {
        Frame::standard((i * 7919 % 0x800) as u16, &data).unwrap()
    }
}

/// Compare identifier, kind and data (not timestamps).
pub fn same(a: &Frame, b: &Frame) -> bool {
    a.id() == b.id() && a.kind() == b.kind() && a.data() == b.data()
}

pub use testkit::{hub_url as url, hub_with as hub};

/// A hand-driven socketcand client, for feeding the hub bad input.
pub struct RawClient {
    pub stream: TcpStream,
}

impl RawClient {
    /// Connect and complete the handshake into raw mode on `channel`.
    pub async fn connect(hub: &HubHandle, channel: &str) -> RawClient {
        let stream = TcpStream::connect(hub.local_addr()).await.unwrap();
        Self::handshake(stream, channel).await
    }

    /// Complete the handshake on a connected stream.
    pub async fn handshake(stream: TcpStream, channel: &str) -> RawClient {
        let mut c = RawClient { stream };
        assert_eq!(c.read_some().await, "< hi >");
        c.write(&format!("< open {channel} >")).await;
        assert_eq!(c.read_some().await, "< ok >");
        c.write("< rawmode >").await;
        assert_eq!(c.read_some().await, "< ok >");
        c
    }

    pub async fn write(&mut self, text: &str) {
        self.stream.write_all(text.as_bytes()).await.unwrap();
    }

    /// One read's worth of text (what python-can's `_expect_msg` sees).
    pub async fn read_some(&mut self) -> String {
        let mut buf = [0u8; 256];
        let n = tokio::time::timeout(Duration::from_secs(5), self.stream.read(&mut buf))
            .await
            .expect("hub answered in time")
            .unwrap();
        String::from_utf8_lossy(&buf[..n]).into_owned()
    }

    /// Read until EOF (or error); returns whether the hub closed the connection within `limit`.
    pub async fn closed_within(&mut self, limit: Duration) -> bool {
        let mut buf = vec![0u8; 64 * 1024];
        tokio::time::timeout(limit, async {
            loop {
                match self.stream.read(&mut buf).await {
                    Ok(0) | Err(_) => return,
                    Ok(_) => {}
                }
            }
        })
        .await
        .is_ok()
    }
}
