//! One connection to the portal: TCP, TLS, the WebSocket upgrade with the `cloud, lift`
//! subprotocols (NXg SW003 §5.1), then the [`Session`] driven by messages, job results,
//! subscription values, pings and its own timer.

use std::time::{Duration, Instant};

use futures_util::stream::FuturesUnordered;
use futures_util::{FutureExt, SinkExt, StreamExt};
use nxg::gateway::{Job, JobId, JobResult, Output, Phase, Session};

use tokio::sync::mpsc;
use tokio_rustls::TlsConnector;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{self, Message};

use crate::access::Objects;
use crate::feed::{Feed, Update};
use crate::Shared;

/// The subprotocols the gateway offers; the portal must select one of them.
pub const SUBPROTOCOLS: [&str; 2] = ["cloud", "lift"];

/// How a connection ended.
#[derive(Debug)]
pub struct Ended {
    /// Whether CONNACK had come (the connection was in service).
    pub served: bool,
    /// Why it ended.
    pub cause: String,
    /// The gateway is shutting down.
    pub shutdown: bool,
}

fn ended(served: bool, cause: impl Into<String>) -> Ended {
    Ended {
        served,
        cause: cause.into(),
        shutdown: false,
    }
}

/// Connect once and serve until the connection ends.
pub async fn run(shared: &Shared, shutdown: &mut tokio::sync::watch::Receiver<bool>) -> Ended {
    let cloud = &shared.config.cloud;
    let timeout = Duration::from_secs(cloud.connect_timeout_s.max(1));
    let mut request = match cloud.url.as_str().into_client_request() {
        Ok(r) => r,
        Err(e) => return ended(false, format!("cloud.url: {e}")),
    };
    let uri = request.uri().clone();
    let Some(host) = uri.host().map(|h| h.trim_matches(['[', ']']).to_owned()) else {
        return ended(false, "cloud.url has no host");
    };
    let port = uri.port_u16().unwrap_or(443);
    request.headers_mut().insert(
        "Sec-WebSocket-Protocol",
        HeaderValue::from_static("cloud, lift"),
    );
    if let Some(origin) = &cloud.origin {
        match HeaderValue::from_str(origin) {
            Ok(v) => {
                request.headers_mut().insert("Origin", v);
            }
            Err(_) => return ended(false, "cloud.origin is not a valid header value"),
        }
    }
    let proxies = match &cloud.proxy {
        Some(url) => tls::reach::Proxies::Configured(url.clone()),
        None => tls::reach::Proxies::Environment,
    };
    let proxy = match proxies.for_server(&host, port) {
        Ok(proxy) => proxy,
        Err(e) => return ended(false, format!("cloud.proxy or HTTPS_PROXY: {e}")),
    };
    let connecting = tls::reach::connect(&host, port, cloud.source_address, proxy.as_ref());
    let tcp = match tokio::time::timeout(timeout, connecting).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return ended(false, format!("TCP {host}:{port}: {e}")),
        Err(_) => {
            return ended(
                false,
                format!("TCP {host}:{port}: no answer in {timeout:?}"),
            )
        }
    };
    let _ = tcp.set_nodelay(true);
    let local = tcp.local_addr().ok();
    let server_name = match rustls::pki_types::ServerName::try_from(host.clone()) {
        Ok(n) => n,
        Err(e) => return ended(false, format!("{host}: {e}")),
    };
    let tls = TlsConnector::from(
        shared
            .tls
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone(),
    );
    let tls = match tokio::time::timeout(timeout, tls.connect(server_name, tcp)).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return ended(false, format!("TLS with {host}: {}", refusal(&e))),
        Err(_) => {
            return ended(
                false,
                format!("TLS with {host}: no handshake in {timeout:?}"),
            )
        }
    };
    let ws_config = WebSocketConfig::default()
        .max_message_size(Some(shared.config.limits.max_message_bytes))
        .max_frame_size(Some(shared.config.limits.max_message_bytes))
        .read_buffer_size(8 * 1024)
        // Answers collect here until the loop has nothing else ready (then it flushes) or
        // 16 KiB are waiting: one TLS write for many answers instead of a syscall each.
        .write_buffer_size(16 * 1024);
    let handshake = tokio_tungstenite::client_async_with_config(request, tls, Some(ws_config));
    let (mut ws, response) = match tokio::time::timeout(timeout, handshake).await {
        Ok(Ok(pair)) => pair,
        Ok(Err(tungstenite::Error::Io(e))) => {
            return ended(false, format!("TLS with {host}: {}", refusal(&e)))
        }
        Ok(Err(e)) => return ended(false, format!("WebSocket upgrade refused: {e}")),
        Err(_) => return ended(false, "WebSocket upgrade: no answer in time"),
    };
    let selected = response
        .headers()
        .get("Sec-WebSocket-Protocol")
        .and_then(|v| v.to_str().ok())
        .map(str::trim)
        .unwrap_or("");
    if !SUBPROTOCOLS.contains(&selected) {
        let _ = ws.close(None).await;
        return ended(
            false,
            format!("the portal selected neither cloud nor lift ({selected:?})"),
        );
    }
    let local = local.map_or_else(String::new, |a| a.to_string());
    tracing::info!(url = %cloud.url, %local, subprotocol = selected, "connected; sending CONNECT");
    serve(shared, ws, shutdown).await
}

