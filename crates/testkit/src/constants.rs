//! The lift every test talks about: the identity of the specification's CONNECT sample, its
//! account and passwords.

/// Serial number (NXg SW003 §5.2.1 sample).
pub const SERNUM: &str = "180917010200000102";
/// CiA vendor-ID of the sample.
pub const VENDORID: u32 = 1050;
/// Product code of the sample.
pub const PRODUCTCODE: u32 = 4096;
/// The owner's lift number of the sample.
pub const LIFTNUM: &str = "40/7289/20399-126";
/// The domain token of the sample: the account the lift belongs to.
pub const DOMAIN: &str = "MAS";
/// The name of the account of [`DOMAIN`] at the test portals.
pub const ACCOUNT: &str = "masora";
/// The lift's id at the portal: `VENDORID-PRODUCTCODE-SERNUM`.
pub const LIFT: &str = "1050-4096-180917010200000102";
/// The service password the test gateways accept.
pub const SERVICE_PASSWORD: &str = "service";
/// SHA-1 of [`SERVICE_PASSWORD`] (what the gateway keeps).
pub const SERVICE_SHA1: &str = "4cf5bc59bee9e1c44c6254b5f84e7f066bd8e5fe";
/// The setup password.
pub const SETUP_PASSWORD: &str = "setup";
/// SHA-1 of [`SETUP_PASSWORD`].
pub const SETUP_SHA1: &str = "80437a44a661d141174209119d54125a59a64b2a";
/// How long a test waits for something that should happen at once.
pub const WAIT: std::time::Duration = std::time::Duration::from_secs(10);
/// The `[server] metrics_token` of the test portals (`/metrics` on their public port).
pub const METRICS_TOKEN: &str = "metrics-of-the-test-portal";
