//! Electronic Data Sheets (CiA 306 §4, EDS 4.0) read into a description
//! of a node's object dictionary, and `perpend eds`, which prints the EDS
//! built into the binary (the board's, [`perpend_can::eds`]).
//!
//! Read: the object lists `[MandatoryObjects]`, `[OptionalObjects]` and
//! `[ManufacturerObjects]` (`SupportedObjects=N`, `1=0x1000` …); per listed
//! object its section `[1018]` (`ParameterName`, `ObjectType` 0x7 VAR,
//! 0x8 ARRAY, 0x9 RECORD, 0x2 DOMAIN, `SubNumber`, `CompactSubObj`) and
//! for arrays and records the sub sections `[1018sub1]` (`ParameterName`,
//! `DataType`, `AccessType`, `DefaultValue`, `LowLimit`, `HighLimit`,
//! `PDOMapping`). Numbers are decimal or `0x` hex; a default may be
//! `$NODEID+0x180` (or `0x180+$NODEID`). REAL limits may also be given as
//! the comment line `;Range=LO..HI` that perpend's own EDS writes (see
//! [`perpend_can::eds`] for why). Section and key names are compared
//! without regard to case, as CiA 306 asks. Every error names the file, the
//! line and what is wrong.
//!
//! Units: CiA 306 has no unit key; a unit is read from the end of the
//! object's name (perpend's convention, "Zero point x mm"): the last word
//! when it is one of [`UNITS`], `A per B` as `A/B` and `per B` as `1/B`;
//! otherwise there is none.
//!
//! Hand-written rather than an INI crate: the line numbers the errors name
//! and the `;Range=` comments are exactly what INI crates drop, and the
//! format itself is a few lines of splitting.
//!
//! Limits: `CompactSubObj` is read for arrays (the sub names from a
//! `[XXXXName]` section where there is one); `DummyUsage`, `[DynamicChannels]`
//! and module (`[M1…]`) sections are ignored, as are object sections that no
//! list names; a `$NODEID` limit is not checked (it has no fixed value).

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// Units recognised as the last word of an object's name.
pub const UNITS: &[&str] = &[
    "mm", "mm2", "um", "nm", "deg", "degC", "rad", "us", "ms", "s", "min", "h", "Hz", "kHz", "ohm",
    "V", "mV", "mA", "uA", "kbps", "bps", "bytes", "percent",
];

/// A CiA 301 data type (table 44), by its EDS `DataType` code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Type {
    /// BOOLEAN (0x0001).
    Boolean,
    /// INTEGER8 (0x0002).
    I8,
    /// INTEGER16 (0x0003).
    I16,
    /// INTEGER32 (0x0004).
    I32,
    /// UNSIGNED8 (0x0005).
    U8,
    /// UNSIGNED16 (0x0006).
    U16,
    /// UNSIGNED32 (0x0007).
    U32,
    /// REAL32 (0x0008).
    Real32,
    /// VISIBLE_STRING (0x0009).
    VisibleString,
    /// OCTET_STRING (0x000A).
    OctetString,
    /// UNICODE_STRING (0x000B).
    UnicodeString,
    /// DOMAIN (0x000F).
    Domain,
    /// REAL64 (0x0011).
    Real64,
    /// INTEGER64 (0x0015).
    I64,
    /// UNSIGNED64 (0x001B).
    U64,
    /// Any other code (shown and transferred as raw bytes).
    Other(u16),
}

impl Type {
    /// The type of a `DataType` code.
    pub fn from_code(code: u16) -> Self {
        match code {
            0x01 => Type::Boolean,
            0x02 => Type::I8,
            0x03 => Type::I16,
            0x04 => Type::I32,
            0x05 => Type::U8,
            0x06 => Type::U16,
            0x07 => Type::U32,
            0x08 => Type::Real32,
            0x09 => Type::VisibleString,
            0x0A => Type::OctetString,
            0x0B => Type::UnicodeString,
            0x0F => Type::Domain,
            0x11 => Type::Real64,
            0x15 => Type::I64,
            0x1B => Type::U64,
            c => Type::Other(c),
        }
    }

