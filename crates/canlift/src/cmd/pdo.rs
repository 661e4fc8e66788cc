//! `canlift pdo show|set`: another node's PDOs over SDO — what each one sends or receives, and
//! configuring one with the CiA 301 mapping procedure (`canopen::pdo::remote`).

use std::path::PathBuf;

use anyhow::{bail, Context};

use super::address::Names;
use super::parse_number;
use canopen::master::Master;
use canopen::pdo::remote::{Direction, PdoId, RemotePdo};
use canopen::pdo::MapEntry;
use canopen::sdo::client::ClientConfig;

/// Command-line arguments of `canlift pdo`.
#[derive(Debug, clap::Args)]
pub struct PdoArgs {
    #[command(flatten)]
    bus: super::BusArg,
    #[command(subcommand)]
    op: PdoOp,
}

#[derive(Debug, clap::Subcommand)]
enum PdoOp {
    /// Print every PDO of NODE: COB-ID, transmission type, inhibit, event timer, mapping.
    Show {
        /// Node-ID (1–127).
        node: u8,
        /// Name mapped objects from this EDS/DCF (default: the CiA 417 catalog).
        #[arg(long)]
        eds: Option<PathBuf>,
        /// Also list PDOs that are off (COB-ID bit 31).
        #[arg(long)]
        all: bool,
    },
    /// Configure one PDO of NODE (parameters not given stay as they are).
    Set {
        /// Node-ID (1–127).
        node: u8,
        /// tpdo1 … tpdo512 or rpdo1 … rpdo512.
        pdo: String,
        /// The CAN-ID (e.g. 0x181); default: keep the node's.
        #[arg(long)]
        cob_id: Option<String>,
        /// Transmission type (0, 1–240, 254, 255).
        #[arg(long = "type")]
        transmission: Option<u8>,
        /// Inhibit time in 100 µs units (TPDO).
        #[arg(long)]
        inhibit: Option<u16>,
        /// Event timer (TPDO) or deadline (RPDO) in ms.
        #[arg(long)]
        event: Option<u16>,
        /// The mapping: INDEX:SUB:BITS,… (e.g. 0x6520:1:32,0x6300:0:8); empty maps nothing.
        #[arg(long)]
        map: Option<String>,
        /// Leave the PDO off (COB-ID bit 31).
        #[arg(long)]
        disable: bool,
    },
}

/// `0x6520:1:32,…` as mapping entries.
fn parse_map(text: &str) -> anyhow::Result<Vec<MapEntry>> {
    text.split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|entry| {
            let parts: Vec<&str> = entry.split(':').collect();
            let [index, sub, bits] = parts.as_slice() else {
                bail!("--map entry {entry:?} is not INDEX:SUB:BITS");
            };
            let bits: u8 = parse_number("length in --map", bits)?;
            if !(1..=64).contains(&bits) {
                bail!("--map entry {entry:?}: the length is 1–64 bits");
            }
            let entry = MapEntry {
                index: parse_number("index in --map", index)?,
                sub: parse_number("sub-index in --map", sub)?,
                bits,
            };
            Ok(entry)
        })
        .collect::<anyhow::Result<Vec<_>>>()
        .and_then(|entries| {
            if entries.len() > 64 {
                bail!("at most 64 mapping entries");
            }
            Ok(entries)
        })
}

fn transmission_text(kind: Direction, t: u8) -> String {
    let meaning = match (kind, t) {
        (_, 0) => "acyclic synchronous",
        (_, 1..=240) => "every n-th SYNC",
        (Direction::Transmit, 252) => "synchronous on RTR",
        (Direction::Transmit, 253) => "on RTR",
        (_, 254) => "event (manufacturer)",
        (_, 255) => "event (profile)",
        _ => "reserved",
    };
    format!("{t} ({meaning})")
}

