//! `canlift`: the NXg CANopen-Lift Connector and the CANopen stack beneath it, in one binary.

mod cmd;
mod config;
mod logging;
mod service;

use clap::{CommandFactory, Parser, Subcommand};

/// canlift — CANopen-Lift (CiA 417) to cloud, and the tools around it.
#[derive(Debug, Parser)]
#[command(name = "canlift", version, about, long_about = None)]
struct Cli {
    /// Log format on stderr (level from RUST_LOG; default info, warn for loadgen).
    #[arg(
        long,
        value_enum,
        global = true,
        default_value = "text",
        env = "CANLIFT_LOG_FORMAT"
    )]
    log_format: logging::LogFormat,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    #[cfg(feature = "portal")]
    /// Everything in one process: hub, simulated lift, gateway and portal.
    Demo(cmd::demo::DemoArgs),
    /// Virtual CAN bus server speaking socketcand's raw mode (python-can and canlift can join).
    Hub(cmd::hub::HubArgs),
    /// Print frames from a bus like candump, with their CANopen meaning.
    Dump(cmd::dump::DumpArgs),
    /// Send an NMT command (start, stop, preop, reset, reset-comm) to a node or all.
    Nmt(cmd::nmt::NmtArgs),
    /// Read or write an object of a node by SDO.
    Sdo(cmd::sdo::SdoArgs),
    /// CiA 309-3 ASCII gateway: `[1] 4 read 0x1017 0 u16` over TCP or standard input.
    Ascii(cmd::ascii::AsciiArgs),
    /// Which nodes are on the bus: heartbeats (and with --probe SDO reads), with identities.
    Scan(cmd::scan::ScanArgs),
    /// Layer setting services (CiA 305): node-IDs and bit rates, Fastscan.
    Lss(cmd::lss::LssArgs),
    /// Another node's PDOs over SDO: show them, or configure one (CiA 301 mapping procedure).
    Pdo(cmd::pdo::PdoArgs),
    /// A node's configuration as a DCF: apply one (identity checked), or read one.
    Dcf(cmd::dcf::DcfArgs),
    /// EDS and DCF files (CiA 306): `check` lists every defect with file, line and severity.
    Eds(cmd::eds::EdsArgs),
    /// Produce SYNC at a period (with the counter if asked).
    Sync(cmd::sync::SyncArgs),
    /// Send the TIME object: the system's time or a given one.
    Time(cmd::time::TimeArgs),
    /// Send an EMCY as a node, or watch EMCYs with their meaning.
    Emcy(cmd::emcy::EmcyArgs),
    /// The elevator gateway: connects the lift to a cloud portal (NXg connector).
    Gateway(cmd::gateway::GatewayArgs),
    #[cfg(feature = "portal")]
    /// The cloud portal: gateways on /ws, the operator REST API (`account add` makes API keys).
    Cloud(cmd::cloud::CloudArgs),
    #[cfg(feature = "portal")]
    /// The account's lifts on the portal.
    Lifts(cmd::operator::LiftsArgs),
    #[cfg(feature = "portal")]
    /// Read an object of a lift through the portal.
    Get(cmd::operator::GetArgs),
    #[cfg(feature = "portal")]
    /// Write an object of a lift through the portal.
    Put(cmd::operator::PutArgs),
    #[cfg(feature = "portal")]
    /// Ask a lift for service or setup rights (the password from CANLIFT_LIFT_PASSWORD or stdin).
    Elevate(cmd::operator::ElevateArgs),
    #[cfg(feature = "portal")]
    /// Print the values a lift pushes for some objects.
    Watch(cmd::operator::WatchArgs),
    #[cfg(feature = "portal")]
    /// A lift's cloud token on the portal: rotate it now, or reset it for a new gateway.
    Token(cmd::operator::TokenArgs),
    #[cfg(feature = "portal")]
    /// The account's alarms on the portal (`alarms ack ID` takes one on).
    Alarms(cmd::alarms::AlarmsArgs),
    #[cfg(feature = "portal")]
    /// A lift's stored bus events (EMCY, node states, network states).
    Events(cmd::alarms::EventsArgs),
    /// Simulated CiA 417 lift controller (and I/O node) on a bus.
    Sim(cmd::sim::SimArgs),
    /// Many gateways (the real gateway code, embedded mode) against one portal, for load tests.
    Loadgen(cmd::loadgen::LoadgenArgs),
    /// Shell completions on standard output (`canlift completions bash`).
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
    /// Write the manual pages (canlift.1 and one per subcommand) into a directory.
    #[command(hide = true)]
    Manpages {
        /// An existing directory.
        dir: std::path::PathBuf,
    },
}

