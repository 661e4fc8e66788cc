//! The lifts held here: the holder entry of each (written when its connection is admitted,
//! again when its status changes, when NATS is back or another write got over it), and the
//! requests other processes relay to it, answered through [`crate::Local`].

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use async_nats::jetstream::kv;
use futures_util::StreamExt;
use nxg::msg::Method;
use nxg::portal::Failure;
use tokio::sync::watch;

use cloud_types::subscriptions::Terms;

use crate::msgs::{self, HolderEntry, Key, Relayed, RelayedAnswer};
use crate::{lock, Cluster, DONE, NEW_LEASE};

impl Cluster {
    /// The entry of a connection admitted here at `epoch`, of a lift of account `domain`
    /// whose gateway has serial number `sernum`.
    pub fn entry(&self, epoch: u64, domain: String, sernum: String) -> HolderEntry {
        HolderEntry {
            node: self.node.clone(),
            incarnation: self.incarnation,
            epoch,
            domain,
            sernum,
            error_register: None,
            lift_state: None,
        }
    }

    /// A connection of `lift` was admitted here: claim the lift in the bucket and answer its
    /// relayed requests until [`Cluster::release`].
    pub fn hold(self: &Arc<Self>, lift: &str, entry: HolderEntry) {
        let (tx, rx) = watch::channel(entry);
        lock(&self.held).insert(lift.to_owned(), tx);
        tokio::spawn(self.clone().serve_held(lift.to_owned(), rx));
    }

    /// The connection of `epoch` no longer serves `lift`: its holder task ends (and deletes
    /// the entry, unless another process wrote it since).
    pub fn release(&self, lift: &str, epoch: u64) {
        let mut held = lock(&self.held);
        if held.get(lift).is_some_and(|h| h.borrow().epoch == epoch) {
            held.remove(lift);
            lock(&self.watched).forget(lift);
        }
    }

    /// The held lift's condition changed: other processes' fleet pages show it.
    pub fn status(&self, lift: &str, error_register: Option<u8>, lift_state: Option<u8>) {
        if let Some(held) = lock(&self.held).get(lift) {
            held.send_if_modified(|h| {
                let changed = (h.error_register, h.lift_state) != (error_register, lift_state);
                h.error_register = error_register;
                h.lift_state = lift_state;
                changed
            });
        }
    }

    /// A held lift's task: its entry written (again when its status changes, when NATS is
    /// back, when another write got over it, and after a write that failed), its requests
    /// answered.
    pub(crate) async fn serve_held(
        self: Arc<Self>,
        lift: String,
        mut held: watch::Receiver<HolderEntry>,
    ) {
        let key = Key::Lift(lift.clone()).encode();
        let mut generation = self.generation.subscribe();
        let mut rpc = match self.client.subscribe(msgs::rpc_subject(&lift)).await {
            Ok(rpc) => Some(rpc),
            Err(e) => {
                tracing::warn!(%lift, error = %e, "NATS: cannot answer relayed requests");
                None
            }
        };
        let current = held.borrow_and_update().clone();
        let mut written = self.write(&key, &current, None).await;
        loop {
            // A write that failed on a live connection is tried again (after NATS was lost,
            // the generation's change writes it): within a second or two, spread.
            let retry = matches!(written, Written::Not | Written::Unsure(_)) && self.connected();
            let pause = Duration::from_millis(1_000 + rand::random::<u64>() % 1_000);
            let write_from = tokio::select! {
                changed = held.changed() => match changed {
                    Ok(()) => written,
                    Err(_) => break,
                },
                _ = tokio::time::sleep(pause), if retry => written,
                _ = generation.changed() => Written::Not,
                Some(message) = next_message(&mut rpc) => {
                    tokio::spawn(answer(self.clone(), lift.clone(), message));
                    continue;
                }
            };
            let current = held.borrow_and_update().clone();
            written = self.write(&key, &current, write_from.revision()).await;
            if let Written::Superseded(newer) = &written {
                if let Some(local) = self.local() {
                    local.taken_over(&lift, newer);
                }
                break;
            }
        }
        if let Some(mut rpc) = rpc {
            let _ = rpc.unsubscribe().await;
        }
        if let (Written::At(revision), Some(kv)) = (written, self.kv()) {
            // Only the entry written last by this holder: not a newer holder's.
            let _ = kv.delete_expect_revision(&key, Some(revision)).await;
        }
    }

