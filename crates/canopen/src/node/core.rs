//! The node core, sans-IO: every service of a CANopen device (NMT, SDO server channels,
//! heartbeat producer and consumer, node/life guarding, EMCY, SYNC, TIME, PDOs, LSS) composed
//! into one state machine. It takes frames, dictionary changes, application commands and the
//! time, and gives frames to send, events and its next deadline — like CANopenNode's
//! `CO_process` with `timerNext_us`. The dictionary is passed into each step, so whoever owns
//! it decides how it is shared; [`super::LocalNode`] is the tokio shell around this core.

use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};
use std::time::Instant;

use canbus::{CanId, Filter, Frame};

use super::objects::renumber;
use super::{NodeCommand, NodeConfig, NodeEvent};
use crate::emcy::{codes, EmcyMessage, EmcyProducer};
use crate::guarding::{GuardEvent, GuardingSlave};
use crate::heartbeat::{timeout_emcy, HeartbeatConsumer, HeartbeatEvent, HeartbeatProducer};
use crate::lss::{LssAction, LssSlave, LssState, UNCONFIGURED};
use crate::nmt::{NmtAction, NmtCommand, NmtSlave, NmtState};
use crate::objects::*;
use crate::od::ObjectDictionary;
use crate::pdo::{PdoEngine, PdoEvent};
use crate::sdo::server::{server_channels, ServerChannels, ServerConfig};
use crate::sync::{SyncConfig, SyncProducer};
use crate::types::Value;

/// What a step of the node gives: frames to send, in order, and events for the application.
#[derive(Debug, Default)]
pub struct NodeOutput {
    /// Frames to send.
    pub frames: Vec<Frame>,
    /// What happened.
    pub events: Vec<NodeEvent>,
}

/// The TIME settings of 0x1012.
#[derive(Debug, Clone, Copy, Default)]
struct TimeConfig {
    cob_id: Option<CanId>,
    /// Bit 31: this node consumes TIME.
    consumes: bool,
    /// Bit 30: this node produces TIME.
    produces: bool,
}

/// A CANopen device's protocol state.
pub struct Node {
    node_id: u8,
    storage: Option<PathBuf>,
    lss: LssSlave,
    sdo_config: ServerConfig,
    /// The dictionary as it was configured: what resets restore.
    initial: ObjectDictionary,
    /// Whether it enters operational by itself after each boot (CiA 302 1F80h bit 2).
    self_starting: bool,
    nmt: NmtSlave,
    sdo: ServerChannels,
    producer: HeartbeatProducer,
    consumer: HeartbeatConsumer,
    guarding: GuardingSlave,
    emcy: EmcyProducer,
    sync_config: SyncConfig,
    sync: SyncProducer,
    time: TimeConfig,
    pdo: PdoEngine,
}

fn u32_value(od: &ObjectDictionary, index: u16, sub: u8) -> u32 {
    od.get_u32(index, sub).unwrap_or(0)
}

/// Where LSS "store configuration" keeps the node-ID and bit timing: beside the parameters.
fn lss_path(storage: &Path) -> PathBuf {
    storage.with_extension("lss")
}

/// The node-ID stored by LSS, if any.
fn stored_node_id(storage: &Path) -> Option<u8> {
    let text = std::fs::read_to_string(lss_path(storage)).ok()?;
    let id: u8 = text.split_whitespace().next()?.parse().ok()?;
    (1..=127).contains(&id).then_some(id)
}

/// Put the stored values of `range` from `path` into `od`; a damaged file is reported and
/// ignored (the node starts with its defaults rather than not at all).
fn apply_stored(od: &mut ObjectDictionary, path: &Path, range: RangeInclusive<u16>) {
    match crate::storage::load(path) {
        Ok(entries) => {
            let entries: Vec<_> = entries
                .into_iter()
                .filter(|(i, _, _)| range.contains(i))
                .collect();
            crate::storage::apply(od, &entries);
        }
        Err(e) => tracing::error!(error = %e, "stored parameters not loaded"),
    }
}

impl Node {
    /// A node configured by `config` over `od`: the communication objects it lacks are added
    /// (and 1010h/1011h with storage), a node-ID stored by LSS replaces the configured one, and
    /// stored parameters are applied; what `od` holds then is what resets go back to, before
    /// stored values. Call [`Node::start`] next.
    pub fn new(config: &NodeConfig, od: &mut ObjectDictionary, now: Instant) -> Node {
        let mut config = config.clone();
        if let Some(id) = config.storage.as_deref().and_then(stored_node_id) {
            config.node_id = id;
        }
        super::add_communication_objects(od, &config);
        if let Some(path) = &config.storage {
            crate::storage::add_storage_objects(od, path.clone());
        }
        // The defaults, for resets; stored values come on top of them.
        let initial = od.clone();
        if let Some(path) = &config.storage {
            apply_stored(od, path, 0x0000..=0xFFFF);
        }
        Node::assemble(&config, od, initial, now)
    }

