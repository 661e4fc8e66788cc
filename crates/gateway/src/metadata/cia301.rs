//! The communication profile area 1000h–1FFFh (CiA 301 §7.5.2) in the connector's vocabulary:
//! the standard objects with names in English and German, data types, access, forms, units and
//! the privilege a write needs. A lift controller without an EDS is described by the CiA 417
//! catalog and these; a node with an EDS takes their texts where the EDS has the object with the
//! same data type.

use nxg::meta::{
    Access, DataType, Description, FormType, Hints, ObjCode, PhysUnit, Privilege, Texts,
};

/// One sub-object's description in the table: names, type, access, form, unit, privilege.
#[derive(Clone, Copy)]
struct Sub {
    en: &'static str,
    de: &'static str,
    datatype: u16,
    access: Access,
    form: FormType,
    unit: PhysUnit,
    privilege: Privilege,
}

const U8: u16 = 0x05;
const U16: u16 = 0x06;
const U32: u16 = 0x07;
const TEXT: u16 = 0x09;
const DOMAIN: u16 = 0x0F;

const fn sub(en: &'static str, de: &'static str, datatype: u16, access: Access) -> Sub {
    Sub {
        en,
        de,
        datatype,
        access,
        form: FormType::Number,
        unit: PhysUnit::None,
        privilege: Privilege::Setup,
    }
}

const fn hex(s: Sub) -> Sub {
    Sub {
        form: FormType::Hex,
        ..s
    }
}

const fn ms(s: Sub) -> Sub {
    Sub {
        unit: PhysUnit::Millisecond,
        form: FormType::Duration,
        ..s
    }
}

const fn text(en: &'static str, de: &'static str) -> Sub {
    Sub {
        form: FormType::Text,
        ..sub(en, de, TEXT, Access::Const)
    }
}

const fn by(privilege: Privilege, s: Sub) -> Sub {
    Sub { privilege, ..s }
}

/// Sub-index 0 of an array or record.
const COUNT: Sub = sub(
    "Highest sub-index supported",
    "Höchster unterstützter Subindex",
    U8,
    Access::Ro,
);

use Access::{Ro, Rw};

/// A command sub-object (store, restore): a u32 written with a signature.
const fn command(en: &'static str, de: &'static str) -> Sub {
    Sub {
        form: FormType::Command,
        ..sub(en, de, U32, Rw)
    }
}

const STORE: &[(u8, Sub)] = &[
    (0, COUNT),
    (
        1,
        command("Save all parameters", "Alle Parameter speichern"),
    ),
    (
        2,
        command(
            "Save communication parameters",
            "Kommunikationsparameter speichern",
        ),
    ),
    (
        3,
        command(
            "Save application parameters",
            "Anwendungsparameter speichern",
        ),
    ),
    (
        4,
        command(
            "Save manufacturer parameters",
            "Herstellerparameter speichern",
        ),
    ),
];

const RESTORE: &[(u8, Sub)] = &[
    (0, COUNT),
    (
        1,
        command(
            "Restore all default parameters",
            "Alle Standardparameter wiederherstellen",
        ),
    ),
    (
        2,
        command(
            "Restore communication default parameters",
            "Kommunikations-Standardparameter wiederherstellen",
        ),
    ),
    (
        3,
        command(
            "Restore application default parameters",
            "Anwendungs-Standardparameter wiederherstellen",
        ),
    ),
    (
        4,
        command(
            "Restore manufacturer default parameters",
            "Hersteller-Standardparameter wiederherstellen",
        ),
    ),
];

const IDENTITY: &[(u8, Sub)] = &[
    (0, COUNT),
    (1, hex(sub("Vendor-ID", "Hersteller-ID", U32, Ro))),
    (2, hex(sub("Product code", "Produktcode", U32, Ro))),
    (3, hex(sub("Revision number", "Revisionsnummer", U32, Ro))),
    (4, sub("Serial number", "Seriennummer", U32, Ro)),
];

/// An SDO parameter record (1200h…, 1280h…): both COB-IDs and the peer's node-ID.
const fn sdo_parameter(peer_en: &'static str, peer_de: &'static str) -> [(u8, Sub); 4] {
    [
        (0, COUNT),
        (
            1,
            hex(sub(
                "COB-ID client to server",
                "COB-ID Client an Server",
                U32,
                Rw,
            )),
        ),
        (
            2,
            hex(sub(
                "COB-ID server to client",
                "COB-ID Server an Client",
                U32,
                Rw,
            )),
        ),
        (3, sub(peer_en, peer_de, U8, Rw)),
    ]
}

