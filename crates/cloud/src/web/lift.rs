//! The lift page: identity, live values (kept current by the script from the lift's events),
//! the parameter table with its edit dialog, and reading any object.

use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Path, Query, State};
use axum::response::{IntoResponse, Response};
use maud::{html, Markup};
use nxg::meta::{FormType, PhysUnit, Privilege};
use nxg::mplex::Mplex;
use nxg::msg::{Lang, ObjectAnswer, ObjectData};
use nxg::portal::Failure;
use serde::Deserialize;

use super::i18n::Locale;
use super::page::{layout, lift_path, online_badge, time, unavailable};
use super::{owned, SignedIn};
use crate::state::AppState;
use cloud_types::api::Form;
use cloud_types::users::Role;

use cloud_store::AlarmFilter;

/// Floor level positions (CiA 417 manufacturer area, one element per floor): sub-index 0 is
/// the lift's number of floors, which sizes the "call the car" buttons.
const FLOOR_LEVELS: Mplex = Mplex {
    index: 0x4010,
    sub: 0,
};
/// Passenger call: writing a floor number calls the car there (privilege 0).
const PASSENGER_CALL: Mplex = Mplex {
    index: 0x5022,
    sub: 0,
};
/// More floors than this get no buttons (the edit dialog still calls any floor).
const MAX_FLOOR_BUTTONS: u8 = 64;

/// How long a page waits for the gateway's metadata before it shows what it has.
const READ_TIMEOUT: Duration = Duration::from_secs(4);

/// The attributes the page's script reads an object's value and metadata from.
struct Data {
    mplex: String,
    name: String,
    raw: String,
    datatype: String,
    physunit: String,
    form: String,
    min: String,
    max: String,
    privilege: String,
    unit: &'static str,
    list: String,
    hints: String,
}

/// An element (`tag` with optional classes) carrying an object's [`Data`] around `content`.
macro_rules! with_data {
    ($tag:ident $(.$class:ident)*, $data:expr, $content:expr) => {{
        let d = &$data;
        html! {
            $tag $(.$class)* data-mplex=(d.mplex) data-name=(d.name) data-raw=(d.raw)
                data-datatype=(d.datatype) data-physunit=(d.physunit) data-form=(d.form)
                data-min=(d.min) data-max=(d.max) data-privilege=(d.privilege)
                data-unit=(d.unit) data-list=(d.list) data-hints=(d.hints) { ($content) }
        }
    }};
}

/// What the gateway says about one object (a full `get_canopen_object` answer), or why it
/// could not, and the newest stored value.
struct Object {
    mplex: Mplex,
    answer: Result<ObjectAnswer, String>,
    stored: Option<(i64, String)>,
}

impl Object {
    /// The object's metadata and value.
    fn data(&self) -> Option<&ObjectData> {
        self.answer.as_ref().ok().map(|a| &a.object)
    }

    /// The object's name; a trailing ` [unit]` goes when the unit is shown beside the value.
    fn name(&self) -> String {
        let Some(d) = self.data() else {
            return self.mplex.to_string();
        };
        let name = d.name.clone().unwrap_or_else(|| self.mplex.to_string());
        let has_unit = d
            .physunit
            .is_some_and(|u| PhysUnit::from_code(u).is_ok_and(|u| !u.text().is_empty()));
        match name.rsplit_once(" [") {
            Some((bare, unit)) if has_unit && unit.ends_with(']') => bare.to_owned(),
            _ => name,
        }
    }

    /// The current value: the gateway's answer, else the newest stored one.
    fn raw(&self) -> String {
        self.data()
            .map(ObjectData::value_text)
            .or_else(|| self.stored.as_ref().map(|(_, v)| v.clone()))
            .unwrap_or_default()
    }

    fn form(&self) -> Option<FormType> {
        self.data()
            .and_then(|d| d.formtype)
            .and_then(|f| FormType::from_code(f).ok())
    }

    fn writable(&self) -> bool {
        self.data()
            .is_some_and(|d| matches!(d.access.as_deref(), Some("rw" | "wo")))
    }

    /// Whether someone with `role` may write it: privilege 0 from a technician on, above
    /// only an engineer (who elevates first; docs/PORTAL.md §Users and roles).
    fn writable_by(&self, role: Role) -> bool {
        let needed = self.data().and_then(|d| d.privilege).unwrap_or(1);
        self.writable()
            && role
                >= if needed == 0 {
                    Role::Technician
                } else {
                    Role::Engineer
                }
    }

