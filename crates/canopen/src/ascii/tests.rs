use proptest::prelude::*;

use super::*;

fn session() -> Session {
    Session::new(1, Duration::from_millis(500), "test gateway")
}

fn job(line: &str) -> Job {
    match session().handle(line) {
        Step::Run(job) => job,
        other => panic!("{line:?}: {other:?}"),
    }
}

fn reply(s: &mut Session, line: &str) -> String {
    match s.handle(line) {
        Step::Reply(r) => r.to_string(),
        other => panic!("{line:?}: {other:?}"),
    }
}

#[test]
fn reads_with_and_without_sequence_net_and_type() {
    let j = job("[1] 4 read 0x1017 0 u16");
    assert_eq!((j.sequence, j.net, j.node), (Some(1), 1, 4));
    assert_eq!(
        j.action,
        Action::Read {
            index: 0x1017,
            sub: 0,
            ty: AsciiType::from_mnemonic("u16")
        }
    );
    let j = job("1 5 r 4096 0");
    assert_eq!((j.sequence, j.net, j.node), (None, 1, 5));
    assert_eq!(
        j.action,
        Action::Read {
            index: 0x1000,
            sub: 0,
            ty: None
        }
    );
    // Upper case, a comment, CR left by the transport's line split.
    let j = job("[77] 5 READ 0x1018 1 X32   # vendor\r");
    assert_eq!(j.sequence, Some(77));
    assert!(
        matches!(j.action, Action::Read { index: 0x1018, sub: 1, ty: Some(t) } if t.form == Form::Hex)
    );
}