const SDO_SERVER: &[(u8, Sub)] =
    &sdo_parameter("Node-ID of the SDO client", "Knoten-ID des SDO-Clients");
const SDO_CLIENT: &[(u8, Sub)] =
    &sdo_parameter("Node-ID of the SDO server", "Knoten-ID des SDO-Servers");

/// A PDO communication parameter record (1400h…, 1800h…).
const fn pdo_communication(cob_en: &'static str, cob_de: &'static str) -> [(u8, Sub); 6] {
    [
        (0, COUNT),
        (1, hex(sub(cob_en, cob_de, U32, Rw))),
        (2, sub("Transmission type", "Übertragungsart", U8, Rw)),
        (
            3,
            sub("Inhibit time [100 µs]", "Sperrzeit [100 µs]", U16, Rw),
        ),
        (5, ms(sub("Event timer", "Ereigniszeitgeber", U16, Rw))),
        (6, sub("SYNC start value", "SYNC-Startwert", U8, Rw)),
    ]
}

const RPDO_COMMUNICATION: &[(u8, Sub)] =
    &pdo_communication("COB-ID used by RPDO", "COB-ID des RPDO");
const TPDO_COMMUNICATION: &[(u8, Sub)] =
    &pdo_communication("COB-ID used by TPDO", "COB-ID des TPDO");

/// A PDO mapping parameter array (1600h…, 1A00h…).
const PDO_MAPPING: Shape = Shape::Array {
    count: sub(
        "Number of mapped objects",
        "Anzahl gemappter Objekte",
        U8,
        Rw,
    ),
    element: hex(sub("Mapped object {i}", "Gemapptes Objekt {i}", U32, Rw)),
    len: 64,
};

