//! SDO block download with CRC (CiA 301 §7.2.4.3.10-16), server side.
//!
//! Protocol (client → server on 0x600+id, server → client on 0x580+id):
//! 1. initiate `[0xC0 | cc<<2 | s<<1, index, sub, size(4)]` (cc: the
//!    client computes a CRC, s: size indicated) → `[0xA4, index, sub,
//!    blksize]` (0xA4: the server computes a CRC too);
//! 2. sub-blocks of `blksize` segments `[c<<7 | seqno, data(7)]`, seqno
//!    1..=blksize, c on the last segment of the transfer; the server
//!    answers each sub-block with `[0xA2, ackseq, blksize]`: ackseq is the
//!    last segment received in sequence, and the client sends again from
//!    ackseq + 1;
//! 3. end `[0xC1 | n<<2, crc lo, crc hi]` (n bytes of the last segment
//!    carry no data) → `[0xA1]`.
//!
//! The CRC is CRC-16-CCITT (polynomial 0x1021, initial value 0, no
//! reflection, no final XOR) over the data bytes, as `crc16_ccitt` of
//! CANopenNode; [`crc16_ccitt`] is public for the host client.
//!
//! Where CiA 301 leaves the server a choice, this one does what
//! CANopenNode's `CO_SDOserver.c` (v4) does:
//! * a segment out of sequence ends the sub-block at once: the server
//!   acknowledges the last good seqno and ignores the rest of the
//!   sub-block; a repeated segment (seqno = the last good one), and every
//!   segment while nothing of the sub-block arrived yet (seqno 1 lost),
//!   are ignored. It never sends 0x05040003: the ackseq is the remedy.
//! * the transfer aborts with 0x05040000 after the full SDO timeout
//!   without a segment.
//! * a repeated segment after the last one (c set), or anything but the
//!   end request then, aborts with 0x05040001.
//!
//! Where this server departs from CANopenNode: a sub-block whose tail was
//! lost (segments received in sequence, then silence) is acknowledged
//! with the last good seqno after [`BLOCK_GAP_US`] (20 ms) without a
//! segment, not after 70 % of the SDO timeout as CANopenNode's
//! `block_SDOtimeoutTime_us` (`SDOtimeoutTime_ms * 700`): no later frame
//! comes to end such a sub-block early, and at 0.7 s every master that
//! waits less for the acknowledgement (python-canopen 2.4 waits 0.3 s,
//! `perpend` waited 0.5 s) aborted before the ackseq could help.
//! CiA 301 (§7.2.4.3.10-16) fixes no time for this acknowledgement. A client
//! sends a sub-block back to back (a frame takes 0.13-1 ms at 1000-125
//! kbit/s), so 20 ms is far above a sane gap inside one and below any
//! sane client's wait; a client that does pause longer mid sub-block gets
//! an early acknowledgement and resends from it (its late segments are
//! ignored), which costs time, never data. A sub-block of which nothing
//! arrived in sequence (its first segment lost, or the client not yet
//! sending) keeps CANopenNode's 70 %: after an early acknowledgement the
//! rest of the old sub-block may still be on the way, and a second, stale
//! acknowledgement would desynchronise the client.
//!
//! Memory: one 889-byte buffer (127 segments × 7 bytes) in the server,
//! shared with segmented DOMAIN downloads; a DOMAIN's sub-block goes to
//! [`crate::sdo::Dictionary::write_part`] at each acknowledgement (so a
//! part the application refuses aborts at a sub-block boundary), the last
//! sub-block only after the end request and its CRC check. A non-DOMAIN
//! object (≤ 8 bytes) is written whole at the end.
//!
//! Limits: server-chosen blksize 127 (less when data wait in the buffer: a
//! non-DOMAIN download, or a stalled sub-block acknowledged by a timer,
//! whose next sub-block fills the buffer's room); no block upload.

use super::{abort_payload, Dictionary, SdoAbort, SdoServer, Transfer, Written};

/// Segments in a full sub-block (CiA 301: 1..=127).
pub const MAX_BLKSIZE: u8 = 127;
/// Bytes in a full sub-block: 127 segments of 7 bytes.
pub const BLOCK_BYTES: usize = MAX_BLKSIZE as usize * 7;
/// Gap timer \[µs\]: a sub-block with segments in sequence and then none
/// for this long is acknowledged as it stands (its tail was lost; module
/// docs). Capped at 70 % of the SDO timeout.
pub const BLOCK_GAP_US: u64 = 20_000;
// Well below a client's wait for the acknowledgement (module docs).
const _: () = assert!(BLOCK_GAP_US <= 50_000);

