//! `canlift lifts|get|put|watch|elevate`: the operator client of the portal's REST API
//! (docs/PORTAL.md §Command-line client), reading and writing the API's own types.

use std::path::PathBuf;

use anyhow::{bail, Context};
use cloud::client::Client;
use cloud_types::api::{EventsQuery, Form, GetQuery, LiftSummary, PrivilegeBody, PutBody};
use cloud_types::live::ValueMessage;
use nxg::msg::{ElevateAnswer, ObjectAnswer};
use serde::de::DeserializeOwned;
use serde_json::Value;

/// Where the portal is and who is asking.
#[derive(Debug, Clone, clap::Args)]
pub struct PortalArgs {
    /// The portal, `https://HOST[:PORT]`.
    #[arg(
        long,
        env = "CANLIFT_PORTAL",
        default_value = "https://127.0.0.1:8443",
        global = true
    )]
    portal: String,
    /// The account's API key.
    #[arg(long, env = "CANLIFT_API_KEY", global = true, hide_env_values = true)]
    api_key: Option<String>,
    /// CA certificate to trust (the portal's development CA, for instance); system roots otherwise.
    #[arg(long, env = "CANLIFT_CA", global = true)]
    ca: Option<PathBuf>,
}

impl PortalArgs {
    pub(crate) fn client(&self) -> anyhow::Result<Client> {
        let key = self
            .api_key
            .as_deref()
            .context("an API key is needed: --api-key or CANLIFT_API_KEY")?;
        Ok(Client::new(&self.portal, Some(key), self.ca.as_deref())?)
    }
}

/// `canlift lifts`.
#[derive(Debug, clap::Args)]
pub struct LiftsArgs {
    #[command(flatten)]
    portal: PortalArgs,
    /// Print the JSON answer.
    #[arg(long)]
    json: bool,
}

/// Which node a request is for.
#[derive(Debug, Clone, clap::Args)]
pub struct NodeArgs {
    /// Another node than the lift controller.
    #[arg(long)]
    node: Option<u8>,
    /// Its CAN network (1 = the gateway's bus).
    #[arg(long)]
    net: Option<u8>,
    /// Its data type (for nodes without an EDS on the gateway).
    #[arg(long)]
    datatype: Option<u32>,
}

/// `canlift get LIFT MPLEX`.
#[derive(Debug, clap::Args)]
pub struct GetArgs {
    /// Lift id `VENDORID-PRODUCTCODE-SERNUM` (see `canlift lifts`).
    lift: String,
    /// Object: `0x652001`, `0x6520:1`, `6520sub1` or a catalog name ("Trip counter").
    mplex: String,
    #[command(flatten)]
    node: NodeArgs,
    /// Language of names and hints.
    #[arg(long, default_value = "en")]
    lang: String,
    /// Only the value.
    #[arg(long, conflicts_with = "stripped")]
    naked: bool,
    /// Without names, hints and lists.
    #[arg(long)]
    stripped: bool,
    /// All elements of an array (mplex with sub-index 1).
    #[arg(long)]
    compact: bool,
    #[command(flatten)]
    portal: PortalArgs,
}

/// `canlift put LIFT MPLEX VALUE`.
#[derive(Debug, clap::Args)]
pub struct PutArgs {
    /// Lift id.
    lift: String,
    /// Object.
    mplex: String,
    /// Value in the connector's text form.
    value: String,
    #[command(flatten)]
    node: NodeArgs,
    /// Physical unit the caller expects (default: the object's, read first).
    #[arg(long)]
    physunit: Option<u32>,
    #[command(flatten)]
    portal: PortalArgs,
}

/// `canlift elevate LIFT --level service|setup`: the lift's password is read from
/// `CANLIFT_LIFT_PASSWORD` or, without it, the first line of standard input — never from the
/// command line, where other users of the machine could read it.
#[derive(Debug, clap::Args)]
pub struct ElevateArgs {
    /// Lift id.
    lift: String,
    /// The rights wanted (NXg §8.4): `service` (1) or `setup` (2).
    #[arg(long, value_enum)]
    level: Level,
    #[command(flatten)]
    portal: PortalArgs,
}

/// A level of rights `canlift elevate` asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Level {
    /// Privilege 1.
    Service,
    /// Privilege 2.
    Setup,
}

/// `canlift watch LIFT MPLEX…`.
#[derive(Debug, clap::Args)]
pub struct WatchArgs {
    /// Lift id.
    lift: String,
    /// Objects to watch.
    #[arg(required = true)]
    mplex: Vec<String>,
    /// Minimum gap between two pushes of one object (ms).
    #[arg(long, default_value_t = 0)]
    inhibit: u64,
    /// Smallest change pushed.
    #[arg(long, default_value_t = 0.0)]
    threshold: f64,
    /// Stop after this many values (0: until Ctrl-C).
    #[arg(long, default_value_t = 0)]
    count: usize,
    #[command(flatten)]
    portal: PortalArgs,
}

