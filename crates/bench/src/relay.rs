//! `canlift-bench relay`: a process that copies TCP bytes both ways and does nothing else —
//! `portal`'s measure of what one more process in a request's path costs at the least.

use std::net::SocketAddr;

/// Arguments of the hidden `canlift-bench relay`.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct RelayArgs {
    /// Where to accept connections.
    #[arg(long)]
    pub(crate) listen: SocketAddr,
    /// Where to relay each of them.
    #[arg(long)]
    pub(crate) to: SocketAddr,
}

/// Relay every connection to `args.to`, byte for byte, as a TCP proxy does: no TLS, no
/// parsing, Nagle off on both sides so that nothing waits to be batched.
pub(crate) async fn relay(args: RelayArgs) -> anyhow::Result<()> {
    let listener = tokio::net::TcpListener::bind(args.listen).await?;
    loop {
        let (mut inbound, _) = listener.accept().await?;
        tokio::spawn(async move {
            // Onward only once the client has spoken: a probe that connects to see whether
            // the relay listens must not take the place of a real client at the far end.
            if inbound.peek(&mut [0]).await? == 0 {
                return Ok(());
            }
            let mut outbound = tokio::net::TcpStream::connect(args.to).await?;
            inbound.set_nodelay(true)?;
            outbound.set_nodelay(true)?;
            tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await?;
            anyhow::Ok(())
        });
    }
}