/// What woke the connection's loop.
enum Wake {
    /// The portal sent something (or the stream ended).
    Message(Option<Result<Message, tokio_tungstenite::tungstenite::Error>>),
    /// A job finished.
    Job(JobId, JobResult),
    /// A subscribed value changed.
    Update(Update),
    /// The session's timer.
    Timer,
    /// Bus events wait for the portal.
    Events,
    /// Time for a WebSocket ping.
    Ping,
    /// The gateway is shutting down.
    Shutdown,
}

/// A job that did not finish at once (an SDO transfer, the token written to disk): polled by
/// the connection's own task, so that its wake-ups and its result need no task and no channel
/// of their own.
type Running = std::pin::Pin<Box<dyn std::future::Future<Output = (JobId, JobResult)> + Send>>;

/// What [`start_job`] made of a job.
enum Started {
    /// Answered at once (the local dictionary).
    Done(JobResult),
    /// To be polled until it has its result.
    Running(Running),
}

/// The connection's jobs in flight. Those still running when the connection ends finish in a
/// task of their own, as a request sent to the bus does: a write the operator asked for is
/// made and logged, not cut off mid-way (the SDO client would abort the transfer on the bus,
/// CiA 301 §7.2.4.3.17, and the write would not be made).
#[derive(Default)]
struct InFlight(FuturesUnordered<Running>);

impl Drop for InFlight {
    fn drop(&mut self) {
        let mut rest = std::mem::take(&mut self.0);
        if rest.is_empty() {
            return;
        }
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            runtime.spawn(async move { while rest.next().await.is_some() {} });
        }
    }
}

/// What the loop waits on, borrowed for one wait.
struct Sources<'a, S> {
    ws: &'a mut tokio_tungstenite::WebSocketStream<S>,
    jobs: &'a mut FuturesUnordered<Running>,
    feed: &'a mut mpsc::Receiver<Update>,
    shared: &'a Shared,
    ping: &'a mut tokio::time::Interval,
    shutdown: &'a mut tokio::sync::watch::Receiver<bool>,
}

