//! How operators reach a gateway's connection: the requests waiting for it (bounded) and the
//! order to close (a newer connection of the lift, here or on another process of a cluster).
//!
//! One small allocation per connection that holds nothing while nobody writes: a tokio channel
//! allocates its first block of slots when it is made, and with thousands of idle gateways
//! that block was most of what reaching one cost (docs/BENCHMARKS.md §Where an idle gateway
//! connection's memory goes).

use std::collections::VecDeque;
use std::sync::{Mutex, PoisonError};

use tokio::sync::Notify;

/// A connection's mailbox; the registry holds one end (`Arc`), the connection the other.
pub(crate) struct Mailbox<T> {
    inbox: Mutex<Inbox<T>>,
    ready: Notify,
    capacity: usize,
}

struct Inbox<T> {
    items: VecDeque<T>,
    close: bool,
    ended: bool,
}

/// What the connection takes next.
#[derive(Debug, PartialEq)]
pub(crate) enum Letter<T> {
    /// A request.
    Item(T),
    /// Close the connection.
    Close,
}

/// Why a request was not posted.
#[derive(Debug, PartialEq)]
pub(crate) enum Refused<T> {
    /// `capacity` requests wait already.
    Full(T),
    /// The connection has ended.
    Ended(T),
}

impl<T> Mailbox<T> {
    /// A mailbox that holds at most `capacity` waiting requests.
    pub(crate) fn new(capacity: usize) -> Mailbox<T> {
        Mailbox {
            inbox: Mutex::new(Inbox {
                items: VecDeque::new(),
                close: false,
                ended: false,
            }),
            ready: Notify::new(),
            capacity: capacity.max(1),
        }
    }

    fn inbox(&self) -> std::sync::MutexGuard<'_, Inbox<T>> {
        self.inbox.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Leave a request for the connection, without waiting.
    pub(crate) fn post(&self, item: T) -> Result<(), Refused<T>> {
        {
            let mut inbox = self.inbox();
            if inbox.ended {
                return Err(Refused::Ended(item));
            }
            if inbox.items.len() >= self.capacity {
                return Err(Refused::Full(item));
            }
            inbox.items.push_back(item);
        }
        self.ready.notify_one();
        Ok(())
    }

    /// Tell the connection to close (before the requests still waiting).
    pub(crate) fn close(&self) {
        self.inbox().close = true;
        self.ready.notify_one();
    }

    /// The next letter, once there is one. Cancel-safe: a letter is taken only when returned.
    pub(crate) async fn next(&self) -> Letter<T> {
        loop {
            if let Some(letter) = self.take() {
                return letter;
            }
            // A notification given while nobody waited is kept for the next wait.
            self.ready.notified().await;
        }
    }

    /// A request waiting now, if any and no order to close came (that one `next` gives): the
    /// connection takes the requests that came together at once and sends them in one write.
    pub(crate) fn try_item(&self) -> Option<T> {
        match self.take()? {
            Letter::Item(item) => Some(item),
            Letter::Close => None,
        }
    }

    /// The order to close (kept) or else the first request waiting.
    fn take(&self) -> Option<Letter<T>> {
        let mut inbox = self.inbox();
        if inbox.close {
            return Some(Letter::Close);
        }
        let item = inbox.items.pop_front()?;
        if inbox.items.is_empty() {
            // A burst's queue is not kept.
            inbox.items = VecDeque::new();
        }
        Some(Letter::Item(item))
    }

    /// The connection is gone: requests waiting are dropped (their senders learn it), new ones
    /// are refused.
    pub(crate) fn end(&self) {
        let items = {
            let mut inbox = self.inbox();
            inbox.ended = true;
            std::mem::take(&mut inbox.items)
        };
        drop(items);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::time::Duration;

    #[tokio::test]
    async fn requests_come_in_order_up_to_the_capacity() {
        let mailbox = Mailbox::new(2);
        assert_eq!(mailbox.post(1), Ok(()));
        assert_eq!(mailbox.post(2), Ok(()));
        assert_eq!(mailbox.post(3), Err(Refused::Full(3)));
        assert_eq!(mailbox.next().await, Letter::Item(1));
        assert_eq!(mailbox.post(3), Ok(()));
        assert_eq!(mailbox.next().await, Letter::Item(2));
        assert_eq!(mailbox.next().await, Letter::Item(3));
        assert_eq!(
            mailbox.inbox().items.capacity(),
            0,
            "an empty queue holds no memory"
        );
    }

    #[tokio::test]
    async fn a_waiting_connection_is_woken_and_close_comes_first() {
        let mailbox = Arc::new(Mailbox::new(4));
        let waiting = tokio::spawn({
            let mailbox = mailbox.clone();
            async move { mailbox.next().await }
        });
        tokio::time::sleep(Duration::from_millis(20)).await;
        mailbox.post("get").unwrap();
        assert_eq!(waiting.await.unwrap(), Letter::Item("get"));
        mailbox.post("put").unwrap();
        mailbox.close();
        assert_eq!(mailbox.next().await, Letter::Close);
    }

    #[test]
    fn what_came_together_is_taken_at_once_but_never_past_an_order_to_close() {
        let mailbox = Mailbox::new(4);
        assert_eq!(mailbox.try_item(), None::<u8>);
        mailbox.post(1).unwrap();
        mailbox.post(2).unwrap();
        assert_eq!(mailbox.try_item(), Some(1));
        mailbox.close();
        assert_eq!(mailbox.try_item(), None, "the close is not passed over");
        assert_eq!(mailbox.take(), Some(Letter::Close), "and is still there");
    }

    #[tokio::test]
    async fn an_abandoned_wait_loses_nothing() {
        let mailbox = Mailbox::new(4);
        // A select! that took another branch drops the wait.
        let timed_out = tokio::time::timeout(Duration::from_millis(10), mailbox.next()).await;
        assert!(timed_out.is_err());
        mailbox.post(7).unwrap();
        assert_eq!(mailbox.next().await, Letter::Item(7));
    }

    #[tokio::test]
    async fn an_ended_connection_drops_and_refuses_requests() {
        let mailbox = Mailbox::new(4);
        let (reply, answer) = tokio::sync::oneshot::channel::<()>();
        mailbox.post(reply).unwrap();
        mailbox.end();
        assert!(
            answer.await.is_err(),
            "the waiting request's sender learns it is gone"
        );
        let (reply, _answer) = tokio::sync::oneshot::channel::<()>();
        assert!(matches!(mailbox.post(reply), Err(Refused::Ended(_))));
    }
}
