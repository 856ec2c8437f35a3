//! A RON parser that keeps a span on every value.
//!
//! The `ron` crate reports only the first syntax error and forgets where values were, but a
//! pipeline check must point at *every* problem: an unknown param three stages down, a type
//! mismatch on one input. So pipeline files are parsed here into a [`Value`] tree with spans,
//! and typed params are then read from that tree through serde (see [`crate::de`]).
//!
//! Accepted: `Name(field: v, ...)` and `(field: v, ...)` structs, `Name(a, b)` and `(a, b)`
//! tuples, `[a, b]` lists, `{k: v}` maps, strings with escapes and raw strings `r"..."`/`r#"..."#`,
//! chars, integers, floats, `true`/`false`, bare identifiers (unit enum variants, `None`),
//! `//` and `/* */` comments, trailing commas.

use crate::diag::Diagnostic;
use crate::source::{SourceId, Span};

#[derive(Clone, Debug, PartialEq)]
pub struct Value {
    pub kind: ValueKind,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub enum ValueKind {
    Unit,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Char(char),
    /// A bare identifier: a unit enum variant such as `None`, or a dimension name.
    Ident(String),
    List(Vec<Value>),
    Map(Vec<(Value, Value)>),
    /// `Name(a, b)` or `(a, b)`.
    Tuple(Option<Name>, Vec<Value>),
    /// `Name(x: 1)` or `(x: 1)`.
    Struct(Option<Name>, Vec<Field>),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Name {
    pub text: String,
    pub span: Span,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Field {
    pub name: Name,
    pub value: Value,
}

impl Value {
    /// A short description for messages: "a string", "a struct `Foo(..)`".
    pub fn describe(&self) -> String {
        match &self.kind {
            ValueKind::Unit => "`()`".into(),
            ValueKind::Bool(_) => "a boolean".into(),
            ValueKind::Int(_) => "an integer".into(),
            ValueKind::Float(_) => "a float".into(),
            ValueKind::Str(_) => "a string".into(),
            ValueKind::Char(_) => "a char".into(),
            ValueKind::Ident(i) => format!("the identifier `{i}`"),
            ValueKind::List(_) => "a list".into(),
            ValueKind::Map(_) => "a map".into(),
            ValueKind::Tuple(Some(n), _) => format!("`{}(..)`", n.text),
            ValueKind::Tuple(None, _) => "a tuple".into(),
            ValueKind::Struct(Some(n), _) => format!("a struct `{}(..)`", n.text),
            ValueKind::Struct(None, _) => "a struct".into(),
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match &self.kind {
            ValueKind::Str(s) => Some(s),
            _ => None,
        }
    }

    /// The fields of a struct value (named or not); an empty `()` counts as a struct with no fields.
    pub fn fields(&self) -> Option<&[Field]> {
        match &self.kind {
            ValueKind::Struct(_, f) => Some(f),
            ValueKind::Unit | ValueKind::Tuple(_, _) if self.tuple_items().is_some_and(|i| i.is_empty()) => Some(&[]),
            _ => None,
        }
    }

    pub fn fields_mut(&mut self) -> Option<&mut Vec<Field>> {
        if matches!(&self.kind, ValueKind::Unit) {
            self.kind = ValueKind::Struct(None, Vec::new());
        }
        if let ValueKind::Tuple(name, items) = &self.kind {
            if items.is_empty() {
                self.kind = ValueKind::Struct(name.clone(), Vec::new());
            }
        }
        match &mut self.kind {
            ValueKind::Struct(_, f) => Some(f),
            _ => None,
        }
    }

    pub fn field(&self, name: &str) -> Option<&Field> {
        self.fields()?.iter().find(|f| f.name.text == name)
    }

    fn tuple_items(&self) -> Option<&[Value]> {
        match &self.kind {
            ValueKind::Unit => Some(&[]),
            ValueKind::Tuple(_, items) => Some(items),
            _ => None,
        }
    }

    /// The `Name` of `Name(..)`, if any.
    pub fn type_name(&self) -> Option<&Name> {
        match &self.kind {
            ValueKind::Tuple(n, _) | ValueKind::Struct(n, _) => n.as_ref(),
            _ => None,
        }
    }
}

/// How deep values may nest (each `(..)`, `[..]` and `{..}` is one level). The parser recurses
/// once per level, and so do serde and `Drop` on the tree, so an unbounded depth (a file of
/// 20,000 `[`) overflows the stack. A pipeline needs about 6 levels (`Pipeline(stages: {"s":
/// Kind(inputs: {"p": Window(..)}))`), a params value a few more.
pub const MAX_NESTING: usize = 64;

/// Why [`parse_value`] failed.
#[derive(Clone, Debug, PartialEq)]
pub struct SyntaxError {
    pub diagnostic: Diagnostic,
    /// The text nests deeper than [`MAX_NESTING`]: it was meant as a value, not plain text.
    pub too_deep: bool,
}

/// Parses one RON value filling the whole text.
pub fn parse(text: &str, source: SourceId) -> Result<Value, Diagnostic> {
    parse_value(text, source).map_err(|e| e.diagnostic)
}

/// [`parse`], saying whether it failed on the nesting limit.
pub fn parse_value(text: &str, source: SourceId) -> Result<Value, SyntaxError> {
    let mut p = Parser { text, bytes: text.as_bytes(), pos: 0, source, depth: 0, too_deep: false };
    p.parse_all().map_err(|diagnostic| SyntaxError { diagnostic, too_deep: p.too_deep })
}

struct Parser<'a> {
    text: &'a str,
    bytes: &'a [u8],
    pos: usize,
    source: SourceId,
    /// Containers open around the current position.
    depth: usize,
    too_deep: bool,
}

impl<'a> Parser<'a> {
    /// The one value that fills the text.
    fn parse_all(&mut self) -> Result<Value, Diagnostic> {
        self.skip_trivia()?;
        if self.pos >= self.bytes.len() {
            return Err(Diagnostic::error("the file is empty: expected a pipeline `Pipeline(..)`", self.span(0, 0)));
        }
        let v = self.value()?;
        self.skip_trivia()?;
        if self.pos < self.bytes.len() {
            return Err(Diagnostic::error(
                "unexpected text after the end of the value",
                self.span(self.pos, self.pos + 1),
            )
            .with_label("expected nothing more here"));
        }
        Ok(v)
    }

    fn span(&self, start: usize, end: usize) -> Span {
        Span::new(self.source, start, end)
    }

    fn err<T>(&self, message: impl Into<String>, start: usize, end: usize) -> Result<T, Diagnostic> {
        Err(Diagnostic::error(message, self.span(start, end)))
    }

    fn peek(&self) -> Option<u8> {
        self.bytes.get(self.pos).copied()
    }

    fn skip_trivia(&mut self) -> Result<(), Diagnostic> {
        loop {
            match self.peek() {
                Some(b' ' | b'\t' | b'\n' | b'\r') => self.pos += 1,
                Some(b'/') if self.bytes.get(self.pos + 1) == Some(&b'/') => {
                    while let Some(c) = self.peek() {
                        if c == b'\n' {
                            break;
                        }
                        self.pos += 1;
                    }
                }
                Some(b'/') if self.bytes.get(self.pos + 1) == Some(&b'*') => {
                    let start = self.pos;
                    self.pos += 2;
                    let mut depth = 1;
                    while depth > 0 {
                        if self.pos >= self.bytes.len() {
                            return self.err("unterminated block comment", start, start + 2);
                        }
                        if self.bytes[self.pos..].starts_with(b"*/") {
                            depth -= 1;
                            self.pos += 2;
                        } else if self.bytes[self.pos..].starts_with(b"/*") {
                            depth += 1;
                            self.pos += 2;
                        } else {
                            self.pos += 1;
                        }
                    }
                }
                _ => return Ok(()),
            }
        }
    }

    fn expect(&mut self, c: u8, what: &str) -> Result<(), Diagnostic> {
        self.skip_trivia()?;
        if self.peek() == Some(c) {
            self.pos += 1;
            Ok(())
        } else {
            self.unexpected(what)
        }
    }

    fn unexpected<T>(&self, expected: &str) -> Result<T, Diagnostic> {
        match self.text[self.pos..].chars().next() {
            None => self.err(format!("unexpected end of file: expected {expected}"), self.pos, self.pos),
            Some(c) => Err(Diagnostic::error(
                format!("unexpected `{c}`: expected {expected}"),
                self.span(self.pos, self.pos + c.len_utf8()),
            )
            .with_label(format!("expected {expected}"))),
        }
    }

    /// Runs `f`, which parses a container starting at `start`, one level deeper; refuses to go
    /// beyond [`MAX_NESTING`].
    fn nested<T>(&mut self, start: usize, f: impl FnOnce(&mut Self) -> Result<T, Diagnostic>) -> Result<T, Diagnostic> {
        if self.depth >= MAX_NESTING {
            self.too_deep = true;
            return Err(Diagnostic::error(
                format!("values nest deeper than {MAX_NESTING} levels here"),
                self.span(start, start + 1),
            )
            .with_label(format!("level {}", MAX_NESTING + 1))
            .with_note("a pipeline needs a handful of levels; look for unbalanced or runaway brackets"));
        }
        self.depth += 1;
        let r = f(self);
        self.depth -= 1;
        r
    }

    fn value(&mut self) -> Result<Value, Diagnostic> {
        self.skip_trivia()?;
        let start = self.pos;
        let kind = match self.peek() {
            None => return self.unexpected("a value"),
            Some(b'(') => return self.nested(start, |p| p.parens(None, start)),
            Some(b'[') => self.nested(start, |p| p.list())?,
            Some(b'{') => self.nested(start, |p| p.map())?,
            Some(b'"') => ValueKind::Str(self.string()?),
            Some(b'\'') => ValueKind::Char(self.char_lit()?),
            Some(b'r') if matches!(self.bytes.get(self.pos + 1), Some(b'"' | b'#')) => {
                ValueKind::Str(self.raw_string()?)
            }
            Some(c) if c == b'-' || c == b'+' || c == b'.' || c.is_ascii_digit() => self.number()?,
            Some(c) if c == b'_' || c.is_ascii_alphabetic() => {
                let name = self.ident();
                let name_span = self.span(start, self.pos);
                let after_name = self.pos;
                self.skip_trivia()?;
                if self.peek() == Some(b'(') {
                    return self.nested(start, |p| p.parens(Some(Name { text: name, span: name_span }), start));
                }
                self.pos = after_name;
                match name.as_str() {
                    "true" => ValueKind::Bool(true),
                    "false" => ValueKind::Bool(false),
                    "inf" => ValueKind::Float(f64::INFINITY),
                    "NaN" => ValueKind::Float(f64::NAN),
                    _ => ValueKind::Ident(name),
                }
            }
            Some(_) => return self.unexpected("a value"),
        };
        Ok(Value { kind, span: self.span(start, self.pos) })
    }

    fn ident(&mut self) -> String {
        let start = self.pos;
        while let Some(c) = self.peek() {
            if c == b'_' || c.is_ascii_alphanumeric() {
                self.pos += 1;
            } else {
                break;
            }
        }
        self.text[start..self.pos].to_string()
    }

    /// `( ... )`, optionally after a name: a struct if the first entry is `ident:`, else a tuple.
    fn parens(&mut self, name: Option<Name>, start: usize) -> Result<Value, Diagnostic> {
        self.expect(b'(', "`(`")?;
        self.skip_trivia()?;
        if self.peek() == Some(b')') {
            self.pos += 1;
            let kind = match name {
                Some(n) => ValueKind::Tuple(Some(n), Vec::new()),
                None => ValueKind::Unit,
            };
            return Ok(Value { kind, span: self.span(start, self.pos) });
        }
        if self.at_field_name() {
            let mut fields: Vec<Field> = Vec::new();
            loop {
                self.skip_trivia()?;
                if self.peek() == Some(b')') {
                    self.pos += 1;
                    break;
                }
                let fstart = self.pos;
                if !self.peek().is_some_and(|c| c == b'_' || c.is_ascii_alphabetic()) {
                    return self.unexpected("a field name or `)`");
                }
                let fname = self.ident();
                let fname = Name { text: fname, span: self.span(fstart, self.pos) };
                if fields.iter().any(|f| f.name.text == fname.text) {
                    return Err(Diagnostic::error(format!("field `{}` is given twice", fname.text), fname.span)
                        .with_label("second time here"));
                }
                self.expect(b':', "`:` after the field name")?;
                let value = self.value()?;
                fields.push(Field { name: fname, value });
                if !self.comma_or_close(b')')? {
                    break;
                }
            }
            Ok(Value { kind: ValueKind::Struct(name, fields), span: self.span(start, self.pos) })
        } else {
            let mut items = Vec::new();
            loop {
                self.skip_trivia()?;
                if self.peek() == Some(b')') {
                    self.pos += 1;
                    break;
                }
                items.push(self.value()?);
                if !self.comma_or_close(b')')? {
                    break;
                }
            }
            Ok(Value { kind: ValueKind::Tuple(name, items), span: self.span(start, self.pos) })
        }
    }

    /// After a list entry: `,` (returns true: more may follow) or the closing bracket (false).
    fn comma_or_close(&mut self, close: u8) -> Result<bool, Diagnostic> {
        self.skip_trivia()?;
        match self.peek() {
            Some(b',') => {
                self.pos += 1;
                Ok(true)
            }
            Some(c) if c == close => {
                self.pos += 1;
                Ok(false)
            }
            _ => self.unexpected(&format!("`,` or `{}`", close as char)),
        }
    }

    fn at_field_name(&mut self) -> bool {
        let save = self.pos;
        let ok = self.peek().is_some_and(|c| c == b'_' || c.is_ascii_alphabetic()) && {
            self.ident();
            let _ = self.skip_trivia();
            self.peek() == Some(b':')
        };
        self.pos = save;
        ok
    }

    fn list(&mut self) -> Result<ValueKind, Diagnostic> {
        self.expect(b'[', "`[`")?;
        let mut items = Vec::new();
        loop {
            self.skip_trivia()?;
            if self.peek() == Some(b']') {
                self.pos += 1;
                break;
            }
            items.push(self.value()?);
            if !self.comma_or_close(b']')? {
                break;
            }
        }
        Ok(ValueKind::List(items))
    }

    fn map(&mut self) -> Result<ValueKind, Diagnostic> {
        self.expect(b'{', "`{`")?;
        let mut entries: Vec<(Value, Value)> = Vec::new();
        loop {
            self.skip_trivia()?;
            if self.peek() == Some(b'}') {
                self.pos += 1;
                break;
            }
            let key = self.value()?;
            if entries.iter().any(|(k, _)| k.kind == key.kind) {
                return Err(
                    Diagnostic::error("this key is given twice in the map", key.span).with_label("second time here")
                );
            }
            self.expect(b':', "`:` after the map key")?;
            let value = self.value()?;
            entries.push((key, value));
            if !self.comma_or_close(b'}')? {
                break;
            }
        }
        Ok(ValueKind::Map(entries))
    }

    fn string(&mut self) -> Result<String, Diagnostic> {
        let start = self.pos;
        self.pos += 1;
        let mut out = String::new();
        loop {
            let Some(c) = self.text[self.pos..].chars().next() else {
                return self.err("unterminated string", start, start + 1);
            };
            self.pos += c.len_utf8();
            match c {
                '"' => return Ok(out),
                '\\' => out.push(self.escape()?),
                c => out.push(c),
            }
        }
    }

    fn escape(&mut self) -> Result<char, Diagnostic> {
        let at = self.pos - 1;
        let Some(c) = self.peek() else {
            return self.err("unterminated escape", at, at + 1);
        };
        self.pos += 1;
        Ok(match c {
            b'n' => '\n',
            b't' => '\t',
            b'r' => '\r',
            b'0' => '\0',
            b'\\' => '\\',
            b'"' => '"',
            b'\'' => '\'',
            b'u' => {
                let open = self.pos;
                if self.peek() != Some(b'{') {
                    return self.err("expected `{` after `\\u`", at, self.pos);
                }
                let Some(close) = self.text[open..].find('}') else {
                    return self.err("unterminated `\\u{..}` escape", at, self.pos);
                };
                let hex = &self.text[open + 1..open + close];
                self.pos = open + close + 1;
                match u32::from_str_radix(hex, 16).ok().and_then(char::from_u32) {
                    Some(c) => c,
                    None => return self.err(format!("`\\u{{{hex}}}` is not a character"), at, self.pos),
                }
            }
            other => return self.err(format!("unknown escape `\\{}`", other as char), at, self.pos),
        })
    }

    fn raw_string(&mut self) -> Result<String, Diagnostic> {
        let start = self.pos;
        self.pos += 1;
        let mut hashes = 0;
        while self.peek() == Some(b'#') {
            hashes += 1;
            self.pos += 1;
        }
        if self.peek() != Some(b'"') {
            return self.err("expected `\"` to open the raw string", start, self.pos);
        }
        self.pos += 1;
        let close = format!("\"{}", "#".repeat(hashes));
        match self.text[self.pos..].find(&close) {
            Some(i) => {
                let s = self.text[self.pos..self.pos + i].to_string();
                self.pos += i + close.len();
                Ok(s)
            }
            None => self.err("unterminated raw string", start, start + 1),
        }
    }

    fn char_lit(&mut self) -> Result<char, Diagnostic> {
        let start = self.pos;
        self.pos += 1;
        let Some(c) = self.text[self.pos..].chars().next() else {
            return self.err("unterminated char", start, start + 1);
        };
        self.pos += c.len_utf8();
        let c = if c == '\\' { self.escape()? } else { c };
        if self.peek() != Some(b'\'') {
            return self.err("unterminated char: expected `'`", start, self.pos);
        }
        self.pos += 1;
        Ok(c)
    }

    fn number(&mut self) -> Result<ValueKind, Diagnostic> {
        let start = self.pos;
        if matches!(self.peek(), Some(b'-' | b'+')) {
            self.pos += 1;
        }
        if self.text[self.pos..].starts_with("inf") {
            self.pos += 3;
            let neg = self.bytes[start] == b'-';
            return Ok(ValueKind::Float(if neg { f64::NEG_INFINITY } else { f64::INFINITY }));
        }
        let mut is_float = false;
        while let Some(c) = self.peek() {
            match c {
                b'0'..=b'9' | b'_' => self.pos += 1,
                b'.' | b'e' | b'E' => {
                    is_float = true;
                    self.pos += 1;
                    if matches!(c, b'e' | b'E') && matches!(self.peek(), Some(b'-' | b'+')) {
                        self.pos += 1;
                    }
                }
                _ => break,
            }
        }
        let text: String = self.text[start..self.pos].chars().filter(|c| *c != '_').collect();
        let bad = |p: &Self| p.err::<ValueKind>(format!("`{}` is not a number", &p.text[start..p.pos]), start, p.pos);
        if is_float {
            match text.parse::<f64>() {
                Ok(f) => Ok(ValueKind::Float(f)),
                Err(_) => bad(self),
            }
        } else {
            match text.parse::<i64>() {
                Ok(i) => Ok(ValueKind::Int(i)),
                Err(_) => bad(self),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::Sources;

    fn parse_str(text: &str) -> Result<Value, Diagnostic> {
        let mut s = Sources::default();
        let id = s.add("t.ron", text);
        parse(text, id)
    }

    #[test]
    fn parses_the_shapes_a_pipeline_uses() {
        let v = parse_str(
            r#"Pipeline( // a comment
                name: "x", /* block */ n: -3, f: 1.5e2, b: true, none: None,
                l: [1, 2,], m: {"a": Window("s.p", frame, -1, 1)}, u: (), raw: r"c:\d",
            )"#,
        )
        .unwrap();
        assert_eq!(v.type_name().unwrap().text, "Pipeline");
        let f = |n: &str| v.field(n).unwrap().value.kind.clone();
        assert_eq!(f("name"), ValueKind::Str("x".into()));
        assert_eq!(f("n"), ValueKind::Int(-3));
        assert_eq!(f("f"), ValueKind::Float(150.0));
        assert_eq!(f("b"), ValueKind::Bool(true));
        assert_eq!(f("none"), ValueKind::Ident("None".into()));
        assert_eq!(f("raw"), ValueKind::Str("c:\\d".into()));
        let ValueKind::Map(m) = f("m") else { panic!() };
        let ValueKind::Tuple(Some(name), items) = &m[0].1.kind else { panic!() };
        assert_eq!(name.text, "Window");
        assert_eq!(items.len(), 4);
        assert_eq!(items[1].kind, ValueKind::Ident("frame".into()));
        assert_eq!(items[2].kind, ValueKind::Int(-1));
    }

    #[test]
    fn spans_point_at_the_value() {
        let text = "(a: \"hello\")";
        let v = parse_str(text).unwrap();
        let span = v.field("a").unwrap().value.span;
        assert_eq!(&text[span.start as usize..span.end as usize], "\"hello\"");
    }

    #[test]
    fn syntax_errors_say_what_was_expected_and_where() {
        let e = parse_str("(a: 1 b: 2)").unwrap_err();
        assert!(e.message.contains("expected `,` or `)`"), "{}", e.message);
        assert_eq!(e.span.unwrap().start, 6);
        let e = parse_str("(a: \"open)").unwrap_err();
        assert!(e.message.contains("unterminated string"));
        let e = parse_str("(a: 1, a: 2)").unwrap_err();
        assert!(e.message.contains("given twice"));
        let e = parse_str("").unwrap_err();
        assert!(e.message.contains("empty"));
    }
}
