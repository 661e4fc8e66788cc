use super::*;
use nxg::meta::{Hints, Privilege};

fn catalog() -> &'static Catalog {
    Catalog::builtin()
}

fn en(texts: &Texts) -> &str {
    texts.get("en").unwrap()
}

#[test]
fn the_builtin_catalog_is_sound() {
    let problems = catalog().validate();
    assert!(problems.is_empty(), "{problems:#?}");
    assert_eq!(catalog().languages(), ["en", "de"]);
    // The CiA 417 groups of the issue are all there, for lift 1.
    for index in [
        0x6000, 0x6001, 0x6010, 0x6011, 0x6012, 0x6020, 0x6100, 0x611F, 0x6120, 0x619F, 0x6200,
        0x629F, 0x6300, 0x6301, 0x6302, 0x6304, 0x6307, 0x6310, 0x6380, 0x6383, 0x6390, 0x6391,
        0x63B0, 0x63BB, 0x63C8, 0x63D3, 0x6400, 0x6438, 0x6480, 0x6485, 0x6500, 0x651F, 0x6520,
        0x653F, 0x6540, 0x657F,
    ] {
        assert!(catalog().object(index).is_some(), "{index:04X}h missing");
    }
    assert_eq!(
        en(&catalog().object(0x611F).unwrap().name()),
        "Input group 32"
    );
    assert_eq!(
        en(&catalog().object(0x6307).unwrap().name()),
        "Door 4 configuration"
    );
    assert_eq!(
        en(&catalog().object(0x6521).unwrap().name()),
        "Sensor parameter 1 group 2"
    );
}

/// The built-in catalog's text, as `build.rs` reads it.
const BUILTIN_TOML: &str = include_str!("../../catalog/lift.toml");

#[test]
fn the_static_tables_hold_what_the_catalog_text_reads_into() {
    let read = Catalog::from_toml(BUILTIN_TOML).unwrap();
    assert_eq!(&read, catalog());
    assert!(matches!(catalog().tables.objects, Cow::Borrowed(_)));
    assert!(matches!(read.tables.objects, Cow::Owned(_)));
    // A catalog read at run time shares its texts with its descriptions instead of copying.
    assert!(matches!(read.tables.text, tables::TextTables::Shared(_)));
    // Texts borrowed from the static tables read as those copied from the owned ones.
    for (ours, theirs) in catalog().objects().zip(read.objects()) {
        assert_eq!((ours.name(), ours.hint()), (theirs.name(), theirs.hint()));
        assert!(ours.entries().eq(theirs.entries()), "{:04X}h", ours.index());
    }
}

#[test]
fn every_span_of_the_tables_lands_inside_its_table() {
    let t = &catalog().tables;
    let tables::TextTables::Static { pool, pairs } = &t.text else {
        panic!("the built-in catalog's tables are static");
    };
    let string = |s: tables::Span| {
        let end = (s.start + s.len) as usize;
        assert!(pool.get(s.start as usize..end).is_some(), "{s:?}");
    };
    let texts = |s: tables::Span| {
        let end = (s.start + s.len) as usize;
        for p in pairs.get(s.start as usize..end).unwrap() {
            string(tables::Span {
                start: p.lang_start,
                len: p.lang_len,
            });
            string(tables::Span {
                start: p.text_start,
                len: p.text_len,
            });
        }
    };
    for e in t.entries.iter() {
        texts(e.name);
        texts(e.hint);
        let end = (e.list.start + e.list.len) as usize;
        t.lists
            .get(e.list.start as usize..end)
            .unwrap()
            .iter()
            .for_each(|&l| texts(l));
        e.default.map(string);
    }
    let mut previous = None;
    for o in t.objects.iter() {
        assert!(previous < Some(o.index), "objects by index");
        previous = Some(o.index);
        texts(o.name);
        texts(o.hint);
        let listed = t.listed(o);
        assert_eq!(listed.len(), o.listed.len as usize);
        assert!(
            listed.windows(2).all(|w| w[0].sub < w[1].sub),
            "{:04X}h",
            o.index
        );
        assert!(listed.iter().all(|e| e.index == o.index));
        assert_eq!(t.element(o).is_some(), o.element.is_some());
    }
}