impl<S> Sources<'_, S>
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    /// The next thing to act on. Every branch is cancel-safe: the loop polls this once without
    /// waiting, and drops it to flush what it wrote when nothing is ready.
    async fn next(&mut self, deadline: Option<Instant>) -> Wake {
        tokio::select! {
            message = self.ws.next() => Wake::Message(message),
            Some((id, result)) = self.jobs.next(), if !self.jobs.is_empty() => Wake::Job(id, result),
            Some(update) = self.feed.recv() => Wake::Update(update),
            _ = canopen::wake::sleep_until(deadline) => Wake::Timer,
            _ = self.shared.events_ready.notified() => Wake::Events,
            _ = self.ping.tick() => Wake::Ping,
            _ = self.shutdown.changed() => Wake::Shutdown,
        }
    }

    /// What is ready now; otherwise flush what was written (when `unflushed`, which is then
    /// cleared) and wait. The jobs are polled here too, so the answers of several SDO channels
    /// that came in one read from the bus are all written before the one flush.
    async fn wait(
        &mut self,
        deadline: Option<Instant>,
        unflushed: &mut bool,
    ) -> Result<Wake, tokio_tungstenite::tungstenite::Error> {
        if let Some(wake) = FutureExt::now_or_never(self.next(deadline)) {
            return Ok(wake);
        }
        if *unflushed {
            self.ws.flush().await?;
            *unflushed = false;
        }
        Ok(self.next(deadline).await)
    }
}

async fn serve<S>(
    shared: &Shared,
    mut ws: tokio_tungstenite::WebSocketStream<S>,
    shutdown: &mut tokio::sync::watch::Receiver<bool>,
) -> Ended
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    let now = Instant::now();
    let mut session = Session::new(
        shared.config.settings(),
        shared.context.clone(),
        shared.token.load(),
        now,
    );
    let mut running = InFlight::default();
    let (feed_tx, mut feed_rx) = mpsc::channel::<Update>(1024);
    let feed: Feed = shared.feed(feed_tx).await;
    let mut ping = tokio::time::interval(Duration::from_secs(shared.config.cloud.ping_s.max(1)));
    ping.tick().await;
    let mut outputs = vec![session.connect()];
    let max_jobs = shared.config.limits.max_in_flight.max(1);
    let mut jobs = std::collections::VecDeque::new();
    let mut served = false;
    // Answers written since the last flush: they go out together, in one TLS write, once
    // nothing else is ready (a portal with 32 requests in flight gets one write, not 32).
    let mut unflushed = false;
    loop {
        // A lock-out state is on disk before the answer that follows from it goes out: a gateway
        // stopped or killed right after answering still counts the failure.
        for output in &outputs {
            if let Output::Lockout(state) = output {
                let (store, state) = (shared.lockout.clone(), *state);
                let stored = tokio::task::spawn_blocking(move || store.store(&state)).await;
                if let Ok(Err(e)) = stored {
                    tracing::error!(error = %e, "elevation lock-out not stored");
                }
            }
        }
        for output in outputs.drain(..) {
            match output {
                Output::Send(text) => {
                    if let Err(e) = ws.feed(Message::Text(text.into())).await {
                        return ended(served, format!("sending failed: {e}"));
                    }
                    unflushed = true;
                }
                Output::Close(reason) => {
                    let _ = ws.close(None).await;
                    return ended(served, reason.to_string());
                }
                Output::Start(id, job) => jobs.push_back((id, job)),
                Output::Watch(target, index, sub) => feed.watch(target, index, sub),
                Output::Unwatch(target, index, sub) => feed.unwatch(target, index, sub),
                // Stored above, before anything of this batch was sent.
                Output::Lockout(_) => {}
            }
        }
        // Jobs run at most `max_in_flight` at once (with the subscriptions' first reads there
        // can be more jobs than requests); the rest wait here as small values, not as futures.
        // A job that is done at once (the local dictionary) is answered in this round.
        while running.0.len() < max_jobs {
            let Some((id, job)) = jobs.pop_front() else {
                break;
            };
            match start_job(shared, id, job) {
                Started::Done(result) => {
                    outputs.extend(session.handle_job(id, result, Instant::now()))
                }
                Started::Running(job) => running.0.push(job),
            }
        }
        if !outputs.is_empty() {
            continue;
        }
        // What a burst of subscriptions queued is not kept for the rest of the connection.
        if jobs.is_empty() && jobs.capacity() > 64 {
            jobs.shrink_to(64);
        }
        if outputs.capacity() > 64 {
            outputs.shrink_to(64);
        }
        if !served {
            if let Phase::Connected(api) = session.phase() {
                served = true;
                shared.online.send_replace(true);
                if let Some(metrics) = &shared.metrics {
                    metrics.connected.set(1);
                    metrics.connections.inc();
                }
                tracing::info!(api, "CONNACK: serving the portal");
            }
        }
        let mut sources = Sources {
            ws: &mut ws,
            jobs: &mut running.0,
            feed: &mut feed_rx,
            shared,
            ping: &mut ping,
            shutdown,
        };
        let wake = match sources.wait(session.poll_timeout(), &mut unflushed).await {
            Ok(wake) => wake,
            Err(e) => return ended(served, format!("sending failed: {e}")),
        };
        outputs = match wake {
            Wake::Message(message) => {
                let now = Instant::now();
                match message {
                    Some(Ok(Message::Text(text))) => session.handle_text(text.as_str(), now),
                    // Liveness is the portal's NXg messages alone (NXg §5.3): a proxy may
                    // answer pings for a portal that is gone.
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => Vec::new(),
                    Some(Ok(Message::Binary(_))) => {
                        tracing::warn!("binary message ignored: the connector speaks JSON text");
                        Vec::new()
                    }
                    Some(Ok(Message::Close(frame))) => {
                        let why = frame
                            .map(|f| format!("{} {}", u16::from(f.code), f.reason))
                            .unwrap_or_default();
                        return ended(served, format!("portal closed the connection {why}"));
                    }
                    Some(Ok(Message::Frame(_))) => Vec::new(),
                    Some(Err(e)) => {
                        let cause = format!("connection failed: {e}");
                        if matches!(e, tokio_tungstenite::tungstenite::Error::Capacity(_)) {
                            let frame = CloseFrame {
                                code: CloseCode::Size,
                                reason: "message too big".into(),
                            };
                            let _ = ws.close(Some(frame)).await;
                        }
                        return ended(served, cause);
                    }
                    None => return ended(served, "portal went away"),
                }
            }
            Wake::Job(id, result) => session.handle_job(id, result, Instant::now()),
            Wake::Update((target, index, sub, bytes)) => {
                let out = session.handle_bytes(target, index, sub, &bytes, Instant::now());
                if let Some(metrics) = &shared.metrics {
                    let pushed = out.iter().filter(|o| matches!(o, Output::Send(_))).count();
                    metrics.notifications.inc_by(pushed as u64);
                }
                out
            }
            Wake::Timer => session.handle_timeout(Instant::now()),
            Wake::Events => session.deliver_events(),
            Wake::Ping => {
                if let Err(e) = ws.send(Message::Ping(Vec::new().into())).await {
                    return ended(served, format!("ping failed: {e}"));
                }
                unflushed = false;
                Vec::new()
            }
            Wake::Shutdown => {
                let frame = CloseFrame {
                    code: CloseCode::Away,
                    reason: "gateway shutting down".into(),
                };
                let _ = ws.close(Some(frame)).await;
                return Ended {
                    served,
                    cause: "shutdown".into(),
                    shutdown: true,
                };
            }
        };
    }
}

