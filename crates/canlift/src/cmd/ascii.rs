//! `canlift ascii`: a CiA 309-3 ASCII gateway (the command language of CANopenNode's
//! `cocomm` and of gateway devices) on a TCP port or on standard input/output. The language
//! itself is `canopen::ascii`; this is the driver that runs each command on the bus.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use canopen::ascii::{
    format_address, AsciiType, Failure, Internal, Job, LssJob, Outcome, Reply, Session, Step,
};
use canopen::lss::{FastscanMaster, FastscanPart};
use canopen::master::{LssError, Master};
use canopen::sdo::client::{ClientConfig, Transfer};
use canopen::sdo::clients::{ClientError, TransferOptions};
use tokio::io::{AsyncBufReadExt, AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, BufReader};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

/// Command-line arguments of `canlift ascii`.
#[derive(Debug, clap::Args)]
pub struct AsciiArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// Serve clients on this TCP address (one session each).
    #[arg(long, default_value = "127.0.0.1:60000")]
    listen: SocketAddr,
    /// Serve one session on standard input and output instead.
    #[arg(long)]
    stdio: bool,
    /// Default SDO timeout in milliseconds (a session changes its own with `set sdo_timeout`).
    #[arg(long, default_value_t = 500)]
    sdo_timeout_ms: u64,
    /// How long an LSS slave has to answer, in milliseconds.
    #[arg(long, default_value_t = 200)]
    lss_timeout_ms: u64,
    /// Longest command line in bytes (at least 64: the longest command without data); a
    /// longer one closes that client.
    #[arg(long, default_value_t = 1 << 20, value_parser = clap::value_parser!(u64).range(64..))]
    max_line: u64,
    /// Clients served at once; more are told so and closed.
    #[arg(long, default_value_t = 32)]
    max_clients: usize,
}

/// What every session shares.
struct Gateway {
    master: Master,
    sdo_timeout: Duration,
    max_line: usize,
    info: String,
}

