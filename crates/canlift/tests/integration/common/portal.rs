//! A portal process for the tests that kill and start it, alone or as one of a cluster.

use std::path::{Path, PathBuf};
use std::time::Duration;

use tokio::net::TcpStream;
use tokio::process::Child;

use testkit::constants::METRICS_TOKEN;
use testkit::free_port;

use super::{daemon, kill, run, stderr};

/// A portal process (`canlift cloud`) with its state in a directory of its own, SQLite by
/// default, on a fixed port so it can be killed and started again where its gateways look.
pub struct PortalProcess {
    /// The CA its certificate is of (the development CA unless the configuration names one).
    pub ca: PathBuf,
    pub config: PathBuf,
    pub state: PathBuf,
    pub port: u16,
    pub child: Option<Child>,
}

impl PortalProcess {
    /// Configure (account `load` for domain `LOAD`; `extra` TOML appended) and start; returns
    /// it and the API key.
    pub async fn start(dir: &Path, extra: &str) -> (PortalProcess, String) {
        let mut portal = PortalProcess::configure(dir, extra);
        let key = portal.add_account("load", "LOAD").await;
        portal.restart().await;
        (portal, key)
    }

    /// Write the configuration (state in `dir/portal`, a free loopback port, `extra` TOML
    /// appended: keys before a section header belong to `[server]`); not started yet.
    pub fn configure(dir: &Path, extra: &str) -> PortalProcess {
        let state = dir.join("portal");
        let port = free_port();
        let config = dir.join("portal.toml");
        std::fs::create_dir_all(dir).expect("the portal's directory");
        std::fs::write(
            &config,
            format!(
                "[state]\ndir = \"{}\"\n[server]\nlisten = \"127.0.0.1:{port}\"\nmetrics_token = \"{METRICS_TOKEN}\"\n{extra}",
                state.display()
            ),
        )
        .expect("written");
        PortalProcess {
            ca: state.join("dev-ca.pem"),
            config,
            state,
            port,
            child: None,
        }
    }

    /// `canlift cloud account add NAME --domain DOMAIN` (a short one, as the load generator's):
    /// the new account's API key.
    pub async fn add_account(&self, name: &str, domain: &str) -> String {
        let config = self.config.to_str().expect("UTF-8");
        let out = run(&[
            "cloud",
            "account",
            "add",
            name,
            "--domain",
            domain,
            "--allow-short-domain-token",
            "--json",
            "--config",
            config,
        ])
        .await;
        assert!(out.status.success(), "{}", stderr(&out));
        let account: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
        account["api_key"].as_str().expect("a key").to_owned()
    }

    /// Start the process again (after a kill) and wait until it listens.
    pub async fn restart(&mut self) {
        let config = self.config.to_str().expect("UTF-8");
        self.child = Some(daemon(&["cloud", "--config", config]));
        self.wait_listening().await;
    }

    /// Start the process again with at most `files` open files (`ulimit -n`) and wait until it
    /// listens; the lines of its standard error (`RUST_LOG=warn`).
    pub async fn restart_with_files(
        &mut self,
        files: u32,
    ) -> tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStderr>> {
        use tokio::io::AsyncBufReadExt;
        let config = self.config.to_str().expect("UTF-8");
        let mut child = tokio::process::Command::new("sh")
            .args(["-c", "ulimit -n \"$0\" && exec \"$@\""])
            .arg(files.to_string())
            .arg(env!("CARGO_BIN_EXE_canlift"))
            .args(["cloud", "--config", config])
            .env("RUST_LOG", "warn")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .expect("sh and canlift start");
        let stderr = child.stderr.take().expect("stderr");
        self.child = Some(child);
        self.wait_listening().await;
        tokio::io::BufReader::new(stderr).lines()
    }

    async fn wait_listening(&self) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        while TcpStream::connect(("127.0.0.1", self.port)).await.is_err() {
            assert!(
                tokio::time::Instant::now() < deadline,
                "the portal listens within 30 s"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// SIGKILL: no shutdown, no flush, nothing the process could still do.
    pub async fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            kill(&mut child).await;
        }
    }

    pub fn ca(&self) -> PathBuf {
        self.ca.clone()
    }

    pub fn database(&self) -> PathBuf {
        self.state.join("canlift.db")
    }

    /// An operator client of this portal.
    pub fn client(&self, key: &str) -> cloud::client::Client {
        let url = format!("https://localhost:{}", self.port);
        cloud::client::Client::new(&url, Some(key), Some(&self.ca())).expect("a client")
    }

    /// How many of the account's lifts the portal reports online (0 while it does not answer).
    pub async fn online(&self, key: &str) -> usize {
        match self.client(key).call("GET", "/api/v1/lifts", None).await {
            Ok((200, serde_json::Value::Array(lifts))) => {
                lifts.iter().filter(|l| l["online"] == true).count()
            }
            _ => 0,
        }
    }

    /// Wait until `count` lifts are online; how long it took.
    pub async fn wait_online(&self, key: &str, count: usize, limit: Duration) -> Duration {
        let begin = tokio::time::Instant::now();
        loop {
            let online = self.online(key).await;
            if online == count {
                return begin.elapsed();
            }
            assert!(
                begin.elapsed() < limit,
                "{online} of {count} lifts online after {limit:?}"
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// `canlift_telemetry_stored_total` from `/metrics`: values the portal has written to its
    /// database (the counter moves after the transaction committed).
    pub async fn stored(&self) -> u64 {
        self.metric("canlift_telemetry_stored_total").await
    }

    /// One counter or gauge from `/metrics`.
    pub async fn metric(&self, name: &str) -> u64 {
        let value = self.client(METRICS_TOKEN).metric(name).await;
        match value {
            Ok(Some(v)) => v as u64,
            other => panic!("/metrics, {name}: {other:?}"),
        }
    }

    /// Rows in the telemetry table and the result of SQLite's `integrity_check`.
    pub async fn inspect(&self) -> (u64, String) {
        use sqlx::{Connection, Row};
        let url = format!("sqlite://{}", self.database().display());
        let mut db = sqlx::SqliteConnection::connect(&url)
            .await
            .expect("the portal's database opens");
        let check: String = sqlx::query("PRAGMA integrity_check")
            .fetch_one(&mut db)
            .await
            .expect("integrity_check")
            .get(0);
        let rows: i64 = sqlx::query("SELECT COUNT(*) FROM telemetry")
            .fetch_one(&mut db)
            .await
            .expect("count")
            .get(0);
        let _ = db.close().await;
        (u64::try_from(rows).unwrap_or(0), check)
    }
}
