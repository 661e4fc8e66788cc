//! Admissions (NXg §5.2, docs/PORTAL.md §Stores) looked up in batches: each CONNECT waits
//! for the registry's answer about it, and the CONNECTs that came meanwhile are asked about in
//! one statement ([`Store::gateway_rows`]) and decided here ([`decide`]).
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

use cloud_store::{GatewayRow, Store, StoreError};

use super::refusals::Reason;

/// What the registry says about a CONNECT.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Admission {
    /// No token on record (never issued, or reset by an administrator): accept and issue one.
    FirstContact {
        /// The lift's key in the registry (docs/PORTAL.md §Lifts and accounts).
        key: String,
        /// Whether users hold subscriptions of the lift (after a token reset they may).
        subscribed: bool,
    },
    /// The token matches the one on record (or the one being rotated to, which now is).
    Known(Known),
    /// Refused: why, in a word for `/metrics` and in words to record.
    Refused(Reason, String),
}

/// What the registry knows of a gateway whose token matched.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Known {
    /// The lift's key in the registry (docs/PORTAL.md §Lifts and accounts).
    pub key: String,
    /// The boardhash on record when the CONNECT's differs (the gateway's hardware changed, or
    /// its token was copied to another board).
    pub board_was: Option<String>,
    /// When the token in use was confirmed (ms since the epoch; 0 when not recorded).
    pub token_set: i64,
    /// Whether users hold subscriptions of the lift (to register when it connects).
    pub subscribed: bool,
    /// The gateway sent the token a rotation gave it, whose confirmation the portal did not
    /// see (NXg §5.4: the answer was lost with the connection): that token is the lift's now,
    /// and is recorded as confirmed before the gateway is admitted.
    pub rotation_confirmed: bool,
}

impl Admission {
    /// The lift's key, for an admitted gateway.
    pub fn key(&self) -> Option<&str> {
        match self {
            Admission::FirstContact { key, .. } | Admission::Known(Known { key, .. }) => Some(key),
            Admission::Refused(..) => None,
        }
    }
}

/// What the registry's `row` says about `connect` (NXg §5.2, §5.4): the domain token names
/// the account; within it the registry is keyed by vendor, product and serial number, apart
/// from every other account's lifts (docs/PORTAL.md §Lifts and accounts); the token proves
/// the gateway is the one that was admitted before. Decided here, without the database (the
/// row is read with others in one statement: [`Store::gateway_rows`]).
pub fn decide(connect: &Connect, row: &GatewayRow) -> Admission {
    let identity = &connect.identity;
    if row.account.is_none() {
        return Admission::Refused(Reason::Domain, "no account for this domain token".into());
    }
    let subscribed = row.subscribed;
    let key = row.key.clone();
    let Some(registered) = &row.registered else {
        return Admission::FirstContact { key, subscribed };
    };
    let known = |token_set, rotation_confirmed| {
        Admission::Known(Known {
            key: key.clone(),
            board_was: (registered.boardhash != identity.boardhash)
                .then(|| registered.boardhash.clone()),
            token_set,
            subscribed,
            rotation_confirmed,
        })
    };
    let matches = |digest: &Option<String>, token: &str| {
        digest
            .as_deref()
            .is_some_and(|d| nxg::digest::matches(d, &cloud_store::digest(token)))
    };
    match (&registered.token_hash, identity.cloudtoken.as_deref()) {
        (None, _) => Admission::FirstContact {
            key: key.clone(),
            subscribed,
        },
        (hash, Some(t)) if matches(hash, t) => known(registered.token_set, false),
        // The gateway stored the token of a rotation whose answer the portal did not see.
        (_, Some(t)) if matches(&registered.token_next, t) => known(cloud_types::now_ms(), true),
        (Some(_), Some(_)) => Admission::Refused(Reason::Token, "wrong cloud token".into()),
        (Some(_), None) => Admission::Refused(
            Reason::Token,
            "no cloud token although one was issued".into(),
        ),
    }
}