    /// The CiA 301 name (`UNSIGNED16`), or `DATATYPE 0x0123`.
    pub fn name(self) -> String {
        let s = match self {
            Type::Boolean => "BOOLEAN",
            Type::I8 => "INTEGER8",
            Type::I16 => "INTEGER16",
            Type::I32 => "INTEGER32",
            Type::U8 => "UNSIGNED8",
            Type::U16 => "UNSIGNED16",
            Type::U32 => "UNSIGNED32",
            Type::Real32 => "REAL32",
            Type::VisibleString => "VISIBLE_STRING",
            Type::OctetString => "OCTET_STRING",
            Type::UnicodeString => "UNICODE_STRING",
            Type::Domain => "DOMAIN",
            Type::Real64 => "REAL64",
            Type::I64 => "INTEGER64",
            Type::U64 => "UNSIGNED64",
            Type::Other(c) => return format!("DATATYPE {c:#06x}"),
        };
        s.to_string()
    }

    /// Size in bytes of a value of fixed size (`None`: strings, domains,
    /// unknown types).
    pub fn size(self) -> Option<usize> {
        match self {
            Type::Boolean | Type::I8 | Type::U8 => Some(1),
            Type::I16 | Type::U16 => Some(2),
            Type::I32 | Type::U32 | Type::Real32 => Some(4),
            Type::I64 | Type::U64 | Type::Real64 => Some(8),
            _ => None,
        }
    }

    /// An integer type: `Some(signed)`.
    pub fn integer(self) -> Option<bool> {
        match self {
            Type::I8 | Type::I16 | Type::I32 | Type::I64 => Some(true),
            Type::U8 | Type::U16 | Type::U32 | Type::U64 | Type::Boolean => Some(false),
            _ => None,
        }
    }

    /// A floating-point type.
    pub fn real(self) -> bool {
        matches!(self, Type::Real32 | Type::Real64)
    }
}

/// EDS `AccessType`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// `const`.
    Const,
    /// `ro`.
    Ro,
    /// `wo`.
    Wo,
    /// `rw`.
    Rw,
    /// `rwr` (rw, mapped into TPDOs).
    Rwr,
    /// `rww` (rw, mapped into RPDOs).
    Rww,
}

impl Access {
    fn parse(s: &str) -> Option<Self> {
        Some(match s.to_ascii_lowercase().as_str() {
            "const" => Access::Const,
            "ro" => Access::Ro,
            "wo" => Access::Wo,
            "rw" => Access::Rw,
            "rwr" => Access::Rwr,
            "rww" => Access::Rww,
            _ => return None,
        })
    }

    /// As written in an EDS.
    pub fn as_str(self) -> &'static str {
        match self {
            Access::Const => "const",
            Access::Ro => "ro",
            Access::Wo => "wo",
            Access::Rw => "rw",
            Access::Rwr => "rwr",
            Access::Rww => "rww",
        }
    }

    /// Whether a master may write it.
    pub fn writable(self) -> bool {
        matches!(self, Access::Wo | Access::Rw | Access::Rwr | Access::Rww)
    }
}

/// A limit or default as a number.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Num {
    /// An integer (any CANopen integer fits).
    Int(i128),
    /// A real number.
    Real(f64),
}

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Num::Int(v) => write!(f, "{v}"),
            Num::Real(v) => write!(f, "{v}"),
        }
    }
}

/// One sub-index as the EDS describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// Index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// `ParameterName`.
    pub name: String,
    /// The object's name (the same as `name` for a VAR).
    pub object: String,
    /// `DataType`.
    pub ty: Type,
    /// `AccessType`.
    pub access: Access,
    /// `LowLimit` (or the low end of `;Range=`).
    pub low: Option<Num>,
    /// `HighLimit` (or the high end of `;Range=`).
    pub high: Option<Num>,
    /// `DefaultValue` as written (`None`: absent or empty).
    pub default: Option<String>,
    /// `PDOMapping`.
    pub pdo: bool,
    /// The unit, from the end of the name (see the module header).
    pub unit: Option<String>,
    /// The line of its section.
    pub line: usize,
}