    fn numeric(&self) -> bool {
        match self.form() {
            Some(f) => matches!(
                f,
                FormType::Number | FormType::Real | FormType::Duration | FormType::Choice
            ),
            None => self.raw().parse::<f64>().is_ok(),
        }
    }

    /// The `data-…` attributes the script formats values and fills the edit dialog with.
    fn attributes(&self, l: Locale) -> Data {
        let d = self.data();
        let number = |v: Option<u32>| v.map(|n| n.to_string()).unwrap_or_default();
        let limit = |v: Option<&serde_json::Number>| v.map(ToString::to_string).unwrap_or_default();
        Data {
            mplex: self.mplex.to_string(),
            name: self.name(),
            raw: self.raw(),
            datatype: number(d.and_then(|d| d.datatype)),
            physunit: number(d.and_then(|d| d.physunit)),
            form: number(d.and_then(|d| d.formtype)),
            min: limit(d.and_then(|d| d.min.as_ref())),
            max: limit(d.and_then(|d| d.max.as_ref())),
            privilege: number(d.and_then(|d| d.privilege)),
            unit: d
                .and_then(|d| d.physunit)
                .and_then(|u| PhysUnit::from_code(u).ok())
                .map_or("", |u| unit(u, l)),
            list: serde_json::to_string(&d.and_then(|d| d.list.as_ref())).unwrap_or_default(),
            hints: serde_json::to_string(&self.answer.as_ref().ok().and_then(|a| a.hints))
                .unwrap_or_default(),
        }
    }

    /// A chart link where values are stored (the live objects; parameters are not pushed).
    fn history_link(&self, lift: &str, l: Locale) -> Markup {
        html! {
            @if self.numeric() && self.stored.is_some() {
                a.chart href={ (lift_path(lift)) "/history?mplex=" (self.mplex) } { (l.t("chart")) }
            }
        }
    }

    fn card(&self, lift: &str, l: Locale) -> Markup {
        let content = html! {
            h3 { (self.name()) }
            p { span.v { (self.raw()) } " " span.u {} }
            @if let (Err(e), None) = (&self.answer, &self.stored) {
                p.error { (e) }
            }
            (self.history_link(lift, l))
        };
        with_data!(div.card, self.attributes(l), content)
    }

    fn row(&self, lift: &str, role: Role, l: Locale) -> Markup {
        let d = self.data();
        let range = match (
            d.and_then(|d| d.min.as_ref()),
            d.and_then(|d| d.max.as_ref()),
        ) {
            (Some(lo), Some(hi)) => format!("{lo} … {hi}"),
            _ => String::new(),
        };
        let privilege = d
            .and_then(|d| d.privilege)
            .and_then(|p| Privilege::from_code(p).ok())
            .map_or("", |p| l.t(p.text()));
        let content = html! {
            td { code { (self.mplex) } }
            td title=(d.and_then(|d| d.hint.as_deref()).unwrap_or_default()) { (self.name()) }
            td {
                @match &self.answer {
                    Err(e) => span.error { (e) },
                    Ok(_) => { span.v { (self.raw()) } " " span.u {} },
                }
            }
            td { (range) }
            td { (d.and_then(|d| d.access.as_deref()).unwrap_or_default()) }
            td { (privilege) }
            td {
                @if self.writable_by(role) {
                    button.edit type="button" { (l.t("Edit")) }
                }
                " "
                (self.history_link(lift, l))
            }
        };
        with_data!(tr, self.attributes(l), content)
    }
}

/// A unit as the page shows it: symbols as they are, the two units that are words in words of
/// the page's language.
fn unit(u: PhysUnit, l: Locale) -> &'static str {
    match u {
        PhysUnit::Trips | PhysUnit::Increments => l.t(u.text()),
        _ => u.text(),
    }
}

/// Read full metadata of `mplexes` from the lift's gateway, all at once, each waiting at most
/// [`READ_TIMEOUT`].
async fn read_all(app: &AppState, lift: &str, mplexes: &[Mplex], l: Locale) -> Vec<Object> {
    let online = app.registry.online(lift);
    let reads = mplexes.iter().map(|&mplex| async move {
        let answer = if online {
            let params = Form::Full.get(mplex.into(), Lang::new(l.code(), "en"));
            match tokio::time::timeout(READ_TIMEOUT, app.registry.call(lift, &params)).await {
                Ok(Ok(v)) => Ok(v),
                Ok(Err(Failure::Error(e))) => Err(e.to_string()),
                Ok(Err(f)) => Err(format!("{f:?}").to_lowercase()),
                Err(_) => Err(l.t("no answer in time").into()),
            }
        } else {
            Err(l.t("offline (the lift is not connected)").into())
        };
        Object {
            mplex,
            answer,
            stored: None,
        }
    });
    futures_util::future::join_all(reads).await
}

