//! `canlift nmt`: NMT node control from the command line.

use std::time::Duration;

use anyhow::{bail, Context};
use canbus::{Bus, BusEvent};
use canopen::heartbeat::{HeartbeatConsumer, HeartbeatEvent, NodeState};
use canopen::nmt::NmtCommand;

/// Command-line arguments of `canlift nmt`.
#[derive(Debug, clap::Args)]
pub struct NmtArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// start, stop, preop, reset or reset-comm.
    command: String,
    /// Node-ID 1–127, or `all`.
    node: String,
    /// Wait up to this many milliseconds for the node's heartbeat to show the new state
    /// (NMT itself is unconfirmed). Needs a single node and a heartbeat producer on it.
    #[arg(long)]
    wait_ms: Option<u64>,
}

fn parse_command(text: &str) -> anyhow::Result<NmtCommand> {
    Ok(match text {
        "start" => NmtCommand::Start,
        "stop" => NmtCommand::Stop,
        "preop" | "pre-operational" => NmtCommand::EnterPreOperational,
        "reset" | "reset-node" => NmtCommand::ResetNode,
        "reset-comm" | "reset-communication" => NmtCommand::ResetCommunication,
        other => bail!("unknown NMT command {other:?}: start, stop, preop, reset, reset-comm"),
    })
}

fn parse_node(text: &str) -> anyhow::Result<u8> {
    if text == "all" {
        return Ok(0);
    }
    let node: u8 = text
        .parse()
        .with_context(|| format!("invalid node {text:?}"))?;
    if !(1..=127).contains(&node) {
        bail!("node-ID {node} is outside 1–127");
    }
    Ok(node)
}

/// The heartbeat state a command leads to (resets end in a boot-up message).
fn expected_state(command: NmtCommand) -> NodeState {
    match command {
        NmtCommand::Start => NodeState::Operational,
        NmtCommand::Stop => NodeState::Stopped,
        NmtCommand::EnterPreOperational => NodeState::PreOperational,
        NmtCommand::ResetNode | NmtCommand::ResetCommunication => NodeState::BootUp,
    }
}

/// Send one NMT command.
pub async fn run(args: NmtArgs) -> anyhow::Result<()> {
    let command = parse_command(&args.command)?;
    let node = parse_node(&args.node)?;
    if args.wait_ms.is_some() && node == 0 {
        bail!("--wait-ms needs a single node");
    }
    let mut bus = Bus::open(&args.bus.url).await?;
    bus.send(command.frame(node)).await?;
    bus.sender.flush().await?;
    let Some(wait) = args.wait_ms else {
        return Ok(());
    };
    let want = expected_state(command);
    let mut consumer = HeartbeatConsumer::new();
    let mut events = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_millis(wait);
    loop {
        let event = tokio::time::timeout_at(deadline, bus.recv()).await;
        let Ok(Some(BusEvent::Frame(frame))) = event else {
            bail!("node {node} did not report {want:?} within {wait} ms");
        };
        consumer.handle(&frame, std::time::Instant::now(), &mut events);
        let seen = events.drain(..).any(|e| {
            matches!(e,
            HeartbeatEvent::StateChanged { node: n, new, .. } if n == node && new == want)
        });
        if seen {
            println!("node {node}: {want:?}");
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arguments() {
        assert_eq!(
            parse_command("preop").unwrap(),
            NmtCommand::EnterPreOperational
        );
        assert!(parse_command("go").is_err());
        assert_eq!(parse_node("all").unwrap(), 0);
        assert_eq!(parse_node("127").unwrap(), 127);
        assert!(parse_node("0").is_err() && parse_node("128").is_err());
    }
}