    fn assemble(
        config: &NodeConfig,
        od: &mut ObjectDictionary,
        initial: ObjectDictionary,
        now: Instant,
    ) -> Node {
        let mut node = Node {
            node_id: config.node_id,
            storage: config.storage.clone(),
            lss: LssSlave::new(config.identity, config.node_id),
            sdo_config: config.sdo.clone(),
            initial,
            self_starting: config.self_starting,
            nmt: NmtSlave::new(config.node_id),
            sdo: ServerChannels::new(server_channels(od, config.node_id), &config.sdo),
            producer: HeartbeatProducer::new(config.node_id),
            consumer: HeartbeatConsumer::new(),
            guarding: GuardingSlave::new(config.node_id),
            emcy: EmcyProducer::new(config.node_id),
            sync_config: SyncConfig::default(),
            sync: SyncProducer::new(SyncConfig::default(), now),
            time: TimeConfig::default(),
            pdo: PdoEngine::default(),
        };
        node.load_communication(od, now);
        node
    }

    /// The node-ID (changes when LSS configures one).
    pub fn node_id(&self) -> u8 {
        self.node_id
    }

    /// The frames this node's bus endpoint takes: all but the default SDO channels of the other
    /// nodes (581h–5FFh, 601h–67Fh). CiA 301 §7.3.5 reserves those for SDO
    /// ([`crate::cob::restricted`]: no PDO, SYNC, TIME, EMCY or further SDO channel may use
    /// them), so nothing the node serves arrives there but requests on its own default channel;
    /// refused at the endpoint, a gateway's SDO traffic with the other nodes does not wake the
    /// node for every frame. It depends on the node-ID alone: ask again when that changes.
    pub fn receive_filters(&self) -> Vec<Filter> {
        let mut filters = vec![
            Filter::standard(0x000, 0x400), // 000h–3FFh
            Filter::standard(0x400, 0x700), // 400h–4FFh
            Filter::standard(0x500, 0x780), // 500h–57Fh
            Filter::exact(CanId::Standard(0x580)),
            Filter::exact(CanId::Standard(0x600)),
            Filter::standard(0x680, 0x780), // 680h–6FFh
            Filter::standard(0x700, 0x700), // 700h–7FFh: error control, LSS
            Filter::extended(0, 0),         // every 29-bit identifier
            Filter {
                id: canbus::ERR_FLAG,
                mask: canbus::ERR_FLAG,
            },
        ];
        if (1..=127).contains(&self.node_id) {
            let own = 0x600 + u16::from(self.node_id);
            filters.push(Filter::exact(CanId::Standard(own)));
        }
        filters
    }

    /// The NMT state.
    pub fn state(&self) -> NmtState {
        self.nmt.state()
    }

    /// Boot (boot-up message, pre-operational) — unless the node waits for LSS to give it a
    /// node-ID.
    pub fn start(&mut self, od: &mut ObjectDictionary, now: Instant, out: &mut NodeOutput) {
        if self.node_id != UNCONFIGURED {
            self.boot(od, now, out);
        }
    }

    /// When [`Node::handle_timeout`] must be called next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        [
            self.producer.poll_timeout(),
            self.consumer.poll_timeout(),
            self.guarding.poll_timeout(),
            self.emcy.poll_timeout(),
            self.sync.poll_timeout(),
            self.sdo.poll_timeout(),
            self.pdo
                .poll_timeout()
                .filter(|_| self.nmt.state().allows_pdo()),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// (Re)read every communication parameter from the dictionary.
    fn load_communication(&mut self, od: &mut ObjectDictionary, now: Instant) {
        for index in [
            SYNC_COB_ID,
            GUARD_TIME,
            TIME_COB_ID,
            EMCY_COB_ID,
            EMCY_INHIBIT,
            CONSUMER_HEARTBEAT,
            PRODUCER_HEARTBEAT,
        ] {
            self.change(od, index, 0, now);
        }
        self.sdo = ServerChannels::new(server_channels(od, self.node_id), &self.sdo_config);
        self.pdo = PdoEngine::configure(od, now);
    }

    /// Sub-object (`index`, `sub`) of the dictionary changed (by SDO, a PDO or the
    /// application): communication parameters steer the node; any other change may trigger a
    /// TPDO.
    pub fn handle_change(
        &mut self,
        od: &mut ObjectDictionary,
        index: u16,
        sub: u8,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        self.change(od, index, sub, now);
        self.settle(od, now, out);
    }