#[test]
fn writes_keep_the_value_text_whole() {
    let j = job(r#"[2] 5 w 0x2000 0 vs "lift ""A"" #1""#);
    assert_eq!(
        j.action,
        Action::Write {
            index: 0x2000,
            sub: 0,
            data: br#"lift "A" #1"#.to_vec()
        }
    );
    let j = job("[3] 5 write 0x6520 1 u32 0x10");
    assert!(matches!(j.action, Action::Write { data, .. } if data == [0x10, 0, 0, 0]));
    let j = job("5 w 0x2001 0 d AAEC/w==");
    assert!(matches!(j.action, Action::Write { data, .. } if data == [0, 1, 2, 0xFF]));
    let j = job("5 w 0x2001 0 hex 00 01 02 ff");
    assert!(matches!(j.action, Action::Write { data, .. } if data == [0, 1, 2, 0xFF]));
    let j = job("5 w 0x2002 0 vs single");
    assert!(matches!(j.action, Action::Write { data, .. } if data == b"single"));
}

#[test]
fn values_that_do_not_fit_answer_the_abort_code() {
    let mut s = session();
    assert_eq!(
        reply(&mut s, "[4] 5 w 0x2000 0 u8 256"),
        "[4] ERROR: 0x06090031 #Value of parameter written too high (download only).\r\n"
    );
    assert_eq!(
        reply(&mut s, "[5] 5 w 0x2000 0 i8 -129"),
        "[5] ERROR: 0x06090032 #Value of parameter written too low (download only).\r\n"
    );
    assert!(reply(&mut s, "[6] 5 w 0x2000 0 d !!!").starts_with("[6] ERROR: 0x06090030"));
    assert!(reply(&mut s, "[7] 5 w 0x2000 0 vs \"open").starts_with("[7] ERROR: 0x06090030"));
}

#[test]
fn nmt_commands_and_all_nodes() {
    for (line, cmd) in [
        ("5 start", NmtCommand::Start),
        ("5 stop", NmtCommand::Stop),
        ("5 preop", NmtCommand::EnterPreOperational),
        ("5 preoperational", NmtCommand::EnterPreOperational),
        ("5 reset node", NmtCommand::ResetNode),
        ("5 reset comm", NmtCommand::ResetCommunication),
        ("5 reset communication", NmtCommand::ResetCommunication),
    ] {
        assert_eq!(job(line).action, Action::Nmt(cmd), "{line}");
    }
    assert_eq!(job("0 start").node, 0, "node 0 is every node for NMT");
    let mut s = session();
    assert!(reply(&mut s, "0 r 0x1000 0").contains("ERROR: 107"));
}

#[test]
fn defaults_come_from_set() {
    let mut s = session();
    assert_eq!(
        reply(&mut s, "[1] r 0x1000 0"),
        "[1] ERROR: 105 #No default node set.\r\n"
    );
    assert_eq!(reply(&mut s, "[2] set node 5"), "[2] OK\r\n");
    assert_eq!(reply(&mut s, "[3] set sdo_timeout 2000"), "[3] OK\r\n");
    assert_eq!(reply(&mut s, "[4] 1 set sdo_block 1"), "[4] OK\r\n");
    let Step::Run(j) = s.handle("[5] r 0x1000 0") else {
        panic!()
    };
    assert_eq!(j.node, 5);
    assert_eq!(j.sdo_timeout, Duration::from_millis(2000));
    assert!(j.sdo_block);
    assert_eq!(
        reply(&mut s, "[6] set network 2"),
        "[6] ERROR: 106 #Unsupported net.\r\n"
    );
    assert!(reply(&mut s, "[7] 2 5 r 0x1000 0").contains("ERROR: 106"));
    assert!(reply(&mut s, "[8] set node 128").contains("ERROR: 107"));
    assert!(reply(&mut s, "[9] set sdo_block 2").contains("ERROR: 101"));
    assert!(reply(&mut s, "[10] set colour 2").contains("ERROR: 100"));
}

#[test]
fn malformed_lines_answer_errors() {
    let mut s = session();
    for (line, code) in [
        ("[1] 5 r", "101"),
        ("[2] 5 r 0x10000 0", "101"),
        ("[3] 5 r 0x1000 256", "101"),
        ("[4] 5 r 0x1000 0 q7", "101"),
        ("[5] 5 w 0x1000 0 u8", "101"),
        ("[6] 5 jump", "100"),
        ("[7] 5 reset everything", "101"),
        ("[8] 1 2 3 r 0x1000 0", "101"),
        ("[x] 5 r 0x1000 0", "101"),
        ("[9", "101"),
        ("[10] lss_set_node 200", "502"),
        ("[11] lss_conf_bitrate 1 2", "503"),
        ("[12] lss_switch_glob 2", "101"),
        ("[13] lss_frobnicate", "100"),
    ] {
        let r = reply(&mut s, line);
        assert!(r.contains(&format!("ERROR: {code} #")), "{line}: {r}");
        assert!(r.ends_with("\r\n"));
    }
    assert_eq!(s.handle("   # only a comment"), Step::Nothing);
    assert_eq!(s.handle(""), Step::Nothing);
}

#[test]
fn lss_commands() {
    let lss = |line: &str| match job(line).action {
        Action::Lss(j) => j,
        other => panic!("{other:?}"),
    };
    assert_eq!(lss("lss_switch_glob 1"), LssJob::SwitchGlobal(true));
    assert_eq!(
        lss("[1] lss_switch_sel 0x428 0x431 2 0x5C17EEBC"),
        LssJob::SwitchSelective([0x428, 0x431, 2, 0x5C17_EEBC])
    );
    assert_eq!(lss("lss_set_node 0xFF"), LssJob::SetNode(0xFF));
    assert_eq!(lss("lss_conf_bitrate 0 4"), LssJob::ConfigureBitRate(4));
    assert_eq!(
        lss("lss_activate_bitrate 100"),
        LssJob::ActivateBitRate(100)
    );
    assert_eq!(lss("1 lss_store"), LssJob::Store);
    assert_eq!(lss("lss_inquire_addr"), LssJob::InquireAddress(None));
    assert_eq!(lss("lss_inquire_addr 3"), LssJob::InquireAddress(Some(3)));
    assert_eq!(lss("lss_get_node"), LssJob::GetNode);
    assert_eq!(
        lss("_lss_fastscan 50"),
        LssJob::Fastscan {
            step: Duration::from_millis(50),
            parts: [FastscanPart::Scan; 4]
        }
    );
    assert_eq!(
        lss("lss_allnodes 50 10 1"),
        LssJob::AllNodes {
            step: Duration::from_millis(50),
            parts: [FastscanPart::Scan; 4],
            first: 10,
            store: true
        }
    );
    assert_eq!(
        lss("lss_allnodes 50 10 0 2 0x41A 0 0 1 0 0 0"),
        LssJob::AllNodes {
            step: Duration::from_millis(50),
            parts: [
                FastscanPart::Match(0x41A),
                FastscanPart::Scan,
                FastscanPart::Skip,
                FastscanPart::Scan
            ],
            first: 10,
            store: false
        }
    );
    for bad in [
        "lss_allnodes 50 10 0 1 0 0 0 0 0 0 0",
        "lss_allnodes 50 10 0 0 0 0 0 0 0 1 0",
        "lss_allnodes 50 10 0 3 0 0 0 0 0 0 0",
        "lss_allnodes 50 10 0 2 0x100000000 0 0 0 0 0 0",
        "lss_allnodes 50 10 0 2 0",
    ] {
        let answer = reply(&mut session(), bad);
        assert!(answer.starts_with("ERROR: 101"), "{bad}: {answer}");
    }
}

#[test]
fn replies_print_as_the_document_shows() {
    let r = |outcome| {
        Reply {
            sequence: Some(3),
            outcome,
        }
        .to_string()
    };
    assert_eq!(r(Outcome::Ok), "[3] OK\r\n");
    assert_eq!(r(Outcome::Value("4660".into())), "[3] 4660\r\n");
    assert_eq!(
        r(Outcome::Error(Failure::Abort(AbortCode(0x0602_0000)))),
        "[3] ERROR: 0x06020000 #Object does not exist in the object dictionary.\r\n"
    );
    assert_eq!(
        r(Outcome::Error(Failure::Abort(AbortCode(0x1234_5678)))),
        "[3] ERROR: 0x12345678 #Unknown abort code.\r\n"
    );
    assert_eq!(
        r(Outcome::Lines(vec!["a".into(), "b".into()])),
        "a\r\nb\r\n[3] OK\r\n"
    );
    let unsequenced = Reply {
        sequence: None,
        outcome: Outcome::Ok,
    };
    assert_eq!(unsequenced.to_string(), "OK\r\n");
    assert_eq!(
        format_address([0x428, 1, 2, 3]),
        "0x00000428 0x00000001 0x00000002 0x00000003"
    );
}

#[test]
fn every_mnemonic_names_one_type() {
    for (m, ..) in MNEMONICS {
        let t = AsciiType::from_mnemonic(m).unwrap();
        assert_eq!(t.mnemonic(), Some(*m));
        assert_eq!(t.to_string(), *m);
        assert_eq!(AsciiType::from_mnemonic(&m.to_uppercase()), Some(t));
    }
    assert_eq!(AsciiType::from_mnemonic("str"), None);
}

#[test]
fn formats_of_each_kind() {
    let t = |m| AsciiType::from_mnemonic(m).unwrap();
    assert_eq!(t("u16").format(&[0x34, 0x12]).unwrap(), "4660");
    assert_eq!(t("x16").format(&[0x34, 0x12]).unwrap(), "0x1234");
    assert_eq!(t("x32").format(&[1, 0, 0, 0]).unwrap(), "0x00000001");
    assert_eq!(t("i8").format(&[0xFF]).unwrap(), "-1");
    assert_eq!(t("b").format(&[1]).unwrap(), "1");
    assert_eq!(t("r32").format(&1.5f32.to_le_bytes()).unwrap(), "1.5");
    assert_eq!(t("vs").format(b"say \"hi\"").unwrap(), "\"say \"\"hi\"\"\"");
    assert_eq!(t("d").format(&[0, 1, 2, 0xFF]).unwrap(), "AAEC/w==");
    assert_eq!(t("hex").format(&[0, 1, 0xAB]).unwrap(), "00 01 AB");
    assert!(t("u16").format(&[1]).is_err(), "length checked");
    assert_eq!(t("x8").parse("0xA5").unwrap(), [0xA5]);
    assert_eq!(t("u8").parse("165").unwrap(), [0xA5]);
}

fn scalar() -> impl Strategy<Value = (&'static str, usize)> {
    prop::sample::select(vec![
        ("u8", 1usize),
        ("u16", 2),
        ("u32", 4),
        ("u64", 8),
        ("i8", 1),
        ("i16", 2),
        ("i32", 4),
        ("i64", 8),
        ("x8", 1),
        ("x16", 2),
        ("x32", 4),
        ("x64", 8),
        ("os", 0),
        ("d", 0),
        ("hex", 0),
    ])
}

proptest! {
    /// What a node holds, printed and typed back, is the same bytes.
    #[test]
    fn format_then_parse_is_identity((m, size) in scalar(), bytes in prop::collection::vec(any::<u8>(), 0..64)) {
        let t = AsciiType::from_mnemonic(m).unwrap();
        let bytes = if size == 0 { bytes } else { let mut b = bytes; b.resize(size, 0x5A); b };
        let text = t.format(&bytes).unwrap();
        prop_assert_eq!(t.parse(&text).unwrap(), bytes);
    }

    #[test]
    fn visible_strings_survive_quoting(s in "[ -~]{0,40}") {
        let t = AsciiType::from_mnemonic("vs").unwrap();
        let text = t.format(s.as_bytes()).unwrap();
        prop_assert_eq!(t.parse(&text).unwrap(), s.as_bytes());
        // And as a whole command line, comment characters included.
        let line = format!("[1] 5 w 0x2000 0 vs {text}");
        let mut session = Session::new(1, Duration::from_millis(500), "");
        match session.handle(&line) {
            Step::Run(Job { action: Action::Write { data, .. }, .. }) => prop_assert_eq!(data, s.as_bytes()),
            other => prop_assert!(false, "{:?}", other),
        }
    }

    /// No line makes the parser panic, and every reply is one CR LF terminated line.
    #[test]
    fn any_line_is_answered(line in "\\PC{0,80}") {
        let mut s = session();
        if let Step::Reply(r) = s.handle(&line) {
            let text = r.to_string();
            prop_assert!(text.ends_with("\r\n"));
        }
    }
}
