//! `canlift hub`: the socketcand-compatible virtual CAN bus (docs/ARCHITECTURE.md §Conventions).

use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context};
use canbus::hub::{Hub, HubConfig};
use serde::{Deserialize, Serialize};

use crate::config;

/// Command-line arguments of `canlift hub`.
#[derive(Debug, clap::Args)]
pub struct HubArgs {
    /// Configuration file (TOML, section `[hub]`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Address to listen on [default: 127.0.0.1:29536].
    #[arg(long)]
    listen: Option<SocketAddr>,
    /// Simulate a bus of this bit rate (1000–1000000 bit/s): frames take their wire time and
    /// arbitrate by CAN-ID.
    #[arg(long)]
    bitrate: Option<u32>,
    /// Print the effective configuration and exit.
    #[arg(long)]
    print_config: bool,
}

/// The `[hub]` section of the configuration file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HubSettings {
    /// Address to listen on.
    pub listen: SocketAddr,
    /// Bus bit rate; absent: frames go through as fast as the host allows.
    pub bitrate: Option<u32>,
    /// Frames queued for one client before it is disconnected for not reading.
    pub client_queue: usize,
    /// Frames one client may have waiting for the bus in bit-rate mode.
    pub client_tx_queue: usize,
    /// Concurrent clients at most.
    pub max_clients: usize,
    /// Distinct channels at most.
    pub max_channels: usize,
    /// Seconds a client has to reach raw mode.
    pub handshake_timeout_s: u64,
}

impl Default for HubSettings {
    fn default() -> Self {
        let d = HubConfig::default();
        HubSettings {
            listen: d.listen,
            bitrate: d.bitrate,
            client_queue: d.client_queue,
            client_tx_queue: d.client_tx_queue,
            max_clients: d.max_clients,
            max_channels: d.max_channels,
            handshake_timeout_s: d.handshake_timeout.as_secs(),
        }
    }
}

impl HubSettings {
    fn into_config(self) -> anyhow::Result<HubConfig> {
        if let Some(rate) = self.bitrate {
            if !(1_000..=1_000_000).contains(&rate) {
                bail!("bitrate {rate} is outside 1000..=1000000 bit/s (classic CAN)");
            }
        }
        if self.client_queue == 0 || self.client_tx_queue == 0 || self.max_clients == 0 {
            bail!("client_queue, client_tx_queue and max_clients must be at least 1");
        }
        Ok(HubConfig {
            listen: self.listen,
            bitrate: self.bitrate,
            client_queue: self.client_queue,
            client_tx_queue: self.client_tx_queue,
            max_clients: self.max_clients,
            max_channels: self.max_channels,
            handshake_timeout: Duration::from_secs(self.handshake_timeout_s.max(1)),
            ..HubConfig::default()
        })
    }
}

/// Run the hub until SIGINT/SIGTERM.
pub async fn run(args: HubArgs) -> anyhow::Result<()> {
    let mut settings: HubSettings = config::load(args.config.as_deref(), "hub")?;
    if let Some(listen) = args.listen {
        settings.listen = listen;
    }
    if args.bitrate.is_some() {
        settings.bitrate = args.bitrate;
    }
    if args.print_config {
        print!("{}", config::render("hub", &settings)?);
        return Ok(());
    }
    let config = settings.into_config()?;
    let bitrate = config.bitrate;
    let hub = Hub::bind(config.clone())
        .await
        .with_context(|| format!("binding {}", config.listen))?;
    let addr = hub.local_addr()?;
    let mode = match bitrate {
        Some(b) => format!("{b} bit/s with arbitration"),
        None => "unthrottled".to_owned(),
    };
    // Tools (and `canlift-bench`) read the bound address from this first stdout line.
    println!("canlift hub listening on {addr} ({mode}); join with socketcand://{addr}/CHANNEL");
    std::io::stdout().flush()?;
    let stats = hub.stats();
    hub.run(crate::service::shutdown_signal()).await;
    let load = |c: &std::sync::atomic::AtomicU64| c.load(std::sync::atomic::Ordering::Relaxed);
    tracing::info!(
        frames_in = load(&stats.frames_in),
        frames_out = load(&stats.frames_out),
        clients_dropped = load(&stats.clients_dropped),
        bad_messages = load(&stats.bad_messages),
        "hub stopped"
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bitrate_is_validated() {
        let mut s = HubSettings {
            bitrate: Some(500),
            ..HubSettings::default()
        };
        assert!(s.clone().into_config().is_err());
        s.bitrate = Some(250_000);
        assert_eq!(s.into_config().unwrap().bitrate, Some(250_000));
    }
}
