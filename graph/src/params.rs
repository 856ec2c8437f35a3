//! Params (of a stage) and config (of a dataset): checked once, when the pipeline loads, into a
//! [`ParamsValue`] that holds both the typed value the operator or dataset is built from and its
//! canonical text, the form hashed into task keys.

use crate::canonical::to_canonical;
use crate::checks::{ParamProblem, Validate};
use crate::de::{from_value, struct_fields, DeError};
use crate::source::Sources;
use crate::syntax::{parse, Value};
use serde::{de::DeserializeOwned, Serialize};
use std::any::Any;
use std::fmt;
use std::sync::Arc;

/// One param: its name and its default in canonical text.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamInfo {
    pub name: String,
    pub default: String,
}

/// The check of a written params value: why it is not usable.
#[derive(Debug)]
pub enum ParamsError {
    /// The value does not have the params' type (unknown field, a string for a number).
    Type(DeError),
    /// It has the type but is out of range.
    Range(Vec<ParamProblem>),
}

/// Checked params: the typed value and its canonical text (every field, defaults filled, printed
/// by [`crate::canonical`]). Two values are equal when their canonical texts are.
#[derive(Clone)]
pub struct ParamsValue {
    /// What task keys hash and `explain` compares field by field.
    pub canonical: String,
    typed: Arc<dyn Any + Send + Sync>,
}

impl ParamsValue {
    /// Params of type `P` with their canonical text, as [`ParamsSpec::check`] makes them after
    /// validating; made directly (tools, tests), they are not range-checked.
    pub fn new<P: Serialize + Send + Sync + 'static>(params: P) -> Result<ParamsValue, ParamsError> {
        let canonical = to_canonical(&params).map_err(|e| {
            ParamsError::Type(DeError { message: format!("cannot write the params canonically: {e}"), span: None })
        })?;
        Ok(ParamsValue { canonical, typed: Arc::new(params) })
    }

    /// The typed params, when they are a `P` (the type the spec that checked them was made for).
    pub fn get<P: 'static>(&self) -> Option<&P> {
        self.typed.downcast_ref::<P>()
    }
}

impl Default for ParamsValue {
    /// Empty params: the canonical text `()` holding `()`, for nodes of a pipeline that failed to load.
    fn default() -> Self {
        ParamsValue { canonical: "()".into(), typed: Arc::new(()) }
    }
}

impl PartialEq for ParamsValue {
    fn eq(&self, other: &Self) -> bool {
        self.canonical == other.canonical
    }
}

impl fmt::Debug for ParamsValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.canonical)
    }
}

type CheckFn = dyn Fn(Option<&Value>) -> Result<ParamsValue, ParamsError> + Send + Sync;

/// The params of a stage (or the config of a dataset): their names, defaults, and the check that
/// turns the written value into a [`ParamsValue`].
pub struct ParamsSpec {
    pub fields: Vec<ParamInfo>,
    check: Box<CheckFn>,
}

impl ParamsSpec {
    /// The spec of a serde params struct (`deny_unknown_fields`, `default`) and its ranges.
    pub fn of<P: DeserializeOwned + Serialize + Default + Validate + Send + Sync + 'static>() -> ParamsSpec {
        let names = struct_fields::<P>();
        let defaults_text = to_canonical(&P::default()).unwrap_or_default();
        let mut sources = Sources::default();
        let id = sources.add("defaults", defaults_text.clone());
        let defaults = parse(&defaults_text, id).ok();
        let fields = names
            .iter()
            .map(|n| {
                let default = defaults
                    .as_ref()
                    .and_then(|d| d.field(n))
                    .map(|f| sources.slice(f.value.span).to_string())
                    // Every field has a default (`P: Default`); one the canonical text leaves out is
                    // an `Option` that is `None` (`skip_serializing_if`, which keeps the task keys of
                    // params written before the field was): not set, never required.
                    .unwrap_or_else(|| "None".into());
                ParamInfo { name: n.to_string(), default }
            })
            .collect();
        let check = Box::new(|value: Option<&Value>| -> Result<ParamsValue, ParamsError> {
            let params: P = match value {
                Some(v) => from_value(v).map_err(ParamsError::Type)?,
                None => P::default(),
            };
            let problems = params.validate();
            if !problems.is_empty() {
                return Err(ParamsError::Range(problems));
            }
            ParamsValue::new(params)
        });
        ParamsSpec { fields, check }
    }

    /// The checked params (`None`: every default), or the first type error, or every range problem.
    pub fn check(&self, value: Option<&Value>) -> Result<ParamsValue, ParamsError> {
        (self.check)(value)
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.fields.iter().map(|f| f.name.as_str())
    }

    /// `a (default 1.0), b (default "x")` for messages.
    pub fn describe(&self) -> String {
        if self.fields.is_empty() {
            return "none".into();
        }
        self.fields.iter().map(|f| format!("{} (default {})", f.name, f.default)).collect::<Vec<_>>().join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checks::ParamChecks;
    use serde::Deserialize;

    #[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
    #[serde(deny_unknown_fields, default)]
    struct P {
        scale: f32,
        names: Vec<String>,
    }

    impl Default for P {
        fn default() -> Self {
            P { scale: 0.5, names: vec!["a".into()] }
        }
    }

    impl Validate for P {
        fn validate(&self) -> Vec<ParamProblem> {
            ParamChecks::new().within("scale", self.scale as f64, 0.0, 1.0).done()
        }
    }

    fn written(text: &str) -> Value {
        let mut s = Sources::default();
        let id = s.add("t", text);
        parse(text, id).unwrap()
    }

    #[test]
    fn check_gives_the_typed_value_and_its_canonical_text() {
        let spec = ParamsSpec::of::<P>();
        let v = spec.check(Some(&written("(scale: 1)"))).unwrap();
        assert_eq!(v.canonical, r#"(scale:1.0,names:["a"])"#);
        assert_eq!(v.get::<P>(), Some(&P { scale: 1.0, names: vec!["a".into()] }));
        assert_eq!(v.get::<u32>(), None);
        // Written or defaulted, the same params are the same value.
        assert_eq!(spec.check(None).unwrap(), spec.check(Some(&written("(scale: 0.5, names: [\"a\"])"))).unwrap());
        assert!(matches!(spec.check(Some(&written("(scale: 2)"))), Err(ParamsError::Range(_))));
        assert!(matches!(spec.check(Some(&written("(scale: \"x\")"))), Err(ParamsError::Type(_))));
    }

    #[test]
    fn defaults_are_shown_in_canonical_text() {
        let spec = ParamsSpec::of::<P>();
        assert_eq!(spec.describe(), r#"scale (default 0.5), names (default ["a"])"#);
    }
}
