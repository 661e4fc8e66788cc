//! The elevator gateway's side of a connection (NXg SW003 §5–§7): its [`Settings`] with the
//! owner's write [`Policy`], where it learns what objects are ([`Metadata`]), the elevation
//! [`Lockout`] all its connections share, how it builds answers, and the sans-IO [`Session`].

mod answer;
mod lockout;
mod metadata;
mod policy;
mod session;
mod settings;

use std::sync::{Arc, Mutex};

pub use lockout::{Failed, LevelState, Lockout, LockoutState, FIRST_LOCK};
pub use metadata::{bare, Lookup, Metadata, Target};
pub use policy::{Policy, RemoteWrites, Rule};
pub use session::{CloseReason, Job, JobId, JobResult, Output, Phase, Session};
pub use settings::{Identity, Settings};

/// What every connection of one gateway shares: where metadata comes from, and the elevation
/// lock-out (a reconnecting portal finds it where it left it).
#[derive(Clone)]
pub struct Context {
    /// Descriptions of the objects.
    pub metadata: Arc<dyn Metadata>,
    /// Wrong password hashes and locks, per level.
    pub lockout: Arc<Mutex<Lockout>>,
}

impl Context {
    /// A context over `metadata` with a fresh lock-out.
    pub fn new(metadata: Arc<dyn Metadata>) -> Context {
        Context {
            metadata,
            lockout: Arc::default(),
        }
    }
}
