//! The in-memory bus of the tests: what the client sends goes to a
//! [`Peer`] (a scripted responder, or a whole virtual board), what the peer
//! produces comes back from [`Bus::recv`]. Nothing is timed: when the peer
//! has nothing to say, `recv` gives the peer an idle turn
//! ([`Peer::idle`]) and, if that produced nothing either, sleeps a little
//! (at most 1 ms) and reports no frame, so the client's own timeouts run.

use std::collections::VecDeque;
use std::time::Duration;

use perpend_can::Frame;

use super::{Bus, BusError};

/// The other side of a [`FakeBus`].
pub trait Peer: Send {
    /// A frame the client sent; push answers to `out`.
    fn frame(&mut self, f: &Frame, out: &mut Vec<Frame>);
    /// An idle turn (a board samples and polls here); push frames to `out`.
    fn idle(&mut self, _out: &mut Vec<Frame>) {}
}

/// A peer made of a closure over each received frame.
pub struct FnPeer<F>(pub F);

impl<F: FnMut(&Frame, &mut Vec<Frame>) + Send> Peer for FnPeer<F> {
    fn frame(&mut self, f: &Frame, out: &mut Vec<Frame>) {
        (self.0)(f, out);
    }
}

/// The in-memory bus.
pub struct FakeBus<P: Peer> {
    /// The peer.
    pub peer: P,
    /// Frames waiting to be received.
    pub inbox: VecDeque<Frame>,
    /// Every frame the client sent.
    pub sent: Vec<Frame>,
    /// When set, `send` fails as a closed link would.
    pub closed: bool,
}

impl<P: Peer> FakeBus<P> {
    /// A bus to `peer`.
    pub fn new(peer: P) -> Self {
        Self {
            peer,
            inbox: VecDeque::new(),
            sent: Vec::new(),
            closed: false,
        }
    }
}

impl<P: Peer> Bus for FakeBus<P> {
    fn send(&mut self, f: &Frame) -> Result<(), BusError> {
        if self.closed {
            return Err(BusError::Closed { bus: "fake".into() });
        }
        self.sent.push(*f);
        let mut out = Vec::new();
        self.peer.frame(f, &mut out);
        self.inbox.extend(out);
        Ok(())
    }

    fn recv(&mut self, timeout: Duration) -> Result<Option<Frame>, BusError> {
        if self.inbox.is_empty() {
            let mut out = Vec::new();
            self.peer.idle(&mut out);
            self.inbox.extend(out);
        }
        match self.inbox.pop_front() {
            Some(f) => Ok(Some(f)),
            None => {
                std::thread::sleep(timeout.min(Duration::from_millis(1)));
                Ok(None)
            }
        }
    }

    fn name(&self) -> &str {
        "fake"
    }
}
