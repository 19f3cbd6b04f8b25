//! Tests of the EDS reader: the built-in EDS against the dictionary table,
//! and malformed files against their line-numbered errors.
#![allow(clippy::unwrap_used, clippy::panic)]

use super::*;
use perpend_can::od::{self, Limits};

fn ty_of(t: od::DataType) -> Type {
    match t {
        od::DataType::U8 => Type::U8,
        od::DataType::U16 => Type::U16,
        od::DataType::U32 => Type::U32,
        od::DataType::Real32 => Type::Real32,
        od::DataType::VisibleString => Type::VisibleString,
        od::DataType::Domain => Type::Domain,
    }
}

fn access_of(a: od::Access) -> Access {
    match a {
        od::Access::Const => Access::Const,
        od::Access::Ro => Access::Ro,
        od::Access::Rw => Access::Rw,
        od::Access::Wo => Access::Wo,
    }
}

fn limits_of(l: Limits) -> (Option<Num>, Option<Num>) {
    let int = |v: u32| Some(Num::Int(v.into()));
    match l {
        Limits::Any => (None, None),
        Limits::Range(a, b) | Limits::PowerOfTwo(a, b) => (int(a), int(b)),
        Limits::OneOf(s) => (
            int(s.iter().copied().min().unwrap()),
            int(s.iter().copied().max().unwrap()),
        ),
        // Compared in REAL32, as the device compares.
        Limits::Real(a, b) => (Some(Num::Real(a.into())), Some(Num::Real(b.into()))),
    }
}

fn as_f32(n: Option<Num>) -> Option<f32> {
    match n {
        Some(Num::Real(v)) => Some(v as f32),
        Some(Num::Int(v)) => Some(v as f32),
        None => None,
    }
}

#[test]
fn the_builtin_eds_describes_every_dictionary_entry() {
    let eds = Eds::builtin().unwrap();
    let mut n = 0;
    for (_, index, e) in od::entries() {
        let got = eds
            .get(index, e.sub)
            .unwrap_or_else(|| panic!("{index:#06x} sub {} missing", e.sub));
        assert_eq!(got.name, e.name, "{index:#06x} sub {}", e.sub);
        assert_eq!(got.ty, ty_of(e.ty), "{index:#06x} sub {}", e.sub);
        assert_eq!(
            got.access,
            access_of(e.access),
            "{index:#06x} sub {}",
            e.sub
        );
        assert_eq!(got.pdo, e.pdo, "{index:#06x} sub {}", e.sub);
        let (lo, hi) = limits_of(e.limits);
        if e.ty == od::DataType::Real32 {
            assert_eq!(as_f32(got.low), as_f32(lo), "{index:#06x} sub {}", e.sub);
            assert_eq!(as_f32(got.high), as_f32(hi), "{index:#06x} sub {}", e.sub);
        } else {
            assert_eq!((got.low, got.high), (lo, hi), "{index:#06x} sub {}", e.sub);
        }
        n += 1;
    }
    assert_eq!(
        eds.entries.len(),
        n,
        "the EDS has entries the table has not"
    );
    let r = eds.get(0x2300, 4).unwrap();
    assert_eq!(r.object, "Acquisition");
    assert_eq!(r.unit.as_deref(), Some("mm"));
    assert_eq!(
        eds.get(0x1800, 1).unwrap().default.as_deref(),
        Some("$NODEID+0x40000180")
    );
}

#[test]
fn units_come_from_the_end_of_the_name() {
    let cases = [
        ("Zero point x mm", Some("mm")),
        ("Die temperature degC", Some("degC")),
        ("Sample time us", Some("us")),
        ("Thermal drift mm per degC", Some("mm/degC")),
        ("Quadratic nonlinearity per mm", Some("1/mm")),
        ("Cubic nonlinearity per mm2", Some("1/mm2")),
        ("Thermal time constant s", Some("s")),
        ("Shunt ohm or divider ratio", None),
        ("Normal x", None),
        ("s", None),
        ("Producer heartbeat time", None),
    ];
    for (name, unit) in cases {
        assert_eq!(unit_of(name).as_deref(), unit, "{name}");
    }
}

const GOOD: &str = "\
[DeviceInfo]
VendorName=other
[MandatoryObjects]
SupportedObjects=2
1=0x1000
2=0x1018
[1000]
ParameterName=Device type
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00020192
[1018]
ParameterName=Identity object
ObjectType=0x9
SubNumber=2
[1018sub0]
ParameterName=Number of entries
DataType=0x0005
AccessType=ro
DefaultValue=1
[1018sub1]
ParameterName=Vendor-ID
DataType=0x0007
AccessType=ro
[ManufacturerObjects]
SupportedObjects=2
1=0x2000
2=0x2100
[2000]
ParameterName=Gain
DataType=0x0008
AccessType=rw
LowLimit=-1.5
HighLimit=2.5
DefaultValue=1.0
[2100]
ParameterName=Offsets mV
ObjectType=0x8
CompactSubObj=3
DataType=0x0003
AccessType=rw
LowLimit=-100
HighLimit=100
[2100Name]
NrOfEntries=1
2=Offset B mV
";