/// CRC-16-CCITT (polynomial 0x1021, no reflection, no final XOR) of
/// `data`, continuing from `crc` (0 to start), as CiA 301 §7.2.4.3.16
/// and CANopenNode's `crc16_ccitt`.
pub fn crc16_ccitt(data: &[u8], crc: u16) -> u16 {
    data.iter().fold(crc, |mut c, &b| {
        c ^= u16::from(b) << 8;
        for _ in 0..8 {
            c = if c & 0x8000 != 0 {
                (c << 1) ^ 0x1021
            } else {
                c << 1
            };
        }
        c
    })
}

/// State of a block download in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockDown {
    index: u16,
    sub: u8,
    /// Size the client indicated \[bytes\].
    declared: Option<u32>,
    /// Whether the client computes a CRC (checked at the end).
    crc_on: bool,
    /// CRC of the data already handed to the dictionary.
    crc: u16,
    /// Bytes already handed to the dictionary (DOMAIN).
    offset: u32,
    /// Segments in the current sub-block.
    blksize: u8,
    /// Last segment received in sequence (0: none yet).
    seqno: u8,
    /// Bytes in the buffer.
    fill: usize,
    /// The last segment is in: waiting for the end request.
    ending: bool,
    domain: bool,
    /// Abort 0x05040000 at this time without a segment \[µs\].
    deadline: u64,
    /// Acknowledge a sub-block with nothing in sequence at this time \[µs\].
    ack_at: u64,
    /// Acknowledge a sub-block whose tail stalled at this time \[µs\]
    /// (when `seqno` > 0).
    gap_at: u64,
}

impl BlockDown {
    /// The object being written.
    pub(crate) fn addr(&self) -> (u16, u8) {
        (self.index, self.sub)
    }

    /// Timeouts counted from `now_us` (`timeout_us` the SDO timeout).
    pub(crate) fn rearm(&mut self, now_us: u64, timeout_us: u64) {
        let long = timeout_us / 10 * 7;
        self.deadline = now_us.saturating_add(timeout_us);
        self.ack_at = now_us.saturating_add(long);
        self.gap_at = now_us.saturating_add(BLOCK_GAP_US.min(long));
    }

    fn ack(&self, ackseq: u8) -> [u8; 8] {
        [0xA2, ackseq, self.blksize, 0, 0, 0, 0, 0]
    }
}

impl SdoServer {
    /// Routes a request that belongs to a block download in progress:
    /// `Some(answer)` when it did, `None` for the ordinary dispatch (a
    /// client abort `0x80` always goes there).
    pub(crate) fn block_route<D: Dictionary>(
        &mut self,
        od: &mut D,
        req: &[u8],
        now_us: u64,
    ) -> Option<Option<[u8; 8]>> {
        let Transfer::BlockDown(b) = self.transfer else {
            return None;
        };
        let seg: &[u8; 8] = req.try_into().ok()?;
        if seg[0] == 0x80 {
            return None;
        }
        Some(if b.ending {
            self.block_end(od, b, seg)
        } else {
            self.block_segment(od, b, seg, now_us)
        })
    }

    /// A block-download request outside a sub-block (ccs 6): initiate.
    pub(crate) fn block_request<D: Dictionary>(
        &mut self,
        od: &mut D,
        req: &[u8; 8],
        index: u16,
        sub: u8,
        now_us: u64,
    ) -> Option<[u8; 8]> {
        self.reset();
        if req[0] & 0x01 != 0 {
            // An end request without a transfer.
            return Some(abort_payload(index, sub, SdoAbort::Command));
        }
        let declared =
            (req[0] & 0x02 != 0).then(|| u32::from_le_bytes([req[4], req[5], req[6], req[7]]));
        if let Err(a) = od.check_write(index, sub, declared.map(|d| d as usize)) {
            return Some(abort_payload(index, sub, a));
        }
        let mut b = BlockDown {
            index,
            sub,
            declared,
            crc_on: req[0] & 0x04 != 0,
            crc: 0,
            offset: 0,
            blksize: MAX_BLKSIZE,
            seqno: 0,
            fill: 0,
            ending: false,
            domain: od.domain(index, sub),
            deadline: 0,
            ack_at: 0,
            gap_at: 0,
        };
        b.rearm(now_us, self.timeout_us);
        self.transfer = Transfer::BlockDown(b);
        let i = index.to_le_bytes();
        Some([0xA4, i[0], i[1], sub, MAX_BLKSIZE, 0, 0, 0])
    }

