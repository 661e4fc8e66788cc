//! `canlift demo`: everything in one process (docs/ARCHITECTURE.md §Conventions): the hub, the simulated lift
//! controller and I/O node, the gateway in bus-node mode and the portal with a development CA and
//! SQLite. The first run generates the CA, an account and the gateway's configuration into the
//! state directory; later runs reuse them, so the lift's counters keep counting.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use canbus::hub::{Hub, HubConfig};
use cloud::server::Portal;
use cloud_store::Store;
use gateway::config::{NodeSection, SdoChannel};
use lift417::catalog::Device;
use lift417::sim::{export_eds, SimConfig, Simulator};

/// How a user runs this binary from a shell: `canlift` when that name on the `PATH` is this
/// binary, else its path (after `cargo run`, `target/release/canlift`).
fn command_name() -> String {
    let Ok(exe) = std::env::current_exe().and_then(std::fs::canonicalize) else {
        return "canlift".into();
    };
    let on_path = std::env::var_os("PATH").is_some_and(|path| {
        std::env::split_paths(&path)
            .any(|dir| std::fs::canonicalize(dir.join("canlift")).is_ok_and(|found| found == exe))
    });
    if on_path {
        return "canlift".into();
    }
    let shown = std::env::current_dir()
        .ok()
        .and_then(|cwd| exe.strip_prefix(cwd).ok().map(|p| p.to_path_buf()))
        .unwrap_or_else(|| exe.clone());
    let shown = shown.display().to_string();
    if shown.contains(' ') {
        format!("'{shown}'")
    } else {
        shown
    }
}

/// Command-line arguments of `canlift demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// State directory [default: $XDG_DATA_HOME/canlift/demo or ~/.local/share/canlift/demo].
    #[arg(long)]
    state: Option<PathBuf>,
    /// Simulated time runs this many times faster.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Where the hub listens.
    #[arg(long, default_value = "127.0.0.1:29536")]
    hub_listen: SocketAddr,
    /// Where the portal listens.
    #[arg(long, default_value = "127.0.0.1:8443")]
    portal_listen: SocketAddr,
    /// Simulated passengers press a button about every this many simulated seconds (0: never).
    #[arg(long, default_value_t = 45.0)]
    passengers: f64,
}

/// The demo's account.
const ACCOUNT: &str = "demo";
const SERNUM: &str = "DEMO-0001";
/// The simulated controller's further SDO channels (1201h, 1202h), the gateway's to use.
const DEMO_SDO_CHANNELS: [SdoChannel; 2] = [
    SdoChannel {
        request: 0x6A1,
        response: 0x6C1,
    },
    SdoChannel {
        request: 0x6A2,
        response: 0x6C2,
    },
];

fn default_state() -> PathBuf {
    let data = std::env::var_os("XDG_DATA_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/share")))
        .unwrap_or_else(|| PathBuf::from("."));
    data.join("canlift/demo")
}

/// The account's API key and domain token: created on the first run (the domain token a
/// random one, as `canlift cloud account add` makes it) and kept in the state directory,
/// readable by its owner alone (a demo convenience; a real portal shows the key once and
/// keeps only its digest).
async fn account(store: &Store, dir: &Path) -> anyhow::Result<(String, String)> {
    let path = dir.join("api-key");
    if let (Ok(key), Some(account)) = (
        std::fs::read_to_string(&path),
        store.account(ACCOUNT).await?,
    ) {
        return Ok((key.trim().to_owned(), account.domain));
    }
    let domain = cloud_store::secret("").to_uppercase();
    let key = store
        .add_account(ACCOUNT, &domain)
        .await
        .context("creating the demo account")?;
    canopen::storage::write_private_atomically(&path, &format!("{key}\n"))?;
    Ok((key, domain))
}

/// The lift's service and setup passwords: made on the first run and kept in the state
/// directory, so that the banner can print them and elevation works in the demo.
fn lift_passwords(dir: &Path) -> anyhow::Result<(String, String)> {
    let path = dir.join("lift-passwords");
    if let Ok(text) = std::fs::read_to_string(&path) {
        if let Some((service, setup)) = text.trim().split_once('\n') {
            return Ok((service.trim().to_owned(), setup.trim().to_owned()));
        }
    }
    let (service, setup) = (cloud_store::secret("svc-"), cloud_store::secret("set-"));
    let (service, setup) = (service[..12].to_owned(), setup[..12].to_owned());
    canopen::storage::write_private_atomically(&path, &format!("{service}\n{setup}\n"))?;
    Ok((service, setup))
}

