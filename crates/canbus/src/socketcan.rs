//! `socketcan://IFACE`: Linux SocketCAN through the `socketcan` crate's tokio socket.
//!
//! Compiled on every Linux build. Where the kernel has no AF_CAN (containers, CI machines) opening
//! fails with a clear error instead of a bare errno.

use crate::bus::{BusError, BusOptions, BusSender, RxFeed};

/// Whether this kernel offers AF_CAN raw sockets at all; `Err` carries the reason if not.
pub fn af_can_available() -> Result<(), String> {
    imp::af_can_available()
}

pub(crate) fn open(iface: &str, feed: RxFeed, options: &BusOptions) -> Result<BusSender, BusError> {
    imp::open(iface, feed, options)
}

#[cfg(target_os = "linux")]
pub(crate) use imp::SocketcanSender;

#[cfg(target_os = "linux")]
mod imp {
    use std::sync::Arc;

    use socketcan::tokio::CanSocket;
    use socketcan::{
        CanErrorFrame, CanFrame, EmbeddedFrame, ExtendedId, Frame as _, SocketOptions, StandardId,
    };

    use crate::bus::{BusError, BusEvent, BusOptions, BusSender, RxFeed, SenderInner};
    use crate::frame::{CanId, Frame, FrameError, FrameKind};

    /// `EAFNOSUPPORT`: the kernel has no CAN protocol family.
    const EAFNOSUPPORT: i32 = 97;
    /// `AF_CAN` and `CAN_RAW` from linux/can.h.
    const AF_CAN: i32 = 29;
    const CAN_RAW: i32 = 1;

    pub(super) fn af_can_available() -> Result<(), String> {
        use socket2::{Domain, Protocol, Socket, Type};
        Socket::new(
            Domain::from(AF_CAN),
            Type::RAW,
            Some(Protocol::from(CAN_RAW)),
        )
        .map(drop)
        .map_err(|e| format!("this kernel offers no AF_CAN raw sockets ({e})"))
    }

    fn to_socketcan(frame: &Frame) -> Option<CanFrame> {
        let id: socketcan::Id = match frame.id() {
            CanId::Standard(id) => StandardId::new(id)?.into(),
            CanId::Extended(id) => ExtendedId::new(id)?.into(),
        };
        match frame.kind() {
            FrameKind::Data => CanFrame::new(id, frame.data()),
            FrameKind::Remote => CanFrame::new_remote(id, frame.dlc().into()),
            _ => CanErrorFrame::new_error(frame.id().as_raw(), frame.data())
                .ok()
                .map(CanFrame::Error),
        }
    }

    fn from_socketcan(frame: &CanFrame) -> Result<Frame, FrameError> {
        let ours = Frame::from_raw(frame.id_word(), frame.data())?;
        match frame {
            CanFrame::Remote(r) => Frame::remote(ours.id(), r.dlc() as u8),
            _ => Ok(ours),
        }
    }

    /// The sending side of a `socketcan://` endpoint.
    #[derive(Clone)]
    pub(crate) struct SocketcanSender {
        socket: Arc<CanSocket>,
        iface: Arc<str>,
    }

    impl SocketcanSender {
        pub(crate) async fn send(&self, frame: Frame) -> Result<(), BusError> {
            let raw = to_socketcan(&frame).ok_or_else(|| {
                BusError::Unsupported(format!("cannot send {frame} on SocketCAN"))
            })?;
            self.socket
                .write_frame(raw)
                .await
                .map_err(|e| BusError::io(format!("sending on {}", self.iface), e))
        }
    }

    pub(super) fn open(
        iface: &str,
        feed: RxFeed,
        options: &BusOptions,
    ) -> Result<BusSender, BusError> {
        af_can_available().map_err(|reason| {
            BusError::io(
                format!("opening socketcan://{iface}: {reason}"),
                std::io::Error::from_raw_os_error(EAFNOSUPPORT),
            )
        })?;
        let socket = CanSocket::open(iface)
            .map_err(|e| BusError::io(format!("opening socketcan://{iface}"), e))?;
        socket
            .set_recv_own_msgs(options.receive_own)
            .map_err(|e| BusError::io("setting CAN_RAW_RECV_OWN_MSGS", e))?;
        let socket = Arc::new(socket);
        let reader = socket.clone();
        let name: Arc<str> = iface.into();
        let log_name = name.clone();
        tokio::spawn(async move {
            loop {
                let result = tokio::select! {
                    r = reader.read_frame_with_timestamp() => r,
                    _ = feed.closed() => return,
                };
                match result {
                    Ok((raw, at)) => match from_socketcan(&raw) {
                        Ok(frame) => {
                            if !feed.push(BusEvent::Frame(frame.with_timestamp(at))) {
                                return;
                            }
                        }
                        Err(e) => tracing::warn!(iface = %log_name, error = %e, "bad frame"),
                    },
                    Err(e) => {
                        let reason = format!("reading from {log_name}: {e}");
                        feed.push_link(BusEvent::LinkDown { reason }).await;
                        return;
                    }
                }
            }
        });
        Ok(BusSender::new(SenderInner::Socketcan(SocketcanSender {
            socket,
            iface: name,
        })))
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn conversions_round_trip() {
            let frames = [
                Frame::standard(0x181, &[1, 2, 3]).unwrap(),
                Frame::new(CanId::Extended(0x1234_5678), &[0; 8]).unwrap(),
                Frame::remote(CanId::Standard(0x701), 1).unwrap(),
            ];
            for f in frames {
                let back = from_socketcan(&to_socketcan(&f).unwrap()).unwrap();
                assert_eq!(back, f);
            }
        }
    }
}

#[cfg(not(target_os = "linux"))]
mod imp {
    use crate::bus::{BusError, BusOptions, BusSender, RxFeed};

    pub(super) fn af_can_available() -> Result<(), String> {
        Err("SocketCAN exists on Linux only".into())
    }

    pub(super) fn open(iface: &str, _: RxFeed, _: &BusOptions) -> Result<BusSender, BusError> {
        Err(BusError::Unsupported(format!(
            "socketcan://{iface}: SocketCAN exists on Linux only"
        )))
    }
}
