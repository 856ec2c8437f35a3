//! Typed params from a spanned [`Value`] through serde, with the span of the value that failed.
//!
//! Params structs are ordinary `#[derive(Deserialize)] #[serde(deny_unknown_fields, default)]`
//! structs; reading them from the spanned tree (instead of from text with the `ron` crate) is what
//! lets a type error in one param point at that param.

use crate::source::Span;
use crate::syntax::{Field, Value, ValueKind};
use serde::de::{self, DeserializeSeed, Visitor};
use std::fmt;

/// A params error with the span of the innermost value it concerns.
#[derive(Clone, Debug, PartialEq)]
pub struct DeError {
    pub message: String,
    pub span: Option<Span>,
}

impl fmt::Display for DeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for DeError {}

impl de::Error for DeError {
    fn custom<T: fmt::Display>(msg: T) -> Self {
        DeError { message: msg.to_string(), span: None }
    }
}

impl DeError {
    fn at(mut self, span: Span) -> Self {
        self.span.get_or_insert(span);
        self
    }
}

/// Reads a `T` from a spanned value.
pub fn from_value<'de, T: de::Deserialize<'de>>(value: &'de Value) -> Result<T, DeError> {
    T::deserialize(ValueDe(value))
}

/// The field names of a serde struct, found by asking its `Deserialize` impl.
pub fn struct_fields<'de, T: de::Deserialize<'de>>() -> &'static [&'static str] {
    struct Probe;
    #[derive(Debug)]
    struct Found(&'static [&'static str]);
    impl fmt::Display for Found {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("probe")
        }
    }
    impl std::error::Error for Found {}
    impl de::Error for Found {
        fn custom<M: fmt::Display>(_: M) -> Self {
            Found(&[])
        }
    }
    impl<'de> de::Deserializer<'de> for Probe {
        type Error = Found;
        fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, Found> {
            Err(Found(&[]))
        }
        fn deserialize_struct<V: Visitor<'de>>(
            self,
            _: &'static str,
            fields: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, Found> {
            Err(Found(fields))
        }
        serde::forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf option unit
            unit_struct newtype_struct seq tuple tuple_struct map enum identifier ignored_any
        }
    }
    match T::deserialize(Probe) {
        Err(Found(f)) => f,
        Ok(_) => &[],
    }
}

struct ValueDe<'a>(&'a Value);

impl<'a> ValueDe<'a> {
    fn invalid<T>(&self, expected: &str) -> Result<T, DeError> {
        Err(DeError { message: format!("expected {expected}, found {}", self.0.describe()), span: Some(self.0.span) })
    }
}

macro_rules! int_method {
    ($name:ident, $visit:ident, $ty:ty) => {
        fn $name<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
            match &self.0.kind {
                ValueKind::Int(i) => match <$ty>::try_from(*i) {
                    Ok(x) => v.$visit(x),
                    Err(_) => Err(DeError {
                        message: format!("{} does not fit in {}", i, stringify!($ty)),
                        span: Some(self.0.span),
                    }),
                },
                _ => self.invalid(concat!("an integer (", stringify!($ty), ")")),
            }
        }
    };
}

