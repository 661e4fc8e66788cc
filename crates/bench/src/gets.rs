//! The portal's gets the gateway benchmarks send (NXg §6.2 `get_canopen_object`).

/// Get request `id` of `mplex` in `form` (`naked`, `stripped`, otherwise full), asking for
/// English and German texts.
pub(crate) fn get(id: usize, mplex: &str, form: &str) -> String {
    let flag = match form {
        "naked" => r#","naked":true"#,
        "stripped" => r#","stripped":true"#,
        _ => "",
    };
    format!(
        r#"{{"jsonrpc":"2.0","id":{id},"method":"get_canopen_object","params":{{"lang":{{"preferred_language":"en","alternate_language":"de"}},"object":{{"mplex":"{mplex}"{flag}}}}}}}"#
    )
}
