//! A NATS server of the test's own (Debian's `nats-server` with JetStream, on a loopback port,
//! its storage in a scratch directory) for the cluster tests; stopped when dropped, and
//! stoppable and startable again on the same port for the tests of NATS outages.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// A running (or stopped) `nats-server -js`.
pub struct Nats {
    port: u16,
    store: tempfile::TempDir,
    /// More command-line options (authentication, TLS).
    options: Vec<String>,
    child: Option<Child>,
}

impl Nats {
    /// Start a server, or `None` after printing why the test is skipped (no `nats-server` on
    /// the PATH; with CANLIFT_REQUIRE_NATS=1 the test fails instead).
    pub fn start() -> Option<Nats> {
        Nats::start_with(&[])
    }

    /// The same with more command-line options, such as `--user`, `--pass`, `--tls…`.
    pub fn start_with(options: &[&str]) -> Option<Nats> {
        if Command::new("nats-server")
            .arg("--version")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_err()
        {
            return crate::unavailable(
                "CANLIFT_REQUIRE_NATS",
                "nats: no nats-server on the PATH (apt-get install nats-server)",
            );
        }
        let port = crate::free_port();
        let mut nats = Nats {
            port,
            store: crate::scratch(),
            options: options.iter().map(|o| o.to_string()).collect(),
            child: None,
        };
        nats.start_again();
        Some(nats)
    }

    /// The port it listens on (127.0.0.1).
    pub fn port(&self) -> u16 {
        self.port
    }

    /// `nats://127.0.0.1:PORT`.
    pub fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }

    /// Stop the server (SIGKILL: as a crash or a lost link would look to its clients).
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Have the running server read its configuration file again (`nats-server --signal
    /// reload`): its clients stay connected, under the permissions now configured.
    pub fn reload(&self) {
        let pid = self.child.as_ref().expect("a running nats-server").id();
        let status = Command::new("nats-server")
            .arg("--signal")
            .arg(format!("reload={pid}"))
            .status()
            .expect("nats-server --signal runs");
        assert!(status.success(), "nats-server --signal reload={pid}");
    }

    /// Start the stopped server again on the same port, and wait until it listens.
    pub fn start_again(&mut self) {
        self.stop();
        // Its log (what it says when a configuration stops it) for the assertion below.
        let log_path = self.store.path().join("nats-server.log");
        let log = std::fs::File::create(&log_path).expect("a log file in the scratch directory");
        let child = Command::new("nats-server")
            .args([
                "-js",
                "-a",
                "127.0.0.1",
                "-p",
                &self.port.to_string(),
                "-sd",
            ])
            .arg(self.store.path())
            .args(&self.options)
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("nats-server starts");
        self.child = Some(child);
        let begin = std::time::Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(
                begin.elapsed() < Duration::from_secs(10),
                "nats-server listens within 10 s; its log:\n{}",
                std::fs::read_to_string(&log_path).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.stop();
    }
}

/// `count` servers forming one NATS cluster with JetStream (a bucket of several replicas lives
/// on several of them), each with its monitoring port; `None` as [`Nats::start`].
pub fn cluster(count: usize) -> Option<Vec<(Nats, u16)>> {
    let routes: Vec<u16> = (0..count).map(|_| crate::free_port()).collect();
    let all = routes
        .iter()
        .map(|port| format!("nats://127.0.0.1:{port}"))
        .collect::<Vec<_>>()
        .join(",");
    (0..count)
        .map(|i| {
            let monitor = crate::free_port();
            let options = [
                "--server_name".to_owned(),
                format!("n{i}"),
                "--cluster_name".to_owned(),
                "canlift".to_owned(),
                "--cluster".to_owned(),
                format!("nats://127.0.0.1:{}", routes[i]),
                "--routes".to_owned(),
                all.clone(),
                "-m".to_owned(),
                monitor.to_string(),
            ];
            let options: Vec<&str> = options.iter().map(String::as_str).collect();
            Nats::start_with(&options).map(|nats| (nats, monitor))
        })
        .collect()
}

/// Whether the server monitored on `monitor` has a client named `client` connected now (its
/// `/connz`).
pub fn serves(monitor: u16, client: &str) -> bool {
    monitoring(monitor, "/connz").contains(&format!("\"{client}\""))
}

/// A page of the monitoring port `monitor` (empty when it does not answer).
pub fn monitoring(monitor: u16, path: &str) -> String {
    use std::io::{Read, Write};
    let mut page = String::new();
    if let Ok(mut stream) = std::net::TcpStream::connect(("127.0.0.1", monitor)) {
        let request = format!("GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n");
        if stream.write_all(request.as_bytes()).is_ok() {
            let _ = stream.read_to_string(&mut page);
        }
    }
    page
}