#[test]
fn the_nxg_sample_objects_carry_the_sample_metadata() {
    // NXg SW003 §6.1.1: the trip counter.
    let trip = catalog().lookup(0x6520, 1).unwrap().entry;
    assert_eq!(trip.description.objcode, nxg::meta::ObjCode::Array);
    assert_eq!(trip.description.datatype.code(), 7);
    assert_eq!(trip.description.formtype.code(), 10);
    assert_eq!(trip.description.physunit.code(), 26);
    assert_eq!(trip.description.access, Access::Ro);
    assert_eq!(trip.description.privilege.code(), 0);
    assert_eq!(en(&trip.description.name), "Trip counter [trips]");
    assert_eq!(
        en(&trip.description.hint),
        "This object represents the internal trip counter of the lift controller."
    );
    assert_eq!(trip.description.min, Some(Bound::Int(0)));
    assert_eq!(trip.description.max, Some(Bound::Int(4_294_967_295)));
    assert!(
        !trip.description.zero
            && trip.description.list.is_empty()
            && trip.description.hints == Hints::default()
    );
    assert!(trip.persist);
    let hours = catalog().lookup(0x6520, 2).unwrap().entry;
    assert_eq!(en(&hours.description.name), "Operating hours [h]");
    // §6.1.4: hall lantern options with a list of four.
    let lantern = catalog().lookup(0x4112, 0).unwrap().entry;
    assert_eq!(
        (
            lantern.description.objcode,
            lantern.description.datatype.code(),
            lantern.description.formtype.code()
        ),
        (nxg::meta::ObjCode::Var, 5, 15)
    );
    assert_eq!(
        (
            lantern.description.access,
            lantern.description.privilege.code()
        ),
        (Access::Rw, 1)
    );
    assert_eq!(
        (lantern.description.min, lantern.description.max),
        (Some(Bound::Int(0)), Some(Bound::Int(3)))
    );
    let texts: Vec<&str> = lantern.description.list.iter().map(en).collect();
    assert_eq!(
        texts[0],
        "Turn the hall lantern on, when approaching to the floor"
    );
    assert_eq!(texts[3], "off");
    assert_eq!(
        en(&lantern.description.hint),
        "This object defines the moment to turn on the hall lantern.."
    );
    // §6.2.2: floor level positions, read compact.
    let floors = catalog().lookup(0x4010, 1).unwrap().entry;
    assert_eq!(
        (
            floors.description.objcode,
            floors.description.datatype.code(),
            floors.description.formtype.code(),
            floors.description.physunit.code()
        ),
        (nxg::meta::ObjCode::Array, 4, 26, 15)
    );
    assert_eq!(
        (
            floors.description.access,
            floors.description.privilege.code()
        ),
        (Access::Ro, 1)
    );
    assert_eq!(floors.description.max, Some(Bound::Int(2_147_483_647)));
    assert_eq!(
        en(&catalog().object(0x4010).unwrap().name()),
        "Floor level positions"
    );
    // §6.3.1: the passenger call takes UNSIGNED32, physunit 0, from any user.
    let call = catalog().lookup(0x5022, 0).unwrap().entry;
    assert_eq!(
        (
            call.description.datatype.code(),
            call.description.physunit.code()
        ),
        (7, 0)
    );
    assert_eq!(
        (call.description.access, call.description.privilege),
        (Access::Rw, Privilege::User)
    );
}

