//! The simulated lift (controller and I/O node on an in-process bus) with the real gateway in
//! front of it, connecting to a portal.

use std::path::Path;

use gateway::config::{Config, NodeSection};
use gateway::Gateway;
use lift417::catalog::Device;
use lift417::sim::{SimConfig, Simulator};
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::constants::*;

/// The sample identity (NXg §5.2.1) as the gateway's `[identity]`.
pub fn identity() -> nxg::gateway::Identity {
    nxg::gateway::Identity {
        sernum: SERNUM.into(),
        vendorid: VENDORID,
        productcode: PRODUCTCODE,
        liftnum: LIFTNUM.into(),
        hardware: "Thor @ NX-T2".into(),
        software: "01.23.10".into(),
        boardhash: "2354A687AF6DC79B203E754E8E426A87FE188A62983B7AC48F9D5E195B728112".into(),
        domaintoken: DOMAIN.into(),
        api: 1,
    }
}

/// A gateway configuration for the portal at `portal` (`wss://…/ws`) trusting `ca`, on `bus`,
/// with its state in `state`: the sample identity, both passwords, a short SDO timeout, fast
/// polling, and the simulated I/O node described by the EDS the simulator exports (written
/// into `state`).
pub fn gateway_config(portal: &str, ca: &Path, bus: &str, state: &Path) -> Config {
    let mut c = Config::for_portal(identity(), portal, ca, bus, state);
    c.bus.sdo_timeout_ms = 300;
    c.bus.poll_ms = 100;
    c.privileges.service_sha1 = Some(SERVICE_SHA1.into());
    c.privileges.setup_sha1 = Some(SETUP_SHA1.into());
    let sim = SimConfig::default();
    if let Some(id) = sim.io_node {
        let eds = state.join(format!("io-node-{id}.eds"));
        let text = lift417::sim::export_eds(&sim, Device::Io).expect("the I/O node's EDS");
        std::fs::create_dir_all(state).expect("the state directory");
        std::fs::write(&eds, text).expect("the I/O node's EDS is written");
        c.bus.nodes.push(NodeSection::with_eds(id, eds));
    }
    c
}

/// A gateway running in a task until [`RunningGateway::stop`].
pub struct RunningGateway {
    stop: watch::Sender<bool>,
    task: JoinHandle<()>,
}

impl RunningGateway {
    /// Run `gateway`.
    pub fn spawn(gateway: Gateway) -> RunningGateway {
        let (stop, stopped) = watch::channel(false);
        RunningGateway {
            stop,
            task: tokio::spawn(gateway.run(stopped)),
        }
    }

    /// Stop it and wait until it has.
    pub async fn stop(self) {
        let _ = self.stop.send(true);
        tokio::time::timeout(WAIT, self.task)
            .await
            .expect("the gateway stops")
            .expect("the gateway task ends cleanly");
    }
}

/// The simulator's configuration in tests: 20 × speed, so tests see movement quickly.
pub fn sim_config() -> SimConfig {
    SimConfig {
        speed: 20.0,
        ..SimConfig::default()
    }
}

/// The simulator on `bus` with [`sim_config`].
pub async fn simulator(bus: &str) -> Simulator {
    Simulator::start(bus, sim_config())
        .await
        .expect("the simulator starts")
}

/// The simulated lift and its gateway.
pub struct Lift {
    /// The simulator.
    pub sim: Simulator,
    /// The gateway (absent once stopped).
    pub gateway: Option<RunningGateway>,
}

impl Lift {
    /// The simulator on `bus` with `sim` and a gateway in bus-node mode with `config`.
    pub async fn start(bus: &str, sim: SimConfig, config: Config) -> Lift {
        let sim = Simulator::start(bus, sim)
            .await
            .expect("the simulator starts");
        let gateway = Gateway::bus_node(config).await.expect("the gateway starts");
        Lift {
            sim,
            gateway: Some(RunningGateway::spawn(gateway)),
        }
    }

    /// Start a gateway with `config` in front of the simulator (after [`Lift::stop_gateway`]).
    pub async fn start_gateway(&mut self, config: Config) {
        self.stop_gateway().await;
        let gateway = Gateway::bus_node(config).await.expect("the gateway starts");
        self.gateway = Some(RunningGateway::spawn(gateway));
    }

    /// Stop the gateway (the lift goes offline).
    pub async fn stop_gateway(&mut self) {
        if let Some(g) = self.gateway.take() {
            g.stop().await;
        }
    }

    /// Stop both.
    pub async fn stop(mut self) {
        self.stop_gateway().await;
        self.sim.stop().await;
    }
}
