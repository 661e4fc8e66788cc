//! The merge rule on the test controller of another vendor (tests/fixtures/controller.eds and
//! its vendor file controller-nxg.toml).

use std::path::{Path, PathBuf};

use nxg::gateway::{Lookup, Metadata, Target};
use nxg::meta::{Access, Bound, Description, FormType, PhysUnit, Privilege};

use super::BusMetadata;
use crate::config::{Config, NodeSection};
use crate::GatewayError;

const CONTROLLER: Target = Target { net: 1, node: 1 };
const IO_NODE: Target = Target { net: 1, node: 13 };

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fixtures")
        .join(name)
}

fn node(id: u8, eds: Option<PathBuf>, metadata: Option<PathBuf>) -> NodeSection {
    NodeSection {
        eds,
        metadata,
        ..NodeSection::new(id)
    }
}

fn load(nodes: Vec<NodeSection>) -> Result<BusMetadata, GatewayError> {
    let mut config = Config::default();
    config.bus.nodes = nodes;
    BusMetadata::load(&config)
}

fn with_eds() -> BusMetadata {
    let eds = Some(fixture("controller.eds"));
    let vendor = Some(fixture("controller-nxg.toml"));
    load(vec![node(1, eds, vendor)]).expect("the fixtures load")
}

fn found(m: &BusMetadata, target: Target, index: u16, sub: u8) -> Description {
    match m.lookup(target, index, sub) {
        Lookup::Found(d) => *d,
        other => panic!("{index:04X}sub{sub}: {other:?}"),
    }
}

fn text(d: &Description, name: bool, lang: &str) -> Option<String> {
    let texts = if name { &d.name } else { &d.hint };
    texts.get(lang).map(str::to_owned)
}

fn write_file(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("scratch file");
    path
}

#[test]
fn vendor_objects_take_the_eds_facts_and_the_vendor_texts() {
    let m = with_eds();
    let d = found(&m, CONTROLLER, 0x2000, 0);
    assert_eq!(
        text(&d, true, "en").as_deref(),
        Some("Door hold time"),
        "EDS name"
    );
    assert_eq!(
        text(&d, true, "de").as_deref(),
        Some("Türoffenhaltezeit"),
        "vendor name"
    );
    assert_eq!(
        text(&d, false, "de").as_deref(),
        Some("Wie lange die Türen an einer Etage offen bleiben.")
    );
    assert_eq!(d.access, Access::Rw);
    assert_eq!((d.min, d.max), (Some(Bound::Int(0)), Some(Bound::Int(600))));
    assert_eq!(d.privilege, Privilege::Service);
    assert_eq!(d.formtype.code(), 12);
    assert_eq!(d.physunit.code(), 3);

    let mode = found(&m, CONTROLLER, 0x2003, 0);
    assert_eq!(mode.list.len(), 3);
    assert_eq!(mode.list[1].get("de"), Some("Inspektion"));
    assert_eq!(mode.privilege, Privilege::Setup);
}

#[test]
fn an_object_no_one_describes_is_derived_from_the_eds_and_needs_the_default_privilege() {
    let m = with_eds();
    let d = found(&m, CONTROLLER, 0x2001, 0);
    assert_eq!(text(&d, true, "en").as_deref(), Some("Total trips"));
    assert_eq!(
        text(&d, true, "de"),
        None,
        "no German name invented: the portal falls back"
    );
    assert_eq!(d.access, Access::Ro);
    assert_eq!(d.formtype, FormType::Number);
    assert_eq!(d.physunit, PhysUnit::None);
    assert_eq!(d.privilege, Privilege::Setup, "default_privilege");
}

#[test]
fn the_default_privilege_comes_from_the_policy() {
    let mut config = Config::default();
    config.bus.nodes = vec![node(1, Some(fixture("controller.eds")), None)];
    config.policy.default_privilege = 1;
    let m = BusMetadata::load(&config).expect("loads");
    assert_eq!(
        found(&m, CONTROLLER, 0x2001, 0).privilege,
        Privilege::Service
    );
}

#[test]
fn a_catalog_object_takes_the_catalogs_texts_where_the_eds_has_it() {
    let m = with_eds();
    let d = found(&m, CONTROLLER, 0x6520, 1);
    assert_eq!(
        text(&d, true, "en").as_deref(),
        Some("Trip counter [trips]")
    );
    assert_eq!(
        text(&d, true, "de").as_deref(),
        Some("Fahrtenzähler [Fahrten]")
    );
    assert_eq!(d.access, Access::Ro, "from the EDS");
}

#[test]
fn a_catalog_object_the_eds_lacks_does_not_exist() {
    let m = with_eds();
    assert!(matches!(m.lookup(CONTROLLER, 0x4112, 0), Lookup::NoObject));
    assert!(matches!(m.lookup(CONTROLLER, 0x6520, 2), Lookup::NoSub));
    assert!(m.object_texts(CONTROLLER, 0x4112).is_none());
}

