//! Electronic Data Sheet (CiA 306, EDS 4.0) generated from the object
//! dictionary table, so that the file integrators load can never disagree
//! with what the device answers. The committed `perpend.eds` at the
//! repository root is [`write()`] with [`crate::Defaults::nominal`]; a test
//! checks that they are identical.
//!
//! Node-relative defaults are written as `$NODEID+0x...`; integer limits
//! of writable objects as `LowLimit`/`HighLimit`. REAL32 limits are
//! written as a comment line `;Range=LO..HI` instead: CiA 306 makes both
//! keys optional and does not fix a notation for REAL limits, and
//! CanFestival's `objdictgen` refuses any non-integer `LowLimit` (python
//! canopen ignores one); the device enforces the range itself
//! (0x06090031/0x06090032). `LSS_Supported=1`: see [`crate::lss`].
//!
//! Limits: the file describes the nominal defaults; a board whose firmware
//! uses other defaults (serial number, calibrated head) reports its actual
//! values over SDO.

use core::fmt::{self, Write};

use crate::config::Defaults;
use crate::od::{self, Access, DataType, Init, Kind, Limits, Object, Text};

/// Date written to `[FileInfo]` (`MM-DD-YYYY`): the date of the dictionary
/// layout, changed by hand together with [`FILE_VERSION`].
pub const FILE_DATE: &str = "11-27-2026";
/// `FileVersion` of the EDS: increment when the dictionary changes.
pub const FILE_VERSION: u32 = 6;

fn access(a: Access) -> &'static str {
    match a {
        Access::Const => "const",
        Access::Ro => "ro",
        Access::Rw => "rw",
        Access::Wo => "wo",
    }
}

fn init_value(d: &Defaults, e: &od::Entry) -> InitText {
    let f = |x: f32| InitText::Real(x);
    match e.init {
        Init::Fixed(v) => InitText::Int(v, e.ty),
        Init::Node(0) => InitText::NodeId(0),
        Init::Node(base) => InitText::NodeId(base),
        Init::DeviceType => InitText::Int(d.device_type, e.ty),
        Init::Identity(k) => InitText::Int(
            match k {
                1 => d.identity.vendor_id,
                2 => d.identity.product_code,
                3 => d.identity.revision,
                _ => d.identity.serial,
            },
            e.ty,
        ),
        Init::Heartbeat => InitText::Int(d.heartbeat_ms as u32, e.ty),
        Init::Calibration(s, k) => f(d
            .calibration
            .get(s as usize)
            .and_then(|c| c.to_array().get(k as usize).copied())
            .unwrap_or(0.0)),
        Init::Transfer(s, k) => match d.transfer.get(s as usize) {
            Some(t) => match k {
                0 => InitText::Int(t.kind as u32, e.ty),
                1 => f(t.scale),
                2 => f(t.mm_at_low),
                _ => f(t.mm_at_high),
            },
            None => InitText::Int(0, e.ty),
        },
        Init::Acquisition(k) => {
            let a = &d.acquisition;
            match k {
                0 => InitText::Int(a.period_us, e.ty),
                1 => InitText::Int(a.oversampling as u32, e.ty),
                2 => InitText::Int(a.method as u32, e.ty),
                _ => f(a.residual_limit_mm),
            }
        }
        Init::ThermalTau => f(d.thermal_tau_s),
        Init::BitRate => InitText::Int(d.bit_rate_kbps as u32, e.ty),
        Init::Text(t) => InitText::Str(match t {
            Text::DeviceName => d.device_name,
            Text::HardwareVersion => d.hardware_version,
            Text::SoftwareVersion => d.software_version,
        }),
    }
}

enum InitText {
    Int(u32, DataType),
    Real(f32),
    NodeId(u32),
    Str(&'static str),
}

impl fmt::Display for InitText {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            InitText::Int(v, DataType::U8) => write!(f, "0x{v:02X}"),
            InitText::Int(v, DataType::U16) => write!(f, "0x{v:04X}"),
            InitText::Int(v, _) => write!(f, "0x{v:08X}"),
            InitText::Real(x) if x.is_nan() => write!(f, "nan"),
            InitText::Real(x) => write!(f, "{x:?}"),
            InitText::NodeId(0) => write!(f, "$NODEID+0x0"),
            InitText::NodeId(b) => write!(f, "$NODEID+0x{b:X}"),
            InitText::Str(s) => write!(f, "{s}"),
        }
    }
}

