//! SDO server (CiA 301 §7.2.4): expedited and segmented upload and
//! download, toggle check, server-side timeout, abort codes.
//!
//! The server is a state machine over 8-byte request payloads; it reaches
//! the object dictionary through the [`Dictionary`] trait, which applies the
//! access, state, lock and range rules and answers with an [`SdoAbort`] when
//! one is violated. Every request the server receives gets exactly one
//! response (an answer or an abort) except a client's abort, which is
//! unconfirmed by definition. A write whose effect needs the application
//! (0x1010 store, 0x1011 restore) is answered when the application reports
//! the outcome ([`crate::Device::finish_request`]); a request meanwhile is
//! answered with the abort 0x08000020 that ends that transfer (CiA 301: an
//! abort ends a transfer on both sides), so the outcome is then sent to
//! nobody. A segment that fits no transfer in progress is aborted with
//! that transfer's object.
//!
//! Block download with CRC (CiA 301 §7.2.4.3.10-16) is in
//! [`crate::sdo::block`] (feature `sdo-block`, which sizes the transfer
//! buffer for a whole sub-block of 127 segments, 889 bytes); without it a
//! block request is refused with 0x05040001 and a client falls back to
//! segmented transfer.
//!
//! DOMAIN objects ([`Dictionary::domain`], e.g. 0x1F50 program data) are
//! streamed: the data go to [`Dictionary::write_part`] in parts of up to
//! [`BUF_LEN`] bytes (each sub-block, or each buffer-full of segments), each
//! at its byte offset; the last part says so.
//!
//! Limits: block upload is not implemented (abort 0x05040001; CiA 301 lets
//! the client use a segmented upload instead); segmented downloads of a
//! non-DOMAIN object carry at most 8 bytes (no writable object is larger).

/// SDO block download with CRC (CiA 301 §7.2.4.3.10-16).
#[cfg(feature = "sdo-block")]
pub mod block;

/// CiA 301 SDO abort codes the server produces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SdoAbort {
    /// 0x05030000 toggle bit not alternated.
    Toggle,
    /// 0x05040000 SDO protocol timed out.
    Timeout,
    /// 0x05040001 client/server command specifier not valid or unknown.
    Command,
    /// 0x05040002 invalid block size (block mode only).
    BlockSize,
    /// 0x05040003 invalid sequence number (block mode only).
    SeqNo,
    /// 0x05040004 CRC error (block mode only).
    Crc,
    /// 0x06010000 unsupported access to an object.
    Unsupported,
    /// 0x06010001 attempt to read a write-only object.
    WriteOnly,
    /// 0x06010002 attempt to write a read-only object.
    ReadOnly,
    /// 0x06020000 object does not exist in the object dictionary.
    NoObject,
    /// 0x06040041 object cannot be mapped to the PDO.
    NotMappable,
    /// 0x06040042 the number and length of the mapped objects would exceed
    /// the PDO length.
    PdoLength,
    /// 0x06040043 general parameter incompatibility (mapping length does not
    /// match the object).
    Incompatible,
    /// 0x06070010 data type does not match, length of service parameter
    /// does not match: the length is wrong but neither too long nor too
    /// short can be told (a segmented download whose data differ from the
    /// size it declared).
    Length,
    /// 0x06070012 length of service parameter too high: more bytes than
    /// the object holds.
    TooLong,
    /// 0x06070013 length of service parameter too low: fewer bytes than
    /// the object holds.
    TooShort,
    /// 0x06090011 sub-index does not exist.
    NoSub,
    /// 0x06090030 invalid value for parameter (download only).
    Range,
    /// 0x06090031 value of parameter written too high.
    TooHigh,
    /// 0x06090032 value of parameter written too low.
    TooLow,
    /// 0x08000000 general error.
    General,
    /// 0x08000020 data cannot be transferred or stored to the application.
    Store,
    /// 0x08000021 ... because of local control (calibration locked).
    Locked,
    /// 0x08000022 ... because of the present device state.
    State,
}

impl SdoAbort {
    /// The 32-bit abort code sent on the bus.
    pub const fn code(self) -> u32 {
        match self {
            SdoAbort::Toggle => 0x0503_0000,
            SdoAbort::Timeout => 0x0504_0000,
            SdoAbort::Command => 0x0504_0001,
            SdoAbort::BlockSize => 0x0504_0002,
            SdoAbort::SeqNo => 0x0504_0003,
            SdoAbort::Crc => 0x0504_0004,
            SdoAbort::Unsupported => 0x0601_0000,
            SdoAbort::WriteOnly => 0x0601_0001,
            SdoAbort::ReadOnly => 0x0601_0002,
            SdoAbort::NoObject => 0x0602_0000,
            SdoAbort::NotMappable => 0x0604_0041,
            SdoAbort::PdoLength => 0x0604_0042,
            SdoAbort::Incompatible => 0x0604_0043,
            SdoAbort::Length => 0x0607_0010,
            SdoAbort::TooLong => 0x0607_0012,
            SdoAbort::TooShort => 0x0607_0013,
            SdoAbort::NoSub => 0x0609_0011,
            SdoAbort::Range => 0x0609_0030,
            SdoAbort::TooHigh => 0x0609_0031,
            SdoAbort::TooLow => 0x0609_0032,
            SdoAbort::General => 0x0800_0000,
            SdoAbort::Store => 0x0800_0020,
            SdoAbort::Locked => 0x0800_0021,
            SdoAbort::State => 0x0800_0022,
        }
    }

