//! The CiA 309-3 ASCII mapping, sans-IO: the command language of CANopen gateways that
//! integrators type (`[1] 4 read 0x1017 0 u16`) or script over TCP. This module parses one
//! command line against a session's defaults into a [`Job`], and formats the [`Reply`]; a
//! driver (`canlift ascii`) executes the job on the bus.
//!
//! Grammar (CiA 309-3 §5, as CANopenNode's gateway documents it): an optional `[<sequence>]`,
//! then `[[<net>] <node>] r[ead] <index> <sub> [<type>]`, `w[rite] <index> <sub> <type>
//! <value>`, `start`, `stop`, `preop[erational]`, `reset node`, `reset comm[unication]`;
//! `[<net>] set network|node|sdo_timeout|sdo_block <value>`; the LSS commands; `help`, `info`.
//! `#` starts a comment outside a quoted string. Replies are `[<sequence>] OK`, `[<sequence>]
//! <value>` or `[<sequence>] ERROR: <code> #<text>` with an SDO abort code (`0x06020000`) or
//! one of the gateway's internal error codes ([`Internal`]).

use std::fmt;
use std::time::Duration;

use base64::Engine as _;

use crate::lss::{FastscanMaster, FastscanPart};
use crate::nmt::NmtCommand;
use crate::sdo::abort::AbortCode;
use crate::types::{self, DataType, TypeError, Value};

/// How a value is written in a command and printed in a reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form {
    /// The value's plain text: decimal integers, reals, `0`/`1`, times.
    Plain,
    /// An unsigned integer in hex with its width (`x8` … `x64`, `0x0000ABCD`).
    Hex,
    /// A visible string in double quotes, `""` for a quote inside (`vs`).
    Quoted,
    /// The bytes in base64, RFC 2045 alphabet, one line (`os`, `us`, `d`).
    Base64,
    /// The bytes in hex, space separated (`hex`, non-standard).
    HexBytes,
}

/// A data type as the ASCII mapping names it: the CANopen type and its text form.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AsciiType {
    /// The CANopen data type on the wire.
    pub data_type: DataType,
    /// Its text form.
    pub form: Form,
}

/// The CiA 309-3 mnemonics, with the non-standard `x…` and `hex` of CANopenNode.
const MNEMONICS: &[(&str, DataType, Form)] = &[
    ("b", DataType::Boolean, Form::Plain),
    ("i8", DataType::Integer8, Form::Plain),
    ("i16", DataType::Integer16, Form::Plain),
    ("i32", DataType::Integer32, Form::Plain),
    ("i64", DataType::Integer64, Form::Plain),
    ("u8", DataType::Unsigned8, Form::Plain),
    ("u16", DataType::Unsigned16, Form::Plain),
    ("u32", DataType::Unsigned32, Form::Plain),
    ("u64", DataType::Unsigned64, Form::Plain),
    ("x8", DataType::Unsigned8, Form::Hex),
    ("x16", DataType::Unsigned16, Form::Hex),
    ("x32", DataType::Unsigned32, Form::Hex),
    ("x64", DataType::Unsigned64, Form::Hex),
    ("r32", DataType::Real32, Form::Plain),
    ("r64", DataType::Real64, Form::Plain),
    ("t", DataType::TimeOfDay, Form::Plain),
    ("td", DataType::TimeDifference, Form::Plain),
    ("vs", DataType::VisibleString, Form::Quoted),
    ("os", DataType::OctetString, Form::Base64),
    ("us", DataType::UnicodeString, Form::Base64),
    ("d", DataType::Domain, Form::Base64),
    ("hex", DataType::Domain, Form::HexBytes),
];

impl AsciiType {
    /// The type a mnemonic names (`u16`, `vs`, `x32`, …), case-insensitive.
    pub fn from_mnemonic(name: &str) -> Option<Self> {
        MNEMONICS
            .iter()
            .find(|(m, ..)| m.eq_ignore_ascii_case(name))
            .map(|&(_, data_type, form)| AsciiType { data_type, form })
    }

