//! What a lift's EMCY error codes mean, in English and German: the codes of the CANopen-Lift
//! additions to CiA 417-1 (§8.4) that the simulator raises, and for every other code the CiA 301
//! class (`canopen::emcy::describe`). Used for the gateway's `emcy` events and `canlift dump`.

use nxg::meta::Texts;

/// The specific lift faults: code, English, German.
const LIFT: &[(u16, &str, &str)] = &[
    (0xFF01, "Door blocked", "Tür blockiert"),
    (0xFF04, "Overload", "Überlast"),
    (
        0xF001,
        "Drive fault: fast stop",
        "Antriebsstörung: Schnellhalt",
    ),
];

/// What `code` means: the specific fault where known, else its CiA 301 class.
pub fn describe(code: u16) -> (&'static str, &'static str) {
    LIFT.iter()
        .find(|(c, ..)| *c == code)
        .map_or_else(|| canopen::emcy::describe(code), |(_, en, de)| (*en, *de))
}

/// The same as texts per language.
pub fn text(code: u16) -> Texts {
    let (en, de) = describe(code);
    Texts::en_de(en, de)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lift_faults_first_then_the_cia_301_class() {
        assert_eq!(describe(0xFF01), ("Door blocked", "Tür blockiert"));
        assert_eq!(describe(0xFF02).0, "Device specific");
        assert_eq!(
            text(0x8130).get("de"),
            Some("Node-Guarding- oder Heartbeat-Fehler")
        );
        assert_eq!(describe(0).0, "Error reset or no error");
    }
}