    /// Every code, for tests and documentation.
    pub const ALL: [SdoAbort; 24] = [
        SdoAbort::Toggle,
        SdoAbort::Timeout,
        SdoAbort::Command,
        SdoAbort::BlockSize,
        SdoAbort::SeqNo,
        SdoAbort::Crc,
        SdoAbort::Unsupported,
        SdoAbort::WriteOnly,
        SdoAbort::ReadOnly,
        SdoAbort::NoObject,
        SdoAbort::NotMappable,
        SdoAbort::PdoLength,
        SdoAbort::Incompatible,
        SdoAbort::Length,
        SdoAbort::TooLong,
        SdoAbort::TooShort,
        SdoAbort::NoSub,
        SdoAbort::Range,
        SdoAbort::TooHigh,
        SdoAbort::TooLow,
        SdoAbort::General,
        SdoAbort::Store,
        SdoAbort::Locked,
        SdoAbort::State,
    ];

    /// The abort with this code, if the server can produce it.
    pub fn from_code(code: u32) -> Option<Self> {
        Self::ALL.iter().copied().find(|a| a.code() == code)
    }
}

/// A value read from the dictionary for an upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Value {
    /// A numeric value: little-endian bytes and their count (1, 2 or 4).
    Num([u8; 4], usize),
    /// A string constant.
    Str(&'static [u8]),
}

/// What a successful write did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Written {
    /// Done: confirm now.
    Done,
    /// The application must complete it; confirm (or abort) later.
    Deferred,
}

/// The server's view of the object dictionary.
pub trait Dictionary {
    /// Reads `(index, sub)`.
    ///
    /// # Errors
    /// The abort to send.
    fn read(&self, index: u16, sub: u8) -> Result<Value, SdoAbort>;
    /// Checks that `(index, sub)` exists, is writable now and takes `len`
    /// bytes (`None`: size not indicated), before a segmented download.
    ///
    /// # Errors
    /// The abort to send.
    fn check_write(&self, index: u16, sub: u8, len: Option<usize>) -> Result<(), SdoAbort>;
    /// Writes `data` to `(index, sub)` with every rule applied.
    ///
    /// # Errors
    /// The abort to send; the dictionary is unchanged.
    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<Written, SdoAbort>;
    /// Whether `(index, sub)` is a DOMAIN, written in parts by
    /// [`Dictionary::write_part`] instead of [`Dictionary::write`].
    fn domain(&self, _index: u16, _sub: u8) -> bool {
        false
    }
    /// Writes one part of a DOMAIN download: `data` at byte `offset` of the
    /// object (parts come in order, without gaps, the first at offset 0);
    /// `last` closes the download. A download that ends otherwise (abort,
    /// timeout, CRC error) simply never sends its last part: the next one
    /// starts again at offset 0.
    ///
    /// # Errors
    /// The abort to send; the transfer ends.
    fn write_part(
        &mut self,
        _index: u16,
        _sub: u8,
        _offset: u32,
        _data: &[u8],
        _last: bool,
    ) -> Result<Written, SdoAbort> {
        Err(SdoAbort::Unsupported)
    }
}

/// The abort for writing `got` bytes to an object of `size` bytes:
/// 0x06070012 too long, 0x06070013 too short, `None` when they match.
pub const fn length_abort(size: usize, got: usize) -> Option<SdoAbort> {
    if got > size {
        Some(SdoAbort::TooLong)
    } else if got < size {
        Some(SdoAbort::TooShort)
    } else {
        None
    }
}

/// Largest segmented download of a non-DOMAIN object accepted \[bytes\].
pub const MAX_DOWNLOAD: usize = 8;

/// Bytes of the server's transfer buffer: one whole sub-block of 127
/// segments of 7 bytes with the feature `sdo-block`, else one 7-byte
/// segment (DOMAIN parts are then a segment each) or an 8-byte value.
#[cfg(feature = "sdo-block")]
pub const BUF_LEN: usize = crate::sdo::block::BLOCK_BYTES;
/// Bytes of the server's transfer buffer: one whole sub-block of 127
/// segments of 7 bytes with the feature `sdo-block`, else one 7-byte
/// segment (DOMAIN parts are then a segment each) or an 8-byte value.
#[cfg(not(feature = "sdo-block"))]
pub const BUF_LEN: usize = MAX_DOWNLOAD;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Transfer {
    Idle,
    Upload {
        index: u16,
        sub: u8,
        data: &'static [u8],
        pos: usize,
        toggle: bool,
        deadline: u64,
    },
    /// Segmented download: `len` bytes in the buffer, `offset` bytes
    /// already handed to the dictionary (DOMAIN only).
    Download {
        index: u16,
        sub: u8,
        len: usize,
        offset: usize,
        domain: bool,
        declared: Option<usize>,
        toggle: bool,
        deadline: u64,
    },
    /// Block download (`sdo/block.rs`).
    #[cfg(feature = "sdo-block")]
    BlockDown(crate::sdo::block::BlockDown),
    /// A write handed to the application; `resp` is the confirmation to
    /// send on success, `None` once the transfer was aborted meanwhile
    /// (the application still holds the write, which cannot be recalled;
    /// its outcome is then sent to nobody).
    Deferred {
        index: u16,
        sub: u8,
        resp: Option<[u8; 8]>,
    },
}