/// The body of a 2xx answer as a `T`; any other answer is an error with the portal's message,
/// and the exit status it means (docs/PORTAL.md §Command-line client).
pub(crate) fn check<T: DeserializeOwned>((status, body): (u16, Value)) -> anyhow::Result<T> {
    if !(200..300).contains(&status) {
        return Err(super::exit::Refused::of(status, &body).into());
    }
    serde_json::from_value(body).context("the portal's answer is not what the API documents")
}

/// The query of a read for `node`.
fn query(node: &NodeArgs, form: Form) -> GetQuery {
    GetQuery {
        form: Some(form),
        node: node.node,
        net: node.net,
        datatype: node.datatype,
        ..GetQuery::default()
    }
}

fn object_path(lift: &str, mplex: &str, query: &GetQuery) -> anyhow::Result<String> {
    let query = serde_urlencoded::to_string(query)?;
    Ok(format!("/api/v1/lifts/{lift}/objects/{mplex}?{query}"))
}

/// `canlift token rotate|reset LIFT`.
#[derive(Debug, clap::Args)]
pub struct TokenArgs {
    #[command(subcommand)]
    what: TokenCommand,
    #[command(flatten)]
    portal: PortalArgs,
}

#[derive(Debug, clap::Subcommand)]
enum TokenCommand {
    /// Send the online gateway a new cloud token now (NXg §5.4); the old one stops counting.
    Rotate {
        /// Lift id `VENDORID-PRODUCTCODE-SERNUM`.
        lift: String,
    },
    /// Forget the lift's token: its gateway's next CONNECT is a first contact and gets a new
    /// one (for a replaced or wiped gateway, which its old token no longer proves).
    Reset {
        /// Lift id `VENDORID-PRODUCTCODE-SERNUM`.
        lift: String,
    },
}

/// `canlift token`.
pub async fn token(args: TokenArgs) -> anyhow::Result<()> {
    let (method, lift, done) = match &args.what {
        TokenCommand::Rotate { lift } => ("POST", lift, "the gateway stored a new token"),
        TokenCommand::Reset { lift } => (
            "DELETE",
            lift,
            "token forgotten: the gateway's next connection is a first contact",
        ),
    };
    let path = format!("/api/v1/lifts/{lift}/token");
    check::<Value>(args.portal.client()?.call(method, &path, None).await?)?;
    println!("{lift}: {done}");
    Ok(())
}

/// `canlift lifts`.
pub async fn lifts(args: LiftsArgs) -> anyhow::Result<()> {
    let answer = args
        .portal
        .client()?
        .call("GET", "/api/v1/lifts", None)
        .await?;
    if args.json {
        println!("{}", check::<Value>(answer)?);
        return Ok(());
    }
    let lifts: Vec<LiftSummary> = check(answer)?;
    println!(
        "{:<32} {:<8} {:<22} {:<14} LAST SEEN",
        "LIFT", "ONLINE", "LIFTNUM", "SOFTWARE"
    );
    for l in &lifts {
        let r = &l.record;
        println!(
            "{:<32} {:<8} {:<22} {:<14} {}",
            r.id,
            if l.online { "yes" } else { "no" },
            r.liftnum,
            r.software,
            super::local_time::of_ms(r.last_seen)
        );
    }
    Ok(())
}

/// `canlift get`.
pub async fn get(mut args: GetArgs) -> anyhow::Result<()> {
    args.mplex = object(&args.mplex)?;
    let form = if args.naked {
        Form::Naked
    } else if args.stripped {
        Form::Stripped
    } else {
        Form::Full
    };
    let query = GetQuery {
        lang: Some(args.lang.clone()),
        compact: Some(args.compact),
        ..query(&args.node, form)
    };
    let path = object_path(&args.lift, &args.mplex, &query)?;
    let answer: ObjectAnswer = check(args.portal.client()?.call("GET", &path, None).await?)?;
    println!("{}", serde_json::to_string_pretty(&answer)?);
    Ok(())
}

/// The object as the portal takes it: an mplex as written, any other address form or a catalog
/// name (`"Trip counter"`, docs/TOOLS.md) as the mplex it stands for.
fn object(text: &str) -> anyhow::Result<String> {
    if nxg::mplex::Mplex::parse(text).is_ok() {
        return Ok(text.to_owned());
    }
    Ok(super::address::Names::catalog()
        .resolve(text)?
        .mplex
        .to_string())
}

