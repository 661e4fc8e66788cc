//! The UI's languages — the catalog's, English and German — and its message catalogue.
//!
//! Texts are written in English where they are used (`locale.t("Fleet")`); the German table
//! below holds their translations, keyed by the English text. A unit test reads the web
//! sources and the script and fails when a text has no German entry or an entry is no longer
//! used, so the catalogue stays complete in both languages. The script's texts reach it as a
//! JSON block in each page (`texts`), translated on the server.

use std::collections::HashMap;
use std::sync::OnceLock;

use axum::extract::{FromRequestParts, Request};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, HeaderValue};
use axum::middleware::Next;
use axum::response::Response;

/// The cookie that keeps a language chosen with `?lang=`.
const COOKIE: &str = "canlift_lang";

/// A language of the UI.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) enum Locale {
    /// English, the default.
    #[default]
    En,
    /// German.
    De,
}

impl Locale {
    /// Every language, in the order the switch shows them.
    pub(super) const ALL: [Locale; 2] = [Locale::En, Locale::De];

    /// Its ISO 639-1 code (`html lang`, `?lang=`, the gateway's `preferred_language`).
    pub(super) fn code(self) -> &'static str {
        match self {
            Locale::En => "en",
            Locale::De => "de",
        }
    }

    /// Its name in itself, for the switch.
    pub(super) fn name(self) -> &'static str {
        match self {
            Locale::En => "English",
            Locale::De => "Deutsch",
        }
    }

    fn parse(code: &str) -> Option<Locale> {
        let code = code.trim();
        Locale::ALL
            .into_iter()
            .find(|l| l.code().eq_ignore_ascii_case(code))
    }

    /// `?lang=`, else the language chosen before (cookie), else the browser's first language
    /// the UI speaks, else English.
    pub(super) fn of(query: Option<&str>, headers: &HeaderMap) -> Locale {
        let chosen = || crate::auth::sessions::cookie(headers, COOKIE).and_then(Locale::parse);
        let browser = || {
            headers
                .get(header::ACCEPT_LANGUAGE)
                .and_then(|v| v.to_str().ok())?
                .split(',')
                .filter_map(|l| l.split([';', '-']).next())
                .find_map(Locale::parse)
        };
        query
            .and_then(Locale::parse)
            .or_else(chosen)
            .or_else(browser)
            .unwrap_or_default()
    }

    /// `english` in this language.
    pub(super) fn t(self, english: &'static str) -> &'static str {
        match self {
            Locale::En => english,
            Locale::De => german().get(english).copied().unwrap_or_else(|| {
                debug_assert!(false, "no German for {english:?}");
                english
            }),
        }
    }

    /// `english` with its `{}` filled by `args` in order, in this language.
    pub(super) fn fill(self, english: &'static str, args: &[&dyn std::fmt::Display]) -> String {
        let mut parts = self.t(english).split("{}");
        let mut text = parts.next().unwrap_or_default().to_owned();
        for (part, arg) in parts.zip(
            args.iter()
                .chain(std::iter::repeat(&(&"" as &dyn std::fmt::Display))),
        ) {
            text.push_str(&arg.to_string());
            text.push_str(part);
        }
        text
    }

    /// The script's texts in this language, as the JSON object of the page's `texts` block.
    pub(super) fn script_texts(self) -> String {
        let texts: serde_json::Map<String, serde_json::Value> = SCRIPT
            .iter()
            .chain(&super::fleet::ERROR_BITS)
            .map(|&en| (en.to_owned(), self.t(en).into()))
            .collect();
        // `</` cannot end the block: JSON allows `\/`.
        serde_json::Value::Object(texts)
            .to_string()
            .replace("</", "<\\/")
    }
}

impl<S: Send + Sync> FromRequestParts<S> for Locale {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, Self::Rejection> {
        Ok(Locale::of(
            asked(parts.uri.query()).as_deref(),
            &parts.headers,
        ))
    }
}

/// The `lang` of a query string.
fn asked(query: Option<&str>) -> Option<String> {
    serde_urlencoded::from_str::<Vec<(String, String)>>(query?)
        .ok()?
        .into_iter()
        .find_map(|(k, v)| (k == "lang").then_some(v))
}

/// Remember a language chosen with `?lang=` in a cookie, so the next page speaks it too.
pub(super) async fn remember(request: Request, next: Next) -> Response {
    let chosen = asked(request.uri().query()).and_then(|l| Locale::parse(&l));
    let mut response = next.run(request).await;
    if let Some(locale) = chosen {
        let cookie = format!(
            "{COOKIE}={}; Path=/; Secure; SameSite=Lax; Max-Age=31536000",
            locale.code()
        );
        if let Ok(v) = HeaderValue::from_str(&cookie) {
            response.headers_mut().append(header::SET_COOKIE, v);
        }
    }
    response
}