impl Transfer {
    /// The object of the transfer in progress: what its aborts carry.
    fn addr(&self) -> Option<(u16, u8)> {
        match *self {
            Transfer::Idle => None,
            Transfer::Upload { index, sub, .. }
            | Transfer::Download { index, sub, .. }
            | Transfer::Deferred { index, sub, .. } => Some((index, sub)),
            #[cfg(feature = "sdo-block")]
            Transfer::BlockDown(b) => Some(b.addr()),
        }
    }
}

/// The SDO server state (one server, default SDO channel).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SdoServer {
    pub(crate) transfer: Transfer,
    /// What continues once a deferred DOMAIN part is confirmed.
    pub(crate) resume: Transfer,
    pub(crate) timeout_us: u64,
    /// The time of the last request or timeout check \[µs\].
    pub(crate) now_us: u64,
    /// Data of the download in progress (segments, or a sub-block).
    pub(crate) buf: [u8; BUF_LEN],
}

pub(crate) fn abort_payload(index: u16, sub: u8, a: SdoAbort) -> [u8; 8] {
    let i = index.to_le_bytes();
    let c = a.code().to_le_bytes();
    [0x80, i[0], i[1], sub, c[0], c[1], c[2], c[3]]
}

pub(crate) fn addr_payload(cmd: u8, index: u16, sub: u8) -> [u8; 8] {
    let i = index.to_le_bytes();
    [cmd, i[0], i[1], sub, 0, 0, 0, 0]
}

impl SdoServer {
    /// An idle server whose segmented transfers time out after `timeout_us`.
    pub const fn new(timeout_us: u64) -> Self {
        Self {
            transfer: Transfer::Idle,
            resume: Transfer::Idle,
            timeout_us,
            now_us: 0,
            buf: [0; BUF_LEN],
        }
    }

    /// [`SdoServer::new`] written in place at `dst` (the 889-byte buffer
    /// zeroed there, not copied through a stack frame).
    ///
    /// # Safety
    /// `dst` is valid for writes and aligned; what it held is overwritten
    /// without being dropped.
    pub(crate) unsafe fn init(dst: *mut SdoServer, timeout_us: u64) {
        // SAFETY: the caller's guarantee; every field is written once
        // (`SdoServer`'s fields are all listed: the struct literal in
        // `new` fails to compile when one is added, and so does the
        // pattern below).
        unsafe {
            core::ptr::addr_of_mut!((*dst).transfer).write(Transfer::Idle);
            core::ptr::addr_of_mut!((*dst).resume).write(Transfer::Idle);
            core::ptr::addr_of_mut!((*dst).timeout_us).write(timeout_us);
            core::ptr::addr_of_mut!((*dst).now_us).write(0);
            core::ptr::addr_of_mut!((*dst).buf).write_bytes(0, 1);
        }
        #[allow(dead_code)]
        fn fields(s: SdoServer) {
            let SdoServer {
                transfer: _,
                resume: _,
                timeout_us: _,
                now_us: _,
                buf: _,
            } = s;
        }
    }

    /// The data of the DOMAIN part last handed to the application
    /// ([`Dictionary::write_part`] answered [`Written::Deferred`]): the
    /// first `len` bytes of the transfer buffer.
    pub fn part(&self, len: usize) -> &[u8] {
        self.buf.get(..len).unwrap_or(&[])
    }

    /// Whether a segmented transfer or a deferred write is in progress.
    pub fn busy(&self) -> bool {
        self.transfer != Transfer::Idle
    }

    /// Whether a block download is in progress (its segments are answered
    /// per sub-block, not one by one).
    pub fn in_block(&self) -> bool {
        #[cfg(feature = "sdo-block")]
        if let Transfer::BlockDown(_) = self.transfer {
            return true;
        }
        false
    }

    /// Forgets any transfer in progress (NMT reset, stop).
    pub fn reset(&mut self) {
        self.transfer = Transfer::Idle;
        self.resume = Transfer::Idle;
    }

