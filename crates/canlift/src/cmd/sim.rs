//! `canlift sim`: a simulated CiA 417 lift controller and I/O node on a bus (docs/SIMULATOR.md).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use canbus::CanId;
use lift417::catalog::Device;
use lift417::sim::{export_eds, SimConfig, Simulator};

/// Command-line arguments of `canlift sim`.
#[derive(Debug, clap::Args)]
pub struct SimArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// Node-ID of the lift controller.
    #[arg(long, default_value_t = 1)]
    node: u8,
    /// Node-ID of the I/O node with the hall and car buttons; 0 for none.
    #[arg(long, default_value_t = 12)]
    io_node: u8,
    /// Floors per lift (2–32 with an I/O node, 2–254 without).
    #[arg(long, default_value_t = 8)]
    floors: u8,
    /// Lifts the controller serves (1–8, at the CiA 417 offsets).
    #[arg(long, default_value_t = 1)]
    lifts: u8,
    /// Run simulated time this many times faster than the clock.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Heartbeat producer time (ms).
    #[arg(long, default_value_t = 1000)]
    heartbeat_ms: u16,
    /// Directory for stored parameters and counters (kept across restarts).
    #[arg(long)]
    state: Option<PathBuf>,
    /// Start lift 1 with faults or in a special operation: door-blocked, overload, drive,
    /// io-offline, fire-service, inspection (comma-separated; 0x5030 ends each).
    #[arg(long, value_delimiter = ',')]
    fault: Vec<FaultArg>,
    /// Wear a part: `door-closing=PERCENT` makes every lift's door close PERCENT % more slowly
    /// per simulated hour (0x4403 shows it) until its closing supervision calls it blocked.
    #[arg(long, value_name = "PART=PERCENT", value_parser = parse_wear)]
    wear: Vec<Wear>,
    /// Simulated passengers press a button about every this many simulated seconds.
    #[arg(long)]
    passengers: Option<f64>,
    /// Stay pre-operational until an NMT master starts the nodes.
    #[arg(long)]
    no_autostart: bool,
    /// A further SDO server channel of the controller, REQUEST:RESPONSE COB-IDs (e.g.
    /// 0x6A1:0x6C1; 1201h, 1202h, … in order): a gateway given the same channels reads the
    /// controller with as many transfers at once. Repeat for more.
    #[arg(long = "sdo-server", value_name = "REQUEST:RESPONSE", value_parser = parse_channel)]
    sdo_servers: Vec<(CanId, CanId)>,
    /// Write the controller's EDS to this file (and the I/O node's beside it) and exit.
    #[arg(long)]
    export_eds: Option<PathBuf>,
}

/// A part that wears, and how fast (% per simulated hour).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Wear {
    /// The car door closes more slowly.
    DoorClosing(f64),
}

/// `door-closing=PERCENT`.
fn parse_wear(text: &str) -> anyhow::Result<Wear> {
    let Some((part, percent)) = text.split_once('=') else {
        anyhow::bail!("{text:?} is not PART=PERCENT (e.g. door-closing=5)");
    };
    let percent: f64 = percent
        .trim()
        .parse()
        .ok()
        .filter(|p: &f64| p.is_finite() && (0.0..=10_000.0).contains(p))
        .with_context(|| format!("{percent:?}: a percentage per hour, 0 to 10000"))?;
    match part.trim() {
        "door-closing" => Ok(Wear::DoorClosing(percent)),
        other => anyhow::bail!("no part {other:?} wears here: door-closing"),
    }
}

/// A fault to start with.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum FaultArg {
    /// The light barrier stays interrupted.
    DoorBlocked,
    /// The car is overloaded.
    Overload,
    /// The drive has failed.
    Drive,
    /// The I/O node has lost its supply: silent until the fault is cleared (0x5030 bit 3).
    IoOffline,
    /// Fire service: the car is recalled to the lowest floor and takes no calls (0x5030 bit 4).
    FireService,
    /// Inspection operation: the car takes no calls (0x5030 bit 5).
    Inspection,
}

