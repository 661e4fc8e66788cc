//! The operator CLI against a running portal, gateway and simulated lift: `lifts`, `get`, `put`
//! (learning datatype and unit first), `watch` until the trip counter rises, `alarms`, `events`,
//! and the cloud token: `token rotate|reset`, `cloud token reset` on the portal's machine; a
//! cluster's NATS user key: `cloud nats-nkey`.

use std::time::Duration;

use testkit::constants::LIFT;
use testkit::portal::Rig;
use tokio::io::{AsyncBufReadExt, BufReader};

use crate::common;

/// `canlift` for the rig's portal, key and CA.
fn canlift(rig: &Rig) -> tokio::process::Command {
    let mut cmd = common::canlift();
    cmd.env("CANLIFT_PORTAL", rig.url())
        .env("CANLIFT_API_KEY", &rig.key)
        .env("CANLIFT_CA", &rig.ca);
    cmd
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lifts_get_put_watch() {
    let rig = Rig::builder().start().await;
    let lift = LIFT;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let out = canlift(&rig)
            .args(["lifts", "--json"])
            .output()
            .await
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let lifts: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        if lifts[0]["online"] == true {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "not online: {lifts}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let table = canlift(&rig).arg("lifts").output().await.unwrap();
    assert!(String::from_utf8_lossy(&table.stdout).contains(LIFT));
    let get = canlift(&rig)
        .args(["get", lift, "0x652001", "--naked"])
        .output()
        .await
        .unwrap();
    let answer: serde_json::Value = serde_json::from_slice(&get.stdout).unwrap();
    assert_eq!(answer["object"]["value"][0], "0");
    // The same object by its address form and by its catalog name.
    for object in ["0x6520:1", "trip counter"] {
        let get = canlift(&rig)
            .args(["get", lift, object, "--naked"])
            .output()
            .await
            .unwrap();
        assert!(
            get.status.success(),
            "{object}: {}",
            String::from_utf8_lossy(&get.stderr)
        );
        let by_name: serde_json::Value = serde_json::from_slice(&get.stdout).unwrap();
        assert_eq!(by_name["object"]["mplex"], "0x652001", "{object}");
    }
    // watch first, then call the car: the baseline and the new trip count come out.
    let mut watch = canlift(&rig)
        .args(["watch", lift, "0x652001", "--count", "2"])
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(watch.stdout.take().unwrap()).lines();
    let first = tokio::time::timeout(Duration::from_secs(10), lines.next_line())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(first.ends_with(" 0x652001 0"), "{first}");
    let put = canlift(&rig)
        .args(["put", lift, "0x502200", "2"])
        .output()
        .await
        .unwrap();
    assert!(
        put.status.success(),
        "{}",
        String::from_utf8_lossy(&put.stderr)
    );
    let second = tokio::time::timeout(Duration::from_secs(15), lines.next_line())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(second.ends_with(" 0x652001 1"), "{second}");
    assert!(tokio::time::timeout(Duration::from_secs(5), watch.wait())
        .await
        .unwrap()
        .unwrap()
        .success());
    // Errors are reported with the abort code.
    let refused = canlift(&rig)
        .args(["put", lift, "0x652001", "5"])
        .output()
        .await
        .unwrap();
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("06010002h"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
    rig.stop().await;
}

/// Run `canlift ARGS` for the rig; its standard output.
async fn output(rig: &Rig, args: &[&str]) -> String {
    let out = canlift(rig).args(args).output().await.unwrap();
    assert!(
        out.status.success(),
        "canlift {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn alarms_ack_and_events() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    assert!(output(&rig, &["alarms"]).await.contains("no active alarm"));
    // A drive fault in the simulator (setup rights for 5030h).
    let privilege =
        serde_json::json!({"privilege": 2, "password": testkit::constants::SETUP_PASSWORD});
    let (status, _) = rig
        .call(
            "POST",
            &format!("/api/v1/lifts/{LIFT}/privilege"),
            Some(&rig.key),
            Some(privilege),
        )
        .await;
    assert_eq!(status, 200);
    assert!(output(&rig, &["put", LIFT, "0x503000", "4"])
        .await
        .contains("= 4"));
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    let alarms: serde_json::Value = loop {
        let list: serde_json::Value =
            serde_json::from_str(&output(&rig, &["alarms", "--json"]).await).unwrap();
        if !list["alarms"].as_array().unwrap().is_empty() {
            break list;
        }
        assert!(tokio::time::Instant::now() < deadline, "no alarm: {list}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let id = alarms["alarms"][0]["id"].as_i64().unwrap().to_string();
    let table = output(&rig, &["alarms"]).await;
    assert!(
        table.contains(&id) && table.contains("major") && table.contains("Drive fault"),
        "{table}"
    );
    let acked = output(&rig, &["alarms", "ack", &id, "--comment", "checked"]).await;
    assert!(acked.contains("acknowledged by masora"), "{acked}");
    let events = output(&rig, &["events", LIFT]).await;
    assert!(events.contains("EMCY  node 1/1 0xF001"), "{events}");
    let json: serde_json::Value =
        serde_json::from_str(&output(&rig, &["events", LIFT, "--json", "--limit", "1"]).await)
            .unwrap();
    assert_eq!(json["events"].as_array().unwrap().len(), 1);
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_rotate_and_reset() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    let tokens = || rig.gateway_token();
    testkit::portal::until(Duration::from_secs(10), "a token", || async {
        tokens().is_some()
    })
    .await;
    let first = tokens();
    let rotated = output(&rig, &["token", "rotate", LIFT]).await;
    assert!(rotated.contains("stored a new token"), "{rotated}");
    assert_ne!(tokens(), first);
    let reset = output(&rig, &["token", "reset", LIFT]).await;
    assert!(reset.contains("first contact"), "{reset}");
    let unknown = canlift(&rig)
        .args(["token", "rotate", "1-2-3"])
        .output()
        .await
        .unwrap();
    assert!(!unknown.status.success());
    assert!(String::from_utf8_lossy(&unknown.stderr).contains("404"));

    // On the portal's machine, with its configuration and no API key.
    let config = rig.dir().join("cloud.toml");
    let state = rig.dir().join("portal");
    std::fs::write(
        &config,
        format!("[state]\ndir = {:?}\n", state.display().to_string()),
    )
    .unwrap();
    let config = config.display().to_string();
    let local = |lift: &'static str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_canlift"))
            .args(["cloud", "token", "reset", lift, "--config", &config])
            .output()
            .unwrap()
    };
    let out = local(LIFT);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("token forgotten"));
    let out = local("1-2-3");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no lift"));
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    let actions: Vec<(&str, &str)> = audit
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["action"].as_str().unwrap(),
                e["account"].as_str().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        actions,
        [
            ("token reset", "(administrator)"),
            ("token reset", "masora"),
            ("token rotated", "masora")
        ]
    );
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn users_and_keys_on_the_command_line() {
    let rig = Rig::builder().start().await;
    rig.online().await;
    let config = rig.dir().join("cloud.toml");
    let state = rig.dir().join("portal").display().to_string();
    std::fs::write(&config, format!("[state]\ndir = {state:?}\n")).unwrap();
    let config = config.display().to_string();
    let admin = |args: &str| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_canlift"))
            .arg("cloud")
            .args(args.split_whitespace())
            .args(["--config", &config])
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        (out.status.success(), stdout, stderr)
    };
    let (ok, out, err) = admin("user add tess --account masora --role technician --json");
    assert!(ok, "{err}");
    let added: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(
        (&added["user"], &added["account"], &added["role"]),
        (&"tess".into(), &"masora".into(), &"technician".into())
    );
    assert!(added["secret"].as_str().unwrap().starts_with("cls_"));
    let (ok, _, err) = admin("user add tess --account masora --role viewer");
    assert!(!ok && err.contains("has a user"), "{err}");
    let (ok, _, err) = admin("user add x --account masora --role boss");
    assert!(!ok && err.contains("no role"), "{err}");

    let (ok, out, err) = admin("key add --account masora --user tess --expires 90d --json");
    assert!(ok, "{err}");
    let key: serde_json::Value = serde_json::from_str(&out).unwrap();
    let (api_key, id) = (
        key["api_key"].as_str().unwrap(),
        key["id"].as_str().unwrap(),
    );
    let lifts = |key: &str| {
        let mut cmd = common::canlift();
        cmd.env("CANLIFT_PORTAL", rig.url())
            .env("CANLIFT_API_KEY", key)
            .env("CANLIFT_CA", &rig.ca)
            .args(["lifts", "--json"]);
        cmd
    };
    assert!(lifts(api_key).output().await.unwrap().status.success());
    let (ok, out, _) = admin("user list --account masora");
    assert!(ok && out.contains("tess") && out.contains("technician") && out.contains("enabled"));
    let (ok, out, _) = admin("key list --account masora");
    assert!(ok && out.contains(id) && out.contains("valid"), "{out}");

    // Revoked: refused by the running portal within a second or two.
    let (ok, _, err) = admin(&format!("key revoke {id} --account masora"));
    assert!(ok, "{err}");
    testkit::portal::until(
        Duration::from_secs(5),
        "the revoked key refused",
        || async {
            let out = lifts(api_key).output().await.unwrap();
            !out.status.success() && String::from_utf8_lossy(&out.stderr).contains("401")
        },
    )
    .await;
    let (ok, out, _) = admin("user reset tess --account masora --json");
    assert!(ok && out.contains("cls_"), "{out}");
    let (ok, _, _) = admin("user role tess --account masora --role engineer");
    assert!(ok);
    let (ok, _, _) = admin("user disable tess --account masora");
    assert!(ok);
    let (ok, out, _) = admin("user list --account masora --json");
    assert!(ok);
    let users: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(users[0]["role"], "engineer");
    assert_eq!(users[0]["disabled"], true);
    rig.stop().await;
}

/// `canlift cloud nats-nkey FILE` writes a NATS user's seed that its owner alone may read and
/// prints the public key it signs as (what the NATS server lists); an existing file is kept.
#[tokio::test]
async fn a_nats_user_key_for_its_owner_alone() {
    use std::os::unix::fs::PermissionsExt;
    let dir = testkit::scratch();
    let file = dir.path().join("nats.nk");
    let make = || {
        common::canlift()
            .args(["cloud", "nats-nkey"])
            .arg(&file)
            .output()
    };
    let made = make().await.expect("canlift runs");
    assert!(made.status.success(), "{made:?}");
    let public = String::from_utf8_lossy(&made.stdout).trim().to_owned();
    let seed = std::fs::read_to_string(&file).expect("the seed file");
    let pair = nkeys::KeyPair::from_seed(seed.trim()).expect("an NKey seed");
    assert_eq!(pair.key_pair_type(), nkeys::KeyPairType::User);
    assert_eq!(pair.public_key(), public);
    let mode = std::fs::metadata(&file)
        .expect("metadata")
        .permissions()
        .mode();
    assert_eq!(mode & 0o777, 0o600, "{mode:o}");

    let again = make().await.expect("canlift runs");
    assert!(!again.status.success());
    let said = String::from_utf8_lossy(&again.stderr);
    assert!(said.contains("an existing file is kept"), "{said}");
    assert_eq!(std::fs::read_to_string(&file).expect("the seed file"), seed);
}

/// The operator commands' exit statuses tell what went wrong apart (docs/PORTAL.md §Command-line
/// client), and their text output shows local times, not epoch milliseconds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exit_statuses_tell_failures_apart() {
    let mut rig = Rig::builder().start().await;
    rig.online().await;
    let (url, key, ca) = (rig.url(), rig.key.clone(), rig.ca.clone());
    let status = |args: &'static [&'static str], wrong_key: Option<&'static str>| {
        let mut cmd = common::canlift();
        cmd.env("CANLIFT_PORTAL", &url)
            .env("CANLIFT_API_KEY", wrong_key.unwrap_or(&key))
            .env("CANLIFT_CA", &ca);
        async move { cmd.args(args).output().await.unwrap().status.code() }
    };
    assert_eq!(status(&["lifts"], None).await, Some(0));
    let table = canlift(&rig).arg("lifts").output().await.unwrap();
    let table = String::from_utf8_lossy(&table.stdout).into_owned();
    let row = table
        .lines()
        .find(|l| l.starts_with(LIFT))
        .unwrap_or_default();
    let year = row
        .split_whitespace()
        .find(|w| w.len() == 10 && w.starts_with("20"));
    assert!(year.is_some(), "a local date in {row:?}");
    assert_eq!(status(&["get"], None).await, Some(2), "usage");
    assert_eq!(
        status(&["get", "1050-4096-NOSUCHLIFT", "0x652001"], None).await,
        Some(3),
        "not found"
    );
    assert_eq!(
        status(&["get", LIFT, "0x652001"], Some("clk_wrong")).await,
        Some(4),
        "not allowed"
    );
    // 6520h sub 1 (the car position) is read-only: the lift refuses the write.
    assert_eq!(
        status(&["put", LIFT, "0x652001", "7"], None).await,
        Some(5),
        "refused by the lift"
    );
    rig.stop_gateway().await;
    assert_eq!(
        status(&["get", LIFT, "0x652001"], None).await,
        Some(6),
        "the lift offline"
    );
    let nowhere = canlift(&rig)
        .env(
            "CANLIFT_PORTAL",
            format!("https://localhost:{}", testkit::free_port()),
        )
        .args(["lifts"])
        .output()
        .await
        .unwrap();
    assert_eq!(nowhere.status.code(), Some(6), "the portal unreachable");
    rig.stop().await;
}

