//! The processes a benchmark starts and what it reads of them: `canlift` daemons (hub, portal,
//! load generators) started and stopped, their CPU time, wake-ups and memory from `/proc`.

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};

/// CPU time (user + system) of process `pid` so far, summed over its threads.
pub(crate) fn cpu_time(pid: u32) -> Option<Duration> {
    schedstat(pid).map(|(cpu, _)| cpu)
}

/// CPU time of process `pid` so far and how many times one of its threads was put on a CPU
/// (each wake-up at least once), summed over its threads: `/proc/PID/task/*/schedstat`.
pub(crate) fn schedstat(pid: u32) -> Option<(Duration, u64)> {
    let tasks = std::fs::read_dir(format!("/proc/{pid}/task")).ok()?;
    let (mut total, mut slices) = (0u64, 0u64);
    for task in tasks.flatten() {
        let (cpu, n) = task_schedstat(&task.path().join("schedstat"))?;
        total += cpu;
        slices += n;
    }
    Some((Duration::from_nanos(total), slices))
}

/// The calling thread's CPU time so far and how many times it was put on a CPU
/// (`/proc/thread-self/schedstat`).
pub(crate) fn thread_schedstat() -> Option<(Duration, u64)> {
    let (cpu, slices) = task_schedstat(Path::new("/proc/thread-self/schedstat"))?;
    Some((Duration::from_nanos(cpu), slices))
}

/// One thread's `schedstat`: nanoseconds on a CPU, and time slices.
fn task_schedstat(path: &Path) -> Option<(u64, u64)> {
    let text = std::fs::read_to_string(path).ok()?;
    let mut fields = text.split_whitespace();
    let cpu = fields.next()?.parse::<u64>().ok()?;
    let slices = fields.nth(1)?.parse::<u64>().ok()?;
    Some((cpu, slices))
}

/// What process `pid` used since `before` (its [`schedstat`] then): CPU time and wake-ups.
pub(crate) fn used_since(pid: u32, before: Option<(Duration, u64)>) -> Option<(Duration, u64)> {
    let (cpu, slices) = before?;
    let (now, slices_now) = schedstat(pid)?;
    Some((now.saturating_sub(cpu), slices_now.saturating_sub(slices)))
}

/// `used` (CPU time, wake-ups) per one of `n` things done, as the benchmarks print it.
pub(crate) fn per_one(used: Option<(Duration, u64)>, n: f64) -> String {
    match used {
        Some((cpu, slices)) => format!(
            "{:.1} µs CPU and {:.2} wake-ups",
            cpu.as_secs_f64() * 1e6 / n,
            slices as f64 / n
        ),
        None => "not measured".to_owned(),
    }
}

/// The `p`th percentile of sorted durations, in µs.
pub(crate) fn percentile(sorted: &[Duration], p: f64) -> f64 {
    let rank = ((p / 100.0) * (sorted.len().max(1) - 1) as f64).round() as usize;
    sorted.get(rank).map_or(0.0, |d| d.as_secs_f64() * 1e6)
}

/// A canlift daemon (`gateway`, `cloud`) started by a benchmark as a process of its own, so its
/// memory is its own: quiet, and killed if the benchmark fails.
pub(crate) struct Daemon {
    child: tokio::process::Child,
    /// Its process id.
    pub(crate) pid: u32,
}

impl Daemon {
    /// `exe COMMAND --config CONFIG`, its warnings on the benchmark's standard error; on
    /// `cpus` only when given (`taskset -c CPUS`, which execs it: the process id is the
    /// daemon's, and each of its threads keeps the CPUs).
    pub(crate) fn start(
        exe: &Path,
        command: &str,
        config: &Path,
        cpus: Option<&str>,
    ) -> anyhow::Result<Daemon> {
        let args = [command.as_ref(), "--config".as_ref(), config.as_os_str()];
        match cpus {
            Some(cpus) => {
                let pinned = [&["-c".as_ref(), cpus.as_ref(), exe.as_os_str()], &args[..]].concat();
                Daemon::spawn(Path::new("taskset"), &pinned, Stdio::inherit())
            }
            None => Daemon::spawn(exe, &args, Stdio::inherit()),
        }
    }

    /// `exe ARGS…` with its standard error to `stderr` (a load generator's thousands of
    /// gateways would each log a reconnect: `Stdio::null()`).
    pub(crate) fn spawn(
        exe: &Path,
        args: &[&std::ffi::OsStr],
        stderr: Stdio,
    ) -> anyhow::Result<Daemon> {
        let command = args
            .first()
            .map_or_else(Default::default, |c| c.to_string_lossy());
        let child = tokio::process::Command::new(exe)
            .args(args)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(stderr)
            .kill_on_drop(true)
            .spawn()?;
        let pid = child.id().with_context(|| format!("{command} process"))?;
        Ok(Daemon { child, pid })
    }

    /// SIGKILL: nothing the process could still do (a crash, a power cut).
    pub(crate) async fn kill(mut self) {
        let _ = self.child.start_kill();
        let _ = self.child.wait().await;
    }

    /// SIGINT (the daemons' graceful shutdown), then wait up to `limit` for the exit.
    pub(crate) async fn stop(&mut self, limit: Duration) {
        if let Ok(pid) = libc::pid_t::try_from(self.pid) {
            // SAFETY: signalling a process id of a child this process started and has not
            // reaped (`self.child` holds it), so the id is not another process's.
            unsafe { libc::kill(pid, libc::SIGINT) };
        }
        let _ = tokio::time::timeout(limit, self.child.wait()).await;
    }
}

/// One embedded gateway on a local dictionary in a process of its own (`canlift loadgen`,
/// gateway number `number` of `domain`), dialling `url`.
pub(crate) fn lone_gateway(
    exe: &Path,
    url: &str,
    ca: &Path,
    domain: &str,
    number: usize,
    state: &Path,
) -> anyhow::Result<Daemon> {
    let number = number.to_string();
    Daemon::spawn(
        exe,
        &[
            "loadgen".as_ref(),
            "--portal".as_ref(),
            url.as_ref(),
            "--ca".as_ref(),
            ca.as_os_str(),
            "--domain".as_ref(),
            domain.as_ref(),
            "--gateways".as_ref(),
            "1".as_ref(),
            "--first".as_ref(),
            number.as_ref(),
            "--state".as_ref(),
            state.as_os_str(),
        ],
        Stdio::null(),
    )
}

/// RSS, PSS and anonymous memory of a process in KiB (`/proc/PID/smaps_rollup`): RSS counts the
/// binary's pages shared with other canlift processes in full, PSS shares them out, anonymous is
/// the process's own heap and stacks.
pub(crate) fn memory_kib(pid: u32) -> Option<[u64; 3]> {
    let rollup = std::fs::read_to_string(format!("/proc/{pid}/smaps_rollup")).ok()?;
    let field = |name: &str| {
        rollup
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
    };
    Some([field("Rss:")?, field("Pss:")?, field("Anonymous:")?])
}

pub(crate) fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

/// Wait until something listens on loopback `port` (a process the benchmark started), at
/// most `limit`.
pub(crate) async fn listening(port: u16, what: &str, limit: Duration) -> anyhow::Result<()> {
    let deadline = Instant::now() + limit;
    while tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .is_err()
    {
        if Instant::now() > deadline {
            bail!("{what} did not start");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    Ok(())
}