/// Run the demo until Ctrl-C or SIGTERM.
pub async fn run(args: DemoArgs) -> anyhow::Result<()> {
    let dir = args.state.clone().unwrap_or_else(default_state);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let dir = dir.canonicalize()?;
    // The bus.
    let hub = Hub::bind(HubConfig {
        listen: args.hub_listen,
        ..HubConfig::default()
    })
    .await
    .with_context(|| {
        format!(
            "the hub cannot listen on {} (is a demo running?)",
            args.hub_listen
        )
    })?
    .spawn()?;
    let bus = format!("socketcand://{}/can0", hub.local_addr());
    // The portal.
    let mut portal_config = cloud::config::Config::default();
    portal_config.server.listen = args.portal_listen;
    portal_config.state.dir = dir.join("portal");
    let portal = Portal::bind(&portal_config, lift417::catalog::Catalog::builtin().names())
        .await
        .with_context(|| format!("starting the portal on {}", args.portal_listen))?;
    let portal_addr = portal.local_addr();
    let store = Store::open(&portal_config.database_url()).await?;
    let (key, domain) = account(&store, &dir).await?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let portal_task = tokio::spawn(portal.run(stopped.clone()));
    // The lift.
    let sim_config = SimConfig {
        speed: args.speed,
        state_dir: Some(dir.join("lift")),
        passengers: (args.passengers > 0.0).then(|| Duration::from_secs_f64(args.passengers)),
        sdo_servers: DEMO_SDO_CHANNELS.iter().map(SdoChannel::ids).collect(),
        ..SimConfig::default()
    };
    let sim = Simulator::start(&bus, sim_config.clone())
        .await
        .context("starting the simulated lift")?;
    // The gateway, with a configuration a user can reuse for `canlift gateway`.
    let ca = portal_config.state.dir.join("dev-ca.pem");
    let identity = nxg::gateway::Identity {
        sernum: SERNUM.into(),
        vendorid: 1050,
        productcode: 4096,
        liftnum: "demo lift".into(),
        hardware: "canlift demo".into(),
        domaintoken: domain.clone(),
        ..Default::default()
    };
    let portal_ws = format!("wss://localhost:{}/ws", portal_addr.port());
    let mut gw =
        gateway::config::Config::for_portal(identity, &portal_ws, &ca, &bus, &dir.join("gateway"));
    let (service, setup) = lift_passwords(&dir)?;
    gw.privileges.service_sha1 = Some(cloud_store::passhash(&service));
    gw.privileges.setup_sha1 = Some(cloud_store::passhash(&setup));
    // The gateway reads the controller on SDO channels of its own, two transfers at once, and
    // leaves the default channel to the user's tools (`canlift sdo`, python-canopen) on the
    // same bus: one client per channel (docs/GATEWAY.md §Behaviour).
    gw.bus.nodes.push(NodeSection {
        sdo_channels: DEMO_SDO_CHANNELS.to_vec(),
        ..NodeSection::new(sim_config.node_id)
    });
    // The I/O node described by its EDS, as an integrator would (docs/GATEWAY.md §Metadata).
    if let Some(id) = sim_config.io_node {
        let eds = dir.join(format!("io-node-{id}.eds"));
        std::fs::write(&eds, export_eds(&sim_config, Device::Io)?)
            .with_context(|| format!("writing {}", eds.display()))?;
        gw.bus.nodes.push(NodeSection::with_eds(id, eds));
    }
    let gateway_toml = dir.join("gateway.toml");
    std::fs::write(&gateway_toml, toml::to_string_pretty(&gw)?)?;
    let gateway = gateway::Gateway::bus_node(gw)
        .await
        .context("starting the gateway")?;
    let gateway_task = tokio::spawn(gateway.run(stopped));

    let lift = format!("1050-4096-{SERNUM}");
    let portal_url = format!("https://localhost:{}", portal_addr.port());
    println!(
        "canlift demo is running (Ctrl-C stops it); state in {}",
        dir.display()
    );
    println!(
        "  portal   {portal_url}  (web UI: sign in with the API key; operator API under /api/v1)"
    );
    println!("  API key  {key}");
    println!("  service password  {service}  (the lift's; elevation on the lift page)");
    println!("  setup password    {setup}");
    println!(
        "  CA       {}  (trust it to reach the portal)",
        ca.display()
    );
    println!(
        "  bus      {bus}  (python-can: interface=socketcand, host={}, port={}, channel=can0)",
        hub.local_addr().ip(),
        hub.local_addr().port()
    );
    println!(
        "  lift     {lift}  (gateway configuration: {})",
        gateway_toml.display()
    );
    println!("try:");
    println!(
        "  export CANLIFT_PORTAL={portal_url} CANLIFT_API_KEY={key} CANLIFT_CA={}",
        ca.display()
    );
    let canlift = command_name();
    println!("  {canlift} get {lift} \"Trip counter\"");
    println!("  {canlift} watch {lift} 0x652001 0x638301");
    println!("  {canlift} put {lift} 0x502200 4");
    println!("  {canlift} alarms        (set 5030h on the lift page with the setup password to make faults)");
    crate::service::shutdown_signal().await;
    let _ = stop.send(true);
    let _ = gateway_task.await;
    sim.stop().await;
    let _ = portal_task.await;
    hub.shutdown().await;
    println!("canlift demo stopped");
    Ok(())
}