#[test]
fn communication_objects_take_the_standard_texts() {
    let m = with_eds();
    let d = found(&m, CONTROLLER, 0x1018, 1);
    assert_eq!(text(&d, true, "en").as_deref(), Some("Vendor-ID"));
    assert!(text(&d, true, "de").is_some(), "German from CiA 301");
    let (name, _) = m.object_texts(CONTROLLER, 0x1003).expect("object texts");
    assert_eq!(name.get("en"), Some("Pre-defined error field"));
}

#[test]
fn a_vendor_text_of_another_data_type_is_not_used() {
    let dir = tempfile::tempdir().expect("scratch");
    let vendor = write_file(
        dir.path(),
        "other.toml",
        "[[object]]\nindex = 0x2001\ncode = \"var\"\nname = { en = \"Fahrten\" }\ntype = 7\nform = 10\naccess = \"ro\"\n",
    );
    let m = load(vec![node(1, Some(fixture("controller.eds")), Some(vendor))]).expect("loads");
    assert_eq!(
        found(&m, CONTROLLER, 0x2001, 0).name.get("en"),
        Some("Fahrten"),
        "same type: used"
    );
}

#[test]
fn without_an_eds_the_controller_is_the_catalog_plus_the_communication_profile() {
    let m = load(Vec::new()).expect("loads");
    let trips = found(&m, CONTROLLER, 0x6520, 1);
    assert_eq!(trips.name.get("en"), Some("Trip counter [trips]"));
    let identity = found(&m, CONTROLLER, 0x1018, 4);
    assert_eq!(identity.name.get("en"), Some("Serial number"));
    assert_eq!(identity.access, Access::Ro);
    assert!(matches!(m.lookup(CONTROLLER, 0x2000, 0), Lookup::NoObject));
    assert!(matches!(m.lookup(CONTROLLER, 0x1018, 9), Lookup::NoSub));
}

#[test]
fn another_node_is_described_only_by_what_describes_it() {
    let m = load(vec![node(13, Some(fixture("controller.eds")), None)]).expect("loads");
    let trips = found(&m, IO_NODE, 0x6520, 1);
    assert_eq!(
        trips.name.get("de"),
        Some("Fahrtenzähler [Fahrten]"),
        "catalog names on any node with the object"
    );
    let bare = load(Vec::new()).expect("loads");
    assert!(matches!(bare.lookup(IO_NODE, 0x2000, 0), Lookup::Unknown));
    assert!(matches!(
        bare.lookup(Target { net: 2, node: 1 }, 0x6520, 1),
        Lookup::Unknown
    ));
}

#[test]
fn a_vendor_file_alone_describes_a_node() {
    let m = load(vec![node(13, None, Some(fixture("controller-nxg.toml")))]).expect("loads");
    let d = found(&m, IO_NODE, 0x2002, 0);
    assert_eq!(d.name.get("de"), Some("Standortname"));
    assert!(matches!(m.lookup(IO_NODE, 0x2001, 0), Lookup::NoObject));
}

