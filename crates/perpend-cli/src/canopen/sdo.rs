//! SDO client (CiA 301 §7.2.4): expedited and segmented upload and
//! download on the default channel (`0x600+id` → `0x580+id`), toggle and
//! multiplexer checks, the client's abort (0x05040000) sent when the server
//! does not answer in time, and typed helpers for the dictionary's types.
//!
//! Block download with CRC (CiA 301 §7.2.4.3.10-16, [`Client::download_block`]):
//! sub-blocks of the server's blksize sent back to back, resent from the
//! server's ackseq (the segments resent are counted), CRC-16-CCITT at the
//! end; a server without block transfer (abort 0x05040001 to the
//! initiate) gets a segmented download instead. The wait for a
//! sub-block's acknowledgement is at least [`BLOCK_ACK_WAIT`]: a server
//! learns of a lost tail of a sub-block only from its own timer (issue
//! 49).
//!
//! Limits: no block upload; an upload larger than [`MAX_UPLOAD`] bytes is
//! aborted.

use std::time::Duration;

use perpend_can::Frame;

use super::{Client, ClientError};

/// Largest upload accepted \[bytes\].
pub const MAX_UPLOAD: usize = 4096;

/// Least wait for the acknowledgement of a sub-block: far above the
/// board's gap timer (`perpend_can::sdo::block::BLOCK_GAP_US`, 20 ms),
/// after which it acknowledges a sub-block whose last segments were lost,
/// and above the 0.7 s after which a board before issue 49 (and
/// CANopenNode's server at a 1 s SDO timeout) does.
pub const BLOCK_ACK_WAIT: Duration = Duration::from_millis(900);

/// Abort code the client sends: SDO protocol timed out.
const ABORT_TIMEOUT: u32 = 0x0504_0000;
/// Abort code the client sends: toggle bit not alternated.
const ABORT_TOGGLE: u32 = 0x0503_0000;
/// Abort code the client sends: command specifier not valid.
const ABORT_COMMAND: u32 = 0x0504_0001;
/// Abort code the client sends: invalid block size.
const ABORT_BLKSIZE: u32 = 0x0504_0002;
/// Abort code the client sends: invalid sequence number.
const ABORT_SEQNO: u32 = 0x0504_0003;

/// One transfer's address and direction, for messages.
#[derive(Debug, Clone, Copy)]
struct Ctx {
    node: u8,
    index: u16,
    sub: u8,
    write: bool,
}

impl Ctx {
    fn what(&self) -> String {
        if self.write {
            format!("SDO write of {:#06x} sub {}", self.index, self.sub)
        } else {
            format!("SDO read of {:#06x} sub {}", self.index, self.sub)
        }
    }

    fn mux(&self) -> [u8; 3] {
        let i = self.index.to_le_bytes();
        [i[0], i[1], self.sub]
    }

    fn protocol(&self, what: &str) -> ClientError {
        ClientError::Protocol {
            node: self.node,
            what: format!("{}: {what}", self.what()),
        }
    }
}

impl Client {
    /// Sends an abort for `ctx` (best effort: the transfer already failed).
    fn send_abort(&mut self, ctx: &Ctx, code: u32) {
        let m = ctx.mux();
        let c = code.to_le_bytes();
        let f = Frame::new(
            0x600 + ctx.node as u16,
            &[0x80, m[0], m[1], m[2], c[0], c[1], c[2], c[3]],
        );
        let _ = self.send(&f);
    }

    /// Sends one request and waits for the server's answer.
    fn exchange(
        &mut self,
        ctx: &Ctx,
        req: [u8; 8],
        timeout: Duration,
    ) -> Result<[u8; 8], ClientError> {
        self.send(&Frame::new(0x600 + ctx.node as u16, &req))?;
        self.answer(ctx, timeout)
    }

    /// Waits for the server's answer (an abort is an error; none in
    /// `timeout` is answered with the client's abort 0x05040000).
    fn answer(&mut self, ctx: &Ctx, timeout: Duration) -> Result<[u8; 8], ClientError> {
        let id = 0x580 + ctx.node as u16;
        match self.wait_for(timeout, |f| f.id == id && f.len == 8 && !f.rtr)? {
            Some(f) if f.data[0] == 0x80 => Err(ClientError::Abort {
                node: ctx.node,
                index: ctx.index,
                sub: ctx.sub,
                code: u32::from_le_bytes([f.data[4], f.data[5], f.data[6], f.data[7]]),
                write: ctx.write,
            }),
            Some(f) => Ok(f.data),
            None => {
                self.send_abort(ctx, ABORT_TIMEOUT);
                Err(self.timeout_error(ctx.node, &ctx.what(), timeout))
            }
        }
    }

