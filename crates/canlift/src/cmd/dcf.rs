//! `canlift dcf apply|read`: a node's configuration as a DCF (CiA 306), in the manner of
//! CiA 302-2 configuration management: check the node's identity against the DCF's
//! `[DeviceInfo]`, write every `ParameterValue` by SDO (PDOs through the CiA 301 mapping
//! procedure), optionally store (1010h); or read a node's current values into a DCF.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{bail, Context};
use canopen::eds::{self, DeviceDescription};
use canopen::master::Master;
use canopen::pdo::remote::{PdoId, RemotePdo};
use canopen::pdo::MapEntry;
use canopen::sdo::client::ClientConfig;
use canopen::types;

/// Command-line arguments of `canlift dcf`.
#[derive(Debug, clap::Args)]
pub struct DcfArgs {
    #[command(flatten)]
    bus: super::BusArg,
    #[command(subcommand)]
    op: DcfOp,
}

#[derive(Debug, clap::Subcommand)]
enum DcfOp {
    /// Write the DCF's ParameterValues to NODE (after checking its identity).
    Apply {
        /// Node-ID (1–127).
        node: u8,
        /// The DCF.
        file: PathBuf,
        /// Then make the node store its parameters (1010h sub 1 = "save").
        #[arg(long)]
        store: bool,
    },
    /// Read NODE's current values of every object in EDS and print them as a DCF.
    Read {
        /// Node-ID (1–127).
        node: u8,
        /// The node's EDS (or a DCF).
        eds: PathBuf,
    },
}

/// "save" (CiA 301 §7.5.2.13): the signature 1010h takes.
const SAVE: u32 = 0x6576_6173;

/// Identity keys of `[DeviceInfo]` and the 1018h sub-index each must match.
const IDENTITY: [(&str, u8); 3] = [
    ("VendorNumber", 1),
    ("ProductNumber", 2),
    ("RevisionNumber", 3),
];

/// Objects whose writes are commands, not configuration: error history (1003h: writing 0
/// clears it), store and restore (1010h, 1011h: `--store` is the explicit way), program
/// download and control (1F50h–1F5Fh, CiA 302-3).
fn is_command(index: u16) -> bool {
    matches!(index, 0x1003 | 0x1010 | 0x1011 | 0x1F50..=0x1F5F)
}

/// Run `apply` or `read`.
pub async fn run(args: DcfArgs) -> anyhow::Result<()> {
    let master = Master::open(&args.bus.url, ClientConfig::default())
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    match args.op {
        DcfOp::Apply { node, file, store } => {
            // A configuration is written exactly or not at all: a defect of the file stops it.
            let imported = eds::import_file(&file, Some(node))?;
            if !imported.findings.is_empty() {
                for finding in &imported.findings {
                    eprintln!("{finding}");
                }
                bail!(
                    "{}: {} defect(s); nothing written (canlift eds check lists them)",
                    file.display(),
                    imported.findings.len()
                );
            }
            let dcf = imported.description;
            check_identity(&master, node, &dcf).await?;
            let failed = apply(&master, node, &dcf).await;
            if store {
                master
                    .sdo()
                    .write(node, 0x1010, 1, SAVE)
                    .await
                    .context("storing the parameters (1010h sub 1)")?;
                println!("1010h sub 1  save  OK");
            }
            if failed > 0 {
                bail!("{failed} write(s) failed");
            }
            Ok(())
        }
        DcfOp::Read { node, eds } => {
            let mut description = eds::import_file(&eds, Some(node))?.logged();
            read_values(&master, node, &mut description).await;
            description
                .commissioning
                .get_or_insert_with(Default::default)
                .node_id = Some(node);
            print!("{}", eds::export(&description, true));
            Ok(())
        }
    }
}

/// Refuse a node whose 1018h differs from the DCF's `[DeviceInfo]`.
async fn check_identity(master: &Master, node: u8, dcf: &DeviceDescription) -> anyhow::Result<()> {
    let mut differences = Vec::new();
    for (key, sub) in IDENTITY {
        let Some((_, text)) = dcf
            .device_info
            .iter()
            .find(|(k, v)| k.eq_ignore_ascii_case(key) && !v.trim().is_empty())
        else {
            continue;
        };
        let expected: u32 = super::parse_number(&format!("[DeviceInfo] {key}"), text)?;
        let actual = master
            .sdo()
            .read::<u32>(node, 0x1018, sub)
            .await
            .with_context(|| format!("reading node {node}'s identity (1018h sub {sub})"))?;
        if actual != expected {
            differences.push(format!(
                "{key}: the DCF says 0x{expected:08X}, node {node} has 0x{actual:08X}"
            ));
        }
    }
    if !differences.is_empty() {
        bail!(
            "node {node} is not the device this DCF describes:\n  {}",
            differences.join("\n  ")
        );
    }
    Ok(())
}

