//! The gateway in the field (docs/GATEWAY.md §Metadata, §Write policy, §Elevation): `canlift
//! gateway` in front of another vendor's controller — python-canopen LocalNodes serving
//! tests/fixtures/controller.eds, an independent CANopen implementation — through `canlift hub`,
//! queried by a scripted portal that checks each answer's exact error code.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use gateway::config::{Config, NodeSection};
use serde_json::{json, Value};
use testkit::constants::{SERNUM, SERVICE_SHA1, SETUP_SHA1, WAIT};
use testkit::pki::{pki, TestPki};
use testkit::scripted::{ask, connack, Portal, Ws};
use tokio::io::{AsyncBufReadExt, AsyncRead, BufReader};
use tokio::process::{Child, Command};

/// The lift controller of the other vendor.
const CONTROLLER: u8 = 1;
/// Another node with the same EDS and no vendor metadata.
const OTHER: u8 = 5;
/// A node-ID nothing describes and nothing answers at.
const UNKNOWN: u8 = 7;

const NO_OBJECT: u32 = 0x0602_0000;
const READ_ONLY: u32 = 0x0601_0002;
const PRIVILEGE: u32 = 0x0800_0021;
const WRONG_HASH: u32 = 0x0800_0020;
const LOCKED: u32 = 0x0800_0022;
const TOO_HIGH: u32 = 0x0609_0031;

fn fixture(name: &str) -> PathBuf {
    testkit::workspace().join("tests/fixtures").join(name)
}

/// The lines a child writes, collected as they come.
#[derive(Clone, Default)]
struct Lines(Arc<Mutex<Vec<String>>>);

impl Lines {
    fn follow(reader: impl AsyncRead + Unpin + Send + 'static) -> Lines {
        let lines = Lines::default();
        let sink = lines.0.clone();
        tokio::spawn(async move {
            let mut reader = BufReader::new(reader).lines();
            while let Ok(Some(line)) = reader.next_line().await {
                sink.lock().unwrap().push(line);
            }
        });
        lines
    }

    fn all(&self) -> Vec<String> {
        self.0.lock().unwrap().clone()
    }

    fn text(&self) -> String {
        self.all().join("\n")
    }