fn write_entry(w: &mut impl Write, d: &Defaults, section: &str, e: &od::Entry) -> fmt::Result {
    writeln!(w, "[{section}]")?;
    writeln!(w, "ParameterName={}", e.name)?;
    writeln!(w, "ObjectType=0x7")?;
    writeln!(w, "DataType=0x{:04X}", e.ty.code())?;
    writeln!(w, "AccessType={}", access(e.access))?;
    if e.ty == od::DataType::Domain {
        // A DOMAIN has no default value (CiA 306: the entry is left out).
    } else {
        writeln!(w, "DefaultValue={}", init_value(d, e))?;
    }
    writeln!(w, "PDOMapping={}", u8::from(e.pdo))?;
    match e.limits {
        Limits::Range(lo, hi) | Limits::PowerOfTwo(lo, hi) => {
            writeln!(w, "LowLimit={}", InitText::Int(lo, e.ty))?;
            writeln!(w, "HighLimit={}", InitText::Int(hi, e.ty))?;
        }
        Limits::Real(lo, hi) => {
            // CiA 306 leaves the notation of REAL limits open and
            // CanFestival's importer accepts integer limits only: the range
            // goes into a comment, the device enforces it (0x06090031/32).
            writeln!(w, ";Range={}..{}", InitText::Real(lo), InitText::Real(hi))?;
        }
        Limits::OneOf(set) => {
            let lo = set.iter().copied().min().unwrap_or(0);
            let hi = set.iter().copied().max().unwrap_or(0);
            writeln!(w, "LowLimit={}", InitText::Int(lo, e.ty))?;
            writeln!(w, "HighLimit={}", InitText::Int(hi, e.ty))?;
        }
        Limits::Any => {}
    }
    writeln!(w)
}

fn write_object(w: &mut impl Write, d: &Defaults, o: &Object) -> fmt::Result {
    match o.kind {
        Kind::Var => {
            let Some(e) = o.subs.first() else {
                return Ok(());
            };
            let mut s = SectionName::new();
            write!(s, "{:04X}", o.index)?;
            write_entry(w, d, s.as_str(), e)
        }
        Kind::Array | Kind::Record => {
            writeln!(w, "[{:04X}]", o.index)?;
            writeln!(w, "ParameterName={}", o.name)?;
            writeln!(w, "ObjectType=0x{:X}", o.kind.code())?;
            writeln!(w, "SubNumber=0x{:X}", o.subs.len())?;
            writeln!(w)?;
            for e in o.subs {
                let mut s = SectionName::new();
                write!(s, "{:04X}sub{:X}", o.index, e.sub)?;
                write_entry(w, d, s.as_str(), e)?;
            }
            Ok(())
        }
    }
}

/// A small fixed buffer for section names (`XXXXsubYY`).
struct SectionName {
    buf: [u8; 16],
    len: usize,
}

impl SectionName {
    fn new() -> Self {
        Self {
            buf: [0; 16],
            len: 0,
        }
    }
    fn as_str(&self) -> &str {
        core::str::from_utf8(&self.buf[..self.len]).unwrap_or("")
    }
}

impl Write for SectionName {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        let b = s.as_bytes();
        if self.len + b.len() > self.buf.len() {
            return Err(fmt::Error);
        }
        self.buf[self.len..self.len + b.len()].copy_from_slice(b);
        self.len += b.len();
        Ok(())
    }
}

fn write_list(
    w: &mut impl Write,
    title: &str,
    items: &mut dyn Iterator<Item = u16>,
) -> fmt::Result {
    let mut buf = [0u16; 64];
    let mut n = 0;
    for i in items {
        if n < buf.len() {
            buf[n] = i;
            n += 1;
        }
    }
    writeln!(w, "[{title}]")?;
    writeln!(w, "SupportedObjects={n}")?;
    for (k, i) in buf[..n].iter().enumerate() {
        writeln!(w, "{}=0x{i:04X}", k + 1)?;
    }
    writeln!(w)
}

/// Number of objects of the dictionary with an index in `range` (the PDO
/// communication objects for `NrOfRXPDO` / `NrOfTXPDO`).
fn count_objects(range: core::ops::RangeInclusive<u16>) -> usize {
    od::OBJECTS
        .iter()
        .filter(|o| range.contains(&o.index))
        .count()
}

