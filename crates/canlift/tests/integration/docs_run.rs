//! The docs as a new user runs them. Every `sh` block of README.md and docs/ (but the benchmark
//! commands of docs/BENCHMARKS.md, minutes each) says on the line above it whether it runs:
//!
//! - `<!-- runs: shell -->`: run as written by bash in an empty directory of its own, `canlift`
//!   on the PATH;
//! - `<!-- runs: demo -->`: the same beside a `canlift demo` the test started, its banner's
//!   `export` done (`CANLIFT_PORTAL`, `CANLIFT_API_KEY`, `CANLIFT_CA`) and `CANLIFT_BUS` set to
//!   its bus;
//! - `<!-- not run: WHY -->`: a synopsis, or what needs root, systemd or another machine.
//!
//! A block runs under `set -euo pipefail`: every command must succeed; what it leaves running
//! in the background is stopped when it ends. A doc that drifts from the program fails here.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use crate::common;

/// How long one block may take.
const BLOCK_LIMIT: Duration = Duration::from_secs(120);

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Runs {
    Shell,
    Demo,
}

/// One `sh` block: where it is, what its marker says, its text.
struct Block {
    place: String,
    runs: Result<Option<Runs>, String>,
    script: String,
}

fn documents() -> Vec<PathBuf> {
    let root = testkit::workspace();
    let mut files = vec![root.join("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("docs/")
        .filter_map(|e| Some(e.ok()?.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "md") && !p.ends_with("BENCHMARKS.md"))
        .collect();
    docs.sort();
    files.extend(docs);
    files
}

/// The `sh` blocks of `path` with their markers.
fn blocks(path: &Path) -> Vec<Block> {
    let text = std::fs::read_to_string(path).expect("a document");
    let name = path
        .strip_prefix(testkit::workspace())
        .unwrap_or(path)
        .display()
        .to_string();
    let lines: Vec<&str> = text.lines().collect();
    let mut found = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        if lines[i].trim_end() != "```sh" {
            i += 1;
            continue;
        }
        let marker = i.checked_sub(1).map_or("", |m| lines[m].trim());
        let runs = match marker {
            "<!-- runs: shell -->" => Ok(Some(Runs::Shell)),
            "<!-- runs: demo -->" => Ok(Some(Runs::Demo)),
            m if m.starts_with("<!-- not run: ") && m.ends_with("-->") => Ok(None),
            m => Err(format!("no marker above the block ({m:?})")),
        };
        let end = (i + 1..lines.len())
            .find(|&j| lines[j].trim_end() == "```")
            .expect("a closed block");
        found.push(Block {
            place: format!("{name}:{}", i + 1),
            runs,
            script: lines[i + 1..end].join("\n"),
        });
        i = end + 1;
    }
    found
}

#[test]
fn every_shell_block_says_whether_it_runs() {
    let unmarked: Vec<String> = documents()
        .iter()
        .flat_map(|d| blocks(d))
        .filter_map(|b| b.runs.err().map(|why| format!("{}: {why}", b.place)))
        .collect();
    assert!(unmarked.is_empty(), "{}", unmarked.join("\n"));
}

/// Run `script` under bash in `dir` with `env`; `Err` with what a reader needs when it fails.
async fn run(script: &str, dir: &Path, env: &[(&str, String)]) -> Result<(), String> {
    let bin = Path::new(env!("CARGO_BIN_EXE_canlift"))
        .parent()
        .expect("the binary's directory");
    let path = std::env::join_paths(std::iter::once(bin.to_path_buf()).chain(
        std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()),
    ))
    .expect("a PATH");
    let child = tokio::process::Command::new("bash")
        .arg("-c")
        .arg(format!("set -euo pipefail\n{script}"))
        .current_dir(dir)
        .env("PATH", path)
        .env("RUST_LOG", "warn")
        .envs(env.iter().map(|(k, v)| (k, v)))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0)
        .kill_on_drop(true)
        .spawn()
        .expect("bash runs");
    let mut child = child;
    let group = child.id().expect("running");
    // Read both streams to their end meanwhile: what the block leaves in the background holds
    // them open until it is stopped.
    let read = |stream: Option<Box<dyn tokio::io::AsyncRead + Unpin + Send>>| {
        tokio::spawn(async move {
            let mut bytes = Vec::new();
            if let Some(mut stream) = stream {
                let _ = tokio::io::AsyncReadExt::read_to_end(&mut stream, &mut bytes).await;
            }
            bytes
        })
    };
    let stdout = read(child.stdout.take().map(|s| Box::new(s) as _));
    let stderr = read(child.stderr.take().map(|s| Box::new(s) as _));
    let ended = tokio::time::timeout(BLOCK_LIMIT, child.wait()).await;
    // What the block left in the background (a hub, a simulator) ends with it.
    let _ = std::process::Command::new("kill")
        .args(["-KILL", "--", &format!("-{group}")])
        .stderr(Stdio::null())
        .status();
    let status = match ended {
        Ok(status) => status.expect("bash ends"),
        Err(_) => return Err(format!("still running after {BLOCK_LIMIT:?}")),
    };
    let collect = |reader: tokio::task::JoinHandle<Vec<u8>>| async move {
        let collected = tokio::time::timeout(Duration::from_secs(10), reader).await;
        collected.ok().and_then(Result::ok).unwrap_or_default()
    };
    let out = std::process::Output {
        status,
        stdout: collect(stdout).await,
        stderr: collect(stderr).await,
    };
    if out.status.success() {
        return Ok(());
    }
    let tail = |bytes: &[u8]| {
        let text = String::from_utf8_lossy(bytes);
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(15)..].join("\n")
    };
    Err(format!(
        "{}\n--- stdout\n{}\n--- stderr\n{}",
        out.status,
        tail(&out.stdout),
        tail(&out.stderr)
    ))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_runnable_shell_blocks_run_as_written() {
    let runnable: Vec<(String, Runs, String)> = documents()
        .iter()
        .flat_map(|d| blocks(d))
        .filter_map(|b| Some((b.place, b.runs.ok()??, b.script)))
        .collect();
    assert!(
        runnable.iter().any(|b| b.1 == Runs::Shell) && runnable.iter().any(|b| b.1 == Runs::Demo),
        "runnable blocks of both kinds"
    );
    let scratch = testkit::scratch();
    let demo = common::demo::start(&scratch.path().join("demo")).await;
    let demo_env = [
        ("CANLIFT_PORTAL", demo.portal.clone()),
        ("CANLIFT_API_KEY", demo.key.clone()),
        ("CANLIFT_CA", demo.ca.display().to_string()),
        ("CANLIFT_BUS", demo.bus.clone()),
    ];
    let mut failed = Vec::new();
    for (n, (place, runs, script)) in runnable.iter().enumerate() {
        let dir = scratch.path().join(format!("block-{n}"));
        std::fs::create_dir_all(&dir).expect("a directory");
        let env: &[(&str, String)] = match runs {
            Runs::Shell => &[],
            Runs::Demo => &demo_env,
        };
        if let Err(why) = run(script, &dir, env).await {
            failed.push(format!("{place}:\n{script}\n=> {why}"));
        }
    }
    let mut child = demo.child;
    common::interrupt(&mut child, Duration::from_secs(20)).await;
    assert!(failed.is_empty(), "{}", failed.join("\n\n"));
}
