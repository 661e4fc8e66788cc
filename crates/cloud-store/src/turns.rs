//! Work on the whole fleet's data done by one process of a cluster at a time (docs/CLUSTER.md
//! §Work done once): every process runs the same periodic jobs (the roll-ups, the deletions
//! after the retention time), and on one PostgreSQL they ran them all at once. The roll-ups of
//! six processes read the same minutes, merged them into the same hours six times over and
//! deadlocked on each other's rows; the deletions did the same work six times.
//!
//! A job's turn is a PostgreSQL advisory lock held by a transaction of its own: it ends with
//! the transaction, the connection or the process, so a process that dies mid-job leaves
//! nothing locked. A process that finds the turn taken skips the round (the one holding it is
//! doing the work now). One process holds a SQLite database: there the turn is always free.

use sqlx::Row;

use crate::{Store, StoreError};

/// The first key of every turn's advisory lock ("CANL"): the locks of canlift's jobs apart
/// from any other application's on the same server.
const NAMESPACE: i32 = 0x4341_4E4C;

/// A fleet-wide job's turn, this process's until [`Turn::end`] (or until it is dropped).
pub struct Turn(Option<sqlx::Transaction<'static, sqlx::Any>>);

impl Turn {
    /// Give the turn back (at once; dropped, it goes back when the pool has rolled back).
    pub async fn end(self) {
        if let Some(tx) = self.0 {
            let _ = tx.rollback().await;
        }
    }
}

impl Store {
    /// The turn of job `job` (a name: each its own lock), or `None` while another process of
    /// the cluster holds it.
    pub async fn turn(&self, job: &str) -> Result<Option<Turn>, StoreError> {
        if self.copy.is_none() {
            return Ok(Some(Turn(None)));
        }
        let mut tx = self.pool.begin().await?;
        let taken = sqlx::query("SELECT pg_try_advisory_xact_lock($1, $2) AS ours")
            .bind(NAMESPACE)
            .bind(key(job))
            .fetch_one(&mut *tx)
            .await?
            .try_get::<bool, _>("ours")?;
        if taken {
            return Ok(Some(Turn(Some(tx))));
        }
        tx.rollback().await?;
        Ok(None)
    }
}

/// The lock's second key: FNV-1a of the job's name, the same in every process and build.
fn key(job: &str) -> i32 {
    let hash = job.bytes().fold(0x811c_9dc5_u32, |h, b| {
        (h ^ u32::from(b)).wrapping_mul(0x0100_0193)
    });
    i32::from_ne_bytes(hash.to_ne_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_job_has_a_key_of_its_own_that_does_not_change() {
        assert_eq!(key("roll-up"), key("roll-up"));
        assert_ne!(key("roll-up"), key("retention telemetry"));
        // FNV-1a's published value for "a": the key is the same in every build.
        assert_eq!(key("a") as u32, 0xe40c_292c);
    }

    #[tokio::test]
    async fn sqlite_has_one_process_and_the_turn_is_always_free() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        let first = store.turn("roll-up").await.unwrap();
        assert!(first.is_some());
        assert!(store.turn("roll-up").await.unwrap().is_some());
    }

    /// Two stores on one database are two processes of a cluster: a job's turn is one's at a
    /// time, other jobs' turns are free meanwhile, and an ended turn is free again (also when
    /// dropped: the connection's transaction is rolled back).
    #[tokio::test]
    async fn postgres_gives_a_turn_to_one_process_at_a_time() {
        let Some(url) = testkit::postgres("turns").await else {
            return;
        };
        let a = Store::open_pooled(&url, 2).await.unwrap();
        let b = Store::open_pooled(&url, 2).await.unwrap();
        let held = a.turn("roll-up").await.unwrap().expect("free at first");
        assert!(b.turn("roll-up").await.unwrap().is_none());
        assert!(
            a.turn("roll-up").await.unwrap().is_none(),
            "not even twice in one process"
        );
        let other = b.turn("retention telemetry").await.unwrap();
        assert!(other.is_some(), "another job's turn is free");
        held.end().await;
        let again = b.turn("roll-up").await.unwrap().expect("free once ended");
        drop(again);
        let mut free = None;
        for _ in 0..100 {
            free = a.turn("roll-up").await.unwrap();
            if free.is_some() {
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
        assert!(free.is_some(), "a dropped turn is free again");
    }
}
