//! `canlift scan`: which nodes are on the bus, and what they are. Nodes are found by their
//! heartbeat or boot-up message (CiA 301 §7.2.8.3.2) and, with `--probe`, by an SDO read of
//! 1000h on every node-ID; each one found is asked for its identity (1000h, 1018h, 1008h,
//! 100Ah), in parallel.

use std::time::Duration;

use anyhow::Context;
use canopen::heartbeat::NodeState;
use canopen::master::Master;
use canopen::sdo::client::ClientConfig;
use canopen::sdo::clients::SdoClients;
use futures_util::future::join_all;
use serde::Serialize;

/// Command-line arguments of `canlift scan`.
#[derive(Debug, clap::Args)]
pub struct ScanArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// Listen this long for heartbeats and boot-up messages.
    #[arg(long, default_value_t = 1500)]
    listen_ms: u64,
    /// Also read 1000h of every node-ID 1–127 (finds nodes without a heartbeat).
    #[arg(long)]
    probe: bool,
    /// SDO timeout for each read, in milliseconds.
    #[arg(long, default_value_t = 300)]
    timeout_ms: u64,
    /// Print a JSON list instead of a table.
    #[arg(long)]
    json: bool,
}

/// One node found, as `--json` prints it.
#[derive(Debug, Serialize)]
struct Found {
    node: u8,
    /// NMT state from its heartbeat, `unknown` when found by probing only.
    state: &'static str,
    /// 1000h, e.g. `0x000901A1`.
    device_type: Option<String>,
    /// The profile in 1000h's low word, e.g. `417 lift control`.
    profile: Option<String>,
    vendor: Option<String>,
    product: Option<String>,
    revision: Option<String>,
    serial: Option<String>,
    /// 1008h.
    name: Option<String>,
    /// 100Ah.
    software: Option<String>,
}

/// CiA device profiles by number (the low 16 bits of 1000h, CiA 301 §7.5.2.1).
fn profile_name(number: u16) -> &'static str {
    match number {
        0 => "no profile",
        401 => "generic I/O",
        402 => "drives and motion control",
        404 => "measuring devices",
        405 => "IEC 61131-3 programmable devices",
        406 => "encoders",
        408 => "hydraulic drives",
        410 => "inclinometers",
        413 => "truck gateways",
        415 => "road construction machinery",
        417 => "lift control",
        418 => "battery modules",
        419 => "battery chargers",
        443 => "SIIS level-2 devices",
        447 => "car add-on devices",
        _ => "other profile",
    }
}

fn state_name(state: NodeState) -> &'static str {
    match state {
        NodeState::Unknown => "unknown",
        NodeState::BootUp => "boot-up",
        NodeState::PreOperational => "pre-operational",
        NodeState::Operational => "operational",
        NodeState::Stopped => "stopped",
        NodeState::Offline => "offline",
    }
}

/// Run the scan and print what was found.
pub async fn run(args: ScanArgs) -> anyhow::Result<()> {
    let timeout = Duration::from_millis(args.timeout_ms.max(1));
    let config = ClientConfig {
        timeout,
        ..ClientConfig::default()
    };
    let master = Master::open(&args.bus.url, config)
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    let sdo = master.sdo();
    let probing = async {
        if !args.probe {
            return Vec::new();
        }
        let reads = (1..=127u8)
            .map(|node| async move { sdo.read_raw(node, 0x1000, 0).await.ok().map(|_| node) });
        join_all(reads).await.into_iter().flatten().collect()
    };
    let (probed, ()) = tokio::join!(
        probing,
        tokio::time::sleep(Duration::from_millis(args.listen_ms))
    );
    let mut nodes: Vec<(u8, NodeState)> = master
        .nodes()
        .into_iter()
        .filter(|(node, _)| (1..=127).contains(node))
        .collect();
    for node in probed {
        if !nodes.iter().any(|(n, _)| *n == node) {
            nodes.push((node, NodeState::Unknown));
        }
    }
    nodes.sort_by_key(|(node, _)| *node);
    let found = join_all(
        nodes
            .into_iter()
            .map(|(node, state)| identify(sdo, node, state)),
    )
    .await;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&found)?);
    } else {
        print!("{}", table(&found));
    }
    Ok(())
}

/// Ask `node` who it is; what it does not answer stays empty.
async fn identify(sdo: &SdoClients, node: u8, state: NodeState) -> Found {
    let u32_at = |index, sub| async move { sdo.read::<u32>(node, index, sub).await.ok() };
    let text_at = |index| async move {
        sdo.read_raw(node, index, 0).await.ok().map(|b| {
            String::from_utf8_lossy(&b)
                .trim_end_matches('\0')
                .to_owned()
        })
    };
    let hex = |v: Option<u32>| v.map(|v| format!("0x{v:08X}"));
    let device_type = u32_at(0x1000, 0).await;
    Found {
        node,
        state: state_name(state),
        device_type: hex(device_type),
        profile: device_type.map(|t| {
            let number = (t & 0xFFFF) as u16;
            format!("{number} {}", profile_name(number))
        }),
        vendor: hex(u32_at(0x1018, 1).await),
        product: hex(u32_at(0x1018, 2).await),
        revision: hex(u32_at(0x1018, 3).await),
        serial: hex(u32_at(0x1018, 4).await),
        name: text_at(0x1008).await,
        software: text_at(0x100A).await,
    }
}

/// The table the command prints: one row per node, `-` for what the node did not answer.
fn table(found: &[Found]) -> String {
    let header = [
        "node", "state", "profile", "vendor", "product", "revision", "serial", "name", "software",
    ];
    let rows: Vec<[String; 9]> = found
        .iter()
        .map(|f| {
            let or_dash = |v: &Option<String>| v.clone().unwrap_or_else(|| "-".into());
            [
                f.node.to_string(),
                f.state.to_owned(),
                or_dash(&f.profile),
                or_dash(&f.vendor),
                or_dash(&f.product),
                or_dash(&f.revision),
                or_dash(&f.serial),
                or_dash(&f.name),
                or_dash(&f.software),
            ]
        })
        .collect();
    let mut widths = header.map(str::len);
    for row in &rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let line = |cells: &[String]| {
        let mut out = String::new();
        for (i, (cell, w)) in cells.iter().zip(widths).enumerate() {
            if i + 1 == cells.len() {
                out.push_str(cell);
            } else {
                out.push_str(&format!("{cell:<w$}  "));
            }
        }
        out.push('\n');
        out
    };
    let mut out = line(&header.map(str::to_owned));
    for row in &rows {
        out.push_str(&line(row));
    }
    if rows.is_empty() {
        out.push_str("no node answered\n");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_aligns_and_dashes_what_is_missing() {
        let found = [Found {
            node: 1,
            state: "operational",
            device_type: Some("0x000901A1".into()),
            profile: Some("417 lift control".into()),
            vendor: Some("0x00000123".into()),
            product: None,
            revision: None,
            serial: None,
            name: Some("controller".into()),
            software: None,
        }];
        let t = table(&found);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 2);
        assert!(lines[0].starts_with("node  state        profile           vendor"));
        assert!(lines[1].starts_with("1     operational  417 lift control  0x00000123"));
        assert!(lines[1].ends_with("controller  -"));
        assert_eq!(table(&[]).lines().nth(1), Some("no node answered"));
        assert_eq!(profile_name(417), "lift control");
        assert_eq!(profile_name(401), "generic I/O");
    }
}