impl Entry {
    /// `limits LO..HI`, `limits ≥ LO`, `limits ≤ HI` or `None`.
    pub fn limits_text(&self) -> Option<String> {
        match (self.low, self.high) {
            (Some(l), Some(h)) => Some(format!("limits {l}..{h}")),
            (Some(l), None) => Some(format!("limits ≥ {l}")),
            (None, Some(h)) => Some(format!("limits ≤ {h}")),
            (None, None) => None,
        }
    }
}

/// A dictionary read from an EDS.
#[derive(Debug, Clone)]
pub struct Eds {
    /// The file it came from (for messages).
    pub file: String,
    /// Every entry by `(index, sub)`.
    pub entries: BTreeMap<(u16, u8), Entry>,
    /// Each object's name.
    pub objects: BTreeMap<u16, String>,
    /// `[DeviceInfo] VendorNumber` (0x1018 sub 1 of the device it describes).
    pub vendor: Option<u32>,
    /// `[DeviceInfo] ProductNumber` (0x1018 sub 2).
    pub product: Option<u32>,
}

/// A malformed EDS: which file, which line, what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EdsError {
    /// The file.
    pub file: String,
    /// The line (1-based; 0: the file as a whole).
    pub line: usize,
    /// What is wrong and what to do.
    pub what: String,
}

impl fmt::Display for EdsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.line == 0 {
            write!(f, "{}: {}", self.file, self.what)
        } else {
            write!(f, "{} line {}: {}", self.file, self.line, self.what)
        }
    }
}

impl std::error::Error for EdsError {}

/// The name under which the built-in EDS appears in messages.
pub const BUILTIN: &str = "perpend.eds (built in)";

/// The EDS built into the binary: the board's, from its dictionary.
pub fn builtin_text() -> String {
    perpend_can::eds::to_string(&perpend_can::Defaults::nominal())
}

impl Eds {
    /// The board's dictionary, from the EDS built into the binary.
    ///
    /// # Errors
    /// None in practice (a test parses it); kept an error for the caller.
    pub fn builtin() -> Result<Self, EdsError> {
        Self::parse(BUILTIN, &builtin_text())
    }

    /// Reads the EDS file `path`.
    ///
    /// # Errors
    /// An unreadable file, or its first problem with file and line.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read(path)
            .with_context(|| format!("cannot read the EDS {}", path.display()))?;
        // EDS files are ASCII by the standard; vendors' files are often
        // Latin-1: keep what can be read.
        let text = String::from_utf8_lossy(&text);
        Ok(Self::parse(&path.display().to_string(), &text)?)
    }

    /// The built-in EDS, or the file `path` when given.
    ///
    /// # Errors
    /// As [`Eds::load`].
    pub fn builtin_or(path: Option<&PathBuf>) -> Result<Self> {
        match path {
            Some(p) => Self::load(p),
            None => Ok(Self::builtin()?),
        }
    }

    /// Parses the text of an EDS; `file` names it in errors.
    ///
    /// # Errors
    /// The first problem found, with its line.
    pub fn parse(file: &str, text: &str) -> Result<Self, EdsError> {
        let ini = Ini::parse(file, text)?;
        let mut eds = Eds {
            file: file.to_string(),
            entries: BTreeMap::new(),
            objects: BTreeMap::new(),
            vendor: None,
            product: None,
        };
        if let Some(d) = ini.section("DeviceInfo") {
            let num = |k: &str| {
                d.get(k)
                    .and_then(|k| parse_int(&k.value))
                    .and_then(|v| u32::try_from(v).ok())
            };
            eds.vendor = num("VendorNumber");
            eds.product = num("ProductNumber");
        }
        let mut any = false;
        for list in ["MandatoryObjects", "OptionalObjects", "ManufacturerObjects"] {
            if let Some(s) = ini.section(list) {
                any = true;
                for (index, line) in object_list(&ini, s)? {
                    read_object(&ini, &mut eds, index, line)?;
                }
            }
        }
        if !any {
            return Err(ini.err(
                0,
                "no [MandatoryObjects], [OptionalObjects] or [ManufacturerObjects] \
                 section: is this an EDS (CiA 306)?",
            ));
        }
        Ok(eds)
    }

    /// The entry at `(index, sub)`.
    pub fn get(&self, index: u16, sub: u8) -> Option<&Entry> {
        self.entries.get(&(index, sub))
    }

    /// The entries of object `index`, in sub-index order.
    pub fn object(&self, index: u16) -> impl Iterator<Item = &Entry> {
        self.entries
            .range((index, 0)..=(index, 0xFF))
            .map(|(_, e)| e)
    }
}

