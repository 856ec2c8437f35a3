//! The canonical text of params: a small serde serializer whose output this project owns.
//!
//! Canonical params are hashed into task keys, so their text must not change unless the params
//! do: not with a dependency's upgrade, not with a printer option. Hence a printer of our own, pinned
//! by tests (here and the key-stability test in `dist4d-runtime`). Its output is the RON subset
//! that [`crate::syntax`] parses, so `explain` can read old and new params field by field:
//!
//! - structs (named or not) and struct variants' fields: `(a:1,b:"x")`, every field, in declaration
//!   order, no spaces, no trailing comma; an empty struct is `()`;
//! - tuples and tuple structs `(1,2)`; sequences `[1,2]`; maps `{"k":1}`; bytes as a sequence;
//! - integers in decimal; floats in Rust's shortest round-trip form (`{:?}`), which always holds a
//!   `.` or an exponent (`1.0`, `0.1`, `1e-7`), or is `inf`, `-inf`, `NaN`, so a float never reads as
//!   an integer; an `f32` is printed as the `f32` it is (`0.1`, not `0.10000000149011612`);
//! - strings and chars quoted, with `\\`, `\"`, `\n`, `\r`, `\t`, `\0` and `\u{..}` (other control
//!   characters) escaped;
//! - `None`, `Some(x)`, `()`; newtype structs as their inner value (as [`crate::de`] reads them);
//!   enum variants by name: `Near`, `Shift(2.0)`, `Pair(1,2)`, `Box(w:1.0)`.

use serde::ser::{self, Serialize};
use std::fmt::{self, Write};

/// A value that cannot be written canonically (a `Serialize` impl reported an error).
#[derive(Clone, Debug, PartialEq)]
pub struct CanonicalError(pub String);

impl fmt::Display for CanonicalError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CanonicalError {}

impl ser::Error for CanonicalError {
    fn custom<T: fmt::Display>(msg: T) -> Self {
        CanonicalError(msg.to_string())
    }
}

/// The canonical text of `value`.
pub fn to_canonical<T: Serialize + ?Sized>(value: &T) -> Result<String, CanonicalError> {
    let mut out = String::new();
    value.serialize(Printer { out: &mut out })?;
    Ok(out)
}

struct Printer<'a> {
    out: &'a mut String,
}

type R = Result<(), CanonicalError>;

impl Printer<'_> {
    fn float(self, text: String) -> R {
        // `{:?}` gives `1.0`, `1e-7`, `inf`, `NaN`: always a float to the parser.
        self.out.push_str(&text);
        Ok(())
    }
}

fn quoted(out: &mut String, s: &str, quote: char) {
    out.push(quote);
    for c in s.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            '\0' => out.push_str("\\0"),
            c if c == quote => {
                out.push('\\');
                out.push(c);
            }
            c if c.is_control() => {
                let _ = write!(out, "\\u{{{:x}}}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push(quote);
}

/// Writes the items of a container between `open` and `close`, comma separated.
struct Seq<'a> {
    out: &'a mut String,
    first: bool,
    close: &'static str,
}

impl<'a> Seq<'a> {
    fn open(out: &'a mut String, open: &str, close: &'static str) -> Seq<'a> {
        out.push_str(open);
        Seq { out, first: true, close }
    }

    fn sep(&mut self) {
        if !self.first {
            self.out.push(',');
        }
        self.first = false;
    }

    fn item<T: Serialize + ?Sized>(&mut self, value: &T) -> R {
        self.sep();
        value.serialize(Printer { out: self.out })
    }

    fn field<T: Serialize + ?Sized>(&mut self, name: &str, value: &T) -> R {
        self.sep();
        self.out.push_str(name);
        self.out.push(':');
        value.serialize(Printer { out: self.out })
    }

    fn end(self) -> R {
        self.out.push_str(self.close);
        Ok(())
    }
}

impl<'a> ser::Serializer for Printer<'a> {
    type Ok = ();
    type Error = CanonicalError;
    type SerializeSeq = Seq<'a>;
    type SerializeTuple = Seq<'a>;
    type SerializeTupleStruct = Seq<'a>;
    type SerializeTupleVariant = Seq<'a>;
    type SerializeMap = Seq<'a>;
    type SerializeStruct = Seq<'a>;
    type SerializeStructVariant = Seq<'a>;

