//! Running the session's dictionary accesses: by SDO on a CAN network (bus-node mode) or on the
//! controller's own dictionary (embedded mode).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, PoisonError};

use canopen::od::SharedDictionary;
use canopen::sdo::abort::AbortCode;
use canopen::sdo::clients::SdoClients;
use nxg::gateway::{Job, JobResult, Policy, Target};
use nxg::mplex::Mplex;

/// The objects the gateway serves, and how it reaches them.
#[derive(Clone)]
pub enum Objects {
    /// SDO clients per `net`.
    Bus(HashMap<u8, SdoClients>),
    /// The dictionary of the controller the gateway is linked into; `node` is its node-ID.
    Local {
        /// The dictionary.
        od: SharedDictionary,
        /// Its node-ID (requests for other nodes find no object).
        node: u8,
    },
}

impl Objects {
    /// Run `job` (not `StoreToken`, which the connection handles).
    pub async fn run(&self, job: Job) -> JobResult {
        match job {
            Job::Read { target, index, sub } => match self.read(target, index, sub).await {
                Ok(bytes) => JobResult::Read(vec![bytes]),
                Err(code) => JobResult::Failed(code),
            },
            Job::ReadArray { target, index } => {
                let count = match self.read(target, index, 0).await {
                    Ok(bytes) => bytes.first().copied().unwrap_or(0),
                    Err(code) => return JobResult::Failed(code),
                };
                let mut values = Vec::with_capacity(usize::from(count));
                for sub in 1..=count {
                    match self.read(target, index, sub).await {
                        Ok(bytes) => values.push(bytes),
                        Err(code) => return JobResult::Failed(code),
                    }
                }
                JobResult::Read(values)
            }
            Job::Write {
                target,
                index,
                sub,
                data,
            } => match self.write(target, index, sub, &data).await {
                Ok(()) => JobResult::Done,
                Err(code) => JobResult::Failed(code),
            },
            Job::StoreToken(_) => JobResult::Failed(AbortCode::GENERAL),
        }
    }

    /// Where requests for `target` go.
    fn route(&self, target: Target) -> Result<Route<'_>, AbortCode> {
        match self {
            Objects::Bus(nets) => nets
                .get(&target.net)
                .map(Route::Sdo)
                .ok_or(AbortCode::NO_OBJECT),
            Objects::Local { od, node } if target.node == *node && target.net == 1 => {
                Ok(Route::Local(od))
            }
            Objects::Local { .. } => Err(AbortCode::NO_OBJECT),
        }
    }

    /// Read one sub-object.
    pub async fn read(&self, target: Target, index: u16, sub: u8) -> Result<Vec<u8>, AbortCode> {
        match self.route(target)? {
            Route::Sdo(sdo) => sdo
                .read_raw(target.node, index, sub)
                .await
                .map_err(|e| e.abort_code()),
            Route::Local(od) => od
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .read(index, sub),
        }
    }

    async fn write(
        &self,
        target: Target,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), AbortCode> {
        match self.route(target)? {
            Route::Sdo(sdo) => sdo
                .write_raw(target.node, index, sub, data)
                .await
                .map_err(|e| e.abort_code()),
            Route::Local(od) => od
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .write(index, sub, data),
        }
    }
}

enum Route<'a> {
    Sdo(&'a SdoClients),
    Local(&'a SharedDictionary),
}

/// The lift-safety interlock (docs/GATEWAY.md §Lift-safety interlock): before each remote write
/// the lift controller's state object is read, on the bus or in its own dictionary, so that the
/// decision is never older than the write. In a state the policy names (out of order, fire
/// service, fire brigade service, inspection) the write is refused with 08000022h ("… because of
/// the present device state", CiA 301 §7.2.4.3.17); reads are never held back.
#[derive(Clone)]
pub struct Interlock {
    policy: Arc<Policy>,
    controller: Target,
    state: Mplex,
}

/// Whether "the controller has no state object" was logged: once per process, not once for each
/// of a load generator's thousands of gateways.
static ABSENT_TOLD: AtomicBool = AtomicBool::new(false);

impl Interlock {
    /// The interlock `policy` asks for on the lift `controller`, if any.
    pub fn new(policy: &Policy, controller: Target) -> Option<Interlock> {
        Some(Interlock {
            state: policy.lift_state?,
            policy: Arc::new(policy.clone()),
            controller,
        })
    }

    /// Whether a write may go ahead now: `Err` with the code to answer when it may not.
    pub async fn check(
        &self,
        objects: &Objects,
        target: Target,
        index: u16,
        sub: u8,
    ) -> Result<(), AbortCode> {
        if !self.policy.guarded(target, index) {
            return Ok(());
        }
        let (state_index, state_sub) = (self.state.index, self.state.sub);
        match objects.read(self.controller, state_index, state_sub).await {
            Ok(bytes) => {
                let state = bytes
                    .iter()
                    .take(8)
                    .rev()
                    .fold(0u64, |v, b| (v << 8) | u64::from(*b));
                if self.policy.interlocked(state) {
                    tracing::warn!(
                        node = target.node,
                        net = target.net,
                        object = %Mplex { index, sub },
                        lift_state = state,
                        "write refused: the lift is in a state that forbids remote writes (policy refuse_writes_in)"
                    );
                    return Err(AbortCode::DEVICE_STATE);
                }
                Ok(())
            }
            // A controller without the object cannot say: the interlock does not apply to it.
            Err(AbortCode::NO_OBJECT | AbortCode::NO_SUB_INDEX) => {
                if !ABSENT_TOLD.swap(true, Ordering::Relaxed) {
                    tracing::warn!(
                        node = self.controller.node,
                        object = %self.state,
                        "the lift controller has no such state object: the interlock cannot act \
                         (set [policy] lift_state to its state object, or \"\" to say none)"
                    );
                }
                Ok(())
            }
            // Not knowing the state is not knowing that writing is safe.
            Err(code) => {
                tracing::warn!(
                    node = target.node,
                    object = %Mplex { index, sub },
                    code = %format_args!("{:08X}h", code.0),
                    "write refused: the lift state could not be read"
                );
                Err(code)
            }
        }
    }
}
