//! A NATS server of the test's own (Debian's `nats-server` with JetStream, on a loopback port,
//! its storage in a scratch directory) for the cluster tests; stopped when dropped, and
//! stoppable and startable again on the same port for the tests of NATS outages.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use crate::skip;

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
            let reason = "nats: no nats-server on the PATH (apt-get install nats-server)";
            if std::env::var("CANLIFT_REQUIRE_NATS").as_deref() == Ok("1") {
                panic!("{reason}");
            }
            skip(reason);
            return None;
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

    /// Start the stopped server again on the same port, and wait until it listens.
    pub fn start_again(&mut self) {
        self.stop();
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
            .stderr(Stdio::null())
            .spawn()
            .expect("nats-server starts");
        self.child = Some(child);
        let begin = std::time::Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(
                begin.elapsed() < Duration::from_secs(10),
                "nats-server listens within 10 s"
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
