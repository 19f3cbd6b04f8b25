//! `perpend board --fault bus:block-tail:N:K`: the last K segments of the
//! N-th sub-block of the client's next SDO block download never reach
//! the board (issue 49), as when a bus error or an overrun takes the tail
//! of a sub-block. No later frame then ends the sub-block early: the
//! board acknowledges it with its gap timer
//! (`perpend_can::sdo::block::BLOCK_GAP_US`) and the client resends from
//! the ackseq.
//!
//! The fault follows the transfer on the bus: a block download initiate
//! from the client (`0xC0`-`0xC6` on 0x600+id) arms it; the board's
//! initiate answer (`0xA4`) and each acknowledgement (`0xA2`) give the
//! block size of the next sub-block; every segment with seqno 1 starts a
//! sub-block (a sub-block resent after an ackseq counts as one). In the
//! N-th one the segments with seqno above blksize − K are dropped (of a
//! last, shorter sub-block only those it has); the acknowledgement of
//! that sub-block ends the fault. An abort from either side disarms it
//! until the next initiate. Each fault fires once; several may be given
//! (they count the same sub-blocks of the same transfer).

use anyhow::{bail, Result};
use perpend_can::Frame;

/// One `bus:block-tail:N:K`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockTail {
    /// Which sub-block of the transfer (1 = the first).
    pub sub_block: u32,
    /// How many of its last segments are lost (1..=127).
    pub segments: u8,
}

impl std::str::FromStr for BlockTail {
    type Err = anyhow::Error;
    /// Parses `N:K` (after `bus:block-tail:`).
    fn from_str(s: &str) -> Result<Self> {
        let mut it = s.split(':').map(str::trim);
        let n = it.next().and_then(|t| t.parse::<u32>().ok());
        let k = it.next().and_then(|t| t.parse::<u8>().ok());
        match (n, k, it.next()) {
            (Some(sub_block @ 1..), Some(segments @ 1..=127), None) => Ok(Self {
                sub_block,
                segments,
            }),
            _ => bail!(
                "--fault 'bus:block-tail:{s}': expected bus:block-tail:N:K (N ≥ 1: the N-th \
                 sub-block of the next SDO block download; K 1..127: its last K segments lost)"
            ),
        }
    }
}

/// Where a [`BlockTail`] stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Waiting for a block download initiate.
    Idle,
    /// In a block download of `node`: `count` sub-blocks begun, the
    /// board's block size `blksize`.
    Armed { node: u8, count: u32, blksize: u8 },
    /// Fired (once).
    Done,
}

/// The block-tail faults of a run.
#[derive(Debug, Clone, Default)]
pub struct BlockTails(Vec<(BlockTail, Phase)>);

impl BlockTails {
    /// The faults of the arguments, none fired.
    pub fn new(faults: impl IntoIterator<Item = BlockTail>) -> Self {
        Self(faults.into_iter().map(|f| (f, Phase::Idle)).collect())
    }

    /// Looks at the client's `frames` of one turn in order and removes
    /// the segments that are lost; returns how many.
    pub fn apply(&mut self, frames: &mut Vec<Frame>) -> usize {
        if self.0.is_empty() {
            return 0;
        }
        let before = frames.len();
        frames.retain(|f| !self.client_frame(f));
        before - frames.len()
    }

    /// One frame from the client: `true` when it is lost.
    fn client_frame(&mut self, f: &Frame) -> bool {
        if !(0x601..=0x67F).contains(&f.id) || f.len != 8 || f.rtr {
            return false;
        }
        let node = (f.id - 0x600) as u8;
        let cmd = f.data[0];
        let mut lost = false;
        for (fault, phase) in &mut self.0 {
            match *phase {
                Phase::Idle if cmd & 0xE1 == 0xC0 => {
                    *phase = Phase::Armed {
                        node,
                        count: 0,
                        blksize: 127,
                    };
                }
                Phase::Armed { node: n, .. } if n == node && cmd == 0x80 => {
                    *phase = Phase::Idle;
                }
                Phase::Armed {
                    node: n,
                    ref mut count,
                    blksize,
                } if n == node => {
                    let seqno = cmd & 0x7F;
                    if seqno == 1 {
                        *count += 1;
                    }
                    let tail = blksize.saturating_sub(fault.segments);
                    if *count == fault.sub_block && seqno > tail && seqno <= blksize {
                        lost = true;
                    }
                }
                _ => {}
            }
        }
        if lost {
            eprintln!(
                "perpend board: fault: segment {} of a block download lost",
                cmd & 0x7F
            );
        }
        lost
    }

