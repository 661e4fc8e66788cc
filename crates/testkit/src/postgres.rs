//! A fresh PostgreSQL database per test.

/// A fresh PostgreSQL database for test `name`, or `None` after printing why the test is
/// skipped. CANLIFT_TEST_POSTGRES is a URL to an existing database whose user may create
/// databases (CI sets it after starting Debian's PostgreSQL); with CANLIFT_REQUIRE_POSTGRES=1 a
/// missing or unreachable server fails the test instead.
pub async fn postgres(name: &str) -> Option<Database> {
    use sqlx::Connection;
    let give_up = |reason: String| crate::unavailable("CANLIFT_REQUIRE_POSTGRES", &reason);
    let Ok(admin) = std::env::var("CANLIFT_TEST_POSTGRES") else {
        return give_up("postgres: CANLIFT_TEST_POSTGRES is not set".into());
    };
    let mut conn = match sqlx::PgConnection::connect(&admin).await {
        Ok(c) => c,
        Err(e) => return give_up(format!("postgres: {admin}: {e}")),
    };
    let name = format!("canlift_{name}_{}", std::process::id());
    for statement in [drop_statement(&name), format!("CREATE DATABASE {name}")] {
        if let Err(e) = sqlx::query(&statement).execute(&mut conn).await {
            return give_up(format!("postgres: {statement}: {e}"));
        }
    }
    let base = admin.rsplit_once('/').map_or(admin.as_str(), |(b, _)| b);
    Some(Database {
        url: format!("{base}/{name}"),
        name,
        admin,
    })
}

/// A test's database (its URL, as `&str` and in `format!`), dropped when the test drops it: a
/// developer's server would otherwise keep one per test and run, some forty a suite.
#[derive(Debug)]
pub struct Database {
    url: String,
    name: String,
    admin: String,
}

impl std::ops::Deref for Database {
    type Target = str;
    fn deref(&self) -> &str {
        &self.url
    }
}

impl std::fmt::Display for Database {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.url)
    }
}

impl Drop for Database {
    /// Dropped from a thread with a runtime of its own (a test drops it inside its own
    /// runtime, which cannot be blocked on). Sessions the test left open (a pool's, a portal
    /// process's) are ended with it; a failure is printed, not raised: the test has its
    /// outcome already, and the next run of the same process id drops the database first.
    fn drop(&mut self) {
        use sqlx::Connection;
        let (admin, statement) = (self.admin.clone(), drop_statement(&self.name));
        let dropped = std::thread::spawn(move || {
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .map_err(|e| e.to_string())?;
            runtime.block_on(async {
                let mut conn = sqlx::PgConnection::connect(&admin)
                    .await
                    .map_err(|e| e.to_string())?;
                sqlx::query(&statement)
                    .execute(&mut conn)
                    .await
                    .map(drop)
                    .map_err(|e| e.to_string())
            })
        })
        .join();
        match dropped {
            Ok(Ok(())) => {}
            Ok(Err(e)) => eprintln!("postgres: {}: {e}", self.name),
            Err(_) => eprintln!("postgres: {}: the drop's thread panicked", self.name),
        }
    }
}

/// The statement that drops database `name`, ending its sessions (PostgreSQL 13 and later).
fn drop_statement(name: &str) -> String {
    format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")
}

/// A PostgreSQL server of the test's own (Debian's binaries, a throw-away cluster in a scratch
/// directory, on a loopback port) for tests that stop and start the database; stopped when
/// dropped. As root the server runs as the `postgres` user, which PostgreSQL insists on.
pub struct Server {
    bin: std::path::PathBuf,
    data: tempfile::TempDir,
    port: u16,
    running: bool,
}

impl Server {
    /// Create and start a cluster, or `None` after printing why the test is skipped (no
    /// PostgreSQL installed; with CANLIFT_REQUIRE_POSTGRES=1 the test fails instead).
    pub fn start() -> Option<Server> {
        Server::start_in(None)
    }