    /// Checks an initiate answer: command `expect` (under `mask`) and the
    /// multiplexer.
    fn check_initiate(
        &mut self,
        ctx: &Ctx,
        resp: &[u8; 8],
        mask: u8,
        expect: u8,
    ) -> Result<(), ClientError> {
        if resp[0] & mask != expect {
            self.send_abort(ctx, ABORT_COMMAND);
            return Err(ctx.protocol(&format!("unexpected answer command {:#04x}", resp[0])));
        }
        if resp[1..4] != ctx.mux() {
            return Err(ctx.protocol(&format!(
                "the answer is for {:#06x} sub {}",
                u16::from_le_bytes([resp[1], resp[2]]),
                resp[3]
            )));
        }
        Ok(())
    }

    /// Reads `(index, sub)` of `node`: the value's bytes.
    ///
    /// # Errors
    /// [`ClientError`]: timeout, abort (with its sentence), protocol error.
    pub fn upload(&mut self, node: u8, index: u16, sub: u8) -> Result<Vec<u8>, ClientError> {
        let ctx = Ctx {
            node,
            index,
            sub,
            write: false,
        };
        let m = ctx.mux();
        let t = self.timeout;
        let resp = self.exchange(&ctx, [0x40, m[0], m[1], m[2], 0, 0, 0, 0], t)?;
        self.check_initiate(&ctx, &resp, 0xE0, 0x40)?;
        if resp[0] & 0x02 != 0 {
            let n = if resp[0] & 0x01 != 0 {
                4 - ((resp[0] >> 2) & 3) as usize
            } else {
                4
            };
            return Ok(resp[4..4 + n].to_vec());
        }
        let size = (resp[0] & 0x01 != 0)
            .then(|| u32::from_le_bytes([resp[4], resp[5], resp[6], resp[7]]) as usize);
        if size.is_some_and(|s| s > MAX_UPLOAD) {
            self.send_abort(&ctx, ABORT_COMMAND);
            return Err(ctx.protocol(&format!(
                "the value is {} bytes, more than the {MAX_UPLOAD} accepted",
                size.unwrap_or(0)
            )));
        }
        let data = self.upload_segments(&ctx)?;
        match size {
            Some(s) if s != data.len() => Err(ctx.protocol(&format!(
                "the server announced {s} bytes and sent {}",
                data.len()
            ))),
            _ => Ok(data),
        }
    }

    /// The segments of a segmented upload.
    fn upload_segments(&mut self, ctx: &Ctx) -> Result<Vec<u8>, ClientError> {
        let mut data = Vec::new();
        let mut toggle = 0u8;
        loop {
            let t = self.timeout;
            let resp = self.exchange(ctx, [0x60 | toggle, 0, 0, 0, 0, 0, 0, 0], t)?;
            if resp[0] & 0xE0 != 0x00 {
                self.send_abort(ctx, ABORT_COMMAND);
                return Err(ctx.protocol(&format!("unexpected segment command {:#04x}", resp[0])));
            }
            if resp[0] & 0x10 != toggle {
                self.send_abort(ctx, ABORT_TOGGLE);
                return Err(ctx.protocol("the toggle bit of a segment did not alternate"));
            }
            let n = 7 - ((resp[0] >> 1) & 7) as usize;
            data.extend_from_slice(&resp[1..1 + n]);
            if resp[0] & 0x01 != 0 {
                return Ok(data);
            }
            if data.len() > MAX_UPLOAD {
                self.send_abort(ctx, ABORT_COMMAND);
                return Err(ctx.protocol(&format!("more than {MAX_UPLOAD} bytes")));
            }
            toggle ^= 0x10;
        }
    }

    /// Writes `data` to `(index, sub)` of `node` (expedited up to 4 bytes,
    /// else segmented), waiting [`Client::timeout`] for each answer.
    ///
    /// # Errors
    /// [`ClientError`]: timeout, abort (with its sentence), protocol error.
    pub fn download(
        &mut self,
        node: u8,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), ClientError> {
        let t = self.timeout;
        self.download_timeout(node, index, sub, data, t)
    }

