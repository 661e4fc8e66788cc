//! `canlift cloud --config FILE`: the cloud portal (docs/PORTAL.md); `canlift cloud account add` creates
//! an operator account and prints its API key once; `canlift cloud token reset LIFT` forgets a
//! lift's cloud token in the portal's database; `user` and `key` manage an account's people and
//! their API keys (docs/PORTAL.md §Users and roles); `nats-nkey FILE` makes a cluster's NATS user
//! key (docs/CLUSTER.md §Securing NATS); `backup FILE` and `restore FILE` copy a SQLite
//! portal's database out and back (docs/PORTAL.md §Backups). These are the administrator's
//! commands on the portal's machine: they need the configuration, not an API key.

use std::path::PathBuf;

use anyhow::Context;
use cloud::config::Config;
use cloud::server::Portal;
use cloud_store::Store;
use cloud_types::users::Role;

/// Command-line arguments of `canlift cloud`.
#[derive(Debug, clap::Args)]
pub struct CloudArgs {
    /// Configuration file (TOML: `[server]`, `[state]`, `[database]`, `[gateways]`); default:
    /// /etc/canlift/portal.toml when present.
    #[arg(long, global = true, env = "CANLIFT_CONFIG")]
    config: Option<PathBuf>,
    /// Print the effective configuration and exit.
    #[arg(long)]
    print_config: bool,
    #[command(subcommand)]
    what: Option<CloudCommand>,
}

#[derive(Debug, clap::Subcommand)]
enum CloudCommand {
    /// Operator accounts.
    Account {
        #[command(subcommand)]
        what: AccountCommand,
    },
    /// Gateways' cloud tokens.
    Token {
        #[command(subcommand)]
        what: TokenCommand,
    },
    /// Lifts of the registry.
    Lift {
        #[command(subcommand)]
        what: LiftCommand,
    },
    /// People of an account, with their roles (viewer, technician, engineer, admin).
    User {
        #[command(subcommand)]
        what: UserCommand,
    },
    /// API keys of users.
    Key {
        #[command(subcommand)]
        what: KeyCommand,
    },
    /// A consistent copy of a running SQLite portal's database into FILE (which must not exist).
    ///
    /// Taken while the portal runs (SQLite's online copy, one read transaction: every write
    /// committed before it began is in it). A PostgreSQL portal is backed up with pg_dump
    /// (docs/PORTAL.md §Backups).
    Backup {
        /// Where the copy goes (readable by its owner alone).
        file: PathBuf,
    },
    /// Put a backup back into a stopped SQLite portal (its database replaced).
    ///
    /// The backup is checked first (SQLite's integrity check, the portal's tables); the
    /// portal must not run on the state directory. Gateways whose tokens changed since the
    /// backup are refused until their tokens are reset (docs/PORTAL.md §Backups).
    Restore {
        /// The backup.
        file: PathBuf,
    },
    /// A new NATS user key for the cluster: its seed written to FILE, its public key printed.
    ///
    /// The seed goes to FILE readable by its owner alone, for `[cluster] nats_nkey`; the public
    /// key is for the NATS server's configuration (docs/CLUSTER.md §Securing NATS). An existing
    /// FILE is kept.
    NatsNkey {
        /// Where the seed goes.
        file: PathBuf,
    },
}

#[derive(Debug, clap::Subcommand)]
enum UserCommand {
    /// Add a user; prints its sign-in secret once.
    Add {
        /// User name (unique within the account).
        name: String,
        #[arg(long)]
        account: String,
        #[arg(long)]
        role: Role,
        /// Print `{"user": …, "account": …, "role": …, "secret": …}`.
        #[arg(long)]
        json: bool,
    },
    /// The account's users.
    List(Listing),
    /// Disable a user: its keys and sessions stop working within a second.
    Disable {
        name: String,
        #[arg(long)]
        account: String,
    },
    /// A new sign-in secret for a user (printed once); the old one stops working.
    Reset {
        name: String,
        #[arg(long)]
        account: String,
        #[arg(long)]
        json: bool,
    },
    /// Give a user another role.
    Role {
        name: String,
        #[arg(long)]
        account: String,
        #[arg(long)]
        role: Role,
    },
}

