//! `perpend node sdo read|write|list`: any object of a node by index and
//! sub-index, typed by an EDS (CiA 306): the board's, built in, unless
//! `--eds FILE` names another (another vendor's node on the same bus).
//!
//! ```text
//! perpend node --bus BUS --node-id N sdo read IDX SUB [--json]
//! perpend node --bus BUS --node-id N sdo write IDX SUB VALUE [--force] [--json]
//! perpend node sdo list [IDX] [--json]   (no bus needed; with one, checks 0x1018)
//! ```
//!
//! IDX is `0x2300`, `2300h` or decimal; SUB decimal or `0x` hex. `read`
//! uploads (CiA 301 §7.2.4.3) and decodes in the entry's type; an object
//! the EDS does not list is still read and shown as bytes. `write` parses
//! VALUE in the entry's type (integers decimal or `0x` hex, reals as
//! floats, strings as text, OCTET_STRING/DOMAIN as hex bytes), refuses
//! before sending a value outside the EDS limits or an entry that is `ro`
//! or `const` (`--force` sends anyway), downloads it with the type's size,
//! reads it back and prints old → new. Before the first transfer the
//! node's identity (0x1018 sub 1, 2) is compared with the EDS's
//! `VendorNumber`/`ProductNumber`: a difference is a one-line warning
//! for `read`, a refusal for `write` (`--force` writes anyway). An abort
//! prints its code, its sentence ([`crate::canopen::abort::describe`]),
//! for a refused value the rule that refused it (`sdo_rules.rs`) and, for the board's
//! state and lock aborts (0x08000022, 0x08000021, see
//! [`perpend_can::od::Class`]), the command that clears them.
//!
//! Limits: an object whose type the EDS does not give cannot be written;
//! objects are addressed by number, not by name.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{anyhow, bail, Result};
use serde_json::json;

use super::Node;
use crate::canopen::ClientError;
use crate::eds::{parse_int, Eds, Entry, Num, Type};

/// `JSON` schema tag of every `sdo` output.
pub const SCHEMA: &str = "perpend.sdo/1";

/// Arguments of `perpend node sdo`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The EDS that types the node's objects (default: the board's, built in).
    #[arg(long, global = true)]
    pub eds: Option<PathBuf>,
    /// What to do.
    #[command(subcommand)]
    pub cmd: SdoCmd,
}

impl Args {
    /// Whether the command runs without a bus (`list`).
    pub fn offline(&self) -> bool {
        matches!(self.cmd, SdoCmd::List(_))
    }
}

/// The subcommands of `sdo`.
#[derive(clap::Subcommand, Debug)]
pub enum SdoCmd {
    /// Read one object (upload) and show it in its EDS type, unit and limits.
    Read(ReadArgs),
    /// Write one object (download) after checking type, access, limits and the node's identity; read it back.
    Write(WriteArgs),
    /// The EDS's entries: names, types, access, limits, units (no bus needed;
    /// with --bus and --node-id, also whether it is that node's EDS).
    List(ListArgs),
}

