//! The portal's side of a gateway connection (NXg SW003 §5–§7): the sans-IO [`Session`].

mod session;

pub use session::{CloseReason, Failure, Output, RequestId, Session, Settings};
