//! `canlift ascii` (CiA 309-3) against the simulator, a python-canopen LocalNode and
//! unconfigured canlift nodes on one hub, driven by a client written from the command syntax's
//! documentation (tests/interop/ascii_client.py), and by raw TCP clients for the edge cases.

use std::process::Stdio;
use std::time::Duration;

use canbus::Bus;
use canopen::node::{LocalNode, NodeConfig};
use canopen::od::ObjectDictionary;
use serde_json::Value;
use testkit::{interop_script, python};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tokio::process::{Child, Command};

use crate::common;
use common::{canlift, python_node};

/// The two unconfigured nodes' LSS addresses.
const VENDOR: u32 = 0x41A;
const UNCONFIGURED: [u32; 2] = [0x777, 0x778];

/// `canlift ascii` on an ephemeral port; its address from the banner.
async fn gateway(bus: &str) -> (Child, String) {
    let mut child = canlift()
        .args(["ascii", "--bus", bus, "--listen", "127.0.0.1:0"])
        .args([
            "--max-line",
            "4096",
            "--max-clients",
            "4",
            "--lss-timeout-ms",
            "1000",
        ])
        .spawn()
        .expect("canlift runs");
    let mut lines = BufReader::new(child.stderr.take().expect("stderr")).lines();
    let banner = tokio::time::timeout(Duration::from_secs(20), async {
        loop {
            let line = lines.next_line().await.expect("stderr").expect("banner");
            if line.contains("CiA 309-3 gateway on ") {
                return line;
            }
        }
    })
    .await
    .expect("the banner");
    // Its log goes on to the test's output (and the pipe stays open).
    tokio::spawn(async move {
        while let Ok(Some(line)) = lines.next_line().await {
            eprintln!("canlift ascii: {line}");
        }
    });
    let addr = banner
        .split("gateway on ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next())
        .expect("an address")
        .to_owned();
    (child, addr)
}

/// Run `commands` through the documented client; its parsed replies.
async fn session(python: &std::path::Path, addr: &str, commands: &[&str]) -> Vec<Value> {
    let (host, port) = addr.rsplit_once(':').expect("host:port");
    let mut client = Command::new(python)
        .arg(interop_script("ascii_client.py"))
        .args([host, port])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .kill_on_drop(true)
        .spawn()
        .expect("python runs");
    let mut stdin = client.stdin.take().expect("stdin");
    let script = commands.join("\n") + "\n";
    stdin.write_all(script.as_bytes()).await.expect("commands");
    drop(stdin);
    let out = tokio::time::timeout(Duration::from_secs(120), client.wait_with_output())
        .await
        .expect("the client ends")
        .expect("its output");
    assert!(out.status.success(), "ascii_client.py failed");
    let replies: Vec<Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON"))
        .collect();
    assert_eq!(replies.len(), commands.len(), "{replies:?}");
    replies
}

fn value(reply: &Value) -> &str {
    assert_eq!(reply["kind"], "value", "{reply}");
    reply["value"].as_str().unwrap_or_default()
}

fn ok(reply: &Value) {
    assert_eq!(reply["kind"], "ok", "{reply}");
}

fn error(reply: &Value) -> Value {
    assert_eq!(reply["kind"], "error", "{reply}");
    reply["code"].clone()
}

/// Read 1018h sub 4 of `node` until it answers (a node that just took its ID boots first).
async fn serial_of(python: &std::path::Path, addr: &str, node: u8) -> String {
    let command = format!("{node} r 0x1018 4 x32");
    for _ in 0..20 {
        let r = session(python, addr, &[&command]).await;
        if r[0]["kind"] == "value" {
            return value(&r[0]).to_owned();
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    panic!("node {node} never answered");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_ascii_gateway_speaks_cia_309_3() {
    let Some(python) = python() else { return };
    let hub = testkit::hub().await;
    let bus = testkit::hub_url(&hub, "can0");
    let _sim = testkit::lift::simulator(&bus).await;
    let mut node5 = python_node(&python, &hub, "local_node.py", 5).await.0;
    let dir = testkit::scratch();
    let unconfigured: Vec<LocalNode> = {
        let mut nodes = Vec::new();
        for serial in UNCONFIGURED {
            let config = NodeConfig {
                identity: [VENDOR, 0x1000, 1, serial],
                storage: Some(dir.path().join(format!("node-{serial:x}.params"))),
                ..NodeConfig::new(canopen::lss::UNCONFIGURED)
            };
            let bus = Bus::open(&bus).await.expect("the hub");
            nodes.push(LocalNode::start(bus, ObjectDictionary::new(), config));
        }
        nodes
    };
    // Node 9: a canlift node with a DOMAIN, for block transfers (python-canopen's LocalNode
    // has none).
    let node9 = LocalNode::start(
        Bus::open(&bus).await.expect("the hub"),
        testkit::sample::dictionary(),
        NodeConfig::new(9),
    );
    let (mut child, addr) = gateway(&bus).await;

    // SDO in every type form, against python-canopen (node 5) and the simulator (1 and 12).
    let blob: Vec<u8> = (0..3000u32).map(|i| (i * 7) as u8).collect();
    let blob64 = {
        use base64::Engine as _;
        base64::engine::general_purpose::STANDARD.encode(&blob)
    };
    let write_blob = format!("9 w 0x{:04X} 0 d {blob64}", testkit::sample::BLOB);
    let read_blob = format!("9 r 0x{:04X} 0 d", testkit::sample::BLOB);
    let r = session(
        &python,
        &addr,
        &[
            "5 r 0x1008 0 vs",
            "5 w 0x2001 0 u32 0x1234",
            "5 r 0x2001 0 u32",
            "5 read 0x2001 0 x32",
            "5 r 0x2001 0",
            "5 w 0x2002 0 i16 -5",
            "5 r 0x2002 0 i16",
            "5 w 0x2002 0 i16 40000",
            "5 r 0x4000 0 u8",
            "1 r 0x1008 0 vs",
            "12 r 0x1008 0 vs",
            "1 r 0x1018 1 x32",
            "set sdo_block 1",
            &write_blob,
            &read_blob,
            "set sdo_block 0",
            &read_blob,
            "set node 5",
            "r 0x2001 0 u32",
            "set sdo_timeout 200",
            "77 r 0x1000 0",
            "info",
            "help",
        ],
    )
    .await;
    assert_eq!(value(&r[0]), "\"python-canopen\"");
    ok(&r[1]);
    assert_eq!(value(&r[2]), "4660");
    assert_eq!(value(&r[3]), "0x00001234");
    assert_eq!(value(&r[4]), "34 12 00 00", "hex bytes without a type");
    ok(&r[5]);
    assert_eq!(value(&r[6]), "-5");
    assert_eq!(error(&r[7]), "0x06090031", "40000 does not fit i16");
    assert_eq!(error(&r[8]), "0x06020000");
    assert_eq!(
        r[8]["comment"],
        "Object does not exist in the object dictionary."
    );
    assert_eq!(value(&r[9]), "\"canlift simulated lift controller\"");
    assert_eq!(value(&r[10]), "\"canlift simulated I/O node\"");
    assert!(value(&r[11]).starts_with("0x"), "{}", r[11]);
    ok(&r[12]);
    ok(&r[13]);
    assert_eq!(value(&r[14]), blob64, "block upload");
    ok(&r[15]);
    assert_eq!(value(&r[16]), blob64, "segmented upload");
    ok(&r[17]);
    assert_eq!(value(&r[18]), "4660", "the default node");
    ok(&r[19]);
    assert_eq!(error(&r[20]), "0x05040000", "no node 77: SDO timeout");
    assert!(r[21]["lines"][0]
        .as_str()
        .unwrap_or_default()
        .contains("sdo_timeout 200 ms"));
    ok(&r[21]);
    assert!(r[22]["lines"].as_array().map_or(0, Vec::len) > 10, "help");

    // Malformed input answers an error and the session goes on.
    let r = session(
        &python,
        &addr,
        &[
            "5 r",
            "5 frobnicate",
            "5 r 0x1000 0 q9",
            "r 0x1000 0",
            "2 5 r 0x1000 0",
            "lss_set_node 200",
            "5 r 0x2001 0 u32",
        ],
    )
    .await;
    assert_eq!(error(&r[0]), 101);
    assert_eq!(error(&r[1]), 100);
    assert_eq!(error(&r[2]), 101);
    assert_eq!(error(&r[3]), 105, "a new session has no default node");
    assert_eq!(error(&r[4]), 106);
    assert_eq!(error(&r[5]), 502);
    assert_eq!(value(&r[6]), "4660");

    // NMT, to one node and to all.
    let r = session(
        &python,
        &addr,
        &["5 stop", "5 preop", "5 start", "0 preop", "5 reset comm"],
    )
    .await;
    r.iter().for_each(ok);

    // LSS: Fastscan finds the lowest unconfigured address, which then gets node-ID 42. Each
    // step waits its timeout for the nodes (another process, through the hub): 60 ms was
    // missed on a loaded two-core machine running the suite, and a step answered late reads
    // as a bit of 1 — the scan then finds nobody. 250 ms costs only the steps nobody answers.
    let r = session(
        &python,
        &addr,
        &[
            "_lss_fastscan 250",
            "lss_get_node",
            "lss_inquire_addr",
            "lss_inquire_addr 3",
            "lss_set_node 42",
            "lss_store",
            "lss_switch_glob 0",
            "lss_get_node",
        ],
    )
    .await;
    let first = format!(
        "0x{VENDOR:08X} 0x00001000 0x00000001 0x{:08X}",
        UNCONFIGURED[0]
    );
    assert_eq!(value(&r[0]), first);
    assert_eq!(value(&r[1]), "255");
    assert_eq!(value(&r[2]), first);
    assert_eq!(value(&r[3]), format!("0x{:08X}", UNCONFIGURED[0]));
    ok(&r[4]);
    ok(&r[5]);
    ok(&r[6]);
    assert_eq!(error(&r[7]), 103, "nobody in configuration any more");
    assert_eq!(
        serial_of(&python, &addr, 42).await,
        format!("0x{:08X}", UNCONFIGURED[0])
    );
    // lss_allnodes gives the rest IDs from 50: vendor, product and revision matched, the
    // serial scanned (37 steps of 250 ms instead of the whole scan's 133, which the Fastscan
    // above went through).
    let allnodes = format!("lss_allnodes 250 50 0 2 0x{VENDOR:X} 2 0x1000 2 1 0 0");
    let r = session(&python, &addr, &[&allnodes, "_lss_fastscan 250"]).await;
    ok(&r[0]);
    let lines: Vec<&str> = r[0]["lines"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    assert_eq!(
        lines,
        [
            format!(
                "# node 50: 0x{VENDOR:08X} 0x00001000 0x00000001 0x{:08X}",
                UNCONFIGURED[1]
            )
            .as_str(),
            "# 1 node(s) configured"
        ]
    );
    assert_eq!(error(&r[1]), 103, "no unconfigured node left");
    assert_eq!(
        serial_of(&python, &addr, 50).await,
        format!("0x{:08X}", UNCONFIGURED[1])
    );

    // Several clients at once, each with its own sequence numbers and defaults.
    let mut clients = Vec::new();
    for i in 0..3u32 {
        let addr = addr.clone();
        clients.push(tokio::spawn(async move {
            let mut socket = TcpStream::connect(&addr).await.expect("connect");
            let mut replies = String::new();
            for n in 0..20u32 {
                let seq = i * 100 + n;
                socket
                    .write_all(format!("[{seq}] 5 r 0x2001 0 u32\r\n").as_bytes())
                    .await
                    .expect("send");
                let mut line = Vec::new();
                loop {
                    let b = socket.read_u8().await.expect("a reply");
                    line.push(b);
                    if line.ends_with(b"\r\n") {
                        break;
                    }
                }
                replies.push_str(&String::from_utf8_lossy(&line));
                assert_eq!(String::from_utf8_lossy(&line), format!("[{seq}] 4660\r\n"));
            }
            replies.len()
        }));
    }
    // A line over the bound closes only its own client.
    let mut long = TcpStream::connect(&addr).await.expect("connect");
    long.write_all(&vec![b'x'; 5000]).await.expect("send");
    let mut answer = String::new();
    let _ = tokio::time::timeout(Duration::from_secs(10), long.read_to_string(&mut answer)).await;
    assert!(answer.starts_with("ERROR: 101"), "{answer}");
    for client in clients {
        assert!(client.await.expect("client task") > 0);
    }
    let r = session(&python, &addr, &["5 r 0x2001 0 u32"]).await;
    assert_eq!(value(&r[0]), "4660", "still serving");

    common::interrupt(&mut child, Duration::from_secs(10)).await;
    drop(node5.stdin.take());
    let _ = tokio::time::timeout(Duration::from_secs(10), node5.wait()).await;
    drop(unconfigured);
    drop(node9);
    hub.shutdown().await;
}

/// A line limit below what a command without data needs is refused at start (exit 2, naming
/// the range), not raised behind the user's back.
#[tokio::test]
async fn a_line_limit_too_short_for_a_command_is_refused() {
    let out = crate::common::run(&["ascii", "--stdio", "--max-line", "10"]).await;
    assert_eq!(out.status.code(), Some(2));
    let text = crate::common::stderr(&out);
    assert!(
        text.contains("--max-line") && text.contains("64.."),
        "{text}"
    );
}