impl<'de> de::Deserializer<'de> for ValueDe<'de> {
    type Error = DeError;

    fn deserialize_any<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        let span = self.0.span;
        let r: Result<V::Value, DeError> = match &self.0.kind {
            ValueKind::Unit => v.visit_unit(),
            ValueKind::Bool(b) => v.visit_bool(*b),
            ValueKind::Int(i) => v.visit_i64(*i),
            ValueKind::Float(f) => v.visit_f64(*f),
            ValueKind::Str(s) => v.visit_borrowed_str(s),
            ValueKind::Char(c) => v.visit_char(*c),
            ValueKind::Ident(i) => v.visit_borrowed_str(i),
            ValueKind::List(items) | ValueKind::Tuple(_, items) => v.visit_seq(Seq(items.iter())),
            ValueKind::Map(entries) => v.visit_map(MapEntries { iter: entries.iter(), value: None }),
            ValueKind::Struct(_, fields) => v.visit_map(StructFields { iter: fields.iter(), value: None }),
        };
        r.map_err(|e| e.at(span))
    }

    fn deserialize_bool<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match self.0.kind {
            ValueKind::Bool(b) => v.visit_bool(b),
            _ => self.invalid("`true` or `false`"),
        }
    }

    int_method!(deserialize_i8, visit_i8, i8);
    int_method!(deserialize_i16, visit_i16, i16);
    int_method!(deserialize_i32, visit_i32, i32);
    int_method!(deserialize_i64, visit_i64, i64);
    int_method!(deserialize_u8, visit_u8, u8);
    int_method!(deserialize_u16, visit_u16, u16);
    int_method!(deserialize_u32, visit_u32, u32);
    int_method!(deserialize_u64, visit_u64, u64);

    fn deserialize_f32<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        self.deserialize_f64(v)
    }

    fn deserialize_f64<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match self.0.kind {
            ValueKind::Float(f) => v.visit_f64(f),
            ValueKind::Int(i) => v.visit_f64(i as f64),
            _ => self.invalid("a number"),
        }
    }

    fn deserialize_str<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            // A bare word is a string too, so that `--set dataset.version=trainval` reads naturally.
            ValueKind::Str(s) | ValueKind::Ident(s) => v.visit_borrowed_str(s),
            _ => self.invalid("a string"),
        }
    }

    fn deserialize_string<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        self.deserialize_str(v)
    }

    fn deserialize_option<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            ValueKind::Ident(i) if i == "None" => v.visit_none(),
            ValueKind::Tuple(Some(n), items) if n.text == "Some" && items.len() == 1 => {
                v.visit_some(ValueDe(&items[0]))
            }
            _ => v.visit_some(self),
        }
    }

    fn deserialize_unit<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            ValueKind::Unit => v.visit_unit(),
            _ => self.invalid("`()`"),
        }
    }

    fn deserialize_newtype_struct<V: Visitor<'de>>(self, _: &'static str, v: V) -> Result<V::Value, DeError> {
        v.visit_newtype_struct(self)
    }

    fn deserialize_seq<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            ValueKind::List(items) | ValueKind::Tuple(None, items) => {
                v.visit_seq(Seq(items.iter())).map_err(|e| e.at(self.0.span))
            }
            ValueKind::Unit => v.visit_seq(Seq([].iter())),
            _ => self.invalid("a list `[..]`"),
        }
    }

    fn deserialize_tuple<V: Visitor<'de>>(self, _: usize, v: V) -> Result<V::Value, DeError> {
        self.deserialize_seq(v)
    }

    fn deserialize_tuple_struct<V: Visitor<'de>>(self, _: &'static str, _: usize, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            ValueKind::Tuple(_, items) | ValueKind::List(items) => {
                v.visit_seq(Seq(items.iter())).map_err(|e| e.at(self.0.span))
            }
            _ => self.invalid("a tuple `(..)`"),
        }
    }

    fn deserialize_map<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            ValueKind::Map(entries) => {
                v.visit_map(MapEntries { iter: entries.iter(), value: None }).map_err(|e| e.at(self.0.span))
            }
            _ => self.invalid("a map `{..}`"),
        }
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _: &'static str,
        _: &'static [&'static str],
        v: V,
    ) -> Result<V::Value, DeError> {
        match self.0.fields() {
            Some(fields) => {
                v.visit_map(StructFields { iter: fields.iter(), value: None }).map_err(|e| e.at(self.0.span))
            }
            None => self.invalid("a struct `(name: value, ..)`"),
        }
    }

    fn deserialize_enum<V: Visitor<'de>>(
        self,
        _: &'static str,
        _: &'static [&'static str],
        v: V,
    ) -> Result<V::Value, DeError> {
        v.visit_enum(EnumDe(self.0)).map_err(|e| e.at(self.0.span))
    }

    fn deserialize_identifier<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match &self.0.kind {
            ValueKind::Ident(s) | ValueKind::Str(s) => v.visit_borrowed_str(s),
            _ => self.invalid("an identifier"),
        }
    }

    fn deserialize_ignored_any<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        v.visit_unit()
    }

    serde::forward_to_deserialize_any! { i128 u128 char bytes byte_buf unit_struct }
}

struct Seq<'a>(std::slice::Iter<'a, Value>);

impl<'de> de::SeqAccess<'de> for Seq<'de> {
    type Error = DeError;
    fn next_element_seed<T: DeserializeSeed<'de>>(&mut self, seed: T) -> Result<Option<T::Value>, DeError> {
        match self.0.next() {
            Some(v) => seed.deserialize(ValueDe(v)).map(Some).map_err(|e| e.at(v.span)),
            None => Ok(None),
        }
    }
}

struct MapEntries<'a> {
    iter: std::slice::Iter<'a, (Value, Value)>,
    value: Option<&'a Value>,
}

impl<'de> de::MapAccess<'de> for MapEntries<'de> {
    type Error = DeError;
    fn next_key_seed<K: DeserializeSeed<'de>>(&mut self, seed: K) -> Result<Option<K::Value>, DeError> {
        match self.iter.next() {
            Some((k, v)) => {
                self.value = Some(v);
                seed.deserialize(ValueDe(k)).map(Some).map_err(|e| e.at(k.span))
            }
            None => Ok(None),
        }
    }
    fn next_value_seed<T: DeserializeSeed<'de>>(&mut self, seed: T) -> Result<T::Value, DeError> {
        let v = self.value.take().expect("serde asks for a value after its key");
        seed.deserialize(ValueDe(v)).map_err(|e| e.at(v.span))
    }
}

struct StructFields<'a> {
    iter: std::slice::Iter<'a, Field>,
    value: Option<&'a Value>,
}