#[test]
fn lookups_follow_the_lift_number_rule_and_the_manufacturer_stride() {
    let c = catalog();
    let pos2 = c.lookup(0x6B83, 1).unwrap();
    assert_eq!((pos2.lift, pos2.entry.index), (2, 0x6383));
    let trip8 = c.lookup(0x9D20, 1).unwrap();
    assert_eq!(
        (trip8.lift, en(&trip8.entry.description.name)),
        (8, "Trip counter [trips]")
    );
    let call3 = c.lookup(0x5222, 0).unwrap();
    assert_eq!((call3.lift, call3.entry.index), (3, 0x5022));
    let floors2 = c.lookup(0x4110, 4).unwrap();
    assert_eq!((floors2.lift, floors2.entry.index), (2, 0x4010));
    assert!(c.lookup(0x6383, 5).is_none(), "only four position units");
    assert!(c.lookup(0x5021, 0).is_none());
    assert!(c.lookup(0x2000, 0).is_some(), "the I/O node's object");
    assert!(c.lookup(0x2100, 0).is_none(), "not per lift");
}

#[test]
fn languages_fall_back_in_the_requested_order() {
    let c = catalog();
    let trip = c.lookup(0x6520, 1).unwrap().entry;
    assert_eq!(
        c.text(&trip.description.name, "fr", "de"),
        Some(("fr", "Compteur de courses [courses]"))
    );
    assert_eq!(
        c.text(&trip.description.name, "DE", "en"),
        Some(("de", "Fahrtenzähler [Fahrten]"))
    );
    let hours = c.lookup(0x6520, 2).unwrap().entry;
    assert_eq!(
        c.text(&hours.description.name, "fr", "de").map(|t| t.0),
        Some("de")
    );
    assert_eq!(
        c.text(&hours.description.name, "fr", "it").map(|t| t.0),
        Some("en")
    );
    assert_eq!(
        c.text(&hours.description.name, "it", "es").map(|t| t.0),
        Some("en")
    );
}

#[test]
fn dictionaries_hold_every_lift_and_floor() {
    let c = catalog();
    let od = c.dictionary(Device::Controller, 3, 6).unwrap();
    for index in [
        0x6383, 0x6B83, 0x7383, 0x4010, 0x4110, 0x4210, 0x5022, 0x5222,
    ] {
        assert!(od.object(index).is_some(), "{index:04X}h missing");
    }
    assert!(od.object(0x7B83).is_none(), "no lift 4");
    assert!(od.object(0x2000).is_none(), "the I/O node's object");
    let floors = od.object(0x4010).unwrap();
    assert_eq!(floors.subs.len(), 7, "sub 0 and six floors");
    assert_eq!(od.get_value(0x4010, 0), Ok(Value::Uint(6)));
    assert_eq!(od.object(0x6B83).unwrap().name, "Position value (lift 2)");
    assert!(od.variable(0x6520, 1).unwrap().persist);
    assert!(od.variable(0x6383, 1).unwrap().pdo_mappable);
    assert_eq!(od.get_value(0x6304, 0), Ok(Value::Uint(11)));
    assert_eq!(od.get_value(0x6301, 1), Ok(Value::Uint(0xFFFF)));
    // Writes keep to the catalog's limits; 0 stays possible where it means "off".
    let mut od = od;
    assert_eq!(od.write(0x4112, 0, &[4]), Err(AbortCode::VALUE_TOO_HIGH));
    assert_eq!(od.write(0x4112, 0, &[3]), Ok(()));
    assert_eq!(
        od.write(0x4114, 0, &5u16.to_le_bytes()),
        Err(AbortCode::VALUE_TOO_LOW)
    );
    assert_eq!(od.write(0x4114, 0, &0u16.to_le_bytes()), Ok(()));
    assert_eq!(od.write(0x4114, 0, &60u16.to_le_bytes()), Ok(()));
    assert_eq!(
        od.write(0x6520, 1, &[1, 0, 0, 0]),
        Err(AbortCode::READ_ONLY)
    );
    let io = c.dictionary(Device::Io, 1, 8).unwrap();
    assert!(io.object(0x2000).is_some() && io.object(0x6100).is_some());
    assert!(io.object(0x6383).is_none());
    assert!(c.dictionary(Device::Controller, 9, 8).is_err());
}