#[derive(Debug, clap::Subcommand)]
enum KeyCommand {
    /// A new API key acting for a user with its role; printed once.
    Add {
        #[arg(long)]
        account: String,
        #[arg(long)]
        user: String,
        /// How long it works: `90d`, `12h` (default: until revoked).
        #[arg(long, value_parser = parse_lifetime)]
        expires: Option<std::time::Duration>,
        /// Print `{"api_key": …, "id": …}`.
        #[arg(long)]
        json: bool,
    },
    /// The account's users' keys (never the keys themselves).
    List(Listing),
    /// Revoke a key by its id: it stops working within a second.
    Revoke {
        id: String,
        #[arg(long)]
        account: String,
    },
}

/// What a `list` command lists, and how.
#[derive(Debug, clap::Args)]
struct Listing {
    #[arg(long)]
    account: String,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// `90d` or `12h`.
fn parse_lifetime(text: &str) -> Result<std::time::Duration, String> {
    let bad = || format!("{text:?}: a number of days or hours, like 90d or 12h");
    let Some((at, unit)) = text.char_indices().last() else {
        return Err(bad());
    };
    let n: u64 = text[..at].parse().map_err(|_| bad())?;
    let seconds = match unit {
        'd' => n.checked_mul(86_400),
        'h' => n.checked_mul(3_600),
        _ => None,
    };
    seconds
        .filter(|s| *s > 0)
        .map(std::time::Duration::from_secs)
        .ok_or_else(bad)
}

#[derive(Debug, clap::Subcommand)]
enum TokenCommand {
    /// Forget a lift's token: its gateway's next CONNECT is a first contact and gets a new one
    /// (for a replaced or wiped gateway, refused otherwise for the token it no longer has).
    Reset(LiftName),
}

#[derive(Debug, clap::Subcommand)]
enum LiftCommand {
    /// Retire a lift: its registry entry and everything stored of it (telemetry, events,
    /// alarms, subscriptions) are removed, audited; its gateway's next CONNECT is a first
    /// contact.
    Remove(LiftName),
}

/// A lift as an administrator names it.
#[derive(Debug, clap::Args)]
struct LiftName {
    /// Lift id `VENDORID-PRODUCTCODE-SERNUM`.
    lift: String,
    /// The lift's account (needed when lifts of several accounts have the id).
    #[arg(long)]
    account: Option<String>,
}

/// Domain tokens shorter than this need `--allow-short-domain-token` (docs/SECURITY.md
/// §Tenants).
use cloud::server::SHORT_DOMAIN_TOKEN;

#[derive(Debug, clap::Subcommand)]
enum AccountCommand {
    /// Create an account for the gateways of one domain token; prints its API key once.
    Add {
        /// Account name.
        name: String,
        /// The domain token its gateways send in CONNECT; default: a new random one (128 bits),
        /// printed.
        #[arg(long)]
        domain: Option<String>,
        /// Accept a domain token shorter than 16 characters (the protocol's examples use
        /// three): anyone who guesses it can add lifts to the account. Warned about at every
        /// start of the portal.
        #[arg(long)]
        allow_short_domain_token: bool,
        /// Print `{"account": …, "domain": …, "api_key": …}`.
        #[arg(long)]
        json: bool,
    },
}

const SECTIONS: [&str; 4] = ["server", "state", "database", "gateways"];

/// Run the portal, or an account command.
pub async fn run(args: CloudArgs) -> anyhow::Result<()> {
    let file = crate::config::or_installed(args.config, "portal");
    let config: Config = crate::config::load_document(file.as_deref(), &SECTIONS)?;
    if args.print_config {
        print!("{}", toml::to_string_pretty(&config)?);
        return Ok(());
    }
    match args.what {
        Some(CloudCommand::Account {
            what:
                AccountCommand::Add {
                    name,
                    domain,
                    allow_short_domain_token,
                    json,
                },
        }) => {
            let domain = domain.unwrap_or_else(|| cloud_store::secret("").to_uppercase());
            anyhow::ensure!(
                domain.chars().count() >= SHORT_DOMAIN_TOKEN || allow_short_domain_token,
                "a domain token of {} characters is a guess away from admitting lifts into the \
                 account: give one of at least {SHORT_DOMAIN_TOKEN}, leave --domain out for a random \
                 one, or add --allow-short-domain-token",
                domain.chars().count()
            );
            let store = store(&config).await?;
            let key = store.add_account(&name, &domain).await.with_context(|| {
                format!("adding account {name:?} (names and domains are unique)")
            })?;
            if json {
                println!(
                    "{}",
                    serde_json::json!({"account": name, "domain": domain, "api_key": key})
                );
            } else {
                println!("account {name} for domain {domain}\nAPI key (shown only now): {key}");
            }
            Ok(())
        }
        Some(CloudCommand::Token {
            what: TokenCommand::Reset(named),
        }) => {
            let store = store(&config).await?;
            let (account, key) = lift_named(&store, &named).await?;
            store
                .reset_token(&account.domain, &key, cloud_types::audit::BY_ADMINISTRATOR)
                .await?;
            println!(
                "{} of {}: token forgotten; the gateway's next connection is a first contact",
                named.lift, account.name
            );
            Ok(())
        }
        Some(CloudCommand::Lift {
            what: LiftCommand::Remove(named),
        }) => {
            let store = store(&config).await?;
            let (account, key) = lift_named(&store, &named).await?;
            store
                .retire(&account, &key, cloud_types::audit::BY_ADMINISTRATOR)
                .await?;
            println!(
                "{} of {}: retired with its data; its gateway's next connection is a first contact",
                named.lift, account.name
            );
            Ok(())
        }
        Some(CloudCommand::NatsNkey { file }) => nats_nkey(&file),
        Some(CloudCommand::Backup { file }) => backup(&config, &file).await,
        Some(CloudCommand::Restore { file }) => restore(&config, &file).await,
        Some(CloudCommand::User { what }) => users(&config, what).await,
        Some(CloudCommand::Key { what }) => keys(&config, what).await,
        None => {
            let portal = Portal::bind(&config, lift417::catalog::Catalog::builtin().names())
                .await
                .context("starting the portal")?;
            tracing::info!(listen = %portal.local_addr(), database = %cloud_store::shown_url(&config.database_url()), tls = tls::PROVIDER, "portal running");
            let reload = portal.tls_reload();
            crate::service::on_hangup("the TLS certificate, key and client CA", move || {
                reload.reload()
            });
            let status = format!("serving on {}", portal.local_addr());
            let (stop, stopped) = tokio::sync::watch::channel(false);
            let task = tokio::spawn(portal.run(stopped));
            crate::service::notify(crate::service::State::Ready(&status));
            crate::service::shutdown_signal().await;
            crate::service::notify(crate::service::State::Stopping);
            let _ = stop.send(true);
            let _ = task.await;
            Ok(())
        }
    }
}

/// The account and registry key of the lift an administrator named.
async fn lift_named(
    store: &cloud_store::Store,
    named: &LiftName,
) -> anyhow::Result<(cloud_types::users::Account, String)> {
    let mut owners = store.owners_of(&named.lift).await?;
    if let Some(account) = &named.account {
        owners.retain(|(a, _)| &a.name == account);
    }
    match owners.len() {
        0 => anyhow::bail!(
            "no lift {:?}{} in the registry",
            named.lift,
            named
                .account
                .as_ref()
                .map(|a| format!(" of account {a}"))
                .unwrap_or_default()
        ),
        1 => Ok(owners.remove(0)),
        _ => {
            let names: Vec<&str> = owners.iter().map(|(a, _)| a.name.as_str()).collect();
            anyhow::bail!(
                "lifts of several accounts have the id {:?} ({}): add --account",
                named.lift,
                names.join(", ")
            )
        }
    }
}

/// `canlift cloud backup FILE`.
async fn backup(config: &Config, file: &std::path::Path) -> anyhow::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    anyhow::ensure!(
        !file.exists(),
        "{} exists: a backup goes into a new file",
        file.display()
    );
    let started = std::time::Instant::now();
    let store = store(config).await?;
    store.backup_to(file).await?;
    // Secrets' digests, users' hashes, the registry: for the portal's owner alone.
    std::fs::set_permissions(file, std::fs::Permissions::from_mode(0o600))
        .with_context(|| format!("making {} readable by its owner alone", file.display()))?;
    let contents = cloud_store::backup::check(file).await?;
    println!(
        "{}: {} lifts, {} values, taken in {:.1} s",
        file.display(),
        contents.lifts,
        contents.values,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `canlift cloud restore FILE`.
async fn restore(config: &Config, file: &std::path::Path) -> anyhow::Result<()> {
    let database = config.database_url();
    let Some(path) = database
        .strip_prefix("sqlite://")
        .filter(|p| !p.contains(":memory:"))
        .map(|p| PathBuf::from(p.split('?').next().unwrap_or(p)))
    else {
        anyhow::bail!(
            "{}: a PostgreSQL portal is restored with pg_restore (docs/PORTAL.md §Backups)",
            cloud_store::shown_url(&database)
        );
    };
    let contents = cloud_store::backup::check(file)
        .await
        .with_context(|| format!("checking {}", file.display()))?;
    std::fs::create_dir_all(&config.state.dir)
        .with_context(|| format!("creating {}", config.state.dir.display()))?;
    // Held until the database is replaced: no portal starts on it meanwhile.
    let _lock = cloud::server::lock_state_dir(&config.state.dir).map_err(|e| match e.kind() {
        std::io::ErrorKind::WouldBlock => anyhow::anyhow!(
            "a portal runs on {}: stop it before restoring",
            config.state.dir.display()
        ),
        _ => anyhow::anyhow!("{}/portal.lock: {e}", config.state.dir.display()),
    })?;
    // Copied beside the database, then renamed over it (never half a database); the old
    // database's WAL must not be applied to the restored one.
    let staged = path.with_extension("restoring");
    std::fs::copy(file, &staged)
        .with_context(|| format!("copying {} to {}", file.display(), staged.display()))?;
    std::fs::File::open(&staged)?.sync_all()?;
    for suffix in ["-wal", "-shm"] {
        let side = PathBuf::from(format!("{}{suffix}", path.display()));
        match std::fs::remove_file(&side) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(e).with_context(|| format!("removing {}", side.display())),
        }
    }
    std::fs::rename(&staged, &path)
        .with_context(|| format!("moving {} to {}", staged.display(), path.display()))?;
    println!(
        "{} restored from {}: {} lifts, {} values. Gateways whose token changed since the backup \
         are refused (\"wrong cloud token\") until their token is reset: canlift cloud token reset LIFT",
        path.display(),
        file.display(),
        contents.lifts,
        contents.values
    );
    Ok(())
}

/// `canlift cloud nats-nkey FILE`.
fn nats_nkey(file: &std::path::Path) -> anyhow::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let (public, seed) = cloud_cluster::nats::new_user_nkey()?;
    // Created for its owner alone, never over an existing seed (which a NATS server may list).
    let mut out = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(file)
        .with_context(|| format!("creating {} (an existing file is kept)", file.display()))?;
    writeln!(out, "{seed}").with_context(|| format!("writing {}", file.display()))?;
    println!("{public}");
    Ok(())
}

