//! `canlift emcy send|watch`: emergency messages (CiA 301 §7.2.7) from the command line: send
//! one as a node would (to test a supervisor or the portal's alarms), or watch them with their
//! meaning (the CiA 301 class and the CiA 417 / lift fault).

use anyhow::{bail, Context};

use super::parse_number;
use canbus::{Bus, BusEvent, Frame};
use canopen::emcy::EmcyMessage;

/// Command-line arguments of `canlift emcy`.
#[derive(Debug, clap::Args)]
pub struct EmcyArgs {
    #[command(flatten)]
    bus: super::BusArg,
    #[command(subcommand)]
    op: EmcyOp,
}

#[derive(Debug, clap::Subcommand)]
enum EmcyOp {
    /// Send one EMCY as node NODE (COB-ID 80h + NODE).
    Send {
        /// The producing node-ID (1–127).
        node: u8,
        /// The error code, e.g. 0xFF01 (0x0000 = error reset).
        code: String,
        /// The error register (1001h) to report.
        #[arg(long, default_value = "0x01")]
        register: String,
        /// The manufacturer-specific field: up to 5 bytes in hex.
        #[arg(long, default_value = "")]
        data: String,
    },
    /// Print every EMCY with its meaning until Ctrl-C (or --count).
    Watch {
        /// Stop after this many.
        #[arg(long)]
        count: Option<u64>,
    },
}

/// One watched EMCY as a line: node, code, meaning, register and data.
pub fn describe(node: u8, message: &EmcyMessage) -> String {
    let (en, _) = lift417::emcy::describe(message.code);
    let data: Vec<String> = message
        .manufacturer
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect();
    format!(
        "node {node:<3} {:04X}  {en}  register 0x{:02X}  data {}",
        message.code,
        message.register,
        data.join(" ")
    )
}

/// Send or watch.
pub async fn run(args: EmcyArgs) -> anyhow::Result<()> {
    let mut bus = Bus::open(&args.bus.url)
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    match args.op {
        EmcyOp::Send {
            node,
            code,
            register,
            data,
        } => {
            if !(1..=127).contains(&node) {
                bail!("node-ID {node} is outside 1–127");
            }
            let bytes = match canopen::types::from_text(canopen::types::DataType::Domain, &data)? {
                canopen::types::Value::Bytes(b) if b.len() <= 5 => b,
                _ => bail!("--data takes at most 5 bytes in hex"),
            };
            let mut manufacturer = [0u8; 5];
            manufacturer[..bytes.len()].copy_from_slice(&bytes);
            let message = EmcyMessage {
                code: parse_number("error code", &code)?,
                register: parse_number("error register", &register)?,
                manufacturer,
            };
            let frame = Frame::standard(0x080 + u16::from(node), &message.to_bytes())?;
            bus.send(frame).await?;
            bus.sender.flush().await?;
            println!("{}", describe(node, &message));
            Ok(())
        }
        EmcyOp::Watch { count } => {
            eprintln!("watching EMCY on {} (Ctrl-C ends)", args.bus.url);
            let mut seen = 0u64;
            let watch = async {
                while count.is_none_or(|n| seen < n) {
                    match bus.receiver.recv().await {
                        Some(BusEvent::Frame(frame)) => {
                            if let Some((node, message)) = EmcyMessage::from_frame(&frame) {
                                println!("{}", describe(node, &message));
                                seen += 1;
                            }
                        }
                        Some(_) => {}
                        None => bail!("the bus closed"),
                    }
                }
                anyhow::Ok(())
            };
            tokio::select! {
                result = watch => result,
                signal = tokio::signal::ctrl_c() => signal.context("waiting for Ctrl-C"),
            }
        }
    }
}
