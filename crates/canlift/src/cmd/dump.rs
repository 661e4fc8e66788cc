//! `canlift dump`: a candump-style bus monitor with a CANopen column.

use std::collections::HashMap;
use std::io::{BufWriter, ErrorKind, Write};
use std::time::{Duration, UNIX_EPOCH};

use anyhow::Context;
use canbus::{Bus, BusEvent, BusUrl, CanId, Frame};
use canopen::monitor::{decode_pdo, pdo_layouts, Meaning, PdoLayout, SdoTracker};
use canopen::nmt::NmtState;
use canopen::od::ObjectDictionary;
use canopen::sdo::client::ClientConfig;
use canopen::sdo::clients::SdoClients;

/// Command-line arguments of `canlift dump`.
#[derive(Debug, clap::Args)]
pub struct DumpArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// Print the receive time (seconds since the epoch) before each frame.
    #[arg(short = 't', long)]
    timestamp: bool,
    /// Leave out the CANopen column.
    #[arg(long)]
    raw: bool,
    /// Exit after this many frames.
    #[arg(short = 'n', long)]
    count: Option<u64>,
    /// Decode the PDOs of node NODE with the mappings (and data types) of an EDS/DCF:
    /// `--eds 1=lift.eds`. Repeatable.
    #[arg(long, value_name = "NODE=FILE")]
    eds: Vec<String>,
    /// Read the PDO mappings of every node over SDO when it is first heard and again when it
    /// turns operational (values are then shown as unsigned integers, the types being unknown).
    #[arg(long)]
    read_pdo_mappings: bool,
}

type Layouts = HashMap<CanId, PdoLayout>;

fn load_eds_layouts(specs: &[String]) -> anyhow::Result<Layouts> {
    let mut layouts = Layouts::new();
    for spec in specs {
        let (node, file) = spec
            .split_once('=')
            .with_context(|| format!("--eds takes NODE=FILE, not {spec:?}"))?;
        let node: u8 = node
            .parse()
            .with_context(|| format!("invalid node-ID in {spec:?}"))?;
        let description =
            canopen::eds::import_file(std::path::Path::new(file), Some(node))?.logged();
        layouts.extend(pdo_layouts(&description.od, node));
    }
    Ok(layouts)
}

/// Read the PDO communication and mapping parameters of `node` (PDOs 1–4 each way).
async fn read_mappings(sdo: &SdoClients, node: u8) -> Vec<(CanId, PdoLayout)> {
    let mut od = ObjectDictionary::new();
    canopen::pdo::add_pdo_objects(&mut od, node, 4, 4);
    for base in [canopen::pdo::TPDO_COMM, canopen::pdo::RPDO_COMM] {
        for n in 0..4u16 {
            let map = base + 0x200 + n;
            let cob = sdo.read::<u32>(node, base + n, 1).await;
            let count = sdo.read::<u8>(node, map, 0).await;
            let (Ok(cob), Ok(count)) = (cob, count) else {
                continue;
            };
            let _ = od.set(base + n, 1, &cob.to_le_bytes());
            for sub in 1..=count.min(8) {
                if let Ok(entry) = sdo.read::<u32>(node, map, sub).await {
                    let _ = od.set(map, sub, &entry.to_le_bytes());
                }
            }
            let _ = od.set(map, 0, &[count.min(8)]);
        }
    }
    pdo_layouts(&od, node)
}

/// Interface name in the first column, as candump shows it.
fn channel_name(url: &BusUrl) -> &str {
    match url {
        BusUrl::Mem(name) | BusUrl::Socketcan(name) => name,
        BusUrl::Socketcand { channel, .. } => channel,
    }
}

/// One output line for `frame`, decoding PDOs whose layout is known.
fn format_line(
    channel: &str,
    frame: &Frame,
    timestamp: bool,
    decode: bool,
    layouts: &Layouts,
) -> String {
    let mut line = String::with_capacity(96);
    if timestamp {
        let at = frame
            .timestamp()
            .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
            .unwrap_or_default();
        line.push_str(&format!("({}.{:06}) ", at.as_secs(), at.subsec_micros()));
    }
    let body = format!("{channel:>6}  {frame}");
    let meaning = match (decode, layouts.get(&frame.id())) {
        (false, _) => String::new(),
        (true, Some(layout)) => decode_pdo(layout, frame.data()),
        (true, None) => canopen::monitor::decode(frame)
            .explained(lift417::emcy::describe)
            .to_string(),
    };
    if meaning.is_empty() {
        line.push_str(&body);
    } else {
        line.push_str(&format!("{body:<50}  {meaning}"));
    }
    line
}

