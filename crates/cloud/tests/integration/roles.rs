//! Users and roles through the REST API (docs/PORTAL.md §Users and roles): every role against
//! every operation (allowed, or 403), elevation per person, and rights taken away reaching the
//! portal within a second.

use std::time::Duration;

use cloud::client::{Body, Reply};
use cloud_types::users::Role;
use serde_json::{json, Value};
use testkit::constants::{LIFT, SERVICE_PASSWORD, WAIT};
use testkit::portal::{until, Rig};

/// User `name` of the lift's account with `role`, and an API key of it.
pub(crate) async fn user(rig: &Rig, name: &str, role: Role) -> String {
    let store = rig.store().await;
    store.add_user("masora", name, role).await.expect("a user");
    store.add_key("masora", name, None).await.expect("a key").1
}

/// One operation of the API and the least role that may do it.
struct Operation {
    method: &'static str,
    path: String,
    body: Option<Value>,
    least: Role,
}

fn operations() -> Vec<Operation> {
    let lift = |tail: &str| format!("/api/v1/lifts/{LIFT}{tail}");
    let op = |method, path: String, body: Option<Value>, least| Operation {
        method,
        path,
        body,
        least,
    };
    let call = json!({"value": "2", "datatype": 7, "physunit": 0});
    let elevate = json!({"privilege": 1, "password": SERVICE_PASSWORD});
    let lantern = json!({"value": "1", "datatype": 5, "physunit": 0});
    vec![
        op("GET", "/api/v1/lifts".into(), None, Role::Viewer),
        op("GET", lift("/objects/0x652001"), None, Role::Viewer),
        op("GET", lift("/objects/0x652001/history"), None, Role::Viewer),
        op("GET", lift("/event-log"), None, Role::Viewer),
        op("GET", "/api/v1/alarms".into(), None, Role::Viewer),
        op("GET", "/api/v1/audit".into(), None, Role::Viewer),
        op(
            "PUT",
            lift("/objects/0x502200"),
            Some(call),
            Role::Technician,
        ),
        op(
            "POST",
            lift("/subscriptions"),
            Some(json!({"mplex": ["0x638301"]})),
            Role::Technician,
        ),
        op(
            "POST",
            "/api/v1/alarms/1/ack".into(),
            Some(json!({"comment": ""})),
            Role::Technician,
        ),
        op("POST", lift("/privilege"), Some(elevate), Role::Engineer),
        op(
            "PUT",
            lift("/objects/0x411200"),
            Some(lantern),
            Role::Engineer,
        ),
        op("POST", lift("/token"), None, Role::Admin),
        op("GET", "/api/v1/users".into(), None, Role::Admin),
        op("GET", "/api/v1/keys".into(), None, Role::Admin),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_role_against_every_operation() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    for role in Role::ALL {
        let key = user(&rig, role.name(), role).await;
        for op in operations() {
            let (status, body) = rig.call(op.method, &op.path, Some(&key), op.body).await;
            let what = format!("{role} {} {}: {status} {body}", op.method, op.path);
            if role < op.least {
                assert_eq!(status, 403, "{what}");
                assert!(
                    body["message"]
                        .as_str()
                        .unwrap_or_default()
                        .contains("role"),
                    "{what}"
                );
            } else {
                // Allowed: done, or refused for another reason than the role (no such alarm).
                assert!(matches!(status, 200 | 204 | 404), "{what}");
            }
        }
    }
    // The account's own key acts as its administrator.
    let (status, _) = rig
        .call(
            "POST",
            &format!("/api/v1/lifts/{LIFT}/token"),
            Some(&rig.key),
            None,
        )
        .await;
    assert_eq!(status, 204);
    rig.stop().await;
}

async fn put_lantern(rig: &Rig, key: &str, value: &str) -> (u16, Value) {
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x411200");
    let body = json!({"value": value, "datatype": 5, "physunit": 0});
    rig.call("PUT", &path, Some(key), Some(body)).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_elevation_is_the_persons_who_entered_the_password() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let ann = user(&rig, "ann", Role::Engineer).await;
    let bob = user(&rig, "bob", Role::Engineer).await;
    let (status, body) = put_lantern(&rig, &ann, "1").await;
    assert_eq!(status, 403, "not elevated yet: {body}");
    let privilege = format!("/api/v1/lifts/{LIFT}/privilege");
    let elevate = json!({"privilege": 1, "password": SERVICE_PASSWORD});
    let (status, body) = rig
        .call("POST", &privilege, Some(&ann), Some(elevate.clone()))
        .await;
    assert_eq!(status, 200, "{body}");

    // Bob rides on nobody's password; Ann writes.
    let (status, body) = put_lantern(&rig, &bob, "2").await;
    assert_eq!(status, 403);
    assert!(
        body["message"]
            .as_str()
            .unwrap()
            .contains("elevated by ann"),
        "{body}"
    );
    assert_eq!(put_lantern(&rig, &ann, "2").await.0, 200);
    // A privilege-0 object needs no elevation.
    let call = json!({"value": "2", "datatype": 7, "physunit": 0});
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x502200");
    assert_eq!(rig.call("PUT", &path, Some(&bob), Some(call)).await.0, 200);

    // The audit shows who elevated and who wrote, and the refusal.
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    let lines: Vec<(String, String, String)> = audit
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["object"] != "0x502200")
        .map(|e| {
            let field = |k: &str| e[k].as_str().unwrap_or_default().to_owned();
            (field("account"), field("action"), field("result"))
        })
        .collect();
    assert_eq!(lines.len(), 4, "{lines:?}");
    assert_eq!(lines[0], ("ann".into(), "put".into(), "ok".into()));
    assert_eq!((lines[1].0.as_str(), lines[1].1.as_str()), ("bob", "put"));
    assert!(lines[1].2.starts_with("refused: "), "{lines:?}");
    assert_eq!(lines[2], ("ann".into(), "elevate".into(), "ok".into()));
    assert!(
        lines[3].2.starts_with("refused: elevate first"),
        "{lines:?}"
    );

    // The gateway reconnects: the grant died with the connection.
    rig.stop_gateway().await;
    until(WAIT, "the lift offline", || async {
        !rig.registry().online(LIFT)
    })
    .await;
    rig.restart_gateway(|_| {}).await;
    rig.online().await;
    let (status, body) = put_lantern(&rig, &ann, "0").await;
    assert_eq!(status, 403);
    assert!(
        body["message"].as_str().unwrap().contains("elevate first"),
        "{body}"
    );
    assert_eq!(
        rig.call("POST", &privilege, Some(&ann), Some(elevate))
            .await
            .0,
        200
    );
    assert_eq!(put_lantern(&rig, &ann, "0").await.0, 200);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rights_taken_away_count_within_a_second() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    let store = rig.store().await;
    let carl = user(&rig, "carl", Role::Technician).await;
    let (id, second) = store.add_key("masora", "carl", None).await.unwrap();
    assert_eq!(
        rig.call("GET", "/api/v1/lifts", Some(&carl), None).await.0,
        200
    );
    assert_eq!(
        rig.call("GET", "/api/v1/lifts", Some(&second), None)
            .await
            .0,
        200
    );

    // A revoked key stops, the user's other key does not.
    store.revoke_key("masora", &id).await.unwrap();
    let took = until(
        Duration::from_secs(5),
        "the revoked key refused",
        || async {
            rig.call("GET", "/api/v1/lifts", Some(&second), None)
                .await
                .0
                == 401
        },
    )
    .await;
    assert!(took < Duration::from_secs(3), "{took:?}");
    assert_eq!(
        rig.call("GET", "/api/v1/lifts", Some(&carl), None).await.0,
        200
    );

    // A lowered role counts, a disabled user's keys stop.
    store
        .set_role("masora", "carl", Role::Viewer)
        .await
        .unwrap();
    let path = format!("/api/v1/lifts/{LIFT}/subscriptions");
    let body = json!({"mplex": ["0x638301"]});
    until(Duration::from_secs(5), "the viewer refused", || async {
        rig.call("POST", &path, Some(&carl), Some(body.clone()))
            .await
            .0
            == 403
    })
    .await;
    store.disable_user("masora", "carl").await.unwrap();
    until(
        Duration::from_secs(5),
        "the disabled user refused",
        || async { rig.call("GET", "/api/v1/lifts", Some(&carl), None).await.0 == 401 },
    )
    .await;
    rig.stop().await;
}

