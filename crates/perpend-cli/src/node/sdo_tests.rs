//! Tests of `sdo`'s value parsing, encoding, decoding, limits and text.
#![allow(clippy::unwrap_used, clippy::panic)]

use super::*;
use crate::eds::Eds;

#[test]
fn indices_and_subs_parse_in_hex_and_decimal() {
    assert_eq!(parse_index("0x2300"), Ok(0x2300));
    assert_eq!(parse_index("2300h"), Ok(0x2300));
    assert_eq!(parse_index("1017H"), Ok(0x1017));
    assert_eq!(parse_index("4119"), Ok(0x1017));
    assert!(parse_index("0x12345").is_err());
    assert!(parse_index("x")
        .unwrap_err()
        .contains("not an object index"));
    assert_eq!(parse_sub("0x10"), Ok(16));
    assert_eq!(parse_sub("4"), Ok(4));
    assert!(parse_sub("256").is_err());
}

#[test]
fn every_type_round_trips_through_encode_and_decode() {
    let cases: &[(Type, &str, Value, &[u8])] = &[
        (Type::Boolean, "true", Value::Bool(true), &[1]),
        (Type::U8, "0xff", Value::Uint(255), &[0xFF]),
        (Type::U16, "250", Value::Uint(250), &[0xFA, 0]),
        (Type::U32, "0x6C616375", Value::Uint(0x6C61_6375), b"ucal"),
        (Type::U64, "1", Value::Uint(1), &[1, 0, 0, 0, 0, 0, 0, 0]),
        (Type::I8, "-2", Value::Int(-2), &[0xFE]),
        (Type::I16, "-300", Value::Int(-300), &[0xD4, 0xFE]),
        (Type::I32, "-1", Value::Int(-1), &[0xFF; 4]),
        (
            Type::Real32,
            "0.05",
            Value::Real32(0.05),
            &0.05f32.to_le_bytes(),
        ),
        (
            Type::Real64,
            "-1e-3",
            Value::Real64(-1e-3),
            &(-1e-3f64).to_le_bytes(),
        ),
        (
            Type::VisibleString,
            "abc",
            Value::Text("abc".into()),
            b"abc",
        ),
        (
            Type::OctetString,
            "01 a2 ff",
            Value::Bytes(vec![1, 0xA2, 0xFF]),
            &[1, 0xA2, 0xFF],
        ),
        (Type::Domain, "0x0102", Value::Bytes(vec![1, 2]), &[1, 2]),
    ];
    for (ty, text, v, bytes) in cases {
        let (got, b) = encode(*ty, text).unwrap();
        assert_eq!((&got, b.as_slice()), (v, *bytes), "{}", ty.name());
        assert_eq!(decode(*ty, bytes).unwrap(), *v, "{}", ty.name());
    }
}

#[test]
fn values_outside_their_type_are_refused_in_words() {
    let cases: &[(Type, &str, &str)] = &[
        (Type::U8, "256", "not a UNSIGNED8 (0..255"),
        (Type::U16, "-1", "not a UNSIGNED16"),
        (Type::I8, "128", "not an INTEGER8 (-128..127)"),
        (Type::U32, "1.5", "decimal or 0x hex"),
        (Type::Real32, "1e39", "beyond the range of a REAL32"),
        (Type::Real32, "fast", "not a REAL32"),
        (Type::Boolean, "2", "not a BOOLEAN"),
        (Type::OctetString, "abc", "not hex bytes"),
    ];
    for (ty, text, want) in cases {
        let e = encode(*ty, text).unwrap_err();
        assert!(e.contains(want), "{text}: {e}");
    }
}

