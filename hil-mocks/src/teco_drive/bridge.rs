//! An in-process bus served on another CAN transport (a SocketCAN interface, e.g. `vcan0`): the
//! mock drives on the bus exchange frames with whatever else is on that interface, as drives on
//! a wire would. Frames go both ways, one at a time, in order; error frames the transport reports
//! without ending the connection are skipped (the drives have no controller to tell).

use amr_drivers::canopen::error::TransportError;
use amr_drivers::canopen::transport::CanTransport;
use amr_drivers::canopen::transport::in_process::BusPort;

/// Forward frames between `port` (a port of the drives' in-process bus) and `transport` until
/// either fails; returns why. Both `recv`s are cancel-safe (the trait requires it), so no frame is
/// lost to the `select!`.
pub async fn bridge<T: CanTransport>(mut port: BusPort, mut transport: T) -> TransportError {
    // Bounded by its inputs: each pass forwards one frame or ends.
    loop {
        tokio::select! {
            from_bus = port.recv() => match from_bus {
                Ok(f) => {
                    if let Err(e) = transport.send(f).await {
                        return e;
                    }
                }
                Err(e) => return e,
            },
            from_wire = transport.recv() => match from_wire {
                Ok(f) => port.send_now(f),
                Err(TransportError::ErrorFrame { .. } | TransportError::BusOff) => {}
                Err(e) => return e,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use std::time::Duration;

    use amr_drivers::canopen::frame::CanFrame;
    use amr_drivers::canopen::transport::in_process::InProcessBus;

    use super::*;

    #[tokio::test(start_paused = true)]
    async fn frames_cross_the_bridge_both_ways_in_order() {
        let (drives, wire) = (InProcessBus::default(), InProcessBus::default());
        let mut drive = drives.port();
        let mut peer = wire.port();
        let task = tokio::spawn(bridge(drives.port(), wire.port()));
        for i in 0..5u8 {
            drive.send(CanFrame::new(0x181, &[i]).unwrap()).await.unwrap();
            peer.send(CanFrame::new(0x201, &[i]).unwrap()).await.unwrap();
        }
        for i in 0..5u8 {
            let f = tokio::time::timeout(Duration::from_secs(1), peer.recv()).await.unwrap().unwrap();
            assert_eq!((f.id(), f.data()), (0x181, &[i][..]));
            let f = tokio::time::timeout(Duration::from_secs(1), drive.recv()).await.unwrap().unwrap();
            assert_eq!((f.id(), f.data()), (0x201, &[i][..]));
        }
        task.abort();
    }
}
