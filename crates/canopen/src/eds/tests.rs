use proptest::prelude::*;

use super::*;

fn fixture(name: &str) -> (String, String) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/eds")
        .join(name);
    (
        path.display().to_string(),
        std::fs::read_to_string(&path).unwrap(),
    )
}

/// A file that imports without a finding.
fn clean(name: &str, text: &str, node_id: Option<u8>) -> DeviceDescription {
    let imported = import(name, text, node_id).unwrap();
    assert_eq!(imported.findings, [], "{name}");
    imported.description
}

fn round_trip(d: &DeviceDescription, dcf: bool, node_id: Option<u8>) -> DeviceDescription {
    let text = export(d, dcf);
    let imported = import("exported", &text, node_id).unwrap_or_else(|e| panic!("{e}\n{text}"));
    assert_eq!(imported.findings, [], "{text}");
    imported.description
}

#[test]
fn canopennode_style_eds() {
    let (name, text) = fixture("canopennode-style.eds");
    let d = clean(&name, &text, Some(5));
    let od = &d.od;
    assert_eq!(od.get_value(0x1000, 0).unwrap(), Value::Uint(0x0001_01A1));
    assert_eq!(
        od.get_value(0x1014, 0).unwrap(),
        Value::Uint(0x85),
        "$NODEID+0x80"
    );
    assert_eq!(od.get_value(0x1200, 1).unwrap(), Value::Uint(0x605));
    assert_eq!(
        od.get_value(0x1200, 2).unwrap(),
        Value::Uint(0x585),
        "0x580+$NODEID"
    );
    assert_eq!(od.get_value(0x1800, 1).unwrap(), Value::Uint(0x4000_0185));
    assert_eq!(
        od.get_value(0x1008, 0).unwrap(),
        Value::Text("canlift lift controller".into())
    );
    assert_eq!(od.object(0x1018).unwrap().subs.len(), 5);
    assert_eq!(od.object(0x1018).unwrap().code, ObjectCode::Record);
    let v = od.variable(0x1017, 0).unwrap();
    assert_eq!(
        (v.low.clone(), v.high.clone()),
        (Some(Value::Uint(0)), Some(Value::Uint(65535)))
    );
    assert!(od.variable(0x2000, 0).unwrap().pdo_mappable);
    assert_eq!(od.variable(0x1008, 0).unwrap().access, Access::Const);
    assert_eq!(od.object(0x2100).unwrap().code, ObjectCode::Domain);
    assert_eq!(d.variable_default(0x1014), Some("$NODEID+0x80"));
    assert_eq!(
        d.device_info
            .iter()
            .find(|(k, _)| k == "ProductName")
            .unwrap()
            .1,
        "Lift controller"
    );
    assert_eq!(d.comments, vec!["generated for the canlift EDS tests"]);
    // The same file for another node.
    let other = clean(&name, &text, Some(9));
    assert_eq!(other.od.get_value(0x1200, 1).unwrap(), Value::Uint(0x609));
    assert_eq!(round_trip(&d, false, Some(5)), d);
    assert_eq!(round_trip(&d, true, Some(5)), d);
}

#[test]
fn odd_style_dcf() {
    let (name, text) = fixture("odd-style.dcf");
    let d = clean(&name, &text, None);
    let c = d.commissioning.clone().unwrap();
    assert_eq!((c.node_id, c.baudrate), (Some(12), Some(250)));
    assert_eq!(c.node_name.as_deref(), Some("car terminal box"));
    let od = &d.od;
    assert_eq!(
        od.get_value(0x1000, 0).unwrap(),
        Value::Uint(0o417),
        "leading zero is octal"
    );
    let hb = od.object(0x1016).unwrap();
    assert_eq!(hb.code, ObjectCode::Array);
    assert_eq!(hb.subs.len(), 4, "CompactSubObj=3 plus sub-index 0");
    assert_eq!(od.get_value(0x1016, 0).unwrap(), Value::Uint(3));
    assert_eq!(hb.subs[&1].name, "Consumer 1 (lift controller)");
    assert_eq!(
        hb.subs[&3].name, "Consumer heartbeat time3",
        "unnamed compact entries"
    );
    assert_eq!(
        od.get_value(0x1016, 2).unwrap(),
        Value::Uint(0x0002_03E8),
        "[1016Value]"
    );
    assert_eq!(od.get_value(0x1016, 3).unwrap(), Value::Uint(0));
    assert_eq!(
        od.get_value(0x2001, 0).unwrap(),
        Value::Bool(false),
        "ParameterValue wins over DefaultValue"
    );
    assert_eq!(
        od.variable(0x2001, 0).unwrap().denotation.as_deref(),
        Some("light in car 1")
    );
    assert_eq!(od.variable(0x2001, 0).unwrap().access, Access::Rww);
    assert_eq!(
        od.get_value(0x6000, 0).unwrap(),
        Value::Int(0x18C),
        "0x180 + $NODEID with NodeID 12"
    );
    assert_eq!(od.variable(0x6000, 0).unwrap().low, Some(Value::Int(-100)));
    assert_eq!(
        od.variable(0x6000, 0).unwrap().high,
        Some(Value::Int(100)),
        "0144 octal"
    );
    assert_eq!(d.object_links.get(&0x2001), Some(&vec![0x6000]));
    assert_eq!(round_trip(&d, true, None), d);
}

