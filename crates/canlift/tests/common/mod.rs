//! What the CLI tests share: the `canlift` binary as a command, running it to its end, and
//! stopping a daemon as Ctrl-C would.
#![allow(dead_code)]

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

/// Run `canlift ARGS` to its end.
pub async fn run(args: &[&str]) -> Output {
    canlift().args(args).output().await.expect("canlift runs")
}

/// Its standard error, for assertion messages.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// SIGINT, as Ctrl-C would; the exit status within `limit`.
pub async fn interrupt(child: &mut tokio::process::Child, limit: Duration) -> ExitStatus {
    let pid = child.id().expect("running");
    let _ = std::process::Command::new("kill")
        .args(["-INT", &pid.to_string()])
        .status();
    tokio::time::timeout(limit, child.wait())
        .await
        .expect("exits after SIGINT")
        .expect("the exit status")
}
