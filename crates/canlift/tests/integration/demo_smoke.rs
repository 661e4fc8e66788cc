//! The README's first command, as CI runs it: `canlift demo` with a temporary state directory;
//! the lift comes online through the REST API, 0x652001 reads, a passenger call to floor 3 makes
//! the trip counter rise, Ctrl-C stops everything cleanly, and a second run keeps the counters;
//! schemathesis finds the demo's API as its OpenAPI document says.

use std::time::Duration;

use cloud::client::Client;
use serde_json::json;

use crate::common;
use common::demo::{start, Demo};
use common::interrupt;

const LIFT: &str = "1050-4096-DEMO-0001";

async fn trips(client: &Client) -> u64 {
    let (status, v) = client
        .call(
            "GET",
            &format!("/api/v1/lifts/{LIFT}/objects/0x652001?form=naked"),
            None,
        )
        .await
        .unwrap();
    assert_eq!(status, 200, "{v}");
    v["object"]["value"][0].as_str().unwrap().parse().unwrap()
}

async fn online(client: &Client) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let (status, lifts) = client.call("GET", "/api/v1/lifts", None).await.unwrap();
        if status == 200 && lifts[0]["online"] == true {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the demo lift never came online: {lifts}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

async fn stop(mut demo: Demo) {
    let status = interrupt(&mut demo.child, Duration::from_secs(20)).await;
    assert!(status.success(), "the demo stops after Ctrl-C: {status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_demo_runs_a_lift_end_to_end() {
    let scratch = testkit::scratch();
    let state = scratch.path();
    let demo = start(state).await;
    online(&demo.client).await;
    // The web UI is served on the same port: the sign-in page.
    let (status, page) = demo.client.call("GET", "/login", None).await.unwrap();
    assert_eq!(status, 200);
    assert!(
        page.as_str().is_some_and(|p| p.contains("Sign in")),
        "{page}"
    );
    let before = trips(&demo.client).await;
    let put = json!({"value": "3", "datatype": 7, "physunit": 0});
    let (status, answer) = demo
        .client
        .call(
            "PUT",
            &format!("/api/v1/lifts/{LIFT}/objects/0x502200"),
            Some(put),
        )
        .await
        .unwrap();
    assert_eq!(
        (status, answer),
        (200, json!({"object": {"mplex": "0x502200"}}))
    );
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let after = loop {
        let now = trips(&demo.client).await;
        if now > before {
            break now;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the trip counter did not rise"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    stop(demo).await;
    // Every secret the demo wrote is its owner's alone, from the start.
    let secrets = secret_files(state);
    let names: Vec<String> = secrets
        .iter()
        .filter_map(|p| p.file_name()?.to_str().map(str::to_owned))
        .collect();
    for expected in ["api-key", "lift-passwords", "cloudtoken", "dev-server.key"] {
        assert!(
            names.iter().any(|n| n == expected),
            "{expected} in {names:?}"
        );
    }
    for path in &secrets {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600, "{}", path.display());
    }
    // Later runs reuse the state: same account, same token, the counters keep counting.
    let demo = start(state).await;
    online(&demo.client).await;
    assert!(trips(&demo.client).await >= after);
    stop(demo).await;
}

/// The files under `dir` that hold secrets: keys, tokens, passwords.
fn secret_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut found = Vec::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for entry in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let path = entry.path();
            if path.is_dir() {
                dirs.push(path);
                continue;
            }
            let name = path
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or_default();
            let secret = matches!(
                name,
                "api-key" | "lift-passwords" | "cloudtoken" | "tls-ticket-keys"
            ) || name.ends_with(".key");
            if secret {
                found.push(path);
            }
        }
    }
    found
}

/// schemathesis (PyPI, pinned in the interop venv) with every check (`--checks all`) against the
/// demo's served OpenAPI document: no request the document allows is refused by the portal
/// itself, none it forbids is taken, every answer is documented with its schema (Server-Sent
/// Events too), no 5xx; the seed and what the lift decides are in tests/interop/schemathesis.toml.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn schemathesis_finds_the_api_as_documented() {
    let Some(python) = testkit::python() else {
        return;
    };
    let schemathesis = python.with_file_name("schemathesis");
    assert!(
        schemathesis.is_file(),
        "{} is missing: scripts/test installs tests/interop/requirements.txt",
        schemathesis.display()
    );
    let state = testkit::scratch();
    let mut demo = start(state.path()).await;
    online(&demo.client).await;
    let out = tokio::process::Command::new(&schemathesis)
        // Its cache (crashes it replays first) in the scratch directory: each run starts from
        // the seed alone, and nothing is written into the source tree.
        .current_dir(state.path())
        .arg("--config-file")
        .arg(testkit::workspace().join("tests/interop/schemathesis.toml"))
        .arg("--no-color")
        .args(["run", &format!("{}/api/v1/openapi.json", demo.portal)])
        .args(["--checks", "all", "--tls-verify", "false", "--workers", "1"])
        .args(["-H", &format!("Authorization: Bearer {}", demo.key)])
        .output()
        .await
        .expect("schemathesis runs");
    let report = String::from_utf8_lossy(&out.stdout);
    let summary = report.rsplit("SUMMARY").next().unwrap_or_default().trim();
    println!("{summary}");
    assert!(
        out.status.success(),
        "schemathesis found breaches:\n{report}"
    );
    let operations: usize = cloud::api::document()
        .paths
        .paths
        .values()
        .map(|item| {
            [&item.get, &item.put, &item.post, &item.delete]
                .into_iter()
                .flatten()
                .count()
        })
        .sum();
    let all = format!("{operations}/{operations}");
    assert!(
        report.contains(&all) && !report.contains(" failed"),
        "every operation ({all}) tested, none failed:\n{summary}"
    );
    interrupt(&mut demo.child, Duration::from_secs(30)).await;
}
