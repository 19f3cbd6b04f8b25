//! Classic CAN frames with 11-bit identifiers: what the device consumes and
//! produces. The transport (FDCAN on the board, slcan over TCP on the host)
//! converts its own frame type to and from [`Frame`].
//!
//! Limits: extended (29-bit) identifiers and CAN FD payloads are not part of
//! CANopen CiA 301 classic and are not represented; the transport drops them.

/// Largest valid 11-bit identifier.
pub const MAX_ID: u16 = 0x7FF;

/// A classic CAN data or remote frame with an 11-bit identifier.
///
/// `len` is the data length code (0..=8); only `data[..len]` is meaningful.
/// A frame with `id > 0x7FF` or `len > 8` can be constructed (the fields are
/// public so that transports can fill them directly) but the device ignores
/// it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Frame {
    /// 11-bit CAN identifier (COB-ID).
    pub id: u16,
    /// Remote transmission request.
    pub rtr: bool,
    /// Data length code, 0..=8.
    pub len: u8,
    /// Payload; bytes at and beyond `len` are zero in frames the device
    /// produces and ignored in frames it consumes.
    pub data: [u8; 8],
}

impl Frame {
    /// A data frame with the given payload (at most 8 bytes; longer payloads
    /// are truncated to 8).
    pub fn new(id: u16, payload: &[u8]) -> Self {
        let n = payload.len().min(8);
        let mut data = [0u8; 8];
        data[..n].copy_from_slice(&payload[..n]);
        Self {
            id,
            rtr: false,
            len: n as u8,
            data,
        }
    }

    /// A remote frame requesting `len` bytes.
    pub fn remote(id: u16, len: u8) -> Self {
        Self {
            id,
            rtr: true,
            len: len.min(8),
            data: [0; 8],
        }
    }

    /// The meaningful payload bytes (`data[..len]`, `len` clamped to 8).
    pub fn payload(&self) -> &[u8] {
        &self.data[..(self.len as usize).min(8)]
    }

    /// Whether the identifier and length are valid for a classic CAN frame.
    pub fn is_well_formed(&self) -> bool {
        self.id <= MAX_ID && self.len <= 8
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn new_truncates_and_zero_fills() {
        let f = Frame::new(0x123, &[1, 2, 3]);
        assert_eq!(f.len, 3);
        assert_eq!(f.data, [1, 2, 3, 0, 0, 0, 0, 0]);
        assert_eq!(f.payload(), &[1, 2, 3]);
        let g = Frame::new(0x7FF, &[9; 12]);
        assert_eq!(g.len, 8);
        assert!(g.is_well_formed());
        let bad = Frame { id: 0x800, ..g };
        assert!(!bad.is_well_formed());
        let r = Frame::remote(0x700, 1);
        assert!(r.rtr);
        assert_eq!(r.payload(), &[0]);
    }
}