/// The admissions of `connects`, read in one statement and decided; a rotation the gateway
/// confirmed by using its new token is recorded before the answer.
async fn admit_all(store: &Store, connects: &[&Connect]) -> Result<Vec<Admission>, StoreError> {
    let rows = store.gateway_rows(connects).await?;
    let mut admissions = Vec::with_capacity(rows.len());
    for (connect, row) in connects.iter().zip(&rows) {
        let admission = decide(connect, row);
        if let (Admission::Known(known), Some(token)) = (&admission, &connect.identity.cloudtoken) {
            if known.rotation_confirmed {
                store
                    .set_token(&known.key, &connect.domaintoken, token)
                    .await?;
            }
        }
        admissions.push(admission);
    }
    Ok(admissions)
}

/// The admission of one CONNECT, decided now on its own.
pub async fn admit_alone(store: &Store, connect: &Connect) -> Result<Admission, StoreError> {
    let mut admissions = admit_all(store, &[connect]).await?;
    admissions.pop().ok_or_else(StoreError::no_row)
}

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
    pub fn start(
        store: Store,
        timer: crate::metrics::Timer,
    ) -> (Admissions, tokio::task::JoinHandle<()>) {
        let (tx, rx) = mpsc::channel(QUEUE);
        let counters = Arc::new(AdmissionCounters::default());
        let task = tokio::spawn(ask(store, rx, counters.clone(), timer));
        (Admissions { tx, counters }, task)
    }

    /// What the registry says about `connect` ([`decide`]).
    pub async fn admit(&self, connect: &Connect) -> Result<Admission, StoreError> {
        let (answer, answered) = oneshot::channel();
        let asked = Asked {
            connect: connect.clone(),
            answer,
        };
        // Without the task (the portal stops) there is nobody to ask.
        let closed = StoreError::closed;
        self.tx.send(asked).await.map_err(|_| closed())?;
        answered.await.unwrap_or_else(|_| Err(closed()))
    }
}

