//! `canlift sdo read|write`: one-shot SDO transfers from the command line.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canbus::Bus;
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
        /// Data type: u8…u64, i8…i64, f32, f64, bool, str, domain, or a CiA name (UNSIGNED24).
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

/// The data type named on the command line.
pub fn parse_type(name: &str) -> anyhow::Result<DataType> {
    let short = match name.to_ascii_lowercase().as_str() {
        "u8" => Some(DataType::Unsigned8),
        "u16" => Some(DataType::Unsigned16),
        "u24" => Some(DataType::Unsigned24),
        "u32" => Some(DataType::Unsigned32),
        "u64" => Some(DataType::Unsigned64),
        "i8" => Some(DataType::Integer8),
        "i16" => Some(DataType::Integer16),
        "i24" => Some(DataType::Integer24),
        "i32" => Some(DataType::Integer32),
        "i64" => Some(DataType::Integer64),
        "f32" => Some(DataType::Real32),
        "f64" => Some(DataType::Real64),
        "bool" => Some(DataType::Boolean),
        "str" | "string" => Some(DataType::VisibleString),
        "domain" | "bytes" => Some(DataType::Domain),
        _ => None,
    };
    short
        .or_else(|| DataType::from_name(name))
        .with_context(|| format!("unknown data type {name:?}"))
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
                .unwrap_or(DataType::Domain);
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
                    let value = types::decode(ty, &bytes)
                        .with_context(|| format!("{index:04X}:{sub:02X} as {ty}"))?;
                    println!("{}", types::to_text(ty, &value));
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
                (None, Some(ty), Some(value)) => {
                    let ty = parse_type(&ty)?;
                    let v = types::from_text(ty, &value)?;
                    Box::new(types::encode(ty, &v)?)
                }
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
    use super::*;

    #[test]
    fn type_names() {
        assert_eq!(parse_type("u32").unwrap(), DataType::Unsigned32);
        assert_eq!(parse_type("UNSIGNED24").unwrap(), DataType::Unsigned24);
        assert_eq!(
            parse_type("visible_string").unwrap(),
            DataType::VisibleString
        );
        assert!(parse_type("u33").is_err());
        assert_eq!(parse_number::<u16>("index", "0x1017").unwrap(), 0x1017);
        assert!(parse_number::<u8>("sub", "256").is_err());
    }
}