/// The texts `app.js` asks for with `t("…")`, besides the error register's bits.
const SCRIPT: &[&str] = &[
    "off",
    "unlimited",
    "undefined",
    "none",
    "closed",
    "closing",
    "opened",
    "opening",
    "re-opening",
    "stopped",
    "error",
    "not installed",
    "state {}",
    "{}, contact closed",
    "no error",
    "online",
    "offline",
    "failed",
    "service",
    "setup",
    "elevated",
    "{} rights for {} more",
    "0 = off",
    "0 (off) or ",
    "Changing this needs {} rights: enter the lift's {} password. ",
    "The rights then last {} min.",
    "The rights then last as long as the lift grants them.",
    "saving…",
    "Elevation refused: {}",
    "saved",
    "{} — elevate and save again.",
    "times in {}",
    "{} at {}",
    "called to floor {}",
];

fn german() -> &'static HashMap<&'static str, &'static str> {
    static TABLE: OnceLock<HashMap<&'static str, &'static str>> = OnceLock::new();
    TABLE.get_or_init(|| GERMAN.iter().copied().collect())
}

/// English → German.
const GERMAN: &[(&str, &str)] = &[
    // Layout and navigation.
    ("Fleet", "Anlagen"),
    ("Alarms", "Alarme"),
    ("Audit", "Protokoll"),
    ("Reports", "Berichte"),
    ("Sign out", "Abmelden"),
    ("Language", "Sprache"),
    ("viewer", "Betrachter"),
    ("technician", "Techniker"),
    ("engineer", "Ingenieur"),
    ("administrator", "Administrator"),
    // Sign-in.
    ("Sign in", "Anmelden"),
    ("Account ", "Konto "),
    ("Sign in from the portal's own page.", "Bitte über die Anmeldeseite des Portals anmelden."),
    ("User name ", "Benutzername "),
    ("Secret ", "Geheimnis "),
    ("or with an API key", "oder mit einem API-Schlüssel"),
    ("API key ", "API-Schlüssel "),
    ("A user's secret is printed once by ", "Das Geheimnis eines Benutzers gibt einmal aus: "),
    ("; an account's key by ", "; den Schlüssel eines Kontos: "),
    (" (or by ", " (oder "),
    (").", ")."),
    // Single sign-on.
    ("Sign in with {}", "Anmelden mit {}"),
    ("or with the portal's own sign-in", "oder mit der Anmeldung des Portals"),
    ("Single sign-on is not set up on this portal.", "Dieses Portal hat keine zentrale Anmeldung."),
    ("The sign-on provider cannot be reached: try again, or sign in with a secret or an API key.", "Der Anmeldedienst ist nicht erreichbar: bitte erneut versuchen oder mit Geheimnis oder API-Schlüssel anmelden."),
    ("This sign-on was not begun in this browser, or took longer than ten minutes: sign in again.", "Diese Anmeldung wurde nicht in diesem Browser begonnen oder dauerte länger als zehn Minuten: bitte erneut anmelden."),
    ("The sign-on could not be verified.", "Die Anmeldung konnte nicht geprüft werden."),
    ("The sign-on provider refused: {}", "Der Anmeldedienst lehnte ab: {}"),
    ("None of your groups gives a role on this portal: ask its administrator.", "Keine Ihrer Gruppen gibt eine Rolle in diesem Portal: bitte an dessen Administrator wenden."),
    ("Your user is disabled on this portal: ask its administrator.", "Ihr Benutzer ist in diesem Portal gesperrt: bitte an dessen Administrator wenden."),
    ("The portal has another user named {}: its administrator must rename or remove it.", "Das Portal hat schon einen anderen Benutzer namens {}: sein Administrator muss ihn umbenennen oder entfernen."),
    ("Wrong account, user name, secret or API key.", "Konto, Benutzername, Geheimnis oder API-Schlüssel falsch."),
    ("Too many failed sign-ins: try again in {} s.", "Zu viele fehlgeschlagene Anmeldungen: bitte in {} s erneut versuchen."),
    ("Wrong CSRF token.", "Falsches CSRF-Token."),
    ("A viewer cannot acknowledge alarms.", "Als Betrachter können Sie keine Alarme quittieren."),
    // Errors.
    ("The database is unavailable.", "Die Datenbank ist nicht erreichbar."),
    ("No such lift.", "Diese Anlage gibt es nicht."),
    ("No such alarm.", "Diesen Alarm gibt es nicht."),
    ("The form has expired; reload the page.", "Das Formular ist abgelaufen; bitte die Seite neu laden."),
    ("never", "nie"),
    ("online", "online"),
    ("offline", "offline"),
    // Fleet.
    ("in service", "in Betrieb"),
    ("out of service", "außer Betrieb"),
    ("faults", "Störungen"),
    ("generic", "allgemein"),
    ("current", "Strom"),
    ("voltage", "Spannung"),
    ("temperature", "Temperatur"),
    ("communication", "Kommunikation"),
    ("device profile", "Geräteprofil"),
    ("reserved", "reserviert"),
    ("manufacturer", "herstellerspezifisch"),
    ("no data", "keine Daten"),
    ("none", "keine"),
    ("No lift of domain {} has connected yet.", "Noch keine Anlage der Domäne {} hat sich verbunden."),
    ("No lift has connected yet.", "Noch keine Anlage hat sich verbunden."),
    ("{} lift", "{} Anlage"),
    ("{} lifts", "{} Anlagen"),
    ("lift id or number", "Anlagen-ID oder -nummer"),
    ("Find", "Suchen"),
    ("No lift matches.", "Keine Anlage passt."),
    ("Lift", "Anlage"),
    ("Lift number", "Anlagennummer"),
    ("State", "Zustand"),
    ("Last value / seen", "Letzter Wert / zuletzt gesehen"),
    ("Alarm", "Alarm"),
    ("Active faults", "Aktive Störungen"),
    ("page {} of {}", "Seite {} von {}"),
    ("← previous", "← zurück"),
    ("next →", "weiter →"),
    // Lift.
    ("Lift {}", "Anlage {}"),
    ("Vendor-ID", "Hersteller-ID"),
    ("Product code", "Produktcode"),
    ("Serial number", "Seriennummer"),
    ("Hardware", "Hardware"),
    ("Software", "Software"),
    ("API", "API"),
    ("Last seen", "Zuletzt gesehen"),
    ("No active alarm.", "Kein aktiver Alarm."),
    ("Live values", "Live-Werte"),
    ("Call the car", "Kabine rufen"),
    ("Call the car to floor {}", "Kabine in Etage {} rufen"),
    ("called to floor {}", "in Etage {} gerufen"),
    ("Parameters", "Parameter"),
    ("Read an object", "Objekt lesen"),
    ("0x652001, 0x6520:1 or a name", "0x652001, 0x6520:1 oder ein Name"),
    ("Read", "Lesen"),
    ("Event log", "Ereignisse"),
    ("No bus event stored (canlift gateways push them).", "Kein Busereignis gespeichert (canlift-Gateways senden sie)."),
    ("chart", "Verlauf"),
    ("Edit", "Ändern"),
    ("Object", "Objekt"),
    ("Name", "Name"),
    ("Value", "Wert"),
    ("Range", "Bereich"),
    ("Access", "Zugriff"),
    ("Privilege", "Berechtigung"),
    ("New value ", "Neuer Wert "),
    ("Privilege needed", "Berechtigung nötig"),
    ("Privilege ", "Berechtigung "),
    ("user", "Benutzer"),
    ("service", "Service"),
    ("engineer on site", "Techniker vor Ort"),
    ("setup", "Einrichtung"),
    ("The lift's password ", "Passwort der Anlage "),
    ("Cancel", "Abbrechen"),
    ("Save", "Speichern"),
    ("trips", "Fahrten"),
    ("increments", "Inkremente"),
    ("offline (the lift is not connected)", "offline (die Anlage ist nicht verbunden)"),
    ("no answer in time", "keine Antwort in der Zeit"),
    // History.
    ("History of {} on", "Verlauf von {} auf"),
    ("{} values, last ", "{} Werte, zuletzt "),
    (" at ", " um "),
    ("No stored numeric values in this period. Values are stored while the gateway pushes them (the dashboard's objects, or a subscription).", "Keine gespeicherten Zahlenwerte in diesem Zeitraum. Werte werden gespeichert, solange das Gateway sie sendet (die Objekte der Übersicht oder ein Abonnement)."),
    ("History {}", "Verlauf {}"),
    ("mplex: {}", "mplex: {}"),
    ("history chart", "Verlaufsdiagramm"),
    ("CSV of these values", "CSV dieser Werte"),
    ("Drag across a chart to zoom in.", "Zum Vergrößern über ein Diagramm ziehen."),
    ("times in {}", "Zeiten in {}"),
    ("{} at {}", "{} um {}"),
    // Audit.
    ("Every change and privilege elevation, newest first.", "Jede Änderung und Rechteerhöhung, neueste zuerst."),
    ("When", "Wann"),
    ("Who", "Wer"),
    ("Action", "Aktion"),
    ("Before", "Vorher"),
    ("After", "Nachher"),
    ("Result", "Ergebnis"),
    ("ok", "ok"),
    ("protocol error", "Protokollfehler"),
    // Alarms and events.
    ("Severity", "Schwere"),
    ("Where", "Wo"),
    ("Raised", "Ausgelöst"),
    ("Acknowledged", "Quittiert"),
    ("Cleared", "Behoben"),
    ("comment", "Kommentar"),
    ("Acknowledge", "Quittieren"),
    ("active", "aktiv"),
    ("{} active", "{} aktiv"),
    ("Recently cleared", "Kürzlich behoben"),
    ("None.", "Keine."),
    ("node {} (net {})", "Knoten {} (Netz {})"),
    ("net {}", "Netz {}"),
    ("gateway", "Gateway"),
    ("Time", "Zeit"),
    ("Type", "Art"),
    ("What", "Was"),
    ("state", "Zustand"),
    ("network", "Netz"),
    (", register ", ", Register "),
    ("critical", "kritisch"),
    ("major", "schwer"),
    ("minor", "leicht"),
    // The script.
    ("off", "aus"),
    ("unlimited", "unbegrenzt"),
    ("undefined", "undefiniert"),
    ("closed", "geschlossen"),
    ("closing", "schließt"),
    ("opened", "offen"),
    ("opening", "öffnet"),
    ("re-opening", "öffnet wieder"),
    ("stopped", "angehalten"),
    ("error", "Fehler"),
    ("not installed", "nicht vorhanden"),
    ("state {}", "Zustand {}"),
    ("{}, contact closed", "{}, Kontakt geschlossen"),
    ("no error", "kein Fehler"),
    ("failed", "fehlgeschlagen"),
    ("elevated", "erhöhte"),
    ("{} rights for {} more", "{}-Rechte noch {}"),
    ("0 = off", "0 = aus"),
    ("0 (off) or ", "0 (aus) oder "),
    ("Changing this needs {} rights: enter the lift's {} password. ", "Diese Änderung braucht {}-Rechte: bitte das {}-Passwort der Anlage eingeben. "),
    ("The rights then last {} min.", "Die Rechte gelten dann {} min."),
    ("The rights then last as long as the lift grants them.", "Die Rechte gelten dann so lange, wie die Anlage sie gewährt."),
    ("saving…", "speichert…"),
    ("Elevation refused: {}", "Rechteerhöhung abgelehnt: {}"),
    ("saved", "gespeichert"),
    ("{} — elevate and save again.", "{} — Rechte erhöhen und erneut speichern."),
    // The monthly report and availability.
    ("Monthly report {}", "Monatsbericht {}"),
    ("A month is written YYYY-MM.", "Ein Monat wird JJJJ-MM geschrieben."),
    ("← previous month", "← Vormonat"),
    ("next month →", "nächster Monat →"),
    ("Account", "Konto"),
    ("Availability", "Verfügbarkeit"),
    ("target met", "Ziel erreicht"),
    ("target missed", "Ziel verfehlt"),
    ("Target", "Ziel"),
    ("Lifts", "Anlagen"),
    ("The months before", "Die Monate davor"),
    ("Month", "Monat"),
    ("Faults by kind", "Störungen nach Art"),
    ("No fault.", "Keine Störung."),
    ("EMCY code", "EMCY-Code"),
    ("Faults", "Störungen"),
    ("Lifts, the least available first", "Anlagen, die am wenigsten verfügbare zuerst"),
    ("In service", "In Betrieb"),
    ("Out of service", "Außer Betrieb"),
    ("Gateway offline", "Gateway offline"),
    ("Unknown", "Unbekannt"),
    ("Trips", "Fahrten"),
    ("Faults per 1000 trips", "Störungen je 1000 Fahrten"),
    ("mean time between failures", "mittlere Betriebsdauer zwischen Ausfällen"),
    ("mean time to repair", "mittlere Instandsetzungsdauer"),
    ("Door cycles", "Türspiele"),
    ("Reopenings", "Wiederöffnungen"),
    ("Availability (30 days)", "Verfügbarkeit (30 Tage)"),
];