#[test]
fn defects_are_findings_with_file_line_and_what_was_done() {
    use Severity::{Error, Warning};
    // (file text, line, severity, reason, whether object 0x1000 is still there)
    let cases: &[(&str, usize, Severity, &str, bool)] = &[
        ("[FileInfo\nx=1\n[1000]\nParameterName=x\nDataType=7\n", 1, Warning, "closing ']'", true),
        ("x=1\n[1000]\nParameterName=x\nDataType=7\n", 1, Warning, "before the first", true),
        ("[1000]\nParameterName=x\nnot a pair\nDataType=7\n", 3, Warning, "KEY=VALUE", true),
        ("[1000]\nParameterName=x\nDataType=7\n[1000]\nParameterName=y\n", 4, Warning, "appears twice", true),
        ("[1000]\nParameterName=x\nDataType=7\nDataType=5\n", 4, Warning, "key DataType appears twice", true),
        ("[MandatoryObjects]\nSupportedObjects=2\n1=0x1000\n2=0x1001\n[1000]\nParameterName=x\nDataType=7\n", 4, Error, "no [1001] section", true),
        ("[ManufacturerObjects]\nSupportedObjects=3\n1=0x1000\n[1000]\nParameterName=x\nDataType=7\n", 2, Warning, "counts 3 objects and lists 1", true),
        ("[1000]\nParameterName=x\nDataType=7\n[1001]\nParameterName=y\nDataType=0x0040\n", 6, Error, "0x0040 is not a CiA 301 type", true),
        ("[1000]\nParameterName=x\nDataType=0x0005\nDefaultValue=300\n", 4, Warning, "not a valid UNSIGNED8: left empty", true),
        ("[1000]\nParameterName=x\nDataType=0x0009\nDefaultValue=Türe\t€\n", 4, Warning, "VISIBLE_STRING", true),
        ("[1000]\nParameterName=x\nDataType=0x000F\nDefaultValue=@ABCD\n", 4, Warning, "DOMAIN", true),
        ("[1000]\nParameterName=x\nDataType=0x0005\nAccessType=readonly\n", 4, Error, "read-only here", true),
        ("[1000]\nParameterName=x\nDataType=0x0005\nAccessType=rw\nHighLimit=x\n", 5, Error, "HighLimit", true),
        ("[1000]\nDataType=7\n", 1, Warning, "no ParameterName", true),
        ("[1000]\nParameterName=x\nDataType=7\n[1018]\nParameterName=x\nObjectType=0x9\nSubNumber=5\n[1018sub0]\nParameterName=n\nDataType=5\n[1018sub1]\nParameterName=v\nDataType=7\n", 7, Warning, "SubNumber=5 but 2", true),
        ("[1000]\nParameterName=x\nDataType=7\n[1F51]\nParameterName=x\nObjectType=0x8\nSubNumber=8\n[1F51sub7]\nParameterName=s\nDataType=5\n", 4, Warning, "no sub-index 0: made", true),
        ("[1000]\nParameterName=x\nDataType=7\n[1018]\nParameterName=x\nObjectType=0x9\n", 4, Error, "no usable sub-object", true),
    ];
    for (text, line, severity, reason, kept) in cases {
        let imported = import("bad.eds", text, Some(1)).unwrap_or_else(|e| panic!("{text:?}: {e}"));
        let found = imported
            .findings
            .iter()
            .find(|f| f.message.contains(reason))
            .unwrap_or_else(|| panic!("{text:?}: {:?}", imported.findings));
        assert_eq!(
            (found.line, found.severity),
            (*line, *severity),
            "{text:?}: {found}"
        );
        assert!(found
            .to_string()
            .starts_with(&format!("bad.eds:{line}: {}: ", severity.name())));
        assert_eq!(
            imported.description.od.object(0x1000).is_some(),
            *kept,
            "{text:?}"
        );
    }
    // What is left out is not there; what is kept read-only cannot be written.
    let imported = import("bad.eds", cases[7].0, Some(1)).unwrap();
    assert!(imported.description.od.object(0x1001).is_none());
    let imported = import("bad.eds", cases[12].0, Some(1)).unwrap();
    assert_eq!(
        imported.description.od.variable(0x1000, 0).unwrap().access,
        Access::Ro
    );
    let sub0 = import("bad.eds", cases[15].0, Some(1)).unwrap();
    assert_eq!(
        sub0.description.od.get_value(0x1F51, 0).unwrap(),
        Value::Uint(7)
    );
}