    /// [`Client::download`] with its own answer timeout (a store waits for
    /// the flash).
    ///
    /// # Errors
    /// As [`Client::download`].
    pub fn download_timeout(
        &mut self,
        node: u8,
        index: u16,
        sub: u8,
        data: &[u8],
        timeout: Duration,
    ) -> Result<(), ClientError> {
        let ctx = Ctx {
            node,
            index,
            sub,
            write: true,
        };
        let m = ctx.mux();
        if !data.is_empty() && data.len() <= 4 {
            let mut req = [
                0x23 | (((4 - data.len()) as u8) << 2),
                m[0],
                m[1],
                m[2],
                0,
                0,
                0,
                0,
            ];
            req[4..4 + data.len()].copy_from_slice(data);
            let resp = self.exchange(&ctx, req, timeout)?;
            return self.check_initiate(&ctx, &resp, 0xFF, 0x60);
        }
        let l = (data.len() as u32).to_le_bytes();
        let req = [0x21, m[0], m[1], m[2], l[0], l[1], l[2], l[3]];
        let resp = self.exchange(&ctx, req, self.timeout)?;
        self.check_initiate(&ctx, &resp, 0xFF, 0x60)?;
        let mut toggle = 0u8;
        let chunks: Vec<&[u8]> = data.chunks(7).collect();
        for (k, chunk) in chunks.iter().enumerate() {
            let last = u8::from(k + 1 == chunks.len());
            let mut req = [
                toggle | (((7 - chunk.len()) as u8) << 1) | last,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            ];
            req[1..1 + chunk.len()].copy_from_slice(chunk);
            let wait = if last == 1 { timeout } else { self.timeout };
            let resp = self.exchange(&ctx, req, wait)?;
            if resp[0] != 0x20 | toggle {
                self.send_abort(&ctx, ABORT_TOGGLE);
                return Err(ctx.protocol(&format!("unexpected segment answer {:#04x}", resp[0])));
            }
            toggle ^= 0x10;
        }
        Ok(())
    }

    /// Writes `data` to `(index, sub)` of `node` by SDO block download
    /// with CRC; `progress` gets the bytes the server acknowledged after
    /// each sub-block. A server that refuses block transfer (0x05040001)
    /// gets a segmented download; `timeout` is the wait for the last
    /// answer (the server may write to flash then); each sub-block's
    /// acknowledgement is awaited at least [`BLOCK_ACK_WAIT`]. Returns the
    /// number of segments sent again after the server's ackseq (0 on a
    /// clean bus).
    ///
    /// # Errors
    /// [`ClientError`]: timeout, abort (with its sentence), protocol error
    /// (a block size or ackseq out of range: the client aborts with
    /// 0x05040002 / 0x05040003).
    pub fn download_block(
        &mut self,
        node: u8,
        (index, sub): (u16, u8),
        data: &[u8],
        timeout: Duration,
        progress: &mut dyn FnMut(usize),
    ) -> Result<usize, ClientError> {
        let ctx = Ctx {
            node,
            index,
            sub,
            write: true,
        };
        if data.is_empty() {
            return Err(ctx.protocol("no data to write (a block download needs at least 1 byte)"));
        }
        let (m, l) = (ctx.mux(), (data.len() as u32).to_le_bytes());
        let req = [0xC6, m[0], m[1], m[2], l[0], l[1], l[2], l[3]];
        let t = self.timeout;
        let resp = match self.exchange(&ctx, req, t) {
            Err(e) if e.abort_code() == Some(ABORT_COMMAND) => {
                self.download_timeout(node, index, sub, data, timeout)?;
                progress(data.len());
                return Ok(0);
            }
            r => r?,
        };
        self.check_initiate(&ctx, &resp, 0xFB, 0xA0)?;
        let crc_on = resp[0] & 0x04 != 0;
        let mut blksize = self.check_blksize(&ctx, resp[4])?;
        let (mut pos, mut resent) = (0usize, 0usize);
        loop {
            let sent = self.send_sub_block(&ctx, data, pos, blksize)?;
            let wait = if pos + 7 * sent >= data.len() {
                timeout
            } else {
                t
            };
            let ack = self.answer(&ctx, wait.max(BLOCK_ACK_WAIT))?;
            if ack[0] != 0xA2 {
                self.send_abort(&ctx, ABORT_COMMAND);
                return Err(ctx.protocol(&format!("unexpected block answer {:#04x}", ack[0])));
            }
            if usize::from(ack[1]) > sent {
                self.send_abort(&ctx, ABORT_SEQNO);
                return Err(ctx.protocol(&format!(
                    "the server acknowledged segment {} of {sent}",
                    ack[1]
                )));
            }
            resent += sent - usize::from(ack[1]);
            pos = (pos + 7 * usize::from(ack[1])).min(data.len());
            progress(pos);
            blksize = self.check_blksize(&ctx, ack[2])?;
            if pos == data.len() {
                break;
            }
        }
        self.end_block(&ctx, data, crc_on, timeout)?;
        Ok(resent)
    }

