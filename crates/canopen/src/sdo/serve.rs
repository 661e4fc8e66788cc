//! The SDO server as a task (feature `tokio`): a dictionary served on a [`canbus::Bus`] on
//! every SDO server channel it configures (CiA 301 §7.5.2.33), the sans-IO
//! [`super::server::ServerChannels`] driven by frames and time.

use std::sync::PoisonError;
use std::time::Instant;

use canbus::Bus;
use tokio::task::JoinHandle;

use crate::od::SharedDictionary;
use crate::sdo::server::{server_channels, ServerChannels, ServerConfig};
use crate::wake::sleep_until;

/// Serve `od` on `bus` as node `node_id` on every SDO server channel, until the bus closes.
pub fn serve_sdo(
    bus: Bus,
    od: SharedDictionary,
    node_id: u8,
    config: ServerConfig,
) -> JoinHandle<()> {
    let (sender, mut receiver) = bus.split();
    let mut servers = ServerChannels::new(
        server_channels(&od.lock().unwrap_or_else(PoisonError::into_inner), node_id),
        &config,
    );
    receiver.set_filters(&servers.filters());
    tokio::spawn(async move {
        let mut out = Vec::new();
        loop {
            let received = tokio::select! {
                f = receiver.recv_frame() => match f {
                    Some(f) => Some(f),
                    None => return,
                },
                _ = sleep_until(servers.poll_timeout()) => None,
            };
            let now = Instant::now();
            match &received {
                Some(f) => {
                    let mut od = od.lock().unwrap_or_else(PoisonError::into_inner);
                    servers.handle(&mut od, f, now, &mut out);
                }
                None => servers.handle_timeout(now, &mut out),
            }
            for f in out.drain(..) {
                if sender.send(f).await.is_err() {
                    return;
                }
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::od::{Access, Object, ObjectDictionary, Variable};
    use crate::types::{DataType, Value};
    use canbus::CanId;

    #[test]
    fn server_channels_from_the_dictionary() {
        let mut od = ObjectDictionary::new();
        assert_eq!(
            server_channels(&od, 3),
            vec![(CanId::Standard(0x603), CanId::Standard(0x583))]
        );
        let u32v = |v: u32| {
            Variable::new("COB-ID", DataType::Unsigned32, Access::Ro)
                .with_value(Value::Uint(v.into()))
        };
        od.insert(Object::composite(
            0x1201,
            "SDO server 2",
            crate::od::ObjectCode::Record,
            [(1, u32v(0x640)), (2, u32v(0x5C0))],
        ));
        od.insert(Object::composite(
            0x1202,
            "SDO server 3",
            crate::od::ObjectCode::Record,
            [(1, u32v(0x8000_0641)), (2, u32v(0x5C1))],
        ));
        assert_eq!(
            server_channels(&od, 3),
            vec![
                (CanId::Standard(0x603), CanId::Standard(0x583)),
                (CanId::Standard(0x640), CanId::Standard(0x5C0))
            ]
        );
    }
}
