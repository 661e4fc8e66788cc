//! `canlift alarms [ack ID]` and `canlift events LIFT`: the account's alarms and a lift's bus
//! events through the portal's REST API (docs/PORTAL.md §Alarms).

use cloud_types::alarms::Alarm;
use cloud_types::api::{AckBody, AlarmList, AlarmState, AlarmsQuery, EventLog, EventLogQuery};
use nxg::msg::Event;
use serde_json::Value;

use super::operator::{check, PortalArgs};

/// `canlift alarms`.
#[derive(Debug, clap::Args)]
pub struct AlarmsArgs {
    #[command(subcommand)]
    action: Option<AlarmsAction>,
    /// Every alarm, cleared ones too (default: the active ones).
    #[arg(long)]
    all: bool,
    /// One lift's only.
    #[arg(long)]
    lift: Option<String>,
    /// Print the JSON answer.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    portal: PortalArgs,
}

/// What to do with an alarm.
#[derive(Debug, clap::Subcommand)]
enum AlarmsAction {
    /// Acknowledge an alarm: you have taken it on.
    Ack {
        /// The alarm's id.
        id: i64,
        /// What you say about it.
        #[arg(long, default_value = "")]
        comment: String,
    },
}

/// `canlift events`.
#[derive(Debug, clap::Args)]
pub struct EventsArgs {
    /// The lift's id.
    lift: String,
    /// From this time on (RFC 3339 or ms since the epoch); default: the newest.
    #[arg(long)]
    since: Option<String>,
    /// At most this many.
    #[arg(long, default_value_t = 100)]
    limit: u32,
    /// Print the JSON answer.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    portal: PortalArgs,
}

fn row(a: &Alarm) -> String {
    let place = match a.node {
        Some(p) => match p.id {
            Some(id) => format!("node {id}/{}", p.net),
            None => format!("net {}", p.net),
        },
        None => "gateway".into(),
    };
    let state = match (&a.cleared, &a.acknowledged) {
        (Some(c), _) => format!("cleared {}", super::local_time::of_rfc3339(c)),
        (None, Some(ack)) => format!("acknowledged by {}", ack.by),
        (None, None) => "active".into(),
    };
    format!(
        "{:<17} {:<9} {:<32} {:<12} {:<25} {} — {}",
        a.id,
        a.severity.name(),
        a.lift,
        place,
        super::local_time::of_rfc3339(&a.raised),
        a.text,
        state
    )
}

/// `canlift alarms`.
pub async fn alarms(args: AlarmsArgs) -> anyhow::Result<()> {
    let client = args.portal.client()?;
    if let Some(AlarmsAction::Ack { id, comment }) = args.action {
        let body = serde_json::to_value(AckBody { comment })?;
        let path = format!("/api/v1/alarms/{id}/ack");
        let alarm: Alarm = check(client.call("POST", &path, Some(body)).await?)?;
        println!("{}", row(&alarm));
        return Ok(());
    }
    let query = AlarmsQuery {
        state: Some(if args.all {
            AlarmState::All
        } else {
            AlarmState::Active
        }),
        lift: args.lift,
        limit: None,
    };
    let path = format!("/api/v1/alarms?{}", serde_urlencoded::to_string(&query)?);
    let answer = client.call("GET", &path, None).await?;
    if args.json {
        println!("{}", check::<Value>(answer)?);
        return Ok(());
    }
    let list: AlarmList = check(answer)?;
    if list.alarms.is_empty() {
        println!("no {}alarm", if args.all { "" } else { "active " });
    }
    for a in &list.alarms {
        println!("{}", row(a));
    }
    Ok(())
}

/// `canlift events`.
pub async fn events(args: EventsArgs) -> anyhow::Result<()> {
    let query = EventLogQuery {
        since: args.since,
        limit: Some(args.limit),
    };
    let path = format!(
        "/api/v1/lifts/{}/event-log?{}",
        args.lift,
        serde_urlencoded::to_string(&query)?
    );
    let answer = args.portal.client()?.call("GET", &path, None).await?;
    if args.json {
        println!("{}", check::<Value>(answer)?);
        return Ok(());
    }
    let log: EventLog = check(answer)?;
    for e in &log.events {
        let local = super::local_time::of_rfc3339;
        let line = match e {
            Event::Emcy {
                node,
                time,
                code,
                register,
                text,
                ..
            } => format!(
                "{} EMCY  node {}/{} {code} register {register} {text}",
                local(time),
                node.id.get(),
                node.net
            ),
            Event::State { node, time, state } => format!(
                "{} STATE node {}/{} {}",
                local(time),
                node.id.get(),
                node.net,
                state.name()
            ),
            Event::Bus { net, time, state } => {
                format!("{} BUS   net {net} {}", local(time), state.name())
            }
        };
        println!("{line}");
    }
    Ok(())
}
