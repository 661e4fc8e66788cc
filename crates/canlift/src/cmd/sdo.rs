//! `canlift sdo read|write`: one-shot SDO transfers from the command line.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canbus::Bus;
use canopen::ascii::AsciiType;
use canopen::driver::{SdoClients, TransferOptions};
use canopen::sdo::client::{ClientConfig, DownloadSource, FileSource, Transfer};
use canopen::types::{self, DataType};

/// Command-line arguments of `canlift sdo`.
#[derive(Debug, clap::Args)]
pub struct SdoArgs {
    /// The bus.
    #[arg(
        long,
        global = true,
        default_value = "socketcand://127.0.0.1:29536/can0"
    )]
    bus: String,
    /// SDO timeout in milliseconds.
    #[arg(long, global = true, default_value_t = 1000)]
    timeout_ms: u64,
    /// Use block transfer.
    #[arg(long, global = true)]
    block: bool,
    #[command(subcommand)]
    op: SdoOp,
}

#[derive(Debug, clap::Subcommand)]
enum SdoOp {
    /// Read an object and print it (as TYPE; default: hex bytes).
    Read {
        /// Node-ID (1–127).
        node: u8,
        /// Index (0x1017 or decimal).
        index: String,
        /// Sub-index.
        sub: String,
        /// Data type: a CiA 309-3 mnemonic (b, i8…i64, u8…u64, x8…x64, r32, r64, t, td, vs, os,
        /// us, d, hex), u24, i24, f32, f64, bool, str, domain, or a CiA 301 name (UNSIGNED24).
        #[arg(value_name = "TYPE")]
        ty: Option<String>,
        /// Write the raw bytes to this file instead of printing.
        #[arg(long)]
        file: Option<PathBuf>,
    },
    /// Write a value (given as text of TYPE) or a file's bytes.
    Write {
        /// Node-ID (1–127).
        node: u8,
        /// Index.
        index: String,
        /// Sub-index.
        sub: String,
        /// Data type (see `read`).
        #[arg(value_name = "TYPE")]
        ty: Option<String>,
        /// The value in its text form.
        value: Option<String>,
        /// Write this file's bytes.
        #[arg(long, conflicts_with = "value")]
        file: Option<PathBuf>,
    },
}

/// The data type named on the command line: a CiA 309-3 mnemonic (`u16`, `vs`, `x32`, `d`, …,
/// printed and parsed as the ASCII gateway does), one of canlift's short names (`u24`, `f32`,
/// `bool`, `str`, `domain`) or a CiA 301 name (`UNSIGNED24`).
pub fn parse_type(name: &str) -> anyhow::Result<AsciiType> {
    if let Some(ty) = AsciiType::from_mnemonic(name) {
        return Ok(ty);
    }
    let short = match name.to_ascii_lowercase().as_str() {
        "u24" => Some(DataType::Unsigned24),
        "i24" => Some(DataType::Integer24),
        "f32" => Some(DataType::Real32),
        "f64" => Some(DataType::Real64),
        "bool" => Some(DataType::Boolean),
        "str" | "string" => Some(DataType::VisibleString),
        "domain" | "bytes" => Some(DataType::Domain),
        _ => None,
    };
    short
        .or_else(|| DataType::from_name(name))
        .map(AsciiType::plain)
        .with_context(|| {
            format!(
                "unknown data type {name:?} (b, i8…i64, u8…u64, x8…x64, r32, r64, t, td, vs, os, us, d, hex, or a CiA 301 name)"
            )
        })
}

fn parse_number<T: TryFrom<i128>>(what: &str, text: &str) -> anyhow::Result<T> {
    types::parse_integer(text)
        .and_then(|v| T::try_from(v).ok())
        .with_context(|| format!("invalid {what} {text:?}"))
}

/// A progress line on stderr, only when stderr is a terminal.
struct ProgressLine {
    enabled: bool,
    started: Instant,
    last: std::sync::Mutex<Instant>,
}

impl ProgressLine {
    fn new() -> Self {
        ProgressLine {
            enabled: std::io::stderr().is_terminal(),
            started: Instant::now(),
            last: std::sync::Mutex::new(Instant::now()),
        }
    }