/// `canlift put`: data type and unit default to the object's, read with a stripped get.
pub async fn put(mut args: PutArgs) -> anyhow::Result<()> {
    args.mplex = object(&args.mplex)?;
    let client = args.portal.client()?;
    let (datatype, physunit) = match (args.node.datatype, args.physunit) {
        (Some(t), Some(u)) => (t, u),
        (t, u) => {
            let path = object_path(&args.lift, &args.mplex, &query(&args.node, Form::Stripped))?;
            let meta: ObjectAnswer = check(client.call("GET", &path, None).await?)?;
            (
                t.or(meta.object.datatype)
                    .context("no datatype known; give --datatype")?,
                u.or(meta.object.physunit).unwrap_or(0),
            )
        }
    };
    let body = PutBody {
        value: args.value.clone(),
        datatype,
        physunit,
        node: args.node.node,
        net: args.node.node.map(|_| args.node.net.unwrap_or(1)),
    };
    let path = format!("/api/v1/lifts/{}/objects/{}", args.lift, args.mplex);
    check::<Value>(
        client
            .call("PUT", &path, Some(serde_json::to_value(&body)?))
            .await?,
    )?;
    println!("{} {} = {}", args.lift, args.mplex, args.value);
    Ok(())
}

/// `canlift elevate`: ask the lift for `service` or `setup` rights for this API key's user
/// (docs/PORTAL.md §Command-line client); the writes that follow within the grant may change
/// objects of that privilege.
pub async fn elevate(args: ElevateArgs) -> anyhow::Result<()> {
    let password = match std::env::var("CANLIFT_LIFT_PASSWORD") {
        Ok(p) => p,
        Err(_) => {
            let mut line = String::new();
            std::io::stdin()
                .read_line(&mut line)
                .context("reading the lift's password from standard input")?;
            line.trim_end_matches(['\r', '\n']).to_owned()
        }
    };
    if password.is_empty() {
        bail!("no password: set CANLIFT_LIFT_PASSWORD or give it on standard input");
    }
    let (privilege, name) = match args.level {
        Level::Service => (1, "service"),
        Level::Setup => (2, "setup"),
    };
    let body = PrivilegeBody {
        privilege,
        password,
    };
    let path = format!("/api/v1/lifts/{}/privilege", args.lift);
    let client = args.portal.client()?;
    let granted: ElevateAnswer = check(
        client
            .call("POST", &path, Some(serde_json::to_value(&body)?))
            .await?,
    )?;
    println!("{}: {name} rights for {} s", args.lift, granted.duration);
    Ok(())
}

/// `canlift watch`: open the event stream, subscribe, then print `TIME MPLEX VALUE` per push.
pub async fn watch(mut args: WatchArgs) -> anyhow::Result<()> {
    args.mplex = args
        .mplex
        .iter()
        .map(|m| object(m))
        .collect::<anyhow::Result<_>>()?;
    let client = args.portal.client()?;
    // The stream holds the subscriptions while it is open: ending it, however, lets go of them
    // and of nothing anyone else holds.
    let query = serde_urlencoded::to_string(EventsQuery {
        mplex: Some(args.mplex.join(",")),
        inhibit: Some(args.inhibit),
        threshold: Some(args.threshold),
    })?;
    let path = format!("/api/v1/lifts/{}/events?{query}", args.lift);
    let mut events = match client.events(&path).await? {
        Ok(stream) => stream,
        Err(answer) => {
            check::<Value>(answer)?;
            bail!("no event stream");
        }
    };
    let wanted: Vec<String> = args
        .mplex
        .iter()
        .map(|m| nxg::mplex::normalized(m))
        .collect();
    let mut seen = 0;
    let shutdown = crate::service::shutdown_signal();
    tokio::pin!(shutdown);
    while args.count == 0 || seen < args.count {
        let next = tokio::select! {
            next = events.next() => next,
            _ = &mut shutdown => break,
        };
        let Some(next) = next else {
            bail!("the portal ended the event stream");
        };
        let (event, data) = next?;
        match event.as_str() {
            "value" => {
                let Ok(v) = serde_json::from_str::<ValueMessage>(&data) else {
                    continue;
                };
                if wanted.contains(&v.object.mplex) {
                    println!(
                        "{} {} {}",
                        super::local_time::of_ms(cloud_types::now_ms()),
                        v.object.mplex,
                        v.object.value
                    );
                    seen += 1;
                }
            }
            "online" => {
                if let Ok(o) = serde_json::from_str::<cloud_types::live::OnlineMessage>(&data) {
                    eprintln!("{} online: {}", args.lift, o.online);
                }
            }
            _ => {}
        }
    }
    Ok(())
}