fn refused(nodes: Vec<NodeSection>) -> String {
    match load(nodes) {
        Ok(_) => panic!("loaded"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn a_vendor_type_that_contradicts_the_eds_stops_the_gateway_at_its_line() {
    let dir = tempfile::tempdir().expect("scratch");
    let vendor = write_file(
        dir.path(),
        "wrong.toml",
        "languages = [\"en\"]\n\n[[object]]\nindex = 0x2000\ncode = \"var\"\nname = { en = \"Door\" }\ntype = 7\nform = 10\naccess = \"rw\"\n",
    );
    let message = refused(vec![node(
        1,
        Some(fixture("controller.eds")),
        Some(vendor.clone()),
    )]);
    let at = format!("{}:4:", vendor.display());
    assert!(message.starts_with(&at), "{message}");
    assert!(message.contains("data type"), "{message}");
}

#[test]
fn an_unknown_key_in_a_vendor_file_stops_the_gateway_at_its_line() {
    let dir = tempfile::tempdir().expect("scratch");
    let vendor = write_file(
        dir.path(),
        "typo.toml",
        "[[object]]\nindex = 0x2000\ncode = \"var\"\nnmae = { en = \"Door\" }\ntype = 6\nform = 10\naccess = \"rw\"\n",
    );
    let message = refused(vec![node(1, None, Some(vendor.clone()))]);
    let at = format!("{}:4:", vendor.display());
    assert!(message.starts_with(&at), "{message}");
    assert!(message.contains("nmae"), "{message}");
}

#[test]
fn a_broken_limit_is_a_finding_and_keeps_its_object_read_only() {
    let dir = tempfile::tempdir().expect("scratch");
    let good = std::fs::read_to_string(fixture("controller.eds")).expect("fixture");
    let broken = good.replacen(
        "DataType=0x0006\nAccessType=rw\nLowLimit=0",
        "DataType=0x0006\nAccessType=rw\nLowLimit=zero",
        1,
    );
    assert_ne!(good, broken);
    let line = broken
        .lines()
        .position(|l| l == "LowLimit=zero")
        .expect("the broken line");
    // The object whose section holds the broken line.
    let index = broken.lines().take(line).filter_map(|l| {
        let name = l.strip_prefix('[')?.strip_suffix(']')?;
        u16::from_str_radix(name.get(..4)?, 16).ok()
    });
    let index = index.last().expect("its section");
    let eds = write_file(dir.path(), "broken.eds", &broken);
    let m = load(vec![node(1, Some(eds), None)]).expect("the gateway starts");
    let sub = if broken
        .lines()
        .take(line)
        .any(|l| l.starts_with(&format!("[{index:04X}sub")))
    {
        1
    } else {
        0
    };
    let d = found(&m, CONTROLLER, index, sub);
    assert_eq!(d.access, Access::Ro, "{index:04X}sub{sub}: never written");
}

#[test]
fn an_eds_without_a_usable_object_stops_the_gateway() {
    let dir = tempfile::tempdir().expect("scratch");
    let eds = write_file(dir.path(), "empty.eds", "[FileInfo]\nFileName=empty.eds\n");
    let message = refused(vec![node(1, Some(eds.clone()), None)]);
    assert!(
        message.starts_with(&format!("{}:0: no usable object", eds.display())),
        "{message}"
    );
}

/// A CiA 401 I/O module's inputs (6000h), as such a module's EDS writes them, with `device`
/// in 1000h.
fn io_module(dir: &Path, device: u32) -> PathBuf {
    let text = format!(
        "[1000]\nParameterName=Device type\nObjectType=0x7\nDataType=0x0007\nAccessType=ro\nDefaultValue=0x{device:08X}\n\
         [6000]\nParameterName=Read input 8-bit\nObjectType=0x8\nSubNumber=2\n\
         [6000sub0]\nParameterName=Number of entries\nObjectType=0x7\nDataType=0x0005\nAccessType=ro\nDefaultValue=1\n\
         [6000sub1]\nParameterName=Input block 1\nObjectType=0x7\nDataType=0x0005\nAccessType=ro\n"
    );
    write_file(dir, &format!("io-{device:08X}.eds"), &text)
}

#[test]
fn the_lift_catalog_describes_only_a_lift() {
    let dir = tempfile::tempdir().expect("scratch");
    // A CiA 401 module (profile 401 = 0191h): its own names, none of the lift's.
    let m = load(vec![node(
        13,
        Some(io_module(dir.path(), 0x000F_0191)),
        None,
    )])
    .expect("loads");
    for sub in [0, 1] {
        let d = found(&m, IO_NODE, 0x6000, sub);
        assert_eq!(d.name.get("de"), None, "6000sub{sub}: {:?}", d.name);
    }
    assert_eq!(
        found(&m, IO_NODE, 0x6000, 0).name.get("en"),
        Some("Number of entries")
    );
    assert_eq!(
        m.object_texts(IO_NODE, 0x6000)
            .map(|(name, _)| name.get("de").map(str::to_owned)),
        Some(None),
        "the object's name is its EDS's"
    );
    // The same module saying it is a CiA 417 device (01A1h): the catalog's texts.
    let m = load(vec![node(
        13,
        Some(io_module(dir.path(), 0x0008_01A1)),
        None,
    )])
    .expect("loads");
    let d = found(&m, IO_NODE, 0x6000, 0);
    assert!(d.name.get("de").is_some(), "{:?}", d.name);
}

#[test]
fn a_missing_file_names_itself() {
    let message = refused(vec![node(
        1,
        None,
        Some(PathBuf::from("/nonexistent/nxg.toml")),
    )]);
    assert!(message.starts_with("/nonexistent/nxg.toml:"), "{message}");
}

#[test]
fn catalog_texts_in_the_manufacturer_area_need_the_same_name() {
    let dir = tempfile::tempdir().expect("scratch");
    let good = std::fs::read_to_string(fixture("controller.eds")).expect("fixture");
    // 5022h is canlift's call object (u32, "Car call"-like); another vendor's 5022h is not.
    let extra = "\n[5022]\nParameterName=Fan speed\nObjectType=0x7\nDataType=0x0007\nAccessType=rw\nPDOMapping=0\n";
    let eds = write_file(dir.path(), "fan.eds", &format!("{good}{extra}"));
    let m = load(vec![node(1, Some(eds), None)]).expect("loads");
    let d = found(&m, CONTROLLER, 0x5022, 0);
    assert_eq!(d.name.get("en"), Some("Fan speed"));
    assert_eq!(d.name.get("de"), None, "not the catalog's 5022h");

    let same = write_file(
        dir.path(),
        "call.eds",
        &format!("{good}{}", extra.replace("Fan speed", "Passenger call")),
    );
    let m = load(vec![node(1, Some(same), None)]).expect("loads");
    let d = found(&m, CONTROLLER, 0x5022, 0);
    assert_eq!(
        d.name.get("de"),
        Some("Fahrgastruf"),
        "the catalog's own object"
    );
    assert_eq!(d.privilege, Privilege::User);
}
