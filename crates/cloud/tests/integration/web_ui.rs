//! The web UI in headless Chromium (Debian's `chromium`, driven through ChromeDriver by
//! WebDriver): sign in, fleet, a lift page whose values move by themselves, a put through the
//! edit dialog that makes the car travel, a put that needs service rights and gets them by
//! elevation, the history chart, the audit log, CSRF protection and signing out; users signing
//! in with their secret and seeing what their role may do.

use std::time::Duration;

use fantoccini::{Client, Locator};
use serde_json::json;

use super::browser::{browser, chromedriver, click, eval, number_of, text_of, type_into, until};

use testkit::constants::{LIFT, SERVICE_PASSWORD};
use testkit::portal::Rig;

/// Going to `url` leads to the sign-in form.
async fn assert_sign_in_asked(client: &Client, url: &str) {
    client.goto(url).await.unwrap();
    let at = client.current_url().await.unwrap();
    assert!(at.path().ends_with("/login"), "{url} led to {at}");
}

/// Submit the sign-in form with `key`.
pub(crate) async fn sign_in(client: &Client, key: &str) {
    type_into(client, "input[name=key]", key).await;
    click(client, "form.login button").await;
}

/// Open the edit dialog of `mplex`'s row, enter `value` and press Enter (which saves).
async fn edit(client: &Client, mplex: &str, value: &str) {
    click(
        client,
        &format!("table.objects tr[data-mplex=\"{mplex}\"] button.edit"),
    )
    .await;
    let input = client
        .wait()
        .at_most(Duration::from_secs(5))
        .for_element(Locator::Css("dialog#edit [name=value]"))
        .await
        .unwrap();
    input.clear().await.unwrap();
    let enter = char::from(fantoccini::key::Key::Enter);
    input.send_keys(&format!("{value}{enter}")).await.unwrap();
}

/// A picture of the page for people: `target/screenshots/NAME.png`, or with
/// `CANLIFT_UPDATE_SCREENSHOTS=1` the one docs/PORTAL.md shows (`docs/screenshots/`).
async fn screenshot(client: &Client, name: &str) {
    let dir = if std::env::var_os("CANLIFT_UPDATE_SCREENSHOTS").is_some() {
        testkit::workspace().join("docs/screenshots")
    } else {
        testkit::workspace().join("target/screenshots")
    };
    // Live values settle and times turn local before the picture.
    tokio::time::sleep(Duration::from_millis(300)).await;
    if let Ok(png) = client.screenshot().await {
        let _ = std::fs::create_dir_all(&dir);
        let _ = std::fs::write(dir.join(format!("{name}.png")), png);
    }
}

/// Whether `text` holds `phrase` as whole words.
fn has_phrase(text: &str, phrase: &str) -> bool {
    text.match_indices(phrase).any(|(at, _)| {
        let before = text[..at].chars().next_back();
        let after = text[at + phrase.len()..].chars().next();
        !before.is_some_and(char::is_alphanumeric) && !after.is_some_and(char::is_alphanumeric)
    })
}

/// Open the edit dialog of `mplex`'s row.
async fn open_editor(client: &Client, mplex: &str) {
    let button = format!("table.objects tr[data-mplex=\"{mplex}\"] button.edit");
    click(client, &button).await;
    until("dialog open", 5, || async {
        dialog_open(client).await.then_some(())
    })
    .await;
}

/// In the open edit dialog, enter `value` and the lift's `password`, save, and wait until the
/// dialog closed (the elevation and the put done).
async fn save_with_password(client: &Client, value: &str, password: &str) {
    let input = client
        .find(Locator::Css("dialog#edit [name=value]"))
        .await
        .unwrap();
    input.clear().await.unwrap();
    input.send_keys(value).await.unwrap();
    type_into(client, "dialog#edit [name=password]", password).await;
    click(client, "dialog#edit button.save").await;
    until("the dialog closes after elevation and put", 10, || async {
        (!dialog_open(client).await).then_some(())
    })
    .await;
}