/// `perpend eds`: the EDS built into the binary.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Write it to this file instead of stdout.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Runs `perpend eds`.
///
/// # Errors
/// A file that cannot be written.
pub fn run(a: &Args) -> Result<()> {
    let text = builtin_text();
    match &a.out {
        Some(p) => std::fs::write(p, &text)
            .with_context(|| format!("cannot write the EDS to {}", p.display())),
        None => {
            use std::io::Write;
            std::io::stdout()
                .write_all(text.as_bytes())
                .context("cannot write the EDS to stdout")
        }
    }
}

/// One key of a section.
#[derive(Debug)]
struct Key {
    /// As written (for list entries, whose keys are numbers).
    name: String,
    value: String,
    line: usize,
}

/// One section: its line, keys (lower-case name → key) and `;Range=`.
#[derive(Debug, Default)]
struct Section {
    line: usize,
    keys: BTreeMap<String, Key>,
    order: Vec<String>,
    range: Option<(String, usize)>,
}

impl Section {
    fn get(&self, key: &str) -> Option<&Key> {
        self.keys.get(&key.to_ascii_lowercase())
    }
}

/// The INI layer: sections by lower-case name.
struct Ini {
    file: String,
    sections: BTreeMap<String, Section>,
}

impl Ini {
    fn err(&self, line: usize, what: impl Into<String>) -> EdsError {
        EdsError {
            file: self.file.clone(),
            line,
            what: what.into(),
        }
    }

    fn section(&self, name: &str) -> Option<&Section> {
        self.sections.get(&name.to_ascii_lowercase())
    }

    fn parse(file: &str, text: &str) -> Result<Self, EdsError> {
        let mut ini = Ini {
            file: file.to_string(),
            sections: BTreeMap::new(),
        };
        let mut current: Option<String> = None;
        for (k, raw) in text.lines().enumerate() {
            let line = k + 1;
            let s = raw.trim_start_matches('\u{feff}').trim();
            if s.is_empty() {
                continue;
            }
            if let Some(rest) = s.strip_prefix('[') {
                current = Some(ini.open_section(rest, line)?);
            } else if s.starts_with(';') || s.starts_with('#') {
                ini.comment(current.as_deref(), s, line);
            } else {
                ini.key(current.as_deref(), s, line)?;
            }
        }
        Ok(ini)
    }

    fn open_section(&mut self, rest: &str, line: usize) -> Result<String, EdsError> {
        let Some(name) = rest.strip_suffix(']') else {
            return Err(self.err(line, "a section header without its closing `]`"));
        };
        let lower = name.trim().to_ascii_lowercase();
        if let Some(first) = self.sections.get(&lower) {
            let at = first.line;
            return Err(self.err(line, format!("section [{name}] again (first at line {at})")));
        }
        self.sections.insert(
            lower.clone(),
            Section {
                line,
                ..Section::default()
            },
        );
        Ok(lower)
    }

    fn comment(&mut self, current: Option<&str>, s: &str, line: usize) {
        let body = s[1..].trim();
        let Some(v) = body
            .split_once('=')
            .filter(|(k, _)| k.trim().eq_ignore_ascii_case("range"))
            .map(|(_, v)| v.trim().to_string())
        else {
            return;
        };
        if let Some(sec) = current.and_then(|c| self.sections.get_mut(c)) {
            sec.range = Some((v, line));
        }
    }