#[cfg(test)]
mod tests {
    use super::*;

    /// Texts that reach `t` through a variable (besides the error bits and the table heads):
    /// the fleet's states, severities, badges, privileges, identity terms, headings, units.
    const TERMS: &[&str] = &[
        "in service",
        "out of service",
        "faults",
        "critical",
        "major",
        "minor",
        "online",
        "offline",
        "user",
        "service",
        "setup",
        "engineer on site",
        "Lift number",
        "Vendor-ID",
        "Product code",
        "Serial number",
        "Hardware",
        "Software",
        "API",
        "Lift",
        "State",
        "Last value / seen",
        "ok",
        "trips",
        "increments",
    ];

    const PAGES: [&str; 10] = [
        include_str!("alarms.rs"),
        include_str!("audit.rs"),
        include_str!("fleet.rs"),
        include_str!("history.rs"),
        include_str!("lift.rs"),
        include_str!("login.rs"),
        include_str!("mod.rs"),
        include_str!("page.rs"),
        include_str!("reports.rs"),
        include_str!("sso.rs"),
    ];
    const SCRIPT_SOURCE: &str = include_str!("app.js");

    /// Every literal text of `sources` handed to `t(` or `fill(`.
    fn used_in(sources: &[&str]) -> Vec<String> {
        let mut found = Vec::new();
        for source in sources {
            for call in ["t(", "fill("] {
                for (at, _) in source.match_indices(call) {
                    // `t(` of `split(` is not a call of `t`.
                    let before = source[..at].chars().next_back();
                    if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                        continue;
                    }
                    let rest = source[at + call.len()..].trim_start();
                    let Some(literal) = rest.strip_prefix('"') else {
                        continue;
                    };
                    if let Some(end) = literal.find('"') {
                        found.push(literal[..end].to_owned());
                    }
                }
            }
        }
        found
    }

    #[test]
    fn every_text_has_german_and_every_german_is_used() {
        let script = used_in(&[SCRIPT_SOURCE]);
        let indirect = TERMS.iter().chain(&super::super::fleet::ERROR_BITS).chain(
            super::super::lift::TABLE_HEAD
                .iter()
                .filter(|h| !h.is_empty()),
        );
        let mut used = used_in(&PAGES);
        used.extend(script.iter().cloned());
        used.extend(indirect.map(|t| (*t).to_owned()));
        assert!(used.len() > 50, "the sources were read: {}", used.len());
        let table = german();
        assert_eq!(table.len(), GERMAN.len(), "an English text twice in GERMAN");
        let missing: Vec<&String> = used
            .iter()
            .filter(|t| !table.contains_key(t.as_str()))
            .collect();
        assert!(missing.is_empty(), "no German for {missing:?}");
        let unused: Vec<&str> = GERMAN
            .iter()
            .map(|(en, _)| *en)
            .filter(|en| !used.iter().any(|u| u == en))
            .collect();
        assert!(
            unused.is_empty(),
            "German for texts no longer used: {unused:?}"
        );
        for text in SCRIPT {
            assert!(
                script.iter().any(|u| u == text),
                "SCRIPT lists {text:?}, app.js does not use it"
            );
        }
        for text in &script {
            assert!(
                SCRIPT.contains(&text.as_str())
                    || super::super::fleet::ERROR_BITS.contains(&text.as_str()),
                "app.js uses {text:?}, SCRIPT does not list it"
            );
        }
        for (en, de) in GERMAN {
            assert_eq!(en.matches("{}").count(), de.matches("{}").count(), "{en:?}");
        }
    }

    #[test]
    fn the_language_is_asked_chosen_or_the_browsers() {
        let mut h = HeaderMap::new();
        assert_eq!(Locale::of(None, &h), Locale::En);
        h.insert(
            header::ACCEPT_LANGUAGE,
            HeaderValue::from_static("fr-FR,de;q=0.8"),
        );
        assert_eq!(
            Locale::of(None, &h),
            Locale::De,
            "the first language the UI speaks"
        );
        h.insert(
            header::COOKIE,
            HeaderValue::from_static("canlift_session=x; canlift_lang=en"),
        );
        assert_eq!(Locale::of(None, &h), Locale::En, "chosen before");
        assert_eq!(Locale::of(Some("DE"), &h), Locale::De);
        assert_eq!(Locale::of(Some("<x>"), &h), Locale::En);
        assert_eq!(asked(Some("read=x&lang=de")).as_deref(), Some("de"));
    }

    #[test]
    fn texts_are_translated_and_filled() {
        assert_eq!(Locale::De.t("Fleet"), "Anlagen");
        assert_eq!(Locale::En.fill("page {} of {}", &[&2, &5]), "page 2 of 5");
        assert_eq!(Locale::De.fill("page {} of {}", &[&2, &5]), "Seite 2 von 5");
        let block = Locale::De.script_texts();
        let texts: serde_json::Value = serde_json::from_str(&block).unwrap();
        assert_eq!(texts["saved"], "gespeichert");
    }
}