    /// Write the entry: over `revision` when given (so that another process's newer entry
    /// is never overwritten), else unconditionally.
    async fn write(&self, key: &str, held: &HolderEntry, revision: Option<u64>) -> Written {
        let Some(kv) = self.kv() else {
            return Written::Not;
        };
        let Ok(value) = serde_json::to_vec(held) else {
            return Written::Not;
        };
        let value = bytes::Bytes::from(value);
        let Some(revision) = revision else {
            return match kv.put(key, value).await {
                Ok(revision) => Written::At(revision),
                Err(e) => {
                    tracing::debug!(key, error = %e, "NATS: holder entry not written");
                    Written::Not
                }
            };
        };
        match kv.update(key, value.clone(), revision).await {
            Ok(revision) => Written::At(revision),
            Err(e) if e.kind() == kv::UpdateErrorKind::WrongLastRevision => {
                let other = kv.entry(key).await.ok().flatten().and_then(|entry| {
                    (entry.operation == kv::Operation::Put)
                        .then(|| serde_json::from_slice::<HolderEntry>(&entry.value).ok())
                        .flatten()
                });
                match other {
                    Some(other) if other.newer_than(held) => Written::Superseded(other),
                    // An older connection's late write, or the entry expired: ours stands.
                    _ => match kv.put(key, value).await {
                        Ok(revision) => Written::At(revision),
                        Err(_) => Written::Not,
                    },
                }
            }
            // A timeout may or may not have written it; a sweep may have deleted the entry
            // meanwhile: written again over the revision it stood at.
            Err(e) => {
                tracing::debug!(key, error = %e, "NATS: holder entry perhaps not written");
                Written::Unsure(revision)
            }
        }
    }
}

/// What the last write of a holder entry left.
#[derive(Debug, Clone)]
enum Written {
    /// Written, at this revision.
    At(u64),
    /// Not written (no NATS, or the bucket is new): the next write is unconditional.
    Not,
    /// Perhaps not written over this revision (NATS did not answer in time).
    Unsure(u64),
    /// Another process holds a newer connection of the lift.
    Superseded(HolderEntry),
}

impl Written {
    fn revision(&self) -> Option<u64> {
        match self {
            Written::At(revision) | Written::Unsure(revision) => Some(*revision),
            _ => None,
        }
    }
}

async fn next_message(rpc: &mut Option<async_nats::Subscriber>) -> Option<async_nats::Message> {
    match rpc {
        Some(rpc) => rpc.next().await,
        None => std::future::pending().await,
    }
}

/// Answer one relayed request from the lift's connection here.
async fn answer(cluster: Arc<Cluster>, lift: String, message: async_nats::Message) {
    let Some(reply) = message.reply else {
        return;
    };
    cluster.counters.served.fetch_add(1, Ordering::Relaxed);
    let Some(local) = cluster.local() else {
        return;
    };
    let outcome = match serde_json::from_slice::<Relayed>(&message.payload) {
        Ok(Relayed::Call(call)) => match Method::from_name(&call.method) {
            Some(method) => local.call(&lift, method, call.params).await,
            None => Err(Failure::Invalid(format!("no method {:?}", call.method))),
        },
        Ok(Relayed::Hold(hold)) => {
            let objects: Vec<_> = hold.mplex.iter().map(|m| m.mplex).collect();
            let terms = Terms {
                inhibit: hold.inhibit,
                threshold: hold.threshold,
            };
            let held = local
                .subscribe(&lift, &hold.subscriber, &objects, terms)
                .await;
            // A watcher's terms last as long as its process's watch of the lift.
            if let (Ok(()), Some(process)) = (&held, hold.subscriber.process()) {
                let _ = cluster.watch_granted(&lift, process);
            }
            held.map(|()| DONE.to_owned())
        }
        Ok(Relayed::Release(release)) => {
            let objects: Option<Vec<_>> = release
                .mplex
                .map(|list| list.iter().map(|m| m.mplex).collect());
            local
                .unsubscribe(&lift, &release.subscriber, objects.as_deref())
                .await
                .map(|()| DONE.to_owned())
        }
        Ok(Relayed::Watch(watch)) => {
            let renewed = cluster.watch_granted(&lift, watch.process);
            Ok(if renewed { DONE } else { NEW_LEASE }.to_owned())
        }
        Err(e) => Err(Failure::Invalid(e.to_string())),
    };
    let Ok(body) = serde_json::to_vec(&RelayedAnswer::of(outcome)) else {
        return;
    };
    if let Err(e) = cluster.client.publish(reply, body.into()).await {
        tracing::debug!(%lift, error = %e, "NATS: answer not sent");
    }
}