    /// The mnemonic of this type, if it has one.
    pub fn mnemonic(self) -> Option<&'static str> {
        MNEMONICS
            .iter()
            .find(|&&(_, t, f)| t == self.data_type && f == self.form)
            .map(|(m, ..)| *m)
    }

    /// A CANopen type in its plain text form (`UNSIGNED24`, which has no mnemonic).
    pub fn plain(data_type: DataType) -> Self {
        AsciiType {
            data_type,
            form: Form::Plain,
        }
    }

    /// Print `bytes` read from a node.
    pub fn format(self, bytes: &[u8]) -> Result<String, TypeError> {
        let ty = self.data_type;
        Ok(match self.form {
            Form::Base64 => base64::engine::general_purpose::STANDARD.encode(bytes),
            Form::HexBytes => bytes
                .iter()
                .map(|b| format!("{b:02X}"))
                .collect::<Vec<_>>()
                .join(" "),
            Form::Hex => match types::decode(ty, bytes)? {
                Value::Uint(v) => format!("0x{v:0width$X}", width = bytes.len() * 2),
                other => types::to_text(ty, &other),
            },
            Form::Quoted => {
                let text = String::from_utf8_lossy(bytes);
                format!("\"{}\"", text.replace('"', "\"\""))
            }
            Form::Plain => types::to_text(ty, &types::decode(ty, bytes)?),
        })
    }

    /// The bytes to write for `text`.
    pub fn parse(self, text: &str) -> Result<Vec<u8>, TypeError> {
        let ty = self.data_type;
        let invalid = || TypeError::Invalid {
            ty,
            value: text.to_owned(),
        };
        match self.form {
            Form::Base64 => base64::engine::general_purpose::STANDARD
                .decode(text.trim())
                .map_err(|_| invalid()),
            Form::HexBytes => match types::from_text(DataType::Domain, text)? {
                Value::Bytes(b) => Ok(b),
                _ => Err(invalid()),
            },
            Form::Quoted => {
                let text = unquote(text.trim()).ok_or_else(invalid)?;
                types::encode(ty, &Value::Text(text))
            }
            Form::Hex | Form::Plain => types::encode(ty, &types::from_text(ty, text)?),
        }
    }
}

impl fmt::Display for AsciiType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.mnemonic() {
            Some(m) => f.write_str(m),
            None => write!(f, "{}", self.data_type),
        }
    }
}

/// A visible string as typed: in double quotes with `""` for a quote, or bare.
fn unquote(text: &str) -> Option<String> {
    let Some(inner) = text.strip_prefix('"') else {
        return Some(text.to_owned());
    };
    let inner = inner.strip_suffix('"')?;
    let mut out = String::with_capacity(inner.len());
    let mut chars = inner.chars();
    while let Some(c) = chars.next() {
        if c == '"' {
            // Inside the quotes a quote only stands doubled.
            if chars.next() != Some('"') {
                return None;
            }
        }
        out.push(c);
    }
    Some(out)
}

/// The gateway's own error codes (CiA 309-3 §5.4), printed as `ERROR: <n>`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Internal {
    /// 100: the request is not supported.
    NotSupported,
    /// 101: syntax error.
    Syntax,
    /// 102: not processed in the gateway's current state.
    InternalState,
    /// 103: time-out.
    Timeout,
    /// 104: no default net set.
    NoDefaultNet,
    /// 105: no default node set.
    NoDefaultNode,
    /// 106: unsupported net.
    UnsupportedNet,
    /// 107: unsupported node.
    UnsupportedNode,
    /// 501: LSS implementation- or manufacturer-specific error.
    LssManufacturer,
    /// 502: LSS node-ID not supported.
    LssNodeId,
    /// 503: LSS bit rate not supported.
    LssBitRate,
    /// 504: LSS parameter storing failed.
    LssStore,
    /// 505: LSS command failed because of a media error.
    LssMedia,
}

