//! Helpers shared by the integration tests of several crates: a hub on a loopback port, finding
//! the interop Python and the browser, reporting skipped tests where CI logs show them, the
//! constants every test uses for its lift ([`constants`]), a sample dictionary ([`sample`]), and,
//! behind features, a PostgreSQL database per test (`postgres`), a test PKI (`pki`), the
//! simulated lift with its gateway (`lift`), the portal with a lift connected (`portal`) and a
//! scripted portal for exact JSON-RPC exchanges with a gateway (`scripted`), and for the cluster
//! tests a NATS server (`nats`) and a TCP load balancer (`balancer`).

#[cfg(feature = "portal")]
pub mod balancer;
pub mod constants;
#[cfg(feature = "lift")]
pub mod lift;
#[cfg(feature = "nats")]
pub mod nats;
#[cfg(feature = "net")]
pub mod net;
#[cfg(feature = "pki")]
pub mod pki;
#[cfg(feature = "portal")]
pub mod portal;
#[cfg(feature = "postgres")]
mod postgres;
pub mod proxy;
pub mod sample;
#[cfg(feature = "lift")]
pub mod script;
#[cfg(feature = "scripted")]
pub mod scripted;

#[cfg(feature = "postgres")]
pub use postgres::{postgres, Database as PostgresDatabase, Server as PostgresServer};

use std::io::Write;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use canbus::hub::{Hub, HubConfig, HubHandle};

/// A hub on an ephemeral loopback port with `config` (its `listen` is replaced).
pub async fn hub_with(config: HubConfig) -> HubHandle {
    let config = HubConfig {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        ..config
    };
    Hub::bind(config)
        .await
        .expect("bind a loopback port")
        .spawn()
        .expect("start the hub")
}

/// A default hub on an ephemeral loopback port.
pub async fn hub() -> HubHandle {
    hub_with(HubConfig::default()).await
}

/// `socketcand://ADDR/CHANNEL` for a hub.
pub fn hub_url(hub: &HubHandle, channel: &str) -> String {
    format!("socketcand://{}/{channel}", hub.local_addr())
}

/// The workspace root.
pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A script under `tests/interop/`.
pub fn interop_script(name: &str) -> PathBuf {
    workspace().join("tests/interop").join(name)
}

/// Print a skip reason past libtest's output capture, so CI logs show it, and add it to the file
/// `CANLIFT_SKIPS` names where set: cargo-nextest keeps a passing test's output to itself, and
/// scripts/test lists that file's reasons after the run.
pub fn skip(reason: &str) {
    let _ = writeln!(std::io::stderr(), "SKIP: {reason}");
    if let Some(path) = std::env::var_os("CANLIFT_SKIPS") {
        // One short write to a file opened for appending: lines of tests in parallel processes
        // do not mix.
        let appended = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .and_then(|mut file| file.write_all(format!("{reason}\n").as_bytes()));
        if let Err(e) = appended {
            let _ = writeln!(std::io::stderr(), "CANLIFT_SKIPS not written: {e}");
        }
    }
}

/// What a test that needs something missing gets: `None` after printing `reason` as a skip, or
/// a failure where the environment variable `require` is `1` (CI installs everything and sets
/// it, so nothing is skipped there unnoticed).
pub fn unavailable<T>(require: &str, reason: &str) -> Option<T> {
    if std::env::var(require).as_deref() == Ok("1") {
        panic!("{reason}");
    }
    skip(reason);
    None
}

/// `name`'s path on the PATH, if it is there.
pub fn on_path(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|p| p.join(name))
            .find(|p| p.is_file())
    })
}

