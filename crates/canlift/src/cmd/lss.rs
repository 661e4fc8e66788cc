//! `canlift lss …`: layer setting services (CiA 305) from the command line, for giving nodes
//! their node-ID and bit rate on site. Each service runs as the CiA 309-3 gateway runs it
//! (`canlift ascii`), so both report the same way.

use std::time::Duration;

use anyhow::{bail, Context};

use super::parse_number;
use canopen::ascii::{LssJob, Outcome, Reply};
use canopen::lss::FastscanPart;
use canopen::master::Master;
use canopen::sdo::client::ClientConfig;

/// Command-line arguments of `canlift lss`.
#[derive(Debug, clap::Args)]
pub struct LssArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// How long a node has to answer, in milliseconds.
    #[arg(long, global = true, default_value_t = 200)]
    timeout_ms: u64,
    #[command(subcommand)]
    op: LssOp,
}

#[derive(Debug, clap::Subcommand)]
enum LssOp {
    /// Switch every node to configuration state (`on`) or back to waiting (`off`).
    SwitchGlobal {
        /// on (configuration) or off (waiting).
        #[arg(value_parser = ["on", "off"])]
        state: String,
    },
    /// Switch the node with this LSS address to configuration state.
    SwitchSelective {
        /// Vendor-ID (1018h sub 1).
        vendor: String,
        /// Product code (1018h sub 2).
        product: String,
        /// Revision number (1018h sub 3).
        revision: String,
        /// Serial number (1018h sub 4).
        serial: String,
    },
    /// Give the node in configuration state a node-ID (1–127, 255 = unconfigured); it takes
    /// effect at its next reset communication, or at once when it had none.
    SetNode {
        /// The new node-ID.
        id: String,
    },
    /// Set the bit rate of the node in configuration state (CiA 305 table index: 0 = 1000,
    /// 1 = 800, 2 = 500, 3 = 250, 4 = 125, 6 = 50, 7 = 20, 8 = 10 kbit/s, 9 = auto).
    SetBitrate {
        /// The table index.
        index: String,
    },
    /// Tell every node in configuration to switch to its new bit rate after DELAY_MS.
    ActivateBitrate {
        /// Switch delay in milliseconds.
        delay_ms: u16,
    },
    /// Make the node in configuration state store its node-ID and bit rate.
    Store,
    /// The LSS address and node-ID of the node in configuration state.
    Inquire,
    /// Find unconfigured nodes (node-ID 255) by their LSS address, bit by bit.
    Fastscan {
        /// Give every unconfigured node a node-ID in turn, from this one.
        #[arg(long)]
        assign: Option<u8>,
        /// With --assign: make each node store its new node-ID.
        #[arg(long, requires = "assign")]
        store: bool,
        /// How long each of the scan's 133 steps listens, in milliseconds.
        #[arg(long, default_value_t = 50)]
        step_ms: u64,
        /// Only nodes of this vendor-ID (checked in one step instead of 33).
        #[arg(long)]
        vendor: Option<String>,
        /// Only nodes with this product code.
        #[arg(long, conflicts_with = "skip_product")]
        product: Option<String>,
        /// Only nodes with this revision number.
        #[arg(long, conflicts_with = "skip_revision")]
        revision: Option<String>,
        /// Only the node with this serial number.
        #[arg(long)]
        serial: Option<String>,
        /// Do not look at product codes (reported as 0).
        #[arg(long)]
        skip_product: bool,
        /// Do not look at revision numbers (reported as 0).
        #[arg(long)]
        skip_revision: bool,
    },
}

/// What Fastscan does with each part of the address: match the value given, skip, or scan.
fn scan_parts(given: [(&str, Option<String>, bool); 4]) -> anyhow::Result<[FastscanPart; 4]> {
    let mut parts = [FastscanPart::Scan; 4];
    for (part, (what, value, skip)) in parts.iter_mut().zip(given) {
        *part = match (value, skip) {
            (Some(v), _) => FastscanPart::Match(parse_number(what, &v)?),
            (None, true) => FastscanPart::Skip,
            (None, false) => FastscanPart::Scan,
        };
    }
    Ok(parts)
}

/// Run one service and print its answer.
pub async fn run(args: LssArgs) -> anyhow::Result<()> {
    let master = Master::open(&args.bus.url, ClientConfig::default())
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    master.set_lss_timeout(Duration::from_millis(args.timeout_ms.max(1)));
    let jobs: Vec<LssJob> = match args.op {
        LssOp::SwitchGlobal { state } => vec![LssJob::SwitchGlobal(state == "on")],
        LssOp::SwitchSelective {
            vendor,
            product,
            revision,
            serial,
        } => vec![LssJob::SwitchSelective([
            parse_number("vendor-ID", &vendor)?,
            parse_number("product code", &product)?,
            parse_number("revision", &revision)?,
            parse_number("serial", &serial)?,
        ])],
        LssOp::SetNode { id } => {
            let id: u8 = parse_number("node-ID", &id)?;
            if !(1..=127).contains(&id) && id != 0xFF {
                bail!("node-ID {id} is outside 1–127 (or 255 for unconfigured)");
            }
            vec![LssJob::SetNode(id)]
        }
        LssOp::SetBitrate { index } => {
            vec![LssJob::ConfigureBitRate(parse_number("index", &index)?)]
        }
        LssOp::ActivateBitrate { delay_ms } => vec![LssJob::ActivateBitRate(delay_ms)],
        LssOp::Store => vec![LssJob::Store],
        LssOp::Inquire => vec![LssJob::InquireAddress(None), LssJob::GetNode],
        LssOp::Fastscan {
            assign,
            store,
            step_ms,
            vendor,
            product,
            revision,
            serial,
            skip_product,
            skip_revision,
        } => {
            let step = Duration::from_millis(step_ms.clamp(1, 10_000));
            let parts = scan_parts([
                ("vendor-ID", vendor, false),
                ("product code", product, skip_product),
                ("revision", revision, skip_revision),
                ("serial", serial, false),
            ])?;
            match assign {
                Some(first) if (1..=127).contains(&first) => vec![LssJob::AllNodes {
                    step,
                    parts,
                    first,
                    store,
                }],
                Some(first) => bail!("--assign {first} is outside 1–127"),
                None => vec![LssJob::Fastscan { step, parts }],
            }
        }
    };
    for job in &jobs {
        let outcome = super::ascii::run_lss(&master, job).await;
        match outcome {
            Outcome::Ok => println!("OK"),
            Outcome::Value(v) => println!("{v}"),
            Outcome::Lines(lines) => lines.iter().for_each(|l| println!("{l}")),
            error @ Outcome::Error(_) => {
                let reply = Reply {
                    sequence: None,
                    outcome: error,
                };
                bail!("{}", reply.to_string().trim_end());
            }
        }
    }
    if matches!(jobs.as_slice(), [LssJob::Fastscan { .. }]) {
        eprintln!(
            "(the node found is in configuration state: `canlift lss set-node ID` gives it a node-ID; `fastscan --assign FROM` configures every unconfigured node)"
        );
    }
    Ok(())
}
