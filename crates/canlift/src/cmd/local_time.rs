//! Times in the command line's text output as a person reads them: in the system's time zone
//! (`TZ`, else /etc/localtime), with the zone's abbreviation; `--json` keeps the API's own
//! forms (ms since the epoch, RFC 3339 UTC).

use jiff::tz::TimeZone;
use jiff::Timestamp;

/// What the output says of a time it cannot show (out of range).
const UNKNOWN: &str = "?";

/// `ms` since the epoch as `2026-11-28 23:20:23.447 CET`.
pub fn of_ms(ms: i64) -> String {
    Timestamp::from_millisecond(ms).map_or_else(|_| UNKNOWN.into(), shown)
}

/// An RFC 3339 time as [`of_ms`] shows it (the text itself when it is not one).
pub fn of_rfc3339(text: &str) -> String {
    text.parse::<Timestamp>()
        .map_or_else(|_| text.to_owned(), shown)
}

fn shown(at: Timestamp) -> String {
    at.to_zoned(TimeZone::system())
        .strftime("%Y-%m-%d %H:%M:%S%.3f %Z")
        .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_read_in_the_local_zone() {
        // What the process's zone is does not matter to the form: date, time, zone.
        let shown = of_ms(1_764_370_823_447);
        assert!(shown.starts_with("2025-11-"), "{shown}");
        assert!(shown.contains(".447 "), "{shown}");
        assert_eq!(of_rfc3339("not a time"), "not a time");
        assert_eq!(of_rfc3339("2025-11-28T23:00:23.447Z"), shown);
        assert_eq!(of_ms(i64::MAX), UNKNOWN);
    }
}
