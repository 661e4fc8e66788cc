//! CSV as the portal writes it (RFC 4180): the history export and the availability reports.

/// A value as a CSV cell: quoted when it holds a separator, a quote or a line break; a text a
/// spreadsheet would take for a formula (it begins with `=`, `+`, `-`, `@`, a tab or a carriage
/// return: OWASP's CSV injection) is prefixed with `'` so it stays text. Numbers, negative
/// ones too, stay numbers.
pub fn cell(value: &str) -> String {
    let formula =
        value.starts_with(['=', '+', '-', '@', '\t', '\r']) && value.trim().parse::<f64>().is_err();
    let value = if formula {
        format!("'{value}")
    } else {
        value.to_owned()
    };
    if value.contains([',', '"', '\r', '\n', '\t']) || formula {
        format!("\"{}\"", value.replace('"', "\"\""))
    } else {
        value
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A gateway's text a spreadsheet would run stays text; numbers stay numbers; a separator
    /// or quote is quoted (RFC 4180).
    #[test]
    fn csv_cells_hold_no_formulas() {
        assert_eq!(
            cell("=HYPERLINK(\"http://x\")"),
            "\"'=HYPERLINK(\"\"http://x\"\")\""
        );
        assert_eq!(cell("+1+cmd|' /C calc'!A0"), "\"'+1+cmd|' /C calc'!A0\"");
        assert_eq!(cell("@SUM(A1)"), "\"'@SUM(A1)\"");
        assert_eq!(cell("\tx"), "\"'\tx\"");
        assert_eq!(cell("-3.5"), "-3.5");
        assert_eq!(cell("+7"), "+7");
        assert_eq!(cell("12"), "12");
        assert_eq!(cell("a,b"), "\"a,b\"");
        assert_eq!(cell("plain text"), "plain text");
    }
}