    /// Handles one request payload (`req`, the received frame's bytes;
    /// shorter than 8 means a malformed request) and returns the response
    /// payload, or `None` for a client abort, a block segment that needs no
    /// answer yet, or a part handed to the application.
    pub fn handle<D: Dictionary>(
        &mut self,
        od: &mut D,
        req: &[u8],
        now_us: u64,
    ) -> Option<[u8; 8]> {
        self.now_us = now_us;
        let cmd = req.first().copied().unwrap_or(0xFF);
        #[cfg(feature = "sdo-block")]
        if let Some(r) = self.block_route(od, req, now_us) {
            return r;
        }
        let ccs = cmd >> 5;
        if let Some(r) = self.while_deferred(req, ccs) {
            return r;
        }
        if ccs == 4 {
            // Client abort: unconfirmed.
            self.reset();
            return None;
        }
        let index = u16::from_le_bytes([
            req.get(1).copied().unwrap_or(0),
            req.get(2).copied().unwrap_or(0),
        ]);
        let sub = req.get(3).copied().unwrap_or(0);
        if req.len() < 8 {
            // A malformed request ends the transfer in progress (its
            // object in the abort), or is refused with its own.
            let (index, sub) = self.transfer.addr().unwrap_or((index, sub));
            self.reset();
            return Some(abort_payload(index, sub, SdoAbort::Command));
        }
        let mut data = [0u8; 8];
        data.copy_from_slice(&req[..8]);
        match ccs {
            1 => self.initiate_download(od, &data, index, sub, now_us),
            2 => Some(self.initiate_upload(od, index, sub, now_us)),
            0 => self.download_segment(od, &data, now_us),
            3 => Some(self.upload_segment(&data, now_us)),
            #[cfg(feature = "sdo-block")]
            6 => self.block_request(od, &data, index, sub, now_us),
            _ => {
                self.reset();
                Some(abort_payload(index, sub, SdoAbort::Command))
            }
        }
    }

    /// A request while a write is with the application (`Some(answer)`,
    /// `None` when there is none). CiA 301 §7.2.4.3.17: an abort ends the
    /// transfer on both sides, so the abort 0x08000020 that answers the
    /// first request meanwhile (carrying the deferred transfer's object,
    /// like a client's abort) ends that transfer: its confirmation, or a
    /// DOMAIN download's next acknowledgement, is never sent. The write
    /// itself stays with the application (it cannot be recalled), and
    /// every further request until it is done is refused with 0x08000020
    /// on its own object: the transfer buffer still holds the part being
    /// written. A client's abort ends the transfer the same way, without
    /// an answer.
    fn while_deferred(&mut self, req: &[u8], ccs: u8) -> Option<Option<[u8; 8]>> {
        let Transfer::Deferred { index, sub, resp } = self.transfer else {
            return None;
        };
        self.resume = Transfer::Idle;
        self.transfer = Transfer::Deferred {
            index,
            sub,
            resp: None,
        };
        if ccs == 4 {
            return Some(None);
        }
        if resp.is_some() {
            return Some(Some(abort_payload(index, sub, SdoAbort::Store)));
        }
        let own = u16::from_le_bytes([
            req.get(1).copied().unwrap_or(0),
            req.get(2).copied().unwrap_or(0),
        ]);
        let own_sub = req.get(3).copied().unwrap_or(0);
        Some(Some(abort_payload(own, own_sub, SdoAbort::Store)))
    }

    /// Ends a write step with the dictionary's answer `r`: on success
    /// `resp` is sent and the server goes on with `next`; a deferred write
    /// waits for [`SdoServer::complete`] (which sends `resp` and goes on
    /// with `next`); an error aborts the transfer.
    pub(crate) fn conclude(
        &mut self,
        r: Result<Written, SdoAbort>,
        index: u16,
        sub: u8,
        resp: [u8; 8],
        next: Transfer,
    ) -> Option<[u8; 8]> {
        match r {
            Ok(Written::Done) => {
                self.transfer = next;
                Some(resp)
            }
            Ok(Written::Deferred) => {
                // Nothing to send yet: `complete` answers.
                self.transfer = Transfer::Deferred {
                    index,
                    sub,
                    resp: Some(resp),
                };
                self.resume = next;
                None
            }
            Err(a) => {
                self.reset();
                Some(abort_payload(index, sub, a))
            }
        }
    }

    fn initiate_download<D: Dictionary>(
        &mut self,
        od: &mut D,
        req: &[u8; 8],
        index: u16,
        sub: u8,
        now_us: u64,
    ) -> Option<[u8; 8]> {
        self.reset();
        let expedited = req[0] & 0x02 != 0;
        let sized = req[0] & 0x01 != 0;
        let domain = od.domain(index, sub);
        if expedited {
            let len = if sized {
                4 - ((req[0] >> 2) & 3) as usize
            } else if domain {
                4
            } else {
                // Size not indicated: as many bytes as the object holds
                // (CiA 301: "d contains unspecified number of bytes").
                match od.read(index, sub) {
                    Ok(Value::Num(_, n)) => n,
                    Ok(Value::Str(_)) => 4,
                    Err(a) => return Some(abort_payload(index, sub, a)),
                }
            };
            let resp = addr_payload(0x60, index, sub);
            let data = &req[4..4 + len];
            let r = if domain {
                od.check_write(index, sub, Some(len))
                    .and_then(|()| od.write_part(index, sub, 0, data, true))
            } else {
                od.write(index, sub, data)
            };
            return self.conclude(r, index, sub, resp, Transfer::Idle);
        }
        let declared = if sized {
            Some(u32::from_le_bytes([req[4], req[5], req[6], req[7]]) as usize)
        } else {
            None
        };
        if let Err(a) = od.check_write(index, sub, declared) {
            return Some(abort_payload(index, sub, a));
        }
        self.transfer = Transfer::Download {
            index,
            sub,
            len: 0,
            offset: 0,
            domain,
            declared,
            toggle: false,
            deadline: now_us.saturating_add(self.timeout_us),
        };
        Some(addr_payload(0x60, index, sub))
    }