    fn change(&mut self, od: &mut ObjectDictionary, index: u16, sub: u8, now: Instant) {
        match index {
            // Writing 0 to 1003h sub 0 clears the history (our own mirror writes never write 0
            // while a history exists).
            ERROR_HISTORY
                if sub == 0
                    && od.get_value(ERROR_HISTORY, 0) == Ok(Value::Uint(0))
                    && self.emcy.history().next().is_some() =>
            {
                self.emcy.clear_history();
                self.write_history(od);
            }
            SYNC_COB_ID | SYNC_PERIOD | SYNC_WINDOW | SYNC_OVERFLOW => {
                self.sync_config = SyncConfig {
                    cob_id: u32_value(od, SYNC_COB_ID, 0),
                    period_us: u32_value(od, SYNC_PERIOD, 0),
                    window_us: u32_value(od, SYNC_WINDOW, 0),
                    counter_overflow: u32_value(od, SYNC_OVERFLOW, 0) as u8,
                };
                self.sync.reconfigure(self.sync_config, now);
            }
            GUARD_TIME | LIFE_TIME_FACTOR => self.guarding.configure(
                u32_value(od, GUARD_TIME, 0) as u16,
                u32_value(od, LIFE_TIME_FACTOR, 0) as u8,
            ),
            TIME_COB_ID => {
                let value = u32_value(od, TIME_COB_ID, 0);
                self.time = TimeConfig {
                    cob_id: crate::cob::id_from_parameter(value & 0x3FFF_FFFF),
                    consumes: value & 0x8000_0000 != 0,
                    produces: value & 0x4000_0000 != 0,
                };
            }
            EMCY_COB_ID => self.emcy.set_cob_id(u32_value(od, EMCY_COB_ID, 0)),
            EMCY_INHIBIT => self
                .emcy
                .set_inhibit_100us(u32_value(od, EMCY_INHIBIT, 0) as u16),
            CONSUMER_HEARTBEAT => {
                // Re-target monitoring; the table keeps what it knows about every node.
                let known: Vec<u8> = self.consumer.table().map(|(n, _)| n).collect();
                for node in known {
                    self.consumer.monitor(node, None);
                }
                let entries = od
                    .object(CONSUMER_HEARTBEAT)
                    .map(|o| o.subs.len())
                    .unwrap_or(0);
                for s in 1..entries as u8 {
                    self.consumer
                        .monitor_entry(u32_value(od, CONSUMER_HEARTBEAT, s));
                }
            }
            PRODUCER_HEARTBEAT => self
                .producer
                .set_period_ms(u32_value(od, PRODUCER_HEARTBEAT, 0) as u16, now),
            // A further SDO channel moved, opened or closed (CiA 301 §7.5.2.33).
            0x1201..=0x127F => self
                .sdo
                .reconfigure(server_channels(od, self.node_id), &self.sdo_config),
            _ if PdoEngine::is_config(index) => self.pdo = PdoEngine::configure(od, now),
            _ => self.pdo.on_change(index, sub, now),
        }
    }

    /// Mirror the EMCY producer's register and history into 1001h and 1003h.
    fn write_history(&mut self, od: &mut ObjectDictionary) {
        let _ = od.set(ERROR_REGISTER, 0, &[self.emcy.error_register()]);
        let slots = od
            .object(ERROR_HISTORY)
            .map(|o| o.subs.len().saturating_sub(1))
            .unwrap_or(0);
        let history: Vec<u32> = self.emcy.history().take(slots).collect();
        for s in 1..=slots {
            let v = history.get(s - 1).copied().unwrap_or(0);
            let _ = od.set(ERROR_HISTORY, s as u8, &v.to_le_bytes());
        }
        let _ = od.set(ERROR_HISTORY, 0, &[history.len() as u8]);
    }

    fn enter(&mut self, state: NmtState, now: Instant, out: &mut NodeOutput) {
        if state == NmtState::Operational {
            // Event-driven TPDOs announce their current values on entering operational.
            self.pdo.trigger_all(now);
        }
        out.events.push(NodeEvent::Nmt(state));
    }

    fn boot(&mut self, od: &mut ObjectDictionary, now: Instant, out: &mut NodeOutput) {
        self.nmt.boot(&mut out.frames);
        self.load_communication(od, now);
        self.enter(NmtState::PreOperational, now, out);
        if self.self_starting {
            self.own_nmt(od, NmtCommand::Start, now, out);
        }
    }

    /// `command` given by the node itself, as if an NMT master had sent it.
    fn own_nmt(
        &mut self,
        od: &mut ObjectDictionary,
        command: NmtCommand,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        if let Some(action) = self.nmt.handle(&command.frame(self.node_id)) {
            self.nmt_action(od, action, now, out);
        }
    }

    /// Take the node-ID configured by LSS (CiA 305: at reset communication, or at once for a
    /// node that had none).
    fn change_node_id(&mut self, od: &mut ObjectDictionary, new: u8) {
        let old = self.node_id;
        tracing::info!(old, new, "node-ID changed by LSS");
        renumber(&mut self.initial, old, new);
        renumber(od, old, new);
        self.node_id = new;
        self.nmt = NmtSlave::new(new);
        self.producer = HeartbeatProducer::new(new);
        self.guarding = GuardingSlave::new(new);
        self.emcy = EmcyProducer::new(new);
        self.lss.set_active_node_id(new);
    }

    /// LSS "store configuration": the pending node-ID and bit timing beside the parameters.
    /// The answer's code: 0 stored, 1 not supported (no storage), 2 storage error.
    fn store_lss(&self) -> u8 {
        let Some(path) = &self.storage else {
            return 1;
        };
        let timing = self
            .lss
            .pending_bit_timing()
            .map_or(String::from("-"), |b| b.to_string());
        let text = format!("{} {timing}\n", self.lss.pending_node_id());
        match crate::storage::write_atomically(&lss_path(path), &text) {
            Ok(()) => 0,
            Err(e) => {
                tracing::error!(error = %e, "LSS store failed");
                2
            }
        }
    }