/// The portal's database, opened by an administrator's command.
async fn store(config: &Config) -> anyhow::Result<Store> {
    std::fs::create_dir_all(&config.state.dir)
        .with_context(|| format!("creating {}", config.state.dir.display()))?;
    Ok(Store::open(&config.database_url()).await?)
}

/// `canlift cloud user …`.
async fn users(config: &Config, what: UserCommand) -> anyhow::Result<()> {
    let store = store(config).await?;
    match what {
        UserCommand::Add {
            name,
            account,
            role,
            json,
        } => {
            let secret = store.add_user(&account, &name, role).await?;
            print_secret(json, &name, &account, role, &secret);
        }
        UserCommand::List(Listing { account, json }) => {
            let users = store.users(&account).await?;
            if json {
                println!("{}", serde_json::to_string(&users)?);
            } else {
                println!("{:<24} {:<12} STATE", "USER", "ROLE");
                for u in users {
                    let state = if u.disabled { "disabled" } else { "enabled" };
                    println!("{:<24} {:<12} {state}", u.name, u.role.name());
                }
            }
        }
        UserCommand::Disable { name, account } => {
            store.disable_user(&account, &name).await?;
            println!("user {name} disabled: its keys and sessions no longer work");
        }
        UserCommand::Reset {
            name,
            account,
            json,
        } => {
            let (secret, role) = store.reset_user(&account, &name).await?;
            print_secret(json, &name, &account, role, &secret);
        }
        UserCommand::Role {
            name,
            account,
            role,
        } => {
            store.set_role(&account, &name, role).await?;
            println!("user {name} is now {role}");
        }
    }
    Ok(())
}