    /// [`Server::start`] with the cluster's data in a directory under `parent` (a small
    /// filesystem of the test's, to fill up).
    pub fn start_in(parent: Option<&std::path::Path>) -> Option<Server> {
        let Some(bin) = installed() else {
            return crate::unavailable(
                "CANLIFT_REQUIRE_POSTGRES",
                "postgres: no /usr/lib/postgresql/*/bin/initdb (apt-get install postgresql)",
            );
        };
        let data = match parent {
            Some(parent) => tempfile::Builder::new()
                .prefix("pgdata")
                .tempdir_in(parent)
                .expect("a data directory"),
            None => crate::scratch(),
        };
        if as_root() {
            let chown = std::process::Command::new("chown")
                .args(["-R", "postgres:postgres"])
                .arg(data.path())
                .status()
                .expect("chown runs");
            assert!(
                chown.success(),
                "the postgres user owns the cluster directory"
            );
        }
        let port = crate::free_port();
        let mut server = Server {
            bin,
            data,
            port,
            running: false,
        };
        server
            .run(
                "initdb",
                &[
                    "-U",
                    "postgres",
                    "--auth=trust",
                    "-E",
                    "UTF8",
                    "--no-sync",
                    "-D",
                ],
            )
            .expect("initdb");
        server.start_again();
        Some(server)
    }

    /// `postgres://postgres@127.0.0.1:PORT/postgres`.
    pub fn url(&self) -> String {
        format!("postgres://postgres@127.0.0.1:{}/postgres", self.port)
    }

    /// Stop the server (fast shutdown: sessions are ended, as in a restart or a failover).
    pub fn stop(&mut self) {
        if self.running {
            self.run("pg_ctl", &["-m", "fast", "-w", "stop", "-D"])
                .expect("pg_ctl stop");
            self.running = false;
        }
    }

    /// Whether the server runs (it stops by itself after a PANIC it cannot recover from, such
    /// as a full disk under its WAL).
    pub fn is_running(&self) -> bool {
        self.running && self.run("pg_ctl", &["status", "-D"]).is_ok()
    }

    /// Start the server again if it stopped (as systemd's `Restart=` would).
    pub fn revive(&mut self) {
        if !self.is_running() {
            self.running = false;
            self.start_again();
        }
    }

    /// Start the stopped server again on the same port and data.
    pub fn start_again(&mut self) {
        let options = format!(
            "-p {} -k {} -c listen_addresses=127.0.0.1 -c fsync=off",
            self.port,
            self.data.path().display()
        );
        let log = self.data.path().join("server.log");
        let log = log.to_str().expect("a UTF-8 path");
        self.run("pg_ctl", &["-w", "-l", log, "-o", &options, "start", "-D"])
            .expect("pg_ctl start");
        self.running = true;
    }

    /// Run `bin/PROGRAM ARGS DATA_DIR` (as the postgres user when root).
    fn run(&self, program: &str, args: &[&str]) -> Result<(), String> {
        let program = self.bin.join(program);
        let mut command = if as_root() {
            let mut c = std::process::Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(&program);
            c
        } else {
            std::process::Command::new(&program)
        };
        match command.args(args).arg(self.data.path()).output() {
            Ok(out) if out.status.success() => Ok(()),
            Ok(out) => Err(format!(
                "{} {args:?}: {}{}",
                program.display(),
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            )),
            Err(e) => Err(format!("{}: {e}", program.display())),
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if self.running {
            let _ = self.run("pg_ctl", &["-m", "immediate", "-w", "stop", "-D"]);
        }
    }
}

/// The newest installed PostgreSQL's binaries.
fn installed() -> Option<std::path::PathBuf> {
    let mut versions: Vec<(u32, std::path::PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .ok()?
        .filter_map(Result::ok)
        .filter_map(|e| {
            let version = e.file_name().to_str()?.parse().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").is_file().then_some((version, bin))
        })
        .collect();
    versions.sort();
    versions.pop().map(|(_, bin)| bin)
}

fn as_root() -> bool {
    std::process::Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| o.stdout.starts_with(b"0\n"))
}
