//! The registry's rows of the gateways (docs/PORTAL.md §Stores), written behind their
//! connections in batches: what each known gateway said it is at CONNECT, and when it was last
//! heard.
//!
//! A reconnect storm of 10,000 known gateways made as many write transactions, each waiting
//! for SQLite's one writer while it held one of the pool's few connections — the admissions
//! of the gateways behind them waited for a connection too. One writer takes them many at a
//! time, in order, one transaction per batch. What an admission decides on (a first contact's
//! row, a changed board) is written before CONNACK all the same: its connection waits for the
//! batch it is in ([`Records::write_now`]). A confirmed token is queued behind its row, and the
//! next admission of its lift waits until it is written ([`Records::settled`]).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};

use tokio::sync::mpsc::error::TrySendError;
use tokio::sync::{mpsc, oneshot, watch};

use cloud_store::{GatewayRecord, Store, StoreError};

/// A record in the queue, and whoever waits until it is written.
struct Queued {
    record: GatewayRecord,
    written: Option<oneshot::Sender<Result<bool, StoreError>>>,
}

/// Confirmed tokens queued and not yet written, counted by lift (its id and its account's
/// domain: what a CONNECT says before the registry is asked for its key). Until its token is
/// written, a lift's row has none: a CONNECT of that lift would be taken for a first contact
/// again — a new token, and no check of its board. Such an admission waits
/// ([`Records::settled`]).
#[derive(Default)]
struct Unwritten {
    tokens: Mutex<HashMap<String, usize>>,
    /// Bumped after each batch the writer is done with (written or lost).
    batches: watch::Sender<u64>,
}

impl Unwritten {
    /// `record` goes into the queue.
    fn queued(&self, record: &GatewayRecord) {
        if let Some(lift) = Unwritten::token_of(record) {
            *self.lock().entry(lift).or_default() += 1;
        }
    }

    /// `record` left the queue, written or lost.
    fn done(&self, record: &GatewayRecord) {
        if let Some(lift) = Unwritten::token_of(record) {
            let mut tokens = self.lock();
            if let Some(count) = tokens.get_mut(&lift) {
                *count -= 1;
                if *count == 0 {
                    tokens.remove(&lift);
                }
            }
        }
    }

    /// The lift a token record is of, as [`Records::settled`] names it.
    fn token_of(record: &GatewayRecord) -> Option<String> {
        match record {
            GatewayRecord::Token { lift, domain, .. } => {
                Some(Unwritten::name(cloud_types::lifts::shown_id(lift), domain))
            }
            _ => None,
        }
    }