    /// The first line `wanted` accepts, waiting for it up to [`WAIT`].
    async fn wait_for(&self, wanted: impl Fn(&str) -> bool) -> String {
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            if let Some(line) = self.all().into_iter().find(|l| wanted(l)) {
                return line;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "not seen in time; so far:\n{}",
                self.text()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

/// A child process with its output lines.
struct Process {
    child: Child,
    stdout: Lines,
    stderr: Lines,
}

impl Process {
    fn spawn(mut command: Command) -> Process {
        let mut child = command
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .expect("starts");
        let stdout = Lines::follow(child.stdout.take().expect("piped"));
        let stderr = Lines::follow(child.stderr.take().expect("piped"));
        Process {
            child,
            stdout,
            stderr,
        }
    }

    /// Stop it as Ctrl-C would.
    async fn interrupt(&mut self) {
        let status = common::interrupt(&mut self.child, WAIT).await;
        assert!(status.success(), "{status}: {}", self.stderr.text());
    }
}

/// `canlift hub`, the python controller, the scripted portal: everything but the gateway.
struct Field {
    dir: tempfile::TempDir,
    pki: TestPki,
    portal: Portal,
    bus: String,
    controller: Process,
    _hub: Process,
}

impl Field {
    /// `None` (the test is skipped, said on stderr) without the interop Python.
    async fn start() -> Option<Field> {
        let python = testkit::python()?;
        let dir = testkit::scratch();
        let pki = pki(dir.path());
        let portal = Portal::start(&pki).await;
        let mut hub = common::canlift();
        hub.args(["hub", "--listen", "127.0.0.1:0"]);
        let hub = Process::spawn(hub);
        let line = hub.stdout.wait_for(|l| l.contains("listening on")).await;
        let addr: std::net::SocketAddr = line
            .split_whitespace()
            .nth(4)
            .and_then(|a| a.parse().ok())
            .unwrap_or_else(|| panic!("the hub's address in {line:?}"));
        let mut controller = Command::new(python);
        controller
            .arg(testkit::interop_script("controller.py"))
            .args([addr.ip().to_string(), addr.port().to_string()])
            .arg(fixture("controller.eds"))
            .args([CONTROLLER.to_string(), OTHER.to_string()]);
        let controller = Process::spawn(controller);
        controller.stdout.wait_for(|l| l == "READY").await;
        Some(Field {
            bus: format!("socketcand://{addr}/can0"),
            dir,
            pki,
            portal,
            controller,
            _hub: hub,
        })
    }

    /// gateway.toml: the controller with its EDS and the vendor's metadata, node 5 with the
    /// EDS alone, both passwords; then `edit`.
    fn config(&self, edit: impl FnOnce(&mut Config)) -> PathBuf {
        let state = self.dir.path().join("state");
        let mut c = Config::for_portal(
            testkit::lift::identity(),
            &self.portal.url(),
            &self.pki.ca,
            &self.bus,
            &state,
        );
        c.bus.sdo_timeout_ms = 500;
        c.privileges.service_sha1 = Some(SERVICE_SHA1.into());
        c.privileges.setup_sha1 = Some(SETUP_SHA1.into());
        c.bus.nodes = vec![
            NodeSection {
                metadata: Some(fixture("controller-nxg.toml")),
                ..NodeSection::with_eds(CONTROLLER, fixture("controller.eds"))
            },
            NodeSection::with_eds(OTHER, fixture("controller.eds")),
        ];
        edit(&mut c);
        let path = self.dir.path().join("gateway.toml");
        std::fs::write(&path, toml::to_string_pretty(&c).unwrap()).unwrap();
        path
    }

    /// `canlift gateway --config CONFIG` (with `env`), connected and answered.
    async fn gateway(&self, config: &Path, env: &[(&str, &str)]) -> (Process, Ws) {
        let mut command = common::canlift();
        command.arg("gateway").arg("--config").arg(config);
        command.envs(env.iter().copied());
        let gateway = Process::spawn(command);
        let ws = self.connected().await;
        (gateway, ws)
    }

    /// The gateway's next connection, answered with CONNACK.
    async fn connected(&self) -> Ws {
        let (mut ws, _, _) = self.portal.accept().await;
        connack(&mut ws).await;
        ws
    }

    /// The writes the controller accepted, as "NODE INDEX SUB HEX".
    fn writes(&self) -> Vec<String> {
        self.controller
            .stdout
            .all()
            .into_iter()
            .filter_map(|l| l.strip_prefix("WRITE ").map(str::to_owned))
            .collect()
    }
}

fn node(id: Option<u8>) -> Value {
    id.map_or(Value::Null, |id| json!({"id": id, "net": 1}))
}

fn request(method: &str, mut params: Value) -> String {
    if let Some(map) = params.as_object_mut() {
        map.retain(|_, v| !v.is_null());
    }
    json!({"jsonrpc": "2.0", "id": "1", "method": method, "params": params}).to_string()
}

async fn call(ws: &mut Ws, text: String) -> Value {
    ask(ws, &text, &mut Vec::new()).await
}

async fn get(ws: &mut Ws, on: Option<u8>, mplex: &str, lang: &str) -> Value {
    let params = json!({
        "lang": {"preferred_language": lang, "alternate_language": "en"},
        "node": node(on),
        "object": {"mplex": mplex},
    });
    call(ws, request("get_canopen_object", params)).await
}

/// The object of a successful get.
async fn object(ws: &mut Ws, on: Option<u8>, mplex: &str, lang: &str) -> Value {
    let answer = get(ws, on, mplex, lang).await;
    assert!(answer.get("error").is_none(), "{mplex}: {answer}");
    answer["result"]["object"].clone()
}

struct Put<'a> {
    on: Option<u8>,
    mplex: &'a str,
    datatype: u16,
    physunit: u8,
    value: &'a str,
}

async fn put(ws: &mut Ws, p: Put<'_>) -> Value {
    let params = json!({
        "sernum": SERNUM,
        "node": node(p.on),
        "object": {"mplex": p.mplex, "datatype": p.datatype, "physunit": p.physunit, "value": p.value},
    });
    call(ws, request("put_canopen_object", params)).await
}

/// Door hold time, 2000h: u16, seconds (unit 3 from the vendor file), 0…600 in the EDS.
fn door_hold(value: &str) -> Put<'_> {
    Put {
        on: None,
        mplex: "0x200000",
        datatype: 6,
        physunit: 3,
        value,
    }
}

/// Site name, 2002h: a string anyone may write (privilege 0 in the vendor file).
fn site_name(value: &str) -> Put<'_> {
    Put {
        on: None,
        mplex: "0x200200",
        datatype: 9,
        physunit: 0,
        value,
    }
}