    fn lss_frame(
        &mut self,
        od: &mut ObjectDictionary,
        frame: &Frame,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        match self.lss.handle(frame, &mut out.frames) {
            Some(LssAction::Store) => {
                let result = self.store_lss();
                self.lss.store_result(result, &mut out.frames);
            }
            Some(LssAction::ActivateBitTiming { delay_ms }) => {
                // A virtual bus has no bit timing to switch; a SocketCAN deployment does it
                // with `ip link` outside this process.
                tracing::info!(
                    delay_ms,
                    bit_timing = self.lss.pending_bit_timing(),
                    "LSS activate bit timing"
                );
            }
            Some(LssAction::StateChanged(LssState::Waiting)) => {
                let pending = self.lss.pending_node_id();
                if self.node_id == UNCONFIGURED && (1..=127).contains(&pending) {
                    self.change_node_id(od, pending);
                    self.boot(od, now, out);
                }
            }
            Some(LssAction::StateChanged(LssState::Configuration)) | None => {}
        }
    }

    /// Reset: restore the values of `range` from the start-up dictionary, then boot again.
    fn reset(
        &mut self,
        od: &mut ObjectDictionary,
        range: RangeInclusive<u16>,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        // CiA 305 §8.3.2: the node-ID configured by LSS takes effect here — FFh too, after
        // which the node has none and waits, silent, for LSS to give it one.
        let pending = self.lss.pending_node_id();
        if pending != self.node_id && ((1..=127).contains(&pending) || pending == UNCONFIGURED) {
            self.change_node_id(od, pending);
        }
        for object in self.initial.objects().filter(|o| range.contains(&o.index)) {
            for (sub, var) in &object.subs {
                if let Some(bytes) = var.value_bytes() {
                    let _ = od.set(object.index, *sub, bytes);
                }
            }
        }
        if let Some(path) = &self.storage {
            apply_stored(od, path, range);
        }
        self.emcy = EmcyProducer::new(self.node_id);
        self.enter(NmtState::Initialising, now, out);
        if self.node_id != UNCONFIGURED {
            self.boot(od, now, out);
        }
    }

    fn nmt_action(
        &mut self,
        od: &mut ObjectDictionary,
        action: NmtAction,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        match action {
            NmtAction::Entered(state) => self.enter(state, now, out),
            NmtAction::ResetCommunication => self.reset(od, 0x1000..=0x1FFF, now, out),
            NmtAction::ResetNode => self.reset(od, 0x0000..=0xFFFF, now, out),
        }
    }

    /// A frame from the bus.
    pub fn handle_frame(
        &mut self,
        od: &mut ObjectDictionary,
        frame: &Frame,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        self.frame(od, frame, now, out);
        self.settle(od, now, out);
    }

    fn frame(
        &mut self,
        od: &mut ObjectDictionary,
        frame: &Frame,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        if frame.id() == crate::lss::MASTER_ID {
            self.lss_frame(od, frame, now, out);
            return;
        }
        if self.nmt.state() == NmtState::Initialising {
            // No node-ID yet (waiting for LSS): nothing else is served.
            return;
        }
        if let Some(action) = self.nmt.handle(frame) {
            self.nmt_action(od, action, now, out);
            return;
        }
        let state = self.nmt.state();
        if frame.is_remote() {
            if state.allows_pdo() && self.pdo.handle_remote(od, frame, now, &mut out.frames) {
                return;
            }
            let mut events = Vec::new();
            self.guarding
                .handle(frame, state, now, &mut out.frames, &mut events);
            self.guard_events(od, events, out);
            return;
        }
        if state.allows_sdo() && self.sdo.serves(frame.id()) {
            self.sdo.handle(od, frame, now, &mut out.frames);
            return;
        }
        let mut heartbeat = Vec::new();
        self.consumer.handle(frame, now, &mut heartbeat);
        self.heartbeat_events(od, heartbeat, out);
        if let Some((node, message)) = EmcyMessage::from_frame(frame) {
            if node != self.node_id {
                out.events.push(NodeEvent::Emcy { node, message });
            }
        }
        if state.allows_pdo() && self.pdo.is_rpdo(frame.id()) {
            let mut pdo_events = Vec::new();
            let was_pdo = self.pdo.handle_frame(od, frame, now, &mut pdo_events);
            if was_pdo && pdo_events.is_empty() {
                self.rpdo_received(od);
            }
            self.pdo_events(od, pdo_events);
            if was_pdo {
                return;
            }
        }
        if state.allows_sdo() {
            if self.time.consumes && Some(frame.id()) == self.time.cob_id {
                if let Some(stamp) = crate::time::TimeOfDay::parse(frame.data()) {
                    out.events.push(NodeEvent::Time(stamp.to_system()));
                }
                return;
            }
            if let Some(event) = crate::sync::receive(&self.sync_config, frame, now) {
                if state.allows_pdo() {
                    self.pdo.on_sync(od, event.counter, now, &mut out.frames);
                }
                out.events.push(NodeEvent::Sync(event));
            }
        }
    }