    fn update(&self, done: u64, total: Option<u64>) {
        if !self.enabled || done < 1024 {
            return;
        }
        let mut last = self
            .last
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if last.elapsed() < Duration::from_millis(100) && total != Some(done) {
            return;
        }
        *last = Instant::now();
        let rate = done as f64 / 1024.0 / self.started.elapsed().as_secs_f64().max(1e-3);
        let line = match total {
            Some(t) if t > 0 => format!(
                "\r{:.1} / {:.1} KiB  {:3}%  {rate:.1} KiB/s ",
                done as f64 / 1024.0,
                t as f64 / 1024.0,
                done * 100 / t
            ),
            _ => format!("\r{:.1} KiB  {rate:.1} KiB/s ", done as f64 / 1024.0),
        };
        let _ = std::io::stderr().write_all(line.as_bytes());
    }

    fn finish(&self) {
        if self.enabled && self.started.elapsed() > Duration::from_millis(100) {
            let _ = std::io::stderr().write_all(b"\n");
        }
    }
}

/// Run one SDO transfer.
pub async fn run(args: SdoArgs) -> anyhow::Result<()> {
    let bus = Bus::open(&args.bus).await?;
    let config = ClientConfig {
        timeout: Duration::from_millis(args.timeout_ms),
        ..ClientConfig::default()
    };
    let sdo = SdoClients::new(bus, config);
    let progress = ProgressLine::new();
    let report = |done: u64, total: Option<u64>| progress.update(done, total);
    let options = TransferOptions {
        how: if args.block {
            Transfer::Block
        } else {
            Transfer::Normal
        },
        progress: Some(&report),
        ..TransferOptions::default()
    };
    match args.op {
        SdoOp::Read {
            node,
            index,
            sub,
            ty,
            file,
        } => {
            let (index, sub) = (
                parse_number::<u16>("index", &index)?,
                parse_number::<u8>("sub-index", &sub)?,
            );
            let ty = ty
                .as_deref()
                .map(parse_type)
                .transpose()?
                .unwrap_or(AsciiType::plain(DataType::Domain));
            match file {
                Some(path) => {
                    // Streamed to the file as it arrives: large DOMAINs never sit in memory.
                    let mut out = std::fs::File::create(&path)
                        .with_context(|| format!("creating {}", path.display()))?;
                    let result = sdo.read_to(node, index, sub, &mut out, options).await;
                    progress.finish();
                    result?;
                }
                None => {
                    let bytes = sdo.read_with(node, index, sub, options).await;
                    progress.finish();
                    let bytes = bytes?;
                    let text = ty
                        .format(&bytes)
                        .with_context(|| format!("{index:04X}:{sub:02X} as {ty}"))?;
                    println!("{text}");
                }
            }
        }
        SdoOp::Write {
            node,
            index,
            sub,
            ty,
            value,
            file,
        } => {
            let (index, sub) = (
                parse_number::<u16>("index", &index)?,
                parse_number::<u8>("sub-index", &sub)?,
            );
            let source: Box<dyn DownloadSource> = match (file, ty, value) {
                (Some(path), _, _) => Box::new(
                    FileSource::open(&path)
                        .with_context(|| format!("reading {}", path.display()))?,
                ),
                (None, Some(ty), Some(value)) => Box::new(parse_type(&ty)?.parse(&value)?),
                _ => bail!("give TYPE and VALUE, or --file"),
            };
            let result = sdo.write_from(node, index, sub, source, options).await;
            progress.finish();
            result?;
        }
    }
    // The transfer's last frame (an acknowledgement) may still be queued for the bus.
    sdo.flush().await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use canopen::ascii::Form;

    use super::*;

    #[test]
    fn type_names() {
        let data_type = |name| parse_type(name).unwrap().data_type;
        assert_eq!(data_type("u32"), DataType::Unsigned32);
        assert_eq!(data_type("UNSIGNED24"), DataType::Unsigned24);
        assert_eq!(data_type("visible_string"), DataType::VisibleString);
        assert_eq!(data_type("str"), DataType::VisibleString);
        assert_eq!(parse_type("vs").unwrap().form, Form::Quoted);
        assert_eq!(parse_type("x16").unwrap().form, Form::Hex);
        assert_eq!(parse_type("d").unwrap().form, Form::Base64);
        assert!(parse_type("u33").is_err());
        assert_eq!(parse_number::<u16>("index", "0x1017").unwrap(), 0x1017);
        assert!(parse_number::<u8>("sub", "256").is_err());
    }
}