    fn key(&mut self, current: Option<&str>, s: &str, line: usize) -> Result<(), EdsError> {
        let Some((k, v)) = s.split_once('=') else {
            return Err(self.err(line, format!("`{s}` is neither [section] nor key=value")));
        };
        let Some(cur) = current else {
            return Err(self.err(line, "a key before the first [section]"));
        };
        let name = k.trim().to_string();
        let lower = name.to_ascii_lowercase();
        let file = self.file.clone();
        let sec = self.sections.entry(cur.to_string()).or_default();
        if let Some(first) = sec.keys.get(&lower) {
            return Err(EdsError {
                file,
                line,
                what: format!(
                    "key {name} again in this section (first at line {})",
                    first.line
                ),
            });
        }
        sec.order.push(lower.clone());
        sec.keys.insert(
            lower,
            Key {
                name,
                value: v.trim().to_string(),
                line,
            },
        );
        Ok(())
    }
}

/// Parses an unsigned or signed integer: decimal, `0x` hex, leading `-`.
pub fn parse_int(s: &str) -> Option<i128> {
    let s = s.trim();
    let (neg, body) = match s.strip_prefix('-') {
        Some(b) => (true, b),
        None => (false, s),
    };
    let v = match body.strip_prefix("0x").or_else(|| body.strip_prefix("0X")) {
        Some(h) => i128::from_str_radix(h, 16).ok()?,
        None => body.parse::<i128>().ok()?,
    };
    Some(if neg { -v } else { v })
}

/// A number of type `ty` as written in an EDS (`None`: not a number).
fn parse_num(ty: Type, s: &str) -> Option<Num> {
    if ty.real() {
        if let Some(i) = parse_int(s) {
            return Some(Num::Real(i as f64));
        }
        return s.trim().parse::<f64>().ok().map(Num::Real);
    }
    parse_int(s).map(Num::Int)
}

/// The `(index, line)` pairs of an object list section.
fn object_list(ini: &Ini, s: &Section) -> Result<Vec<(u16, usize)>, EdsError> {
    let Some(n) = s.get("SupportedObjects") else {
        return Err(ini.err(s.line, "an object list without SupportedObjects=N"));
    };
    let count = parse_int(&n.value)
        .filter(|c| (0..=0xFFFF).contains(c))
        .ok_or_else(|| {
            ini.err(
                n.line,
                format!("SupportedObjects={} is not a number", n.value),
            )
        })?;
    let mut out = Vec::new();
    for k in 1..=count {
        let Some(key) = s.get(&k.to_string()) else {
            return Err(ini.err(
                n.line,
                format!("SupportedObjects={count} but entry {k}= is missing"),
            ));
        };
        let index = parse_int(&key.value)
            .and_then(|i| u16::try_from(i).ok())
            .ok_or_else(|| {
                ini.err(
                    key.line,
                    format!("{}={} is not an object index", key.name, key.value),
                )
            })?;
        out.push((index, key.line));
    }
    if let Some(extra) = s
        .order
        .iter()
        .filter_map(|k| s.keys.get(k))
        .find(|k| parse_int(&k.name).is_some_and(|i| i < 1 || i > count))
    {
        return Err(ini.err(
            extra.line,
            format!("entry {}= beyond SupportedObjects={count}", extra.name),
        ));
    }
    Ok(out)
}

