//! `canlift loadgen`: many elevator gateways against one portal, for load tests and the
//! portal's benchmarks (docs/PORTAL.md §Load generator): the real gateway in embedded mode,
//! many times over ([`gateway::fleet`]).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use gateway::fleet::{Fleet, FleetOptions};

/// Arguments of `canlift loadgen`.
#[derive(Debug, Clone, clap::Args)]
pub struct LoadgenArgs {
    /// The portal's gateway endpoint.
    #[arg(long, default_value = "wss://localhost:8443/ws")]
    pub portal: String,
    /// PEM CA certificate the gateways trust (the portal's dev-ca.pem).
    #[arg(long)]
    pub ca: PathBuf,
    /// Domain token of the portal account the gateways belong to.
    #[arg(long)]
    pub domain: String,
    /// Gateways to run.
    #[arg(long, default_value_t = 1000)]
    pub gateways: usize,
    /// Number of the first gateway: serial numbers are LOAD-NNNNNN from here on.
    #[arg(long, default_value_t = 1)]
    pub first: usize,
    /// Loopback source addresses to spread the connections over (127.0.0.1…127.0.0.N).
    #[arg(long, default_value_t = 8)]
    pub sources: u8,
    /// Gateways started per second (0: all at once).
    #[arg(long, default_value_t = 0)]
    pub rate: u32,
    /// Change the simulated lift's values this often (ms) so that every gateway pushes what
    /// the portal subscribed; 0: the gateways stay idle.
    #[arg(long, default_value_t = 0)]
    pub change_ms: u64,
    /// Directory for the gateways' cloud tokens (reuse it and they reconnect as known lifts).
    #[arg(long, default_value = "loadgen-state")]
    pub state: PathBuf,
    /// Exit once all are online, after printing how long it took.
    #[arg(long)]
    pub until_online: bool,
}

impl LoadgenArgs {
    /// The fleet these arguments describe.
    pub fn fleet(&self) -> FleetOptions {
        FleetOptions {
            portal: self.portal.clone(),
            ca: self.ca.clone(),
            domain: self.domain.clone(),
            gateways: self.gateways,
            first: self.first,
            sources: self.sources,
            rate: self.rate,
            state: self.state.clone(),
        }
    }
}

/// `canlift loadgen`.
pub async fn run(args: LoadgenArgs) -> anyhow::Result<()> {
    let begin = Instant::now();
    let fleet = Fleet::start(&args.fleet(), None).await?;
    println!(
        "{} gateways made in {:.1} s and started in {:.1} s; waiting for CONNACK",
        args.gateways,
        fleet.launched().duration_since(begin).as_secs_f64(),
        fleet.launched().elapsed().as_secs_f64()
    );
    let mut report = tokio::time::interval(Duration::from_secs(1));
    let mut change = tokio::time::interval(Duration::from_millis(args.change_ms.max(1)));
    let mut step = 0u32;
    let shutdown = crate::service::shutdown_signal();
    tokio::pin!(shutdown);
    {
        let all_online = fleet.all_online(fleet.launched(), Duration::from_secs(24 * 3600));
        tokio::pin!(all_online);
        let mut all = false;
        loop {
            tokio::select! {
                took = &mut all_online, if !all => {
                    all = true;
                    match took {
                        Ok(t) => println!("all {} online after {:.2} s", args.gateways, t.as_secs_f64()),
                        Err(e) => println!("{e}"),
                    }
                    if args.until_online {
                        break;
                    }
                }
                _ = report.tick(), if !all => {
                    println!("{} online after {:.0} s", fleet.online(), fleet.launched().elapsed().as_secs_f64());
                }
                _ = change.tick(), if args.change_ms > 0 => {
                    step = step.wrapping_add(1);
                    fleet.change(step);
                }
                _ = &mut shutdown => break,
            }
        }
    }
    fleet.stop().await;
    Ok(())
}
