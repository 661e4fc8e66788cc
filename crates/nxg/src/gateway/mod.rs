//! The elevator gateway's side of a connection (NXg SW003 §5–§7): its [`Settings`], where it
//! learns what objects are ([`Metadata`]), how it builds answers, and the sans-IO [`Session`].

mod answer;
mod metadata;
mod session;
mod settings;

pub use metadata::{bare, Lookup, Metadata, Target};
pub use session::{CloseReason, Job, JobId, JobResult, Output, Phase, Session};
pub use settings::{Identity, Settings};