    fn block_segment<D: Dictionary>(
        &mut self,
        od: &mut D,
        mut b: BlockDown,
        seg: &[u8; 8],
        now_us: u64,
    ) -> Option<[u8; 8]> {
        let seqno = seg[0] & 0x7F;
        b.rearm(now_us, self.timeout_us);
        if seqno == b.seqno + 1 && seqno <= b.blksize {
            let Some(dst) = self.buf.get_mut(b.fill..b.fill + 7) else {
                self.reset();
                return Some(abort_payload(b.index, b.sub, SdoAbort::TooLong));
            };
            dst.copy_from_slice(&seg[1..]);
            b.fill += 7;
            b.seqno = seqno;
            if seg[0] & 0x80 != 0 {
                // The last segment: its data wait for the end request.
                b.ending = true;
                self.transfer = Transfer::BlockDown(b);
                return Some(b.ack(seqno));
            }
            if seqno == b.blksize {
                return self.block_ack(od, b);
            }
        } else if seqno != b.seqno && b.seqno != 0 {
            // Out of sequence: end the sub-block, resend after the last
            // good one (CANopenNode).
            return self.block_ack(od, b);
        }
        // In sequence, or repeated / before the first: wait for more.
        self.transfer = Transfer::BlockDown(b);
        None
    }

    /// Acknowledges the sub-block up to the last good segment; a DOMAIN's
    /// data go to the dictionary first.
    fn block_ack<D: Dictionary>(&mut self, od: &mut D, mut b: BlockDown) -> Option<[u8; 8]> {
        let ackseq = b.seqno;
        b.seqno = 0;
        let total = b.offset as usize + b.fill;
        if b.declared.is_some_and(|d| total > d as usize) {
            self.reset();
            return Some(abort_payload(b.index, b.sub, SdoAbort::Length));
        }
        if !b.domain {
            // Kept whole until the end: the next sub-block fits the rest.
            b.blksize = ((self.buf.len() - b.fill) / 7) as u8;
            if b.blksize == 0 {
                self.reset();
                return Some(abort_payload(b.index, b.sub, SdoAbort::TooLong));
            }
            self.transfer = Transfer::BlockDown(b);
            return Some(b.ack(ackseq));
        }
        let part = self.buf.get(..b.fill).unwrap_or(&[]);
        b.crc = crc16_ccitt(part, b.crc);
        let (offset, index, sub) = (b.offset, b.index, b.sub);
        b.offset += b.fill as u32;
        b.fill = 0;
        b.blksize = MAX_BLKSIZE;
        let r = if part.is_empty() {
            Ok(Written::Done)
        } else {
            od.write_part(index, sub, offset, part, false)
        };
        self.conclude(r, index, sub, b.ack(ackseq), Transfer::BlockDown(b))
    }

    /// The end request: unused bytes, size and CRC checked, then the last
    /// part (DOMAIN) or the whole value written.
    fn block_end<D: Dictionary>(
        &mut self,
        od: &mut D,
        b: BlockDown,
        req: &[u8; 8],
    ) -> Option<[u8; 8]> {
        self.reset();
        let (index, sub) = (b.index, b.sub);
        let n = ((req[0] >> 2) & 7) as usize;
        if req[0] & 0xE3 != 0xC1 || n > 6 || n > b.fill {
            return Some(abort_payload(index, sub, SdoAbort::Command));
        }
        let len = b.fill - n;
        if b.declared
            .is_some_and(|d| d as usize != b.offset as usize + len)
        {
            return Some(abort_payload(index, sub, SdoAbort::Length));
        }
        let data = self.buf.get(..len).unwrap_or(&[]);
        if b.crc_on && crc16_ccitt(data, b.crc) != u16::from_le_bytes([req[1], req[2]]) {
            return Some(abort_payload(index, sub, SdoAbort::Crc));
        }
        let r = if b.domain {
            od.write_part(index, sub, b.offset, data, true)
        } else {
            od.write(index, sub, data)
        };
        let resp = [0xA1, 0, 0, 0, 0, 0, 0, 0];
        self.conclude(r, index, sub, resp, Transfer::Idle)
    }

    /// Timeouts of a block download at `now_us`: the abort after the full
    /// SDO timeout without a segment, else the acknowledgement of a
    /// stalled sub-block: after [`BLOCK_GAP_US`] when segments came in
    /// sequence, after 70 % of the SDO timeout when none did (module
    /// docs). Not in the DOMAIN's data: it needs no dictionary; the buffer
    /// keeps them and the next sub-block is sized to the room left.
    pub(crate) fn block_timeout(&mut self, mut b: BlockDown, now_us: u64) -> Option<[u8; 8]> {
        if now_us >= b.deadline {
            self.reset();
            return Some(abort_payload(b.index, b.sub, SdoAbort::Timeout));
        }
        let due = if b.seqno > 0 { b.gap_at } else { b.ack_at };
        if b.ending || now_us < due {
            return None;
        }
        let ackseq = b.seqno;
        b.seqno = 0;
        b.blksize = ((self.buf.len() - b.fill) / 7) as u8;
        if b.blksize == 0 {
            self.reset();
            return Some(abort_payload(b.index, b.sub, SdoAbort::TooLong));
        }
        b.ack_at = now_us.saturating_add(self.timeout_us / 10 * 7);
        self.transfer = Transfer::BlockDown(b);
        Some(b.ack(ackseq))
    }
}