#[test]
fn another_vendors_eds_reads() {
    let eds = Eds::parse("other.eds", GOOD).unwrap();
    assert_eq!(eds.entries.len(), 1 + 2 + 1 + 4);
    let g = eds.get(0x2000, 0).unwrap();
    assert_eq!(
        (g.ty, g.low, g.high),
        (Type::Real32, Some(Num::Real(-1.5)), Some(Num::Real(2.5)))
    );
    let o = eds.get(0x2100, 2).unwrap();
    assert_eq!(
        (o.name.as_str(), o.ty, o.unit.as_deref()),
        ("Offset B mV", Type::I16, Some("mV"))
    );
    assert_eq!(eds.get(0x2100, 3).unwrap().name, "Offsets mV3");
    assert_eq!(eds.get(0x2100, 0).unwrap().ty, Type::U8);
    assert_eq!(eds.object(0x1018).count(), 2);
}

/// `GOOD` with `from` replaced by `to`, and the error it gives.
fn broken(from: &str, to: &str) -> EdsError {
    assert!(GOOD.contains(from), "{from}");
    Eds::parse("bad.eds", &GOOD.replacen(from, to, 1)).unwrap_err()
}

#[test]
fn malformed_files_name_file_line_and_problem() {
    let cases: &[(&str, &str, usize, &str)] = &[
        // missing DataType: the section's line
        (
            "DataType=0x0007\nAccessType=ro\nDefaultValue=0x0002",
            "AccessType=ro\nDefaultValue=0x0002",
            7,
            "DataType= is missing",
        ),
        (
            "DefaultValue=0x00020192",
            "DefaultValue=0x0002zz",
            12,
            "not a number of type UNSIGNED32",
        ),
        (
            "HighLimit=2.5",
            "HighLimit=lots",
            35,
            "not a number of type REAL32",
        ),
        ("2=0x1018", "2=0x1019", 6, "no section [1019]"),
        (
            "SupportedObjects=2\n1=0x1000",
            "SupportedObjects=3\n1=0x1000",
            4,
            "entry 3= is missing",
        ),
        (
            "SubNumber=2",
            "SubNumber=3",
            16,
            "SubNumber=3 but 2 sections",
        ),
        (
            "AccessType=rw\nLowLimit=-1.5",
            "AccessType=wr\nLowLimit=-1.5",
            33,
            "AccessType=wr",
        ),
        ("[1000]", "[1000", 7, "closing `]`"),
        (
            "VendorName=other",
            "VendorName other",
            2,
            "neither [section] nor key=value",
        ),
        ("[DeviceInfo]\n", "", 1, "key before the first [section]"),
        (
            "[1018sub1]",
            "[1018sub0]",
            22,
            "section [1018sub0] again (first at line 17)",
        ),
    ];
    for (from, to, line, what) in cases {
        let e = broken(from, to);
        assert_eq!(e.file, "bad.eds", "{to}");
        assert_eq!(e.line, *line, "{to}: {e}");
        assert!(e.to_string().contains(what), "{to}: {e}");
        assert!(
            e.to_string().starts_with(&format!("bad.eds line {line}: ")),
            "{e}"
        );
    }
}

#[test]
fn a_range_comment_is_read_and_a_bad_one_refused() {
    let with = GOOD.replace("LowLimit=-1.5\nHighLimit=2.5\n", ";Range=0.5..1e3\n");
    let eds = Eds::parse("r.eds", &with).unwrap();
    let g = eds.get(0x2000, 0).unwrap();
    assert_eq!(
        (g.low, g.high),
        (Some(Num::Real(0.5)), Some(Num::Real(1000.0)))
    );
    let bad = GOOD.replace("LowLimit=-1.5\nHighLimit=2.5\n", ";Range=0.5...x\n");
    let e = Eds::parse("r.eds", &bad).unwrap_err();
    assert_eq!(e.line, 34, "{e}");
    assert!(e.what.contains("LO..HI"), "{e}");
}

#[test]
fn text_without_object_lists_is_not_an_eds() {
    let e = Eds::parse("x.ini", "[a]\nb=c\n").unwrap_err();
    assert!(e.to_string().contains("is this an EDS"), "{e}");
}

proptest::proptest! {
    /// The built-in EDS with one line replaced, removed or doubled: parsed
    /// or refused with a line of the text, never a panic (the fuzz target
    /// `eds` does the same on arbitrary bytes).
    #[test]
    fn a_damaged_eds_is_refused_with_a_line(at in 0usize..4000, what in 0u8..3, junk in "[ -~]{0,12}") {
        let text = builtin_text();
        let mut lines: Vec<&str> = text.lines().collect();
        let k = at % lines.len();
        match what {
            0 => lines[k] = &junk,
            1 => { lines.remove(k); }
            _ => lines.insert(k, lines[k]),
        }
        let damaged = lines.join("\n");
        if let Err(e) = Eds::parse("d.eds", &damaged) {
            proptest::prop_assert!(e.line <= lines.len(), "{}", e);
        }
    }
}
