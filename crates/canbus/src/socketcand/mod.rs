//! socketcand: the text protocol ([`codec`]) and the `socketcand://` client backend.

#[cfg(feature = "tokio")]
pub(crate) mod client;
pub mod codec;
