//! Admissions (NXg §5.2, docs/PORTAL.md §Stores) looked up in batches: each CONNECT waits
//! for the registry's answer about it, and the CONNECTs that came meanwhile are asked about in
//! one statement ([`Store::admit_many`]).
//!
//! A reconnect storm asked the database once per gateway, and each question held a pooled
//! connection for its round trips while thousands of others waited for one: in a cluster of
//! three processes on one PostgreSQL, tens of thousands of admissions waited past the pool's
//! timeout and were refused "registry unavailable", and their gateways' backoff made the
//! storm's tail. One question at a time is asked at once when nothing else waits; under load a
//! few batches are in flight, each up to 256 CONNECTs.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use nxg::msg::Connect;
use tokio::sync::{mpsc, oneshot, Semaphore};

use crate::store::{Admission, Store, StoreError};

/// CONNECTs asked about in one statement at most.
const BATCH: usize = 256;

/// Batches asked about at the same time at most (each holds a pooled connection).
const IN_FLIGHT: usize = 4;

/// CONNECTs waiting for a batch; beyond this a connection waits for room.
const QUEUE: usize = 4096;

/// A CONNECT waiting for its admission.
struct Asked {
    connect: Connect,
    answer: oneshot::Sender<Result<Admission, StoreError>>,
}

/// What became of CONNECTs, for `/metrics` (docs/PORTAL.md §Metrics).
#[derive(Debug, Default)]
pub struct AdmissionCounters {
    /// Admitted (CONNACK).
    pub admitted: AtomicU64,
    /// Refused by the registry: unknown domain, wrong or missing token, another board.
    pub refused: AtomicU64,
    /// Refused because the database did not answer (the gateway tries again after its backoff).
    pub unavailable: AtomicU64,
    /// Statements that asked about them (CONNECTs per statement: how much batching saves).
    pub lookups: AtomicU64,
}

/// The way to the registry's admissions, batched.
#[derive(Clone)]
pub struct Admissions {
    tx: mpsc::Sender<Asked>,
    /// What became of the CONNECTs.
    pub counters: Arc<AdmissionCounters>,
}

impl Admissions {
    /// The admissions and the task that asks the registry (it ends when every
    /// [`Admissions`] is gone).
    pub fn start(store: Store) -> (Admissions, tokio::task::JoinHandle<()>) {
        let (tx, rx) = mpsc::channel(QUEUE);
        let counters = Arc::new(AdmissionCounters::default());
        let task = tokio::spawn(ask(store, rx, counters.clone()));
        (Admissions { tx, counters }, task)
    }

    /// What the registry says about `connect` ([`Store::admit`]).
    pub async fn admit(&self, connect: &Connect) -> Result<Admission, StoreError> {
        let (answer, answered) = oneshot::channel();
        let asked = Asked {
            connect: connect.clone(),
            answer,
        };
        // Without the task (the portal stops) there is nobody to ask.
        let closed = || StoreError::from(sqlx::Error::PoolClosed);
        self.tx.send(asked).await.map_err(|_| closed())?;
        answered.await.unwrap_or_else(|_| Err(closed()))
    }
}