impl Command {
    /// The service a log line names (the subcommand).
    fn service(&self) -> &'static str {
        match self {
            #[cfg(feature = "portal")]
            Command::Demo(_) => "demo",
            Command::Hub(_) => "hub",
            Command::Dump(_) => "dump",
            Command::Nmt(_) => "nmt",
            Command::Sdo(_) => "sdo",
            Command::Ascii(_) => "ascii",
            Command::Scan(_) => "scan",
            Command::Lss(_) => "lss",
            Command::Pdo(_) => "pdo",
            Command::Dcf(_) => "dcf",
            Command::Eds(_) => "eds",
            Command::Sync(_) => "sync",
            Command::Time(_) => "time",
            Command::Emcy(_) => "emcy",
            Command::Gateway(_) => "gateway",
            #[cfg(feature = "portal")]
            Command::Cloud(_) => "cloud",
            #[cfg(feature = "portal")]
            Command::Lifts(_) => "lifts",
            #[cfg(feature = "portal")]
            Command::Get(_) => "get",
            #[cfg(feature = "portal")]
            Command::Put(_) => "put",
            #[cfg(feature = "portal")]
            Command::Elevate(_) => "elevate",
            #[cfg(feature = "portal")]
            Command::Watch(_) => "watch",
            #[cfg(feature = "portal")]
            Command::Token(_) => "token",
            #[cfg(feature = "portal")]
            Command::Alarms(_) => "alarms",
            #[cfg(feature = "portal")]
            Command::Events(_) => "events",
            Command::Sim(_) => "sim",
            Command::Loadgen(_) => "loadgen",
            Command::Completions { .. } => "completions",
            Command::Manpages { .. } => "manpages",
        }
    }
}

impl Command {
    /// Whether the command prints and ends (or prints until stopped) rather than serving: such a
    /// command ends quietly when its reader goes away (`canlift dump … | head`), as `cat` does.
    /// The daemons keep SIGPIPE ignored: their sockets never raise it (writes use MSG_NOSIGNAL),
    /// and a log reader that went away must not stop a portal or a gateway.
    fn prints(&self) -> bool {
        match self {
            Command::Dump(_)
            | Command::Nmt(_)
            | Command::Sdo(_)
            | Command::Scan(_)
            | Command::Lss(_)
            | Command::Pdo(_)
            | Command::Dcf(_)
            | Command::Eds(_)
            | Command::Sync(_)
            | Command::Time(_)
            | Command::Emcy(_)
            | Command::Completions { .. }
            | Command::Manpages { .. } => true,
            #[cfg(feature = "portal")]
            Command::Lifts(_)
            | Command::Get(_)
            | Command::Put(_)
            | Command::Elevate(_)
            | Command::Watch(_)
            | Command::Token(_)
            | Command::Alarms(_)
            | Command::Events(_) => true,
            Command::Sim(args) => args.exports(),
            _ => false,
        }
    }
}