/// Write every writable `ParameterValue`; PDOs as whole configurations. Returns the failures.
async fn apply(master: &Master, node: u8, dcf: &DeviceDescription) -> usize {
    let mut failed = 0;
    let mut pdos = BTreeSet::new();
    for object in dcf.od.objects() {
        if let Some(id) = PdoId::of_index(object.index) {
            pdos.insert(id.communication());
            continue;
        }
        if is_command(object.index) {
            continue;
        }
        for (&sub, var) in &object.subs {
            if !var.parameter_value || !var.access.writable() {
                continue;
            }
            let Some(bytes) = var.value_bytes() else {
                continue;
            };
            let text = types::decode(var.data_type, bytes)
                .map(|v| types::to_text(var.data_type, &v))
                .unwrap_or_default();
            match master
                .sdo()
                .write_with(node, object.index, sub, bytes.to_vec(), Default::default())
                .await
            {
                Ok(()) => println!("{:04X}h sub {sub:<3}  {text}  OK", object.index),
                Err(e) => {
                    failed += 1;
                    println!("{:04X}h sub {sub:<3}  {text}  FAILED: {e}", object.index);
                }
            }
        }
    }
    for comm in pdos {
        let Some(pdo) = pdo_from_dcf(dcf, comm) else {
            continue;
        };
        match master.configure_remote_pdo(node, &pdo).await {
            Ok(()) => println!(
                "{}  COB-ID 0x{:08X}  type {}  {} mapped  OK",
                pdo.id,
                pdo.cob_id,
                pdo.transmission,
                pdo.mapping.len()
            ),
            Err(e) => {
                failed += 1;
                println!("FAILED: {e}");
            }
        }
    }
    failed
}

/// A PDO's configuration as the DCF gives it (only when it gives a ParameterValue for it).
fn pdo_from_dcf(dcf: &DeviceDescription, comm: u16) -> Option<RemotePdo> {
    let id = PdoId::of_index(comm)?;
    let map = id.mapping();
    let uint = |index, sub| match dcf.od.get_value(index, sub) {
        Ok(types::Value::Uint(u)) => Some(u),
        _ => None,
    };
    let configured = |index, sub| dcf.od.variable(index, sub).is_ok_and(|v| v.parameter_value);
    if ![1, 2, 3, 5, 6].iter().any(|&sub| configured(comm, sub)) && !configured(map, 0) {
        return None;
    }
    // Optional parameters are written only when the DCF configures them.
    let given = |sub| uint(comm, sub).filter(|_| configured(comm, sub));
    let count = uint(map, 0).unwrap_or(0).min(64) as u8;
    Some(RemotePdo {
        id,
        cob_id: uint(comm, 1).unwrap_or(0x8000_0000) as u32,
        transmission: uint(comm, 2).unwrap_or(255) as u8,
        inhibit_100us: given(3).map(|v| v as u16),
        event_ms: given(5).map(|v| v as u16),
        sync_start: given(6).map(|v| v as u8),
        mapping: (1..=count)
            .filter_map(|sub| uint(map, sub))
            .map(|v| MapEntry::from_u32(v as u32))
            .collect(),
    })
}

/// Read every readable object of the description from the node into its values, each one a
/// `ParameterValue` of the DCF; what the node does not answer has none (and is reported on
/// stderr).
async fn read_values(master: &Master, node: u8, description: &mut DeviceDescription) {
    let addresses: Vec<(u16, u8)> = description
        .od
        .objects()
        .flat_map(|o| {
            o.subs
                .iter()
                .filter(|(_, v)| v.access.readable())
                .map(move |(&sub, _)| (o.index, sub))
        })
        .collect();
    for (index, sub) in addresses {
        match master.sdo().read_raw(node, index, sub).await {
            Ok(bytes) => match description.od.set(index, sub, &bytes) {
                Ok(()) => {
                    if let Some(var) = description
                        .od
                        .object_mut(index)
                        .and_then(|o| o.subs.get_mut(&sub))
                    {
                        var.parameter_value = true;
                    }
                }
                Err(e) => {
                    eprintln!("{index:04X}h sub {sub}: the node's value does not fit the EDS: {e}")
                }
            },
            Err(e) => eprintln!("{index:04X}h sub {sub}: {e}"),
        }
    }
}
