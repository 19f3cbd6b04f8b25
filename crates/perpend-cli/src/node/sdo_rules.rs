//! The board's write rules that an EDS cannot state (CiA 306 gives an
//! entry only `LowLimit`/`HighLimit`): a power of two (0x2300 sub 2), one
//! of a list, and the acquisition's period and oversampling checked
//! together (one ADC scan must fit into the period; docs/can.md, "Period
//! and oversampling").
//!
//! `perpend node sdo write` checks the first two before sending
//! ([`precheck`]), and when the node refuses a value with 0x06090030..32
//! the hint says the rule that refused it ([`range_hint`]) instead of
//! limits the value is inside. Values come in as unsigned integers (the
//! only kind these rules are about), so that `sdo.rs` imports this file
//! and not the other way round. A rule applies only to an EDS entry that is
//! the board's own object (same index, sub-index and name in
//! [`perpend_can::od`]), so another vendor's EDS gets no perpend rule.

use perpend_board::scan;
use perpend_can::od::{self, Limits};

use super::Node;
use crate::eds::Entry;

/// The board's descriptor of the EDS entry `e`, when `e` is the board's.
fn board_entry(e: &Entry) -> Option<&'static od::Entry> {
    od::find(e.index, e.sub)
        .ok()
        .map(|(_, b)| b)
        .filter(|b| b.name == e.name)
}

/// A value inside the EDS limits that the board's own rule for this entry
/// refuses (not a power of two, not one of the listed values).
///
/// # Errors
/// The rule, in a sentence naming the values the board takes.
pub fn precheck(e: &Entry, x: Option<u64>) -> Result<(), String> {
    let (Some(b), Some(x)) = (board_entry(e), x) else {
        return Ok(());
    };
    match b.limits {
        Limits::PowerOfTwo(lo, hi) if !(x.is_power_of_two() && (lo..=hi).contains(&(x as u32))) => {
            let list: Vec<String> = (0..32)
                .map(|k| 1u64 << k)
                .filter(|p| (u64::from(lo)..=u64::from(hi)).contains(p))
                .map(|p| p.to_string())
                .collect();
            Err(format!(
                "{x} is not a power of two: the board takes {}",
                list.join(", ")
            ))
        }
        Limits::OneOf(list) if !list.iter().any(|&l| u64::from(l) == x) => {
            let list: Vec<String> = list.iter().map(|l| l.to_string()).collect();
            Err(format!("{x} is not one of {}", list.join(", ")))
        }
        _ => Ok(()),
    }
}

/// Period (0x2300 sub 1) against oversampling (sub 2): the hint when a
/// scan at the ratio would not fit into the period; `None` when that is
/// not why the node refused, or the other value cannot be read.
fn scan_rule(node: &mut Node, e: &Entry, x: u64, link: &str) -> Option<String> {
    if e.index != 0x2300 || board_entry(e).is_none() {
        return None;
    }
    let x = u32::try_from(x).ok()?;
    match e.sub {
        2 if x.is_power_of_two() => {
            let period = node.client.read_u32(node.id, 0x2300, 1).ok()?;
            let min = scan::min_period_us(x);
            (!scan::fits(period, x)).then(|| {
                format!(
                    "one ADC scan at {x}× oversampling takes {min} µs, longer than the sample \
                     period of {period} µs (0x2300 sub 1): write the period first \
                     (`{link} sdo write 0x2300 1 {min}` or more), then the oversampling"
                )
            })
        }
        1 => {
            let ratio = node.client.read_u32(node.id, 0x2300, 2).ok()?;
            let min = scan::min_period_us(ratio);
            (!scan::fits(x, ratio)).then(|| {
                format!(
                    "a sample period of {x} µs is shorter than one ADC scan at the present \
                     {ratio}× oversampling ({min} µs, 0x2300 sub 2): lower the oversampling \
                     first (`{link} sdo write 0x2300 2 N`), then the period"
                )
            })
        }
        _ => None,
    }
}

/// What to do after the node refused the unsigned value `x` for `e`
/// with a value-range abort (0x06090030..32): the board's rule that
/// refused it, `None` when no rule of the board's explains it (the
/// caller then speaks of the EDS limits).
pub fn range_hint(node: &mut Node, e: &Entry, x: Option<u64>, link: &str) -> Option<String> {
    let x = x?;
    scan_rule(node, e, x, link).or_else(|| precheck(e, Some(x)).err())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::eds::Eds;

    fn entry(index: u16, sub: u8) -> Entry {
        Eds::builtin().unwrap().get(index, sub).unwrap().clone()
    }

    #[test]
    fn oversampling_must_be_a_power_of_two_inside_the_eds_limits() {
        let e = entry(0x2300, 2);
        let why = precheck(&e, Some(3)).unwrap_err();
        assert!(why.contains("not a power of two"), "{why}");
        assert!(why.contains("1, 2, 4, 8, 16, 32, 64, 128, 256"), "{why}");
        assert!(precheck(&e, Some(256)).is_ok());
        assert!(precheck(&e, None).is_ok(), "not an integer: no rule");
    }

    #[test]
    fn another_vendors_entry_gets_no_board_rule() {
        let mut e = entry(0x2300, 2);
        e.name = "Something else".into();
        assert!(precheck(&e, Some(3)).is_ok());
    }
}
