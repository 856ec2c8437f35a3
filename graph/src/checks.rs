//! Range checks of params that their types cannot express, worded alike everywhere.

/// A value its type accepts but that is out of range or inconsistent with another param (a
/// negative size, NaN, a minimum above its maximum): found after deserializing, so that `check`
/// refuses what every task would refuse (or would run out of memory on).
#[derive(Clone, Debug, PartialEq)]
pub struct ParamProblem {
    /// The field at fault, as written in the pipeline file.
    pub field: &'static str,
    /// For a list field, the element at fault.
    pub index: Option<usize>,
    /// The other field of a relation (`min` must be below `max`): when only that one
    /// was written, the diagnostic points there.
    pub other: Option<&'static str>,
    /// What is wrong, as a predicate of the field: "must be in [0, 1], found NaN".
    pub message: String,
}

impl ParamProblem {
    pub fn new(field: &'static str, message: impl Into<String>) -> ParamProblem {
        ParamProblem { field, index: None, other: None, message: message.into() }
    }
}

/// Range checks of params (or dataset config) that their types cannot express.
///
/// [`crate::ParamsSpec::of`] requires it, so that every params struct says what it accepts. The default
/// finds nothing; that is right only for params without ranges (no fields, flags, free names).
pub trait Validate {
    /// Every problem, each naming its field; empty when the params are usable.
    fn validate(&self) -> Vec<ParamProblem> {
        Vec::new()
    }
}

/// Collects [`ParamProblem`]s with the checks params need most, worded alike everywhere.
#[derive(Default, Debug)]
pub struct ParamChecks(Vec<ParamProblem>);

impl ParamChecks {
    pub fn new() -> ParamChecks {
        ParamChecks::default()
    }

    /// A problem when `ok` is false.
    pub fn check(&mut self, ok: bool, field: &'static str, message: impl FnOnce() -> String) -> &mut Self {
        if !ok {
            self.0.push(ParamProblem::new(field, message()));
        }
        self
    }

    /// A finite number in `lo..=hi`.
    pub fn within(&mut self, field: &'static str, value: f64, lo: f64, hi: f64) -> &mut Self {
        self.check(value.is_finite() && (lo..=hi).contains(&value), field, || {
            format!("must be a number in [{lo}, {hi}], found {value}")
        })
    }

    /// A finite number above `lo` (strictly) and at most `hi`.
    pub fn above(&mut self, field: &'static str, value: f64, lo: f64, hi: f64) -> &mut Self {
        self.check(value.is_finite() && value > lo && value <= hi, field, || {
            format!("must be a number in ({lo}, {hi}], found {value}")
        })
    }

    /// A whole number in `lo..=hi`.
    pub fn count(&mut self, field: &'static str, value: u64, lo: u64, hi: u64) -> &mut Self {
        self.check((lo..=hi).contains(&value), field, || format!("must be in {lo}..={hi}, found {value}"))
    }

    /// `low` (field `field`) strictly below `high` (field `other`).
    pub fn below(&mut self, field: &'static str, low: f64, other: &'static str, high: f64) -> &mut Self {
        if low >= high && low.is_finite() && high.is_finite() {
            self.0.push(ParamProblem {
                field,
                index: None,
                other: Some(other),
                message: format!("must be below `{other}` ({high}), found {low}"),
            });
        }
        self
    }

    /// Names that become one path component each (a folder or file name in an output layout):
    /// at least one, no repeats, none empty, `.`, `..`, or holding `/`, `\` or NUL.
    pub fn path_names(&mut self, field: &'static str, names: &[String]) -> &mut Self {
        if names.is_empty() {
            self.0.push(ParamProblem::new(field, "must name at least one"));
        }
        for (i, name) in names.iter().enumerate() {
            let problem = match path_component_problem(name) {
                Some(p) => Some(p),
                None if names[..i].contains(name) => Some(format!("names `{name}` twice")),
                None => None,
            };
            if let Some(message) = problem {
                self.0.push(ParamProblem { field, index: Some(i), other: None, message });
            }
        }
        self
    }

    /// One name that becomes one path component (see [`ParamChecks::path_names`]).
    pub fn path_name(&mut self, field: &'static str, name: &str) -> &mut Self {
        if let Some(message) = path_component_problem(name) {
            self.0.push(ParamProblem::new(field, message));
        }
        self
    }

    pub fn push(&mut self, problem: ParamProblem) -> &mut Self {
        self.0.push(problem);
        self
    }

    pub fn done(&mut self) -> Vec<ParamProblem> {
        std::mem::take(&mut self.0)
    }
}

/// Why `name` cannot be one path component, if it cannot: joined to a folder, it must name an
/// entry of that folder and nothing outside it.
pub fn path_component_problem(name: &str) -> Option<String> {
    if name.is_empty() {
        return Some("must not be empty (it becomes a file or folder name)".into());
    }
    if name == "." || name == ".." {
        return Some(format!("must not be `{name}` (it becomes a file or folder name)"));
    }
    if let Some(c) = name.chars().find(|c| matches!(c, '/' | '\\') || c.is_control()) {
        return Some(format!(
            "must be one file or folder name, without `{}`, found `{}`",
            c.escape_default(),
            name.escape_default()
        ));
    }
    None
}
