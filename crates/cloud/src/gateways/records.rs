//! The registry's rows of the gateways (docs/PORTAL.md §Registry), written behind their
//! connections in batches: what each known gateway said it is at CONNECT, and when it was last
//! heard.
//!
//! A reconnect storm of 10,000 known gateways made as many write transactions, each waiting
//! for SQLite's one writer while it held one of the pool's few connections — the admissions
//! of the gateways behind them waited for a connection too. One writer takes them many at a
//! time, in order, one transaction per batch. What an admission decides on (a first contact's
//! row, a changed board) is still written before CONNACK.

use tokio::sync::mpsc::error::TrySendError;
use tokio::sync::{mpsc, watch};

use crate::store::{GatewayRecord, Store};

/// Records waiting for the writer; beyond this a connection waits for room.
const QUEUE: usize = 4096;

/// Records written in one transaction at most.
const BATCH: usize = 1024;

/// The way into the writer.
#[derive(Clone)]
pub struct Records {
    tx: mpsc::Sender<GatewayRecord>,
    store: Store,
}

impl Records {
    /// The queue in front of [`writer`], which takes the receiver.
    pub fn new(store: Store) -> (Records, mpsc::Receiver<GatewayRecord>) {
        let (tx, rx) = mpsc::channel(QUEUE);
        (Records { tx, store }, rx)
    }

    /// Queue `record` behind the ones before it, waiting for room when the writer is behind
    /// (so a storm's connections take turns with it); without a writer (the portal is
    /// stopping) it is written at once.
    pub async fn write(&self, record: GatewayRecord) {
        if let Err(unsent) = self.tx.send(record).await {
            if let Err(e) = self.store.record(&[unsent.0]).await {
                tracing::error!(error = %e, "gateway not recorded");
            }
        }
    }

    /// The same without waiting: when there is no room it waits in the background.
    pub fn write_later(&self, record: GatewayRecord) {
        if let Err(TrySendError::Full(record) | TrySendError::Closed(record)) =
            self.tx.try_send(record)
        {
            let records = self.clone();
            tokio::spawn(async move { records.write(record).await });
        }
    }
}

/// Write what is queued, in order, a batch per transaction, until every [`Records`] is gone
/// or `stop` turns true (then what is queued still is). A batch the database refuses is logged
/// and lost, as a single write's failure was.
pub async fn writer(
    store: Store,
    mut rx: mpsc::Receiver<GatewayRecord>,
    mut stop: watch::Receiver<bool>,
) {
    let mut batch = Vec::with_capacity(BATCH);
    while super::next_batch(&mut rx, &mut batch, BATCH, &mut stop).await > 0 {
        if let Err(e) = store.record(&batch).await {
            tracing::error!(error = %e, records = batch.len(), "gateways not recorded");
        }
        batch.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn connect(sernum: &str, software: &str) -> nxg::msg::Connect {
        let mut connect = crate::store::tests::connect(sernum, "MAS", None);
        connect.identity.software = software.into();
        connect
    }

    /// Records queued from many connections reach the database in order, in few batches:
    /// the last identity a gateway gave wins, and `last_seen` never goes back.
    #[tokio::test]
    async fn records_are_written_in_order_and_last_seen_only_moves_forward() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("records.db").display());
        let store = Store::open(&url).await.unwrap();
        store.add_account("masora", "MAS").await.unwrap();
        let (records, rx) = Records::new(store.clone());
        let (stop, stopping) = watch::channel(false);
        let task = tokio::spawn(writer(store.clone(), rx, stopping));
        for n in 0..3000 {
            let connect = connect(&format!("GW{}", n % 100), &format!("v{n}"));
            records.write(GatewayRecord::connected(&connect, 2)).await;
        }
        let lift = crate::store::lift_id(&connect("GW7", "").identity);
        let at = |record: &GatewayRecord| match record {
            GatewayRecord::Connected { at, .. } | GatewayRecord::Seen { at, .. } => *at,
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
        assert_eq!(lifts.len(), 100);
        let gw7 = lifts.iter().find(|l| l.id == lift).unwrap();
        assert_eq!(gw7.software, "v2907");
        assert_eq!(gw7.last_seen, later);
    }
}