impl SimArgs {
    fn config(&self) -> anyhow::Result<SimConfig> {
        let faults = self.fault.iter().fold(0, |bits, f| {
            bits | match f {
                FaultArg::DoorBlocked => 1,
                FaultArg::Overload => 2,
                FaultArg::Drive => 4,
                FaultArg::IoOffline => lift417::sim::IO_OFFLINE,
                FaultArg::FireService => lift417::sim::FIRE_SERVICE,
                FaultArg::Inspection => lift417::sim::INSPECTION,
            }
        });
        let passengers = match self.passengers {
            Some(s) if s.is_finite() && s > 0.0 => Some(Duration::from_secs_f64(s)),
            Some(s) => anyhow::bail!("--passengers {s}: a positive number of seconds"),
            None => None,
        };
        let door_wear_percent_per_h = self
            .wear
            .iter()
            .map(|Wear::DoorClosing(p)| *p)
            .next_back()
            .unwrap_or(0.0);
        Ok(SimConfig {
            node_id: self.node,
            io_node: (self.io_node != 0).then_some(self.io_node),
            floors: self.floors,
            lifts: self.lifts,
            speed: self.speed,
            heartbeat_ms: self.heartbeat_ms,
            state_dir: self.state.clone(),
            faults,
            door_wear_percent_per_h,
            passengers,
            autostart: !self.no_autostart,
            sdo_servers: self.sdo_servers.clone(),
            ..SimConfig::default()
        })
    }
}

/// `0x6A1:0x6C1` as an SDO channel's (request, response) 11-bit COB-IDs.
fn parse_channel(text: &str) -> anyhow::Result<(CanId, CanId)> {
    let Some((request, response)) = text.split_once(':') else {
        anyhow::bail!("{text:?} is not REQUEST:RESPONSE (e.g. 0x6A1:0x6C1)");
    };
    let id = |what, text| -> anyhow::Result<CanId> {
        Ok(CanId::standard(super::parse_number(what, text)?)?)
    };
    Ok((
        id("request COB-ID", request)?,
        id("response COB-ID", response)?,
    ))
}

impl SimArgs {
    /// Whether the run writes the EDS files and ends (a tool), rather than simulating (a daemon).
    pub fn exports(&self) -> bool {
        self.export_eds.is_some()
    }
}

/// Run `canlift sim` until Ctrl-C or SIGTERM.
pub async fn run(args: SimArgs) -> anyhow::Result<()> {
    let config = args.config()?;
    if let Some(path) = &args.export_eds {
        let text = export_eds(&config, Device::Controller)?;
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
        println!("{}", path.display());
        if let Some(io) = config.io_node {
            let io_path = path.with_file_name(format!("io-node-{io}.eds"));
            std::fs::write(&io_path, export_eds(&config, Device::Io)?)
                .with_context(|| format!("writing {}", io_path.display()))?;
            println!("{}", io_path.display());
        }
        return Ok(());
    }
    if let Some(dir) = &config.state_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let sim = Simulator::start(&args.bus.url, config.clone())
        .await
        .with_context(|| format!("starting the simulator on {}", args.bus.url))?;
    tracing::info!(
        bus = %args.bus.url,
        node = config.node_id,
        io_node = ?config.io_node,
        floors = config.floors,
        lifts = config.lifts,
        speed = config.speed,
        "simulated lift running; call the car with: canlift sdo write {} 0x5022 0 u32 FLOOR",
        config.node_id
    );
    crate::service::shutdown_signal().await;
    sim.stop().await;
    tracing::info!("simulated lift stopped, counters stored");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sdo_server_channels_are_request_colon_response() {
        let id = CanId::Standard;
        assert_eq!(
            parse_channel("0x6A1:0x6C1").unwrap(),
            (id(0x6A1), id(0x6C1))
        );
        assert_eq!(parse_channel("1697:1729").unwrap(), (id(0x6A1), id(0x6C1)));
        for bad in ["0x6A1", "0x6A1:", "0x800:0x6C1", "x:0x6C1", "0x6A1:0x6C1:1"] {
            assert!(parse_channel(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn wear_is_a_part_and_a_percentage_per_hour() {
        assert_eq!(
            parse_wear("door-closing=12.5").unwrap(),
            Wear::DoorClosing(12.5)
        );
        for bad in [
            "door-closing",
            "door-closing=-1",
            "door-closing=x",
            "brake=5",
            "door-closing=1e9",
        ] {
            assert!(parse_wear(bad).is_err(), "{bad}");
        }
    }
}