/// Options of `sdo read`.
#[derive(clap::Args, Debug)]
pub struct ReadArgs {
    /// Object index: 0x2300, 2300h or decimal.
    #[arg(value_parser = parse_index)]
    pub index: u16,
    /// Sub-index (0 for a VAR): decimal or 0x hex.
    #[arg(value_parser = parse_sub)]
    pub sub: u8,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Options of `sdo write`.
#[derive(clap::Args, Debug)]
pub struct WriteArgs {
    /// Object index: 0x2300, 2300h or decimal.
    #[arg(value_parser = parse_index)]
    pub index: u16,
    /// Sub-index (0 for a VAR): decimal or 0x hex.
    #[arg(value_parser = parse_sub)]
    pub sub: u8,
    /// The value in the entry's type: integer (decimal or 0x hex), real,
    /// true/false, text, or hex bytes for OCTET_STRING/DOMAIN.
    #[arg(allow_hyphen_values = true)]
    pub value: String,
    /// Send even a value outside the EDS limits or the board's rules, to a
    /// ro/const entry, or to a node whose identity (0x1018) is not the EDS's.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Options of `sdo list`.
#[derive(clap::Args, Debug)]
pub struct ListArgs {
    /// Only this object: 0x2300, 2300h or decimal.
    #[arg(value_parser = parse_index)]
    pub index: Option<u16>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Parses an object index: `0x2300`, `2300h` or decimal.
///
/// # Errors
/// Not a number in 0..=0xFFFF.
pub fn parse_index(s: &str) -> Result<u16, String> {
    let t = s.trim();
    let v = match t.strip_suffix(['h', 'H']) {
        Some(h) => i128::from_str_radix(h, 16).ok(),
        None => parse_int(t),
    };
    v.and_then(|v| u16::try_from(v).ok())
        .ok_or_else(|| format!("`{s}` is not an object index (0x2300, 2300h or decimal 0..65535)"))
}

/// Parses a sub-index: decimal or `0x` hex.
///
/// # Errors
/// Not a number in 0..=255.
pub fn parse_sub(s: &str) -> Result<u8, String> {
    parse_int(s)
        .and_then(|v| u8::try_from(v).ok())
        .ok_or_else(|| format!("`{s}` is not a sub-index (0..255, decimal or 0x hex)"))
}

/// A value decoded from, or to be encoded into, an object's bytes.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// BOOLEAN.
    Bool(bool),
    /// UNSIGNED8..64.
    Uint(u64),
    /// INTEGER8..64.
    Int(i64),
    /// REAL32.
    Real32(f32),
    /// REAL64.
    Real64(f64),
    /// VISIBLE_STRING, UNICODE_STRING.
    Text(String),
    /// OCTET_STRING, DOMAIN, unknown types.
    Bytes(Vec<u8>),
}

/// Bytes as `01 02 0a`.
pub fn hex(b: &[u8]) -> String {
    b.iter()
        .map(|x| format!("{x:02x}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Decodes `raw` as a value of type `ty`.
///
/// # Errors
/// A length that does not fit the type.
pub fn decode(ty: Type, raw: &[u8]) -> Result<Value, String> {
    if let Some(n) = ty.size() {
        if raw.len() != n {
            let name = ty.name();
            let a = if name.starts_with(['A', 'E', 'I', 'O', 'U']) {
                "an"
            } else {
                "a"
            };
            return Err(format!("{} bytes for {a} {name} ({n} bytes)", raw.len()));
        }
    }
    let mut b = [0u8; 8];
    b[..raw.len().min(8)].copy_from_slice(&raw[..raw.len().min(8)]);
    let u = u64::from_le_bytes(b);
    let bits = raw.len() as u32 * 8;
    Ok(match ty {
        Type::Boolean => Value::Bool(u != 0),
        Type::U8 | Type::U16 | Type::U32 | Type::U64 => Value::Uint(u),
        Type::I8 | Type::I16 | Type::I32 | Type::I64 => {
            Value::Int(((u << (64 - bits)) as i64) >> (64 - bits))
        }
        Type::Real32 => Value::Real32(f32::from_bits(u as u32)),
        Type::Real64 => Value::Real64(f64::from_bits(u)),
        Type::VisibleString => {
            let end = raw.iter().rposition(|&c| c != 0).map_or(0, |p| p + 1);
            Value::Text(String::from_utf8_lossy(&raw[..end]).into_owned())
        }
        Type::UnicodeString => {
            let w: Vec<u16> = raw
                .chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect();
            Value::Text(
                String::from_utf16_lossy(&w)
                    .trim_end_matches('\0')
                    .to_string(),
            )
        }
        Type::OctetString | Type::Domain | Type::Other(_) => Value::Bytes(raw.to_vec()),
    })
}

/// Parses `text` as a value of type `ty` and encodes it in the type's
/// size (little endian).
///
/// # Errors
/// Text that is not a value of the type, in a sentence naming the type.
pub fn encode(ty: Type, text: &str) -> Result<(Value, Vec<u8>), String> {
    let t = text.trim();
    let size = ty.size().unwrap_or(0);
    match ty {
        Type::Boolean => {
            let v = match t.to_ascii_lowercase().as_str() {
                "0" | "false" => false,
                "1" | "true" => true,
                _ => return Err(format!("`{text}` is not a BOOLEAN (0, 1, true, false)")),
            };
            Ok((Value::Bool(v), vec![u8::from(v)]))
        }
        Type::U8 | Type::U16 | Type::U32 | Type::U64 => {
            let max = u64::MAX >> (64 - 8 * size as u32);
            let v = parse_int(t)
                .and_then(|v| u64::try_from(v).ok())
                .filter(|&v| v <= max)
                .ok_or_else(|| {
                    format!(
                        "`{text}` is not a {} (0..{max}, decimal or 0x hex)",
                        ty.name()
                    )
                })?;
            Ok((Value::Uint(v), v.to_le_bytes()[..size].to_vec()))
        }
        Type::I8 | Type::I16 | Type::I32 | Type::I64 => {
            let max = i64::MAX >> (64 - 8 * size as u32);
            let v = parse_int(t)
                .and_then(|v| i64::try_from(v).ok())
                .filter(|&v| v <= max && v >= -max - 1)
                .ok_or_else(|| format!("`{text}` is not an {} ({}..{max})", ty.name(), -max - 1))?;
            Ok((Value::Int(v), v.to_le_bytes()[..size].to_vec()))
        }
        Type::Real32 | Type::Real64 => encode_real(ty, t, text),
        Type::VisibleString => Ok((Value::Text(text.into()), text.as_bytes().to_vec())),
        Type::UnicodeString => {
            let b = text.encode_utf16().flat_map(u16::to_le_bytes).collect();
            Ok((Value::Text(text.into()), b))
        }
        Type::OctetString | Type::Domain | Type::Other(_) => {
            let b = parse_hex_bytes(t).ok_or_else(|| {
                format!(
                    "`{text}` is not hex bytes for a {} (e.g. 01a2ff or \"01 a2 ff\")",
                    ty.name()
                )
            })?;
            Ok((Value::Bytes(b.clone()), b))
        }
    }
}

fn encode_real(ty: Type, t: &str, text: &str) -> Result<(Value, Vec<u8>), String> {
    let v = t.parse::<f64>().map_err(|_| {
        format!(
            "`{text}` is not a {} (a number such as 0.05 or -1e-3)",
            ty.name()
        )
    })?;
    if ty == Type::Real64 {
        return Ok((Value::Real64(v), v.to_le_bytes().to_vec()));
    }
    let f = v as f32;
    if v.is_finite() && !f.is_finite() {
        return Err(format!(
            "`{text}` is beyond the range of a REAL32 (±3.4e38)"
        ));
    }
    Ok((Value::Real32(f), f.to_le_bytes().to_vec()))
}

fn parse_hex_bytes(t: &str) -> Option<Vec<u8>> {
    let s: String = t
        .trim_start_matches("0x")
        .chars()
        .filter(|c| !c.is_whitespace())
        .collect();
    if !s.len().is_multiple_of(2) || !s.is_ascii() {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok())
        .collect()
}

/// Whether `v` lies within the entry's EDS limits; the refusal names them.
/// Reals are compared in the entry's precision (a REAL32 as the node
/// compares it), a non-finite real is outside any limits.
///
/// # Errors
/// The value outside, in a sentence.
pub fn check_limits(e: &Entry, v: &Value) -> Result<(), String> {
    let Some(lim) = e.limits_text() else {
        return Ok(());
    };
    let real32 = |n: Num| match n {
        Num::Int(i) => i as f32 as f64,
        Num::Real(r) => r as f32 as f64,
    };
    let real = |n: Num| match n {
        Num::Int(i) => i as f64,
        Num::Real(r) => r,
    };
    let (x, conv): (f64, &dyn Fn(Num) -> f64) = match v {
        Value::Uint(u) => return check_int(e, i128::from(*u), &lim),
        Value::Int(i) => return check_int(e, i128::from(*i), &lim),
        Value::Real32(f) => (f64::from(*f), &real32),
        Value::Real64(f) => (*f, &real),
        _ => return Ok(()),
    };
    let below = e.low.is_some_and(|l| x < conv(l));
    let above = e.high.is_some_and(|h| x > conv(h));
    if below || above || !x.is_finite() {
        return Err(format!("{} is outside the EDS {lim}", show(v)));
    }
    Ok(())
}

fn check_int(e: &Entry, x: i128, lim: &str) -> Result<(), String> {
    let below = |n: Num| match n {
        Num::Int(l) => x < l,
        Num::Real(l) => (x as f64) < l,
    };
    let above = |n: Num| match n {
        Num::Int(h) => x > h,
        Num::Real(h) => (x as f64) > h,
    };
    if e.low.is_some_and(below) || e.high.is_some_and(above) {
        return Err(format!("{x} is outside the EDS {lim}"));
    }
    Ok(())
}

/// A value as text: unsigned integers above 9 also in hex, strings quoted.
pub fn show(v: &Value) -> String {
    match v {
        Value::Bool(b) => b.to_string(),
        Value::Uint(u) if *u > 9 => format!("{u} ({u:#x})"),
        Value::Uint(u) => u.to_string(),
        Value::Int(i) => i.to_string(),
        Value::Real32(f) => f.to_string(),
        Value::Real64(f) => f.to_string(),
        Value::Text(s) => format!("{s:?}"),
        Value::Bytes(b) if b.is_empty() => "(no bytes)".into(),
        Value::Bytes(b) => hex(b),
    }
}

/// A value as JSON: numbers as numbers (a REAL32 by its shortest decimal),
/// bytes as a hex string.
pub fn to_json(v: &Value) -> serde_json::Value {
    match v {
        Value::Bool(b) => json!(b),
        Value::Uint(u) => json!(u),
        Value::Int(i) => json!(i),
        Value::Real32(f) if f.is_finite() => json!(f.to_string().parse::<f64>().unwrap_or(0.0)),
        Value::Real64(f) if f.is_finite() => json!(f),
        Value::Real32(_) | Value::Real64(_) => json!(null),
        Value::Text(s) => json!(s),
        Value::Bytes(b) => json!(hex(b)),
    }
}

/// `0x2300 sub 4  Acquisition: Residual limit mm (REAL32, rw)`.
fn label(e: &Entry) -> String {
    let name = if e.object == e.name {
        e.name.clone()
    } else {
        format!("{}: {}", e.object, e.name)
    };
    format!(
        "{:#06x} sub {}  {name} ({}, {})",
        e.index,
        e.sub,
        e.ty.name(),
        e.access.as_str()
    )
}

/// ` mm` or nothing.
fn unit_suffix(e: &Entry) -> String {
    e.unit.as_ref().map(|u| format!(" {u}")).unwrap_or_default()
}

/// The JSON fields that describe an entry (or `null`s for one the EDS
/// does not list).
fn describe_json(node: &Node, index: u16, sub: u8, e: Option<&Entry>) -> serde_json::Value {
    json!({
        "schema": SCHEMA, "node_id": node.id, "index": index, "sub": sub,
        "in_eds": e.is_some(),
        "name": e.map(|e| e.name.clone()), "object": e.map(|e| e.object.clone()),
        "type": e.map(|e| e.ty.name()), "access": e.map(|e| e.access.as_str()),
        "unit": e.and_then(|e| e.unit.clone()),
        "low": num_json(e.and_then(|e| e.low)), "high": num_json(e.and_then(|e| e.high)),
    })
}

/// A limit as JSON (an integer beyond i64 as a string).
fn num_json(n: Option<Num>) -> serde_json::Value {
    match n {
        Some(Num::Int(i)) => i64::try_from(i).map_or(json!(i.to_string()), |i| json!(i)),
        Some(Num::Real(r)) => json!(r),
        None => json!(null),
    }
}

fn merge(mut a: serde_json::Value, b: serde_json::Value) -> serde_json::Value {
    if let (Some(a), serde_json::Value::Object(b)) = (a.as_object_mut(), b) {
        a.extend(b);
    }
    a
}

/// Runs `perpend node sdo read|write` (`list` runs through [`list`]).
///
/// # Errors
/// A bad EDS, a refused value, the node's abort or silence, in sentences.
pub fn run(node: &mut Node, a: &Args) -> Result<()> {
    let eds = Eds::builtin_or(a.eds.as_ref())?;
    let builtin = a.eds.is_none();
    match &a.cmd {
        SdoCmd::Read(r) => read(node, &eds, builtin, r),
        SdoCmd::Write(w) => write(node, &eds, builtin, w),
        SdoCmd::List(l) => list_eds(&eds, l),
    }
}

/// The node's identity (0x1018 sub 1, 2) against the EDS's
/// `VendorNumber`/`ProductNumber`, in one line when they differ: the EDS
/// then types another device's objects. The built-in EDS is compared by
/// product only (the board's vendor-ID is set when its firmware is
/// built). `None` when they agree, or the node or the EDS does not say.
fn identity_mismatch(node: &mut Node, eds: &Eds, builtin: bool) -> Option<String> {
    let vendor = node.client.read_u32(node.id, 0x1018, 1).ok();
    let product = node.client.read_u32(node.id, 0x1018, 2).ok();
    let differs = |a: Option<u32>, b: Option<u32>| matches!((a, b), (Some(a), Some(b)) if a != b);
    if !(differs(product, eds.product) || !builtin && differs(vendor, eds.vendor)) {
        return None;
    }
    let hex = |v: Option<u32>| v.map_or("?".into(), |v| format!("{v:#010x}"));
    Some(format!(
        "{} is vendor {} product {} (0x1018), but {} describes vendor {} product {}: its \
         types and limits may not be this node's; give the node's own EDS with --eds FILE",
        node.name(),
        hex(vendor),
        hex(product),
        eds.file,
        hex(eds.vendor),
        hex(eds.product)
    ))
}

/// Uploads `(index, sub)`, turning an abort into a sentence with a hint.
fn upload(node: &mut Node, e: Option<&Entry>, index: u16, sub: u8) -> Result<Vec<u8>> {
    node.client
        .upload(node.id, index, sub)
        .map_err(|err| explain(node, e, err))
}

fn read(node: &mut Node, eds: &Eds, builtin: bool, a: &ReadArgs) -> Result<()> {
    node.hello()?;
    if let Some(w) = identity_mismatch(node, eds, builtin) {
        eprintln!("warning: {w}");
    }
    let e = eds.get(a.index, a.sub);
    let raw = upload(node, e, a.index, a.sub)?;
    let value = e.map(|e| decode(e.ty, &raw));
    if a.json {
        let mut v = merge(
            describe_json(node, a.index, a.sub, e),
            json!({"op": "read", "raw_hex": hex(&raw)}),
        );
        v["value"] = match &value {
            Some(Ok(x)) => to_json(x),
            _ => raw_u32(&raw).map_or(json!(null), |u| json!(u)),
        };
        if let Some(Err(why)) = &value {
            v["decode_error"] = json!(why);
        }
        println!("{}", crate::schema::tagged(SCHEMA, &v));
        return Ok(());
    }
    match (e, value) {
        (Some(e), Some(Ok(v))) => {
            let lim = e
                .limits_text()
                .map(|l| format!("  [{l}]"))
                .unwrap_or_default();
            println!("{} = {}{}{lim}", label(e), show(&v), unit_suffix(e));
        }
        (Some(e), Some(Err(why))) => {
            println!("{} = {} (the node sent {why})", label(e), raw_text(&raw));
        }
        _ => println!(
            "{:#06x} sub {}  = {}  ({} does not list this object)",
            a.index,
            a.sub,
            raw_text(&raw),
            eds.file
        ),
    }
    Ok(())
}

/// Little-endian UNSIGNED32 of up to 4 bytes.
fn raw_u32(raw: &[u8]) -> Option<u32> {
    (!raw.is_empty() && raw.len() <= 4).then(|| {
        let mut b = [0u8; 4];
        b[..raw.len()].copy_from_slice(raw);
        u32::from_le_bytes(b)
    })
}

/// Bytes in hex, and as a little-endian integer when they are ≤ 4.
fn raw_text(raw: &[u8]) -> String {
    match raw_u32(raw) {
        Some(u) => format!(
            "{} byte(s) {} (little-endian UNSIGNED32 {u} = {u:#x})",
            raw.len(),
            hex(raw)
        ),
        None => format!("{} byte(s) {}", raw.len(), hex(raw)),
    }
}

/// Checks a write before anything is sent; returns what to send.
fn prepare(eds: &Eds, a: &WriteArgs) -> Result<(Entry, Value, Vec<u8>)> {
    let Some(e) = eds.get(a.index, a.sub) else {
        bail!(
            "{:#06x} sub {} is not in {}, so its type is unknown and nothing was sent; \
             give the node's EDS with --eds FILE",
            a.index,
            a.sub,
            eds.file
        );
    };
    let (v, bytes) =
        encode(e.ty, &a.value).map_err(|why| anyhow!("{}: {why}; nothing was sent", label(e)))?;
    if !a.force {
        if !e.access.writable() {
            bail!(
                "{} is {} in {}: the node would refuse the write (abort 0x06010002); \
                 nothing was sent (--force sends it anyway)",
                label(e),
                if e.access == crate::eds::Access::Const {
                    "constant"
                } else {
                    "read-only"
                },
                eds.file
            );
        }
        check_limits(e, &v)
            .and_then(|()| super::sdo_rules::precheck(e, as_uint(&v)))
            .map_err(|why| {
                anyhow!(
                    "{}: {why}; nothing was sent (--force sends it anyway)",
                    label(e)
                )
            })?;
    }
    Ok((e.clone(), v, bytes))
}

fn write(node: &mut Node, eds: &Eds, builtin: bool, a: &WriteArgs) -> Result<()> {
    let (e, value, bytes) = prepare(eds, a)?;
    node.hello()?;
    match identity_mismatch(node, eds, builtin) {
        Some(w) if !a.force => bail!("{w}. Nothing was sent (--force sends it anyway)"),
        Some(w) => eprintln!("warning: {w}"),
        None => {}
    }
    let readable = e.access != crate::eds::Access::Wo;
    let old = if readable {
        node.client.upload(node.id, a.index, a.sub).ok()
    } else {
        None
    };
    if let Err(err) = node.client.download(node.id, a.index, a.sub, &bytes) {
        return Err(explain_write(node, &e, &value, err));
    }
    let new = if readable {
        Some(upload(node, Some(&e), a.index, a.sub)?)
    } else {
        None
    };
    let dec = |r: &Option<Vec<u8>>| r.as_ref().and_then(|r| decode(e.ty, r).ok());
    let (old_v, new_v) = (dec(&old), dec(&new));
    if a.json {
        let v = merge(
            describe_json(node, a.index, a.sub, Some(&e)),
            json!({
                "op": "write", "written": to_json(&value), "written_hex": hex(&bytes),
                "old": old_v.as_ref().map(to_json), "old_hex": old.as_deref().map(hex),
                "value": new_v.as_ref().map(to_json), "raw_hex": new.as_deref().map(hex),
            }),
        );
        println!("{}", crate::schema::tagged(SCHEMA, &v));
        return Ok(());
    }
    let u = unit_suffix(&e);
    let s = |v: &Option<Value>| v.as_ref().map_or("?".into(), |v| format!("{}{u}", show(v)));
    println!("{}: {} → {}", label(&e), s(&old_v), s(&new_v));
    if new_v.as_ref().is_some_and(|n| *n != value) {
        println!(
            "  (wrote {}; the node reads back another value: a command object, or the node \
             adjusted it)",
            show(&value)
        );
    }
    Ok(())
}

/// `perpend node --bus BUS --node-id N`, for hints.
fn link_of(node: &Node) -> String {
    format!(
        "perpend node --bus {} --node-id {}",
        node.client.bus_name(),
        node.id
    )
}

/// A refused download as a sentence: a value-range abort says the rule
/// that refused `value` ([`super::sdo_rules::range_hint`]), other aborts
/// as [`explain`].
fn explain_write(node: &mut Node, e: &Entry, value: &Value, err: ClientError) -> anyhow::Error {
    if !matches!(err.abort_code(), Some(0x0609_0030..=0x0609_0032)) {
        return explain(node, Some(e), err);
    }
    let link = link_of(node);
    let rule = super::sdo_rules::range_hint(node, e, as_uint(value), &link);
    let hint = match (rule, e.limits_text(), check_limits(e, value)) {
        (Some(rule), _, _) => rule,
        (None, Some(l), Err(_)) => format!("the EDS gives {l}"),
        (None, Some(l), Ok(())) => format!(
            "{} is inside the EDS {l}, so the node refused it by a rule the EDS cannot \
             state (this board's: docs/can.md, object {:#06x}); check the node's manual",
            show(value),
            e.index
        ),
        (None, None, _) => format!(
            "the node refused {} by a rule the EDS does not state (this board's: \
             docs/can.md, object {:#06x}); check the node's manual",
            show(value),
            e.index
        ),
    };
    anyhow!("{err}\n  what to do: {hint}")
}

/// An unsigned integer value, if `v` is one (the board's rules of
/// `sdo_rules.rs` are about those only).
fn as_uint(v: &Value) -> Option<u64> {
    match v {
        Value::Uint(u) => Some(*u),
        Value::Int(i) => u64::try_from(*i).ok(),
        _ => None,
    }
}

/// A client error as a sentence, with what to do for the aborts that have
/// a remedy.
fn explain(node: &Node, e: Option<&Entry>, err: ClientError) -> anyhow::Error {
    let Some(code) = err.abort_code() else {
        return err.into();
    };
    let link = link_of(node);
    let hint = match code {
        0x0800_0022 => format!(
            "the node is operational or stopped: `{link} nmt preop` first, then write again"
        ),
        0x0800_0021 => format!(
            "to unlock (in pre-operational): `{link} sdo write 0x2010 0 {:#010x}`",
            perpend_can::od::UNLOCK_SIGNATURE
        ),
        0x0609_0030..=0x0609_0032 => match e.and_then(Entry::limits_text) {
            Some(l) => format!("the EDS gives {l}"),
            None => return err.into(),
        },
        0x0602_0000 | 0x0609_0011 if e.is_some() => {
            "the EDS lists it but the node does not have it: another device or firmware? \
             give its EDS with --eds FILE"
                .into()
        }
        _ => return err.into(),
    };
    anyhow!("{err}\n  what to do: {hint}")
}

/// Runs `perpend node sdo list` (no bus needed). With `--bus` and
/// `--node-id` it also says whether the EDS is that node's (0x1018
/// against `VendorNumber`/`ProductNumber`), on stderr.
///
/// # Errors
/// A bad `--eds` file, an index the EDS does not have; with a link, a
/// missing `--bus` or `--node-id` and the node's silence.
pub fn list(link: &super::LinkArgs, a: &Args) -> Result<()> {
    let eds = Eds::builtin_or(a.eds.as_ref())?;
    if link.bus.is_some() || link.node_id.is_some() {
        let mut node = Node::connect(link)?;
        node.hello()?;
        match identity_mismatch(&mut node, &eds, a.eds.is_none()) {
            Some(w) => eprintln!("warning: {w}"),
            None => eprintln!(
                "{}: {} agrees with its identity (0x1018)",
                node.name(),
                eds.file
            ),
        }
    }
    match &a.cmd {
        SdoCmd::List(l) => list_eds(&eds, l),
        _ => bail!("perpend node sdo read and write need --bus"),
    }
}

fn list_eds(eds: &Eds, a: &ListArgs) -> Result<()> {
    let entries: Vec<&Entry> = match a.index {
        Some(i) => eds.object(i).collect(),
        None => eds.entries.values().collect(),
    };
    if let (Some(i), true) = (a.index, entries.is_empty()) {
        bail!("{} does not list object {i:#06x}", eds.file);
    }
    if a.json {
        let rows: Vec<_> = entries.iter().map(|e| list_json(e)).collect();
        let v = json!({"schema": SCHEMA, "op": "list", "eds": eds.file, "entries": rows});
        println!("{}", crate::schema::tagged(SCHEMA, &v));
        return Ok(());
    }
    // A long listing is often piped into `head` or `grep -m`: a closed
    // pipe ends it quietly.
    let mut text = format!("{}: {} entries\n", eds.file, entries.len());
    for e in entries {
        text += &list_line(e);
        text.push('\n');
    }
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}

fn list_line(e: &Entry) -> String {
    let name = if e.object == e.name {
        e.name.clone()
    } else {
        format!("{}: {}", e.object, e.name)
    };
    let mut s = format!(
        "{:#06x} {:>3}  {:<14} {:<5}  {name}",
        e.index,
        e.sub,
        e.ty.name(),
        e.access.as_str()
    );
    if let Some(u) = &e.unit {
        s += &format!("  [{u}]");
    }
    if let Some(l) = e.limits_text() {
        s += &format!("  {l}");
    }
    if let Some(d) = &e.default {
        s += &format!("  default {d}");
    }
    s
}

fn list_json(e: &Entry) -> serde_json::Value {
    json!({
        "index": e.index, "sub": e.sub, "name": e.name, "object": e.object,
        "type": e.ty.name(), "access": e.access.as_str(), "unit": e.unit,
        "low": num_json(e.low), "high": num_json(e.high), "default": e.default, "pdo": e.pdo,
    })
}

#[cfg(test)]
#[path = "sdo_tests.rs"]
mod tests;
