//! CAN frames, the `Bus` abstraction and its backends, and the socketcand-compatible hub.
//!
//! Without the `tokio` feature (on by default) the crate is frames, filters, the socketcand
//! text codec and the wire-time model: what sans-IO protocol code needs, without a runtime.
//!
//! ```no_run
//! # async fn demo() -> Result<(), canbus::BusError> {
//! let mut bus = canbus::Bus::open("socketcand://127.0.0.1:29536/can0").await?;
//! bus.send(canbus::Frame::standard(0x000, &[0x01, 0x00]).expect("valid frame")).await?;
//! while let Some(frame) = bus.receiver.recv_frame().await {
//!     println!("{frame}");
//! }
//! # Ok(()) }
//! ```

#![warn(missing_docs)]

pub mod backoff;
#[cfg(feature = "tokio")]
mod bus;
mod frame;
#[cfg(feature = "tokio")]
pub mod hub;
#[cfg(feature = "tokio")]
mod mem;
#[cfg(feature = "tokio")]
pub mod socketcan;
pub mod socketcand;
pub mod wire;

#[cfg(feature = "tokio")]
pub use bus::{
    Bus, BusError, BusEvent, BusOptions, BusReceiver, BusSender, BusUrl, Handled, Interface,
    DEFAULT_RX_QUEUE, SOCKETCAND_DEFAULT_PORT,
};
pub use frame::{
    CanId, Filter, Frame, FrameError, FrameKind, CLASSIC_MAX_LEN, EFF_FLAG, ERR_FLAG,
    EXTENDED_ID_MAX, RTR_FLAG, STANDARD_ID_MAX,
};