/// JSON log lines name the service and the version, and their fields keep their types.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn json_logs_are_typed_and_name_their_service() {
    let mut hub = common::canlift()
        .env("CANLIFT_LOG_FORMAT", "json")
        .args(["hub", "--listen", "127.0.0.1:0"])
        .spawn()
        .expect("the hub starts");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let status = common::interrupt(&mut hub, Duration::from_secs(10)).await;
    assert!(status.success());
    let out = hub.wait_with_output().await.unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let lines: Vec<serde_json::Value> = stderr
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect();
    assert!(lines.len() >= 2, "{stderr}");
    for line in &lines {
        assert_eq!(line["service"], "hub", "{line}");
        assert_eq!(line["version"], env!("CARGO_PKG_VERSION"), "{line}");
        for (name, value) in line.as_object().into_iter().flatten() {
            let debug = value
                .as_str()
                .is_some_and(|s| s.starts_with("Some(") || s == "None");
            assert!(!debug, "{name} is Debug-formatted: {line}");
        }
    }
    let stopped = lines
        .iter()
        .find(|l| l["message"] == "hub stopped")
        .expect("hub stopped");
    assert!(
        stopped["frames_in"].is_u64(),
        "a number stays a number: {stopped}"
    );
}

/// The operator commands go through `HTTPS_PROXY` (a CONNECT tunnel, TLS end to end) unless
/// `NO_PROXY` names the portal.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operators_reach_the_portal_through_https_proxy() {
    let Some(proxy) = testkit::proxy::Tinyproxy::start(&[]) else {
        return;
    };
    let rig = Rig::builder().without_lift().start().await;
    let through = canlift(&rig)
        .env("HTTPS_PROXY", proxy.url())
        .env_remove("NO_PROXY")
        .args(["lifts", "--json"])
        .output()
        .await
        .unwrap();
    assert!(through.status.success(), "{}", common::stderr(&through));
    let port = rig.url().rsplit(':').next().unwrap_or_default().to_owned();
    let tunnelled = proxy.log();
    assert!(tunnelled.contains(&format!(":{port}")), "{tunnelled}");
    let direct = canlift(&rig)
        .env("HTTPS_PROXY", proxy.url())
        .env("NO_PROXY", "localhost")
        .args(["lifts", "--json"])
        .output()
        .await
        .unwrap();
    assert!(direct.status.success(), "{}", common::stderr(&direct));
    assert_eq!(
        proxy.log().matches("CONNECT").count(),
        tunnelled.matches("CONNECT").count()
    );
    rig.stop().await;
}