    /// A correct RPDO ends the length and timeout errors it may have raised.
    fn rpdo_received(&mut self, od: &mut ObjectDictionary) {
        let cleared: Vec<u16> = [
            codes::PDO_LENGTH,
            codes::PDO_LENGTH_EXCEEDED,
            codes::RPDO_TIMEOUT,
        ]
        .into_iter()
        .filter(|c| self.emcy.is_active(*c))
        .collect();
        for code in &cleared {
            self.emcy.clear_error(*code);
        }
        if !cleared.is_empty() {
            self.write_history(od);
        }
    }

    fn pdo_events(&mut self, od: &mut ObjectDictionary, events: Vec<PdoEvent>) {
        if events.is_empty() {
            return;
        }
        for e in events {
            let number = match e {
                PdoEvent::LengthError { rpdo }
                | PdoEvent::LengthExceeded { rpdo }
                | PdoEvent::Timeout { rpdo } => rpdo,
            };
            let n = number.to_le_bytes();
            self.emcy.set_error(e.emcy_code(), [n[0], n[1], 0, 0, 0]);
        }
        self.write_history(od);
    }

    fn send_time(&mut self, at: std::time::SystemTime, out: &mut NodeOutput) {
        let stamp = crate::time::TimeOfDay::from_system(at);
        match (self.time.cob_id, self.time.produces, stamp) {
            (Some(id), true, Some(stamp)) if self.nmt.state().allows_sdo() => {
                out.frames.push(stamp.frame(id))
            }
            (_, false, _) => tracing::debug!("TIME not sent: 0x1012 bit 30 (producer) is clear"),
            _ => tracing::debug!("TIME not sent: not representable or not allowed in this state"),
        }
    }

    fn guard_events(
        &mut self,
        od: &mut ObjectDictionary,
        events: Vec<GuardEvent>,
        out: &mut NodeOutput,
    ) {
        for event in events {
            match event {
                GuardEvent::LifeGuardingLost => self.emcy.set_error(codes::HEARTBEAT, [0; 5]),
                GuardEvent::LifeGuardingResumed => self.emcy.clear_error(codes::HEARTBEAT),
                _ => {}
            }
            self.write_history(od);
            out.events.push(NodeEvent::Guarding(event));
        }
    }

    fn heartbeat_events(
        &mut self,
        od: &mut ObjectDictionary,
        events: Vec<HeartbeatEvent>,
        out: &mut NodeOutput,
    ) {
        let mut history_changed = false;
        for event in events {
            match event {
                HeartbeatEvent::Timeout { node } => {
                    let (code, data) = timeout_emcy(node);
                    // One heartbeat error per node: the node-ID is in the manufacturer field.
                    self.emcy.set_error(code, data);
                    history_changed = true;
                }
                HeartbeatEvent::Recovered { .. } => {
                    self.emcy.clear_error(codes::HEARTBEAT);
                    history_changed = true;
                }
                HeartbeatEvent::StateChanged { .. } | HeartbeatEvent::BootUp { .. } => {}
            }
            out.events.push(NodeEvent::Heartbeat(event));
        }
        if history_changed {
            self.write_history(od);
        }
    }

    /// An application command.
    pub fn handle_command(
        &mut self,
        od: &mut ObjectDictionary,
        command: NodeCommand,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        match command {
            NodeCommand::SetError(code, data) => self.emcy.set_error(code, data),
            NodeCommand::ClearError(code) => self.emcy.clear_error(code),
            NodeCommand::Nmt(c) => self.own_nmt(od, c, now, out),
            NodeCommand::SendPdo(n) => self.pdo.request(n, now),
            NodeCommand::SendTime(at) => self.send_time(at, out),
            NodeCommand::Defaults(values) => {
                for (index, sub, bytes) in values {
                    let _ = self.initial.set(index, sub, &bytes);
                }
            }
        }
        self.write_history(od);
        self.settle(od, now, out);
    }

    /// Zero-delay work a step caused (EMCY ready to go, PDOs triggered) goes out with it.
    fn settle(&mut self, od: &mut ObjectDictionary, now: Instant, out: &mut NodeOutput) {
        self.handle_timeout(od, now, out);
    }

