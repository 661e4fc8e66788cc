//! `canlift dump`: a candump-style bus monitor with a CANopen column.

use std::io::{BufWriter, ErrorKind, Write};
use std::time::UNIX_EPOCH;

use canbus::{Bus, BusEvent, BusUrl, Frame};

/// Command-line arguments of `canlift dump`.
#[derive(Debug, clap::Args)]
pub struct DumpArgs {
    /// The bus to watch.
    #[arg(long, default_value = "socketcand://127.0.0.1:29536/can0")]
    bus: String,
    /// Print the receive time (seconds since the epoch) before each frame.
    #[arg(short = 't', long)]
    timestamp: bool,
    /// Leave out the CANopen column.
    #[arg(long)]
    raw: bool,
    /// Exit after this many frames.
    #[arg(short = 'n', long)]
    count: Option<u64>,
}

/// Interface name in the first column, as candump shows it.
fn channel_name(url: &BusUrl) -> &str {
    match url {
        BusUrl::Mem(name) | BusUrl::Socketcan(name) => name,
        BusUrl::Socketcand { channel, .. } => channel,
    }
}

/// One output line for `frame`.
pub fn format_line(channel: &str, frame: &Frame, timestamp: bool, decode: bool) -> String {
    let mut line = String::with_capacity(96);
    if timestamp {
        let at = frame
            .timestamp()
            .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
            .unwrap_or_default();
        line.push_str(&format!("({}.{:06}) ", at.as_secs(), at.subsec_micros()));
    }
    let body = format!("{channel:>6}  {frame}");
    let meaning = if decode {
        canopen::monitor::decode(frame).to_string()
    } else {
        String::new()
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
    let mut bus = Bus::open(&args.bus).await?;
    let channel = channel_name(bus.url()).to_owned();
    let mut out = BufWriter::new(std::io::stdout().lock());
    let mut seen = 0u64;
    let shutdown = crate::logging::shutdown_signal();
    tokio::pin!(shutdown);
    loop {
        let event = tokio::select! {
            e = bus.recv() => e,
            _ = &mut shutdown => None,
        };
        let Some(mut event) = event else { break };
        loop {
            let written = match &event {
                BusEvent::Frame(f) => {
                    seen += 1;
                    writeln!(
                        out,
                        "{}",
                        format_line(&channel, f, args.timestamp, !args.raw)
                    )
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
        let line = format_line("can0", &f, false, true);
        assert!(line.starts_with("  can0  181   [4]  CD 82 01 00"), "{line}");
        assert!(line.ends_with("  TPDO1 node 1"), "{line}");
        assert_eq!(
            format_line("can0", &f, false, false),
            "  can0  181   [4]  CD 82 01 00"
        );
        let at = UNIX_EPOCH + std::time::Duration::from_micros(1_700_000_000_000_001);
        let line = format_line("x", &f.with_timestamp(at), true, false);
        assert!(
            line.starts_with("(1700000000.000001)      x  181"),
            "{line}"
        );
    }
}