    fn name(id: &str, domain: &str) -> String {
        format!("{id}\n{domain}")
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, usize>> {
        self.tokens.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Records waiting for the writer; beyond this a connection waits for room.
const QUEUE: usize = 4096;

/// Records written in one transaction at most.
const BATCH: usize = 1024;

/// The way into the writer.
#[derive(Clone)]
pub struct Records {
    tx: mpsc::Sender<Queued>,
    store: Store,
    unwritten: Arc<Unwritten>,
}

/// What [`writer`] takes from the queue.
pub struct Queue(mpsc::Receiver<Queued>, Arc<Unwritten>);

impl Records {
    /// The queue in front of [`writer`], which takes the receiver.
    pub fn new(store: Store) -> (Records, Queue) {
        let (tx, rx) = mpsc::channel(QUEUE);
        let unwritten = Arc::new(Unwritten::default());
        (
            Records {
                tx,
                store,
                unwritten: unwritten.clone(),
            },
            Queue(rx, unwritten),
        )
    }

    /// Returns once no confirmed token of lift `id` of `domain` waits in the queue (at once
    /// almost always: only a gateway that reconnects right after confirming one waits for the
    /// writer).
    pub async fn settled(&self, id: &str, domain: &str) {
        let lift = Unwritten::name(id, domain);
        // Subscribed before looking, so a batch done in between is not missed.
        let mut batches = self.unwritten.batches.subscribe();
        while self.unwritten.lock().contains_key(&lift) {
            if batches.changed().await.is_err() {
                return;
            }
        }
    }

    /// Queue `record` behind the ones before it, waiting for room when the writer is behind
    /// (so a storm's connections take turns with it); without a writer (the portal is
    /// stopping) it is written at once.
    pub async fn write(&self, record: GatewayRecord) {
        self.deliver(self.queued(record, None)).await;
    }

    async fn deliver(&self, queued: Queued) {
        if let Err(e) = self.send(queued).await {
            tracing::error!(error = %e, "gateway not recorded");
        }
    }

    /// [`Records::write`], returning once the record is written (with the others of its
    /// batch): for what the next admission decides on. True when the lift's row is the
    /// record's account's ([`Store::record_batch`]: a first contact learns whether another
    /// account's lift holds its key without asking again).
    pub async fn write_now(&self, record: GatewayRecord) -> Result<bool, StoreError> {
        let (written, done) = oneshot::channel();
        self.send(self.queued(record, Some(written))).await?;
        // The writer dropped the batch unanswered only if it ended mid-way: the portal stops.
        done.await
            .unwrap_or_else(|_| Err(cloud_store::StoreError::closed()))
    }

    /// Into the queue; without a writer (the portal is stopping) written at once.
    async fn send(&self, queued: Queued) -> Result<bool, StoreError> {
        let Err(unsent) = self.tx.send(queued).await else {
            return Ok(true);
        };
        let record = unsent.0.record;
        let written = write_alone(&self.store, &record).await;
        self.unwritten.done(&record);
        written
    }

    /// `record` counted as queued ([`Unwritten`]) until the writer is done with it.
    fn queued(
        &self,
        record: GatewayRecord,
        written: Option<oneshot::Sender<Result<bool, StoreError>>>,
    ) -> Queued {
        self.unwritten.queued(&record);
        Queued { record, written }
    }

    /// [`Records::write`] without waiting: when there is no room it waits in the background.
    pub fn write_later(&self, record: GatewayRecord) {
        let queued = self.queued(record, None);
        if let Err(TrySendError::Full(queued) | TrySendError::Closed(queued)) =
            self.tx.try_send(queued)
        {
            let records = self.clone();
            tokio::spawn(async move { records.deliver(queued).await });
        }
    }
}

/// Write what is queued, in order, a batch per transaction, until every [`Records`] is gone
/// or `stop` turns true (then what is queued still is). A batch the database refuses is logged
/// and lost, as a single write's failure was.
pub async fn writer(
    store: Store,
    Queue(mut rx, unwritten): Queue,
    mut stop: watch::Receiver<bool>,
    timer: crate::metrics::Timer,
) {
    let mut batch = Vec::with_capacity(BATCH);
    let mut records = Vec::with_capacity(BATCH);
    let mut waiting = Vec::with_capacity(BATCH);
    while super::next_batch(&mut rx, &mut batch, BATCH, &mut stop).await > 0 {
        for queued in batch.drain(..) {
            records.push(queued.record);
            waiting.push(queued.written);
        }
        match timer
            .statement(
                "gateway records",
                records.len(),
                store.record_batch(&records),
            )
            .await
        {
            // One record the database refuses fails the transaction for all: each is written
            // alone, so only that one is lost.
            Err(e) if !e.is_unavailable() && records.len() > 1 => {
                for (record, waiter) in records.drain(..).zip(waiting.drain(..)) {
                    let written = write_alone(&store, &record).await;
                    unwritten.done(&record);
                    if let Err(e) = &written {
                        // The lift, not the record: a CONNECT's identity holds its token.
                        tracing::error!(error = %e, lift = %record.lift(), "gateway not recorded");
                    }
                    if let Some(waiter) = waiter {
                        let _ = waiter.send(written);
                    }
                }
            }
            written => {
                if let Err(e) = &written {
                    tracing::error!(error = %e, records = records.len(), "gateways not recorded");
                }
                for (i, waiter) in waiting.drain(..).enumerate() {
                    if let Some(waiter) = waiter {
                        let ours = written
                            .as_ref()
                            .map(|ours| ours.get(i).copied() == Some(true));
                        let _ = waiter.send(ours.map_err(Clone::clone));
                    }
                }
                for record in records.drain(..) {
                    unwritten.done(&record);
                }
            }
        }
        unwritten.batches.send_modify(|n| *n += 1);
    }
    // Nothing is written any more: nobody waits for it.
    unwritten.lock().clear();
    unwritten.batches.send_modify(|n| *n += 1);
}

/// `record` written in a transaction of its own: whether the lift's row is its account's.
async fn write_alone(store: &Store, record: &GatewayRecord) -> Result<bool, StoreError> {
    let ours = store.record_batch(std::slice::from_ref(record)).await?;
    Ok(ours.first().copied() == Some(true))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The record of `connect`'s admission as a lift keyed by its id.
    fn connected(connect: &nxg::msg::Connect) -> GatewayRecord {
        GatewayRecord::connected(&cloud_types::lifts::lift_id(&connect.identity), connect, 2)
    }

    fn connect(sernum: &str, software: &str) -> nxg::msg::Connect {
        let mut connect = testkit::connect(sernum, "MAS", None);
        connect.identity.software = software.into();
        connect
    }

    #[tokio::test]
    async fn sqlite() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("records.db").display());
        records_are_written_in_order_and_last_seen_only_moves_forward(
            Store::open(&url).await.unwrap(),
        )
        .await;
    }

    #[tokio::test]
    async fn postgres() {
        let Some(url) = testkit::postgres("records").await else {
            return;
        };
        records_are_written_in_order_and_last_seen_only_moves_forward(
            Store::open(&url).await.unwrap(),
        )
        .await;
    }

    /// A confirmed token waiting in the queue holds up its lift's next admission, and only
    /// its lift's, until the writer has written it: then the gateway is known, with its board.
    #[tokio::test]
    async fn a_lifts_admission_waits_for_its_queued_token() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("records.db").display());
        let store = Store::open(&url).await.unwrap();
        store.add_account("masora", "MAS").await.unwrap();
        let first = connect("GW1", "v1");
        let lift = cloud_types::lifts::lift_id(&first.identity);
        store.record(&[connected(&first)]).await.unwrap();
        let (records, rx) = Records::new(store.clone());
        records
            .write(GatewayRecord::token(&lift, "MAS", "T1"))
            .await;
        let wait = std::time::Duration::from_millis(300);
        // No writer yet: the token is not on record, and the lift's admission waits.
        let again = testkit::connect("GW1", "MAS", Some("T1"));
        assert!(matches!(
            crate::gateways::admissions::admit_alone(&store, &again)
                .await
                .unwrap(),
            crate::gateways::admissions::Admission::FirstContact { .. }
        ));
        assert!(tokio::time::timeout(wait, records.settled(&lift, "MAS"))
            .await
            .is_err());
        let other = cloud_types::lifts::lift_id(&connect("GW2", "").identity);
        tokio::time::timeout(wait, records.settled(&other, "MAS"))
            .await
            .expect("another lift does not wait");
        let (stop, stopping) = watch::channel(false);
        let task = tokio::spawn(writer(store.clone(), rx, stopping, Default::default()));
        tokio::time::timeout(
            std::time::Duration::from_secs(10),
            records.settled(&lift, "MAS"),
        )
        .await
        .expect("settled once written");
        assert!(matches!(
            crate::gateways::admissions::admit_alone(&store, &again)
                .await
                .unwrap(),
            crate::gateways::admissions::Admission::Known(_)
        ));
        stop.send_replace(true);
        task.await.unwrap();
    }

    /// Records queued from many connections reach the database in order, in few batches:
    /// the last identity a gateway gave wins, and `last_seen` never goes back; one that waits
    /// is written when it returns; one the database refuses is lost alone.
    async fn records_are_written_in_order_and_last_seen_only_moves_forward(store: Store) {
        store.add_account("masora", "MAS").await.unwrap();
        let (records, rx) = Records::new(store.clone());
        let (stop, stopping) = watch::channel(false);
        let task = tokio::spawn(writer(store.clone(), rx, stopping, Default::default()));
        for n in 0..3000 {
            let connect = connect(&format!("GW{}", n % 100), &format!("v{n}"));
            records.write(connected(&connect)).await;
        }
        // PostgreSQL stores no NUL (the session's validation keeps it out of a CONNECT): the
        // batch it is in is written record by record, and the others are not lost with it.
        let poisoned = connected(&connect("GW\u{0}", ""));
        let (first, poisoned) = tokio::join!(
            records.write_now(connected(&connect("FIRST", ""))),
            records.write_now(poisoned)
        );
        first.unwrap();
        if store.free_connections().await.unwrap().is_some() {
            assert!(poisoned.is_err(), "PostgreSQL: {poisoned:?}");
        }
        let lift = cloud_types::lifts::lift_id(&connect("GW7", "").identity);
        let at = |record: &GatewayRecord| match record {
            GatewayRecord::Connected { at, .. }
            | GatewayRecord::Seen { at, .. }
            | GatewayRecord::Token { at, .. } => *at,
        };
        let seen = GatewayRecord::seen(&lift);
        let later = at(&seen);
        records.write_later(seen);
        // Written late, an older time does not take `last_seen` back.
        records.write_later(GatewayRecord::Seen {
            lift: lift.clone(),
            at: later - 60_000,
        });
        // The portal stops with the records still queued: they are written, then the writer
        // ends although a sender is left.
        stop.send_replace(true);
        task.await.unwrap();
        drop(records);
        let lifts = store.lifts("MAS").await.unwrap();
        assert!(lifts.iter().any(|l| l.id.ends_with("-FIRST")));
        let lifts: Vec<_> = lifts.into_iter().filter(|l| l.id.contains("-GW")).collect();
        assert_eq!(lifts.len(), 100 + usize::from(poisoned.is_ok()));
        let gw7 = lifts.iter().find(|l| l.id == lift).unwrap();
        assert_eq!(gw7.software, "v2907");
        assert_eq!(gw7.last_seen, later);
    }
}