    fn serialize_bool(self, v: bool) -> R {
        self.out.push_str(if v { "true" } else { "false" });
        Ok(())
    }
    fn serialize_i8(self, v: i8) -> R {
        self.serialize_i64(v as i64)
    }
    fn serialize_i16(self, v: i16) -> R {
        self.serialize_i64(v as i64)
    }
    fn serialize_i32(self, v: i32) -> R {
        self.serialize_i64(v as i64)
    }
    fn serialize_i64(self, v: i64) -> R {
        let _ = write!(self.out, "{v}");
        Ok(())
    }
    fn serialize_i128(self, v: i128) -> R {
        let _ = write!(self.out, "{v}");
        Ok(())
    }
    fn serialize_u8(self, v: u8) -> R {
        self.serialize_u64(v as u64)
    }
    fn serialize_u16(self, v: u16) -> R {
        self.serialize_u64(v as u64)
    }
    fn serialize_u32(self, v: u32) -> R {
        self.serialize_u64(v as u64)
    }
    fn serialize_u64(self, v: u64) -> R {
        let _ = write!(self.out, "{v}");
        Ok(())
    }
    fn serialize_u128(self, v: u128) -> R {
        let _ = write!(self.out, "{v}");
        Ok(())
    }
    fn serialize_f32(self, v: f32) -> R {
        self.float(format!("{v:?}"))
    }
    fn serialize_f64(self, v: f64) -> R {
        self.float(format!("{v:?}"))
    }
    fn serialize_char(self, v: char) -> R {
        quoted(self.out, v.encode_utf8(&mut [0; 4]), '\'');
        Ok(())
    }
    fn serialize_str(self, v: &str) -> R {
        quoted(self.out, v, '"');
        Ok(())
    }
    fn serialize_bytes(self, v: &[u8]) -> R {
        let mut s = Seq::open(self.out, "[", "]");
        for b in v {
            s.item(b)?;
        }
        s.end()
    }
    fn serialize_none(self) -> R {
        self.out.push_str("None");
        Ok(())
    }
    fn serialize_some<T: Serialize + ?Sized>(self, value: &T) -> R {
        let mut s = Seq::open(self.out, "Some(", ")");
        s.item(value)?;
        s.end()
    }
    fn serialize_unit(self) -> R {
        self.out.push_str("()");
        Ok(())
    }
    fn serialize_unit_struct(self, _: &'static str) -> R {
        self.serialize_unit()
    }
    fn serialize_unit_variant(self, _: &'static str, _: u32, variant: &'static str) -> R {
        self.out.push_str(variant);
        Ok(())
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(self, _: &'static str, value: &T) -> R {
        value.serialize(self)
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
        value: &T,
    ) -> R {
        self.out.push_str(variant);
        let mut s = Seq::open(self.out, "(", ")");
        s.item(value)?;
        s.end()
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Seq<'a>, CanonicalError> {
        Ok(Seq::open(self.out, "[", "]"))
    }
    fn serialize_tuple(self, _: usize) -> Result<Seq<'a>, CanonicalError> {
        Ok(Seq::open(self.out, "(", ")"))
    }
    fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Seq<'a>, CanonicalError> {
        Ok(Seq::open(self.out, "(", ")"))
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
        _: usize,
    ) -> Result<Seq<'a>, CanonicalError> {
        self.out.push_str(variant);
        Ok(Seq::open(self.out, "(", ")"))
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Seq<'a>, CanonicalError> {
        Ok(Seq::open(self.out, "{", "}"))
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Seq<'a>, CanonicalError> {
        Ok(Seq::open(self.out, "(", ")"))
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
        _: usize,
    ) -> Result<Seq<'a>, CanonicalError> {
        self.out.push_str(variant);
        Ok(Seq::open(self.out, "(", ")"))
    }
}

/// Sequences, tuples and tuple structs and variants all print their items in order.
macro_rules! items_in_order {
    ($($trait:ident :: $method:ident),*) => {$(
        impl ser::$trait for Seq<'_> {
            type Ok = ();
            type Error = CanonicalError;
            fn $method<T: Serialize + ?Sized>(&mut self, value: &T) -> R {
                self.item(value)
            }
            fn end(self) -> R {
                Seq::end(self)
            }
        }
    )*};
}

items_in_order!(
    SerializeSeq::serialize_element,
    SerializeTuple::serialize_element,
    SerializeTupleStruct::serialize_field,
    SerializeTupleVariant::serialize_field
);

impl ser::SerializeMap for Seq<'_> {
    type Ok = ();
    type Error = CanonicalError;
    fn serialize_key<T: Serialize + ?Sized>(&mut self, key: &T) -> R {
        self.item(key)
    }
    fn serialize_value<T: Serialize + ?Sized>(&mut self, value: &T) -> R {
        self.out.push(':');
        value.serialize(Printer { out: self.out })
    }
    fn end(self) -> R {
        Seq::end(self)
    }
}

impl ser::SerializeStruct for Seq<'_> {
    type Ok = ();
    type Error = CanonicalError;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, name: &'static str, value: &T) -> R {
        self.field(name, value)
    }
    fn end(self) -> R {
        Seq::end(self)
    }
}

