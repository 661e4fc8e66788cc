//! This process's lifts as the other processes of a cluster reach them
//! ([`cloud_cluster::Local`]): requests they relay to gateways connected here, subscriptions
//! their users and watchers hold on them, and the hand-over when a lift moves.

use std::sync::Arc;

use cloud_cluster::msgs::HolderEntry;
use cloud_types::subscriptions::{Subscriber, Terms};
use futures_util::future::BoxFuture;
use nxg::mplex::Mplex;
use nxg::msg::Method;
use nxg::portal::Failure;
use serde_json::value::RawValue;

use super::subscriptions::Subscriptions;
use super::Registry;

/// The registry and the subscriptions of this process, for the cluster.
pub struct LocalLifts {
    registry: Arc<Registry>,
    subscriptions: Arc<Subscriptions>,
}

impl LocalLifts {
    /// The lifts of `registry` with their `subscriptions`.
    pub fn new(registry: Arc<Registry>, subscriptions: Arc<Subscriptions>) -> LocalLifts {
        LocalLifts {
            registry,
            subscriptions,
        }
    }
}

impl cloud_cluster::Local for LocalLifts {
    fn taken_over(&self, lift: &str, newer: &HolderEntry) -> bool {
        self.registry.taken_over(lift, newer)
    }

    fn call<'a>(
        &'a self,
        lift: &'a str,
        method: Method,
        params: Option<Box<RawValue>>,
    ) -> BoxFuture<'a, Result<String, Failure>> {
        Box::pin(self.registry.send_local(lift, method, params))
    }

    fn subscribe<'a>(
        &'a self,
        lift: &'a str,
        subscriber: &'a Subscriber,
        objects: &'a [Mplex],
        terms: Terms,
    ) -> BoxFuture<'a, Result<(), Failure>> {
        Box::pin(
            self.subscriptions
                .subscribe_here(lift, subscriber, objects, terms),
        )
    }

    fn unsubscribe<'a>(
        &'a self,
        lift: &'a str,
        subscriber: &'a Subscriber,
        objects: Option<&'a [Mplex]>,
    ) -> BoxFuture<'a, Result<(), Failure>> {
        Box::pin(
            self.subscriptions
                .unsubscribe_here(lift, subscriber, objects),
        )
    }

    fn unsubscribe_process<'a>(&'a self, lift: &'a str, process: u64) -> BoxFuture<'a, ()> {
        Box::pin(self.subscriptions.unsubscribe_process(lift, process))
    }

    fn moved(&self, lift: &str) {
        self.subscriptions.clone().moved(lift);
    }

    fn process(&self) -> u64 {
        self.subscriptions.process()
    }
}
