//! Lift insights against the real portal (docs/PORTAL.md §Availability, §Monthly report,
//! §Trends): a timeline injected at known times gives the figures computed by hand, to the
//! second, on SQLite and PostgreSQL; a connection's state pushes become the lift's statuses;
//! a simulator whose door wears raises a trend alarm before its door fails, and one whose door
//! does not raises none.

use std::time::Duration;

use cloud::config::TrendRule;
use cloud_store::{StatusRow, TelemetryRow};
use cloud_types::alarms::{Alarm, Condition, Kind, Place, Severity};
use cloud_types::insights::Status::{self, *};
use futures_util::SinkExt;
use serde_json::{json, Value};
use testkit::portal::{until, Rig};
use tokio_tungstenite::tungstenite::Message;

const H: i64 = 3_600_000;
const M: i64 = 60_000;
/// 2026-03-01T00:00:00Z: the day the timeline is about.
const D: i64 = 1_772_323_200_000;

/// The registry key of the lift of `domain` whose gateway has `sernum`.
async fn key(rig: &Rig, domain: &str, sernum: &str) -> String {
    let lifts = rig.store().await.lifts(domain).await.expect("lifts");
    lifts
        .into_iter()
        .find(|l| l.id.ends_with(sernum))
        .expect("the lift is registered")
        .id
}

fn emcy(lift: &str, code: &str, at: i64) -> Alarm {
    let condition = Condition {
        lift: lift.into(),
        kind: Kind::Emcy,
        place: Some(Place {
            id: Some(1),
            net: 1,
        }),
        code: code.into(),
    };
    Alarm::raised(
        cloud_store::new_id(),
        &condition,
        Severity::Major,
        "fault",
        at,
    )
}

fn value(lift: &str, mplex: &str, value: u32, at: i64) -> TelemetryRow {
    TelemetryRow {
        lift: lift.into(),
        mplex: mplex.into(),
        node: 0,
        value: value.to_string(),
        at,
    }
}

/// Write the day's timeline of `lift`: statuses, faults and counters at known times.
async fn inject(rig: &Rig, lift: &str) {
    let store = rig.store().await;
    let statuses: Vec<StatusRow> = [
        (D - 5 * H, InService),
        (D + 2 * H, OutOfService),
        (D + 3 * H + 30 * M, InService),
        (D + 10 * H, Offline),
        (D + 11 * H, Unknown),
        (D + 11 * H + 15 * M, InService),
        (D + 20 * H, OutOfService),
        (D + 26 * H, InService),
    ]
    .into_iter()
    .map(|(at, status)| StatusRow {
        lift: lift.into(),
        at,
        status,
    })
    .collect();
    let faults = [
        emcy(lift, "0x1000", D - H), // before the period
        emcy(lift, "0xFF01", D + 2 * H),
        emcy(lift, "0xF001", D + 20 * H),
        emcy(lift, "0x2000", D + 24 * H), // at its end: not in it
    ];
    store
        .write_alarm_batch(&[], &statuses, &faults, &[])
        .await
        .expect("the timeline is written");
    store
        .telemetry(&[
            value(lift, "0x652001", 1000, D - H),
            value(lift, "0x652001", 1200, D + 12 * H),
            value(lift, "0x652001", 1350, D + 23 * H),
            value(lift, "0x652001", 1500, D + 25 * H),
            value(lift, "0x440001", 5000, D - 2 * H),
            value(lift, "0x440001", 5300, D + 23 * H + 59 * M),
        ])
        .await
        .expect("the counters are written");
}

fn hours(h: f64) -> Value {
    json!(h * 3600.0)
}