/// Writes the EDS of the dictionary with the defaults `d`.
///
/// # Errors
/// Only those of `w`.
pub fn write(w: &mut impl Write, d: &Defaults) -> fmt::Result {
    writeln!(w, "[FileInfo]")?;
    writeln!(w, "FileName=perpend.eds")?;
    writeln!(w, "FileVersion={FILE_VERSION}")?;
    writeln!(w, "FileRevision=0")?;
    writeln!(w, "EDSVersion=4.0")?;
    writeln!(
        w,
        "Description=perpend surface-normal sensor board (generated by perpend-can)"
    )?;
    writeln!(w, "CreationTime=12:00PM")?;
    writeln!(w, "CreationDate={FILE_DATE}")?;
    writeln!(w, "CreatedBy=perpend-can")?;
    writeln!(w, "ModificationTime=12:00PM")?;
    writeln!(w, "ModificationDate={FILE_DATE}")?;
    writeln!(w, "ModifiedBy=perpend-can")?;
    writeln!(w)?;
    writeln!(w, "[DeviceInfo]")?;
    writeln!(w, "VendorName=perpend")?;
    writeln!(w, "VendorNumber=0x{:08X}", d.identity.vendor_id)?;
    writeln!(w, "ProductName={}", d.device_name)?;
    writeln!(w, "ProductNumber=0x{:08X}", d.identity.product_code)?;
    writeln!(w, "RevisionNumber=0x{:08X}", d.identity.revision)?;
    writeln!(w, "OrderCode=perpend")?;
    for (rate, ok) in [
        (10, false),
        (20, false),
        (50, false),
        (125, true),
        (250, true),
        (500, true),
        (800, false),
        (1000, true),
    ] {
        writeln!(w, "BaudRate_{rate}={}", u8::from(ok))?;
    }
    writeln!(w, "SimpleBootUpMaster=0")?;
    writeln!(w, "SimpleBootUpSlave=1")?;
    writeln!(w, "Granularity=8")?;
    writeln!(w, "DynamicChannelsSupported=0")?;
    writeln!(w, "GroupMessaging=0")?;
    // Counted from the table: the file cannot claim fewer PDOs than it
    // describes.
    writeln!(w, "NrOfRXPDO={}", count_objects(0x1400..=0x15FF))?;
    writeln!(w, "NrOfTXPDO={}", count_objects(0x1800..=0x19FF))?;
    writeln!(w, "LSS_Supported=1")?;
    writeln!(w)?;
    writeln!(w, "[DummyUsage]")?;
    for k in 1..=7 {
        writeln!(w, "Dummy000{k}=0")?;
    }
    writeln!(w)?;
    let mandatory = |i: u16| matches!(i, 0x1000 | 0x1001 | 0x1018);
    write_list(
        w,
        "MandatoryObjects",
        &mut od::OBJECTS
            .iter()
            .map(|o| o.index)
            .filter(|&i| mandatory(i)),
    )?;
    for o in od::OBJECTS.iter().filter(|o| mandatory(o.index)) {
        write_object(w, d, o)?;
    }
    write_list(
        w,
        "OptionalObjects",
        &mut od::OBJECTS
            .iter()
            .map(|o| o.index)
            .filter(|&i| !mandatory(i) && !(0x2000..0x6000).contains(&i)),
    )?;
    for o in od::OBJECTS
        .iter()
        .filter(|o| !mandatory(o.index) && !(0x2000..0x6000).contains(&o.index))
    {
        write_object(w, d, o)?;
    }
    write_list(
        w,
        "ManufacturerObjects",
        &mut od::OBJECTS
            .iter()
            .map(|o| o.index)
            .filter(|i| (0x2000..0x6000).contains(i)),
    )?;
    for o in od::OBJECTS
        .iter()
        .filter(|o| (0x2000..0x6000).contains(&o.index))
    {
        write_object(w, d, o)?;
    }
    Ok(())
}

/// The EDS as a string (host only).
#[cfg(feature = "std")]
pub fn to_string(d: &Defaults) -> String {
    let mut s = String::new();
    // Writing to a String cannot fail.
    let _ = write(&mut s, d);
    s
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn eds() -> String {
        let mut s = String::new();
        write(&mut s, &Defaults::nominal()).unwrap();
        s
    }

    #[test]
    fn every_entry_has_a_section() {
        let s = eds();
        for o in od::OBJECTS {
            assert!(
                s.contains(&format!("[{:04X}]\n", o.index)),
                "{:04X}",
                o.index
            );
            if o.kind != Kind::Var {
                for e in o.subs {
                    assert!(s.contains(&format!("[{:04X}sub{:X}]\n", o.index, e.sub)));
                }
            }
        }
        assert!(s.contains("DefaultValue=$NODEID+0x40000180\n"));
        assert!(s.contains("DefaultValue=perpend normal sensor\n"));
    }

    /// NrOfRXPDO / NrOfTXPDO count the PDO communication objects of the
    /// dictionary (0x1400..0x15FF, 0x1800..0x19FF).
    #[test]
    fn pdo_counts_follow_the_dictionary() {
        let count = |r: core::ops::RangeInclusive<u16>| {
            od::OBJECTS.iter().filter(|o| r.contains(&o.index)).count()
        };
        let (rx, tx) = (count(0x1400..=0x15FF), count(0x1800..=0x19FF));
        assert_eq!((rx, tx), (1, od::TPDOS));
        let s = eds();
        assert!(s.contains(&format!("\nNrOfRXPDO={rx}\n")), "NrOfRXPDO");
        assert!(s.contains(&format!("\nNrOfTXPDO={tx}\n")), "NrOfTXPDO");
    }

    #[test]
    fn committed_eds_is_up_to_date() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../perpend.eds");
        let want = eds();
        let got = std::fs::read_to_string(path).unwrap_or_default();
        if got != want && std::env::var_os("PERPEND_BLESS").is_some() {
            std::fs::write(path, &want).unwrap();
            return;
        }
        assert!(
            got == want,
            "perpend.eds differs from the object dictionary; regenerate with \
             PERPEND_BLESS=1 cargo test -p perpend-can committed_eds"
        );
    }
}
