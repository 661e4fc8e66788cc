//! `canlift cloud --config FILE`: the cloud portal (docs/PORTAL.md); `canlift cloud account add` creates
//! an operator account and prints its API key once; `canlift cloud token reset LIFT` forgets a
//! lift's cloud token in the portal's database (the administrator's way, no API key needed).

use std::path::PathBuf;

use anyhow::Context;
use cloud::config::Config;
use cloud::server::Portal;
use cloud::store::Store;

/// Command-line arguments of `canlift cloud`.
#[derive(Debug, clap::Args)]
pub struct CloudArgs {
    /// Configuration file (TOML: `[server]`, `[state]`, `[database]`, `[gateways]`).
    #[arg(long, global = true)]
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
}

#[derive(Debug, clap::Subcommand)]
enum TokenCommand {
    /// Forget a lift's token: its gateway's next CONNECT is a first contact and gets a new one
    /// (for a replaced or wiped gateway, refused otherwise for the token it no longer has).
    Reset {
        /// Lift id `VENDORID-PRODUCTCODE-SERNUM`.
        lift: String,
    },
}

#[derive(Debug, clap::Subcommand)]
enum AccountCommand {
    /// Create an account for the gateways of one domain token; prints its API key once.
    Add {
        /// Account name.
        name: String,
        /// The domain token its gateways send in CONNECT.
        #[arg(long)]
        domain: String,
        /// Print `{"account": …, "api_key": …}`.
        #[arg(long)]
        json: bool,
    },
}

const SECTIONS: [&str; 4] = ["server", "state", "database", "gateways"];

/// Run the portal, or an account command.
pub async fn run(args: CloudArgs) -> anyhow::Result<()> {
    let config: Config = crate::config::load_document(args.config.as_deref(), &SECTIONS)?;
    if args.print_config {
        print!("{}", toml::to_string_pretty(&config)?);
        return Ok(());
    }
    match args.what {
        Some(CloudCommand::Account {
            what: AccountCommand::Add { name, domain, json },
        }) => {
            std::fs::create_dir_all(&config.state.dir)
                .with_context(|| format!("creating {}", config.state.dir.display()))?;
            let store = Store::open(&config.database_url()).await?;
            let key = store.add_account(&name, &domain).await.with_context(|| {
                format!("adding account {name:?} (names and domains are unique)")
            })?;
            if json {
                println!("{}", serde_json::json!({"account": name, "api_key": key}));
            } else {
                println!("account {name} for domain {domain}\nAPI key (shown only now): {key}");
            }
            Ok(())
        }
        Some(CloudCommand::Token {
            what: TokenCommand::Reset { lift },
        }) => {
            let store = Store::open(&config.database_url()).await?;
            let domain = store
                .domain_of(&lift)
                .await?
                .with_context(|| format!("no lift {lift:?} in the registry"))?;
            store
                .reset_token(&domain, &lift, cloud::store::BY_ADMINISTRATOR)
                .await?;
            println!("{lift}: token forgotten; the gateway's next connection is a first contact");
            Ok(())
        }
        None => {
            let portal = Portal::bind(&config, lift417::catalog::Catalog::builtin().names())
                .await
                .context("starting the portal")?;
            tracing::info!(listen = %portal.local_addr(), database = %config.database_url(), "portal running");
            let (stop, stopped) = tokio::sync::watch::channel(false);
            let task = tokio::spawn(portal.run(stopped));
            crate::logging::shutdown_signal().await;
            let _ = stop.send(true);
            let _ = task.await;
            Ok(())
        }
    }
}