#[test]
fn a_file_without_a_usable_object_or_unreadable_is_refused() {
    for text in [
        "",
        "[FileInfo]\nFileName=x\n",
        "[1000]\nParameterName=x\nDataType=0x0040\n",
    ] {
        let e = import("empty.eds", text, Some(1)).unwrap_err();
        assert_eq!(
            (e.line, e.reason.as_str()),
            (0, "no usable object"),
            "{text:?}"
        );
    }
    let e = import_file(std::path::Path::new("/nonexistent/x.eds"), None).unwrap_err();
    assert_eq!(e.file, "/nonexistent/x.eds");
}

#[test]
fn windows_1252_text_is_read_with_a_finding() {
    let bytes = b"[1000]\nParameterName=T\xfcr \x80\nDataType=7\n";
    let imported = import_bytes("latin.eds", bytes, Some(1)).unwrap();
    assert_eq!(
        imported.description.od.object(0x1000).unwrap().name,
        "Tür €"
    );
    assert_eq!(imported.findings.len(), 1);
    assert_eq!(imported.findings[0].line, 2);
    assert!(imported.findings[0].message.contains("Windows-1252"));
}

fn arb_variable() -> impl Strategy<Value = Variable> {
    let types = vec![
        DataType::Boolean,
        DataType::Integer8,
        DataType::Integer32,
        DataType::Integer64,
        DataType::Unsigned8,
        DataType::Unsigned24,
        DataType::Unsigned32,
        DataType::Real32,
        DataType::Real64,
        DataType::VisibleString,
        DataType::OctetString,
        DataType::Domain,
    ];
    let access = proptest::sample::select(vec![
        Access::Ro,
        Access::Wo,
        Access::Rw,
        Access::Rwr,
        Access::Rww,
        Access::Const,
    ]);
    (
        proptest::sample::select(types),
        access,
        any::<bool>(),
        "[A-Za-z][A-Za-z0-9 ()-]{0,30}",
        any::<u64>(),
        "[ -~&&[^;]]{0,20}",
    )
        .prop_map(|(ty, access, mappable, name, seed, text)| {
            let value = match ty {
                DataType::Boolean => Value::Bool(seed % 2 == 1),
                DataType::Real32 => Value::Real32((seed % 100_000) as f32 / 8.0),
                DataType::Real64 => Value::Real64(seed as f64 / 3.0),
                DataType::VisibleString => Value::Text(text.trim().to_owned()),
                DataType::OctetString | DataType::Domain => {
                    Value::Bytes(seed.to_le_bytes()[..(seed % 9) as usize].to_vec())
                }
                t if t.is_signed() => {
                    let (lo, hi) = t.integer_range().unwrap();
                    Value::Int((lo + (seed as i128 % (hi - lo + 1))) as i64)
                }
                t => {
                    let (_, hi) = t.integer_range().unwrap();
                    Value::Uint((seed as i128 % (hi + 1)) as u64)
                }
            };
            let mut v = Variable::new(name.trim().to_owned() + "x", ty, access).with_value(value);
            v.pdo_mappable = mappable;
            v
        })
}

proptest! {
    #[test]
    fn export_then_import_gives_the_same_dictionary(
        vars in proptest::collection::vec((0x1000u16..0xA000, arb_variable()), 1..20),
        records in proptest::collection::vec((0x2000u16..0x2100, proptest::collection::vec(arb_variable(), 1..5)), 0..4),
    ) {
        let mut d = DeviceDescription::default();
        for (index, var) in vars {
            d.od.insert(Object::var(index, var));
        }
        for (index, vars) in records {
            let code = if index % 2 == 0 { ObjectCode::Record } else { ObjectCode::Array };
            d.od.insert(Object::composite(index, format!("Record {index:04X}"), code, vars.into_iter().enumerate().map(|(i, v)| (i as u8 + 1, v))));
        }
        prop_assert_eq!(&round_trip(&d, false, Some(1)).od, &d.od);
        prop_assert_eq!(&round_trip(&d, true, Some(1)).od, &d.od);
    }

    #[test]
    fn arbitrary_text_never_panics(text in "(\\[[0-9A-Za-z]{0,8}\\]\n|[A-Za-z]{1,12}=[ -~]{0,12}\n|;[ -~]{0,10}\n){0,30}") {
        let _ = import("fuzz.eds", &text, Some(1));
    }
}