impl Internal {
    /// The number on the wire.
    pub fn code(self) -> u16 {
        match self {
            Internal::NotSupported => 100,
            Internal::Syntax => 101,
            Internal::InternalState => 102,
            Internal::Timeout => 103,
            Internal::NoDefaultNet => 104,
            Internal::NoDefaultNode => 105,
            Internal::UnsupportedNet => 106,
            Internal::UnsupportedNode => 107,
            Internal::LssManufacturer => 501,
            Internal::LssNodeId => 502,
            Internal::LssBitRate => 503,
            Internal::LssStore => 504,
            Internal::LssMedia => 505,
        }
    }

    /// Its meaning.
    pub fn text(self) -> &'static str {
        match self {
            Internal::NotSupported => "Request not supported.",
            Internal::Syntax => "Syntax error.",
            Internal::InternalState => "Request not processed due to internal state.",
            Internal::Timeout => "Time-out.",
            Internal::NoDefaultNet => "No default net set.",
            Internal::NoDefaultNode => "No default node set.",
            Internal::UnsupportedNet => "Unsupported net.",
            Internal::UnsupportedNode => "Unsupported node.",
            Internal::LssManufacturer => "LSS implementation- / manufacturer-specific error.",
            Internal::LssNodeId => "LSS node-ID not supported.",
            Internal::LssBitRate => "LSS bit-rate not supported.",
            Internal::LssStore => "LSS parameter storing failed.",
            Internal::LssMedia => "LSS command failed because of media error.",
        }
    }
}

/// Why a command failed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Failure {
    /// The node (or the SDO client) aborted the transfer.
    Abort(AbortCode),
    /// The gateway's own error, with a detail for the comment when there is one.
    Internal(Internal, Option<String>),
}

impl From<Internal> for Failure {
    fn from(e: Internal) -> Self {
        Failure::Internal(e, None)
    }
}

/// The body of a reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// `OK`.
    Ok,
    /// A value (or several, space separated, for LSS addresses).
    Value(String),
    /// Lines of text, then `OK` (help, info, LSS scans).
    Lines(Vec<String>),
    /// `ERROR: …`.
    Error(Failure),
}

/// One reply line (more for [`Outcome::Lines`]), with the request's sequence number.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reply {
    /// The request's `[<sequence>]`, echoed.
    pub sequence: Option<u32>,
    /// What happened.
    pub outcome: Outcome,
}

impl fmt::Display for Reply {
    /// Lines end in CR LF as CiA 309-3 requires.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let prefix = self.sequence.map(|s| format!("[{s}] ")).unwrap_or_default();
        match &self.outcome {
            Outcome::Ok => write!(f, "{prefix}OK\r\n"),
            Outcome::Value(v) => write!(f, "{prefix}{v}\r\n"),
            Outcome::Lines(lines) => {
                for line in lines {
                    write!(f, "{line}\r\n")?;
                }
                write!(f, "{prefix}OK\r\n")
            }
            Outcome::Error(Failure::Abort(code)) => {
                let text = code.description().unwrap_or("Unknown abort code.");
                write!(f, "{prefix}ERROR: 0x{:08X} #{text}", code.0)?;
                if !text.ends_with('.') {
                    f.write_str(".")?;
                }
                f.write_str("\r\n")
            }
            Outcome::Error(Failure::Internal(e, detail)) => {
                write!(f, "{prefix}ERROR: {} #{}", e.code(), e.text())?;
                if let Some(detail) = detail {
                    write!(f, " {detail}")?;
                }
                f.write_str("\r\n")
            }
        }
    }
}