    /// The end of a block download: unused bytes of the last segment and
    /// the CRC (0 when the server computes none); the server's `A1`.
    fn end_block(
        &mut self,
        ctx: &Ctx,
        data: &[u8],
        crc_on: bool,
        timeout: Duration,
    ) -> Result<(), ClientError> {
        let n = ((7 - data.len() % 7) % 7) as u8;
        let crc = if crc_on {
            perpend_can::sdo::block::crc16_ccitt(data, 0)
        } else {
            0
        };
        let c = crc.to_le_bytes();
        let resp = self.exchange(ctx, [0xC1 | n << 2, c[0], c[1], 0, 0, 0, 0, 0], timeout)?;
        if resp[0] != 0xA1 {
            self.send_abort(ctx, ABORT_COMMAND);
            return Err(ctx.protocol(&format!("unexpected block end answer {:#04x}", resp[0])));
        }
        Ok(())
    }

    /// A block size from the server, 1..=127 (else the client aborts).
    fn check_blksize(&mut self, ctx: &Ctx, b: u8) -> Result<u8, ClientError> {
        if (1..=127).contains(&b) {
            return Ok(b);
        }
        self.send_abort(ctx, ABORT_BLKSIZE);
        Err(ctx.protocol(&format!("invalid block size {b}")))
    }

    /// Sends up to `blksize` segments of `data` from byte `pos` (the last
    /// one of the data flagged): how many were sent.
    fn send_sub_block(
        &mut self,
        ctx: &Ctx,
        data: &[u8],
        pos: usize,
        blksize: u8,
    ) -> Result<usize, ClientError> {
        let rest = data.get(pos..).unwrap_or(&[]);
        let mut chunks = rest.chunks(7).take(usize::from(blksize)).peekable();
        let mut k = 0usize;
        while let Some(chunk) = chunks.next() {
            k += 1;
            let last = chunks.peek().is_none() && pos + 7 * k >= data.len();
            let mut seg = [0u8; 8];
            seg[0] = k as u8 | if last { 0x80 } else { 0 };
            seg[1..1 + chunk.len()].copy_from_slice(chunk);
            self.send(&Frame::new(0x600 + ctx.node as u16, &seg))?;
        }
        Ok(k)
    }

    /// Reads an UNSIGNED8/16/32 (any length up to 4 bytes, little endian).
    ///
    /// # Errors
    /// As [`Client::upload`], or a value longer than 4 bytes.
    pub fn read_u32(&mut self, node: u8, index: u16, sub: u8) -> Result<u32, ClientError> {
        let v = self.upload(node, index, sub)?;
        if v.is_empty() || v.len() > 4 {
            return Err(ClientError::Protocol {
                node,
                what: format!(
                    "{index:#06x} sub {sub} sent {} bytes for an integer",
                    v.len()
                ),
            });
        }
        let mut b = [0u8; 4];
        b[..v.len()].copy_from_slice(&v);
        Ok(u32::from_le_bytes(b))
    }

    /// Reads a REAL32.
    ///
    /// # Errors
    /// As [`Client::upload`], or a value that is not 4 bytes.
    pub fn read_f32(&mut self, node: u8, index: u16, sub: u8) -> Result<f32, ClientError> {
        let v = self.upload(node, index, sub)?;
        let b: [u8; 4] = v.as_slice().try_into().map_err(|_| ClientError::Protocol {
            node,
            what: format!("{index:#06x} sub {sub} sent {} bytes for a REAL32", v.len()),
        })?;
        Ok(f32::from_le_bytes(b))
    }

    /// Reads a VISIBLE_STRING (trailing NULs dropped, invalid UTF-8
    /// replaced).
    ///
    /// # Errors
    /// As [`Client::upload`].
    pub fn read_string(&mut self, node: u8, index: u16, sub: u8) -> Result<String, ClientError> {
        let v = self.upload(node, index, sub)?;
        let end = v.iter().rposition(|&b| b != 0).map_or(0, |p| p + 1);
        Ok(String::from_utf8_lossy(&v[..end]).into_owned())
    }

    /// Writes an UNSIGNED32.
    ///
    /// # Errors
    /// As [`Client::download`].
    pub fn write_u32(&mut self, node: u8, index: u16, sub: u8, v: u32) -> Result<(), ClientError> {
        self.download(node, index, sub, &v.to_le_bytes())
    }
}

#[cfg(test)]
#[path = "sdo_tests.rs"]
mod tests;