fn print_secret(json: bool, name: &str, account: &str, role: Role, secret: &str) {
    if json {
        let line =
            serde_json::json!({"user": name, "account": account, "role": role, "secret": secret});
        println!("{line}");
    } else {
        println!(
            "user {name} of account {account}, {role}\nsign-in secret (shown only now): {secret}"
        );
    }
}

/// `canlift cloud key …`.
async fn keys(config: &Config, what: KeyCommand) -> anyhow::Result<()> {
    let store = store(config).await?;
    match what {
        KeyCommand::Add {
            account,
            user,
            expires,
            json,
        } => {
            let until = expires.map(|d| {
                cloud_types::now_ms()
                    .saturating_add(i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
            });
            let (id, key) = store.add_key(&account, &user, until).await?;
            if json {
                println!("{}", serde_json::json!({"api_key": key, "id": id}));
            } else {
                println!(
                    "key {id} for {user} of account {account}\nAPI key (shown only now): {key}"
                );
            }
        }
        KeyCommand::List(Listing { account, json }) => {
            let keys = store.keys(&account).await?;
            if json {
                println!("{}", serde_json::to_string(&keys)?);
            } else {
                println!("{:<14} {:<24} {:<10} EXPIRES (ms)", "ID", "USER", "STATE");
                for k in keys {
                    let state = if k.revoked { "revoked" } else { "valid" };
                    let expires = k.expires.map_or("never".to_owned(), |e| e.to_string());
                    println!("{:<14} {:<24} {:<10} {expires}", k.id, k.user, state);
                }
            }
        }
        KeyCommand::Revoke { id, account } => {
            store.revoke_key(&account, &id).await?;
            println!("key {id} revoked");
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lifetimes() {
        assert_eq!(
            parse_lifetime("90d"),
            Ok(std::time::Duration::from_secs(90 * 86_400))
        );
        assert_eq!(
            parse_lifetime("12h"),
            Ok(std::time::Duration::from_secs(12 * 3_600))
        );
        for bad in ["", "d", "0d", "90", "90ä", "-1d", "99999999999999999d"] {
            assert!(parse_lifetime(bad).is_err(), "{bad:?}");
        }
    }
}