async fn elevate(ws: &mut Ws, privilege: u8, passhash: &str) -> Value {
    let params = json!({"sernum": SERNUM, "privilege": privilege, "passhash": passhash});
    call(ws, request("elevate_privilege", params)).await
}

fn code(answer: &Value) -> Option<u64> {
    answer["error"]["code"].as_u64()
}

/// A put's answer: the object written (NXg §6.6.1).
#[track_caller]
fn assert_done(answer: &Value) {
    assert!(answer["result"]["object"]["mplex"].is_string(), "{answer}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_vendors_controller_is_described_truthfully_and_written_within_its_limits() {
    let Some(field) = Field::start().await else {
        return;
    };
    let config = field.config(|_| {});
    let (mut gateway, mut ws) = field.gateway(&config, &[]).await;

    // A vendor object: existence, type, access and limits from the EDS, texts from the vendor
    // file (German), the English name from the EDS where the vendor file has none.
    let door = object(&mut ws, None, "0x200000", "de").await;
    assert_eq!(door["name"], "Türoffenhaltezeit");
    assert_eq!(
        door["hint"],
        "Wie lange die Türen an einer Etage offen bleiben."
    );
    assert_eq!(
        (&door["datatype"], &door["access"], &door["privilege"]),
        (&json!(6), &json!("rw"), &json!(1))
    );
    assert_eq!(
        (&door["formtype"], &door["physunit"]),
        (&json!(12), &json!(3))
    );
    assert_eq!((&door["min"], &door["max"]), (&json!(0), &json!(600)));
    assert_eq!(door["value"], json!(["30"]));
    let door = object(&mut ws, None, "0x200000", "en").await;
    assert_eq!(door["name"], "Door hold time");
    // An object only the EDS describes: its name, and writing needs setup rights.
    let trips = object(&mut ws, None, "0x200100", "en").await;
    assert_eq!(trips["name"], "Total trips");
    assert_eq!(
        (&trips["access"], &trips["privilege"]),
        (&json!("ro"), &json!(2))
    );
    assert_eq!(trips["value"], json!(["1234"]));
    // A CiA 417 object the EDS has: the catalog's names.
    let counter = object(&mut ws, None, "0x652001", "de").await;
    assert_eq!(counter["name"], "Fahrtenzähler [Fahrten]");
    assert_eq!(counter["value"], json!(["2510"]));
    // A catalog object the controller does not have.
    assert_eq!(
        code(&get(&mut ws, None, "0x411200", "en").await),
        Some(NO_OBJECT.into())
    );
    // Identity, versions and error history, with the communication profile's names.
    let serial = object(&mut ws, None, "0x101804", "en").await;
    assert_eq!(serial["name"], "Serial number");
    assert_eq!(serial["value"], json!(["305419896"]));
    let name = object(&mut ws, None, "0x100800", "de").await;
    assert_eq!(name["value"], json!(["Thor lift controller"]));
    assert_eq!(
        object(&mut ws, None, "0x100900", "en").await["value"],
        json!(["NX-T2 rev B"])
    );
    assert_eq!(
        object(&mut ws, None, "0x100A00", "en").await["value"],
        json!(["01.23.10"])
    );
    assert_eq!(
        object(&mut ws, None, "0x100300", "en").await["value"],
        json!(["0"])
    );

    // Writing: the vendor file's privilege, then the EDS's limits, before any SDO.
    assert_eq!(
        code(&put(&mut ws, door_hold("150")).await),
        Some(PRIVILEGE.into())
    );
    assert!(field.writes().is_empty(), "{:?}", field.writes());
    assert_eq!(
        elevate(&mut ws, 1, SERVICE_SHA1).await["result"]["duration"],
        300
    );
    assert_done(&put(&mut ws, door_hold("150")).await);
    field
        .controller
        .stdout
        .wait_for(|l| l == "WRITE 1 2000 00 9600")
        .await;
    assert_eq!(
        code(&put(&mut ws, door_hold("700")).await),
        Some(TOO_HIGH.into()),
        "the EDS's HighLimit"
    );
    let trips = Put {
        mplex: "0x200100",
        datatype: 7,
        ..door_hold("1")
    };
    let trips = Put {
        physunit: 0,
        ..trips
    };
    assert_eq!(code(&put(&mut ws, trips).await), Some(READ_ONLY.into()));
    assert_eq!(
        object(&mut ws, None, "0x200000", "en").await["value"],
        json!(["150"])
    );
    assert_eq!(field.writes(), ["1 2000 00 9600"], "only the valid write");

    gateway.interrupt().await;
    let log = gateway.stderr.text();
    assert!(
        log.lines().any(|l| l.contains("connection{n=1}")
            && l.contains("put refused")
            && l.contains("0x200000")),
        "refused puts are logged with their connection and object:\n{log}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_owners_policy_decides_what_the_cloud_may_write_and_see() {
    let Some(field) = Field::start().await else {
        return;
    };
    let config = field.config(|c| {
        c.policy = toml::from_str("deny = [\"0x2000\"]\nhide = [\"0x2003\"]\n").unwrap();
    });
    let (mut gateway, mut ws) = field.gateway(&config, &[]).await;
    assert_eq!(
        elevate(&mut ws, 2, SETUP_SHA1).await["result"]["duration"],
        300
    );
    // Denied: refused however high the rights, still readable.
    assert_eq!(
        code(&put(&mut ws, door_hold("45")).await),
        Some(READ_ONLY.into())
    );
    assert_eq!(
        object(&mut ws, None, "0x200000", "en").await["value"],
        json!(["30"])
    );
    assert_done(&put(&mut ws, site_name("Hall B")).await);
    field
        .controller
        .stdout
        .wait_for(|l| l.starts_with("WRITE 1 2002 00"))
        .await;
    // Hidden: not there for get, put or reg.
    assert_eq!(
        code(&get(&mut ws, None, "0x200300", "en").await),
        Some(NO_OBJECT.into())
    );
    let mode = Put {
        mplex: "0x200300",
        datatype: 5,
        physunit: 0,
        ..door_hold("1")
    };
    assert_eq!(code(&put(&mut ws, mode).await), Some(NO_OBJECT.into()));
    let reg = request("reg_canopen_object", json!({"mplex": ["0x200300"]}));
    assert_eq!(code(&call(&mut ws, reg).await), Some(NO_OBJECT.into()));
    // Another node: its communication objects are protected, its own objects are not.
    assert_eq!(
        code(&heartbeat_of_other(&mut ws).await),
        Some(READ_ONLY.into())
    );
    assert_eq!(
        object(&mut ws, Some(OTHER), "0x101700", "en").await["name"],
        "Producer heartbeat time"
    );
    let other_site = Put {
        on: Some(OTHER),
        ..site_name("Hall C")
    };
    assert_done(&put(&mut ws, other_site).await);
    field
        .controller
        .stdout
        .wait_for(|l| l.starts_with("WRITE 5 2002 00"))
        .await;
    // A node nothing describes: no remote writes (and no SDO to find that out).
    let unknown = Put {
        on: Some(UNKNOWN),
        ..site_name("x")
    };
    assert_eq!(code(&put(&mut ws, unknown).await), Some(READ_ONLY.into()));
    gateway.interrupt().await;

    // Read-only (here from the environment): every put refused, reads as before.
    let config = field.config(|c| {
        c.policy = toml::from_str("allow = [{ index = \"0x1017\", node = 5 }]\n").unwrap();
    });
    let env = [("CANLIFT_POLICY_REMOTE_WRITES", "read-only")];
    let (mut gateway, mut ws) = field.gateway(&config, &env).await;
    elevate(&mut ws, 2, SETUP_SHA1).await;
    assert_eq!(
        code(&put(&mut ws, site_name("Hall D")).await),
        Some(READ_ONLY.into())
    );
    assert_eq!(
        code(&heartbeat_of_other(&mut ws).await),
        Some(READ_ONLY.into())
    );
    assert_eq!(
        object(&mut ws, None, "0x200200", "en").await["value"],
        json!(["Hall B"])
    );
    gateway.interrupt().await;

    // Allowed explicitly: the other node's heartbeat time may be written.
    let (mut gateway, mut ws) = field.gateway(&config, &[]).await;
    elevate(&mut ws, 2, SETUP_SHA1).await;
    assert_done(&heartbeat_of_other(&mut ws).await);
    field
        .controller
        .stdout
        .wait_for(|l| l == "WRITE 5 1017 00 6400")
        .await;
    gateway.interrupt().await;
    let writes = field.writes();
    assert_eq!(writes.len(), 3, "{writes:?}");
    assert!(!writes
        .iter()
        .any(|w| w.contains(" 2000 ") || w.contains("Hall D")));
}

/// 100 ms into 1017h of node 5 (a communication object of another node; the unit as the
/// gateway describes it).
async fn heartbeat_of_other(ws: &mut Ws) -> Value {
    let described = object(ws, Some(OTHER), "0x101700", "en").await;
    let physunit = described["physunit"]
        .as_u64()
        .and_then(|u| u8::try_from(u).ok());
    let heartbeat = Put {
        on: Some(OTHER),
        mplex: "0x101700",
        datatype: 6,
        physunit: physunit.expect("a unit"),
        value: "100",
    };
    put(ws, heartbeat).await
}

/// The seconds a lock-out message names.
fn locked_seconds(answer: &Value) -> u64 {
    assert_eq!(code(answer), Some(LOCKED.into()), "{answer}");
    let message = answer["error"]["message"].as_str().unwrap_or_default();
    message
        .split_whitespace()
        .find_map(|w| w.parse().ok())
        .unwrap_or_else(|| panic!("no seconds in {message:?}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn elevation_cannot_be_gamed_across_reconnects_and_restarts() {
    let Some(field) = Field::start().await else {
        return;
    };
    const WRONG: &str = "0000000000000000000000000000000000000000";
    let wrong_three_times = |ws| async move {
        let mut ws = ws;
        for _ in 0..3 {
            assert_eq!(
                code(&elevate(&mut ws, 1, WRONG).await),
                Some(WRONG_HASH.into())
            );
        }
        ws
    };
    // A short lock runs out, and then the right hash works. Nothing else happens meanwhile, so
    // the check right after locking has all of its 5 s even on a loaded machine.
    let short = field.config(|c| c.privileges.lockout_s = 5);
    let (mut gateway, ws) = field.gateway(&short, &[]).await;
    let mut ws = wrong_three_times(ws).await;
    let left = locked_seconds(&elevate(&mut ws, 1, SERVICE_SHA1).await);
    assert!((1..=5).contains(&left), "{left}");
    tokio::time::sleep(Duration::from_secs(left + 1)).await;
    assert_eq!(
        elevate(&mut ws, 1, SERVICE_SHA1).await["result"]["duration"],
        300
    );
    gateway.interrupt().await;

    // A long lock (it cannot run out while reconnects and restarts take their time): the right
    // hash is refused, going back to user rights changes nothing.
    let long = field.config(|c| c.privileges.lockout_s = 600);
    let (mut gateway, ws) = field.gateway(&long, &[]).await;
    let mut ws = wrong_three_times(ws).await;
    locked_seconds(&elevate(&mut ws, 1, SERVICE_SHA1).await);
    assert_eq!(elevate(&mut ws, 0, "").await["result"]["duration"], 300);
    locked_seconds(&elevate(&mut ws, 1, SERVICE_SHA1).await);
    // Per level: setup is not locked.
    assert_eq!(
        elevate(&mut ws, 2, SETUP_SHA1).await["result"]["duration"],
        300
    );
    // A new connection finds the lock.
    drop(ws);
    let mut ws = field.connected().await;
    locked_seconds(&elevate(&mut ws, 1, SERVICE_SHA1).await);
    // So does a restarted gateway.
    gateway.interrupt().await;
    let (mut gateway, mut ws) = field.gateway(&long, &[]).await;
    locked_seconds(&elevate(&mut ws, 1, SERVICE_SHA1).await);
    // The count survives a restart (setup level): two wrong, restart, a third locks.
    for _ in 0..2 {
        assert_eq!(
            code(&elevate(&mut ws, 2, WRONG).await),
            Some(WRONG_HASH.into())
        );
    }
    gateway.interrupt().await;
    let (mut gateway, mut ws) = field.gateway(&long, &[]).await;
    assert_eq!(
        code(&elevate(&mut ws, 2, WRONG).await),
        Some(WRONG_HASH.into())
    );
    locked_seconds(&elevate(&mut ws, 2, SETUP_SHA1).await);
    gateway.interrupt().await;
    // Logged: grants, refusals, locks; never a hash.
    let log = gateway.stderr.text();
    assert!(log.contains("locked out"), "{log}");
    assert!(!log.contains(SERVICE_SHA1) && !log.contains(WRONG), "{log}");
}

/// `canlift gateway` with one bad file: it stops at once, naming the file, the line and why.
async fn refused(config: &Path) -> String {
    let out = common::canlift()
        .arg("gateway")
        .arg("--config")
        .arg(config)
        .output()
        .await
        .unwrap();
    assert!(!out.status.success(), "started with {}", config.display());
    common::stderr(&out)
}

fn line_of(text: &str, wanted: &str) -> usize {
    text.lines()
        .position(|l| l.contains(wanted))
        .unwrap_or_else(|| panic!("{wanted:?} not in the file"))
        + 1
}

#[tokio::test]
async fn malformed_files_stop_the_gateway_with_file_line_and_reason() {
    let dir = testkit::scratch();
    let pki = pki(dir.path());
    let write = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let gateway_toml = |nodes: Vec<NodeSection>| {
        let mut c = Config::for_portal(
            testkit::lift::identity(),
            "wss://127.0.0.1:1/ws",
            &pki.ca,
            "socketcand://127.0.0.1:1/can0",
            &dir.path().join("state"),
        );
        c.bus.nodes = nodes;
        write("gateway.toml", &toml::to_string_pretty(&c).unwrap())
    };
    // An EDS without any usable object stops it; a defect of one object does not (below).
    let empty = "[FileInfo]\nFileName=empty.eds\n\n[1000]\nParameterName=x\nDataType=0x0040\n";
    let empty_eds = write("empty.eds", empty);
    let config = gateway_toml(vec![NodeSection::with_eds(1, empty_eds.clone())]);
    let err = refused(&config).await;
    let at = format!("{}:0: no usable object", empty_eds.display());
    assert!(err.contains(&at), "{at} in {err}");

    // A limit that is no number: the gateway starts, says where, and keeps the object read-only.
    let eds = std::fs::read_to_string(fixture("controller.eds")).unwrap();
    let broken = eds.replacen("HighLimit=600", "HighLimit=six hundred", 1);
    let broken_eds = write("broken.eds", &broken);
    let config = gateway_toml(vec![NodeSection::with_eds(1, broken_eds.clone())]);
    let mut gateway = common::canlift()
        .arg("gateway")
        .arg("--config")
        .arg(&config)
        .spawn()
        .unwrap();
    let stderr = gateway.stderr.take().expect("piped");
    let at = format!(
        "{}:{}: error: HighLimit \"six hundred\"",
        broken_eds.display(),
        line_of(&broken, "six hundred")
    );
    let mut lines = tokio::io::AsyncBufReadExt::lines(tokio::io::BufReader::new(stderr));
    let warned = tokio::time::timeout(std::time::Duration::from_secs(10), async {
        while let Ok(Some(line)) = lines.next_line().await {
            if line.contains(&at) && line.contains("read-only here") {
                return true;
            }
        }
        false
    })
    .await;
    assert_eq!(warned, Ok(true), "{at} not logged");
    assert!(gateway.try_wait().unwrap().is_none(), "the gateway runs");
    gateway.kill().await.unwrap();

    let vendor = std::fs::read_to_string(fixture("controller-nxg.toml")).unwrap();
    let typo = vendor.replacen("form = 15", "from = 15", 1);
    let typo_toml = write("typo.toml", &typo);
    let config = gateway_toml(vec![NodeSection {
        metadata: Some(typo_toml.clone()),
        ..NodeSection::with_eds(1, fixture("controller.eds"))
    }]);
    let err = refused(&config).await;
    let at = format!("{}:{}:", typo_toml.display(), line_of(&typo, "from = 15"));
    assert!(
        err.contains(&at) && err.contains("unknown field `from`"),
        "{at} in {err}"
    );

    let text = "[identity]\nsernum = \"1\"\n\n[cloud]\nurl = \"wss://127.0.0.1:1/ws\"\n\n\
                [policy]\nremote_writes = \"allowed\"\ndeny = [\"0x5022\", \"0x1FFF-0x1000\"]\n";
    let config = write("gateway.toml", text);
    let err = refused(&config).await;
    let at = format!("{}:{}:", config.display(), line_of(text, "0x1FFF-0x1000"));
    assert!(err.contains(&at) && err.contains("above"), "{at} in {err}");
}