/// The Python with python-can and canopen (the venv `scripts/test` makes), or `None` after
/// printing why the test is skipped. With CANLIFT_REQUIRE_INTEROP=1 (as `scripts/test` and CI
/// set) a missing venv fails the test instead.
pub fn python() -> Option<PathBuf> {
    let candidate = std::env::var_os("CANLIFT_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".venv/bin/python"));
    let works = Command::new(&candidate)
        .args(["-c", "import can, canopen"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if works {
        return Some(candidate);
    }
    let reason = format!(
        "interop: {} cannot import can/canopen; run scripts/test to set up .venv",
        candidate.display()
    );
    unavailable("CANLIFT_REQUIRE_INTEROP", &reason)
}

/// Chromium and ChromeDriver (Debian's `chromium` and `chromium-driver`), or `None` after
/// printing why the test is skipped. With CANLIFT_REQUIRE_BROWSER=1 (CI installs both) their
/// absence fails the test instead.
pub fn browser() -> Option<(PathBuf, PathBuf)> {
    match (on_path("chromium"), on_path("chromedriver")) {
        (Some(chromium), Some(driver)) => Some((chromium, driver)),
        _ => unavailable(
            "CANLIFT_REQUIRE_BROWSER",
            "browser: chromium and chromedriver are not on PATH \
             (apt-get install chromium chromium-driver)",
        ),
    }
}

/// The OpenID provider of the single sign-on tests: `tests/interop/oidc` with its pinned npm
/// packages installed (`scripts/test` runs `npm ci` there) and Node.js on PATH, or `None` after
/// printing why the test is skipped. With CANLIFT_REQUIRE_OIDC=1 (CI) their absence fails it.
pub fn oidc_provider() -> Option<PathBuf> {
    let dir = workspace().join("tests/interop/oidc");
    let node = Command::new("node")
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if node && dir.join("node_modules/oidc-provider").is_dir() {
        return Some(dir);
    }
    unavailable(
        "CANLIFT_REQUIRE_OIDC",
        "oidc: node or tests/interop/oidc/node_modules missing (scripts/test installs the \
         pinned oidc-provider with npm ci)",
    )
}

/// Prometheus's `promtool` (Debian's `prometheus` package), or `None` after printing why the
/// test is skipped. With CANLIFT_REQUIRE_PROMTOOL=1 (CI installs it) its absence fails the test.
pub fn promtool() -> Option<PathBuf> {
    on_path("promtool").or_else(|| {
        unavailable(
            "CANLIFT_REQUIRE_PROMTOOL",
            "metrics: promtool is not on PATH (apt-get install prometheus)",
        )
    })
}

/// `promtool ARGS` with `input` on its standard input: its exit status and what it said.
pub fn run_promtool(promtool: &Path, args: &[&str], input: &str) -> (bool, String) {
    let mut child = Command::new(promtool)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("promtool runs");
    if let Some(mut stdin) = child.stdin.take() {
        let _ = stdin.write_all(input.as_bytes());
    }
    let out = child.wait_with_output().expect("promtool ends");
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), said)
}

/// A free TCP port on 127.0.0.1 (for a server a test starts as a separate process).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a loopback port")
        .port()
}

/// A scratch directory, removed when dropped.
pub fn scratch() -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix("canlift-test-")
        .tempdir()
        .expect("a scratch directory")
}

/// A CONNECT (NXg §5.2.1) of gateway `sernum` (vendor 1050, product 4096, no board hash) to
/// the account of `domain`, with a cloud token or without: what the portal's registry and
/// admission tests ask about.
#[cfg(feature = "connect")]
pub fn connect(sernum: &str, domain: &str, token: Option<&str>) -> nxg::msg::Connect {
    nxg::msg::Connect {
        identity: nxg::msg::Identity {
            sernum: sernum.into(),
            vendorid: 1050,
            productcode: 4096,
            liftnum: String::new(),
            hardware: String::new(),
            software: String::new(),
            api: 1,
            boardhash: String::new(),
            cloudtoken: token.map(str::to_owned),
        },
        domaintoken: domain.into(),
    }
}

/// A small filesystem of a test's own (tmpfs) to fill up: mounted on a scratch directory,
/// unmounted when dropped. Mounting needs root (as CI runs); elsewhere the test is skipped.
pub struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    /// A tmpfs of `bytes`, or `None` after printing why the test is skipped.
    pub fn mount(bytes: u64) -> Option<Tmpfs> {
        let dir = scratch();
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o"])
            .arg(format!("size={bytes},mode=0777"))
            .arg("tmpfs")
            .arg(dir.path())
            .output();
        match out {
            Ok(o) if o.status.success() => Some(Tmpfs { dir }),
            Ok(o) => {
                skip(&format!(
                    "tmpfs: mount refused ({}): a full disk is tried as root only",
                    String::from_utf8_lossy(&o.stderr).trim()
                ));
                None
            }
            Err(e) => {
                skip(&format!("tmpfs: no mount command ({e})"));
                None
            }
        }
    }

    /// Where it is mounted.
    pub fn path(&self) -> &std::path::Path {
        self.dir.path()
    }

    /// Bytes free on it now.
    pub fn free(&self) -> u64 {
        let out = Command::new("stat")
            .args(["-f", "-c", "%a %S"])
            .arg(self.path())
            .output()
            .expect("stat runs");
        let text = String::from_utf8_lossy(&out.stdout);
        let mut fields = text
            .split_whitespace()
            .map(|f| f.parse::<u64>().unwrap_or(0));
        fields.next().unwrap_or(0) * fields.next().unwrap_or(0)
    }

    /// Fill it up to `leave` bytes free with a file of zeros; the file, to delete for space.
    pub fn fill(&self, leave: u64) -> PathBuf {
        let filler = self.path().join("filler");
        let size = self.free().saturating_sub(leave);
        let file = std::fs::File::create(&filler).expect("the filler");
        let zeros = vec![0u8; 64 << 10];
        let mut left = size;
        let mut out = std::io::BufWriter::new(file);
        while left > 0 {
            let n = left.min(zeros.len() as u64) as usize;
            if out.write_all(&zeros[..n]).is_err() {
                break;
            }
            left -= n as u64;
        }
        let _ = out.flush();
        filler
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(self.path()).status();
    }
}