    /// One frame from a board: its block size, acknowledgements and
    /// aborts.
    pub fn observe(&mut self, f: &Frame) {
        if !(0x581..=0x5FF).contains(&f.id) || f.len != 8 {
            return;
        }
        let node = (f.id - 0x580) as u8;
        let d = f.data;
        for (fault, phase) in &mut self.0 {
            let Phase::Armed {
                node: n,
                count,
                ref mut blksize,
            } = *phase
            else {
                continue;
            };
            if n != node {
                continue;
            }
            match d[0] {
                0x80 => *phase = Phase::Idle,
                0xA4 | 0xA0 => *blksize = d[4],
                0xA2 if count >= fault.sub_block => *phase = Phase::Done,
                0xA2 => *blksize = d[2],
                _ => {}
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn client(data: [u8; 8]) -> Frame {
        Frame::new(0x610, &data)
    }

    fn board(data: [u8; 8]) -> Frame {
        Frame::new(0x590, &data)
    }

    #[test]
    fn parses_and_refuses() {
        let t: BlockTail = "2:5".parse().unwrap();
        assert_eq!(
            t,
            BlockTail {
                sub_block: 2,
                segments: 5
            }
        );
        for bad in ["0:1", "1:0", "1:128", "1", "1:2:3", "x:1"] {
            assert!(bad.parse::<BlockTail>().is_err(), "{bad}");
        }
    }

    /// Sub-block 2 loses its last 3 segments, once; other nodes, other
    /// sub-blocks and the resent sub-block pass.
    #[test]
    fn drops_the_tail_of_the_nth_sub_block_once() {
        let mut t = BlockTails::new([BlockTail {
            sub_block: 2,
            segments: 3,
        }]);
        let sub_block =
            |n: u8| -> Vec<Frame> { (1..=n).map(|k| client([k, 0, 0, 0, 0, 0, 0, 0])).collect() };
        let mut f = vec![client([0xC6, 0x50, 0x1F, 1, 0, 0x10, 0, 0])];
        assert_eq!(t.apply(&mut f), 0);
        t.observe(&board([0xA4, 0x50, 0x1F, 1, 10, 0, 0, 0]));
        let mut f = sub_block(10);
        assert_eq!(t.apply(&mut f), 0, "sub-block 1 whole");
        t.observe(&board([0xA2, 10, 10, 0, 0, 0, 0, 0]));
        let mut f = sub_block(10);
        f.push(Frame::new(0x611, &[9, 0, 0, 0, 0, 0, 0, 0]));
        assert_eq!(t.apply(&mut f), 3);
        let seq: Vec<u8> = f.iter().map(|f| f.data[0]).collect();
        assert_eq!(seq, [1, 2, 3, 4, 5, 6, 7, 9], "another node's frame passes");
        t.observe(&board([0xA2, 7, 10, 0, 0, 0, 0, 0]));
        let mut f = sub_block(10);
        assert_eq!(t.apply(&mut f), 0, "the resent sub-block passes");
    }

    /// An abort disarms until the next initiate.
    #[test]
    fn an_abort_disarms() {
        let mut t = BlockTails::new([BlockTail {
            sub_block: 1,
            segments: 1,
        }]);
        let mut f = vec![client([0xC6, 0x50, 0x1F, 1, 0, 0, 0, 0])];
        t.apply(&mut f);
        t.observe(&board([0x80, 0x50, 0x1F, 1, 0, 0, 0x22, 8]));
        let mut f: Vec<Frame> = (1..=127)
            .map(|k| client([k, 0, 0, 0, 0, 0, 0, 0]))
            .collect();
        assert_eq!(t.apply(&mut f), 0);
    }
}