/// Run the gateway until interrupted (or, with `--stdio`, until input ends).
pub async fn run(args: AsciiArgs) -> anyhow::Result<()> {
    let sdo_timeout = Duration::from_millis(args.sdo_timeout_ms.max(1));
    let config = ClientConfig {
        timeout: sdo_timeout,
        ..ClientConfig::default()
    };
    let master = Master::open(&args.bus.url, config)
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    master.set_lss_timeout(Duration::from_millis(args.lss_timeout_ms.max(1)));
    let gateway = Arc::new(Gateway {
        master,
        sdo_timeout,
        max_line: usize::try_from(args.max_line).unwrap_or(usize::MAX),
        info: format!(
            "canlift {} CiA 309-3 gateway, net 1 = {}",
            env!("CARGO_PKG_VERSION"),
            args.bus.url
        ),
    });
    if args.stdio {
        return serve(&gateway, tokio::io::stdin(), tokio::io::stdout()).await;
    }
    let listener = TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("listening on {}", args.listen))?;
    eprintln!(
        "canlift ascii: CiA 309-3 gateway on {} for {} (type `help`)",
        listener.local_addr()?,
        args.bus.url
    );
    let slots = Arc::new(Semaphore::new(args.max_clients.max(1)));
    let accept = async {
        loop {
            let (socket, peer) = match listener.accept().await {
                Ok(accepted) => accepted,
                Err(e) => {
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            let _ = socket.set_nodelay(true);
            let gateway = gateway.clone();
            let slots = slots.clone();
            tokio::spawn(async move {
                let (read, mut write) = socket.into_split();
                let Ok(_slot) = slots.try_acquire_owned() else {
                    tracing::warn!(%peer, "too many clients; closing");
                    let busy = Reply {
                        sequence: None,
                        outcome: Outcome::Error(Failure::Internal(
                            Internal::InternalState,
                            Some("(too many clients)".into()),
                        )),
                    };
                    let _ = write.write_all(busy.to_string().as_bytes()).await;
                    return;
                };
                tracing::info!(%peer, "client connected");
                match serve(&gateway, read, write).await {
                    Ok(()) => tracing::info!(%peer, "client left"),
                    Err(e) => tracing::info!(%peer, error = %e, "client closed"),
                }
            });
        }
    };
    tokio::select! {
        () = accept => Ok(()),
        signal = tokio::signal::ctrl_c() => signal.context("waiting for Ctrl-C"),
    }
}

/// One session: lines in, replies out, in order.
async fn serve(
    gateway: &Gateway,
    read: impl AsyncRead + Unpin,
    mut write: impl AsyncWrite + Unpin,
) -> anyhow::Result<()> {
    let mut reader = BufReader::new(read);
    let mut session = Session::new(1, gateway.sdo_timeout, gateway.info.clone());
    let mut line = Vec::new();
    loop {
        line.clear();
        let limit = u64::try_from(gateway.max_line).unwrap_or(u64::MAX) + 1;
        let n = (&mut reader)
            .take(limit)
            .read_until(b'\n', &mut line)
            .await?;
        if n == 0 {
            return Ok(());
        }
        if line.len() > gateway.max_line {
            let reply = Reply {
                sequence: None,
                outcome: Outcome::Error(Failure::Internal(
                    Internal::Syntax,
                    Some(format!("(line longer than {} bytes)", gateway.max_line)),
                )),
            };
            write.write_all(reply.to_string().as_bytes()).await?;
            anyhow::bail!("line longer than {} bytes", gateway.max_line);
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_end_matches(['\r', '\n']);
        let reply = match session.handle(text) {
            Step::Nothing => continue,
            Step::Reply(reply) => reply,
            Step::Run(job) => {
                let outcome = execute(&gateway.master, &job).await;
                job.reply(outcome)
            }
        };
        write.write_all(reply.to_string().as_bytes()).await?;
        write.flush().await?;
    }
}

/// Run one job on the bus.
async fn execute(master: &Master, job: &Job) -> Outcome {
    use canopen::ascii::Action;
    let options = TransferOptions {
        how: if job.sdo_block {
            Transfer::Block
        } else {
            Transfer::Normal
        },
        timeout: Some(job.sdo_timeout),
        ..TransferOptions::default()
    };
    match &job.action {
        Action::Read { index, sub, ty } => {
            match master
                .sdo()
                .read_with(job.node, *index, *sub, options)
                .await
            {
                Ok(bytes) => {
                    let ty = ty.unwrap_or(AsciiType {
                        data_type: canopen::types::DataType::Domain,
                        form: canopen::ascii::Form::HexBytes,
                    });
                    match ty.format(&bytes) {
                        Ok(text) => Outcome::Value(text),
                        Err(e) => Outcome::Error(Failure::Abort(e.abort_code())),
                    }
                }
                Err(e) => sdo_failure(&e),
            }
        }
        Action::Write { index, sub, data } => match master
            .sdo()
            .write_with(job.node, *index, *sub, data.clone(), options)
            .await
        {
            Ok(()) => Outcome::Ok,
            Err(e) => sdo_failure(&e),
        },
        Action::Nmt(command) => match master.nmt(*command, job.node).await {
            Ok(()) => Outcome::Ok,
            Err(e) => internal(Internal::InternalState, &e),
        },
        Action::Lss(lss) => run_lss(master, lss).await,
    }
}

fn sdo_failure(e: &ClientError) -> Outcome {
    match e {
        ClientError::Bus(_) | ClientError::Closed => internal(Internal::InternalState, e),
        _ => Outcome::Error(Failure::Abort(e.abort_code())),
    }
}

fn internal(e: Internal, detail: &dyn std::fmt::Display) -> Outcome {
    Outcome::Error(Failure::Internal(e, Some(format!("({detail})"))))
}

/// An LSS failure: no answer is a time-out; a refusal names what was refused.
fn lss_failure(e: LssError, refused: Internal) -> Outcome {
    match e {
        LssError::NoResponse => internal(Internal::Timeout, &"no LSS slave answered"),
        LssError::Refused(code) => internal(refused, &format_args!("error code {code}")),
        LssError::Bus(e) => internal(Internal::LssMedia, &e),
    }
}

/// Run one LSS service (also `canlift lss`).
pub(crate) async fn run_lss(master: &Master, job: &LssJob) -> Outcome {
    let done = |r: Result<(), LssError>, refused| match r {
        Ok(()) => Outcome::Ok,
        Err(e) => lss_failure(e, refused),
    };
    match *job {
        LssJob::SwitchGlobal(configuration) => done(
            master
                .lss_switch_global(configuration)
                .await
                .map_err(LssError::from),
            Internal::LssManufacturer,
        ),
        LssJob::SwitchSelective(address) => match master.lss_switch_selective(address).await {
            Ok(true) => Outcome::Ok,
            Ok(false) => lss_failure(LssError::NoResponse, Internal::LssManufacturer),
            Err(e) => lss_failure(e.into(), Internal::LssManufacturer),
        },
        LssJob::SetNode(id) => done(master.lss_configure_node_id(id).await, Internal::LssNodeId),
        LssJob::ConfigureBitRate(index) => done(
            master.lss_configure_bit_timing(index).await,
            Internal::LssBitRate,
        ),
        LssJob::ActivateBitRate(delay) => done(
            master
                .lss_activate_bit_timing(delay)
                .await
                .map_err(LssError::from),
            Internal::LssBitRate,
        ),
        LssJob::Store => done(master.lss_store().await, Internal::LssStore),
        LssJob::InquireAddress(None) => match master.lss_inquire_address().await {
            Ok(address) => Outcome::Value(format_address(address)),
            Err(e) => lss_failure(e, Internal::LssManufacturer),
        },
        LssJob::InquireAddress(Some(part)) => match master.lss_inquire_address().await {
            Ok(address) => Outcome::Value(format!("0x{:08X}", address[usize::from(part)])),
            Err(e) => lss_failure(e, Internal::LssManufacturer),
        },
        LssJob::GetNode => match master.lss_inquire_node_id().await {
            Ok(id) => Outcome::Value(id.to_string()),
            Err(e) => lss_failure(e, Internal::LssManufacturer),
        },
        LssJob::Fastscan { step, parts } => match fastscan(master, parts, step).await {
            Ok(Some(address)) => Outcome::Value(format_address(address)),
            Ok(None) => internal(Internal::Timeout, &"no unconfigured node answered"),
            Err(failed) => failed,
        },
        LssJob::AllNodes {
            step,
            parts,
            first,
            store,
        } => all_nodes(master, step, parts, first, store).await,
    }
}

/// One Fastscan (the parts were checked when the command was parsed).
async fn fastscan(
    master: &Master,
    parts: [FastscanPart; 4],
    step: Duration,
) -> Result<Option<[u32; 4]>, Outcome> {
    let scan = FastscanMaster::new(parts).map_err(|e| internal(Internal::Syntax, &e))?;
    master
        .lss_fastscan_parts(scan, step)
        .await
        .map_err(|e| lss_failure(e.into(), Internal::LssManufacturer))
}

/// `lss_allnodes` (and `canlift lss fastscan --assign`): Fastscan one unconfigured node after the other and give each the next
/// node-ID from `first` (storing it if asked); one line per node, then OK.
async fn all_nodes(
    master: &Master,
    step: Duration,
    parts: [FastscanPart; 4],
    first: u8,
    store: bool,
) -> Outcome {
    let mut lines = Vec::new();
    for id in first..=127 {
        let address = match fastscan(master, parts, step).await {
            Ok(Some(address)) => address,
            Ok(None) => break,
            Err(failed) => return failed,
        };
        if let Err(e) = master.lss_configure_node_id(id).await {
            return lss_failure(e, Internal::LssNodeId);
        }
        if store {
            if let Err(e) = master.lss_store().await {
                return lss_failure(e, Internal::LssStore);
            }
        }
        // Back to waiting: the node takes its new ID and boots, and stops answering Fastscan.
        if let Err(e) = master.lss_switch_global(false).await {
            return lss_failure(e.into(), Internal::LssMedia);
        }
        lines.push(format!("# node {id}: {}", format_address(address)));
    }
    lines.push(format!("# {} node(s) configured", lines.len()));
    Outcome::Lines(lines)
}