/// Print frames until interrupted, the count is reached or the bus goes away.
pub async fn run(args: DumpArgs) -> anyhow::Result<()> {
    let mut bus = Bus::open(&args.bus.url).await?;
    let channel = channel_name(bus.url()).to_owned();
    let mut layouts = load_eds_layouts(&args.eds)?;
    let mut tracker = SdoTracker::new();
    let (learned_tx, mut learned) =
        tokio::sync::mpsc::unbounded_channel::<Vec<(CanId, PdoLayout)>>();
    let sdo = if args.read_pdo_mappings && !args.raw {
        let config = ClientConfig {
            timeout: Duration::from_millis(500),
            ..ClientConfig::default()
        };
        Some(SdoClients::new(Bus::open(&args.bus.url).await?, config))
    } else {
        None
    };
    // Each node's last heartbeat state, for when to read its mappings.
    let mut states: HashMap<u8, u8> = HashMap::new();
    let mut out = BufWriter::new(std::io::stdout().lock());
    let mut seen = 0u64;
    let shutdown = crate::service::shutdown_signal();
    tokio::pin!(shutdown);
    loop {
        let event = tokio::select! {
            e = bus.recv() => e,
            Some(found) = learned.recv() => {
                layouts.extend(found);
                continue;
            }
            _ = &mut shutdown => None,
        };
        let Some(mut event) = event else { break };
        loop {
            let written = match &event {
                BusEvent::Frame(f) => {
                    seen += 1;
                    let line = format_line(&channel, f, args.timestamp, !args.raw, &layouts);
                    let transfer = (!args.raw).then(|| tracker.feed(f)).flatten();
                    if let (Some(sdo), Meaning::Heartbeat { node, state, .. }) =
                        (&sdo, canopen::monitor::decode(f))
                    {
                        // When first heard, and again when it turns operational: a master
                        // configures PDOs in pre-operational, after the boot-up (CiA 301 §7.3.2),
                        // and they count from the start on.
                        let before = states.insert(node, state);
                        let operational = NmtState::Operational.code();
                        if before.is_none() || (state == operational && before != Some(state)) {
                            let (sdo, tx) = (sdo.clone(), learned_tx.clone());
                            tokio::spawn(async move {
                                let _ = tx.send(read_mappings(&sdo, node).await);
                            });
                        }
                    }
                    match transfer {
                        Some(t) => writeln!(out, "{line}\n{:>8}=> {t}", ""),
                        None => writeln!(out, "{line}"),
                    }
                }
                BusEvent::LinkDown { reason } => writeln!(out, "# link down: {reason}"),
                BusEvent::LinkUp => writeln!(out, "# link up"),
                BusEvent::Overrun { dropped } => {
                    writeln!(out, "# {dropped} frame(s) lost (overrun)")
                }
            };
            match written {
                Err(e) if e.kind() == ErrorKind::BrokenPipe => return Ok(()),
                other => other?,
            }
            if args.count.is_some_and(|n| seen >= n) {
                out.flush()?;
                return Ok(());
            }
            match bus.receiver.try_recv() {
                Some(next) => event = next,
                None => break,
            }
        }
        match out.flush() {
            Err(e) if e.kind() == ErrorKind::BrokenPipe => return Ok(()),
            other => other?,
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_look_like_candump_with_a_canopen_column() {
        let f = Frame::standard(0x181, &[0xCD, 0x82, 0x01, 0x00]).unwrap();
        let line = format_line("can0", &f, false, true, &Layouts::new());
        assert!(line.starts_with("  can0  181   [4]  CD 82 01 00"), "{line}");
        assert!(line.ends_with("  TPDO1 node 1"), "{line}");
        assert_eq!(
            format_line("can0", &f, false, false, &Layouts::new()),
            "  can0  181   [4]  CD 82 01 00"
        );
        let at = UNIX_EPOCH + std::time::Duration::from_micros(1_700_000_000_000_001);
        let line = format_line("x", &f.with_timestamp(at), true, false, &Layouts::new());
        assert!(
            line.starts_with("(1700000000.000001)      x  181"),
            "{line}"
        );
        // EMCY codes of the lift profile are named.
        let emcy = Frame::standard(0x081, &[0x01, 0xFF, 0x21, 0, 0, 0, 0, 0]).unwrap();
        let line = format_line("can0", &emcy, false, true, &Layouts::new());
        assert!(
            line.ends_with("EMCY node 1: code FF01 Door blocked, register 21, data 00 00 00 00 00"),
            "{line}"
        );
    }
}