/// What a chart needs to know of an object: its name, unit and, for a choice, the names of its
/// values (from `min` on).
pub(super) struct Described {
    pub name: String,
    pub unit: &'static str,
    pub states: Option<(i64, Vec<String>)>,
}

/// Names, units and choices of `mplexes` from the lift's gateway (the mplex itself where the
/// lift is offline or does not say).
pub(super) async fn describe(
    app: &AppState,
    lift: &str,
    mplexes: &[Mplex],
    l: Locale,
) -> Vec<Described> {
    read_all(app, lift, mplexes, l)
        .await
        .into_iter()
        .map(|o| {
            let choice = o.form() == Some(FormType::Choice);
            let d = o.data();
            let min = d
                .and_then(|d| d.min.as_ref())
                .and_then(serde_json::Number::as_i64)
                .unwrap_or(0);
            Described {
                name: o.name(),
                unit: o.attributes(l).unit,
                states: d
                    .and_then(|d| d.list.clone())
                    .filter(|list| choice && !list.is_empty())
                    .map(|list| (min, list)),
            }
        })
        .collect()
}

#[derive(Deserialize)]
pub(super) struct LiftQuery {
    read: Option<String>,
}

pub(super) const TABLE_HEAD: [&str; 7] = [
    "Object",
    "Name",
    "Value",
    "Range",
    "Access",
    "Privilege",
    "",
];

fn table(lift: &str, objects: &[Object], role: Role, l: Locale) -> Markup {
    html! {
        table.objects {
            thead { tr { @for h in TABLE_HEAD { th { (if h.is_empty() { "" } else { l.t(h) }) } } } }
            tbody { @for o in objects { (o.row(lift, role, l)) } }
        }
    }
}

fn edit_dialog(l: Locale) -> Markup {
    html! {
        dialog #edit {
            form method="dialog" {
                h2.title {}
                p.hint.muted {}
                label { (l.t("New value ")) span.field {} }
                p.range.muted {}
                fieldset.elevate hidden {
                    legend { (l.t("Privilege needed")) }
                    p.why.muted {}
                    label {
                        (l.t("Privilege "))
                        select name="privilege" {
                            option value="1" { (l.t("service")) }
                            option value="2" { (l.t("setup")) }
                        }
                    }
                    label { (l.t("The lift's password ")) input type="password" name="password" autocomplete="off"; }
                }
                p.status role="status" {}
                menu {
                    // Save is the form's only submit button, so Enter saves.
                    button.cancel type="button" { (l.t("Cancel")) }
                    button.save value="save" { (l.t("Save")) }
                }
            }
        }
    }
}