impl<'de> de::MapAccess<'de> for StructFields<'de> {
    type Error = DeError;
    fn next_key_seed<K: DeserializeSeed<'de>>(&mut self, seed: K) -> Result<Option<K::Value>, DeError> {
        match self.iter.next() {
            Some(f) => {
                self.value = Some(&f.value);
                let key = de::value::BorrowedStrDeserializer::<'de, DeError>::new(f.name.text.as_str());
                seed.deserialize(key).map(Some).map_err(|e| e.at(f.name.span))
            }
            None => Ok(None),
        }
    }
    fn next_value_seed<T: DeserializeSeed<'de>>(&mut self, seed: T) -> Result<T::Value, DeError> {
        let v = self.value.take().expect("serde asks for a value after its key");
        seed.deserialize(ValueDe(v)).map_err(|e| e.at(v.span))
    }
}

struct EnumDe<'a>(&'a Value);

impl<'de> de::EnumAccess<'de> for EnumDe<'de> {
    type Error = DeError;
    type Variant = VariantDe<'de>;
    fn variant_seed<V: DeserializeSeed<'de>>(self, seed: V) -> Result<(V::Value, VariantDe<'de>), DeError> {
        let (name, span, payload): (&str, Span, Option<&Value>) = match &self.0.kind {
            ValueKind::Ident(s) | ValueKind::Str(s) => (s, self.0.span, None),
            ValueKind::Tuple(Some(n), _) | ValueKind::Struct(Some(n), _) => (&n.text, n.span, Some(self.0)),
            _ => {
                return Err(DeError {
                    message: format!("expected a variant name, found {}", self.0.describe()),
                    span: Some(self.0.span),
                })
            }
        };
        let key = de::value::BorrowedStrDeserializer::<'de, DeError>::new(name);
        let v = seed.deserialize(key).map_err(|e| e.at(span))?;
        Ok((v, VariantDe(payload)))
    }
}

struct VariantDe<'a>(Option<&'a Value>);

impl<'de> de::VariantAccess<'de> for VariantDe<'de> {
    type Error = DeError;
    fn unit_variant(self) -> Result<(), DeError> {
        match self.0 {
            None => Ok(()),
            Some(v) => Err(DeError { message: "this variant takes no values".into(), span: Some(v.span) }),
        }
    }
    fn newtype_variant_seed<T: DeserializeSeed<'de>>(self, seed: T) -> Result<T::Value, DeError> {
        match self.0.map(|v| &v.kind) {
            Some(ValueKind::Tuple(_, items)) if items.len() == 1 => seed.deserialize(ValueDe(&items[0])),
            _ => Err(DeError {
                message: "this variant takes one value: `Variant(value)`".into(),
                span: self.0.map(|v| v.span),
            }),
        }
    }
    fn tuple_variant<V: Visitor<'de>>(self, _: usize, v: V) -> Result<V::Value, DeError> {
        match self.0.map(|x| &x.kind) {
            Some(ValueKind::Tuple(_, items)) => v.visit_seq(Seq(items.iter())),
            _ => Err(DeError {
                message: "this variant takes values: `Variant(a, b)`".into(),
                span: self.0.map(|v| v.span),
            }),
        }
    }
    fn struct_variant<V: Visitor<'de>>(self, _: &'static [&'static str], v: V) -> Result<V::Value, DeError> {
        match self.0.and_then(|x| x.fields()) {
            Some(fields) => v.visit_map(StructFields { iter: fields.iter(), value: None }),
            None => Err(DeError {
                message: "this variant takes named fields: `Variant(x: ..)`".into(),
                span: self.0.map(|v| v.span),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::Sources;
    use crate::syntax::parse;
    use serde::Deserialize;

    #[derive(Deserialize, Debug, PartialEq, Default)]
    #[serde(deny_unknown_fields, default)]
    struct P {
        min_depth: f32,
        border: u32,
        name: Option<String>,
        mode: Mode,
        range: (i32, i32),
    }

    #[derive(Deserialize, Debug, PartialEq, Default)]
    enum Mode {
        #[default]
        Near,
        Far,
    }

    fn read(text: &str) -> (Result<P, DeError>, String) {
        let mut s = Sources::default();
        let id = s.add("t", text);
        let v = parse(text, id).unwrap();
        (from_value::<P>(&v), text.to_string())
    }

    #[test]
    fn reads_typed_params_with_defaults() {
        let (p, _) = read("(min_depth: 2, mode: Far, name: \"x\", range: (-1, 1))");
        assert_eq!(
            p.unwrap(),
            P { min_depth: 2.0, border: 0, name: Some("x".into()), mode: Mode::Far, range: (-1, 1) }
        );
    }

    #[test]
    fn errors_carry_the_span_of_the_bad_value() {
        let (p, text) = read("(min_depth: 1.0, border: -4)");
        let e = p.unwrap_err();
        let span = e.span.unwrap();
        assert_eq!(&text[span.start as usize..span.end as usize], "-4");
        assert!(e.message.contains("does not fit in u32"), "{}", e.message);

        let (p, text) = read("(min_dept: 1.0)");
        let e = p.unwrap_err();
        let span = e.span.unwrap();
        assert_eq!(&text[span.start as usize..span.end as usize], "min_dept");
        assert!(e.message.contains("unknown field `min_dept`"), "{}", e.message);
    }

    #[test]
    fn finds_struct_field_names() {
        assert_eq!(struct_fields::<P>(), &["min_depth", "border", "name", "mode", "range"]);
    }
}