/// Reads object `index` (listed at `line`) and its sub-indices into `eds`.
fn read_object(ini: &Ini, eds: &mut Eds, index: u16, line: usize) -> Result<(), EdsError> {
    let Some(sec) = ini.section(&format!("{index:04X}")) else {
        return Err(ini.err(
            line,
            format!("the list names object {index:#06x} but there is no section [{index:04X}]"),
        ));
    };
    let name = required(ini, sec, "ParameterName")?.value.clone();
    let kind = match sec.get("ObjectType") {
        Some(k) => parse_int(&k.value)
            .ok_or_else(|| ini.err(k.line, format!("ObjectType={} is not a number", k.value)))?,
        None => 7,
    };
    eds.objects.insert(index, name.clone());
    match kind {
        0x7 | 0x2 => {
            let e = read_entry(ini, sec, index, 0, &name)?;
            eds.entries.insert((index, 0), e);
        }
        0x8 | 0x9 => read_subs(ini, eds, sec, index, &name)?,
        k => {
            // DEFTYPE/DEFSTRUCT and the like describe types, not values.
            let l = sec.get("ObjectType").map_or(sec.line, |k| k.line);
            if !matches!(k, 0x0 | 0x5 | 0x6) {
                return Err(ini.err(l, format!("ObjectType={k:#x} is not 0x7, 0x8 or 0x9")));
            }
        }
    }
    Ok(())
}

fn required<'a>(ini: &Ini, sec: &'a Section, key: &str) -> Result<&'a Key, EdsError> {
    sec.get(key)
        .ok_or_else(|| ini.err(sec.line, format!("{key}= is missing from this section")))
}

/// The sub-indices of an ARRAY or RECORD.
fn read_subs(
    ini: &Ini,
    eds: &mut Eds,
    sec: &Section,
    index: u16,
    object: &str,
) -> Result<(), EdsError> {
    if let Some(c) = sec.get("CompactSubObj").filter(|c| c.value.trim() != "0") {
        return compact_subs(ini, eds, sec, c, index, object);
    }
    let mut found = 0usize;
    for sub in 0..=0xFFu8 {
        if let Some(s) = ini.section(&format!("{index:04X}sub{sub:X}")) {
            let e = read_entry(ini, s, index, sub, object)?;
            eds.entries.insert((index, sub), e);
            found += 1;
        }
    }
    if let Some(n) = sec.get("SubNumber") {
        let want = parse_int(&n.value)
            .ok_or_else(|| ini.err(n.line, format!("SubNumber={} is not a number", n.value)))?;
        if want != found as i128 {
            return Err(ini.err(
                n.line,
                format!(
                    "SubNumber={} but {found} sections [{index:04X}subN] follow",
                    n.value
                ),
            ));
        }
    }
    if found == 0 {
        return Err(ini.err(
            sec.line,
            format!("object {index:#06x} is an array or record without [{index:04X}subN] sections"),
        ));
    }
    Ok(())
}

/// `CompactSubObj=N`: sub 0 (UNSIGNED8, ro, N) and subs 1..=N with the
/// object's own type, access and limits.
fn compact_subs(
    ini: &Ini,
    eds: &mut Eds,
    sec: &Section,
    c: &Key,
    index: u16,
    object: &str,
) -> Result<(), EdsError> {
    let n = parse_int(&c.value)
        .and_then(|n| u8::try_from(n).ok())
        .ok_or_else(|| ini.err(c.line, format!("CompactSubObj={} is not 0..255", c.value)))?;
    let names = ini.section(&format!("{index:04X}Name"));
    let proto = read_entry(ini, sec, index, 1, object)?;
    let sub0 = Entry {
        sub: 0,
        name: "Number of entries".into(),
        ty: Type::U8,
        access: Access::Ro,
        low: None,
        high: None,
        default: Some(n.to_string()),
        pdo: false,
        unit: None,
        ..proto.clone()
    };
    eds.entries.insert((index, 0), sub0);
    for k in 1..=n {
        let name = names
            .and_then(|s| s.get(&k.to_string()))
            .map_or_else(|| format!("{object}{k}"), |v| v.value.clone());
        let unit = unit_of(&name);
        let e = Entry {
            sub: k,
            name,
            unit,
            ..proto.clone()
        };
        eds.entries.insert((index, k), e);
    }
    Ok(())
}

