//! TPDOs as the device maps them: the communication (0x1800+k: COB-ID,
//! transmission type) and mapping (0x1A00+k: `index << 16 | sub << 8 |
//! bits`) parameters are read from the device itself, so a PDO an
//! integrator remapped is decoded right. The data type of each mapped
//! object comes from the board's object dictionary
//! ([`perpend_can::od`]); objects it does not know are decoded as unsigned
//! integers of the mapped length.

use perpend_can::od::{self, DataType};

use super::{Client, ClientError};

/// One mapped object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mapped {
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Length in bits.
    pub bits: u8,
}

impl Mapped {
    /// From a mapping entry value.
    pub fn from_entry(v: u32) -> Self {
        Self {
            index: (v >> 16) as u16,
            sub: (v >> 8) as u8,
            bits: v as u8,
        }
    }
}

/// One TPDO's parameters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Tpdo {
    /// 1-based PDO number.
    pub number: u8,
    /// 11-bit COB-ID.
    pub cob_id: u16,
    /// Whether the PDO exists (COB-ID bit 31 clear).
    pub valid: bool,
    /// Transmission type (0 acyclic synchronous, 1..240 every n-th SYNC,
    /// 254/255 event driven).
    pub transmission: u8,
    /// The mapped objects in order.
    pub mapped: Vec<Mapped>,
}

/// A decoded value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PdoValue {
    /// REAL32.
    Real(f32),
    /// UNSIGNED8/16/32 (or an object the dictionary does not know).
    Unsigned(u32),
}

impl PdoValue {
    /// The value as `f64`.
    pub fn as_f64(self) -> f64 {
        match self {
            PdoValue::Real(x) => x as f64,
            PdoValue::Unsigned(u) => u as f64,
        }
    }
}

/// Decodes the little-endian `bytes` of `(index, sub)`.
pub fn value_of(index: u16, sub: u8, bytes: &[u8]) -> Option<PdoValue> {
    let ty = od::find(index, sub).ok().map(|(_, e)| e.ty);
    match (ty, bytes.len()) {
        (Some(DataType::Real32), 4) => {
            let b: [u8; 4] = bytes.try_into().ok()?;
            Some(PdoValue::Real(f32::from_le_bytes(b)))
        }
        (Some(DataType::VisibleString), _) => None,
        (_, 1..=4) => {
            let mut b = [0u8; 4];
            b[..bytes.len()].copy_from_slice(bytes);
            Some(PdoValue::Unsigned(u32::from_le_bytes(b)))
        }
        _ => None,
    }
}

impl Tpdo {
    /// Whether this PDO is sent on SYNC (transmission type 0..=240).
    pub fn synchronous(&self) -> bool {
        self.transmission <= 240
    }

    /// The objects of one frame's payload, in mapping order; stops at an
    /// entry that is not whole bytes or beyond the payload.
    pub fn decode(&self, payload: &[u8]) -> Vec<(Mapped, PdoValue)> {
        let mut out = Vec::new();
        let mut pos = 0usize;
        for m in &self.mapped {
            if m.bits % 8 != 0 || m.bits == 0 {
                break;
            }
            let n = m.bits as usize / 8;
            let Some(bytes) = payload.get(pos..pos + n) else {
                break;
            };
            if let Some(v) = value_of(m.index, m.sub, bytes) {
                out.push((*m, v));
            }
            pos += n;
        }
        out
    }
}

impl Client {
    /// Reads the parameters of TPDOs 1..=`count` of `node`.
    ///
    /// # Errors
    /// As [`Client::upload`].
    pub fn read_tpdos(&mut self, node: u8, count: u8) -> Result<Vec<Tpdo>, ClientError> {
        let mut out = Vec::new();
        for k in 0..count as u16 {
            let cob = self.read_u32(node, 0x1800 + k, 1)?;
            let transmission = self.read_u32(node, 0x1800 + k, 2)? as u8;
            let n = self
                .read_u32(node, 0x1A00 + k, 0)?
                .min(od::MAX_MAPPED as u32) as u8;
            let mut mapped = Vec::new();
            for s in 1..=n {
                mapped.push(Mapped::from_entry(self.read_u32(node, 0x1A00 + k, s)?));
            }
            out.push(Tpdo {
                number: k as u8 + 1,
                cob_id: (cob & 0x7FF) as u16,
                valid: cob & 0x8000_0000 == 0,
                transmission,
                mapped,
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::bus::fake::{FakeBus, Peer};
    use perpend_can::{Defaults, Device, Frame};

    struct Dev(Device, u64);
    impl Peer for Dev {
        fn frame(&mut self, f: &Frame, out: &mut Vec<Frame>) {
            self.1 += 100;
            self.0.handle(f, self.1, &mut |o| out.push(o));
        }
        fn idle(&mut self, out: &mut Vec<Frame>) {
            self.1 += 1000;
            self.0.poll(self.1, &mut |o| out.push(o));
        }
    }

    #[test]
    fn the_default_and_a_remapped_tpdo_decode_right() {
        let mut dev = Device::new(0x10, &Defaults::nominal());
        dev.poll(0, &mut |_| {});
        let mut c = Client::new(Box::new(FakeBus::new(Dev(dev, 0))));
        let t = c.read_tpdos(0x10, 4).unwrap();
        assert_eq!(t[0].cob_id, 0x190);
        assert!(t[0].valid && t[0].synchronous());
        assert_eq!(
            t[1].mapped,
            vec![
                Mapped {
                    index: 0x2005,
                    sub: 0,
                    bits: 32
                },
                Mapped {
                    index: 0x2007,
                    sub: 0,
                    bits: 32
                }
            ]
        );
        // Remap TPDO 1 to distance 1 + status (CiA 301 order: invalidate,
        // clear, write entries, count, validate).
        let node = 0x10;
        c.write_u32(node, 0x1800, 1, 0xC000_0190).unwrap();
        c.download(node, 0x1A00, 0, &[0]).unwrap();
        c.write_u32(node, 0x1A00, 1, od::mapping(0x2004, 1, 32))
            .unwrap();
        c.write_u32(node, 0x1A00, 2, od::mapping(0x2005, 0, 32))
            .unwrap();
        c.download(node, 0x1A00, 0, &[2]).unwrap();
        c.write_u32(node, 0x1800, 1, 0x4000_0190).unwrap();
        let t = c.read_tpdos(node, 1).unwrap();
        let mut payload = 45.5f32.to_le_bytes().to_vec();
        payload.extend_from_slice(&0x1111u32.to_le_bytes());
        let v = t[0].decode(&payload);
        assert_eq!(v[0].1, PdoValue::Real(45.5));
        assert_eq!((v[1].0.index, v[1].1), (0x2005, PdoValue::Unsigned(0x1111)));
    }
}