/// An LSS service (CiA 305) as the ASCII mapping names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LssJob {
    /// `lss_switch_glob 0|1`.
    SwitchGlobal(bool),
    /// `lss_switch_sel VENDOR PRODUCT REVISION SERIAL`.
    SwitchSelective([u32; 4]),
    /// `lss_set_node ID`.
    SetNode(u8),
    /// `lss_conf_bitrate 0 INDEX`.
    ConfigureBitRate(u8),
    /// `lss_activate_bitrate DELAY_MS`.
    ActivateBitRate(u16),
    /// `lss_store`.
    Store,
    /// `lss_inquire_addr [0..3]`: one part, or all four.
    InquireAddress(Option<u8>),
    /// `lss_get_node`.
    GetNode,
    /// `_lss_fastscan [TIMEOUT_MS]`: find one unconfigured node and leave it selected.
    Fastscan {
        /// Each Fastscan step's listening time.
        step: Duration,
        /// What to do with each part of the address.
        parts: [FastscanPart; 4],
    },
    /// `lss_allnodes [TIMEOUT_MS [FIRST STORE [SCAN0 VENDOR SCAN1 PRODUCT SCAN2 REVISION SCAN3
    /// SERIAL]]]`: give every unconfigured node an ID in turn; scan type 0 scans a part, 1
    /// skips it, 2 matches the value given.
    AllNodes {
        /// Each Fastscan step's listening time.
        step: Duration,
        /// What to do with each part of the address.
        parts: [FastscanPart; 4],
        /// The first node-ID to give.
        first: u8,
        /// Store each configuration in the node.
        store: bool,
    },
}

/// What a parsed command asks the driver to do on the bus.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// SDO upload, printed as `ty` (hex bytes without one).
    Read {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The type to print as.
        ty: Option<AsciiType>,
    },
    /// SDO download of these bytes.
    Write {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The value, encoded.
        data: Vec<u8>,
    },
    /// An NMT command.
    Nmt(NmtCommand),
    /// An LSS service.
    Lss(LssJob),
}

/// A command resolved against the session: what to do, on which net and node, how.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Job {
    /// The request's sequence number, for the reply.
    pub sequence: Option<u32>,
    /// The net (1-based).
    pub net: u16,
    /// The node (0 = all nodes for NMT; unused for LSS).
    pub node: u8,
    /// What to do.
    pub action: Action,
    /// SDO response timeout.
    pub sdo_timeout: Duration,
    /// Use block transfers for SDO.
    pub sdo_block: bool,
}

impl Job {
    /// The reply to this job.
    pub fn reply(&self, outcome: Outcome) -> Reply {
        Reply {
            sequence: self.sequence,
            outcome,
        }
    }
}

/// What one line asks for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Step {
    /// Nothing (empty line or comment).
    Nothing,
    /// Answer at once (settings, help, errors).
    Reply(Reply),
    /// Run this on the bus, then reply.
    Run(Job),
}

/// One client's state: the defaults `set` changes (CiA 309-3 §5.3.2).
#[derive(Debug, Clone)]
pub struct Session {
    nets: u16,
    net: u16,
    node: Option<u8>,
    sdo_timeout: Duration,
    sdo_block: bool,
    info: String,
}

/// The help text `help` prints.
pub const HELP: &str = "\
Command strings start with an optional '[' <sequence> ']' followed by:
[[<net>] <node>] r[ead] <index> <subindex> [<datatype>]        # SDO upload.
[[<net>] <node>] w[rite] <index> <subindex> <datatype> <value> # SDO download.
[[<net>] <node>] start|stop|preop[erational]                   # NMT.
[[<net>] <node>] reset node|comm[unication]                    # NMT reset.
[<net>] set network|node <value>                               # Defaults.
[<net>] set sdo_timeout <ms> | set sdo_block <0|1>             # SDO client.
[<net>] lss_switch_glob <0|1>
[<net>] lss_switch_sel <vendor> <product> <revision> <serial>
[<net>] lss_set_node <node> | lss_conf_bitrate 0 <index> | lss_activate_bitrate <ms>
[<net>] lss_store | lss_inquire_addr [<0..3>] | lss_get_node
[<net>] _lss_fastscan [<timeout_ms>] | lss_allnodes [<timeout_ms> [<first> <store> [<scan0> <vendor> <scan1> <product> <scan2> <revision> <scan3> <serial>]]] (scan 0, skip 1, match 2)
help | info
Datatypes: b, i8 i16 i32 i64, u8 u16 u32 u64, x8 x16 x32 x64 (hex), r32 r64, t td,
vs (in double quotes if it has spaces), os us d (base64), hex (hex bytes).
Replies: [<sequence>] OK | <value> | ERROR: <SDO abort code or gateway error> #<text>";

