//! An interop script (tests/interop/) run as a child process that reads commands on its
//! standard input and prints what it saw, one line each: the fake gateways and receivers the
//! portal's tests talk to.

use std::path::Path;
use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::process::{Child, ChildStdin, Command};

/// A child process speaking lines.
pub struct Script {
    child: Child,
    stdin: ChildStdin,
    lines: Arc<Mutex<Vec<String>>>,
}

impl Script {
    /// Start `python` on the interop script `name` with `args`.
    pub fn start(python: &Path, name: &str, args: &[&str]) -> Script {
        let mut child = Command::new(python)
            .arg(crate::interop_script(name))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()
            .unwrap();
        let stdin = child.stdin.take().unwrap();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = lines.clone();
        let mut out = BufReader::new(child.stdout.take().unwrap()).lines();
        tokio::spawn(async move {
            while let Ok(Some(line)) = out.next_line().await {
                sink.lock().unwrap().push(line);
            }
        });
        Script {
            child,
            stdin,
            lines,
        }
    }

    /// Kill it (as a crash would end it) and wait until it has ended.
    pub async fn kill(&mut self) {
        self.child.kill().await.expect("the script is killed");
    }

    /// Write `line` to its standard input.
    pub async fn say(&mut self, line: &str) {
        self.stdin
            .write_all(format!("{line}\n").as_bytes())
            .await
            .unwrap();
        self.stdin.flush().await.unwrap();
    }

    /// The lines it printed that start with `prefix`.
    pub fn seen(&self, prefix: &str) -> Vec<String> {
        self.lines
            .lock()
            .unwrap()
            .iter()
            .filter(|l| l.starts_with(prefix))
            .cloned()
            .collect()
    }

    /// Wait until `n` lines start with `prefix`; those lines.
    pub async fn wait_for(&self, prefix: &str, n: usize, wait: Duration) -> Vec<String> {
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            let seen = self.seen(prefix);
            if seen.len() >= n {
                return seen;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{n} × {prefix:?} not seen; all: {:?}",
                self.lines.lock().unwrap()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}
