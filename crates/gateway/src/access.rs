//! Running the session's dictionary accesses: by SDO on a CAN network (bus-node mode) or on the
//! controller's own dictionary (embedded mode).

use std::collections::HashMap;
use std::sync::PoisonError;

use canopen::od::SharedDictionary;
use canopen::sdo::abort::AbortCode;
use canopen::sdo::clients::SdoClients;
use nxg::gateway::{Job, JobResult, Target};

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