/// An object of the table: its code, names, and its sub-objects.
enum Shape {
    /// A single value at sub-index 0.
    Var(Sub),
    /// Sub-indices 1..=len alike (`{i}` in their names is the sub-index); sub-index 0 as given.
    Array { count: Sub, element: Sub, len: u8 },
    /// Listed sub-indices.
    Record(&'static [(u8, Sub)]),
}

/// What the table knows of `index`: object names (`{n}`: the number in a repeated range) and
/// its shape; the number for a repeated range.
fn object(index: u16) -> Option<(&'static str, &'static str, Shape, u16)> {
    use Access::Wo;
    let numbered = |base: u16| index - base + 1;
    Some(match index {
        0x1000 => (
            "Device type",
            "Gerätetyp",
            Shape::Var(hex(sub("Device type", "Gerätetyp", U32, Ro))),
            0,
        ),
        0x1001 => (
            "Error register",
            "Fehlerregister",
            Shape::Var(Sub {
                form: FormType::Bits,
                ..sub("Error register", "Fehlerregister", U8, Ro)
            }),
            0,
        ),
        0x1002 => (
            "Manufacturer status register",
            "Herstellerstatusregister",
            Shape::Var(hex(sub(
                "Manufacturer status register",
                "Herstellerstatusregister",
                U32,
                Ro,
            ))),
            0,
        ),
        0x1003 => (
            "Pre-defined error field",
            "Fehlerhistorie",
            Shape::Array {
                count: by(
                    Privilege::Service,
                    sub("Number of errors", "Anzahl der Fehler", U8, Rw),
                ),
                element: hex(sub(
                    "Standard error field {i}",
                    "Fehlereintrag {i}",
                    U32,
                    Ro,
                )),
                len: 254,
            },
            0,
        ),
        0x1005 => (
            "COB-ID SYNC",
            "COB-ID SYNC",
            Shape::Var(hex(sub("COB-ID SYNC", "COB-ID SYNC", U32, Rw))),
            0,
        ),
        0x1006 => (
            "Communication cycle period",
            "Kommunikationszykluszeit",
            Shape::Var(sub(
                "Communication cycle period [µs]",
                "Kommunikationszykluszeit [µs]",
                U32,
                Rw,
            )),
            0,
        ),
        0x1007 => (
            "Synchronous window length",
            "Länge des Synchronfensters",
            Shape::Var(sub(
                "Synchronous window length [µs]",
                "Länge des Synchronfensters [µs]",
                U32,
                Rw,
            )),
            0,
        ),
        0x1008 => (
            "Manufacturer device name",
            "Gerätename des Herstellers",
            Shape::Var(text(
                "Manufacturer device name",
                "Gerätename des Herstellers",
            )),
            0,
        ),
        0x1009 => (
            "Manufacturer hardware version",
            "Hardwareversion des Herstellers",
            Shape::Var(text(
                "Manufacturer hardware version",
                "Hardwareversion des Herstellers",
            )),
            0,
        ),
        0x100A => (
            "Manufacturer software version",
            "Softwareversion des Herstellers",
            Shape::Var(text(
                "Manufacturer software version",
                "Softwareversion des Herstellers",
            )),
            0,
        ),
        0x100C => (
            "Guard time",
            "Überwachungszeit",
            Shape::Var(ms(sub("Guard time", "Überwachungszeit", U16, Rw))),
            0,
        ),
        0x100D => (
            "Life time factor",
            "Lebensdauerfaktor",
            Shape::Var(sub("Life time factor", "Lebensdauerfaktor", U8, Rw)),
            0,
        ),
        0x1010 => (
            "Store parameters",
            "Parameter speichern",
            Shape::Record(STORE),
            0,
        ),
        0x1011 => (
            "Restore default parameters",
            "Standardparameter wiederherstellen",
            Shape::Record(RESTORE),
            0,
        ),
        0x1012 => (
            "COB-ID time stamp object",
            "COB-ID Zeitstempel",
            Shape::Var(hex(sub(
                "COB-ID time stamp object",
                "COB-ID Zeitstempel",
                U32,
                Rw,
            ))),
            0,
        ),
        0x1013 => (
            "High resolution time stamp",
            "Hochauflösender Zeitstempel",
            Shape::Var(sub(
                "High resolution time stamp [µs]",
                "Hochauflösender Zeitstempel [µs]",
                U32,
                Rw,
            )),
            0,
        ),
        0x1014 => (
            "COB-ID EMCY",
            "COB-ID EMCY",
            Shape::Var(hex(sub("COB-ID EMCY", "COB-ID EMCY", U32, Rw))),
            0,
        ),
        0x1015 => (
            "Inhibit time EMCY",
            "Sperrzeit EMCY",
            Shape::Var(sub(
                "Inhibit time EMCY [100 µs]",
                "Sperrzeit EMCY [100 µs]",
                U16,
                Rw,
            )),
            0,
        ),
        0x1016 => (
            "Consumer heartbeat time",
            "Heartbeat-Überwachungszeit",
            Shape::Array {
                count: COUNT,
                element: hex(sub(
                    "Consumer heartbeat time {i}",
                    "Heartbeat-Überwachungszeit {i}",
                    U32,
                    Rw,
                )),
                len: 127,
            },
            0,
        ),
        0x1017 => (
            "Producer heartbeat time",
            "Heartbeat-Sendezeit",
            Shape::Var(ms(sub(
                "Producer heartbeat time",
                "Heartbeat-Sendezeit",
                U16,
                Rw,
            ))),
            0,
        ),
        0x1018 => ("Identity object", "Identität", Shape::Record(IDENTITY), 0),
        0x1019 => (
            "Synchronous counter overflow value",
            "Überlaufwert des SYNC-Zählers",
            Shape::Var(sub(
                "Synchronous counter overflow value",
                "Überlaufwert des SYNC-Zählers",
                U8,
                Rw,
            )),
            0,
        ),
        0x1029 => (
            "Error behaviour",
            "Fehlerverhalten",
            Shape::Array {
                count: COUNT,
                element: sub("Error class {i}", "Fehlerklasse {i}", U8, Rw),
                len: 254,
            },
            0,
        ),
        0x1200..=0x127F => (
            "SDO server parameter {n}",
            "SDO-Server-Parameter {n}",
            Shape::Record(SDO_SERVER),
            numbered(0x1200),
        ),
        0x1280..=0x12FF => (
            "SDO client parameter {n}",
            "SDO-Client-Parameter {n}",
            Shape::Record(SDO_CLIENT),
            numbered(0x1280),
        ),
        0x1400..=0x15FF => (
            "RPDO {n} communication parameter",
            "RPDO {n} Kommunikationsparameter",
            Shape::Record(RPDO_COMMUNICATION),
            numbered(0x1400),
        ),
        0x1600..=0x17FF => (
            "RPDO {n} mapping parameter",
            "RPDO {n} Mapping-Parameter",
            PDO_MAPPING,
            numbered(0x1600),
        ),
        0x1800..=0x19FF => (
            "TPDO {n} communication parameter",
            "TPDO {n} Kommunikationsparameter",
            Shape::Record(TPDO_COMMUNICATION),
            numbered(0x1800),
        ),
        0x1A00..=0x1BFF => (
            "TPDO {n} mapping parameter",
            "TPDO {n} Mapping-Parameter",
            PDO_MAPPING,
            numbered(0x1A00),
        ),
        0x1F50 => (
            "Program data",
            "Programmdaten",
            Shape::Array {
                count: COUNT,
                element: Sub {
                    form: FormType::Hex,
                    ..sub("Program {i}", "Programm {i}", DOMAIN, Wo)
                },
                len: 254,
            },
            0,
        ),
        0x1F51 => (
            "Program control",
            "Programmsteuerung",
            Shape::Array {
                count: COUNT,
                element: Sub {
                    form: FormType::Command,
                    ..sub("Program control {i}", "Programmsteuerung {i}", U8, Rw)
                },
                len: 254,
            },
            0,
        ),
        0x1F56 => (
            "Program software identification",
            "Programm-Softwarekennung",
            Shape::Array {
                count: COUNT,
                element: hex(sub(
                    "Program software identification {i}",
                    "Programm-Softwarekennung {i}",
                    U32,
                    Ro,
                )),
                len: 254,
            },
            0,
        ),
        0x1F57 => (
            "Flash status identification",
            "Flash-Statuskennung",
            Shape::Array {
                count: COUNT,
                element: hex(sub(
                    "Flash status identification {i}",
                    "Flash-Statuskennung {i}",
                    U32,
                    Ro,
                )),
                len: 254,
            },
            0,
        ),
        0x1F80 => (
            "NMT startup",
            "NMT-Startverhalten",
            Shape::Var(hex(sub("NMT startup", "NMT-Startverhalten", U32, Rw))),
            0,
        ),
        _ => return None,
    })
}

fn fill(text: &str, n: u16, i: u8) -> String {
    text.replace("{n}", &n.to_string())
        .replace("{i}", &i.to_string())
}

/// The standard description of (`index`, `sub`), if the communication profile defines it:
/// `Ok(None)` for an object the table knows without that sub-index.
pub fn describe(index: u16, sub: u8) -> Option<Option<Description>> {
    let (_, _, shape, n) = object(index)?;
    let (objcode, found) = match shape {
        Shape::Var(s) => (ObjCode::Var, (sub == 0).then_some(s)),
        Shape::Array {
            count,
            element,
            len,
        } => (
            ObjCode::Array,
            match sub {
                0 => Some(count),
                s if s <= len => Some(element),
                _ => None,
            },
        ),
        Shape::Record(subs) => (
            ObjCode::Record,
            subs.iter().find(|(s, _)| *s == sub).map(|(_, d)| *d),
        ),
    };
    Some(found.map(|s| {
        let datatype = DataType::from_code(u32::from(s.datatype)).unwrap_or(DataType::UNSIGNED32);
        let mut d = nxg::gateway::bare(datatype);
        d.objcode = objcode;
        d.access = s.access;
        d.formtype = s.form;
        d.physunit = s.unit;
        d.privilege = s.privilege;
        d.name = Texts::en_de(&fill(s.en, n, sub), &fill(s.de, n, sub));
        d.hint = Texts::default();
        d.hints = Hints::default();
        d
    }))
}

/// The names of the whole object (for a `compact` read).
pub fn object_texts(index: u16) -> Option<(Texts, Texts)> {
    let (en, de, _, n) = object(index)?;
    Some((
        Texts::en_de(&fill(en, n, 0), &fill(de, n, 0)),
        Texts::default(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn standard_objects_are_described() {
        let d = describe(0x1018, 1).unwrap().unwrap();
        assert_eq!(d.name.get("de"), Some("Hersteller-ID"));
        assert_eq!(
            (d.access, d.objcode, d.formtype),
            (Access::Ro, ObjCode::Record, FormType::Hex)
        );
        assert_eq!(describe(0x1018, 5), Some(None), "no sub-index 5");
        let pdo = describe(0x1A03, 2).unwrap().unwrap();
        assert_eq!(pdo.name.get("en"), Some("Mapped object 2"));
        assert_eq!(pdo.privilege, Privilege::Setup);
        assert_eq!(
            object_texts(0x1801).unwrap().0.get("en"),
            Some("TPDO 2 communication parameter")
        );
        let heartbeat = describe(0x1017, 0).unwrap().unwrap();
        assert_eq!(
            (heartbeat.physunit, heartbeat.datatype),
            (PhysUnit::Millisecond, DataType::UNSIGNED16)
        );
        assert!(describe(0x1004, 0).is_none(), "not a standard object");
        assert!(describe(0x2000, 0).is_none());
    }
}
