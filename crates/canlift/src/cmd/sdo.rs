//! `canlift sdo read|write`: one-shot SDO transfers from the command line.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canbus::Bus;
use canopen::ascii::AsciiType;

use super::address::{Names, Resolved};
use canopen::sdo::client::{ClientConfig, DownloadSource, FileSource, Transfer};
use canopen::sdo::clients::{SdoClients, TransferOptions};
use canopen::types::DataType;

/// Command-line arguments of `canlift sdo`.
#[derive(Debug, clap::Args)]
pub struct SdoArgs {
    #[command(flatten)]
    bus: super::BusArg,
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
    /// Read an object and print it (as TYPE; default: the type the catalog or --eds gives,
    /// else hex bytes).
    Read {
        /// Node-ID (1–127).
        node: u8,
        /// The object, then TYPE: `INDEX SUB` (0x1017 0), `0x6520:1`, `6520sub1`, `0x652001`
        /// or a name from the CiA 417 catalog or --eds ("Trip counter", a unique prefix will
        /// do). TYPE: a CiA 309-3 mnemonic (b, i8…i64, u8…u64, x8…x64, r32, r64, t, td, vs,
        /// os, us, d, hex), u24, i24, f32, f64, bool, str, domain, or a CiA 301 name.
        #[arg(value_name = "OBJECT [TYPE]", required = true, num_args = 1..=3)]
        object: Vec<String>,
        /// Names and types from this EDS/DCF instead of the catalog.
        #[arg(long)]
        eds: Option<PathBuf>,
        /// Write the raw bytes to this file instead of printing.
        #[arg(long)]
        file: Option<PathBuf>,
    },
    /// Write a value (given as text of TYPE) or a file's bytes.
    Write {
        /// Node-ID (1–127).
        node: u8,
        /// The object as for `read`, TYPE (optional when the catalog or --eds gives it), then
        /// the value in its text form (none with --file).
        #[arg(value_name = "OBJECT [TYPE] VALUE", required = true, num_args = 1..=4)]
        words: Vec<String>,
        /// Names and types from this EDS/DCF instead of the catalog.
        #[arg(long)]
        eds: Option<PathBuf>,
        /// Write this file's bytes.
        #[arg(long)]
        file: Option<PathBuf>,
    },
}

/// The type to use: the one given, else the one the address resolved with.
fn type_for(given: Option<&str>, resolved: &Resolved) -> anyhow::Result<Option<AsciiType>> {
    match given {
        Some(name) => parse_type(name).map(Some),
        None => Ok(resolved.data_type.map(AsciiType::plain)),
    }
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
    let bus = Bus::open(&args.bus.url).await?;
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
            object,
            eds,
            file,
        } => {
            let names = Names::eds_or_catalog(eds.as_deref())?;
            let (resolved, ty) = names.resolve_words(&object)?;
            let (index, sub) = (resolved.mplex.index, resolved.mplex.sub);
            let ty = type_for(ty, &resolved)?.unwrap_or(AsciiType::plain(DataType::Domain));
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
            words,
            eds,
            file,
        } => {
            let names = Names::eds_or_catalog(eds.as_deref())?;
            // The value is the last word, unless the bytes come from a file.
            let (object, value) = match &file {
                Some(_) => (&words[..], None),
                None => match words.split_last() {
                    Some((value, object)) if !object.is_empty() => (object, Some(value)),
                    _ => bail!("give the object, TYPE and VALUE, or --file"),
                },
            };
            let (resolved, ty) = names.resolve_words(object)?;
            let (index, sub) = (resolved.mplex.index, resolved.mplex.sub);
            let source: Box<dyn DownloadSource> = match (file, value) {
                (Some(path), _) => Box::new(
                    FileSource::open(&path)
                        .with_context(|| format!("reading {}", path.display()))?,
                ),
                (None, Some(value)) => {
                    let ty = type_for(ty, &resolved)?.with_context(|| {
                        format!("give the TYPE of {index:04X}:{sub:02X} (neither the catalog nor --eds describes it)")
                    })?;
                    Box::new(ty.parse(value)?)
                }
                (None, None) => bail!("give the object, TYPE and VALUE, or --file"),
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
    }
}
