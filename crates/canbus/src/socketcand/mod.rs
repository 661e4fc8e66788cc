//! socketcand: the text protocol ([`codec`]) and the `socketcand://` client backend.

pub(crate) mod client;
pub mod codec;