const HEADER: &str = r#"
languages = ["en", "de"]
count_name = { en = "Number of entries", de = "Anzahl der Einträge" }
count_hint = { en = "Highest sub-index.", de = "Höchster Subindex." }
"#;

fn problems(objects: &str) -> Vec<String> {
    Catalog::from_toml(&format!("{HEADER}{objects}"))
        .unwrap()
        .validate()
}

#[test]
fn validation_finds_what_is_wrong() {
    let p = problems(
        r#"
[[object]]
index = 0x2001
code = "var"
name = { en = "Mode", de = "Modus", fr = "Mode" }
hint = { en = "A mode." }
type = 5
form = 15
access = "rw"
privilege = 1
min = 10
max = 300
list = [ { en = "a", de = "a" }, { en = "b", de = "b" } ]
default = "7"
"#,
    );
    let all = p.join("\n");
    assert!(all.contains("name in fr"), "{all}");
    assert!(all.contains("hint has no de text"), "{all}");
    assert!(all.contains("does not fit UNSIGNED8"), "{all}");
    assert!(all.contains("needs 291 list texts, has 2"), "{all}");
    assert!(all.contains("default 7 outside the limits"), "{all}");
    let p = problems(
        r#"
[[object]]
index = 0x2002
code = "var"
name = { en = "Name", de = "Name" }
hint = { en = "Its name.", de = "Sein Name." }
type = 7
form = 1
zero = true
off_at_zero = true
"#,
    );
    let all = p.join("\n");
    assert!(all.contains("form text does not suit UNSIGNED32"), "{all}");
    assert!(all.contains("0 is inside the range anyway"), "{all}");
}

#[test]
fn loading_refuses_overlaps_and_unknown_codes() {
    let object = |index: &str, extra: &str| {
        format!(
            "[[object]]\nindex = {index}\ncode = \"var\"\nname = {{ en = \"x\", de = \"x\" }}\n\
             hint = {{ en = \"x\", de = \"x\" }}\ntype = 7\n{extra}\n"
        )
    };
    let twice = format!("{HEADER}{}{}", object("0x2001", ""), object("0x2001", ""));
    assert!(matches!(
        Catalog::from_toml(&twice),
        Err(CatalogError::Object { index: 0x2001, .. })
    ));
    // Lift 2 of a per-lift object at 2001h lands on 2101h.
    let stride = format!(
        "{HEADER}{}{}",
        object("0x2001", "per_lift = true"),
        object("0x2101", "")
    );
    let err = Catalog::from_toml(&stride).unwrap_err().to_string();
    assert!(err.contains("lands on 2101h, already taken"), "{err}");
    let unit = format!("{HEADER}{}", object("0x2001", "unit = 99"));
    assert!(Catalog::from_toml(&unit)
        .unwrap_err()
        .to_string()
        .contains("99"));
    let syntax = format!("{HEADER}{}", object("0x2001", "colour = 1"));
    let err = Catalog::from_toml(&syntax).unwrap_err();
    assert!(matches!(err, CatalogError::Syntax { .. }));
    // Errors name the file's line: the unknown key's, or the inconsistent object's.
    let line = syntax
        .lines()
        .position(|l| l.starts_with("colour"))
        .unwrap()
        + 1;
    assert_eq!(
        err.located("vendor.toml", &syntax),
        format!("vendor.toml:{line}: unknown field `colour`")
    );
    let err = Catalog::from_toml(&unit).unwrap_err();
    let line = unit.lines().position(|l| l.contains("0x2001")).unwrap() + 1;
    assert!(err
        .located("v.toml", &unit)
        .starts_with(&format!("v.toml:{line}: object 2001h")));
}
