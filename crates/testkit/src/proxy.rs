//! An HTTP proxy of the test's own: Debian's `tinyproxy` on a loopback port, its log in a
//! scratch directory, allowed to `CONNECT` only to the ports the test names; stopped when
//! dropped.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// A running `tinyproxy`.
pub struct Tinyproxy {
    port: u16,
    log: PathBuf,
    _dir: tempfile::TempDir,
    child: Child,
}

impl Tinyproxy {
    /// A proxy that tunnels to `ports` on this host, or `None` after printing why the test is
    /// skipped (no `tinyproxy` on the PATH; with CANLIFT_REQUIRE_TINYPROXY=1 the test fails).
    pub fn start(ports: &[u16]) -> Option<Tinyproxy> {
        let binary = ["/usr/bin/tinyproxy", "/usr/sbin/tinyproxy"]
            .into_iter()
            .map(PathBuf::from)
            .find(|p| p.is_file());
        let Some(binary) = binary else {
            return crate::unavailable(
                "CANLIFT_REQUIRE_TINYPROXY",
                "proxy: tinyproxy is not installed (apt-get install tinyproxy)",
            );
        };
        let dir = crate::scratch();
        let port = crate::free_port();
        let log = dir.path().join("tinyproxy.log");
        let mut config = format!(
            "Port {port}\nListen 127.0.0.1\nTimeout 60\nMaxClients 50\nAllow 127.0.0.1\n\
             LogFile \"{}\"\nLogLevel Connect\nPidFile \"{}\"\n",
            log.display(),
            dir.path().join("tinyproxy.pid").display()
        );
        for p in ports {
            config.push_str(&format!("ConnectPort {p}\n"));
        }
        let conf = dir.path().join("tinyproxy.conf");
        std::fs::write(&conf, config).expect("the proxy's configuration");
        let child = Command::new(binary)
            .arg("-d")
            .arg("-c")
            .arg(&conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("tinyproxy starts");
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                std::time::Instant::now() < deadline,
                "tinyproxy listens within 10 s"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        Some(Tinyproxy {
            port,
            log,
            _dir: dir,
            child,
        })
    }

    /// `http://127.0.0.1:PORT`.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// What it logged so far (its `CONNECT` lines name where it tunnelled).
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Stop it now (its tunnels end with it).
    pub fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Tinyproxy {
    fn drop(&mut self) {
        self.stop();
    }
}
