//! SDO abort codes (CiA 301 §7.2.4.3.17) in words: what the board means by
//! each and, where there is one, what to do about it.

/// The sentence for an abort code.
pub fn describe(code: u32) -> &'static str {
    match code {
        0x0503_0000 => {
            "the toggle bit did not alternate: the transfer got out of step (is another \
             master using the same SDO channel?)"
        }
        0x0504_0000 => "the SDO transfer timed out on the board's side",
        0x0504_0001 => {
            "the board does not know this SDO command (a firmware without block transfer?)"
        }
        0x0504_0002 => "the SDO block size is invalid",
        0x0504_0003 => "an SDO block segment's sequence number is invalid",
        0x0504_0004 => "the CRC of the SDO block download does not match: the data were damaged",
        0x0504_0005 => "the board ran out of memory",
        0x0601_0000 => "this access to the object is not supported",
        0x0601_0001 => "the object is write-only",
        0x0601_0002 => "the object is read-only",
        0x0602_0000 => {
            "the object does not exist in the board's dictionary (another firmware version, \
             or another device at this node-id?)"
        }
        0x0604_0041 => "the object cannot be mapped into a PDO",
        0x0604_0042 => "the mapped objects would not fit into the PDO's 8 bytes",
        0x0604_0043 => "the mapping length does not match the object",
        0x0604_0047 => "an internal incompatibility of the device",
        0x0606_0000 => "the access failed because of a hardware error",
        0x0607_0010 => "the data length does not match the object's type",
        0x0607_0012 => "the data is too long for the object",
        0x0607_0013 => "the data is too short for the object",
        0x0609_0011 => "the sub-index does not exist",
        0x0609_0030 => "the value is not valid for this object",
        0x0609_0031 => "the value is too high for this object",
        0x0609_0032 => "the value is too low for this object",
        0x0609_0036 => "the maximum value is less than the minimum value",
        0x0800_0000 => "a general error of the board",
        0x0800_0020 => {
            "the board cannot store or transfer the data now (a wrong signature for \
             0x1010/0x1011, a store still in progress, or the flash write failed)"
        }
        0x0800_0021 => {
            "calibration is locked: write \"ucal\" (0x6C616375) to 0x2010 first (`perpend node \
             push` does; any NMT state change locks it again)"
        }
        0x0800_0022 => {
            "the board refuses this in its current NMT state: put it in pre-operational first \
             (`perpend node … nmt preop`)"
        }
        0x0800_0023 => "the board's object dictionary is not available",
        0x0800_0024 => "no data is available",
        _ => "an abort code that CiA 301 does not list",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_the_board_sends_has_its_own_sentence() {
        let unknown = describe(0x1234_5678);
        for a in perpend_can::SdoAbort::ALL {
            let s = describe(a.code());
            assert_ne!(s, unknown, "{:#010x}", a.code());
        }
        assert!(describe(0x0800_0022).contains("pre-operational"));
        assert!(describe(0x0800_0021).contains("0x2010"));
    }
}