/// Start `job`: its result now when it has it at once (a read or write of the local
/// dictionary), or the job to poll until it has (SDO, the token on disk).
fn start_job(shared: &Shared, id: JobId, job: Job) -> Started {
    match job {
        Job::StoreToken(token) => {
            let store = shared.token.clone();
            let stored = tokio::task::spawn_blocking(move || match store.store(&token) {
                Ok(()) => {
                    tracing::info!(path = %store.path().display(), "cloud token stored");
                    JobResult::Done
                }
                Err(e) => {
                    tracing::error!(path = %store.path().display(), error = %e, "cloud token not stored");
                    JobResult::Failed(canopen::sdo::abort::AbortCode::CANNOT_STORE)
                }
            });
            Started::Running(Box::pin(async move {
                let result = stored.await.unwrap_or(JobResult::Failed(
                    canopen::sdo::abort::AbortCode::CANNOT_STORE,
                ));
                (id, result)
            }))
        }
        job => {
            let objects = shared.objects.clone();
            let interlock = shared.interlock.clone();
            let mut run = Box::pin(async move {
                if let (
                    Job::Write {
                        target, index, sub, ..
                    },
                    Some(lock),
                ) = (&job, &interlock)
                {
                    if let Err(code) = lock.check(&objects, *target, *index, *sub).await {
                        return JobResult::Failed(code);
                    }
                }
                objects.run(job).await
            });
            let metrics = shared.metrics.clone();
            let ok = |result: &JobResult| !matches!(result, JobResult::Failed(_));
            // The local dictionary answers at once: in this round, with no wake-up.
            if matches!(shared.objects, Objects::Local { .. }) {
                if let Some(result) = FutureExt::now_or_never(run.as_mut()) {
                    if let Some(metrics) = &metrics {
                        metrics.access(ok(&result), None);
                    }
                    return Started::Done(result);
                }
            }
            let started = Instant::now();
            Started::Running(Box::pin(async move {
                // A job that panics (a bug) fails its request, not the connection that polls it.
                let result = std::panic::AssertUnwindSafe(run)
                    .catch_unwind()
                    .await
                    .unwrap_or(JobResult::Failed(canopen::sdo::abort::AbortCode::GENERAL));
                if let Some(metrics) = &metrics {
                    metrics.access(ok(&result), Some(started.elapsed()));
                }
                (id, result)
            }))
        }
    }
}