/// Each figure of the day and of a period cut inside it, as computed by hand.
async fn figures_are_those_computed_by_hand(rig: Rig) {
    rig.hand_made_gateway("AVAIL-1", "MAS").await;
    rig.hand_made_gateway("AVAIL-2", "MAS").await;
    rig.hand_made_gateway("AVAIL-3", "OTH").await;
    let lift = key(&rig, "MAS", "AVAIL-1").await;
    inject(&rig, &lift).await;
    let other = key(&rig, "OTH", "AVAIL-3").await;
    inject(&rig, &other).await;

    let day =
        "/api/v1/reports/availability?from=2026-03-01T00:00:00Z&to=2026-03-02T01:00:00%2B01:00";
    let (status, report) = rig.call("GET", day, Some(&rig.key), None).await;
    assert_eq!(status, 200, "{report}");
    assert_eq!(report["from"], "2026-03-01T00:00:00.000Z");
    assert_eq!(report["to"], "2026-03-02T00:00:00.000Z");
    let lifts = report["lifts"].as_array().expect("lifts");
    let ids: Vec<&str> = lifts.iter().filter_map(|l| l["lift"].as_str()).collect();
    assert!(ids.contains(&"1050-4096-AVAIL-2"), "{ids:?}");
    assert!(
        !ids.iter().any(|id| id.contains("AVAIL-3")),
        "another account's lift is not in the report: {ids:?}"
    );
    let f = lifts
        .iter()
        .find(|l| l["lift"] == "1050-4096-AVAIL-1")
        .expect("the lift");
    // In service 0–2 h, 3.5–10 h, 11.25–20 h; out of service 2–3.5 h and 20–24 h (cut).
    assert_eq!(f["in_service_s"], hours(17.25));
    assert_eq!(f["out_of_service_s"], hours(5.5));
    assert_eq!(f["offline_s"], hours(1.0));
    assert_eq!(f["unknown_s"], hours(0.25));
    assert_eq!(f["availability"], json!(17.25 / 22.75));
    assert_eq!(f["faults"], 2);
    assert_eq!(f["faults_by_kind"], json!({"0xF001": 1, "0xFF01": 1}));
    assert_eq!(f["trips"], 350);
    assert_eq!(f["faults_per_1000_trips"], json!(2.0 * 1000.0 / 350.0));
    assert_eq!(f["mtbf_s"], hours(17.25 / 2.0));
    assert_eq!(f["mttr_s"], hours(5.5 / 2.0));
    assert_eq!(f["door_cycles"], 300);
    assert_eq!(f["reopenings"], Value::Null, "never stored");
    let empty = lifts
        .iter()
        .find(|l| l["lift"] == "1050-4096-AVAIL-2")
        .expect("the second lift");
    assert_eq!(empty["availability"], Value::Null);
    assert_eq!(empty["unknown_s"], hours(24.0));

    // Cut at both edges inside outages: 3 h (out of service since 2 h) to 21 h (since 20 h).
    let cut = "/api/v1/reports/availability?from=2026-03-01T03:00:00Z&to=2026-03-01T21:00:00Z&lift=1050-4096-AVAIL-1";
    let (status, report) = rig.call("GET", cut, Some(&rig.key), None).await;
    assert_eq!(status, 200, "{report}");
    let f = &report["lifts"][0];
    assert_eq!(report["lifts"].as_array().map(Vec::len), Some(1));
    assert_eq!(f["in_service_s"], hours(15.25));
    assert_eq!(f["out_of_service_s"], hours(1.5));
    assert_eq!(f["offline_s"], hours(1.0));
    assert_eq!(f["unknown_s"], hours(0.25));
    assert_eq!(f["faults"], 1);
    assert_eq!(f["trips"], 200);
    assert_eq!(f["mtbf_s"], hours(15.25), "one failure began inside");
    assert_eq!(f["mttr_s"], hours(0.75), "two outages overlap it");

    // The CSV says what the JSON says.
    let (status, csv) = rig
        .call("GET", &format!("{day}&format=csv"), Some(&rig.key), None)
        .await;
    assert_eq!(status, 200, "{csv}");
    let csv = csv.as_str().expect("a text answer");
    let (_, report) = rig.call("GET", day, Some(&rig.key), None).await;
    let mut rows = csv.lines();
    let header: Vec<&str> = rows.next().expect("a header").split(',').collect();
    assert_eq!(header, cloud_types::insights::CSV_COLUMNS);
    for (row, lift) in rows.zip(report["lifts"].as_array().expect("lifts")) {
        let fields: Vec<&str> = row.split(',').collect();
        for (name, field) in header.iter().zip(&fields) {
            let json = &lift[*name];
            let expected = match json {
                Value::Null => String::new(),
                Value::String(s) => s.clone(),
                Value::Object(kinds) => kinds
                    .iter()
                    .map(|(k, n)| format!("{k}={n}"))
                    .collect::<Vec<_>>()
                    .join(";"),
                Value::Number(n) => match n.as_f64() {
                    Some(f) if f.fract() != 0.0 || n.is_f64() => {
                        assert_eq!(field.parse::<f64>().ok(), Some(f), "{name}: {field}");
                        continue;
                    }
                    _ => n.to_string(),
                },
                other => other.to_string(),
            };
            assert_eq!(*field, expected, "{name}");
        }
    }

    // Bounds and strangers.
    for (path, expected) in [
        (
            "/api/v1/reports/availability?from=2026-03-02T00:00:00Z&to=2026-03-01T00:00:00Z",
            400,
        ),
        (
            "/api/v1/reports/availability?from=2026-01-01T00:00:00Z&to=2027-03-01T00:00:00Z",
            400,
        ),
        (
            "/api/v1/reports/availability?from=yesterday&to=2026-03-01T00:00:00Z",
            400,
        ),
        (
            "/api/v1/reports/availability?from=0&to=1000&format=xml",
            400,
        ),
        (
            "/api/v1/reports/availability?from=0&to=1000&lift=1050-4096-AVAIL-3",
            404,
        ),
        ("/api/v1/reports/monthly?month=2026-13", 400),
    ] {
        let (status, body) = rig.call("GET", path, Some(&rig.key), None).await;
        assert_eq!(status, expected, "{path}: {body}");
    }

    // The month: the account's availability against its target, the worst lift first.
    let (status, _) = rig
        .call(
            "PUT",
            "/api/v1/reports/target",
            Some(&rig.key),
            Some(json!({"target": 0.995})),
        )
        .await;
    assert_eq!(status, 200);
    let (status, month) = rig
        .call(
            "GET",
            "/api/v1/reports/monthly?month=2026-03",
            Some(&rig.key),
            None,
        )
        .await;
    assert_eq!(status, 200, "{month}");
    assert_eq!(month["target"], json!(0.995));
    assert_eq!(month["lifts"][0]["lift"], "1050-4096-AVAIL-1");
    // The rest of March in service after the outage that ended at 26 h.
    let up = 17.25 * 3600.0 + (31.0 * 24.0 - 26.0) * 3600.0;
    let down = 7.5 * 3600.0;
    assert_eq!(month["availability"], json!(up / (up + down)));
    assert_eq!(
        month["trend"]
            .as_array()
            .map(|t| t.iter().map(|m| m["month"].clone()).collect::<Vec<_>>()),
        Some(vec![json!("2025-12"), json!("2026-01"), json!("2026-02")])
    );
    assert_eq!(
        month["trend"][2]["availability"],
        json!(1.0),
        "in service since Feb 28th"
    );
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn availability_figures_are_those_computed_by_hand_on_sqlite() {
    figures_are_those_computed_by_hand(Rig::builder().without_lift().start().await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn availability_figures_are_those_computed_by_hand_on_postgres() {
    let Some(url) = testkit::postgres("insights").await else {
        return;
    };
    let rig = Rig::builder()
        .database(Some(url.to_string()))
        .without_lift()
        .start()
        .await;
    figures_are_those_computed_by_hand(rig).await;
}

/// The statuses of `lift` as written, oldest first.
async fn statuses(rig: &Rig, lift: &str) -> Vec<Status> {
    let store = rig.store().await;
    let lifts = cloud_store::Lifts {
        domain: "MAS",
        lift: Some(lift),
    };
    let timelines = store
        .timelines(lifts, 0, cloud_types::LATEST_MS)
        .await
        .expect("timelines");
    timelines
        .get(lift)
        .map(|t| t.changes.iter().map(|c| c.1).collect())
        .unwrap_or_default()
}

/// A connection's life becomes the lift's statuses: unknown when it connects, in or out of
/// service as its state object says, offline when it goes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_and_its_state_pushes_become_the_lifts_statuses() {
    let rig = Rig::builder()
        .without_lift()
        .portal(|c| c.dashboard.inhibit_ms = 0)
        .start()
        .await;
    let mut ws = rig.hand_made_gateway("STATUS-1", "MAS").await;
    let lift = key(&rig, "MAS", "STATUS-1").await;
    let push = |value: &str| {
        Message::Text(
            json!({"jsonrpc": "2.0", "method": "canopen_object", "result": {"mplex": "0x502400", "value": value}})
                .to_string()
                .into(),
        )
    };
    // Idle, travelling (still in service: one status), out of service, in service again.
    for value in ["0", "1", "4", "5", "3"] {
        ws.send(push(value)).await.expect("sent");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(ws);
    let expected = [Unknown, InService, OutOfService, InService, Offline];
    until(
        Duration::from_secs(10),
        "the statuses are written",
        || async { statuses(&rig, &lift).await == expected },
    )
    .await;
    rig.stop().await;
}

/// A trend rule over a window of seconds (the simulator runs 1000 × as fast).
fn rule() -> TrendRule {
    TrendRule {
        mplex: "0x440301".into(),
        name: "Door closing time".into(),
        rise_percent: 10.0,
        baseline_h: 20.0 / 3600.0,
        window_h: 10.0 / 3600.0,
    }
}

async fn worn_rig(wear: f64) -> Rig {
    Rig::builder()
        .portal(|c| {
            c.dashboard.inhibit_ms = 0;
            c.insights.trends = vec![rule()];
        })
        .sim(move |s| {
            s.speed = 1000.0;
            s.passengers = Some(Duration::from_secs(20));
            s.door_wear_percent_per_h = wear;
        })
        .start()
        .await
}

/// Alarms of the rig's lift of `kind`.
async fn alarms_of(rig: &Rig, kind: &str) -> Vec<Value> {
    let (status, list) = rig
        .call("GET", "/api/v1/alarms", Some(&rig.key), None)
        .await;
    assert_eq!(status, 200, "{list}");
    list["alarms"]
        .as_array()
        .map(|a| a.iter().filter(|a| a["kind"] == kind).cloned().collect())
        .unwrap_or_default()
}

/// A door that closes 5 % more slowly every simulated hour — 1.4 % every second at 1000 × —
/// is blocked by its closing supervision after about 72 s; the trend rule sees it in about
/// 20 s. The same simulator without wear raises no trend alarm over the same time.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wearing_door_raises_its_trend_alarm_before_it_fails_and_a_sound_one_none() {
    let (worn, sound) = tokio::join!(worn_rig(5.0), worn_rig(0.0));
    worn.online().await;
    sound.online().await;
    let took = until(Duration::from_secs(60), "the trend alarm", || async {
        !alarms_of(&worn, "trend").await.is_empty()
    })
    .await;
    let trend = &alarms_of(&worn, "trend").await[0];
    assert_eq!(trend["code"], "0x440301");
    assert_eq!(trend["severity"], "minor");
    let text = trend["text"].as_str().unwrap_or_default();
    assert!(
        text.starts_with("Door closing time (0x440301) rose"),
        "{text}"
    );
    assert!(
        alarms_of(&worn, "emcy").await.is_empty(),
        "no door fault before the trend alarm ({took:?})"
    );
    assert!(
        alarms_of(&sound, "trend").await.is_empty(),
        "a sound door has no trend"
    );
    // The door timing the alarm is made of: slower now than at first.
    let (_, timing) = worn
        .call(
            "GET",
            &format!(
                "/api/v1/lifts/{}/objects/0x440302",
                testkit::constants::LIFT
            ),
            Some(&worn.key),
            None,
        )
        .await;
    let mean: f64 = timing["object"]["value"][0]
        .as_str()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.0);
    assert!(mean > 2500.0 * 1.1, "mean closing {mean} ms: {timing}");
    // Over the same time again the sound door stays without one.
    tokio::time::sleep(took.min(Duration::from_secs(20))).await;
    assert!(alarms_of(&sound, "trend").await.is_empty());
    worn.stop().await;
    sound.stop().await;
}

/// The monthly report in the browser, in English and in German; the fleet's availability
/// column and the lift page's last 30 days.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_monthly_report_renders_in_both_languages() {
    use super::browser::{browser, chromedriver, text_of, until as soon};
    let Some((chromium, chromedriver_path)) = testkit::browser() else {
        return;
    };
    let rig = Rig::builder().without_lift().start().await;
    rig.hand_made_gateway("AVAIL-1", "MAS").await;
    let lift = key(&rig, "MAS", "AVAIL-1").await;
    inject(&rig, &lift).await;
    // A status now: the last 30 days have an out-of-service span to show.
    let store = rig.store().await;
    let now = cloud_types::now_ms();
    let recent =
        [(now - 3 * H, OutOfService), (now - 2 * H, InService)].map(|(at, status)| StatusRow {
            lift: lift.clone(),
            at,
            status,
        });
    store
        .write_alarm_batch(&[], &recent, &[], &[])
        .await
        .expect("written");

    let driver = chromedriver(&chromedriver_path).await;
    let client = browser(&driver, &chromium, &rig.dir().join("chromium-profile")).await;
    let base = rig.url();
    client
        .goto(&format!("{base}/"))
        .await
        .expect("the sign-in page");
    super::web_ui::sign_in(&client, &rig.key).await;
    let column = soon("the fleet's availability column", 10, || async {
        text_of(&client, "table.fleet td.availability").await
    })
    .await;
    assert!(column.ends_with('%'), "{column}");

    // The same report in each language: its heading, the summary's verdict on the target, a
    // lift's block.
    for (lang, heading, summary_has, block_has) in [
        (
            "en",
            "Monthly report 2026-03",
            ["target missed", "0xFF01"],
            "Faults per 1000 trips",
        ),
        (
            "de",
            "Monatsbericht 2026-03",
            ["Ziel verfehlt", "Verfügbarkeit"],
            "Störungen je 1000 Fahrten",
        ),
    ] {
        client
            .goto(&format!("{base}/reports?month=2026-03&lang={lang}"))
            .await
            .expect("the report");
        assert_eq!(text_of(&client, "h1").await.as_deref(), Some(heading));
        let summary = text_of(&client, "section.report-summary")
            .await
            .unwrap_or_default();
        for text in summary_has {
            assert!(summary.contains(text), "{lang}: {summary}");
        }
        let block = text_of(&client, "section.lift-report")
            .await
            .unwrap_or_default();
        assert!(block.contains("1050-4096-AVAIL-1"), "{block}");
        assert!(block.contains(block_has), "{lang}: {block}");
    }

    client
        .goto(&format!("{base}/lifts/1050-4096-AVAIL-1?lang=en"))
        .await
        .expect("the lift page");
    let section = text_of(&client, "#availability").await.unwrap_or_default();
    assert!(section.contains("Out of service"), "{section}");
    let spans = super::browser::eval(
        &client,
        "return [...document.querySelectorAll('#availability rect.out-of-service')].length;",
    )
    .await;
    assert!(spans.as_u64().unwrap_or(0) >= 1, "{spans}");
    client.close().await.expect("closed");
    drop(driver);
    rig.stop().await;
}