#[test]
fn a_wrong_length_is_a_decode_error() {
    let e = decode(Type::U16, &[1, 2, 3, 4]).unwrap_err();
    assert!(e.contains("4 bytes for an UNSIGNED16"), "{e}");
    let e = decode(Type::I16, &[1, 2, 3, 4]).unwrap_err();
    assert!(e.contains("4 bytes for an INTEGER16 (2 bytes)"), "{e}");
    let e = decode(Type::Real32, &[1, 2]).unwrap_err();
    assert!(e.contains("2 bytes for a REAL32"), "{e}");
    assert_eq!(
        decode(Type::VisibleString, b"ab\0\0").unwrap(),
        Value::Text("ab".into())
    );
}

#[test]
fn limits_are_checked_in_the_entrys_precision() {
    let eds = Eds::builtin().unwrap();
    let res = eds.get(0x2300, 4).unwrap(); // REAL32 0.0001..100
    assert!(check_limits(res, &Value::Real32(0.0001)).is_ok());
    assert!(check_limits(res, &Value::Real32(100.0)).is_ok());
    let e = check_limits(res, &Value::Real32(200.0)).unwrap_err();
    assert!(e.contains("limits 0.0001..100"), "{e}");
    assert!(check_limits(res, &Value::Real32(f32::NAN)).is_err());
    assert!(check_limits(res, &Value::Real32(0.0)).is_err());
    let period = eds.get(0x2300, 1).unwrap(); // UNSIGNED32 100..100000
    assert!(check_limits(period, &Value::Uint(100)).is_ok());
    let e = check_limits(period, &Value::Uint(99)).unwrap_err();
    assert!(
        e.contains("99 is outside the EDS limits 100..100000"),
        "{e}"
    );
    let hb = eds.get(0x1017, 0).unwrap(); // no limits
    assert!(check_limits(hb, &Value::Uint(65535)).is_ok());
}

#[test]
fn values_show_as_text_and_json() {
    assert_eq!(show(&Value::Uint(1000)), "1000 (0x3e8)");
    assert_eq!(show(&Value::Uint(5)), "5");
    assert_eq!(show(&Value::Real32(0.05)), "0.05");
    assert_eq!(show(&Value::Text("a b".into())), "\"a b\"");
    assert_eq!(show(&Value::Bytes(vec![1, 0xAB])), "01 ab");
    assert_eq!(to_json(&Value::Real32(0.05)).to_string(), "0.05");
    assert_eq!(to_json(&Value::Real32(f32::NAN)), serde_json::Value::Null);
    assert_eq!(to_json(&Value::Bytes(vec![1, 2])), json!("01 02"));
}

#[test]
fn writes_are_checked_before_anything_is_sent() {
    let eds = Eds::builtin().unwrap();
    let w = |index, sub, value: &str, force| WriteArgs {
        index,
        sub,
        value: value.into(),
        force,
        json: false,
    };
    let (e, v, b) = prepare(&eds, &w(0x1017, 0, "250", false)).unwrap();
    assert_eq!((e.ty, v, b), (Type::U16, Value::Uint(250), vec![250, 0]));
    let err = prepare(&eds, &w(0x1018, 1, "5", false))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("is constant") && err.contains("nothing was sent"),
        "{err}"
    );
    assert!(prepare(&eds, &w(0x1018, 1, "5", true)).is_ok());
    let err = prepare(&eds, &w(0x2300, 4, "200", false))
        .unwrap_err()
        .to_string();
    assert!(err.contains("limits 0.0001..100"), "{err}");
    let err = prepare(&eds, &w(0x3000, 0, "1", true))
        .unwrap_err()
        .to_string();
    assert!(err.contains("not in perpend.eds (built in)"), "{err}");
    let err = prepare(&eds, &w(0x1017, 0, "70000", true))
        .unwrap_err()
        .to_string();
    assert!(err.contains("not a UNSIGNED16"), "{err}");
}

#[test]
fn list_lines_name_type_access_unit_and_limits() {
    let eds = Eds::builtin().unwrap();
    let l = list_line(eds.get(0x2300, 4).unwrap());
    assert!(l.starts_with("0x2300   4  REAL32"), "{l}");
    assert!(
        l.contains("Acquisition: Residual limit mm  [mm]  limits 0.0001..100"),
        "{l}"
    );
}
