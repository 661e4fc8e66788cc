//! The cloud token's life at the portal (NXg §5.4, docs/PORTAL.md §Tokens): a reset lets a wiped
//! gateway in again as a first contact, a rotation changes the token the gateway stores (now, or
//! when it connects with a token older than `token_rotate_days`), and a valid token from another
//! board is refused, alarmed or accepted per `[gateways] boardhash_change`.

use std::time::Duration;

use cloud::config::BoardhashChange;
use serde_json::{json, Value};
use testkit::constants::{LIFT, WAIT};
use testkit::portal::{until, Rig};

/// The token the gateway stored once it has one.
async fn stored_token(rig: &Rig) -> String {
    until(WAIT, "the gateway stores a token", || async {
        rig.gateway_token().is_some()
    })
    .await;
    // The gateway answers once its token is stored, and the portal records it then: a gateway
    // stopped in between never confirmed it (and is a first contact again when it returns).
    until(WAIT, "the portal records the confirmed token", || async {
        portal_token_set(rig).await
    })
    .await;
    rig.gateway_token().expect("a token")
}

/// Whether the portal's registry holds a confirmed token of the lift.
async fn portal_token_set(rig: &Rig) -> bool {
    let url = format!(
        "sqlite://{}",
        rig.dir().join("portal").join("canlift.db").display()
    );
    let pool = sqlx::AnyPool::connect(&url).await.expect("the database");
    let set: Option<i64> = sqlx::query_scalar(
        "SELECT COUNT(*) FROM gateways WHERE id = $1 AND token_hash IS NOT NULL",
    )
    .bind(LIFT)
    .fetch_optional(&pool)
    .await
    .expect("the registry");
    pool.close().await;
    set.unwrap_or(0) > 0
}

/// Refused attempts recorded for the lift.
async fn refusals(rig: &Rig) -> Vec<String> {
    let store = rig.store().await;
    let list = store.refusals(LIFT).await.expect("the refusals");
    list.into_iter().map(|r| r.cause).collect()
}

/// The audit entries of the lift's account with `action`.
async fn audited(rig: &Rig, action: &str) -> Vec<Value> {
    let (status, entries) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    assert_eq!(status, 200, "{entries}");
    let entries = entries.as_array().cloned().unwrap_or_default();
    entries
        .into_iter()
        .filter(|e| e["action"] == action)
        .collect()
}

/// The lift's active alarms.
async fn active_alarms(rig: &Rig) -> Vec<Value> {
    let (status, body) = rig
        .call("GET", "/api/v1/alarms", Some(&rig.key), None)
        .await;
    assert_eq!(status, 200, "{body}");
    body["alarms"].as_array().cloned().unwrap_or_default()
}

/// Stop the gateway and wait until the portal has seen it go (so that the lift's next
/// "online" is the next connection's).
async fn offline(rig: &mut Rig) {
    rig.stop_gateway().await;
    until(WAIT, "the portal sees the gateway go", || async {
        !rig.registry().online(LIFT)
    })
    .await;
}

/// Wait until a connection attempt of the lift was refused for `cause`.
async fn refused_for(rig: &Rig, cause: &str) {
    until(WAIT, &format!("a refusal for {cause:?}"), || async {
        refusals(rig).await.iter().any(|c| c.contains(cause))
    })
    .await;
}

/// The gateway's token file.
fn token_file(rig: &Rig) -> std::path::PathBuf {
    rig.dir().join("gateway").join("cloudtoken")
}

#[tokio::test]
async fn a_wiped_gateway_is_let_in_again_after_a_token_reset() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let first = stored_token(&rig).await;

    // The gateway loses its state: refused, since a token was issued for this lift.
    offline(&mut rig).await;
    std::fs::remove_file(token_file(&rig)).expect("the gateway's token file");
    rig.restart_gateway(|_| {}).await;
    refused_for(&rig, "no cloud token").await;
    assert!(!rig.registry().online(LIFT));
    assert_eq!(rig.metric("canlift_gateways_admitted_total").await, 1.0);
    assert!(rig.metric("canlift_gateways_refused_total").await >= 1.0);
    assert_eq!(
        rig.metric("canlift_gateways_registry_unavailable_total")
            .await,
        0.0
    );
    assert!(rig.metric("canlift_admission_lookups_total").await >= 2.0);

    // Another account cannot reset it; the lift's own can.
    let path = format!("/api/v1/lifts/{LIFT}/token");
    let (status, _) = rig.call("DELETE", &path, Some(&rig.other_key), None).await;
    assert_eq!(status, 404);
    let (status, body) = rig.call("DELETE", &path, Some(&rig.key), None).await;
    assert_eq!(status, 204, "{body}");
    rig.online().await;
    let second = stored_token(&rig).await;
    assert_ne!(first, second, "a new token at the new first contact");
    let resets = audited(&rig, "token reset").await;
    assert_eq!(resets.len(), 1, "{resets:?}");
    assert_eq!(resets[0]["account"], "masora");
    rig.stop().await;
}