/// The lines `pdo show` prints for one PDO.
fn describe(pdo: &RemotePdo, names: &Names) -> Vec<String> {
    let mut head = format!(
        "{:<7} COB-ID 0x{:03X}{}  type {}",
        pdo.id.to_string(),
        pdo.cob_id & 0x1FFF_FFFF,
        if pdo.enabled() { "" } else { " (off)" },
        transmission_text(pdo.id.direction, pdo.transmission)
    );
    if let Some(i) = pdo.inhibit_100us {
        head.push_str(&format!("  inhibit {:.1} ms", f64::from(i) / 10.0));
    }
    if let Some(e) = pdo.event_ms {
        let what = match pdo.id.direction {
            Direction::Transmit => "event timer",
            Direction::Receive => "deadline",
        };
        head.push_str(&format!("  {what} {e} ms"));
    }
    head.push_str(&format!("  {} bits", pdo.bits()));
    let mut lines = vec![head];
    for (i, m) in pdo.mapping.iter().enumerate() {
        let line = format!(
            "  {}. {:04X}h sub {:<3} {:>2} bits  {}",
            i + 1,
            m.index,
            m.sub,
            m.bits,
            if (1..=7).contains(&m.index) {
                "dummy"
            } else {
                names.name_of(m.index, m.sub).unwrap_or_default()
            }
        );
        lines.push(line.trim_end().to_owned());
    }
    lines
}

/// Show or set.
pub async fn run(args: PdoArgs) -> anyhow::Result<()> {
    let master = Master::open(&args.bus.url, ClientConfig::default())
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    match args.op {
        PdoOp::Show { node, eds, all } => {
            let names = Names::eds_or_catalog(eds.as_deref())?;
            let mut shown = 0;
            for direction in [Direction::Receive, Direction::Transmit] {
                for number in 1..=512 {
                    let id = PdoId { direction, number };
                    let Some(pdo) = master.read_remote_pdo(node, id).await? else {
                        continue;
                    };
                    shown += 1;
                    if pdo.enabled() || all {
                        describe(&pdo, &names).iter().for_each(|l| println!("{l}"));
                    }
                }
            }
            if shown == 0 {
                println!("node {node} has no PDOs");
            }
            Ok(())
        }
        PdoOp::Set {
            node,
            pdo,
            cob_id,
            transmission,
            inhibit,
            event,
            map,
            disable,
        } => {
            let id = PdoId::parse(&pdo)
                .with_context(|| format!("{pdo:?}: give tpdo1…tpdo512 or rpdo1…rpdo512"))?;
            let Some(mut config) = master.read_remote_pdo(node, id).await? else {
                bail!("node {node} has no {id}");
            };
            if let Some(text) = cob_id {
                let can_id: u32 = parse_number("COB-ID", &text)?;
                if can_id > 0x1FFF_FFFF {
                    bail!("COB-ID {text} is above 0x1FFFFFFF");
                }
                let extended = if can_id > 0x7FF { 0x2000_0000 } else { 0 };
                // Keep the node's RTR bit (30); set the format bit (29) from the identifier.
                config.cob_id = (config.cob_id & 0x4000_0000) | extended | can_id;
            } else {
                config.cob_id &= 0x7FFF_FFFF;
            }
            if disable {
                config.cob_id |= 0x8000_0000;
            }
            if let Some(t) = transmission {
                config.transmission = t;
            }
            // Only what was given is written; the node keeps the rest.
            config.inhibit_100us = inhibit;
            config.event_ms = event;
            config.sync_start = None;
            if let Some(map) = map {
                config.mapping = parse_map(&map)?;
            }
            master.configure_remote_pdo(node, &config).await?;
            let names = Names::catalog();
            let written = master
                .read_remote_pdo(node, id)
                .await?
                .with_context(|| format!("{id} is gone after writing it"))?;
            describe(&written, &names)
                .iter()
                .for_each(|l| println!("{l}"));
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mappings_parse() {
        assert_eq!(
            parse_map("0x6520:1:32, 0x6300:0:8").unwrap(),
            [
                MapEntry {
                    index: 0x6520,
                    sub: 1,
                    bits: 32
                },
                MapEntry {
                    index: 0x6300,
                    sub: 0,
                    bits: 8
                }
            ]
        );
        assert!(parse_map("").unwrap().is_empty());
        assert!(parse_map("0x6520:1").is_err());
        assert!(parse_map("0x6520:1:65").is_err());
        assert!(parse_map("0x16520:1:8").is_err());
    }
}