/// One entry from its section.
fn read_entry(
    ini: &Ini,
    s: &Section,
    index: u16,
    sub: u8,
    object: &str,
) -> Result<Entry, EdsError> {
    let name = required(ini, s, "ParameterName")?.value.clone();
    let dt = required(ini, s, "DataType")?;
    let code = parse_int(&dt.value)
        .and_then(|c| u16::try_from(c).ok())
        .ok_or_else(|| ini.err(dt.line, format!("DataType={} is not a type code", dt.value)))?;
    let ty = Type::from_code(code);
    let at = required(ini, s, "AccessType")?;
    let access = Access::parse(&at.value).ok_or_else(|| {
        ini.err(
            at.line,
            format!(
                "AccessType={} is not const, ro, wo, rw, rwr or rww",
                at.value
            ),
        )
    })?;
    let (low, high) = limits(ini, s, ty)?;
    let default = default_value(ini, s, ty)?;
    let pdo = match s.get("PDOMapping") {
        Some(k) => match k.value.trim() {
            "0" => false,
            "1" => true,
            v => return Err(ini.err(k.line, format!("PDOMapping={v} is not 0 or 1"))),
        },
        None => false,
    };
    Ok(Entry {
        index,
        sub,
        unit: unit_of(&name),
        name,
        object: object.to_string(),
        ty,
        access,
        low,
        high,
        default,
        pdo,
        line: s.line,
    })
}

/// `LowLimit`/`HighLimit`, else `;Range=LO..HI` (REAL limits).
fn limits(ini: &Ini, s: &Section, ty: Type) -> Result<(Option<Num>, Option<Num>), EdsError> {
    let one = |key: &str| -> Result<Option<Num>, EdsError> {
        let Some(k) = s.get(key).filter(|k| !k.value.is_empty()) else {
            return Ok(None);
        };
        if k.value.to_ascii_uppercase().contains("$NODEID") {
            return Ok(None);
        }
        parse_num(ty, &k.value).map(Some).ok_or_else(|| {
            ini.err(
                k.line,
                format!(
                    "{}={} is not a number of type {}",
                    k.name,
                    k.value,
                    ty.name()
                ),
            )
        })
    };
    let (mut low, mut high) = (one("LowLimit")?, one("HighLimit")?);
    if let Some((v, line)) = &s.range {
        let parsed = v.split_once("..").and_then(|(a, b)| {
            Some((a.trim().parse::<f64>().ok()?, b.trim().parse::<f64>().ok()?))
        });
        let Some((a, b)) = parsed else {
            return Err(ini.err(*line, format!(";Range={v} is not LO..HI (two numbers)")));
        };
        low = low.or(Some(Num::Real(a)));
        high = high.or(Some(Num::Real(b)));
    }
    Ok((low, high))
}

/// `DefaultValue`, checked to be a number for numeric types.
fn default_value(ini: &Ini, s: &Section, ty: Type) -> Result<Option<String>, EdsError> {
    let Some(k) = s.get("DefaultValue").filter(|k| !k.value.is_empty()) else {
        return Ok(None);
    };
    let numeric = ty.integer().is_some() || ty.real();
    let v = &k.value;
    let node_relative = v.to_ascii_uppercase().contains("$NODEID");
    if numeric && !node_relative && parse_num(ty, v).is_none() {
        let nan = ty.real() && v.eq_ignore_ascii_case("nan");
        if !nan {
            return Err(ini.err(
                k.line,
                format!("DefaultValue={v} is not a number of type {}", ty.name()),
            ));
        }
    }
    Ok(Some(v.clone()))
}

/// The unit at the end of an object's name (see the module header).
pub fn unit_of(name: &str) -> Option<String> {
    let words: Vec<&str> = name.split_whitespace().collect();
    let is_unit = |w: &str| UNITS.contains(&w);
    match words.as_slice() {
        [.., a, "per", b] if is_unit(a) && is_unit(b) => Some(format!("{a}/{b}")),
        [.., "per", b] if is_unit(b) => Some(format!("1/{b}")),
        [_, .., last] if is_unit(last) => Some((*last).to_string()),
        _ => None,
    }
}

#[cfg(test)]
#[path = "eds_tests.rs"]
mod tests;