/// Longest accepted number of leading net/node numbers.
const MAX_ADDRESS: usize = 2;

impl Session {
    /// A session on a gateway with `nets` networks (numbered from 1), `info` describing it.
    pub fn new(nets: u16, sdo_timeout: Duration, info: impl Into<String>) -> Self {
        Session {
            nets: nets.max(1),
            net: 1,
            node: None,
            sdo_timeout,
            sdo_block: false,
            info: info.into(),
        }
    }

    /// Parse one line (without its line end) against this session.
    pub fn handle(&mut self, line: &str) -> Step {
        let line = strip_comment(line).trim();
        if line.is_empty() {
            return Step::Nothing;
        }
        let (sequence, rest) = match sequence(line) {
            Ok(split) => split,
            Err(()) => return Step::Reply(error(None, Internal::Syntax, "bad [sequence]")),
        };
        let reply = |outcome| Step::Reply(Reply { sequence, outcome });
        match self.command(rest) {
            Ok(Parsed::Settled(outcome)) => reply(outcome),
            Ok(Parsed::Job { net, node, action }) => Step::Run(Job {
                sequence,
                net,
                node,
                action,
                sdo_timeout: self.sdo_timeout,
                sdo_block: self.sdo_block,
            }),
            Err(failure) => reply(Outcome::Error(failure)),
        }
    }

    fn command(&mut self, text: &str) -> Result<Parsed, Failure> {
        let words: Vec<&str> = text.split_whitespace().collect();
        let numbers = words
            .iter()
            .take(MAX_ADDRESS)
            .take_while(|w| types::parse_integer(w).is_some())
            .count();
        let (address, rest) = words.split_at(numbers);
        let Some((&verb, args)) = rest.split_first() else {
            return Err(syntax("no command"));
        };
        if types::parse_integer(verb).is_some() {
            return Err(syntax("more than a net and a node before the command"));
        }
        let verb = verb.to_ascii_lowercase();
        let number = |w: &str| types::parse_integer(w).ok_or_else(|| syntax("not a number"));
        match verb.as_str() {
            "help" | "info" | "set" if numbers > 1 => Err(syntax("more than a net before it")),
            "help" => Ok(Parsed::Settled(Outcome::Lines(
                HELP.lines().map(str::to_owned).collect(),
            ))),
            "info" => Ok(Parsed::Settled(Outcome::Lines(vec![format!(
                "{}; net {} of {}; node {}; sdo_timeout {} ms; sdo_block {}",
                self.info,
                self.net,
                self.nets,
                self.node.map_or("not set".to_owned(), |n| n.to_string()),
                self.sdo_timeout.as_millis(),
                u8::from(self.sdo_block)
            )]))),
            "set" => {
                let net = address.first().map(|w| number(w)).transpose()?;
                self.set(net, args)
            }
            v if v.starts_with("lss_") || v == "_lss_fastscan" => {
                if numbers > 1 {
                    return Err(syntax("LSS commands take a net only"));
                }
                let net = match address.first() {
                    Some(w) => self.net_number(number(w)?)?,
                    None => self.net,
                };
                let job = lss(v, args)?;
                Ok(Parsed::Job {
                    net,
                    node: 0,
                    action: Action::Lss(job),
                })
            }
            _ => {
                let (net, node) = match address {
                    [net, node] => (self.net_number(number(net)?)?, node_number(number(node)?)?),
                    [node] => (self.net, node_number(number(node)?)?),
                    _ => (self.net, self.node.ok_or(Internal::NoDefaultNode)?),
                };
                let action = node_action(&verb, args, text)?;
                if node == 0 && !matches!(action, Action::Nmt(_)) {
                    return Err(Internal::UnsupportedNode.into());
                }
                Ok(Parsed::Job { net, node, action })
            }
        }
    }

