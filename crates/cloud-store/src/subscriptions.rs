//! Users' subscriptions (docs/PORTAL.md §Subscriptions): kept in the database so that the
//! process a gateway connects to next — after a portal restart, or another process of a
//! cluster — registers them again.

use sqlx::Row;

use super::{Store, StoreError};

/// One object a user holds a subscription of on a lift.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredSubscription {
    /// Who holds it.
    pub user: String,
    /// The object (`0x652001`).
    pub mplex: String,
    /// Minimum gap between two pushes (ms).
    pub inhibit: u64,
    /// Smallest change of a number that is pushed.
    pub threshold: f64,
}

impl Store {
    /// Every object users hold on `lift`.
    pub async fn subscribed_objects(
        &self,
        lift: &str,
    ) -> Result<Vec<StoredSubscription>, StoreError> {
        let rows = sqlx::query(
            "SELECT user_name, mplex, inhibit, threshold FROM subscriptions WHERE lift = $1 \
             ORDER BY user_name, mplex",
        )
        .bind(lift)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(StoredSubscription {
                    user: r.try_get("user_name")?,
                    mplex: r.try_get("mplex")?,
                    inhibit: u64::try_from(r.try_get::<i64, _>("inhibit")?).unwrap_or(0),
                    threshold: r.try_get("threshold")?,
                })
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(StoreError::from)
    }

    /// `user` holds `mplex` of `lift` with these terms (replacing its earlier terms).
    pub async fn subscribe_objects(
        &self,
        lift: &str,
        user: &str,
        mplex: &[String],
        inhibit: u64,
        threshold: f64,
    ) -> Result<(), StoreError> {
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
            let mut tx = sqlx::Connection::begin(&mut *conn).await?;
            for object in mplex {
                sqlx::query(
                    "INSERT INTO subscriptions (lift, user_name, mplex, inhibit, threshold) \
                 VALUES ($1, $2, $3, $4, $5) ON CONFLICT (lift, user_name, mplex) \
                 DO UPDATE SET inhibit = excluded.inhibit, threshold = excluded.threshold",
                )
                .bind(lift)
                .bind(user)
                .bind(object)
                .bind(i64::try_from(inhibit).unwrap_or(i64::MAX))
                .bind(threshold)
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
            Ok(())
        }
        .await;
        self.settle(conn, outcome).await
    }

    /// `user` lets go of `mplex` of `lift`.
    pub async fn unsubscribe_objects(
        &self,
        lift: &str,
        user: &str,
        mplex: &[String],
    ) -> Result<(), StoreError> {
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
            let mut tx = sqlx::Connection::begin(&mut *conn).await?;
            for object in mplex {
                sqlx::query(
                    "DELETE FROM subscriptions WHERE lift = $1 AND user_name = $2 AND mplex = $3",
                )
                .bind(lift)
                .bind(user)
                .bind(object)
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
            Ok(())
        }
        .await;
        self.settle(conn, outcome).await
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Run by the store's tests on SQLite and PostgreSQL.
    pub(crate) async fn held_released_and_per_lift(store: &Store) {
        let (lift, other) = ("1050-4096-1", "1050-4096-2");
        let objects = |list: &[&str]| list.iter().map(|s| (*s).to_owned()).collect::<Vec<_>>();
        store
            .subscribe_objects(
                lift,
                "masora",
                &objects(&["0x652001", "0x502200"]),
                500,
                0.5,
            )
            .await
            .unwrap();
        store
            .subscribe_objects(other, "masora", &objects(&["0x652001"]), 0, 0.0)
            .await
            .unwrap();
        // Held again: the new terms replace the old ones.
        store
            .subscribe_objects(lift, "masora", &objects(&["0x652001"]), 100, 2.0)
            .await
            .unwrap();
        store
            .subscribe_objects(lift, "tech", &objects(&["0x652001"]), 1000, 0.0)
            .await
            .unwrap();
        let held = store.subscribed_objects(lift).await.unwrap();
        let terms: Vec<(&str, &str, u64, f64)> = held
            .iter()
            .map(|h| (h.user.as_str(), h.mplex.as_str(), h.inhibit, h.threshold))
            .collect();
        assert_eq!(
            terms,
            [
                ("masora", "0x502200", 500, 0.5),
                ("masora", "0x652001", 100, 2.0),
                ("tech", "0x652001", 1000, 0.0),
            ]
        );
        store
            .unsubscribe_objects(lift, "masora", &objects(&["0x652001"]))
            .await
            .unwrap();
        store
            .unsubscribe_objects(lift, "tech", &objects(&["0x652001", "0x999999"]))
            .await
            .unwrap();
        let held = store.subscribed_objects(lift).await.unwrap();
        assert_eq!(held.len(), 1, "{held:?}");
        assert_eq!(held[0].mplex, "0x502200");
        assert_eq!(store.subscribed_objects(other).await.unwrap().len(), 1);
    }
}
