//! `canlift lifts|get|put|watch`: the operator client of the portal's REST API (issue 7).

use std::path::PathBuf;

use anyhow::{bail, Context};
use cloud::client::Client;
use serde_json::{json, Value};

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
    fn client(&self) -> anyhow::Result<Client> {
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
    /// Object, `0x652001`.
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

fn check((status, body): (u16, Value)) -> anyhow::Result<Value> {
    if status == 200 {
        return Ok(body);
    }
    match (body.get("code"), body.get("message")) {
        (Some(_), Some(_)) => bail!("{status}: {}", nxg::errors::describe(&body)),
        _ => bail!("{status}: {body}"),
    }
}

fn query(node: &NodeArgs) -> String {
    let mut q = String::new();
    for (k, v) in [
        ("node", node.node.map(u32::from)),
        ("net", node.net.map(u32::from)),
        ("datatype", node.datatype),
    ] {
        if let Some(v) = v {
            q.push_str(&format!("&{k}={v}"));
        }
    }
    q
}

/// `canlift lifts`.
pub async fn lifts(args: LiftsArgs) -> anyhow::Result<()> {
    let lifts = check(
        args.portal
            .client()?
            .call("GET", "/api/v1/lifts", None)
            .await?,
    )?;
    if args.json {
        println!("{lifts}");
        return Ok(());
    }
    println!(
        "{:<32} {:<8} {:<22} {:<14} LAST SEEN (ms)",
        "LIFT", "ONLINE", "LIFTNUM", "SOFTWARE"
    );
    for l in lifts.as_array().into_iter().flatten() {
        println!(
            "{:<32} {:<8} {:<22} {:<14} {}",
            l["id"].as_str().unwrap_or(""),
            if l["online"] == true { "yes" } else { "no" },
            l["liftnum"].as_str().unwrap_or(""),
            l["software"].as_str().unwrap_or(""),
            l["last_seen"]
        );
    }
    Ok(())
}

/// `canlift get`.
pub async fn get(args: GetArgs) -> anyhow::Result<()> {
    let form = if args.naked {
        "naked"
    } else if args.stripped {
        "stripped"
    } else {
        "full"
    };
    let path = format!(
        "/api/v1/lifts/{}/objects/{}?form={form}&lang={}&compact={}{}",
        args.lift,
        args.mplex,
        args.lang,
        args.compact,
        query(&args.node)
    );
    let answer = check(args.portal.client()?.call("GET", &path, None).await?)?;
    println!("{}", serde_json::to_string_pretty(&answer)?);
    Ok(())
}

/// `canlift put`: data type and unit default to the object's, read with a stripped get.
pub async fn put(args: PutArgs) -> anyhow::Result<()> {
    let client = args.portal.client()?;
    let (datatype, physunit) = match (args.node.datatype, args.physunit) {
        (Some(t), Some(u)) => (t, u),
        (t, u) => {
            let path = format!(
                "/api/v1/lifts/{}/objects/{}?form=stripped{}",
                args.lift,
                args.mplex,
                query(&args.node)
            );
            let meta = check(client.call("GET", &path, None).await?)?;
            let known = |k: &str| meta["object"][k].as_u64().map(|v| v as u32);
            (
                t.or_else(|| known("datatype"))
                    .context("no datatype known; give --datatype")?,
                u.or_else(|| known("physunit")).unwrap_or(0),
            )
        }
    };
    let mut body = json!({"value": args.value, "datatype": datatype, "physunit": physunit});
    if let Some(n) = args.node.node {
        body["node"] = json!(n);
        body["net"] = json!(args.node.net.unwrap_or(1));
    }
    let path = format!("/api/v1/lifts/{}/objects/{}", args.lift, args.mplex);
    check(client.call("PUT", &path, Some(body)).await?)?;
    println!("{} {} = {}", args.lift, args.mplex, args.value);
    Ok(())
}

/// `canlift watch`: open the event stream, subscribe, then print `TIME MPLEX VALUE` per push.
pub async fn watch(args: WatchArgs) -> anyhow::Result<()> {
    let client = args.portal.client()?;
    let path = format!("/api/v1/lifts/{}/events", args.lift);
    let mut events = match client.events(&path).await? {
        Ok(stream) => stream,
        Err(answer) => {
            check(answer)?;
            bail!("no event stream");
        }
    };
    let body = json!({"mplex": args.mplex, "inhibit": args.inhibit, "threshold": args.threshold});
    let subscriptions = format!("/api/v1/lifts/{}/subscriptions", args.lift);
    check(
        client
            .call("POST", &subscriptions, Some(body.clone()))
            .await?,
    )?;
    let wanted: Vec<String> = args
        .mplex
        .iter()
        .map(|m| nxg::mplex::normalized(m))
        .collect();
    let mut seen = 0;
    let shutdown = crate::logging::shutdown_signal();
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
        let Ok(v) = serde_json::from_str::<Value>(&data) else {
            continue;
        };
        match event.as_str() {
            "value" => {
                let mplex = v["object"]["mplex"].as_str().unwrap_or("");
                if wanted.iter().any(|w| w == mplex) {
                    println!(
                        "{} {} {}",
                        cloud::store::now_ms(),
                        mplex,
                        v["object"]["value"].as_str().unwrap_or("")
                    );
                    seen += 1;
                }
            }
            "online" => eprintln!("{} online: {}", args.lift, v["online"]),
            _ => {}
        }
    }
    let _ = client.call("DELETE", &subscriptions, Some(body)).await;
    Ok(())
}