/// The web UI's sign-in form, posted (a user of account masora).
async fn web_sign_in(client: &cloud::client::Client, user: &str, secret: &str) -> Reply {
    let form = [
        ("account", "masora"),
        ("user", user),
        ("secret", secret),
        ("key", ""),
    ];
    let reply = client.exchange("POST", "/login", Body::Form(&form)).await;
    reply.expect("the portal answers")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sign_ins_and_keys_are_throttled() {
    let rig = Rig::builder()
        .without_lift()
        .portal(|c| c.server.requests_per_key_s = 1)
        .start()
        .await;
    let client = cloud::client::Client::new(&rig.url(), None, Some(&rig.ca)).unwrap();
    let secret = rig
        .store()
        .await
        .add_user("masora", "dora", Role::Viewer)
        .await
        .unwrap();
    let sign_in = |secret| web_sign_in(&client, "dora", secret);
    // Five wrong secrets are free; the sixth makes the next attempt wait a second.
    for _ in 0..6 {
        assert_eq!(sign_in("cls_wrong").await.status, 401);
    }
    let throttled = sign_in("cls_wrong").await;
    assert_eq!(throttled.status, 429);
    assert_eq!(throttled.retry_after, Some(1));
    assert!(throttled
        .body
        .as_str()
        .unwrap()
        .contains("try again in 1 s"));
    // Even the right secret waits; then it signs in (303 to the fleet) and the count is over.
    assert_eq!(sign_in(&secret).await.status, 429);
    tokio::time::sleep(Duration::from_millis(1100)).await;
    assert_eq!(sign_in(&secret).await.status, 303);
    assert_eq!(sign_in("cls_wrong").await.status, 401);

    // A key: a burst of two seconds' worth (2), then 429 with Retry-After; whatever refilled
    // while the requests ran (one a second) counts too.
    let keyed = cloud::client::Client::new(&rig.url(), Some(&rig.key), Some(&rig.ca)).unwrap();
    let begin = std::time::Instant::now();
    let mut answered = 0;
    let refused = loop {
        let reply = keyed
            .exchange("GET", "/api/v1/lifts", Body::Empty)
            .await
            .unwrap();
        if reply.status != 200 {
            break reply;
        }
        answered += 1;
        assert!(answered < 50, "never refused");
    };
    assert_eq!((refused.status, refused.retry_after), (429, Some(1)));
    let refilled = begin.elapsed().as_secs() + 1;
    assert!(
        (2..=2 + refilled).contains(&answered),
        "{answered} answered in {:?}",
        begin.elapsed()
    );
    // Another key is not held back by this one.
    let (status, _) = rig
        .call("GET", "/api/v1/lifts", Some(&rig.other_key), None)
        .await;
    assert_eq!(status, 200);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_administrator_manages_users_and_keys_through_the_api() {
    let rig = Rig::builder().without_lift().start().await;
    let admin = user(&rig, "root", Role::Admin).await;
    let call = |method: &'static str, path: &'static str, body: Option<Value>| {
        let admin = admin.clone();
        let rig = &rig;
        async move { rig.call(method, path, Some(&admin), body).await }
    };
    let (status, made) = call(
        "POST",
        "/api/v1/users",
        Some(json!({"name": "tom", "role": "technician"})),
    )
    .await;
    assert_eq!(status, 201, "{made}");
    assert_eq!(
        (&made["user"], &made["role"]),
        (&json!("tom"), &json!("technician"))
    );
    let secret = made["secret"].as_str().unwrap().to_owned();
    let again = json!({"name": "tom", "role": "viewer"});
    assert_eq!(call("POST", "/api/v1/users", Some(again)).await.0, 409);
    let bad = json!({"name": "no spaces please", "role": "viewer"});
    assert_eq!(call("POST", "/api/v1/users", Some(bad)).await.0, 400);
    let client = cloud::client::Client::new(&rig.url(), None, Some(&rig.ca)).unwrap();
    assert_eq!(web_sign_in(&client, "tom", &secret).await.status, 303);

    let (status, key) = call(
        "POST",
        "/api/v1/keys",
        Some(json!({"user": "tom", "expires_days": 90})),
    )
    .await;
    assert_eq!(status, 201, "{key}");
    let tom = key["api_key"].as_str().unwrap().to_owned();
    let (_, keys) = call("GET", "/api/v1/keys", None).await;
    let listed = keys
        .as_array()
        .unwrap()
        .iter()
        .find(|k| k["id"] == key["id"])
        .cloned();
    assert!(
        listed.is_some_and(|k| k["user"] == "tom" && k["expires"].is_i64()),
        "{keys}"
    );
    // Tom may not manage anyone.
    assert_eq!(
        rig.call("GET", "/api/v1/users", Some(&tom), None).await.0,
        403
    );
    assert_eq!(
        rig.call("GET", "/api/v1/lifts", Some(&tom), None).await.0,
        200
    );
    // Revoked: refused within a second or two; another account's admin cannot touch Tom.
    let path = format!("/api/v1/keys/{}", key["id"].as_str().unwrap());
    let (status, _) = rig.call("DELETE", &path, Some(&rig.other_key), None).await;
    assert_eq!(status, 404);
    assert_eq!(rig.call("DELETE", &path, Some(&admin), None).await.0, 204);
    until(
        Duration::from_secs(5),
        "the revoked key refused",
        || async { rig.call("GET", "/api/v1/lifts", Some(&tom), None).await.0 == 401 },
    )
    .await;
    let role = json!({"role": "engineer"});
    let path = "/api/v1/users/tom/role";
    assert_eq!(rig.call("PUT", path, Some(&admin), Some(role)).await.0, 204);
    let (status, reset) = call("POST", "/api/v1/users/tom/reset", None).await;
    assert_eq!((status, &reset["role"]), (200, &json!("engineer")));
    assert_eq!(
        web_sign_in(&client, "tom", &secret).await.status,
        401,
        "the old secret"
    );
    assert_eq!(call("POST", "/api/v1/users/tom/disable", None).await.0, 204);
    let (_, users) = call("GET", "/api/v1/users", None).await;
    assert!(users
        .as_array()
        .unwrap()
        .iter()
        .any(|u| u["name"] == "tom" && u["disabled"] == true));
    let fresh = reset["secret"].as_str().unwrap();
    assert_eq!(
        web_sign_in(&client, "tom", fresh).await.status,
        401,
        "disabled"
    );
    rig.stop().await;
}
