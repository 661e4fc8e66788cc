//! What the CLI tests share: the `canlift` binary as a command, running it to its end, and
//! stopping a daemon as Ctrl-C would.

use std::process::{ExitStatus, Output, Stdio};
use std::time::Duration;

/// `canlift` with stdout and stderr captured, killed when dropped.
pub fn canlift() -> tokio::process::Command {
    let mut cmd = tokio::process::Command::new(env!("CARGO_BIN_EXE_canlift"));
    cmd.stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    cmd
}

/// `canlift sim --export-eds EDS`: the simulated controller's EDS (and its I/O node's beside it).
pub async fn export_sim_eds(eds: &std::path::Path) {
    let export = canlift()
        .args(["sim", "--export-eds"])
        .arg(eds)
        .output()
        .await
        .expect("canlift runs");
    assert!(export.status.success(), "{}", stderr(&export));
}

/// Run `canlift ARGS` to its end.
pub async fn run(args: &[&str]) -> Output {
    canlift().args(args).output().await.expect("canlift runs")
}

/// Its standard error, for assertion messages.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Send signal `name` (`INT`, `HUP`, `TERM`) to `child`.
pub fn send_signal(child: &tokio::process::Child, name: &str) {
    let pid = child.id().expect("running");
    let sent = std::process::Command::new("kill")
        .args([&format!("-{name}"), &pid.to_string()])
        .status()
        .expect("kill runs");
    assert!(sent.success(), "SIG{name} sent to {pid}");
}

/// SIGINT, as Ctrl-C would; the exit status within `limit`.
pub async fn interrupt(child: &mut tokio::process::Child, limit: Duration) -> ExitStatus {
    send_signal(child, "INT");
    tokio::time::timeout(limit, child.wait())
        .await
        .expect("exits after SIGINT")
        .expect("the exit status")
}

/// Compare `text` with the snapshot `tests/snapshots/NAME` (help texts and tables a user sees);
/// with `CANLIFT_UPDATE_SNAPSHOTS=1` write it instead, for review in the diff.
pub fn snapshot(name: &str, text: &str) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/snapshots")
        .join(name);
    if std::env::var_os("CANLIFT_UPDATE_SNAPSHOTS").is_some() {
        std::fs::create_dir_all(path.parent().expect("a parent")).expect("snapshot directory");
        std::fs::write(&path, text).expect("snapshot written");
        return;
    }
    let expected = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (run with CANLIFT_UPDATE_SNAPSHOTS=1 to create it)",
            path.display()
        )
    });
    assert_eq!(
        text,
        expected,
        "{} differs (CANLIFT_UPDATE_SNAPSHOTS=1 rewrites it)",
        path.display()
    );
}

/// A python-canopen node (`tests/interop/SCRIPT HOST PORT ID`) on the hub, once it printed
/// READY; its further output lines.
pub async fn python_node(
    python: &std::path::Path,
    hub: &canbus::hub::HubHandle,
    script: &str,
    id: u8,
) -> (
    tokio::process::Child,
    tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStdout>>,
) {
    use tokio::io::AsyncBufReadExt;
    let addr = hub.local_addr();
    let mut node = tokio::process::Command::new(python)
        .arg(testkit::interop_script(script))
        .args([
            addr.ip().to_string(),
            addr.port().to_string(),
            id.to_string(),
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .expect("python runs");
    let mut lines = tokio::io::BufReader::new(node.stdout.take().expect("stdout")).lines();
    let ready = tokio::time::timeout(Duration::from_secs(30), lines.next_line())
        .await
        .expect("READY within 30 s")
        .expect("a line");
    assert_eq!(ready.as_deref(), Some("READY"));
    (node, lines)
}

/// `canlift ARGS` in the background, its output discarded.
#[cfg(feature = "portal")]
pub fn daemon(args: &[&str]) -> tokio::process::Child {
    canlift()
        .args(args)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("canlift starts")
}

/// Kill `child` with SIGKILL and reap it.
#[cfg(feature = "portal")]
pub async fn kill(child: &mut tokio::process::Child) {
    child.start_kill().expect("SIGKILL sent");
    let _ = tokio::time::timeout(Duration::from_secs(10), child.wait())
        .await
        .expect("a killed process ends");
}

#[cfg(feature = "portal")]
mod portal;
#[cfg(feature = "portal")]
pub use portal::PortalProcess;
#[cfg(feature = "portal")]
pub mod demo;
#[cfg(feature = "portal")]
pub mod http;