    fn download_segment<D: Dictionary>(
        &mut self,
        od: &mut D,
        req: &[u8; 8],
        now_us: u64,
    ) -> Option<[u8; 8]> {
        let Transfer::Download {
            index,
            sub,
            mut len,
            offset,
            domain,
            declared,
            toggle,
            ..
        } = self.transfer
        else {
            return Some(self.stray_segment());
        };
        let t = req[0] & 0x10 != 0;
        if t != toggle {
            self.reset();
            return Some(abort_payload(index, sub, SdoAbort::Toggle));
        }
        let n = 7 - ((req[0] >> 1) & 7) as usize;
        let last = req[0] & 0x01 != 0;
        let room = if domain { BUF_LEN } else { MAX_DOWNLOAD };
        if let Err(a) = self.append(
            len,
            &req[1..1 + n],
            room,
            declared.map(|d| d.saturating_sub(offset)),
        ) {
            self.reset();
            return Some(abort_payload(index, sub, a));
        }
        len += n;
        let resp = [0x20 | (req[0] & 0x10), 0, 0, 0, 0, 0, 0, 0];
        if last && declared.is_some_and(|d| d != offset + len) {
            self.reset();
            return Some(abort_payload(index, sub, SdoAbort::Length));
        }
        // A DOMAIN part goes out when the buffer cannot take another
        // segment, and at the end.
        let flush = domain && (last || len + 7 > BUF_LEN);
        let next = if last {
            Transfer::Idle
        } else {
            Transfer::Download {
                index,
                sub,
                len: if flush { 0 } else { len },
                offset: if flush { offset + len } else { offset },
                domain,
                declared,
                toggle: !toggle,
                deadline: now_us.saturating_add(self.timeout_us),
            }
        };
        let data = self.buf.get(..len).unwrap_or(&[]);
        let r = if flush {
            od.write_part(index, sub, offset as u32, data, last)
        } else if last {
            od.write(index, sub, data)
        } else {
            Ok(Written::Done)
        };
        self.conclude(r, index, sub, resp, next)
    }

    /// Appends a segment's `data` to the `len` bytes in the buffer:
    /// 0x06070010 past `declared` (what the client declared, less what
    /// already went to the dictionary), 0x06070012 past `room`.
    fn append(
        &mut self,
        len: usize,
        data: &[u8],
        room: usize,
        declared: Option<usize>,
    ) -> Result<(), SdoAbort> {
        let end = len + data.len();
        if declared.is_some_and(|d| end > d) {
            // More data than the client itself declared.
            return Err(SdoAbort::Length);
        }
        // Undeclared size, already longer than any writable object.
        let dst = self
            .buf
            .get_mut(len..end)
            .filter(|_| end <= room)
            .ok_or(SdoAbort::TooLong)?;
        dst.copy_from_slice(data);
        Ok(())
    }

    fn initiate_upload<D: Dictionary>(
        &mut self,
        od: &D,
        index: u16,
        sub: u8,
        now_us: u64,
    ) -> [u8; 8] {
        self.transfer = Transfer::Idle;
        let (bytes, n, seg): ([u8; 4], usize, Option<&'static [u8]>) = match od.read(index, sub) {
            Err(a) => return abort_payload(index, sub, a),
            Ok(Value::Num(b, n)) => (b, n, None),
            Ok(Value::Str(s)) if !s.is_empty() && s.len() <= 4 => {
                let mut b = [0u8; 4];
                b[..s.len()].copy_from_slice(s);
                (b, s.len(), None)
            }
            Ok(Value::Str(s)) => ([0; 4], s.len(), Some(s)),
        };
        let i = index.to_le_bytes();
        match seg {
            None => {
                let cmd = 0x43 | (((4 - n.clamp(1, 4)) as u8) << 2);
                [cmd, i[0], i[1], sub, bytes[0], bytes[1], bytes[2], bytes[3]]
            }
            Some(s) => {
                self.transfer = Transfer::Upload {
                    index,
                    sub,
                    data: s,
                    pos: 0,
                    toggle: false,
                    deadline: now_us.saturating_add(self.timeout_us),
                };
                let l = (s.len() as u32).to_le_bytes();
                [0x41, i[0], i[1], sub, l[0], l[1], l[2], l[3]]
            }
        }
    }

    /// A segment that does not fit the transfer in progress (a download
    /// segment in an upload, or the reverse, or none in progress): abort
    /// 0x05040001 carrying the transfer's object (0x0000/0 when idle, as
    /// the segment names none), and the transfer ends. A master that
    /// matches aborts by object sees it as its transfer's.
    fn stray_segment(&mut self) -> [u8; 8] {
        let (index, sub) = self.transfer.addr().unwrap_or((0, 0));
        self.reset();
        abort_payload(index, sub, SdoAbort::Command)
    }