impl ser::SerializeStructVariant for Seq<'_> {
    type Ok = ();
    type Error = CanonicalError;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, name: &'static str, value: &T) -> R {
        self.field(name, value)
    }
    fn end(self) -> R {
        Seq::end(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::de::from_value;
    use crate::source::Sources;
    use crate::syntax::{parse, ValueKind};
    use serde::{Deserialize, Serialize};
    use std::collections::BTreeMap;

    #[derive(Serialize, Deserialize, Debug, PartialEq, Clone)]
    enum Mode {
        Near,
        Shift(f64),
        Pair(i32, i32),
        Boxed { w: f32 },
    }

    #[derive(Serialize, Deserialize, Debug, PartialEq, Clone)]
    struct Meters(f64);

    #[derive(Serialize, Deserialize, Debug, PartialEq, Clone)]
    struct Inner {
        on: bool,
    }

    #[derive(Serialize, Deserialize, Debug, PartialEq, Clone)]
    #[serde(deny_unknown_fields)]
    struct Params {
        a: u32,
        b: String,
        f: f32,
        g: f64,
        neg: i64,
        maybe: Option<u8>,
        none: Option<u8>,
        list: Vec<f64>,
        pair: (i32, f32),
        mode: Mode,
        modes: Vec<Mode>,
        meters: Meters,
        inner: Inner,
        map: BTreeMap<String, u8>,
        c: char,
        unit: (),
    }

    fn sample() -> Params {
        Params {
            a: 7,
            b: "x \"q\" \\ \n\t\u{1}é".into(),
            f: 0.1,
            g: 1e-7,
            neg: -3,
            maybe: Some(2),
            none: None,
            list: vec![1.0, 2.5, 1e20, -0.0],
            pair: (-1, 3.0),
            mode: Mode::Near,
            modes: vec![Mode::Shift(2.0), Mode::Pair(1, 2), Mode::Boxed { w: 1.5 }],
            meters: Meters(100.0),
            inner: Inner { on: true },
            map: [("k".to_string(), 1u8)].into_iter().collect(),
            c: '\'',
            unit: (),
        }
    }

    /// The whole format in one pinned string: any change to it changes every task key, so it
    /// must be deliberate (bump the key domain in `dist4d-runtime`'s keys module with it).
    #[test]
    fn prints_the_pinned_format() {
        assert_eq!(
            to_canonical(&sample()).unwrap(),
            r#"(a:7,b:"x \"q\" \\ \n\t\u{1}é",f:0.1,g:1e-7,neg:-3,maybe:Some(2),none:None,list:[1.0,2.5,1e20,-0.0],pair:(-1,3.0),mode:Near,modes:[Shift(2.0),Pair(1,2),Boxed(w:1.5)],meters:100.0,inner:(on:true),map:{"k":1},c:'\'',unit:())"#
        );
    }

    #[test]
    fn the_graph_parser_reads_it_back_to_the_same_value() {
        let text = to_canonical(&sample()).unwrap();
        let mut s = Sources::default();
        let id = s.add("canonical", text.clone());
        let v = parse(&text, id).unwrap();
        assert_eq!(from_value::<Params>(&v).unwrap(), sample());
        // Field by field, as explain reads it.
        let f = v.field("f").unwrap();
        assert_eq!(s.slice(f.value.span), "0.1");
    }

    #[test]
    fn floats_never_read_as_integers_and_round_trip() {
        let mut s = Sources::default();
        for x in [0.0, 1.0, -2.0, 0.1, 1.0 / 3.0, 1e-7, 1e16, 1e300, f64::MIN_POSITIVE, f64::MAX, 123456789.0] {
            let text = to_canonical(&x).unwrap();
            assert!(text.contains(['.', 'e']), "{x}: {text}");
            let id = s.add("x", text.clone());
            match parse(&text, id).unwrap().kind {
                ValueKind::Float(y) => assert_eq!(y.to_bits(), x.to_bits(), "{text}"),
                other => panic!("{text} read as {other:?}"),
            }
        }
        for x in [0.1f32, 1.0 / 3.0, 16_777_217.0, f32::MAX, 1e-40] {
            let text = to_canonical(&x).unwrap();
            let id = s.add("x", text.clone());
            let ValueKind::Float(y) = parse(&text, id).unwrap().kind else { panic!("{text}") };
            assert_eq!((y as f32).to_bits(), x.to_bits(), "{text}");
        }
        for (x, want) in [(f64::INFINITY, "inf"), (f64::NEG_INFINITY, "-inf"), (f64::NAN, "NaN")] {
            let text = to_canonical(&x).unwrap();
            assert_eq!(text, want);
            let id = s.add("x", text.clone());
            assert!(matches!(parse(&text, id).unwrap().kind, ValueKind::Float(_)), "{text}");
        }
    }

    #[test]
    fn empty_and_unit_shapes() {
        #[derive(Serialize)]
        struct Empty {}
        #[derive(Serialize)]
        struct UnitStruct;
        assert_eq!(to_canonical(&Empty {}).unwrap(), "()");
        assert_eq!(to_canonical(&UnitStruct).unwrap(), "()");
        assert_eq!(to_canonical(&Vec::<u8>::new()).unwrap(), "[]");
        assert_eq!(to_canonical(&Some(Some(1))).unwrap(), "Some(Some(1))");
        assert_eq!(to_canonical(&u64::MAX).unwrap(), "18446744073709551615");
    }

    #[test]
    fn a_serialize_error_is_reported() {
        struct Refuses;
        impl Serialize for Refuses {
            fn serialize<S: ser::Serializer>(&self, _: S) -> Result<S::Ok, S::Error> {
                Err(ser::Error::custom("no canonical form"))
            }
        }
        assert_eq!(to_canonical(&Refuses), Err(CanonicalError("no canonical form".into())));
    }
}