#[tokio::test]
async fn a_rotation_changes_the_token_the_gateway_stores() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let first = stored_token(&rig).await;
    let path = format!("/api/v1/lifts/{LIFT}/token");
    let (status, body) = rig.call("POST", &path, Some(&rig.key), None).await;
    assert_eq!(status, 204, "{body}");
    let second = rig.gateway_token().expect("a token");
    assert_ne!(
        first, second,
        "the gateway stored the new token before answering"
    );
    assert_eq!(audited(&rig, "token rotated").await[0]["result"], "ok");

    // The next connection uses it and is admitted; the old token no longer counts.
    offline(&mut rig).await;
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    assert!(refusals(&rig).await.is_empty());
    offline(&mut rig).await;
    std::fs::write(token_file(&rig), &first).expect("the old token written back");
    rig.restart_gateway(|_| {}).await;
    refused_for(&rig, "wrong cloud token").await;

    // Offline: nothing to rotate.
    offline(&mut rig).await;
    let (status, _) = rig.call("POST", &path, Some(&rig.key), None).await;
    assert_eq!(status, 503);
    rig.stop().await;
}

#[tokio::test]
async fn a_token_older_than_token_rotate_days_is_replaced_at_connect() {
    let mut rig = Rig::builder()
        .portal(|c| c.gateways.token_rotate_days = 30)
        .start()
        .await;
    rig.online().await;
    let first = stored_token(&rig).await;
    // Reconnecting with a young token changes nothing.
    offline(&mut rig).await;
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(rig.gateway_token().as_deref(), Some(first.as_str()));

    // The token was confirmed 31 days ago.
    offline(&mut rig).await;
    let url = format!(
        "sqlite://{}",
        rig.dir().join("portal").join("canlift.db").display()
    );
    let pool = sqlx::AnyPool::connect(&url).await.expect("the database");
    let month_ago = cloud_types::now_ms() - 31 * 86_400_000;
    sqlx::query("UPDATE gateways SET token_set = $1")
        .bind(month_ago)
        .execute(&pool)
        .await
        .expect("the token's age set");
    pool.close().await;
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    until(WAIT, "the gateway stores a new token", || async {
        rig.gateway_token().is_some_and(|t| t != first)
    })
    .await;
    offline(&mut rig).await;
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    assert!(refusals(&rig).await.is_empty());
    rig.stop().await;
}

/// Another board with the lift's valid token, under `policy`; whether it got in.
async fn board_swapped(policy: BoardhashChange) -> (Rig, bool) {
    let mut rig = Rig::builder()
        .portal(move |c| c.gateways.boardhash_change = policy)
        .start()
        .await;
    rig.online().await;
    stored_token(&rig).await;
    offline(&mut rig).await;
    rig.restart_gateway(|c| c.identity.boardhash = "B0ARD-2".into())
        .await;
    // A refusal for another cause (a database busy on a loaded machine) is no answer here.
    let admitted = tokio::select! {
        lifts = rig.online() => lifts[0]["online"] == true,
        _ = until(WAIT, "a boardhash refusal", || async {
            refusals(&rig).await.iter().any(|r| r.contains("boardhash"))
        }) => false,
    };
    until(WAIT, "the board change audited", || async {
        !audited(&rig, "board changed").await.is_empty()
    })
    .await;
    // Refused, the gateway tries again after its backoff (0–1 s at first), and each attempt is
    // audited: on a loaded machine a second one may be in by now.
    let changes = audited(&rig, "board changed").await;
    for change in &changes {
        assert_eq!(change["new_value"], "B0ARD-2", "{changes:?}");
        assert_eq!(change["account"], "(portal)", "{changes:?}");
    }
    if admitted {
        assert_eq!(changes.len(), 1, "{changes:?}");
    }
    (rig, admitted)
}

#[tokio::test]
async fn a_board_change_is_refused_alarmed_or_accepted() {
    let (rig, admitted) = board_swapped(BoardhashChange::Refuse).await;
    assert!(!admitted);
    assert!(refusals(&rig).await.iter().any(|r| r.contains("boardhash")));
    assert_eq!(audited(&rig, "board changed").await[0]["result"], "refused");
    // The administrator's reset admits the new board as a first contact.
    let path = format!("/api/v1/lifts/{LIFT}/token");
    assert_eq!(rig.call("DELETE", &path, Some(&rig.key), None).await.0, 204);
    rig.online().await;
    rig.stop().await;

    let (rig, admitted) = board_swapped(BoardhashChange::Alarm).await;
    assert!(admitted);
    let alarms = until(WAIT, "a board-changed alarm", || async {
        !active_alarms(&rig).await.is_empty()
    })
    .await;
    let alarm = active_alarms(&rig).await[0].clone();
    assert_eq!(alarm["kind"], "board-changed", "after {alarms:?}: {alarm}");
    assert_eq!(alarm["code"], "B0ARD-2");
    assert_eq!(alarm["node"], Value::Null);
    // Nothing on the lift ends it; the acknowledgement does.
    let ack = format!("/api/v1/alarms/{}/ack", alarm["id"]);
    let body = json!({"comment": "board replaced by our technician"});
    assert_eq!(
        rig.call("POST", &ack, Some(&rig.key), Some(body)).await.0,
        200
    );
    until(WAIT, "the alarm is cleared", || async {
        active_alarms(&rig).await.is_empty()
    })
    .await;
    rig.stop().await;

    let (rig, admitted) = board_swapped(BoardhashChange::Accept).await;
    assert!(admitted);
    assert_eq!(
        audited(&rig, "board changed").await[0]["result"],
        "accepted"
    );
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(active_alarms(&rig).await.is_empty());
    rig.stop().await;
}