/// Take what waits (at once when one CONNECT does) and ask about it in one statement, up to
/// [`IN_FLIGHT`] batches at a time.
async fn ask(store: Store, mut rx: mpsc::Receiver<Asked>, counters: Arc<AdmissionCounters>) {
    let in_flight = Arc::new(Semaphore::new(IN_FLIGHT));
    loop {
        let Ok(permit) = in_flight.clone().acquire_owned().await else {
            return;
        };
        // Sized by what waits: a CONNECT alone takes no room for 256.
        let mut batch = Vec::new();
        if rx.recv_many(&mut batch, BATCH).await == 0 {
            return;
        }
        let (store, counters) = (store.clone(), counters.clone());
        tokio::spawn(async move {
            let connects: Vec<&Connect> = batch.iter().map(|asked| &asked.connect).collect();
            counters.lookups.fetch_add(1, Ordering::Relaxed);
            let answers = crate::store::timed(
                "admission lookup",
                connects.len(),
                store.admit_many(&connects),
            )
            .await;
            match answers {
                Ok(admissions) => {
                    for (asked, admission) in batch.into_iter().zip(admissions) {
                        let _ = asked.answer.send(Ok(admission));
                    }
                }
                // A CONNECT the database refuses to look up fails the statement for all: each
                // is asked about alone, so only that one fails.
                Err(e) if !e.is_unavailable() && batch.len() > 1 => {
                    for asked in batch {
                        counters.lookups.fetch_add(1, Ordering::Relaxed);
                        let _ = asked.answer.send(store.admit(&asked.connect).await);
                    }
                }
                Err(e) => {
                    for asked in batch {
                        let _ = asked.answer.send(Err(e.clone()));
                    }
                }
            }
            drop(permit);
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::tests::connect;
    use crate::store::GatewayRecord;

    #[tokio::test]
    async fn sqlite() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("admit.db").display());
        each_connect_gets_its_own_answer_in_a_batch(Store::open(&url).await.unwrap()).await;
    }

    #[tokio::test]
    async fn postgres() {
        let Some(url) = testkit::postgres("admissions").await else {
            return;
        };
        each_connect_gets_its_own_answer_in_a_batch(Store::open(&url).await.unwrap()).await;
    }

    /// Many CONNECTs at once, of known, new and foreign gateways, each get their own answer
    /// (as [`Store::admit`] gives it one by one), whatever batch they were asked in.
    async fn each_connect_gets_its_own_answer_in_a_batch(store: Store) {
        store.add_account("masora", "MAS").await.unwrap();
        // Even serial numbers are known with a token of their own; odd ones are new.
        for n in (0..600).step_by(2) {
            let gw = connect(&format!("GW{n}"), "MAS", None);
            store
                .record(&[GatewayRecord::connected(&gw, 2)])
                .await
                .unwrap();
            let lift = cloud_types::lifts::lift_id(&gw.identity);
            store.set_token(&lift, &format!("T{n}")).await.unwrap();
        }
        let (admissions, task) = Admissions::start(store.clone());
        let asked = (0..600).map(|n| {
            let admissions = admissions.clone();
            let store = store.clone();
            async move {
                let domain = if n % 7 == 0 { "XYZ" } else { "MAS" };
                let token = match n % 4 {
                    0 => Some(format!("T{n}")),
                    2 => Some("wrong".to_owned()),
                    _ => None,
                };
                let gw = connect(&format!("GW{n}"), domain, token.as_deref());
                let batched = admissions.admit(&gw).await;
                (n, batched, store.admit(&gw).await.unwrap())
            }
        });
        // A CONNECT whose lookup the database refuses (PostgreSQL stores no NUL; the session's
        // validation keeps such a CONNECT from the registry, this is the second line) fails
        // alone, not with the others of its batch.
        let poisoned = {
            let admissions = admissions.clone();
            let gw = connect("GW\u{0}", "MAS", None);
            async move { admissions.admit(&gw).await }
        };
        let (answers, poisoned) = tokio::join!(futures_util::future::join_all(asked), poisoned);
        // 601 CONNECTs in batches of up to 256 (and, on PostgreSQL, the poisoned batch's
        // CONNECTs again one by one).
        let lookups = admissions.counters.lookups.load(Ordering::Relaxed);
        assert!((3..=601 + 256).contains(&lookups), "{lookups} statements");
        if store.free_connections().await.unwrap().is_some() {
            assert!(poisoned.is_err(), "PostgreSQL: {poisoned:?}");
        }
        let mut kinds = std::collections::BTreeMap::new();
        for (n, batched, alone) in answers {
            let batched = batched.unwrap();
            assert_eq!(batched, alone, "gateway {n}");
            let kind = match batched {
                Admission::FirstContact { .. } => "first",
                Admission::Known(_) => "known",
                Admission::Refused(_) => "refused",
            };
            *kinds.entry(kind).or_insert(0) += 1;
        }
        // 257 odd ones not refused for their domain are new; of the even ones, those with
        // their own token are known, those with a wrong one or another domain refused.
        assert_eq!(kinds["first"], 257);
        assert_eq!(kinds["known"], 128);
        assert_eq!(kinds["refused"], 215);
        drop(admissions);
        task.await.unwrap();
    }
}