async fn dialog_open(client: &Client) -> bool {
    eval(client, "return document.getElementById('edit').open;").await == json!(true)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operator_uses_the_web_ui() {
    let Some((chromium, chromedriver_path)) = testkit::browser() else {
        return;
    };
    let rig = Rig::builder()
        .portal(|c| c.dashboard.live.push("0x5FFF00".into()))
        .start()
        .await;
    rig.online().await;
    let driver = chromedriver(&chromedriver_path).await;
    let profile = rig.dir().join("chromium-profile");
    let client = browser(&driver, &chromium, &profile).await;
    let base = rig.url();

    // Not signed in: every page leads to the sign-in form; a wrong key is refused.
    assert_sign_in_asked(&client, &format!("{base}/lifts/{LIFT}")).await;
    sign_in(&client, "clk_wrong").await;
    let refused = until("refusal shown", 10, || text_of(&client, "p.error")).await;
    assert_eq!(refused, "Wrong account, user name, secret or API key.");

    // Sign in: the fleet shows the lift in service, with no fault.
    sign_in(&client, &rig.key).await;
    let state = until("fleet page", 10, || {
        text_of(&client, "table.fleet tbody td:nth-child(3)")
    })
    .await;
    assert_eq!(state, "in service");
    assert_eq!(
        text_of(&client, "p.summary").await.as_deref(),
        Some("1 lift · 1 in service · 0 out of service · 0 faults · 0 offline")
    );
    let faults = until(
        "fault column filled by the pushed error register",
        15,
        || async {
            client.refresh().await.ok()?;
            text_of(&client, "table.fleet td:nth-child(6)")
                .await
                .filter(|t| t != "no data")
        },
    )
    .await;
    assert_eq!(faults, "none");
    let rows = "return document.querySelectorAll('table.fleet tbody tr').length;";
    // Finding lifts by part of their number (the fleet is paged, 100 per page), filters by
    // state, sorting.
    client.goto(&format!("{base}/?q=7289")).await.unwrap();
    assert_eq!(eval(&client, rows).await, json!(1));
    for nothing in ["?q=no-such-lift", "?show=offline", "?show=faults&q=7289"] {
        client.goto(&format!("{base}/{nothing}")).await.unwrap();
        assert_eq!(
            text_of(&client, "p.none").await.as_deref(),
            Some("No lift matches."),
            "{nothing}"
        );
    }
    client
        .goto(&format!("{base}/?show=in-service&sort=state"))
        .await
        .unwrap();
    assert_eq!(eval(&client, rows).await, json!(1));
    assert_eq!(
        text_of(&client, "p.summary a.current").await.as_deref(),
        Some("1 in service")
    );
    assert_eq!(
        text_of(&client, "th a.sort.current").await.as_deref(),
        Some("State")
    );
    assert_eq!(
        text_of(&client, "p.ranges").await.as_deref(),
        Some("page 1 of 1")
    );
    client.goto(&format!("{base}/")).await.unwrap();

    // The lift page: names from the gateway, values formatted by their metadata.
    click(&client, &format!("a[href=\"/lifts/{LIFT}\"]")).await;
    let state = until("lift state formatted from its list", 10, || {
        text_of(&client, "[data-mplex=\"0x502400\"] .v")
    })
    .await;
    assert!(
        ["idle", "doors cycling", "travelling up", "travelling down"].contains(&state.as_str()),
        "lift state {state:?}"
    );
    assert_eq!(
        text_of(&client, "[data-mplex=\"0x652001\"] h3")
            .await
            .as_deref(),
        Some("Trip counter"),
        "the unit is shown beside the value, not twice"
    );
    assert_eq!(
        text_of(&client, "[data-mplex=\"0x652001\"] .u")
            .await
            .as_deref(),
        Some("trips")
    );
    let trips = until("trip counter shown", 10, || {
        number_of(&client, ".card[data-mplex=\"0x652001\"] .v")
    })
    .await;
    let position = number_of(&client, ".card[data-mplex=\"0x638301\"] .v").await;
    // Chart links where values are stored (the live values), none on parameters.
    let links = eval(
        &client,
        "return [document.querySelectorAll('.card a.chart').length,
                 document.querySelectorAll('table.objects a.chart').length];",
    )
    .await;
    assert!(
        links[0].as_u64() > Some(0) && links[1] == 0,
        "chart links: {links}"
    );

    // A passenger call through the edit dialog: the car travels and the page follows by itself.
    edit(&client, "0x502200", "4").await;
    until("dialog closed after the put", 10, || async {
        (!dialog_open(&client).await).then_some(())
    })
    .await;
    until("car position moves on the page", 20, || async {
        let now = number_of(&client, ".card[data-mplex=\"0x638301\"] .v").await;
        (now.is_some() && now != position).then_some(())
    })
    .await;
    let after = until("trip counter rises on the page", 40, || async {
        number_of(&client, ".card[data-mplex=\"0x652001\"] .v")
            .await
            .filter(|t| *t > trips)
    })
    .await;
    assert_eq!(after, trips + 1);

    // "Call the car": one button per floor of the lift (the simulator has 8), the passenger
    // call's range is the lift's floors too, and a button calls the car.
    assert_eq!(
        eval(
            &client,
            "return document.querySelectorAll('div.floors button.floor').length;"
        )
        .await,
        json!(8)
    );
    assert_eq!(
        eval(
            &client,
            "return document.querySelector('tr[data-mplex=\"0x502200\"]').dataset.max;"
        )
        .await,
        json!("8")
    );
    click(&client, "div.floors button.floor[value=\"2\"]").await;
    let called = until("the car is called", 10, || async {
        text_of(&client, "p.call-status")
            .await
            .filter(|t| !t.is_empty())
    })
    .await;
    assert_eq!(called, "called to floor 2");
    let floor = until("the car arrives at floor 2", 40, || async {
        number_of(&client, ".card[data-mplex=\"0x502300\"] .v")
            .await
            .filter(|f| *f == 2)
    })
    .await;
    assert_eq!(floor, 2);

    // Door open time needs service rights: the dialog asks for the lift's service password
    // before the first save, elevation grants the rights, the page counts them down.
    let elevate_hidden = "return document.querySelector('dialog#edit fieldset.elevate').hidden;";
    open_editor(&client, "0x411300").await;
    assert_eq!(eval(&client, elevate_hidden).await, json!(false));
    let why = text_of(&client, "dialog#edit .why")
        .await
        .unwrap_or_default();
    assert!(
        why.contains("service rights") && why.contains("service password"),
        "{why}"
    );
    save_with_password(&client, "7", SERVICE_PASSWORD).await;
    assert_eq!(
        text_of(&client, "tr[data-mplex=\"0x411300\"] .v")
            .await
            .as_deref(),
        Some("7")
    );
    let rights = until("rights counted down", 5, || text_of(&client, "p.rights")).await;
    assert!(rights.starts_with("service rights for "), "{rights}");
    // Held rights: the next change saves at once.
    edit(&client, "0x411300", "8").await;
    until("second put without a password", 10, || async {
        (!dialog_open(&client).await).then_some(())
    })
    .await;
    assert_eq!(eval(&client, elevate_hidden).await, json!(true));
    assert_eq!(
        text_of(&client, "tr[data-mplex=\"0x411300\"] .v")
            .await
            .as_deref(),
        Some("8")
    );
    let (status, read) = rig
        .call(
            "GET",
            &format!("/api/v1/lifts/{LIFT}/objects/0x411300?form=naked"),
            Some(&rig.key),
            None,
        )
        .await;
    assert_eq!((status, &read["object"]["value"][0]), (200, &json!("8")));

    // The session cookie alone does not authorise a change (CSRF), only with the page's token.
    let forged = client
        .execute_async(
            &format!(
                "const done = arguments[0];
                 fetch('/api/v1/lifts/{LIFT}/objects/0x502200', {{method: 'PUT',
                   headers: {{'content-type': 'application/json'}},
                   body: JSON.stringify({{value: '2', datatype: 7, physunit: 0}})}})
                 .then(r => done(r.status), () => done(-1));"
            ),
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(forged, json!(403));

    // Static files: content-hashed names cached for a year, an ETag that answers 304, the icon
    // where browsers look for it (no 404 on every page).
    let assets = client
        .execute_async(
            "const done = arguments[0];
             const css = document.querySelector('link[rel=stylesheet]').getAttribute('href');
             const show = r => [r.status, r.headers.get('content-type'), r.headers.get('cache-control')];
             (async () => {
               const first = await fetch(css);
               const again = await fetch(css, {headers: {'if-none-match': first.headers.get('etag')}});
               const icon = await fetch('/favicon.ico');
               const page = await fetch('/');
               const gzip = r => r.headers.get('content-encoding');
               done([css, show(first), again.status, show(icon), [gzip(first), gzip(page)]]);
             })().catch(() => done(null));",
            vec![],
        )
        .await
        .unwrap();
    let css = assets[0].as_str().unwrap_or_default();
    assert!(
        css.starts_with("/static/style.") && css.len() == "/static/style.".len() + 16 + 4,
        "{assets}"
    );
    assert_eq!(
        assets[1],
        json!([
            200,
            "text/css; charset=utf-8",
            "public, max-age=31536000, immutable"
        ])
    );
    assert_eq!(assets[2], json!(304), "{assets}");
    assert_eq!(
        assets[4],
        json!(["gzip", "gzip"]),
        "text is compressed: {assets}"
    );
    assert_eq!(assets[3], json!([200, "image/svg+xml", "no-cache"]));

    // Reading any object, here by (a prefix of) its German name.
    client
        .goto(&format!(
            "{base}/lifts/{LIFT}?read=optionen%20der%20etagen&lang=de"
        ))
        .await
        .unwrap();
    let name = until("object read in German", 10, || {
        text_of(
            &client,
            "table.objects tr[data-mplex=\"0x411200\"] td:nth-child(2)",
        )
    })
    .await;
    assert_eq!(name, "Optionen der Etagenrichtungsanzeige");

    // German, chosen once, stays: every page speaks it without `?lang=`, and no English text
    // of the UI is left (the catalogue is complete: web/i18n.rs checks it against the sources).
    let english = [
        "Fleet",
        "Alarms",
        "Sign out",
        "in service",
        "Last value",
        "Active faults",
        "Find",
        "Live values",
        "Parameters",
        "Read an object",
        "Event log",
        "Last seen",
        "Edit",
        "chart",
        "Vendor-ID",
        "Serial number",
        "History of",
        "values, last",
        "Every change",
        "When",
        "Result",
        "Before",
        "Recently cleared",
        "No active alarm",
        "page 1 of",
        "trips",
        "no data",
        "none",
    ];
    let german_pages = [
        ("fleet", "/", "Anlagen"),
        ("lift", &*format!("/lifts/{LIFT}"), "Live-Werte"),
        (
            "history",
            &*format!("/lifts/{LIFT}/history?mplex=0x652001"),
            "Verlauf von",
        ),
        ("audit", "/audit", "Jede Änderung"),
        ("alarms", "/alarms", "Kürzlich behoben"),
    ];
    client.set_window_size(1280, 900).await.unwrap();
    for (name, page, german) in german_pages {
        client.goto(&format!("{base}{page}")).await.unwrap();
        let text = until("page loaded", 10, || async {
            let text = eval(&client, "return document.body.innerText;").await;
            text.as_str()
                .filter(|t| t.contains(german))
                .map(str::to_owned)
        })
        .await;
        let text = text.as_str();
        assert!(text.contains(german), "{page} in German: {text}");
        let left: Vec<&str> = english
            .iter()
            .copied()
            .filter(|e| has_phrase(text, e))
            .collect();
        assert!(
            left.is_empty(),
            "{page}: English left in German: {left:?}\n{text}"
        );
        assert_eq!(
            eval(&client, "return document.documentElement.lang;").await,
            json!("de")
        );
        screenshot(&client, &format!("{name}-de")).await;
    }
    // The live status text of the script is German too.
    client.goto(&format!("{base}/lifts/{LIFT}")).await.unwrap();
    let door = until("door status in German", 10, || {
        text_of(&client, "[data-mplex=\"0x630101\"] .v")
    })
    .await;
    assert!(
        [
            "geschlossen",
            "schließt",
            "offen",
            "öffnet",
            "öffnet wieder",
            "angehalten"
        ]
        .iter()
        .any(|w| door.starts_with(w)),
        "door status {door:?}"
    );
    // And back to English, which stays as well.
    client.goto(&format!("{base}/?lang=en")).await.unwrap();
    assert_eq!(text_of(&client, "main h1").await.as_deref(), Some("Fleet"));

    // History chart of the trip counter, asked for by name.
    client
        .goto(&format!("{base}/lifts/{LIFT}/history?mplex=Trip%20counter"))
        .await
        .unwrap();
    let points = eval(
        &client,
        "const p = document.querySelector('svg.chart polyline'); return p ? p.getAttribute('points') : null;",
    )
    .await;
    let points = points.as_str().unwrap_or_default();
    assert!(points.split(' ').count() >= 3, "chart points {points:?}");
    // Local times with the zone named, a hover value, the CSV of what is shown.
    let zone = until("time zone named", 5, || text_of(&client, "p.zone")).await;
    assert!(zone.starts_with("times in "), "{zone}");
    let hover = eval(
        &client,
        "const svg = document.querySelector('svg.chart');
         const r = svg.getBoundingClientRect();
         svg.dispatchEvent(new PointerEvent('pointermove', {clientX: r.right - 20, clientY: r.top + 50}));
         return [svg.querySelector('text.hover').textContent,
                 svg.querySelector('line.cursor').getAttribute('visibility')];",
    )
    .await;
    assert!(
        hover[0].as_str().is_some_and(|t| t.contains(" at ")) && hover[1] == "visible",
        "hover: {hover}"
    );
    let csv = client
        .execute_async(
            "const done = arguments[0];
             fetch(document.querySelector('a.csv').getAttribute('href'))
               .then(async r => done([r.status, r.headers.get('content-type'), await r.text()]), () => done(null));",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(csv[0], json!(200), "{csv}");
    let csv_text = csv[2].as_str().unwrap_or_default();
    assert!(
        csv_text.starts_with("time,object,value\r\n20"),
        "{csv_text}"
    );
    assert!(csv_text.lines().count() >= 2, "{csv_text}");

    // Several values on one time axis: the car position as a line with its unit, the lift
    // state as a state timeline named by its choices; they follow the lift while the page is
    // open; dragging across a chart zooms into that period.
    client
        .goto(&format!(
            "{base}/lifts/{LIFT}/history?mplex=0x638301,Lift%20state&minutes=10"
        ))
        .await
        .unwrap();
    let captions = eval(
        &client,
        "return [...document.querySelectorAll('figure.series figcaption')].map(f => f.textContent);",
    )
    .await;
    assert_eq!(captions.as_array().map(Vec::len), Some(2), "{captions}");
    assert!(
        captions[0].as_str().is_some_and(|c| c.contains("[mm]")),
        "{captions}"
    );
    let states = eval(
        &client,
        "const svg = document.querySelectorAll('svg.chart')[1];
         const r = svg.getBoundingClientRect();
         svg.dispatchEvent(new PointerEvent('pointermove', {clientX: r.right - 20, clientY: r.top + 40}));
         return [svg.querySelectorAll('rect.state').length, svg.querySelector('text.hover').textContent];",
    )
    .await;
    assert!(states[0].as_u64() > Some(0), "state bands: {states}");
    assert!(
        ["idle", "doors cycling", "travelling up", "travelling down"]
            .iter()
            .any(|s| states[1].as_str().is_some_and(|h| h.starts_with(s))),
        "the hover names the state: {states}"
    );
    let before = text_of(&client, "figure.series p.summary")
        .await
        .unwrap_or_default();
    let (status, _) = rig
        .call(
            "PUT",
            &format!("/api/v1/lifts/{LIFT}/objects/0x502200"),
            Some(&rig.key),
            Some(json!({"value": "6", "datatype": 7, "physunit": 0})),
        )
        .await;
    assert_eq!(status, 200);
    until("the chart follows the lift", 30, || async {
        text_of(&client, "figure.series p.summary")
            .await
            .filter(|now| *now != before)
    })
    .await;
    eval(
        &client,
        "const svg = document.querySelector('svg.chart');
         const r = svg.getBoundingClientRect();
         const at = (type, x) => svg.dispatchEvent(new PointerEvent(type, {clientX: x, clientY: r.top + 50, bubbles: true}));
         at('pointerdown', r.left + r.width * 0.5);
         at('pointermove', r.left + r.width * 0.8);
         at('pointerup', r.left + r.width * 0.8);
         return null;",
    )
    .await;
    let zoomed = until("zoomed into the period", 10, || async {
        let url = client.current_url().await.ok()?;
        url.query()
            .filter(|q| q.contains("from="))
            .map(str::to_owned)
    })
    .await;
    until("the zoomed page", 10, || text_of(&client, "#charts figure")).await;
    assert!(
        zoomed.contains("from=") && zoomed.contains("to=") && !zoomed.contains("minutes="),
        "zoomed: {zoomed}"
    );
    assert_eq!(
        eval(
            &client,
            "return document.querySelector('#charts').hasAttribute('data-live');"
        )
        .await,
        json!(false),
        "a fixed period does not move"
    );
    client
        .goto(&format!(
            "{base}/lifts/{LIFT}/history?mplex=0x652001&minutes=10"
        ))
        .await
        .unwrap();
    assert_eq!(
        text_of(&client, ".ranges a.current").await.as_deref(),
        Some("10 min")
    );
    let last = text_of(&client, "p.summary").await.unwrap_or_default();
    assert!(!last.starts_with("0 values"), "{last}");

    // The audit log shows both changes and the elevation.
    client.goto(&format!("{base}/audit")).await.unwrap();
    let audit = text_of(&client, "table.audit tbody")
        .await
        .unwrap_or_default();
    assert!(audit.contains("0x502200"), "{audit}");
    assert!(audit.contains("0x411300"), "{audit}");
    assert!(audit.contains("elevate"), "{audit}");
    let puts = eval(
        &client,
        "return [...document.querySelectorAll('table.audit tbody tr')]
           .filter(r => r.textContent.includes('0x411300') && r.textContent.includes('ok')).length;",
    )
    .await;
    assert_eq!(
        puts,
        json!(2),
        "both puts of the door open time are audited"
    );

    // On a phone (390 × 844): no page scrolls sideways, tables are cards, the lift's Edit and
    // the dialog's Save are on the screen and work.
    let pages = [
        ("fleet", String::from("/")),
        ("lift", format!("/lifts/{LIFT}")),
        (
            "history",
            format!("/lifts/{LIFT}/history?mplex=0x638301,0x502400,0x652001"),
        ),
        ("audit", String::from("/audit")),
        ("alarms", String::from("/alarms")),
    ];
    client.set_window_size(390, 844).await.unwrap();
    let overflow = "return [document.documentElement.scrollWidth, window.innerWidth];";
    for (name, page) in &pages {
        client.goto(&format!("{base}{page}")).await.unwrap();
        until("page loaded", 10, || text_of(&client, "main h1")).await;
        let widths = eval(&client, overflow).await;
        let (scroll, inner) = (widths[0].as_u64(), widths[1].as_u64());
        assert!(
            scroll.is_some() && scroll <= inner,
            "{page} scrolls sideways at 390 px: {widths}"
        );
        screenshot(&client, &format!("{name}-phone")).await;
    }
    client.goto(&format!("{base}/lifts/{LIFT}")).await.unwrap();
    let inside = |css: &str| {
        format!(
            "const r = document.querySelector('{css}').getBoundingClientRect();
             return r.width > 0 && r.left >= 0 && r.right <= window.innerWidth;"
        )
    };
    let edit_button = "tr[data-mplex=\"0x502200\"] button.edit";
    assert_eq!(eval(&client, &inside(edit_button)).await, json!(true));
    edit(&client, "0x502200", "2").await;
    until("dialog closed after the put on a phone", 10, || async {
        (!dialog_open(&client).await).then_some(())
    })
    .await;
    click(&client, edit_button).await;
    assert_eq!(
        eval(&client, &inside("dialog#edit button.save")).await,
        json!(true)
    );
    click(&client, "dialog#edit button.cancel").await;
    client.set_window_size(1280, 900).await.unwrap();
    for (name, page) in &pages {
        client.goto(&format!("{base}{page}")).await.unwrap();
        until("page loaded", 10, || text_of(&client, "main h1")).await;
        screenshot(&client, name).await;
    }
    client.set_window_size(1280, 1600).await.unwrap();

    // A picture for people (target/web-ui-lift.png).
    client.goto(&format!("{base}/lifts/{LIFT}")).await.unwrap();
    until("lift page again", 10, || {
        text_of(&client, ".card[data-mplex=\"0x652001\"] .v")
    })
    .await;
    if let Ok(png) = client.screenshot().await {
        let _ = std::fs::write(testkit::workspace().join("target/web-ui-lift.png"), png);
    }

    // Signing out ends the session.
    click(&client, "nav form button").await;
    until("signed out", 10, || async {
        let url = client.current_url().await.ok()?;
        url.path().ends_with("/login").then_some(())
    })
    .await;
    assert_sign_in_asked(&client, &format!("{base}/")).await;

    // Another account sees none of this domain's lifts.
    sign_in(&client, &rig.other_key).await;
    until("the other account's fleet", 10, || async {
        (text_of(&client, "main h1").await.as_deref() == Some("Fleet")).then_some(())
    })
    .await;
    let empty = text_of(&client, "main p").await.unwrap_or_default();
    assert!(empty.contains("No lift of domain OTH"), "{empty}");
    client.goto(&format!("{base}/lifts/{LIFT}")).await.unwrap();
    assert_eq!(text_of(&client, "main h1").await.as_deref(), Some("404"));

    client.close().await.unwrap();
    drop(driver);
    rig.stop().await;
}

/// The lift (the portal registers its gateway's bus events) and a drive
/// fault injected in the simulator (5030h bit 2, setup rights): an active alarm.
async fn with_a_drive_fault() -> Rig {
    let rig = Rig::builder().start().await;
    rig.online().await;
    let privilege = json!({"privilege": 2, "password": testkit::constants::SETUP_PASSWORD});
    let path = format!("/api/v1/lifts/{LIFT}/privilege");
    let (status, answer) = rig
        .call("POST", &path, Some(&rig.key), Some(privilege))
        .await;
    assert_eq!(status, 200, "{answer}");
    let fault = json!({"value": "4", "datatype": 5, "physunit": 0});
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x503000");
    let (status, answer) = rig.call("PUT", &path, Some(&rig.key), Some(fault)).await;
    assert_eq!(status, 200, "{answer}");
    rig
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fault_reaches_the_fleet_page_and_is_acknowledged() {
    let Some((chromium, chromedriver_path)) = testkit::browser() else {
        return;
    };
    let rig = with_a_drive_fault().await;

    let driver = chromedriver(&chromedriver_path).await;
    let profile = rig.dir().join("chromium-profile");
    let client = browser(&driver, &chromium, &profile).await;
    let base = rig.url();
    client.goto(&format!("{base}/")).await.unwrap();
    sign_in(&client, &rig.key).await;
    // The fleet shows the lift's alarm (the page refreshes its table by itself).
    let alarm = until("the alarm on the fleet page", 30, || async {
        text_of(&client, "table.fleet td.alarm")
            .await
            .filter(|t| t.contains("F001"))
    })
    .await;
    assert!(alarm.starts_with("major"), "{alarm}");
    assert!(alarm.contains("Drive fault"), "{alarm}");
    // The alarms page: acknowledge with a comment.
    client.goto(&format!("{base}/alarms")).await.unwrap();
    type_into(
        &client,
        "table.alarms form.ack input[name=comment]",
        "on my way",
    )
    .await;
    click(&client, "table.alarms form.ack button").await;
    let acknowledged = until("acknowledged", 10, || async {
        text_of(&client, "table.alarms tbody tr td:nth-child(6)")
            .await
            .filter(|t| t.contains("masora"))
    })
    .await;
    assert!(acknowledged.contains("on my way"), "{acknowledged}");
    // The lift page lists it too, with the EMCY in its event log.
    client.goto(&format!("{base}/lifts/{LIFT}")).await.unwrap();
    let section = text_of(&client, "#alarms").await.unwrap_or_default();
    assert!(section.contains("Drive fault"), "{section}");
    let log = text_of(&client, "#events").await.unwrap_or_default();
    assert!(log.contains("0xF001"), "{log}");
    client.close().await.unwrap();
    drop(driver);
    rig.stop().await;
}

/// Sign in with a user's name and secret (of account masora).
async fn sign_in_as(client: &Client, user: &str, secret: &str) {
    type_into(client, "input[name=account]", testkit::constants::ACCOUNT).await;
    type_into(client, "input[name=user]", user).await;
    type_into(client, "input[name=secret]", secret).await;
    click(client, "form.login button").await;
}

/// How many elements match `css`.
async fn count(client: &Client, css: &str) -> u64 {
    let script = format!("return document.querySelectorAll({}).length;", json!(css));
    eval(client, &script).await.as_u64().unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_role_sees_what_it_may_do() {
    let Some((chromium, chromedriver_path)) = testkit::browser() else {
        return;
    };
    // An alarm to acknowledge (or not).
    let rig = with_a_drive_fault().await;
    let store = rig.store().await;
    let viewer = store
        .add_user("masora", "vera", cloud_types::users::Role::Viewer)
        .await
        .unwrap();
    let engineer = store
        .add_user("masora", "enzo", cloud_types::users::Role::Engineer)
        .await
        .unwrap();

    let driver = chromedriver(&chromedriver_path).await;
    let profile = rig.dir().join("chromium-profile");
    let client = browser(&driver, &chromium, &profile).await;
    let base = rig.url();
    let lift_page = format!("{base}/lifts/{LIFT}");

    // The viewer reads everything and is offered nothing to change.
    client.goto(&lift_page).await.unwrap();
    sign_in_as(&client, "vera", "cls_wrong").await;
    let refused = until("refusal shown", 10, || text_of(&client, "p.error")).await;
    assert_eq!(refused, "Wrong account, user name, secret or API key.");
    screenshot(&client, "sign-in").await;
    sign_in_as(&client, "vera", &viewer).await;
    until("the fleet", 10, || text_of(&client, "table.fleet")).await;
    assert_eq!(
        text_of(&client, "span.who").await.as_deref(),
        Some("vera · viewer")
    );
    client.goto(&lift_page).await.unwrap();
    until("the alarm on the lift page", 30, || async {
        client.refresh().await.ok()?;
        text_of(&client, "section#alarms table.alarms").await
    })
    .await;
    until("the parameters", 10, || text_of(&client, "table.objects")).await;
    assert_eq!(count(&client, "button.edit").await, 0, "no edit button");
    assert_eq!(count(&client, "section.call").await, 0, "no call buttons");
    assert_eq!(count(&client, "form.ack").await, 0, "no acknowledge form");
    screenshot(&client, "lift-viewer").await;

    // Disabled: the next page asks for a sign-in again.
    store.disable_user("masora", "vera").await.unwrap();
    until("the disabled viewer signed out", 10, || async {
        client.goto(&lift_page).await.ok()?;
        let at = client.current_url().await.ok()?;
        at.path().ends_with("/login").then_some(())
    })
    .await;

    // The engineer is offered edits, elevates in the dialog and writes.
    sign_in_as(&client, "enzo", &engineer).await;
    until("the fleet", 10, || text_of(&client, "table.fleet")).await;
    client.goto(&lift_page).await.unwrap();
    until("the parameters", 10, || text_of(&client, "table.objects")).await;
    assert!(count(&client, "button.edit").await > 0);
    assert_eq!(count(&client, "section.call").await, 1);
    assert_eq!(count(&client, "form.ack").await, 1);
    // Repaired: the lift-safety interlock lets parameters be written again.
    rig.sim().set_switches(1, 0);
    until("the lift back in service", 30, || async {
        let state = rig.naked("0x502400").await;
        (!["4", "5"].contains(&state.as_str()?)).then_some(())
    })
    .await;
    open_editor(&client, "0x411300").await;
    save_with_password(&client, "7", SERVICE_PASSWORD).await;
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    let by_enzo: Vec<&str> = audit
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["account"] == "enzo")
        .map(|e| e["action"].as_str().unwrap_or_default())
        .collect();
    assert_eq!(by_enzo, ["put", "elevate"], "{audit}");
    client.close().await.unwrap();
    rig.stop().await;
}