/// A TLS failure as the person reading the gateway's log needs it. Under TLS 1.3 the portal
/// judges the client certificate after the gateway's side of the handshake is done, so its
/// refusal arrives as an alert at the first read (the WebSocket upgrade): named here for what it
/// means rather than as the alert or the end of stream it shows up as.
fn refusal(e: &std::io::Error) -> String {
    use rustls::AlertDescription as Alert;
    let alert = e
        .get_ref()
        .and_then(|inner| inner.downcast_ref::<rustls::Error>())
        .and_then(|inner| match inner {
            rustls::Error::AlertReceived(alert) => Some(*alert),
            _ => None,
        });
    match alert {
        Some(Alert::CertificateRequired) => format!(
            "the portal requires a client certificate (mutual TLS): set [cloud] client_cert and \
             client_key ({e})"
        ),
        Some(
            Alert::BadCertificate
            | Alert::UnknownCA
            | Alert::CertificateUnknown
            | Alert::CertificateExpired
            | Alert::CertificateRevoked
            | Alert::UnsupportedCertificate
            | Alert::AccessDenied,
        ) => format!(
            "the portal refused the gateway's client certificate ([cloud] client_cert: not \
             signed by the CA the portal trusts, expired or revoked; {e})"
        ),
        _ => e.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn alert(description: rustls::AlertDescription) -> std::io::Error {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            rustls::Error::AlertReceived(description),
        )
    }

    #[tokio::test]
    async fn jobs_in_flight_finish_after_their_connection_ends() {
        let (answer, answered) = tokio::sync::oneshot::channel::<()>();
        let (done, finished) = tokio::sync::oneshot::channel();
        let running = InFlight::default();
        running.0.push(Box::pin(async move {
            // The node's answer comes after the connection is gone.
            let _ = answered.await;
            let _ = done.send(());
            (7, JobResult::Done)
        }));
        drop(running);
        answer.send(()).unwrap();
        tokio::time::timeout(Duration::from_secs(5), finished)
            .await
            .expect("the job ran on after its connection ended")
            .unwrap();
    }

    #[test]
    fn a_portals_refusal_of_the_client_certificate_is_named() {
        let required = refusal(&alert(rustls::AlertDescription::CertificateRequired));
        assert!(
            required.starts_with("the portal requires a client certificate (mutual TLS): set [cloud] client_cert and client_key"),
            "{required}"
        );
        let refused = refusal(&alert(rustls::AlertDescription::UnknownCA));
        assert!(
            refused.starts_with("the portal refused the gateway's client certificate"),
            "{refused}"
        );
        let other = std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "gone");
        assert_eq!(refusal(&other), "gone");
    }
}