    /// Time passed: whatever is due — heartbeats, timeouts, EMCY, SYNC, PDOs.
    pub fn handle_timeout(
        &mut self,
        od: &mut ObjectDictionary,
        now: Instant,
        out: &mut NodeOutput,
    ) {
        let state = self.nmt.state();
        if state != NmtState::Initialising {
            self.producer.handle_timeout(now, state, &mut out.frames);
        }
        let mut heartbeat = Vec::new();
        self.consumer.handle_timeout(now, &mut heartbeat);
        self.heartbeat_events(od, heartbeat, out);
        let mut guard = Vec::new();
        self.guarding.handle_timeout(now, &mut guard);
        self.guard_events(od, guard, out);
        self.sdo.handle_timeout(now, &mut out.frames);
        if state.allows_sdo() {
            self.emcy.handle_timeout(now, &mut out.frames);
            let before = out.frames.len();
            self.sync.handle_timeout(now, &mut out.frames);
            // This node's own SYNC drives its synchronous PDOs too.
            if let Some(sync) = out.frames.get(before).filter(|_| state.allows_pdo()) {
                let counter = sync.data().first().copied();
                self.pdo.on_sync(od, counter, now, &mut out.frames);
            }
        }
        if state.allows_pdo() {
            let mut pdo_events = Vec::new();
            self.pdo
                .handle_timeout(od, now, &mut out.frames, &mut pdo_events);
            self.pdo_events(od, pdo_events);
        }
        if !state.allows_sdo() && self.sync.poll_timeout().is_some_and(|d| d <= now) {
            // SYNC is not produced while stopped; keep the schedule moving.
            self.sync.handle_timeout(now, &mut Vec::new());
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::od::{Access, Object, Variable};
    use crate::types::DataType;

    /// A node on simulated time: every step's output is collected.
    struct Rig {
        node: Node,
        od: ObjectDictionary,
        now: Instant,
    }

    impl Rig {
        fn new(config: NodeConfig) -> Rig {
            let mut od = ObjectDictionary::new();
            od.insert(Object::var(
                0x2000,
                Variable::new("Value", DataType::Unsigned16, Access::Rw),
            ));
            let now = Instant::now();
            let node = Node::new(&config, &mut od, now);
            Rig { node, od, now }
        }

        fn run(
            &mut self,
            f: impl FnOnce(&mut Node, &mut ObjectDictionary, Instant, &mut NodeOutput),
        ) -> NodeOutput {
            let mut out = NodeOutput::default();
            f(&mut self.node, &mut self.od, self.now, &mut out);
            out
        }

        fn frame(&mut self, frame: Frame) -> NodeOutput {
            self.run(|n, od, now, out| n.handle_frame(od, &frame, now, out))
        }

        fn after(&mut self, d: Duration) -> NodeOutput {
            self.now += d;
            self.run(|n, od, now, out| n.handle_timeout(od, now, out))
        }
    }

    #[test]
    fn the_endpoint_refuses_only_other_nodes_default_sdo_channels() {
        for node_id in [1u8, 5, 127, UNCONFIGURED] {
            let rig = Rig::new(NodeConfig::new(node_id));
            let filters = rig.node.receive_filters();
            let takes = |frame: Frame| filters.iter().any(|f| f.matches(&frame));
            for id in 0..=0x7FFu16 {
                let others_sdo = matches!(id, 0x581..=0x5FF | 0x601..=0x67F)
                    && u32::from(id) != 0x600 + u32::from(node_id);
                let frame = Frame::standard(id, &[0]).unwrap();
                assert_eq!(takes(frame), !others_sdo, "node {node_id}: {id:03X}h");
                let remote = Frame::remote(CanId::Standard(id), 0).unwrap();
                assert_eq!(takes(remote), !others_sdo, "node {node_id}: RTR {id:03X}h");
                if others_sdo {
                    assert!(crate::cob::restricted(id), "{id:03X}h is not reserved");
                }
            }
            let extended = CanId::extended(0x1234_5678).unwrap();
            assert!(takes(Frame::new(extended, &[1]).unwrap()));
            assert!(takes(Frame::error(0x004, &[0; 8]).unwrap()), "error frames");
        }
    }

    #[test]
    fn boots_serves_sdo_and_produces_heartbeats_on_simulated_time() {
        let config = NodeConfig {
            heartbeat_ms: 100,
            device_name: "canlift test".into(),
            ..NodeConfig::new(5)
        };
        let mut rig = Rig::new(config);
        let out = rig.run(|n, od, now, out| n.start(od, now, out));
        assert_eq!(out.frames, [Frame::standard(0x705, &[0]).unwrap()]);
        assert_eq!(out.events, [NodeEvent::Nmt(NmtState::PreOperational)]);
        assert_eq!(
            rig.node.poll_timeout(),
            Some(rig.now + Duration::from_millis(100))
        );
        let out = rig.after(Duration::from_millis(100));
        assert_eq!(out.frames, [Frame::standard(0x705, &[0x7F]).unwrap()]);
        // NMT start: operational, and the heartbeat says so.
        let out = rig.frame(NmtCommand::Start.frame(5));
        assert_eq!(out.events, [NodeEvent::Nmt(NmtState::Operational)]);
        assert_eq!(rig.node.state(), NmtState::Operational);
        let out = rig.after(Duration::from_millis(100));
        assert_eq!(out.frames, [Frame::standard(0x705, &[0x05]).unwrap()]);
        // An expedited SDO read of the device name's first bytes is answered in the same step.
        let out = rig.frame(Frame::standard(0x605, &[0x40, 0x08, 0x10, 0, 0, 0, 0, 0]).unwrap());
        assert_eq!(out.frames.len(), 1);
        assert_eq!(out.frames[0].id(), CanId::Standard(0x585));
        assert_eq!(
            out.frames[0].data()[0],
            0x41,
            "segmented upload, size indicated"
        );
        assert_eq!(out.frames[0].data()[4], 12, "12 characters");
    }

    #[test]
    fn a_self_starting_node_restores_its_own_pdo_at_every_reset() {
        let config = NodeConfig {
            self_starting: true,
            ..NodeConfig::new(5)
        };
        let mut rig = Rig::new(config);
        let out = rig.run(|n, od, now, out| n.start(od, now, out));
        assert_eq!(
            out.events,
            [
                NodeEvent::Nmt(NmtState::PreOperational),
                NodeEvent::Nmt(NmtState::Operational)
            ]
        );
        // The application's own RPDO1 (what LocalNode::configure_pdo hands over as defaults).
        let mut mappable = Variable::new("Input", DataType::Unsigned16, Access::Rw);
        mappable.pdo_mappable = true;
        rig.od.insert(Object::var(0x2001, mappable));
        let setup = crate::node::PdoSetup {
            transmit: false,
            number: 1,
            cob_id: 0x20C,
            objects: vec![(0x2001, 0)],
            transmission_type: 255,
            inhibit_100us: 0,
            event_ms: 0,
        };
        crate::node::configure_pdo(&mut rig.od, &setup).unwrap();
        let defaults: Vec<(u16, u8, Vec<u8>)> = [0x1400, 0x1600]
            .iter()
            .flat_map(|&i| {
                let o = rig.od.object(i).unwrap().clone();
                o.subs
                    .iter()
                    .filter_map(|(s, v)| Some((i, *s, v.value_bytes()?.to_vec())))
                    .collect::<Vec<_>>()
            })
            .collect();
        rig.run(|n, od, now, out| n.handle_command(od, NodeCommand::Defaults(defaults), now, out));
        for reset in [NmtCommand::ResetCommunication, NmtCommand::ResetNode] {
            let out = rig.frame(reset.frame(5));
            assert_eq!(
                out.events.last(),
                Some(&NodeEvent::Nmt(NmtState::Operational)),
                "{reset:?}"
            );
            assert_eq!(rig.od.get_value(0x1600, 0), Ok(Value::Uint(1)), "{reset:?}");
            assert_eq!(
                rig.od.get_value(0x1400, 1),
                Ok(Value::Uint(0x20C)),
                "{reset:?}"
            );
        }
    }

    /// An LSS command frame (CiA 305) from the master.
    fn lss(data: [u8; 8]) -> Frame {
        Frame::standard(0x7E5, &data).unwrap()
    }

    #[test]
    fn node_id_ff_by_lss_leaves_the_node_unconfigured_after_its_reset_until_lss_gives_one() {
        let mut rig = Rig::new(NodeConfig::new(5));
        rig.run(|n, od, now, out| n.start(od, now, out));
        // Switch state global to configuration, configure node-ID FFh (accepted), back to waiting.
        rig.frame(lss([0x04, 1, 0, 0, 0, 0, 0, 0]));
        let out = rig.frame(lss([0x11, 0xFF, 0, 0, 0, 0, 0, 0]));
        assert_eq!(
            out.frames,
            [Frame::standard(0x7E4, &[0x11, 0, 0, 0, 0, 0, 0, 0]).unwrap()]
        );
        rig.frame(lss([0x04, 0, 0, 0, 0, 0, 0, 0]));
        // Reset communication: no boot-up, nothing served under the old node-ID.
        let out = rig.frame(NmtCommand::ResetCommunication.frame(5));
        assert!(out.frames.is_empty(), "{:?}", out.frames);
        assert_eq!(rig.node.state(), NmtState::Initialising);
        let out = rig.frame(Frame::standard(0x605, &[0x40, 0x00, 0x20, 0, 0, 0, 0, 0]).unwrap());
        assert!(out.frames.is_empty(), "no SDO answer: {:?}", out.frames);
        assert!(
            rig.after(Duration::from_secs(5)).frames.is_empty(),
            "silent"
        );
        // LSS gives it node-ID 7: it boots as 7.
        rig.frame(lss([0x04, 1, 0, 0, 0, 0, 0, 0]));
        rig.frame(lss([0x11, 7, 0, 0, 0, 0, 0, 0]));
        let out = rig.frame(lss([0x04, 0, 0, 0, 0, 0, 0, 0]));
        assert_eq!(out.frames, [Frame::standard(0x707, &[0]).unwrap()]);
        let out = rig.frame(Frame::standard(0x607, &[0x40, 0x00, 0x20, 0, 0, 0, 0, 0]).unwrap());
        assert_eq!(out.frames[0].id(), CanId::Standard(0x587));
    }

    #[test]
    fn a_further_sdo_channel_is_moved_only_while_not_valid() {
        let config = NodeConfig {
            sdo_servers: vec![(CanId::Standard(0x6A1), CanId::Standard(0x6C1))],
            ..NodeConfig::new(5)
        };
        let mut rig = Rig::new(config);
        rig.run(|n, od, now, out| n.start(od, now, out));
        let std = |id: u16, data: &[u8]| Frame::standard(id, data).unwrap();
        // Upload of 1201h sub 1 on `request`; the answer's identifier, if any.
        let ask = |rig: &mut Rig, request: u16| {
            let out = rig.frame(std(request, &[0x40, 0x01, 0x12, 0x01, 0, 0, 0, 0]));
            out.frames
                .first()
                .map(|f| (f.id(), f.data()[4..6].to_vec()))
        };
        // Write 1201h `sub` on the default channel, and let the node see the change as a
        // `LocalNode` does; the answer's command byte and abort code.
        let write_to = |rig: &mut Rig, index: u16, sub: u8, value: u32| {
            let mut data = vec![0x23];
            data.extend(index.to_le_bytes());
            data.push(sub);
            data.extend(value.to_le_bytes());
            let out = rig.frame(std(0x605, &data));
            rig.run(|n, od, now, out| n.handle_change(od, index, sub, now, out));
            let answer = &out.frames[0];
            let code = u32::from_le_bytes(answer.data()[4..8].try_into().unwrap());
            (answer.data()[0], code)
        };
        let write = |rig: &mut Rig, sub: u8, value: u32| write_to(rig, 0x1201, sub, value);
        assert_eq!(
            ask(&mut rig, 0x6A1),
            Some((CanId::Standard(0x6C1), vec![0xA1, 0x06]))
        );
        // In use: moving it is refused, closing it is not.
        assert_eq!(write(&mut rig, 1, 0x6A5), (0x80, 0x0609_0030));
        assert_eq!(write(&mut rig, 1, 0x8000_06A1), (0x60, 0));
        assert_eq!(ask(&mut rig, 0x6A1), None, "closed");
        // Closed: it may move, but not onto an identifier the connection set reserves, nor
        // onto one of the node's PDOs (TPDO 1's 185h, RPDO 1's 205h) or its own response.
        assert_eq!(write(&mut rig, 1, 0x605), (0x80, 0x0609_0030));
        assert_eq!(write(&mut rig, 1, 0x185), (0x80, 0x0609_0030));
        assert_eq!(write(&mut rig, 1, 0x205), (0x80, 0x0609_0030));
        assert_eq!(write(&mut rig, 1, 0x6C1), (0x80, 0x0609_0030));
        assert_eq!(write(&mut rig, 1, 0x6A5), (0x60, 0));
        assert_eq!(
            ask(&mut rig, 0x6A5),
            Some((CanId::Standard(0x6C1), vec![0xA5, 0x06]))
        );
        assert_eq!(ask(&mut rig, 0x6A1), None);
        // Nor may a PDO move onto the channel's identifiers.
        assert_eq!(write_to(&mut rig, 0x1800, 1, 0x8000_0185), (0x60, 0));
        assert_eq!(write_to(&mut rig, 0x1800, 1, 0x6A5), (0x80, 0x0609_0030));
        assert_eq!(write_to(&mut rig, 0x1800, 1, 0x6C1), (0x80, 0x0609_0030));
        assert_eq!(write_to(&mut rig, 0x1800, 1, 0x1A5), (0x60, 0));
        // The default channel stays where it is.
        let out = rig.frame(std(0x605, &[0x23, 0x00, 0x12, 0x01, 0xA7, 0x06, 0, 0]));
        assert_eq!(out.frames[0].data()[0], 0x80, "1200h is read-only");
        // A reset of communication brings back the configured channel.
        rig.frame(NmtCommand::ResetCommunication.frame(0));
        assert_eq!(
            ask(&mut rig, 0x6A1),
            Some((CanId::Standard(0x6C1), vec![0xA1, 0x06]))
        );
        assert_eq!(ask(&mut rig, 0x6A5), None);
    }

    #[test]
    fn errors_go_out_as_emcy_with_register_and_history_and_resets_restore_values() {
        let mut rig = Rig::new(NodeConfig::new(5));
        rig.run(|n, od, now, out| n.start(od, now, out));
        let out = rig.run(|n, od, now, out| {
            n.handle_command(od, NodeCommand::SetError(0x5000, [1, 2, 3, 4, 5]), now, out)
        });
        assert_eq!(
            out.frames,
            [Frame::standard(0x085, &[0x00, 0x50, 0x01, 1, 2, 3, 4, 5]).unwrap()]
        );
        assert_eq!(rig.od.get_value(ERROR_REGISTER, 0), Ok(Value::Uint(1)));
        assert_eq!(rig.od.get_value(ERROR_HISTORY, 0), Ok(Value::Uint(1)));
        rig.od.set_value(0x2000, 0, &Value::Uint(7)).unwrap();
        let out = rig.frame(NmtCommand::ResetNode.frame(0));
        assert_eq!(
            out.events,
            [
                NodeEvent::Nmt(NmtState::Initialising),
                NodeEvent::Nmt(NmtState::PreOperational)
            ]
        );
        assert!(out.frames.contains(&Frame::standard(0x705, &[0]).unwrap()));
        assert_eq!(
            rig.od.get_value(0x2000, 0),
            Ok(Value::Uint(0)),
            "reset node"
        );
        assert_eq!(rig.od.get_value(ERROR_REGISTER, 0), Ok(Value::Uint(0)));
    }
}