pub(super) async fn lift_page(
    State(app): State<Arc<AppState>>,
    who: SignedIn,
    Path(id): Path<String>,
    Query(q): Query<LiftQuery>,
) -> Response {
    let lift = match owned(&app, &who, &id).await {
        Ok(l) => l,
        Err(r) => return r,
    };
    // The registry's key: the account's id of the lift is what the page shows and links.
    let key = &lift.id;
    let (session, l) = (&who.session, who.locale);
    let (live, parameters) = (&app.dashboard.live, &app.dashboard.parameters);
    let asked = q.read.as_deref().map(str::trim).filter(|r| !r.is_empty());
    let read = asked.map(|text| app.names.resolve(text));
    let live_keys: Vec<String> = live.iter().map(ToString::to_string).collect();
    let mut wanted = live.clone();
    wanted.extend_from_slice(parameters);
    wanted.push(PASSENGER_CALL);
    wanted.push(FLOOR_LEVELS);
    if let Some(Ok(m)) = read {
        wanted.push(m);
    }
    let active = AlarmFilter {
        active: true,
        lift: Some(key.clone()),
        limit: 100,
    };
    let to = cloud_types::now_ms();
    let from = to - crate::insights::Recent::DAYS * 86_400_000;
    let this = cloud_store::Lifts {
        domain: &session.operator.account.domain,
        lift: Some(key),
    };
    // The gateway's answers and the database's at once: the page waits for the slower only.
    let (mut objects, stored, alarms, events, recent) = tokio::join!(
        read_all(&app, key, &wanted, l),
        app.store.latest(key, &live_keys),
        app.store.alarms(&session.operator.account.domain, &active),
        app.store.event_log(key, None, 50),
        crate::insights::figures_and_timelines(&app.store, &app.insights, this, from, to),
    );
    let (stored, alarms, events, recent) = match (stored, alarms, events, recent) {
        (Ok(s), Ok(a), Ok(e), Ok(r)) => (s, a, e, r),
        (Err(e), ..) | (_, Err(e), ..) | (_, _, Err(e), _) | (.., Err(e)) => {
            return unavailable(e, who.viewer())
        }
    };
    let recent = recent.first().map(|(figures, timeline)| {
        let spans = crate::insights::availability::spans(timeline, from, to);
        (figures, spans)
    });
    for o in &mut objects {
        o.stored = stored.get(&o.mplex.to_string()).cloned();
    }
    let read_object = matches!(read, Some(Ok(_))).then(|| objects.pop()).flatten();
    let floors = objects
        .pop()
        .and_then(|o| o.raw().trim().parse::<u8>().ok())
        .filter(|n| (2..=MAX_FLOOR_BUTTONS).contains(n));
    // The buttons write as the dialog would: with the object's type and unit.
    let role = session.operator.role;
    let call = objects
        .pop()
        .filter(|o| o.writable_by(role))
        .map(|o| o.attributes(l));
    let floors = floors.zip(call);
    let mut parameter_objects = objects.split_off(live.len());
    // The passenger call's range is the lift's floors, not the object's 1 … 254.
    if let Some((n, _)) = floors {
        for o in &mut parameter_objects {
            if o.mplex == PASSENGER_CALL {
                if let Ok(answer) = &mut o.answer {
                    answer.object.max = Some(n.into());
                }
            }
        }
    }
    let events: Vec<nxg::msg::Event> = events
        .iter()
        .filter_map(|b| serde_json::from_str(b).ok())
        .collect();
    let identity = [
        ("Lift number", lift.liftnum.clone()),
        ("Vendor-ID", lift.vendorid.to_string()),
        ("Product code", lift.productcode.to_string()),
        ("Serial number", lift.sernum.clone()),
        ("Hardware", lift.hardware.clone()),
        ("Software", lift.software.clone()),
        ("API", lift.api.to_string()),
    ];
    let body = html! {
        h1 { (l.fill("Lift {}", &[&""])) code { (id) } " " (online_badge(&id, app.registry.online(key), l)) }
        @if let Some((n, call)) = &floors {
            section.call {
                h2 { (l.t("Call the car")) }
                div.floors data-mplex=(call.mplex) data-datatype=(call.datatype) data-physunit=(call.physunit) {
                    @for floor in 1..=*n {
                        button.floor type="button" value=(floor) aria-label=(l.fill("Call the car to floor {}", &[&floor])) { (floor) }
                    }
                }
                p.call-status.muted role="status" {}
            }
        }
        dl.identity {
            @for (term, value) in &identity { dt { (l.t(term)) } dd { (value) } }
            dt { (l.t("Last seen")) } dd { (time(lift.last_seen, l)) }
        }
        section #alarms {
            h2 { (l.t("Alarms")) }
            @if alarms.is_empty() {
                p.ok { (l.t("No active alarm.")) }
            } @else {
                (super::alarms::table(&alarms, &who, &lift_path(&id), false))
            }
        }
        @if let Some((figures, spans)) = &recent {
            (super::reports::recent(figures, spans, from, to, l))
        }
        p.rights.muted hidden role="status" {}
        h2 { (l.t("Live values")) }
        div.cards { @for o in &objects { (o.card(&id, l)) } }
        h2 { (l.t("Parameters")) }
        (table(&id, &parameter_objects, role, l))
        h2 { (l.t("Read an object")) }
        form.read method="get" {
            input name="read" placeholder=(l.t("0x652001, 0x6520:1 or a name"))
                value=(asked.unwrap_or_default()) required;
            button { (l.t("Read")) }
        }
        @if let Some(Err(e)) = &read {
            p.error { (e) }
        }
        @if let Some(o) = &read_object {
            (table(&id, std::slice::from_ref(o), role, l))
        }
        section #events {
            h2 { (l.t("Event log")) }
            @if events.is_empty() {
                p.muted { (l.t("No bus event stored (canlift gateways push them).")) }
            } @else {
                (super::alarms::event_log(&events, l))
            }
        }
        (edit_dialog(l))
    };
    layout(&l.fill("Lift {}", &[&id]), who.viewer(), Some(&id), body).into_response()
}