/// SIGPIPE back to its default (the Rust runtime ignores it, so a write to a closed pipe is an
/// error `println!` panics on — exit 101 and a panic message for `| head`).
#[cfg(unix)]
fn end_quietly_on_a_closed_pipe() {
    // SAFETY: setting a signal's disposition to the default, before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    #[cfg(unix)]
    if cli.command.prints() {
        end_quietly_on_a_closed_pipe();
    }
    // Made from the command-line definition alone: no logging, no runtime.
    let manual = match &cli.command {
        Command::Completions { shell } => Some(cmd::manual::completions(*shell, Cli::command())),
        Command::Manpages { dir } => Some(cmd::manual::pages(Cli::command(), dir)),
        _ => None,
    };
    match manual {
        Some(Ok(())) => return std::process::ExitCode::SUCCESS,
        Some(Err(e)) => {
            eprintln!("canlift: {e:#}");
            return std::process::ExitCode::FAILURE;
        }
        None => {}
    }
    // Thousands of gateways in one process would log every connection: quieter by default.
    let level = match cli.command {
        Command::Loadgen(_) => "warn",
        _ => "info",
    };
    logging::init(cli.log_format, cli.command.service(), level);
    // A gateway serves one connection: one worker thread is enough, and on a device each
    // further thread costs its stack and an allocator arena (docs/BENCHMARKS.md §Elevator
    // gateway). `TOKIO_WORKER_THREADS` still decides where it is set. Everything else (portal,
    // hub, simulator, load generator) gets a worker per core.
    let mut runtime = tokio::runtime::Builder::new_multi_thread();
    runtime.enable_all();
    if matches!(cli.command, Command::Gateway(_))
        && std::env::var_os("TOKIO_WORKER_THREADS").is_none()
    {
        runtime.worker_threads(1);
    }
    let runtime = match runtime.build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("canlift: cannot start the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let result = runtime.block_on(async {
        match cli.command {
            #[cfg(feature = "portal")]
            Command::Demo(args) => cmd::demo::run(args).await,
            Command::Hub(args) => cmd::hub::run(args).await,
            Command::Dump(args) => cmd::dump::run(args).await,
            Command::Nmt(args) => cmd::nmt::run(args).await,
            Command::Sdo(args) => cmd::sdo::run(args).await,
            Command::Ascii(args) => cmd::ascii::run(args).await,
            Command::Scan(args) => cmd::scan::run(args).await,
            Command::Lss(args) => cmd::lss::run(args).await,
            Command::Pdo(args) => cmd::pdo::run(args).await,
            Command::Dcf(args) => cmd::dcf::run(args).await,
            Command::Eds(args) => cmd::eds::run(args),
            Command::Sync(args) => cmd::sync::run(args).await,
            Command::Time(args) => cmd::time::run(args).await,
            Command::Emcy(args) => cmd::emcy::run(args).await,
            Command::Loadgen(args) => cmd::loadgen::run(args).await,
            Command::Sim(args) => cmd::sim::run(args).await,
            Command::Gateway(args) => cmd::gateway::run(args).await,
            Command::Completions { .. } | Command::Manpages { .. } => Ok(()),
            #[cfg(feature = "portal")]
            Command::Cloud(args) => cmd::cloud::run(args).await,
            #[cfg(feature = "portal")]
            Command::Lifts(args) => cmd::operator::lifts(args).await,
            #[cfg(feature = "portal")]
            Command::Get(args) => cmd::operator::get(args).await,
            #[cfg(feature = "portal")]
            Command::Put(args) => cmd::operator::put(args).await,
            #[cfg(feature = "portal")]
            Command::Elevate(args) => cmd::operator::elevate(args).await,
            #[cfg(feature = "portal")]
            Command::Watch(args) => cmd::operator::watch(args).await,
            #[cfg(feature = "portal")]
            Command::Token(args) => cmd::operator::token(args).await,
            #[cfg(feature = "portal")]
            Command::Alarms(args) => cmd::alarms::alarms(args).await,
            #[cfg(feature = "portal")]
            Command::Events(args) => cmd::alarms::events(args).await,
        }
    });
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("canlift: {e:#}");
            #[cfg(feature = "portal")]
            return cmd::exit::status(&e);
            #[cfg(not(feature = "portal"))]
            std::process::ExitCode::FAILURE
        }
    }
}
