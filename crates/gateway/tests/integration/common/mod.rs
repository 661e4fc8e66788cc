//! What the gateway's integration tests share: the scripted portal and the test PKI.

pub use testkit::constants::{SERNUM, SETUP_SHA1, WAIT};
pub use testkit::lift::RunningGateway as Running;
pub use testkit::pki::pki;
pub use testkit::scripted::*;

/// Run `gateway` until [`Running::stop`].
pub fn spawn(gateway: gateway::Gateway) -> Running {
    Running::spawn(gateway)
}