    fn net_number(&self, n: i128) -> Result<u16, Failure> {
        u16::try_from(n)
            .ok()
            .filter(|n| (1..=self.nets).contains(n))
            .ok_or_else(|| Internal::UnsupportedNet.into())
    }

    /// `[<net>] set …`: the net is checked, and the setting serves every net (one client's
    /// defaults are one set).
    fn set(&mut self, net: Option<i128>, args: &[&str]) -> Result<Parsed, Failure> {
        if let Some(net) = net {
            self.net_number(net)?;
        }
        let [what, value] = args else {
            return Err(syntax("set takes a name and a value"));
        };
        let value = types::parse_integer(value).ok_or_else(|| syntax("not a number"))?;
        match what.to_ascii_lowercase().as_str() {
            "network" => self.net = self.net_number(value)?,
            "node" => {
                node_number(value)?;
                self.node = u8::try_from(value).ok().filter(|n| *n > 0);
                if self.node.is_none() {
                    return Err(Internal::UnsupportedNode.into());
                }
            }
            "sdo_timeout" => {
                let ms = u64::try_from(value)
                    .ok()
                    .filter(|ms| (1..=600_000).contains(ms))
                    .ok_or_else(|| syntax("sdo_timeout is 1…600000 ms"))?;
                self.sdo_timeout = Duration::from_millis(ms);
            }
            "sdo_block" => {
                self.sdo_block = match value {
                    0 => false,
                    1 => true,
                    _ => return Err(syntax("sdo_block is 0 or 1")),
                }
            }
            _ => return Err(Internal::NotSupported.into()),
        }
        Ok(Parsed::Settled(Outcome::Ok))
    }
}

enum Parsed {
    Settled(Outcome),
    Job { net: u16, node: u8, action: Action },
}

fn syntax(detail: &str) -> Failure {
    Failure::Internal(Internal::Syntax, Some(format!("({detail})")))
}

fn error(sequence: Option<u32>, e: Internal, detail: &str) -> Reply {
    Reply {
        sequence,
        outcome: Outcome::Error(Failure::Internal(e, Some(format!("({detail})")))),
    }
}

fn node_number(n: i128) -> Result<u8, Failure> {
    u8::try_from(n)
        .ok()
        .filter(|n| *n <= 127)
        .ok_or_else(|| Internal::UnsupportedNode.into())
}

/// The line without its `#` comment; a `#` inside a quoted string is text.
fn strip_comment(line: &str) -> &str {
    let mut quoted = false;
    for (i, c) in line.char_indices() {
        match c {
            '"' => quoted = !quoted,
            '#' if !quoted => return &line[..i],
            _ => {}
        }
    }
    line
}

/// Split off `[<sequence>]`.
fn sequence(line: &str) -> Result<(Option<u32>, &str), ()> {
    let Some(rest) = line.strip_prefix('[') else {
        return Ok((None, line));
    };
    let (number, rest) = rest.split_once(']').ok_or(())?;
    let number = number.trim().parse::<u32>().map_err(|_| ())?;
    Ok((Some(number), rest.trim_start()))
}