/// Take what waits (at once when one CONNECT does) and ask about it in one statement, up to
/// [`IN_FLIGHT`] batches at a time.
async fn ask(
    store: Store,
    mut rx: mpsc::Receiver<Asked>,
    counters: Arc<AdmissionCounters>,
    timer: crate::metrics::Timer,
) {
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
        // Nobody to tell: the gateway left while it waited (its connection stopped waiting,
        // `gateways::connection`). In a storm on a slow database these are many, and asking
        // about them would slow the answers to those still waiting.
        batch.retain(|asked| !asked.answer.is_closed());
        if batch.is_empty() {
            continue;
        }
        let (store, counters, timer) = (store.clone(), counters.clone(), timer.clone());
        tokio::spawn(async move {
            let connects: Vec<&Connect> = batch.iter().map(|asked| &asked.connect).collect();
            counters.lookups.fetch_add(1, Ordering::Relaxed);
            let answers = timer
                .statement(
                    "admission lookup",
                    connects.len(),
                    admit_all(&store, &connects),
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
                        let _ = asked.answer.send(admit_alone(&store, &asked.connect).await);
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
    use cloud_store::GatewayRecord;
    use testkit::connect;

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
            let lift = cloud_types::lifts::lift_id(&gw.identity);
            store
                .record(&[GatewayRecord::connected(&lift, &gw, 2)])
                .await
                .unwrap();
            store
                .set_token(&lift, "MAS", &format!("T{n}"))
                .await
                .unwrap();
        }
        let (admissions, task) = Admissions::start(store.clone(), Default::default());
        let asked = (0..600).map(|n| {
            let admissions = admissions.clone();
            async move {
                let domain = if n % 7 == 0 { "XYZ" } else { "MAS" };
                let token = match n % 4 {
                    0 => Some(format!("T{n}")),
                    2 => Some("wrong".to_owned()),
                    _ => None,
                };
                let gw = connect(&format!("GW{n}"), domain, token.as_deref());
                let batched = admissions.admit(&gw).await;
                (n, gw, batched)
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
        // The answers alone afterwards, one at a time (lookups change nothing): 600 at once
        // beside the batches would wait for the pool's few connections, and past its acquire
        // timeout on a busy machine.
        for (n, gw, batched) in answers {
            let (batched, alone) = (batched.unwrap(), admit_alone(&store, &gw).await.unwrap());
            assert_eq!(batched, alone, "gateway {n}");
            let kind = match batched {
                Admission::FirstContact { .. } => "first",
                Admission::Known(_) => "known",
                Admission::Refused(..) => "refused",
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

    fn registered(token: Option<&str>, next: Option<&str>) -> GatewayRow {
        GatewayRow {
            account: Some("masora".into()),
            key: "1050-4096-180917010200000102".into(),
            subscribed: false,
            registered: Some(cloud_store::Registered {
                domain: "MAS".into(),
                boardhash: String::new(),
                token_hash: token.map(cloud_store::digest),
                token_next: next.map(cloud_store::digest),
                token_set: 7,
            }),
        }
    }

    /// The decision alone, from rows as the registry holds them (NXg §5.2, §5.4).
    #[test]
    fn admissions_are_decided_from_the_registry_row() {
        let gw = |token| connect("180917010200000102", "MAS", token);
        let key = "1050-4096-180917010200000102".to_owned();
        let first = GatewayRow {
            account: Some("masora".into()),
            key: key.clone(),
            ..GatewayRow::default()
        };
        let first_contact = Admission::FirstContact {
            key: key.clone(),
            subscribed: false,
        };
        assert_eq!(decide(&gw(None), &first), first_contact);
        assert!(matches!(
            decide(&gw(None), &GatewayRow::default()),
            Admission::Refused(_, c) if c.contains("no account")
        ));
        // Registered, no token confirmed yet (or reset): a first contact again.
        assert_eq!(
            decide(&gw(Some("x")), &registered(None, None)),
            first_contact
        );
        assert_eq!(
            decide(&gw(Some("T0K3N")), &registered(Some("T0K3N"), None)),
            Admission::Known(Known {
                key,
                board_was: None,
                token_set: 7,
                subscribed: false,
                rotation_confirmed: false
            })
        );
        assert!(matches!(
            decide(&gw(Some("T0K3M")), &registered(Some("T0K3N"), None)),
            Admission::Refused(_, c) if c.contains("wrong")
        ));
        assert!(matches!(
            decide(&gw(None), &registered(Some("T0K3N"), None)),
            Admission::Refused(_, c) if c.contains("no cloud token")
        ));
        // Rotation: old and new token both admitted until one is confirmed.
        let rotating = registered(Some("T0K3N"), Some("N3XT"));
        assert!(matches!(
            decide(&gw(Some("T0K3N")), &rotating),
            Admission::Known(Known {
                rotation_confirmed: false,
                ..
            })
        ));
        assert!(matches!(
            decide(&gw(Some("N3XT")), &rotating),
            Admission::Known(Known {
                rotation_confirmed: true,
                ..
            })
        ));
        // A valid token from another board: known, the board on record named.
        let mut swapped = gw(Some("T0K3N"));
        swapped.identity.boardhash = "B0ARD2".into();
        assert!(matches!(
            decide(&swapped, &registered(Some("T0K3N"), None)),
            Admission::Known(Known { board_was: Some(b), .. }) if b.is_empty()
        ));
        let subscribed = GatewayRow {
            subscribed: true,
            ..registered(Some("T0K3N"), None)
        };
        assert!(matches!(
            decide(&gw(Some("T0K3N")), &subscribed),
            Admission::Known(Known {
                subscribed: true,
                ..
            })
        ));
    }

    /// Rotation on a real registry: a token confirmed by use is recorded, and the old one is
    /// over; a reset makes the next CONNECT a first contact.
    async fn rotation_and_reset(store: Store) {
        store.add_account("masora", "MAS").await.unwrap();
        let gw = |token: Option<&str>| connect("180917010200000102", "MAS", token);
        let lift = cloud_types::lifts::lift_id(&gw(None).identity);
        store
            .record(&[GatewayRecord::connected(&lift, &gw(None), 1)])
            .await
            .unwrap();
        store.set_token(&lift, "MAS", "T0K3N").await.unwrap();
        store.set_next_token(&lift, "N3XT").await.unwrap();
        let known = |a: Admission| matches!(a, Admission::Known(_));
        assert!(known(
            admit_alone(&store, &gw(Some("T0K3N"))).await.unwrap()
        ));
        // The gateway stored the new token but its answer was lost: admitted, and it counts.
        assert!(known(admit_alone(&store, &gw(Some("N3XT"))).await.unwrap()));
        assert!(
            matches!(
                admit_alone(&store, &gw(Some("T0K3N"))).await.unwrap(),
                Admission::Refused(..)
            ),
            "the old token is over once the new one was used"
        );
        assert!(store.reset_token("MAS", &lift, "ops").await.unwrap());
        assert_eq!(
            admit_alone(&store, &gw(Some("N3XT"))).await.unwrap(),
            Admission::FirstContact {
                key: lift.clone(),
                subscribed: false
            }
        );
    }

    #[tokio::test]
    async fn rotation_and_reset_on_sqlite() {
        rotation_and_reset(Store::open("sqlite::memory:").await.unwrap()).await;
    }

    #[tokio::test]
    async fn rotation_and_reset_on_postgres() {
        let Some(url) = testkit::postgres("rotation").await else {
            return;
        };
        rotation_and_reset(Store::open(&url).await.unwrap()).await;
    }

    /// Lifts belong to accounts (docs/PORTAL.md §Lifts and accounts): a gateway with the
    /// identity of another account's lift and its own account's domain token is a first
    /// contact of a lift of its own, keyed apart, whichever came first; neither changes the
    /// other's row or token, and a record of one never lands on the other's row.
    async fn one_identity_in_two_accounts(store: Store) {
        store.add_account("masora", "MAS").await.unwrap();
        store.add_account("evil", "EVL").await.unwrap();
        let serial = "180917010200000102";
        let id = cloud_types::lifts::lift_id(&connect(serial, "MAS", None).identity);
        let scoped = cloud_types::lifts::scoped_key(&id, "evil");
        let admitted = |domain: &'static str, token: Option<&'static str>| {
            let store = store.clone();
            async move {
                let gw = connect(serial, domain, token);
                let admission = admit_alone(&store, &gw).await.unwrap();
                if let Admission::FirstContact { key, .. } = &admission {
                    let record = GatewayRecord::connected(key, &gw, 2);
                    store.record(&[record]).await.unwrap();
                    store
                        .set_token(key, domain, &format!("{domain}-token"))
                        .await
                        .unwrap();
                }
                admission
            }
        };
        assert_eq!(admitted("MAS", None).await.key(), Some(id.as_str()));
        // The squatter: a lift of its own account, the first lift untouched.
        assert_eq!(admitted("EVL", None).await.key(), Some(scoped.as_str()));
        assert_eq!(
            admitted("EVL", Some("EVL-token")).await.key(),
            Some(scoped.as_str())
        );
        let real = admitted("MAS", Some("MAS-token")).await;
        assert!(
            matches!(&real, Admission::Known(k) if k.key == id),
            "{real:?}"
        );
        assert!(matches!(
            admitted("EVL", Some("MAS-token")).await,
            Admission::Refused(_, c) if c.contains("wrong")
        ));
        // A record with another account's domain never lands on this account's row.
        let mut stray = connect(serial, "EVL", None);
        stray.identity.liftnum = "stray".into();
        let ours = store
            .record_batch(&[
                GatewayRecord::connected(&id, &stray, 2),
                GatewayRecord::token(&id, "EVL", "stray"),
            ])
            .await
            .unwrap();
        assert_eq!(ours, [false, true], "the row is not the stray's account's");
        let masora = cloud_types::users::Account {
            name: "masora".into(),
            domain: "MAS".into(),
        };
        let row = store.lift(&masora, &id).await.unwrap().unwrap();
        assert_ne!(row.liftnum, "stray");
        assert!(matches!(
            admitted("MAS", Some("MAS-token")).await,
            Admission::Known(_)
        ));
        // Each account finds its own lift by the same id.
        let evil = cloud_types::users::Account {
            name: "evil".into(),
            domain: "EVL".into(),
        };
        assert_eq!(store.lift(&evil, &id).await.unwrap().unwrap().id, scoped);
        // Retired, the plain key is free: the next other account's first contact takes it.
        assert!(store.retire(&masora, &id, "ops").await.unwrap());
        assert!(store.lift(&masora, &id).await.unwrap().is_none());
        assert_eq!(
            admitted("EVL", Some("EVL-token")).await.key(),
            Some(scoped.as_str())
        );
    }

    #[tokio::test]
    async fn one_identity_in_two_accounts_on_sqlite() {
        one_identity_in_two_accounts(Store::open("sqlite::memory:").await.unwrap()).await;
    }

    #[tokio::test]
    async fn one_identity_in_two_accounts_on_postgres() {
        let Some(url) = testkit::postgres("two_accounts").await else {
            return;
        };
        one_identity_in_two_accounts(Store::open(&url).await.unwrap()).await;
    }
}