    fn upload_segment(&mut self, req: &[u8; 8], now_us: u64) -> [u8; 8] {
        let Transfer::Upload {
            index,
            sub,
            data,
            pos,
            toggle,
            ..
        } = self.transfer
        else {
            return self.stray_segment();
        };
        let t = req[0] & 0x10 != 0;
        if t != toggle {
            self.transfer = Transfer::Idle;
            return abort_payload(index, sub, SdoAbort::Toggle);
        }
        let rest = data.get(pos..).unwrap_or(&[]);
        let k = rest.len().min(7);
        let last = pos + k >= data.len();
        let mut out = [0u8; 8];
        out[0] = (req[0] & 0x10) | (((7 - k) as u8) << 1) | u8::from(last);
        out[1..1 + k].copy_from_slice(&rest[..k]);
        self.transfer = if last {
            Transfer::Idle
        } else {
            Transfer::Upload {
                index,
                sub,
                data,
                pos: pos + k,
                toggle: !toggle,
                deadline: now_us.saturating_add(self.timeout_us),
            }
        };
        out
    }

    /// Whether the last [`SdoServer::handle`] handed a write to the
    /// application (its response is sent by [`SdoServer::complete`]).
    pub fn deferred(&self) -> bool {
        matches!(self.transfer, Transfer::Deferred { .. })
    }

    /// Completes a deferred write: the confirmation, or the abort `err`.
    /// `None` when nothing was deferred, or the transfer was aborted
    /// meanwhile (by the client, or by the server's answer to another
    /// request: [`SdoServer::handle`]). A confirmed DOMAIN part lets the
    /// download go on (its timeouts count again from the last request or
    /// poll).
    pub fn complete(&mut self, err: Option<SdoAbort>) -> Option<[u8; 8]> {
        let Transfer::Deferred { index, sub, resp } = self.transfer else {
            return None;
        };
        let next = core::mem::replace(&mut self.resume, Transfer::Idle);
        self.transfer = Transfer::Idle;
        let resp = resp?;
        Some(match err {
            None => {
                self.transfer = self.rearm(next);
                resp
            }
            Some(a) => abort_payload(index, sub, a),
        })
    }

    /// `t` with its timeouts counted from now.
    fn rearm(&self, mut t: Transfer) -> Transfer {
        let at = self.now_us.saturating_add(self.timeout_us);
        match &mut t {
            Transfer::Upload { deadline, .. } | Transfer::Download { deadline, .. } => {
                *deadline = at;
            }
            #[cfg(feature = "sdo-block")]
            Transfer::BlockDown(b) => b.rearm(self.now_us, self.timeout_us),
            Transfer::Idle | Transfer::Deferred { .. } => {}
        }
        t
    }

