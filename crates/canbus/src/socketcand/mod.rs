//! socketcand: the text protocol ([`codec`]) and the `socketcand://` client backend ([`client`]).

pub(crate) mod client;
pub mod codec;