/// `canlift elevate` from the command line: a wrong password is the lift's refusal (exit 5), the
/// right one (from the environment, or standard input) grants the rights, and the write that
/// needed them goes through.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn elevate_then_put_a_service_object() {
    use testkit::constants::SERVICE_PASSWORD;
    let rig = Rig::builder().start().await;
    rig.online().await;
    // 4113h (door open time) needs service rights.
    let put = || canlift(&rig).args(["put", LIFT, "0x411300", "4"]).output();
    let refused = put().await.unwrap();
    assert_eq!(
        refused.status.code(),
        Some(4),
        "{}",
        common::stderr(&refused)
    );
    assert!(common::stderr(&refused).contains("elevate first"));
    let wrong = canlift(&rig)
        .args(["elevate", LIFT, "--level", "service"])
        .env("CANLIFT_LIFT_PASSWORD", "not it")
        .output()
        .await
        .unwrap();
    assert_eq!(wrong.status.code(), Some(5), "{}", common::stderr(&wrong));
    // The password on standard input, as a script would pipe it.
    let mut elevate = canlift(&rig)
        .args(["elevate", LIFT, "--level", "service"])
        .env_remove("CANLIFT_LIFT_PASSWORD")
        .stdin(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    use tokio::io::AsyncWriteExt;
    let mut stdin = elevate.stdin.take().expect("piped");
    stdin
        .write_all(format!("{SERVICE_PASSWORD}\n").as_bytes())
        .await
        .unwrap();
    drop(stdin);
    let granted = elevate.wait_with_output().await.unwrap();
    assert!(granted.status.success(), "{}", common::stderr(&granted));
    let said = String::from_utf8_lossy(&granted.stdout);
    assert!(
        said.starts_with(&format!("{LIFT}: service rights for ")),
        "{said}"
    );
    let written = put().await.unwrap();
    assert!(written.status.success(), "{}", common::stderr(&written));
    rig.stop().await;
}