    /// The abort to send if a segmented transfer has timed out at `now_us`
    /// (the transfer is then dropped); in a block download also the
    /// acknowledgement that a stalled sub-block is due
    /// ([`crate::sdo::block`]).
    pub fn check_timeout(&mut self, now_us: u64) -> Option<[u8; 8]> {
        self.now_us = now_us;
        let (index, sub, deadline) = match self.transfer {
            Transfer::Upload {
                index,
                sub,
                deadline,
                ..
            }
            | Transfer::Download {
                index,
                sub,
                deadline,
                ..
            } => (index, sub, deadline),
            #[cfg(feature = "sdo-block")]
            Transfer::BlockDown(b) => return self.block_timeout(b, now_us),
            _ => return None,
        };
        if now_us >= deadline {
            self.reset();
            Some(abort_payload(index, sub, SdoAbort::Timeout))
        } else {
            None
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A dictionary of one U32 at 0x2000, one read-only U16 at 0x2001 and a
    /// string at 0x2002; 0x2003 defers.
    struct Mini {
        v: u32,
        name: &'static [u8],
    }

    impl Dictionary for Mini {
        fn read(&self, index: u16, sub: u8) -> Result<Value, SdoAbort> {
            match (index, sub) {
                (0x2000, 0) => Ok(Value::Num(self.v.to_le_bytes(), 4)),
                (0x2001, 0) => Ok(Value::Num([7, 0, 0, 0], 2)),
                (0x2002, 0) => Ok(Value::Str(self.name)),
                (0x2003, 0) => Ok(Value::Num([1, 0, 0, 0], 4)),
                (0x2000..=0x2003, _) => Err(SdoAbort::NoSub),
                _ => Err(SdoAbort::NoObject),
            }
        }
        fn check_write(&self, index: u16, sub: u8, len: Option<usize>) -> Result<(), SdoAbort> {
            match self.read(index, sub)? {
                Value::Num(_, n) if index != 0x2001 => match len {
                    Some(l) => length_abort(n, l).map_or(Ok(()), Err),
                    None => Ok(()),
                },
                _ => Err(SdoAbort::ReadOnly),
            }
        }
        fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<Written, SdoAbort> {
            self.check_write(index, sub, Some(data.len()))?;
            if index == 0x2003 {
                return Ok(Written::Deferred);
            }
            self.v = u32::from_le_bytes([data[0], data[1], data[2], data[3]]);
            Ok(Written::Done)
        }
    }

    fn mini() -> Mini {
        Mini {
            v: 0x1122_3344,
            name: b"perpend normal sensor",
        }
    }

    fn abort_code(r: &[u8; 8]) -> Option<u32> {
        (r[0] == 0x80).then(|| u32::from_le_bytes([r[4], r[5], r[6], r[7]]))
    }

    #[test]
    fn expedited_upload_and_download() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        let r = s
            .handle(&mut od, &[0x40, 0x00, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(r, [0x43, 0x00, 0x20, 0, 0x44, 0x33, 0x22, 0x11]);
        let r = s
            .handle(&mut od, &[0x40, 0x01, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(r, [0x4B, 0x01, 0x20, 0, 7, 0, 0, 0]);
        let r = s
            .handle(&mut od, &[0x23, 0x00, 0x20, 0, 1, 2, 3, 4], 0)
            .unwrap();
        assert_eq!(r, [0x60, 0x00, 0x20, 0, 0, 0, 0, 0]);
        assert_eq!(od.v, 0x0403_0201);
        // size not indicated: the object's size is used
        let r = s
            .handle(&mut od, &[0x22, 0x00, 0x20, 0, 9, 9, 9, 9], 0)
            .unwrap();
        assert_eq!(r[0], 0x60);
        assert_eq!(od.v, 0x0909_0909);
    }

    #[test]
    fn wrong_length_and_unknown_objects_abort() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        let r = s
            .handle(&mut od, &[0x2F, 0x00, 0x20, 0, 1, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0013)); // 1 byte to a U32
        assert_eq!(&r[1..4], &[0x00, 0x20, 0]);
        let r = s
            .handle(&mut od, &[0x21, 0x00, 0x20, 0, 5, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0012)); // 5 declared for a U32
        assert_eq!(&r[1..4], &[0x00, 0x20, 0]);
        let r = s
            .handle(&mut od, &[0x40, 0x99, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0602_0000));
        let r = s
            .handle(&mut od, &[0x40, 0x00, 0x20, 3, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0609_0011));
        let r = s
            .handle(&mut od, &[0x2B, 0x01, 0x20, 0, 1, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0601_0002));
        // block upload (not implemented) and short frames
        let r = s
            .handle(&mut od, &[0xA4, 0x00, 0x20, 0, 127, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0504_0001));
        let r = s.handle(&mut od, &[0x40, 0x00, 0x20], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0504_0001));
        // segment without a transfer
        let r = s.handle(&mut od, &[0x60, 0, 0, 0, 0, 0, 0, 0], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0504_0001));
        // client abort: no answer
        assert_eq!(s.handle(&mut od, &[0x80, 0, 0x20, 0, 0, 0, 0, 0], 0), None);
    }

    #[test]
    fn segmented_upload_with_toggle() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        let r = s
            .handle(&mut od, &[0x40, 0x02, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(r, [0x41, 0x02, 0x20, 0, 21, 0, 0, 0]);
        let mut got = Vec::new();
        let mut t = 0u8;
        loop {
            let r = s
                .handle(&mut od, &[0x60 | t, 0, 0, 0, 0, 0, 0, 0], 0)
                .unwrap();
            assert_eq!(r[0] & 0xE0, 0x00);
            assert_eq!(r[0] & 0x10, t);
            let n = 7 - ((r[0] >> 1) & 7) as usize;
            got.extend_from_slice(&r[1..1 + n]);
            t ^= 0x10;
            if r[0] & 1 != 0 {
                break;
            }
        }
        assert_eq!(got, b"perpend normal sensor");
        assert!(!s.busy());
        // toggle error
        s.handle(&mut od, &[0x40, 0x02, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x70, 0, 0, 0, 0, 0, 0, 0], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0503_0000));
        assert!(!s.busy());
    }

    #[test]
    fn segmented_download_and_checks() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        let r = s
            .handle(&mut od, &[0x21, 0x00, 0x20, 0, 4, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(r, [0x60, 0x00, 0x20, 0, 0, 0, 0, 0]);
        // 4 bytes in one last segment: n = 3 unused, c = 1
        let r = s
            .handle(&mut od, &[0x07, 0xAA, 0xBB, 0xCC, 0xDD, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(r[0], 0x20);
        assert_eq!(od.v, 0xDDCC_BBAA);
        // wrong declared size: too long, too short
        let r = s
            .handle(&mut od, &[0x21, 0x00, 0x20, 0, 9, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0012));
        let r = s
            .handle(&mut od, &[0x21, 0x00, 0x20, 0, 2, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0013));
        // undeclared size, 3 bytes in the last segment: too short
        s.handle(&mut od, &[0x20, 0x00, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x09, 1, 2, 3, 0, 0, 0, 0], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0013));
        // declared 4, 7 sent: differs from the declaration (0x06070010)
        s.handle(&mut od, &[0x21, 0x00, 0x20, 0, 4, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x00, 1, 2, 3, 4, 5, 6, 7], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0010));
        // oversize data without size indication
        s.handle(&mut od, &[0x20, 0x00, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x00, 1, 2, 3, 4, 5, 6, 7], 0).unwrap();
        assert_eq!(r[0], 0x20);
        let r = s.handle(&mut od, &[0x10, 1, 2, 3, 4, 5, 6, 7], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0607_0012));
        // toggle error
        s.handle(&mut od, &[0x21, 0x00, 0x20, 0, 4, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x17, 1, 2, 3, 4, 0, 0, 0], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0503_0000));
        assert_eq!(od.v, 0xDDCC_BBAA);
    }

    #[test]
    fn timeout_aborts_stalled_transfer() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        s.handle(&mut od, &[0x40, 0x02, 0x20, 0, 0, 0, 0, 0], 10)
            .unwrap();
        assert_eq!(s.check_timeout(500), None);
        s.handle(&mut od, &[0x60, 0, 0, 0, 0, 0, 0, 0], 900)
            .unwrap();
        assert_eq!(s.check_timeout(1800), None);
        let r = s.check_timeout(1900).unwrap();
        assert_eq!(abort_code(&r), Some(0x0504_0000));
        assert_eq!(&r[1..4], &[0x02, 0x20, 0]);
        assert!(!s.busy());
    }

