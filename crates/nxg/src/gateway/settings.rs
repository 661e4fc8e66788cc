//! What a gateway session is configured with: who the gateway is (the `[identity]` section of
//! its configuration, sent in CONNECT), its passwords, limits and timers.

use std::time::Duration;

use crate::msg;

/// What the gateway says about itself in CONNECT (NXg SW003 §5.2.1); also the `[identity]`
/// section of the gateway's configuration.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Identity {
    /// Serial number (unique per vendor).
    pub sernum: String,
    /// CiA vendor-ID.
    pub vendorid: u32,
    /// Product code.
    pub productcode: u32,
    /// Lift number as the owner knows it.
    pub liftnum: String,
    /// Hardware description.
    pub hardware: String,
    /// Software version.
    pub software: String,
    /// Hash identifying the board.
    pub boardhash: String,
    /// Which account the unit belongs to.
    pub domaintoken: String,
    /// Highest NXg API version offered (NXg §5.2.1): [`crate::msg::API`] unless set otherwise.
    pub api: u32,
}

impl Default for Identity {
    fn default() -> Self {
        Identity {
            sernum: String::new(),
            vendorid: 0,
            productcode: 0,
            liftnum: String::new(),
            hardware: String::new(),
            software: format!("canlift {}", env!("CARGO_PKG_VERSION")),
            boardhash: String::new(),
            domaintoken: String::new(),
            api: crate::msg::API,
        }
    }
}

impl Identity {
    /// CONNECT's parameters, with the stored cloud token if there is one.
    pub fn connect(&self, cloudtoken: Option<String>) -> msg::Connect {
        msg::Connect {
            identity: msg::Identity {
                sernum: self.sernum.clone(),
                vendorid: self.vendorid,
                productcode: self.productcode,
                liftnum: self.liftnum.clone(),
                hardware: self.hardware.clone(),
                software: self.software.clone(),
                api: self.api.max(1),
                boardhash: self.boardhash.clone(),
                cloudtoken,
            },
            domaintoken: self.domaintoken.clone(),
        }
    }
}

/// The settings of a session.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Who we are.
    pub identity: Identity,
    /// SHA-1 (hex) of the service password; `None`: service rights cannot be granted.
    pub service_sha1: Option<String>,
    /// SHA-1 (hex) of the setup password.
    pub setup_sha1: Option<String>,
    /// How long an elevation lasts.
    pub privilege_duration: Duration,
    /// Requests that may wait for the bus at once.
    pub max_in_flight: usize,
    /// Requests that may queue behind them before new ones are refused as busy.
    pub max_queued: usize,
    /// Subscriptions at most.
    pub max_subscriptions: usize,
    /// The portal's heartbeat interval: silence for 2 × this + 30 s ends the connection.
    pub heartbeat: Duration,
    /// How long to wait for CONNACK after CONNECT.
    pub connack_timeout: Duration,
    /// Node-ID of the lift controller on net 1 (requests without `node`).
    pub lift_controller: u8,
    /// The CAN networks configured (1 is the bus of `[bus]`).
    pub nets: Vec<u8>,
    /// What the owner lets the cloud write and see.
    pub policy: super::Policy,
}
