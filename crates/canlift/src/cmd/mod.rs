//! The subcommands of `canlift`.

pub mod address;

#[cfg(feature = "portal")]
pub mod alarms;
pub mod ascii;
#[cfg(feature = "portal")]
pub mod cloud;
pub mod dcf;
#[cfg(feature = "portal")]
pub mod demo;
pub mod dump;
pub mod eds;
pub mod emcy;
#[cfg(feature = "portal")]
pub mod exit;
pub mod gateway;
pub mod hub;
pub mod loadgen;
#[cfg(feature = "portal")]
pub mod local_time;
pub mod lss;
pub mod manual;
pub mod nmt;
#[cfg(feature = "portal")]
pub mod operator;
pub mod pdo;
pub mod scan;
pub mod sdo;
pub mod sim;
pub mod sync;
pub mod time;

/// A number as typed on the command line (decimal, `0x` hex, or leading-zero octal as EDS
/// files write it) that fits `T`; `what` names it in the error.
pub fn parse_number<T: TryFrom<i128>>(what: &str, text: &str) -> anyhow::Result<T> {
    use anyhow::Context;
    canopen::types::parse_integer(text)
        .and_then(|v| T::try_from(v).ok())
        .with_context(|| format!("invalid {what} {text:?}"))
}

/// The `--bus` option every bus tool takes.
#[derive(Debug, Clone, clap::Args)]
pub struct BusArg {
    /// The bus: socketcand://HOST:PORT/CHANNEL (the hub), socketcan://IFACE or mem://NAME.
    #[arg(
        long = "bus",
        global = true,
        env = "CANLIFT_BUS",
        default_value = "socketcand://127.0.0.1:29536/can0"
    )]
    pub url: String,
}