    #[test]
    fn deferred_write_is_confirmed_later() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        assert_eq!(
            s.handle(&mut od, &[0x23, 0x03, 0x20, 0, 1, 0, 0, 0], 0),
            None
        );
        assert!(s.deferred());
        assert_eq!(s.complete(None).unwrap(), [0x60, 0x03, 0x20, 0, 0, 0, 0, 0]);
        assert_eq!(s.complete(None), None);
        assert_eq!(
            s.handle(&mut od, &[0x23, 0x03, 0x20, 0, 1, 0, 0, 0], 0),
            None
        );
        let r = s.complete(Some(SdoAbort::Store)).unwrap();
        assert_eq!(abort_code(&r), Some(0x0800_0020));
    }

    /// Issue 49: a request while a write is with the application is
    /// refused with 0x08000020 on the deferred object, and that abort ends
    /// the deferred transfer: its confirmation never follows. Requests
    /// until the application is done are refused on their own object.
    #[test]
    fn abort_while_deferred_ends_the_transfer() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        assert_eq!(
            s.handle(&mut od, &[0x23, 0x03, 0x20, 0, 1, 0, 0, 0], 0),
            None
        );
        let r = s
            .handle(&mut od, &[0x40, 0x00, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0800_0020));
        assert_eq!(&r[1..4], &[0x03, 0x20, 0], "the deferred transfer's object");
        let r = s
            .handle(&mut od, &[0x40, 0x02, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(abort_code(&r), Some(0x0800_0020));
        assert_eq!(&r[1..4], &[0x02, 0x20, 0], "a later request's own object");
        assert!(s.deferred(), "the application still holds the write");
        assert_eq!(s.complete(None), None, "no confirmation after the abort");
        assert!(!s.busy());
        // A client's abort meanwhile: nothing answered, nothing confirmed.
        s.handle(&mut od, &[0x23, 0x03, 0x20, 0, 1, 0, 0, 0], 0);
        assert_eq!(
            s.handle(&mut od, &[0x80, 0x03, 0x20, 0, 0, 0, 0, 0], 0),
            None
        );
        assert_eq!(s.complete(Some(SdoAbort::Store)), None);
        // The server serves again.
        let r = s
            .handle(&mut od, &[0x40, 0x00, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        assert_eq!(r[0], 0x43);
    }

    /// Issue 49: a segment that does not fit the transfer in progress is
    /// aborted with that transfer's object, and the transfer ends.
    #[test]
    fn stray_segment_aborts_with_the_transfers_object() {
        let mut s = SdoServer::new(1000);
        let mut od = mini();
        // A download segment in a segmented upload of 0x2002.
        s.handle(&mut od, &[0x40, 0x02, 0x20, 0, 0, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x00, 1, 2, 3, 4, 5, 6, 7], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0504_0001));
        assert_eq!(&r[1..4], &[0x02, 0x20, 0]);
        assert!(!s.busy());
        // An upload segment in a segmented download of 0x2000.
        s.handle(&mut od, &[0x21, 0x00, 0x20, 0, 4, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x60, 0, 0, 0, 0, 0, 0, 0], 0).unwrap();
        assert_eq!(abort_code(&r), Some(0x0504_0001));
        assert_eq!(&r[1..4], &[0x00, 0x20, 0]);
        assert!(!s.busy());
        // A short frame in a transfer: that transfer's object too.
        s.handle(&mut od, &[0x21, 0x00, 0x20, 0, 4, 0, 0, 0], 0)
            .unwrap();
        let r = s.handle(&mut od, &[0x00, 0x99, 0x99], 0).unwrap();
        assert_eq!(&r[1..4], &[0x00, 0x20, 0]);
        // No transfer: no object to name.
        let r = s.handle(&mut od, &[0x60, 0, 0, 0, 0, 0, 0, 0], 0).unwrap();
        assert_eq!(&r[1..8], &[0, 0, 0, 0x01, 0x00, 0x04, 0x05]);
    }

    #[test]
    fn codes_round_trip() {
        for a in SdoAbort::ALL {
            assert_eq!(SdoAbort::from_code(a.code()), Some(a));
        }
        assert_eq!(SdoAbort::from_code(1), None);
    }
}