/// NATS's decentralized authentication for tests: keys, JWTs signed as `nsc` signs them, and
/// the server configuration and credentials files that go with them (an NKey alone:
/// `cloud_cluster::nats::new_user_nkey`).
#[cfg(feature = "nats-auth")]
pub mod auth {
    use base64::engine::general_purpose::URL_SAFE_NO_PAD;
    use base64::Engine as _;
    use nkeys::KeyPair;
    use serde_json::{json, Value};

    /// A NATS server in operator mode (JWT authentication, as `nsc` sets one up): an operator,
    /// its system account (JetStream needs one), and one account with JetStream whose users
    /// [`OperatorMode::user`] makes.
    pub struct OperatorMode {
        /// The server's configuration (`nats-server -c`): the operator, and the accounts
        /// preloaded into a memory resolver.
        pub conf: String,
        account: KeyPair,
    }

    impl OperatorMode {
        /// A new operator with its accounts.
        pub fn new() -> OperatorMode {
            let operator = KeyPair::new_operator();
            let system = KeyPair::new_account();
            let account = KeyPair::new_account();
            let unlimited = json!({
                "subs": -1, "data": -1, "payload": -1, "imports": -1, "exports": -1,
                "wildcards": true, "conn": -1, "leaf": -1,
                "mem_storage": -1, "disk_storage": -1, "streams": -1, "consumer": -1,
            });
            let operator_jwt = jwt(
                &operator,
                &operator,
                "canlift-test",
                json!({"type": "operator", "version": 2, "system_account": system.public_key()}),
                None,
            );
            let system_jwt = jwt(
                &operator,
                &system,
                "SYS",
                json!({"type": "account", "version": 2}),
                None,
            );
            let account_jwt = jwt(
                &operator,
                &account,
                "canlift",
                json!({"type": "account", "version": 2, "limits": unlimited}),
                None,
            );
            let conf = format!(
                "operator: \"{operator_jwt}\"\nsystem_account: {}\nresolver: MEMORY\n\
                 resolver_preload: {{\n  {}: \"{system_jwt}\"\n  {}: \"{account_jwt}\"\n}}\n",
                system.public_key(),
                system.public_key(),
                account.public_key()
            );
            OperatorMode { conf, account }
        }

        /// The credentials file of a new user of the account (what `[cluster] nats_creds`
        /// names), as `nsc generate creds` writes it, and the user's public key; its JWT expires
        /// at `expires` (Unix seconds) when given.
        pub fn user(&self, expires: Option<u64>) -> (String, String) {
            let user = KeyPair::new_user();
            let user_jwt = jwt(
                &self.account,
                &user,
                "portal",
                json!({
                    "type": "user", "version": 2, "pub": {}, "sub": {},
                    "subs": -1, "data": -1, "payload": -1,
                }),
                expires,
            );
            let creds = format!(
                "-----BEGIN NATS USER JWT-----\n{user_jwt}\n------END NATS USER JWT------\n\n\
                 ************************* IMPORTANT *************************\n\
                 NKEY Seed printed below can be used to sign and prove identity.\n\
                 NKEYs are sensitive and should be treated as secrets.\n\n\
                 -----BEGIN USER NKEY SEED-----\n{}\n------END USER NKEY SEED------\n\n\
                 *************************************************************\n",
                seed(&user)
            );
            (creds, user.public_key())
        }
    }

    impl Default for OperatorMode {
        fn default() -> Self {
            OperatorMode::new()
        }
    }

    fn seed(pair: &KeyPair) -> String {
        pair.seed().expect("a key made here has its seed")
    }

    /// A NATS JWT (v2) about `subject`, signed by `issuer`, valid until `expires` if given.
    fn jwt(
        issuer: &KeyPair,
        subject: &KeyPair,
        name: &str,
        nats: Value,
        expires: Option<u64>,
    ) -> String {
        let header = json!({"typ": "JWT", "alg": "ed25519-nkey"});
        let mut claims = json!({
            "iat": 1_700_000_000,
            "iss": issuer.public_key(),
            "name": name,
            "sub": subject.public_key(),
            "nats": nats,
        });
        if let Some(expires) = expires {
            claims["exp"] = json!(expires);
        }
        claims["jti"] = Value::String(format!("canlift-test-{}", subject.public_key()));
        let encode = |value: &Value| URL_SAFE_NO_PAD.encode(value.to_string());
        let signed = format!("{}.{}", encode(&header), encode(&claims));
        let signature = issuer.sign(signed.as_bytes()).expect("signed");
        format!("{signed}.{}", URL_SAFE_NO_PAD.encode(signature))
    }
}