fn node_action(verb: &str, args: &[&str], text: &str) -> Result<Action, Failure> {
    let index_sub = |args: &[&str]| -> Result<(u16, u8), Failure> {
        let index = args
            .first()
            .and_then(|w| types::parse_integer(w))
            .and_then(|v| u16::try_from(v).ok())
            .ok_or_else(|| syntax("index"))?;
        let sub = args
            .get(1)
            .and_then(|w| types::parse_integer(w))
            .and_then(|v| u8::try_from(v).ok())
            .ok_or_else(|| syntax("sub-index"))?;
        Ok((index, sub))
    };
    let mnemonic = |w: &str| {
        AsciiType::from_mnemonic(w).ok_or_else(|| syntax(&format!("unknown datatype {w}")))
    };
    let nmt = |c| Ok(Action::Nmt(c));
    match (verb, args) {
        ("r" | "read", [_, _]) | ("r" | "read", [_, _, _]) => {
            let (index, sub) = index_sub(args)?;
            let ty = args.get(2).map(|w| mnemonic(w)).transpose()?;
            Ok(Action::Read { index, sub, ty })
        }
        ("w" | "write", [_, _, ty, _, ..]) => {
            let (index, sub) = index_sub(args)?;
            let ty = mnemonic(ty)?;
            let value = value_text(text, verb).ok_or_else(|| syntax("value"))?;
            let data = ty
                .parse(value)
                .map_err(|e| Failure::Abort(e.abort_code()))?;
            Ok(Action::Write { index, sub, data })
        }
        ("r" | "read" | "w" | "write", _) => Err(syntax("wrong number of arguments")),
        ("start", []) => nmt(NmtCommand::Start),
        ("stop", []) => nmt(NmtCommand::Stop),
        ("preop" | "preoperational", []) => nmt(NmtCommand::EnterPreOperational),
        ("reset", [what]) => match what.to_ascii_lowercase().as_str() {
            "node" => nmt(NmtCommand::ResetNode),
            "comm" | "communication" => nmt(NmtCommand::ResetCommunication),
            _ => Err(syntax("reset node or reset comm")),
        },
        ("start" | "stop" | "preop" | "preoperational" | "reset", _) => {
            Err(syntax("wrong number of arguments"))
        }
        _ => Err(Internal::NotSupported.into()),
    }
}

/// Everything after `<verb> <index> <sub> <type>` in the original text: a value may hold
/// spaces (a quoted visible string) that splitting on whitespace would lose.
fn value_text<'a>(text: &'a str, verb: &str) -> Option<&'a str> {
    let mut rest = text;
    // Skip the address numbers, the verb and the three arguments before the value.
    loop {
        let trimmed = rest.trim_start();
        let (word, after) = trimmed.split_at(trimmed.find(char::is_whitespace)?);
        rest = after;
        if word.eq_ignore_ascii_case(verb) {
            break;
        }
    }
    for _ in 0..3 {
        let trimmed = rest.trim_start();
        rest = &trimmed[trimmed.find(char::is_whitespace)?..];
    }
    let value = rest.trim();
    (!value.is_empty()).then_some(value)
}

