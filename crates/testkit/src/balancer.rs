//! A TCP load balancer in front of several portal processes, as a cluster is run
//! (docs/CLUSTER.md): each new connection goes to the backend the test points at, or to the
//! next one that accepts when that one does not. Stopped when dropped.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;

/// A running balancer.
pub struct Balancer {
    addr: SocketAddr,
    target: Arc<AtomicUsize>,
    /// Whether a connection the target refuses goes to the next backend.
    fallback: Arc<AtomicBool>,
    task: JoinHandle<()>,
}

impl Balancer {
    /// Listen on a loopback port in front of `backends` (new connections go to the first).
    pub async fn start(backends: Vec<SocketAddr>) -> Balancer {
        let listener = TcpListener::bind("127.0.0.1:0")
            .await
            .expect("a loopback port");
        let addr = listener.local_addr().expect("its address");
        let target = Arc::new(AtomicUsize::new(0));
        let fallback = Arc::new(AtomicBool::new(true));
        let backends = Arc::new(backends);
        let (t, f) = (target.clone(), fallback.clone());
        let task = tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                let (backends, first) = (backends.clone(), t.load(Ordering::Relaxed));
                let tried = match f.load(Ordering::Relaxed) {
                    true => backends.len(),
                    false => 1,
                };
                tokio::spawn(async move {
                    for i in 0..tried {
                        let backend = backends[(first + i) % backends.len()];
                        if let Ok(server) = TcpStream::connect(backend).await {
                            let (mut client, mut server) = (client, server);
                            let _ = tokio::io::copy_bidirectional(&mut client, &mut server).await;
                            return;
                        }
                    }
                });
            }
        });
        Balancer {
            addr,
            target,
            fallback,
            task,
        }
    }

    /// Where gateways connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Send new connections to backend `index` (or the next that accepts).
    pub fn route_to(&self, index: usize) {
        self.target.store(index, Ordering::Relaxed);
        self.fallback.store(true, Ordering::Relaxed);
    }

    /// Send new connections to backend `index` and nowhere else: while it is down, gateways
    /// find the portal unreachable.
    pub fn route_only_to(&self, index: usize) {
        self.target.store(index, Ordering::Relaxed);
        self.fallback.store(false, Ordering::Relaxed);
    }
}

impl Drop for Balancer {
    fn drop(&mut self) {
        self.task.abort();
    }
}
