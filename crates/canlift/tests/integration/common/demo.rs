//! `canlift demo` as a user starts it, on ports of its own and a state directory of the
//! test's: what its banner prints (portal, API key, CA, bus) and a client of its portal.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use cloud::client::Client;
use tokio::io::{AsyncBufReadExt, BufReader};

use super::canlift;

/// A running demo.
pub struct Demo {
    pub child: tokio::process::Child,
    pub client: Client,
    /// The portal's URL, API key, CA file and bus URL, as the banner prints them.
    pub portal: String,
    pub key: String,
    pub ca: PathBuf,
    pub bus: String,
}

/// Start `canlift demo --state STATE` (10 × speed, no simulated passengers) and read its
/// banner; its further output is drained.
pub async fn start(state: &Path) -> Demo {
    let mut child = canlift()
        .args(["demo", "--speed", "10", "--passengers", "0"])
        .args([
            "--hub-listen",
            "127.0.0.1:0",
            "--portal-listen",
            "127.0.0.1:0",
            "--state",
        ])
        .arg(state)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let mut printed = HashMap::new();
    let mut example = None;
    while printed.len() < 4 || example.is_none() {
        let line = tokio::time::timeout(Duration::from_secs(60), lines.next_line())
            .await
            .expect("the demo prints its summary")
            .unwrap()
            .expect("the demo is running");
        if line.contains(" get ") {
            example = Some(line.clone());
        }
        let mut words = line.split_whitespace();
        if let (Some(k @ ("portal" | "API" | "CA" | "bus")), Some(v)) = (words.next(), words.next())
        {
            let v = if k == "API" {
                words.next().unwrap_or_default()
            } else {
                v
            };
            printed.insert(k.to_owned(), v.to_owned());
        }
    }
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
    // The example commands name a binary the user can run: `canlift` on the PATH, else its path.
    let example = example.unwrap_or_default();
    let command = example.split_whitespace().next().unwrap_or_default();
    let runs_this = command == "canlift"
        || std::fs::canonicalize(command).ok()
            == std::fs::canonicalize(env!("CARGO_BIN_EXE_canlift")).ok();
    assert!(
        runs_this,
        "the banner's example does not run this binary: {example}"
    );
    let ca = PathBuf::from(&printed["CA"]);
    let client = Client::new(&printed["portal"], Some(&printed["API"]), Some(&ca)).unwrap();
    Demo {
        child,
        client,
        portal: printed["portal"].clone(),
        key: printed["API"].clone(),
        ca,
        bus: printed["bus"].clone(),
    }
}