fn lss(verb: &str, args: &[&str]) -> Result<LssJob, Failure> {
    let num = |w: &&str| types::parse_integer(w).ok_or_else(|| syntax("not a number"));
    let nums: Vec<i128> = args.iter().map(num).collect::<Result<_, _>>()?;
    let u32s = |v: &[i128]| -> Result<[u32; 4], Failure> {
        let mut out = [0u32; 4];
        for (o, n) in out.iter_mut().zip(v) {
            *o = u32::try_from(*n).map_err(|_| syntax("not a 32-bit value"))?;
        }
        Ok(out)
    };
    let ms = |v: Option<&i128>, default: u64| -> Result<Duration, Failure> {
        match v {
            None => Ok(Duration::from_millis(default)),
            Some(&n) => u64::try_from(n)
                .ok()
                .filter(|n| (1..=10_000).contains(n))
                .map(Duration::from_millis)
                .ok_or_else(|| syntax("timeout 1…10000 ms")),
        }
    };
    Ok(match (verb, nums.as_slice()) {
        ("lss_switch_glob", [0]) => LssJob::SwitchGlobal(false),
        ("lss_switch_glob", [1]) => LssJob::SwitchGlobal(true),
        ("lss_switch_sel", [_, _, _, _]) => LssJob::SwitchSelective(u32s(&nums)?),
        ("lss_set_node", [n]) => LssJob::SetNode(
            u8::try_from(*n)
                .ok()
                .filter(|n| (1..=127).contains(n) || *n == 0xFF)
                .ok_or(Failure::from(Internal::LssNodeId))?,
        ),
        ("lss_conf_bitrate", [0, index]) => LssJob::ConfigureBitRate(
            u8::try_from(*index)
                .ok()
                .filter(|i| *i <= 9)
                .ok_or(Failure::from(Internal::LssBitRate))?,
        ),
        ("lss_conf_bitrate", [_, _]) => return Err(Internal::LssBitRate.into()),
        ("lss_activate_bitrate", [delay]) => {
            LssJob::ActivateBitRate(u16::try_from(*delay).map_err(|_| syntax("delay 0…65535 ms"))?)
        }
        ("lss_store", []) => LssJob::Store,
        ("lss_inquire_addr", []) => LssJob::InquireAddress(None),
        ("lss_inquire_addr", [part]) => LssJob::InquireAddress(Some(
            u8::try_from(*part)
                .ok()
                .filter(|p| *p <= 3)
                .ok_or_else(|| syntax("LSSSUB is 0…3"))?,
        )),
        ("lss_get_node", []) => LssJob::GetNode,
        ("_lss_fastscan", [] | [_]) => LssJob::Fastscan {
            step: ms(nums.first(), 100)?,
            parts: [FastscanPart::Scan; 4],
        },
        ("lss_allnodes", [] | [_] | [_, _, _] | [_, _, _, _, _, _, _, _, _, _, _]) => {
            LssJob::AllNodes {
                step: ms(nums.first(), 100)?,
                parts: scan_types(nums.get(3..).unwrap_or_default())?,
                first: match nums.get(1) {
                    None => 1,
                    Some(&n) => u8::try_from(n)
                        .ok()
                        .filter(|n| (1..=127).contains(n))
                        .ok_or(Failure::from(Internal::LssNodeId))?,
                },
                store: match nums.get(2) {
                    None | Some(0) => false,
                    Some(1) => true,
                    Some(_) => return Err(syntax("store is 0 or 1")),
                },
            }
        }
        (
            "lss_switch_glob"
            | "lss_switch_sel"
            | "lss_set_node"
            | "lss_conf_bitrate"
            | "lss_activate_bitrate"
            | "lss_store"
            | "lss_inquire_addr"
            | "lss_get_node"
            | "_lss_fastscan"
            | "lss_allnodes",
            _,
        ) => return Err(syntax("wrong arguments")),
        _ => return Err(Internal::NotSupported.into()),
    })
}

/// `lss_allnodes`'s eight trailing numbers: scan type and value for each address part (none:
/// scan every part).
fn scan_types(words: &[i128]) -> Result<[FastscanPart; 4], Failure> {
    let mut parts = [FastscanPart::Scan; 4];
    for (part, pair) in parts.iter_mut().zip(words.chunks(2)) {
        let value = pair.get(1).map(|v| u32::try_from(*v)).transpose();
        let value = value.map_err(|_| syntax("an address part is 32 bits"))?;
        *part = match (pair[0], value) {
            (0, _) => FastscanPart::Scan,
            (1, _) => FastscanPart::Skip,
            (2, Some(v)) => FastscanPart::Match(v),
            _ => return Err(syntax("scan type 0 (scan), 1 (skip) or 2 (match)")),
        };
    }
    FastscanMaster::new(parts).map_err(|e| syntax(&e.to_string()))?;
    Ok(parts)
}

/// The reply text of an LSS address.
pub fn format_address(address: [u32; 4]) -> String {
    address
        .iter()
        .map(|p| format!("0x{p:08X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests;
