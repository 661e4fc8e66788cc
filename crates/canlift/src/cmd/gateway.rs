//! `canlift gateway --config FILE`: the elevator gateway (docs/GATEWAY.md).

use std::path::PathBuf;

use anyhow::Context;
use gateway::config::Config;
use gateway::Gateway;

/// Command-line arguments of `canlift gateway`.
#[derive(Debug, clap::Args)]
pub struct GatewayArgs {
    /// Configuration file (TOML: `[identity]`, `[cloud]`, `[state]`, `[bus]`, `[[networks]]`,
    /// `[privileges]`, `[limits]`, `[policy]`, `[metrics]`); default: /etc/canlift/gateway.toml
    /// when present.
    #[arg(long, env = "CANLIFT_CONFIG")]
    config: Option<PathBuf>,
    /// Print the effective configuration and exit.
    #[arg(long)]
    print_config: bool,
}

/// The sections that take `CANLIFT_<SECTION>_<KEY>` overrides.
const SECTIONS: [&str; 7] = [
    "identity",
    "cloud",
    "state",
    "bus",
    "privileges",
    "limits",
    "policy",
];

/// Run the gateway until Ctrl-C or SIGTERM.
pub async fn run(args: GatewayArgs) -> anyhow::Result<()> {
    let file = crate::config::or_installed(args.config, "gateway");
    let config: Config = crate::config::load_document(file.as_deref(), &SECTIONS)?;
    if args.print_config {
        print!("{}", toml::to_string_pretty(&config)?);
        return Ok(());
    }
    let gateway = Gateway::bus_node(config.clone())
        .await
        .context("starting the gateway")?;
    tracing::info!(
        portal = %config.cloud.url,
        bus = %config.bus.url,
        node = config.bus.node_id,
        lift_controller = config.bus.lift_controller,
        tls = tls::PROVIDER,
        "gateway running"
    );
    let reload = gateway.tls_reload();
    crate::service::on_hangup("the portal's CA and the client certificate", move || {
        reload.reload()
    });
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gateway.run(stopped));
    // On the bus and dialling: the portal may stay out of reach for hours, which systemd's
    // start timeout must not count (`canlift_gateway_connected` tells whether it is online).
    crate::service::notify(crate::service::State::Ready(&format!(
        "on {} as node {}",
        config.bus.url, config.bus.node_id
    )));
    crate::service::shutdown_signal().await;
    crate::service::notify(crate::service::State::Stopping);
    let _ = stop.send(true);
    let _ = task.await;
    Ok(())
}
