//! Pipeline file -> [`Pipeline`], reporting every problem at once.
//!
//! Order of work: parse the RON text, apply `--set` overrides to the tree, then check the
//! dataset, each stage (kind, grain, params, inputs), the wiring (ports, types, selectors,
//! grains), cycles and exports. Each check adds diagnostics and goes on, so one run of `check`
//! shows everything that is wrong.

use crate::catalog::Catalog;
use crate::checks::ParamProblem;
use crate::diag::{did_you_mean, render_all, Diagnostic};
use crate::params::{ParamsError, ParamsSpec, ParamsValue};
use crate::pipeline::*;
use crate::source::{SourceId, Sources, Span};
use crate::syntax::{self, Field, Name, Value, ValueKind};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// A pipeline that failed to load, with everything needed to show why.
#[derive(Debug)]
pub struct LoadError {
    pub sources: Sources,
    pub diagnostics: Vec<Diagnostic>,
}

impl LoadError {
    pub fn render(&self) -> String {
        render_all(&self.diagnostics, &self.sources)
    }
}

impl std::fmt::Display for LoadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.render())
    }
}

impl std::error::Error for LoadError {}

/// Reads, overrides and checks a pipeline file.
///
/// `overrides` are `target.field=value` strings (`stage.param=2`, `dataset.root=/data`);
/// relative paths given through them resolve against `cwd`.
pub fn load_file(path: &Path, overrides: &[String], cwd: &Path, catalog: &dyn Catalog) -> Result<Pipeline, LoadError> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) => {
            return Err(LoadError {
                sources: Sources::default(),
                diagnostics: vec![Diagnostic::without_span(format!(
                    "cannot read pipeline file {}: {e}",
                    path.display()
                ))],
            })
        }
    };
    // A byte-order mark some editors write is not part of the pipeline.
    let bytes = bytes.strip_prefix("\u{feff}".as_bytes()).map(<[u8]>::to_vec).unwrap_or(bytes);
    let text = match String::from_utf8(bytes) {
        Ok(t) => t,
        Err(e) => return Err(not_utf8(&path.display().to_string(), e)),
    };
    let base = path
        .parent()
        .map(|p| if p.as_os_str().is_empty() { cwd.to_path_buf() } else { cwd.join(p) })
        .unwrap_or_else(|| cwd.to_path_buf());
    load_str(&path.display().to_string(), &text, path, &base, overrides, cwd, catalog)
}

/// A pipeline file that is not UTF-8, shown at its first invalid byte. The text is kept with
/// that byte and what follows replaced (U+FFFD), so that the valid part before it keeps its byte
/// offsets and the diagnostic can show the line and column.
fn not_utf8(name: &str, e: std::string::FromUtf8Error) -> LoadError {
    let at = e.utf8_error().valid_up_to();
    let byte = e.as_bytes()[at];
    let mut sources = Sources::default();
    let id = sources.add(name, String::from_utf8_lossy(e.as_bytes()).into_owned());
    let d = Diagnostic::error(
        format!("the pipeline file is not valid UTF-8: byte {at} (0x{byte:02X}) is not part of a valid character"),
        Span::new(id, at, at + char::REPLACEMENT_CHARACTER.len_utf8()),
    )
    .with_label("not UTF-8")
    .with_note("pipeline files are UTF-8 text; re-save the file as UTF-8");
    LoadError { sources, diagnostics: vec![d] }
}

/// Like [`load_file`] for text already in memory; `base` is where relative paths in it resolve.
pub fn load_str(
    name: &str,
    text: &str,
    path: &Path,
    base: &Path,
    overrides: &[String],
    cwd: &Path,
    catalog: &dyn Catalog,
) -> Result<Pipeline, LoadError> {
    let mut sources = Sources::default();
    let file = sources.add(name, text);
    let mut root = match syntax::parse(text, file) {
        Ok(v) => v,
        Err(d) => return Err(LoadError { sources, diagnostics: vec![d] }),
    };
    let mut checker = Checker { catalog, diags: Vec::new(), bases: HashMap::new() };
    checker.bases.insert(file, base.to_path_buf());
    apply_overrides(&mut root, overrides, &mut sources, cwd, &mut checker);
    let default_name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "pipeline".into());
    let pipeline = checker.pipeline(&root, default_name, path.to_path_buf());
    match pipeline {
        Some(p) if checker.diags.is_empty() => Ok(p),
        _ => {
            if checker.diags.is_empty() {
                checker.diags.push(Diagnostic::without_span("the pipeline is not valid"));
            }
            Err(LoadError { sources, diagnostics: checker.diags })
        }
    }
}

/// Carries the fields of the pipeline's dataset that the replacing kind also takes and the
/// replacement does not set, so that `--set 'dataset=Py123d(root: ..)'` on a pipeline written for
/// `NuScenes(.., frames: Camera)` keeps its clock: a field like `frames` belongs to the pipeline
/// (video_12hz.ron is about camera rounds), not to the data. Paths are not carried: a root of one
/// kind is not a root of another.
fn keep_shared_fields(old: &Value, new: &mut Value, catalog: &dyn Catalog) {
    let Some(schema) = new.type_name().and_then(|k| catalog.dataset(&k.text)) else { return };
    let (Some(old_fields), Some(new_fields)) = (old.fields(), new.fields_mut()) else { return };
    for f in old_fields {
        let name = f.name.text.as_str();
        let taken = schema.config.fields.iter().any(|p| p.name == name);
        if taken && !schema.path_fields.contains(&name) && !new_fields.iter().any(|n| n.name.text == name) {
            new_fields.push(f.clone());
        }
    }
}

/// Applies `--set target.field=value` arguments to the parsed tree.
fn apply_overrides(root: &mut Value, overrides: &[String], sources: &mut Sources, cwd: &Path, checker: &mut Checker) {
    // A whole new dataset first, so that `dataset.field=..` given with it applies to it.
    let whole = |arg: &&String| arg.starts_with("dataset=");
    for arg in overrides.iter().filter(whole).chain(overrides.iter().filter(|a| !whole(a))) {
        let id = sources.add("--set", arg.clone());
        checker.bases.insert(id, cwd.to_path_buf());
        let whole = Span::new(id, 0, arg.len());
        let Some(eq) = arg.find('=') else {
            checker
                .diags
                .push(Diagnostic::error("a --set takes `target.param=value`", whole).with_label("no `=` here"));
            continue;
        };
        let path_span = Span::new(id, 0, eq);
        if &arg[..eq] == "dataset" {
            // The whole dataset: the same pipeline on another dataset kind (`Dgp(root: ..)`).
            match parse_override_value(arg, eq + 1, id) {
                Ok(mut value) if matches!(value.kind, ValueKind::Struct(Some(_), _)) => {
                    match root.fields_mut().and_then(|f| f.iter_mut().find(|f| f.name.text == "dataset")) {
                        Some(dataset) => {
                            keep_shared_fields(&dataset.value, &mut value, checker.catalog);
                            dataset.value = value
                        }
                        None => {
                            checker.diags.push(Diagnostic::error("the pipeline has no `dataset` to replace", path_span))
                        }
                    }
                }
                Ok(value) => {
                    // The example is the catalog's first kind: the graph names no dataset itself.
                    let kinds = checker.catalog.dataset_kinds();
                    let example = kinds.first().copied().unwrap_or("Kind");
                    let message = format!(
                        "--set dataset=.. takes a dataset, like `{example}(root: \"/data/..\")` (kinds: {})",
                        kinds.join(", ")
                    );
                    checker
                        .diags
                        .push(Diagnostic::error(message, value.span).with_label("not a dataset kind with its fields"))
                }
                Err(d) => checker.diags.push(d),
            }
            continue;
        }
        let parts: Vec<&str> = arg[..eq].split('.').collect();
        if parts.len() != 2 || parts.iter().any(|p| p.is_empty()) {
            checker.diags.push(
                Diagnostic::error("a --set names `stage.param`, `dataset.field` or `dataset`", path_span)
                    .with_label("expected two names joined by `.`"),
            );
            continue;
        }
        let value = match parse_override_value(arg, eq + 1, id) {
            Ok(v) => v,
            Err(d) => {
                checker.diags.push(d);
                continue;
            }
        };
        let field =
            Field { name: Name { text: parts[1].to_string(), span: Span::new(id, parts[0].len() + 1, eq) }, value };
        let target_span = Span::new(id, 0, parts[0].len());
        let target: Option<&mut Value> = if parts[0] == "dataset" {
            root.fields_mut().and_then(|f| f.iter_mut().find(|f| f.name.text == "dataset")).map(|f| &mut f.value)
        } else {
            let stages = root.fields_mut().and_then(|f| f.iter_mut().find(|f| f.name.text == "stages"));
            match stages.map(|f| &mut f.value.kind) {
                Some(ValueKind::Map(entries)) => {
                    let names: Vec<String> = entries.iter().filter_map(|(k, _)| k.as_str().map(String::from)).collect();
                    match entries.iter_mut().find(|(k, _)| k.as_str() == Some(parts[0])) {
                        Some((_, stage)) => params_of(stage),
                        None => {
                            let mut d = Diagnostic::error(
                                format!("--set names stage `{}`, which the pipeline does not have", parts[0]),
                                target_span,
                            )
                            .with_label("no such stage");
                            d = d.with_note(format!("stages: {}", names.join(", ")));
                            checker.diags.push(d);
                            continue;
                        }
                    }
                }
                _ => None,
            }
        };
        match target.and_then(|t| t.fields_mut()) {
            Some(fields) => match fields.iter_mut().find(|f| f.name.text == parts[1]) {
                Some(existing) => existing.value = field.value,
                None => fields.push(field),
            },
            None => checker.diags.push(Diagnostic::error(format!("cannot apply --set to `{}`", parts[0]), target_span)),
        }
    }
}

/// The `params: (..)` struct of a stage value, created when absent.
fn params_of(stage: &mut Value) -> Option<&mut Value> {
    let span = stage.span;
    let fields = stage.fields_mut()?;
    if !fields.iter().any(|f| f.name.text == "params") {
        fields.push(Field {
            name: Name { text: "params".into(), span },
            value: Value { kind: ValueKind::Struct(None, Vec::new()), span },
        });
    }
    fields.iter_mut().find(|f| f.name.text == "params").map(|f| &mut f.value)
}

/// A --set value is RON when it parses as RON, else a plain string (paths, `v1.0-mini`); but
/// brackets nested beyond the limit are a value gone wrong, not a string.
fn parse_override_value(arg: &str, start: usize, id: SourceId) -> Result<Value, Diagnostic> {
    let text = &arg[start..];
    let mut scratch = Sources::default();
    let sid = scratch.add("", text);
    match syntax::parse_value(text, sid) {
        Ok(mut v) => {
            shift_spans(&mut v, id, start as u32);
            Ok(v)
        }
        Err(e) if e.too_deep => {
            let mut d = e.diagnostic;
            d.span = d.span.map(|s| Span { source: id, start: s.start + start as u32, end: s.end + start as u32 });
            Err(d)
        }
        Err(_) => Ok(Value { kind: ValueKind::Str(text.to_string()), span: Span::new(id, start, arg.len()) }),
    }
}

fn shift_spans(v: &mut Value, id: SourceId, by: u32) {
    let fix = |s: &mut Span| {
        s.source = id;
        s.start += by;
        s.end += by;
    };
    fix(&mut v.span);
    match &mut v.kind {
        ValueKind::List(items) | ValueKind::Tuple(_, items) => items.iter_mut().for_each(|i| shift_spans(i, id, by)),
        ValueKind::Map(entries) => entries.iter_mut().for_each(|(k, x)| {
            shift_spans(k, id, by);
            shift_spans(x, id, by)
        }),
        ValueKind::Struct(_, fields) => fields.iter_mut().for_each(|f| {
            fix(&mut f.name.span);
            shift_spans(&mut f.value, id, by)
        }),
        _ => {}
    }
    if let ValueKind::Tuple(Some(n), _) | ValueKind::Struct(Some(n), _) = &mut v.kind {
        fix(&mut n.span);
    }
}

struct Checker<'c> {
    catalog: &'c dyn Catalog,
    diags: Vec<Diagnostic>,
    /// Directory that relative paths written in each source resolve against.
    bases: HashMap<SourceId, PathBuf>,
}

/// A stage as declared, before its inputs are resolved.
struct Declared<'v> {
    node: NodeId,
    name_span: Span,
    inputs: Option<&'v Value>,
    schema_inputs: Vec<crate::catalog::PortSpec>,
    kind_span: Span,
}

impl<'c> Checker<'c> {
    fn err(&mut self, d: Diagnostic) {
        self.diags.push(d);
    }

    /// Reports fields not in `allowed`; returns whether all were known.
    fn known_fields(&mut self, fields: &[Field], allowed: &[&str], what: &str) -> bool {
        let mut ok = true;
        for f in fields {
            if !allowed.contains(&f.name.text.as_str()) {
                ok = false;
                let mut d = Diagnostic::error(format!("unknown field `{}` in {what}", f.name.text), f.name.span)
                    .with_label("unknown field");
                if let Some(s) = did_you_mean(&f.name.text, allowed.iter().copied()) {
                    d = d.with_note(format!("did you mean `{s}`?"));
                }
                d = d.with_note(format!("{what} fields: {}", allowed.join(", ")));
                self.err(d);
            }
        }
        ok
    }

    /// Checks params against a spec: every unknown field, then the first type error, then every
    /// value out of range. `fallback` is where a problem with a param left at its default points
    /// when no params are written (the stage's name).
    fn params(&mut self, value: Option<&Value>, spec: &ParamsSpec, what: &str, fallback: Span) -> Option<ParamsValue> {
        if let Some(v) = value {
            match v.fields() {
                Some(fields) => {
                    let mut unknown = false;
                    for f in fields {
                        if !spec.names().any(|n| n == f.name.text) {
                            unknown = true;
                            let mut d =
                                Diagnostic::error(format!("unknown param `{}` of {what}", f.name.text), f.name.span)
                                    .with_label("not a param of this kind");
                            if let Some(s) = did_you_mean(&f.name.text, spec.names()) {
                                d = d.with_note(format!("did you mean `{s}`?"));
                            }
                            d = d.with_note(format!("params: {}", spec.describe()));
                            self.err(d);
                        }
                    }
                    if unknown {
                        return None;
                    }
                }
                None => {
                    self.err(Diagnostic::error(
                        format!("params of {what} must be a struct `(name: value, ..)`, found {}", v.describe()),
                        v.span,
                    ));
                    return None;
                }
            }
        }
        match spec.check(value) {
            Ok(checked) => Some(checked),
            Err(ParamsError::Type(e)) => {
                let span = e.span.or(value.map(|v| v.span));
                let d = match span {
                    Some(s) => Diagnostic::error(format!("bad params of {what}: {}", e.message), s),
                    None => Diagnostic::without_span(format!("bad params of {what}: {}", e.message)),
                };
                self.err(d.with_note(format!("params: {}", spec.describe())));
                None
            }
            Err(ParamsError::Range(problems)) => {
                for p in problems {
                    self.range_problem(&p, value, spec, what, fallback);
                }
                None
            }
        }
    }

    /// A param out of range, at the value written for it (or for the other field of a relation),
    /// else at the params struct, else at `fallback`.
    fn range_problem(
        &mut self,
        p: &ParamProblem,
        value: Option<&Value>,
        spec: &ParamsSpec,
        what: &str,
        fallback: Span,
    ) {
        let written = |name: &str| value.and_then(|v| v.field(name)).map(|f| &f.value);
        let at = match (written(p.field), p.other.and_then(written)) {
            (Some(v), _) => match (&v.kind, p.index) {
                (ValueKind::List(items) | ValueKind::Tuple(_, items), Some(i)) if i < items.len() => items[i].span,
                _ => v.span,
            },
            (None, Some(other)) => other.span,
            (None, None) => value.map(|v| v.span).unwrap_or(fallback),
        };
        let mut d = Diagnostic::error(format!("`{}` of {what} {}", p.field, p.message), at);
        if written(p.field).is_none() {
            if let Some(f) = spec.fields.iter().find(|f| f.name == p.field) {
                d = d.with_note(format!("`{}` is not written here, so it has its default {}", p.field, f.default));
            }
        }
        self.err(d);
    }

    fn pipeline(&mut self, root: &Value, default_name: String, path: PathBuf) -> Option<Pipeline> {
        let Some(fields) = root.fields().filter(|_| root.type_name().is_none_or(|n| n.text == "Pipeline")) else {
            self.err(Diagnostic::error(
                format!("a pipeline file holds `Pipeline(dataset: .., stages: {{..}})`, found {}", root.describe()),
                root.span,
            ));
            return None;
        };
        self.known_fields(fields, &["name", "dataset", "stages", "export"], "Pipeline");
        let name = match root.field("name") {
            Some(f) => match f.value.as_str() {
                // The name is the default output folder (`out/<name>/`) and owns it.
                Some(s) => match crate::checks::path_component_problem(s) {
                    Some(problem) => {
                        self.err(Diagnostic::error(format!("the pipeline `name` {problem}"), f.value.span));
                        default_name
                    }
                    None => s.to_string(),
                },
                None => {
                    self.err(Diagnostic::error(
                        format!("`name` must be a string, found {}", f.value.describe()),
                        f.value.span,
                    ));
                    default_name
                }
            },
            None => default_name,
        };

        let dataset = match root.field("dataset") {
            Some(f) => self.dataset(&f.value),
            None => {
                self.err(
                    Diagnostic::error("the pipeline has no `dataset`", root.span)
                        .with_note(format!("dataset kinds: {}", self.catalog.dataset_kinds().join(", "))),
                );
                None
            }
        };
        // A known dataset kind gives dimensions and ports even when its config is bad, so that
        // the stages can still be checked.
        let dataset_dims: Option<Vec<Dim>> = dataset.as_ref().map(|(_, dims, _)| dims.clone());
        // Stages may run per variant, a dimension under the dataset's innermost one that exists
        // when a stage declares variants (checked once every stage is known).
        let mut dims = dataset_dims.clone().map(|mut d| {
            d.push(Dim { name: crate::VARIANT_DIM.into(), ordered: false });
            d
        });

        let mut nodes: Vec<Node> = Vec::new();
        let mut declared: Vec<Declared> = Vec::new();
        match root.field("stages").map(|f| &f.value) {
            Some(Value { kind: ValueKind::Map(entries), .. }) => {
                for (key, value) in entries {
                    self.stage(key, value, dims.as_deref(), &mut nodes, &mut declared);
                }
            }
            Some(other) => self.err(Diagnostic::error(
                format!("`stages` must be a map `{{\"name\": Kind(..), ..}}`, found {}", other.describe()),
                other.span,
            )),
            None => self.err(Diagnostic::error("the pipeline has no `stages`", root.span)),
        }

        let variants = self.variant_labels(&nodes, &declared, dims.as_deref());
        if variants.is_empty() {
            // Stages run per variant here were reported: like a refused grain, theirs is none.
            let variant_grain = dims.as_ref().map_or(0, |d| d.len());
            for n in nodes.iter_mut().filter(|n| n.grain == variant_grain) {
                n.grain = 0;
            }
            dims = dataset_dims;
        }

        // Inputs, now that every stage name is known. Sources are added as they are referenced.
        let source_ports = dataset.as_ref().map(|(_, _, ports)| ports.clone()).unwrap_or_default();
        for d in &declared {
            self.inputs(d, dims.as_deref(), &source_ports, dataset.is_some(), &mut nodes);
        }

        self.variant_inputs(&nodes, &declared);
        self.aligned_inputs(&nodes, &declared, dims.as_deref());

        let order = self.order(&nodes, &declared)?;
        let exports = match (root.field("export"), dims.as_deref()) {
            (Some(f), Some(dims)) => self.exports(&f.value, &nodes, dims),
            _ => Vec::new(),
        };
        self.export_template_params(root, &nodes, &exports);
        let (decl, _, _) = dataset?;
        Some(Pipeline { name, path, dataset: decl?, dims: dims?, nodes, order, exports, variants })
    }

    /// Inputs a stage pairs up by position must select the same items: `images` over frames
    /// -1..999999 beside `calibs` over -1..1 passes every other check and fails each task at run
    /// time.
    fn aligned_inputs(&mut self, nodes: &[Node], declared: &[Declared], dims: Option<&[Dim]>) {
        for d in declared {
            let Some(stage) = nodes[d.node].stage() else { continue };
            let Some(schema) = self.catalog.stage(&stage.kind) else { continue };
            let Some(ValueKind::Map(entries)) = d.inputs.map(|v| &v.kind) else { continue };
            for group in &schema.aligned_inputs {
                let wired: Vec<(&Input, Span)> = group
                    .iter()
                    .filter_map(|port| {
                        let input = stage.inputs.iter().find(|i| i.port == *port)?;
                        let span = entries.iter().find(|(k, _)| k.as_str() == Some(port))?.1.span;
                        Some((input, span))
                    })
                    .collect();
                let Some((first, _)) = wired.first() else { continue };
                for (other, span) in wired.iter().skip(1).filter(|(i, _)| i.selector != first.selector) {
                    let message = format!(
                        "input `{}` of stage `{}` selects {} but `{}` selects {}: {} pairs {} up by position, so they \
                         must select the same items",
                        other.port,
                        nodes[d.node].name,
                        describe_selector(other.selector, dims),
                        first.port,
                        describe_selector(first.selector, dims),
                        stage.kind,
                        group.iter().map(|p| format!("`{p}`")).collect::<Vec<_>>().join(", ")
                    );
                    self.err(Diagnostic::error(message, *span).with_label("not the same items"));
                }
            }
        }
    }

    /// Params that say where an export writes (a clip index's paths) must be one of the
    /// pipeline's export templates: a record pointing at a file the run does not write is found
    /// here, not by the loader that opens it.
    fn export_template_params(&mut self, root: &Value, nodes: &[Node], exports: &[Export]) {
        let Some(Value { kind: ValueKind::Map(entries), .. }) = root.field("stages").map(|f| &f.value) else { return };
        for node in nodes {
            let Some(stage) = node.stage() else { continue };
            let Some(schema) = self.catalog.stage(&stage.kind) else { continue };
            let declared = entries.iter().find(|(k, _)| k.as_str() == Some(node.name.as_str()));
            for &field in &schema.export_template_params {
                let written = declared.and_then(|(_, v)| v.field("params")).and_then(|p| p.value.field(field));
                let value = match written {
                    Some(f) => f.value.as_str().map(String::from),
                    None => canonical_field(&stage.params.canonical, field),
                };
                let Some(value) = value else { continue };
                if exports.iter().any(|e| e.template == value) {
                    continue;
                }
                let span = written.map(|f| f.value.span).or(declared.map(|(k, _)| k.span));
                let message = format!(
                    "param `{field}` of stage `{}` is `{value}`, which no export of this pipeline writes",
                    node.name
                );
                let mut d = match span {
                    Some(s) => Diagnostic::error(message, s).with_label("not an export template"),
                    None => Diagnostic::without_span(message),
                };
                let listed: Vec<String> = exports
                    .iter()
                    .map(|e| {
                        format!("{}.{} -> \"{}\"", nodes[e.node].name, nodes[e.node].outputs[e.port].name, e.template)
                    })
                    .collect();
                d = d.with_note(format!(
                    "it is where the stage's records say the file is; exports: {}",
                    listed.join(", ")
                ));
                self.err(d);
            }
        }
    }

    #[allow(clippy::type_complexity)]
    fn dataset(&mut self, v: &Value) -> Option<(Option<DatasetDecl>, Vec<Dim>, Vec<(String, String, usize)>)> {
        let Some(kind) = v.type_name() else {
            self.err(
                Diagnostic::error(
                    format!(
                        "`dataset` must name its kind, e.g. `{}(..)`, found {}",
                        self.catalog.dataset_kinds().first().unwrap_or(&"Kind"),
                        v.describe()
                    ),
                    v.span,
                )
                .with_note(format!("dataset kinds: {}", self.catalog.dataset_kinds().join(", "))),
            );
            return None;
        };
        let Some(schema) = self.catalog.dataset(&kind.text) else {
            let kinds = self.catalog.dataset_kinds();
            let mut d = Diagnostic::error(format!("unknown dataset kind `{}`", kind.text), kind.span)
                .with_label("not a dataset kind");
            if let Some(s) = did_you_mean(&kind.text, kinds.iter().copied()) {
                d = d.with_note(format!("did you mean `{s}`?"));
            }
            self.err(d.with_note(format!("dataset kinds: {}", kinds.join(", "))));
            return None;
        };
        // Resolve relative paths against the directory of the text they were written in.
        let mut config = v.clone();
        if let Some(fields) = config.fields_mut() {
            for f in fields.iter_mut().filter(|f| schema.path_fields.contains(&f.name.text.as_str())) {
                if let ValueKind::Str(s) | ValueKind::Ident(s) = &f.value.kind {
                    let p = Path::new(s);
                    if p.is_relative() {
                        if let Some(base) = self.bases.get(&f.value.span.source) {
                            f.value.kind = ValueKind::Str(base.join(p).display().to_string());
                        }
                    }
                }
            }
        }
        let canonical = match &config.kind {
            ValueKind::Tuple(Some(n), items) if !items.is_empty() => {
                self.err(Diagnostic::error(
                    format!("dataset `{}` takes named fields: `{}(root: \"..\")`", n.text, n.text),
                    v.span,
                ));
                None
            }
            _ => self.params(Some(&config), &schema.config, &format!("dataset {}", schema.kind), kind.span),
        };
        let dims = schema.dims.iter().map(|d| Dim { name: d.name.to_string(), ordered: d.ordered }).collect::<Vec<_>>();
        let ports = schema
            .ports
            .iter()
            .map(|p| {
                (
                    p.name.to_string(),
                    p.ty.to_string(),
                    dims.iter().position(|d| d.name == p.grain).map(|i| i + 1).unwrap_or(0),
                )
            })
            .collect();
        Some((canonical.map(|config| DatasetDecl { kind: schema.kind.to_string(), config }), dims, ports))
    }

    fn stage<'v>(
        &mut self,
        key: &Value,
        value: &'v Value,
        dims: Option<&[Dim]>,
        nodes: &mut Vec<Node>,
        declared: &mut Vec<Declared<'v>>,
    ) {
        let Some(name) = key.as_str() else {
            self.err(Diagnostic::error(format!("stage names are strings, found {}", key.describe()), key.span));
            return;
        };
        if name.is_empty() || name == "dataset" || !name.chars().all(|c| c.is_alphanumeric() || c == '_' || c == '-') {
            self.err(
                Diagnostic::error(format!("`{name}` cannot name a stage"), key.span)
                    .with_note("stage names use letters, digits, `_` and `-`, and `dataset` is reserved"),
            );
            return;
        }
        let Some(kind) = value.type_name() else {
            self.err(
                Diagnostic::error(
                    format!(
                        "stage `{name}` must name its kind, e.g. `{}(inputs: {{..}})`, found {}",
                        self.catalog.stage_kinds().first().unwrap_or(&"Kind"),
                        value.describe()
                    ),
                    value.span,
                )
                .with_note(format!("stage kinds: {}", self.catalog.stage_kinds().join(", "))),
            );
            return;
        };
        let Some(schema) = self.catalog.stage(&kind.text) else {
            let kinds = self.catalog.stage_kinds();
            let mut d = Diagnostic::error(format!("unknown stage kind `{}` (stage `{name}`)", kind.text), kind.span)
                .with_label("not a stage kind");
            if let Some(s) = did_you_mean(&kind.text, kinds.iter().copied()) {
                d = d.with_note(format!("did you mean `{s}`?"));
            }
            self.err(d.with_note(format!("stage kinds: {}", kinds.join(", "))));
            return;
        };
        let fields = match value.fields() {
            Some(f) => f,
            None => {
                self.err(Diagnostic::error(
                    format!("stage `{name}` takes named fields: `{}(inputs: {{..}}, params: (..))`", kind.text),
                    value.span,
                ));
                return;
            }
        };
        self.known_fields(fields, &["inputs", "params", "grain", "every"], &format!("stage `{name}`"));
        let what = format!("stage `{name}` ({})", schema.kind);
        let params = self.params(value.field("params").map(|f| &f.value), &schema.params, &what, key.span);

        let grain = match (value.field("grain"), dims) {
            (_, None) => None,
            (Some(f), Some(dims)) => {
                let g = match &f.value.kind {
                    ValueKind::Ident(s) | ValueKind::Str(s) => Some(s.as_str()),
                    _ => None,
                };
                match g {
                    Some(g) if schema.grains.contains(&g) && dims.iter().any(|d| d.name == g) => {
                        dims.iter().position(|d| d.name == g).map(|i| i + 1)
                    }
                    _ => {
                        self.err(
                            Diagnostic::error(format!("{what} cannot run per `{}`", self.text(&f.value)), f.value.span)
                                .with_note(format!("{} runs per one of: {}", schema.kind, schema.grains.join(", "))),
                        );
                        None
                    }
                }
            }
            (None, Some(dims)) => {
                let g = schema.grains.first().copied().unwrap_or("");
                match dims.iter().position(|d| d.name == g) {
                    Some(i) => Some(i + 1),
                    None => {
                        self.err(
                            Diagnostic::error(
                                format!("{what} runs per `{g}`, which this dataset does not have"),
                                kind.span,
                            )
                            .with_note(format!(
                                "dataset dimensions: {}",
                                dims.iter().map(|d| d.name.as_str()).collect::<Vec<_>>().join(", ")
                            )),
                        );
                        None
                    }
                }
            }
        };

        let every = match value.field("every") {
            None => 1,
            Some(f) => match &f.value.kind {
                ValueKind::Int(n) if (1..=1_000_000).contains(n) => *n as u32,
                other => {
                    let found = match other {
                        ValueKind::Int(n) => n.to_string(),
                        _ => self.text(&f.value),
                    };
                    self.err(
                        Diagnostic::error(
                            format!("{what}: `every` is a whole number of items, 1 to 1000000, found {found}"),
                            f.value.span,
                        )
                        .with_note("`every: 16` runs the stage on every 16th item of its grain's innermost dimension"),
                    );
                    1
                }
            },
        };

        let inputs = value.field("inputs").map(|f| &f.value);
        if inputs.is_none() && !schema.inputs.is_empty() {
            self.err(Diagnostic::error(format!("{what} has no `inputs`"), kind.span).with_note(format!(
                "{} inputs: {}",
                schema.kind,
                describe_ports(&schema.inputs)
            )));
        }
        let variants = schema.variants.zip(params.as_ref()).and_then(|(split, p)| split(p));
        let unused = schema.unused_inputs.zip(params.as_ref()).map(|(f, p)| f(p)).unwrap_or_default();
        let node = nodes.len();
        nodes.push(Node {
            name: name.to_string(),
            grain: grain.unwrap_or(0),
            outputs: schema.outputs.iter().map(|p| OutPort { name: p.name.into(), ty: p.ty.into() }).collect(),
            kind: NodeKind::Stage(StageNode {
                kind: schema.kind.into(),
                version: schema.version,
                params: params.unwrap_or_default(),
                seeded: schema.seeded,
                every,
                inputs: Vec::new(),
                variants,
                unused,
            }),
        });
        declared.push(Declared {
            node,
            name_span: key.span,
            inputs,
            schema_inputs: schema.inputs.clone(),
            kind_span: kind.span,
        });
    }

    /// The labels of the variant dimension: those of the stages that declare variants (which
    /// must agree), or none when no stage does. A stage running per variant without any stage
    /// declaring them is an error, and so is a declaring stage run per another grain.
    fn variant_labels(&mut self, nodes: &[Node], declared: &[Declared], dims: Option<&[Dim]>) -> Vec<String> {
        let Some(dims) = dims else { return Vec::new() };
        let variant_grain = dims.len();
        let mut labels: Option<(Vec<String>, &str)> = None;
        for d in declared {
            let node = &nodes[d.node];
            let Some(stage) = node.stage() else { continue };
            let declares = self.catalog.stage(&stage.kind).is_some_and(|k| k.variants.is_some());
            let these = match &stage.variants {
                Some(v) => v.labels(),
                // Its params were refused (and reported): it still declares variants, so the
                // stages run per variant and the exports naming `{variant}` are not errors too.
                None if declares => {
                    labels.get_or_insert((vec!["?".to_string()], &node.name));
                    continue;
                }
                None => continue,
            };
            if node.grain != 0 && node.grain != variant_grain {
                self.err(
                    Diagnostic::error(
                        format!("stage `{}` declares variants, so it runs per `{}`", node.name, crate::VARIANT_DIM),
                        d.name_span,
                    )
                    .with_note("remove its `grain`"),
                );
            }
            match &labels {
                None => labels = Some((these, &node.name)),
                Some((first, first_stage)) if *first != these => {
                    self.err(
                        Diagnostic::error(
                            format!(
                                "stage `{}` declares the variants {}, and stage `{first_stage}` {}: a pipeline has one variant dimension",
                                node.name,
                                these.join(", "),
                                first.join(", ")
                            ),
                            d.name_span,
                        )
                        .with_note("give both the same variant labels"),
                    );
                }
                Some(_) => {}
            }
        }
        let labels = labels.map(|(l, _)| l).unwrap_or_default();
        if labels.is_empty() {
            for d in declared {
                let node = &nodes[d.node];
                if node.grain == variant_grain && node.stage().is_some_and(|s| s.variants.is_none()) {
                    self.err(
                        Diagnostic::error(
                            format!(
                                "stage `{}` runs per `{}`, but no stage of this pipeline declares variants",
                                node.name,
                                crate::VARIANT_DIM
                            ),
                            d.name_span,
                        )
                        .with_note("variants come from a stage whose params list them (e.g. a `variants: {..}` map)"),
                    );
                }
            }
        }
        labels
    }

    /// Every optional input a stage's variant cannot do without must be wired.
    fn variant_inputs(&mut self, nodes: &[Node], declared: &[Declared]) {
        for d in declared {
            let Some(stage) = nodes[d.node].stage() else { continue };
            let Some(v) = &stage.variants else { continue };
            for ((label, _), plan) in v.each.iter().zip(&v.plans) {
                for need in &plan.needs {
                    if stage.inputs.iter().any(|i| i.port == *need) {
                        continue;
                    }
                    let doc = d.schema_inputs.iter().find(|p| p.name == *need).map_or("", |p| p.doc);
                    self.err(
                        Diagnostic::error(
                            format!(
                                "variant `{label}` of stage `{}` reads input `{need}`, which is not wired",
                                nodes[d.node].name
                            ),
                            d.inputs.map(|v| v.span).unwrap_or(d.kind_span),
                        )
                        .with_note(format!("wire it: \"{need}\": .. ({doc})")),
                    );
                }
            }
        }
    }

    fn text(&self, v: &Value) -> String {
        match &v.kind {
            ValueKind::Ident(s) | ValueKind::Str(s) => s.clone(),
            _ => v.describe(),
        }
    }

    fn inputs(
        &mut self,
        d: &Declared,
        dims: Option<&[Dim]>,
        source_ports: &[(String, String, usize)],
        have_dataset: bool,
        nodes: &mut Vec<Node>,
    ) {
        let stage_name = nodes[d.node].name.clone();
        let what = format!("stage `{stage_name}`");
        let entries: &[(Value, Value)] = match d.inputs.map(|v| &v.kind) {
            Some(ValueKind::Map(e)) => e,
            Some(_) => {
                let v = d.inputs.unwrap();
                self.err(Diagnostic::error(
                    format!(
                        "`inputs` of {what} must be a map `{{\"port\": \"stage.port\", ..}}`, found {}",
                        v.describe()
                    ),
                    v.span,
                ));
                return;
            }
            None => &[],
        };
        let mut wired = Vec::new();
        for (key, sel) in entries {
            let Some(port) = key.as_str() else {
                self.err(Diagnostic::error(
                    format!("input port names are strings, found {}", key.describe()),
                    key.span,
                ));
                continue;
            };
            let Some(spec) = d.schema_inputs.iter().find(|p| p.name == port) else {
                let mut diag = Diagnostic::error(format!("{what} has no input port `{port}`"), key.span)
                    .with_label("unknown input port");
                if let Some(s) = did_you_mean(port, d.schema_inputs.iter().map(|p| p.name)) {
                    diag = diag.with_note(format!("did you mean `{s}`?"));
                }
                self.err(diag.with_note(format!("inputs: {}", describe_ports(&d.schema_inputs))));
                continue;
            };
            wired.push(port);
            let Some((reference, ref_span, selector)) = self.selector(sel, dims) else {
                continue;
            };
            let Some((from, from_port)) = self.resolve(&reference, ref_span, source_ports, have_dataset, nodes) else {
                continue;
            };
            let from_ty = nodes[from].outputs[from_port].ty.clone();
            if from_ty != spec.ty {
                self.err(
                    Diagnostic::error(
                        format!(
                            "type mismatch: input `{port}` of {what} takes {} but `{reference}` gives {from_ty}",
                            spec.ty
                        ),
                        ref_span,
                    )
                    .with_label(format!("this is {from_ty}, not {}", spec.ty)),
                );
                continue;
            }
            if spec.many != selector.gives_many() && !spec.many {
                self.err(
                    Diagnostic::error(
                        format!(
                            "input `{port}` of {what} takes one {} but {} gives several",
                            spec.ty,
                            selector.display(dims.unwrap_or(&[]))
                        ),
                        sel.span,
                    )
                    .with_note("use the plain `\"stage.port\"` form or Offset(..) for one artifact"),
                );
                continue;
            }
            if let Some(dims) = dims {
                let (u, dn) = (nodes[from].grain, nodes[d.node].grain);
                if u > 0 && dn > 0 {
                    if let Err(msg) = grain_allows(selector, u, dn, dims) {
                        self.err(Diagnostic::error(
                            format!(
                                "{what} runs per {} but its input `{port}` from `{reference}` (per {}) {msg}",
                                dims[dn - 1].name,
                                dims[u - 1].name
                            ),
                            sel.span,
                        ));
                        continue;
                    }
                }
            }
            if let NodeKind::Stage(s) = &mut nodes[d.node].kind {
                s.inputs.push(Input {
                    port: port.to_string(),
                    ty: spec.ty.to_string(),
                    from,
                    from_port,
                    selector,
                    many: spec.many,
                });
            }
        }
        for spec in &d.schema_inputs {
            if !wired.contains(&spec.name) && !spec.optional {
                let span = d.inputs.map(|v| v.span).unwrap_or(d.kind_span);
                if d.inputs.is_some() {
                    self.err(
                        Diagnostic::error(format!("input `{}` ({}) of {what} is not wired", spec.name, spec.ty), span)
                            .with_note(format!("wire it: \"{}\": \"stage.port\" ({})", spec.name, spec.doc)),
                    );
                }
            }
        }
        // Inputs in the schema's port order, so that operators can rely on it.
        if let NodeKind::Stage(s) = &mut nodes[d.node].kind {
            s.inputs.sort_by_key(|i| d.schema_inputs.iter().position(|p| p.name == i.port));
        }
        let _ = d.name_span;
    }

    /// Parses `"stage.port"`, `Same(..)`, `Window("stage.port", dim, -1, 1)`, `Offset(..)`, `Gather(..)`,
    /// `Across(..)`, `All(..)`.
    fn selector(&mut self, v: &Value, dims: Option<&[Dim]>) -> Option<(String, Span, Selector)> {
        if let Some(s) = v.as_str() {
            return Some((s.to_string(), v.span, Selector::Same));
        }
        let usage = selector_usage(dims);
        let ValueKind::Tuple(Some(name), items) = &v.kind else {
            self.err(
                Diagnostic::error(format!("expected an input reference, found {}", v.describe()), v.span)
                    .with_note(usage),
            );
            return None;
        };
        let Some(first) = items.first().and_then(|i| i.as_str().map(|s| (s.to_string(), i.span))) else {
            self.err(
                Diagnostic::error(format!("`{}` takes the input reference \"stage.port\" first", name.text), v.span)
                    .with_note(usage),
            );
            return None;
        };
        let arity = match name.text.as_str() {
            "Same" | "All" => 1,
            "Gather" | "Across" => 2,
            "Offset" => 3,
            "Window" => 4,
            _ => {
                self.err(Diagnostic::error(format!("unknown selector `{}`", name.text), name.span).with_note(&usage));
                return None;
            }
        };
        if items.len() != arity {
            self.err(
                Diagnostic::error(format!("`{}` takes {arity} values, found {}", name.text, items.len()), v.span)
                    .with_note(usage),
            );
            return None;
        }
        let dim = |this: &mut Self, i: usize, ordered: bool| -> Option<usize> {
            let item = &items[i];
            let text = match &item.kind {
                ValueKind::Ident(s) | ValueKind::Str(s) => s.clone(),
                _ => {
                    this.err(Diagnostic::error(
                        format!("expected a dimension name, found {}", item.describe()),
                        item.span,
                    ));
                    return None;
                }
            };
            let dims = dims?;
            match dims.iter().position(|d| d.name == text) {
                Some(k) if !ordered || dims[k].ordered => Some(k),
                Some(_) => {
                    this.err(
                        Diagnostic::error(
                            format!("`{}` cannot move along `{text}`: it has no order", name.text),
                            item.span,
                        )
                        .with_note(format!(
                            "ordered dimensions: {}",
                            dims.iter().filter(|d| d.ordered).map(|d| d.name.as_str()).collect::<Vec<_>>().join(", ")
                        )),
                    );
                    None
                }
                None => {
                    this.err(Diagnostic::error(format!("the dataset has no dimension `{text}`"), item.span).with_note(
                        format!("dimensions: {}", dims.iter().map(|d| d.name.as_str()).collect::<Vec<_>>().join(", ")),
                    ));
                    None
                }
            }
        };
        let int = |this: &mut Self, i: usize| -> Option<i32> {
            match items[i].kind {
                // `unsigned_abs`: `abs` of i64::MIN overflows (and wraps to a negative number,
                // which passed the bound, in release builds).
                ValueKind::Int(x) if x.unsigned_abs() <= MAX_SELECTOR_OFFSET as u64 => Some(x as i32),
                ValueKind::Int(x) => {
                    this.err(
                        Diagnostic::error(
                            format!("the offset {x} is out of range: offsets are within ±{MAX_SELECTOR_OFFSET}"),
                            items[i].span,
                        )
                        .with_label("out of range"),
                    );
                    None
                }
                _ => {
                    this.err(Diagnostic::error(
                        format!("expected a whole number, found {}", items[i].describe()),
                        items[i].span,
                    ));
                    None
                }
            }
        };
        let sel = match name.text.as_str() {
            "Same" => Selector::Same,
            "All" => Selector::All,
            "Gather" => Selector::Gather { dim: dim(self, 1, false)? },
            "Across" => Selector::Across { dim: dim(self, 1, false)? },
            "Offset" if matches!(&items[2].kind, ValueKind::Ident(v) if v == crate::VARIANT_DIM) => {
                Selector::VariantOffset { dim: dim(self, 1, true)? }
            }
            "Offset" => Selector::Offset { dim: dim(self, 1, true)?, by: int(self, 2)? },
            _ => {
                let (dim, before, after) = (dim(self, 1, true)?, int(self, 2)?, int(self, 3)?);
                if before > after {
                    self.err(
                        Diagnostic::error(format!("the window {before}..{after} is empty"), v.span)
                            .with_note(format!("write Window(\"s.p\", {}, -1, 1) for i-1..i+1", dim_name(dims, dim))),
                    );
                    return None;
                }
                Selector::Window { dim, before, after }
            }
        };
        Some((first.0, first.1, sel))
    }

    /// `stage.port` or `dataset.port` -> (node, output port); adds source nodes on first use.
    fn resolve(
        &mut self,
        reference: &str,
        span: Span,
        source_ports: &[(String, String, usize)],
        have_dataset: bool,
        nodes: &mut Vec<Node>,
    ) -> Option<(NodeId, usize)> {
        let Some((stage, port)) = reference.split_once('.') else {
            self.err(
                Diagnostic::error(format!("`{reference}` is not a `stage.port` reference"), span)
                    .with_label("expected `stage.port`"),
            );
            return None;
        };
        if stage == "dataset" {
            if !have_dataset {
                return None;
            }
            let Some((_, ty, grain)) = source_ports.iter().find(|(n, _, _)| n == port) else {
                let mut d = Diagnostic::error(format!("the dataset has no port `{port}`"), span)
                    .with_label("unknown dataset port");
                if let Some(s) = did_you_mean(port, source_ports.iter().map(|(n, _, _)| n.as_str())) {
                    d = d.with_note(format!("did you mean `dataset.{s}`?"));
                }
                self.err(d.with_note(format!(
                    "dataset ports: {}",
                    source_ports.iter().map(|(n, t, _)| format!("{n} ({t})")).collect::<Vec<_>>().join(", ")
                )));
                return None;
            };
            let name = format!("dataset.{port}");
            if let Some(i) = nodes.iter().position(|n| n.name == name) {
                return Some((i, 0));
            }
            nodes.push(Node {
                name,
                grain: *grain,
                outputs: vec![OutPort { name: port.into(), ty: ty.clone() }],
                kind: NodeKind::Source { port: port.into() },
            });
            return Some((nodes.len() - 1, 0));
        }
        let Some(from) = nodes.iter().position(|n| n.name == stage && n.stage().is_some()) else {
            let names: Vec<&str> = nodes.iter().filter(|n| n.stage().is_some()).map(|n| n.name.as_str()).collect();
            let mut d = Diagnostic::error(format!("no stage named `{stage}`"), span).with_label("unknown stage");
            if let Some(s) = did_you_mean(stage, names.iter().copied()) {
                d = d.with_note(format!("did you mean `{s}`?"));
            }
            self.err(d.with_note(format!("stages: {} (and `dataset.<port>`)", names.join(", "))));
            return None;
        };
        match nodes[from].outputs.iter().position(|p| p.name == port) {
            Some(p) => Some((from, p)),
            None => {
                let outs =
                    nodes[from].outputs.iter().map(|p| format!("{} ({})", p.name, p.ty)).collect::<Vec<_>>().join(", ");
                let mut d = Diagnostic::error(format!("stage `{stage}` has no output port `{port}`"), span)
                    .with_label("unknown output port");
                if let Some(s) = did_you_mean(port, nodes[from].outputs.iter().map(|p| p.name.as_str())) {
                    d = d.with_note(format!("did you mean `{stage}.{s}`?"));
                }
                self.err(d.with_note(format!("outputs of `{stage}`: {outs}")));
                None
            }
        }
    }

    /// Topological order, or a diagnostic naming the stages of each cycle.
    fn order(&mut self, nodes: &[Node], declared: &[Declared]) -> Option<Vec<NodeId>> {
        let mut g = petgraph::graph::DiGraph::<NodeId, ()>::new();
        let idx: Vec<_> = (0..nodes.len()).map(|n| g.add_node(n)).collect();
        for (n, node) in nodes.iter().enumerate() {
            if let Some(s) = node.stage() {
                for i in &s.inputs {
                    g.add_edge(idx[i.from], idx[n], ());
                }
            }
        }
        match petgraph::algo::toposort(&g, None) {
            Ok(order) => Some(order.into_iter().map(|i| g[i]).collect()),
            Err(_) => {
                for scc in petgraph::algo::tarjan_scc(&g) {
                    let cyclic = scc.len() > 1 || g.contains_edge(scc[0], scc[0]);
                    if !cyclic {
                        continue;
                    }
                    let mut members: Vec<NodeId> = scc.iter().map(|i| g[*i]).collect();
                    members.sort();
                    let names: Vec<String> = members.iter().map(|m| format!("`{}`", nodes[*m].name)).collect();
                    let span = declared.iter().find(|d| d.node == members[0]).map(|d| d.name_span);
                    let msg = format!("the stages {} form a cycle: each needs another's output", names.join(" -> "));
                    let d = match span {
                        Some(s) => Diagnostic::error(msg, s).with_label("this stage is in the cycle"),
                        None => Diagnostic::without_span(msg),
                    };
                    self.err(d);
                }
                None
            }
        }
    }

    fn exports(&mut self, v: &Value, nodes: &[Node], dims: &[Dim]) -> Vec<Export> {
        let ValueKind::Map(entries) = &v.kind else {
            self.err(Diagnostic::error(
                format!(
                    "`export` must be a map `{{\"stage.port\": \"{}.ext\"}}`, found {}",
                    dims.iter().map(|d| format!("{{{}}}", d.name)).collect::<Vec<_>>().join("/"),
                    v.describe()
                ),
                v.span,
            ));
            return Vec::new();
        };
        let mut out: Vec<Export> = Vec::new();
        for (key, value) in entries {
            let (Some(reference), Some(template)) = (key.as_str(), value.as_str()) else {
                self.err(Diagnostic::error(
                    "export entries are \"stage.port\": \"path template\"",
                    key.span.to(value.span),
                ));
                continue;
            };
            let Some((stage, port)) = reference.split_once('.') else {
                self.err(Diagnostic::error(format!("`{reference}` is not a `stage.port` reference"), key.span));
                continue;
            };
            let Some(node) = nodes.iter().position(|n| n.name == stage && n.stage().is_some()) else {
                self.err(Diagnostic::error(
                    format!("export names stage `{stage}`, which the pipeline does not have"),
                    key.span,
                ));
                continue;
            };
            let Some(p) = nodes[node].outputs.iter().position(|o| o.name == port) else {
                let outs = nodes[node].outputs.iter().map(|p| p.name.as_str()).collect::<Vec<_>>().join(", ");
                self.err(
                    Diagnostic::error(format!("stage `{stage}` has no output port `{port}`"), key.span)
                        .with_note(format!("outputs: {outs}")),
                );
                continue;
            };
            let ty = &nodes[node].outputs[p].ty;
            if !self.catalog.exportable(ty) {
                self.err(
                    Diagnostic::error(format!("`{reference}` gives {ty}, which is not an encoded file"), key.span)
                        .with_note(format!("export writes encoded files; add a stage that encodes the {ty} between")),
                );
                continue;
            }
            let grain = nodes[node].grain;
            if grain == 0 {
                // The stage's grain was refused (and reported) already: there is no grain to check
                // the template's placeholders against.
                continue;
            }
            match parse_template(template, dims, grain) {
                Ok(parts) => {
                    if out.iter().any(|e| e.template == template) {
                        self.err(Diagnostic::error(format!("two exports write to `{template}`"), value.span));
                        continue;
                    }
                    out.push(Export { node, port: p, template: template.to_string(), parts })
                }
                Err(msg) => {
                    self.err(Diagnostic::error(format!("bad export path for `{reference}`: {msg}"), value.span))
                }
            }
        }
        out
    }
}

/// A string field of canonical params text (`(a:1,depth:"x")`), as its default is written there.
fn canonical_field(canonical: &str, field: &str) -> Option<String> {
    let mut sources = Sources::default();
    let id = sources.add("", canonical);
    let value = syntax::parse_value(canonical, id).ok()?;
    value.field(field).and_then(|f| f.value.as_str()).map(String::from)
}

/// How inputs are written, with the dataset's dimension names when it is known.
fn selector_usage(dims: Option<&[Dim]>) -> String {
    let ordered = dims.and_then(|d| d.iter().position(|d| d.ordered)).map_or("dim", |k| dim_name(dims, k));
    // The dataset's innermost dimension (not the pipeline's variants).
    let innermost = dims.map_or("dim", |d| {
        let n = d.iter().filter(|d| d.name != crate::VARIANT_DIM).count();
        dim_name(dims, n.saturating_sub(1))
    });
    format!(
        "an input is \"stage.port\", Same(\"stage.port\"), Window(\"stage.port\", {ordered}, -1, 1), \
         Offset(\"stage.port\", {ordered}, 2), Gather(\"stage.port\", {innermost}), Across(\"stage.port\", {innermost}) \
         or All(\"stage.port\")"
    )
}

/// The name of dimension `k`, or `dim` when the dataset (and so its dimensions) is unknown.
fn dim_name(dims: Option<&[Dim]>, k: usize) -> &str {
    dims.and_then(|d| d.get(k)).map_or("dim", |d| d.name.as_str())
}

/// Largest offset a `Window` or `Offset` selector may take along a dimension: far beyond any
/// dimension's length (an hour at 20 Hz is 72,000 steps), small enough for `i32` positions.
const MAX_SELECTOR_OFFSET: i32 = 999_999;

/// Why a selector cannot connect an upstream grain `u` to a downstream grain `d` (depths, 1-based).
fn grain_allows(sel: Selector, u: usize, d: usize, dims: &[Dim]) -> Result<(), String> {
    match sel {
        Selector::Same if u <= d => Ok(()),
        Selector::Same => Err(format!("is finer: gather it with Gather(\"..\", {})", dims[d].name)),
        Selector::VariantOffset { dim } if u <= d && dim < u && d == dims.len() && dims[d - 1].name == crate::VARIANT_DIM => {
            Ok(())
        }
        Selector::VariantOffset { .. } => {
            Err("moves by the task's variant's offset, so the stage must run per `variant`".into())
        }
        Selector::Window { dim, .. } | Selector::Offset { dim, .. } if u <= d && dim < u => Ok(()),
        Selector::Window { dim, .. } | Selector::Offset { dim, .. } => {
            Err(format!("cannot be moved along `{}` that way: the upstream must be per `{}` or coarser and have that dimension", dims[dim].name, dims[d - 1].name))
        }
        Selector::Gather { dim } if d == dim && u == d + 1 => Ok(()),
        Selector::Gather { dim } => Err(format!(
            "cannot be gathered over `{}`: Gather needs the upstream one grain finer than the stage, along that dimension",
            dims[dim].name
        )),
        Selector::All => Ok(()),
        Selector::Across { dim } if u <= d && dim < u => Ok(()),
        Selector::Across { dim } => Err(format!(
            "cannot be taken across `{}`: the upstream must be per `{}` or coarser and have that dimension",
            dims[dim].name,
            dims[d - 1].name
        )),
    }
}

/// `{a}/{c}/{b}.exr` -> parts; the template must name every dimension of the grain (here a, b, c).
fn parse_template(template: &str, dims: &[Dim], grain: usize) -> Result<Vec<TemplatePart>, String> {
    if template.starts_with('/') || template.split('/').any(|s| s == ".." || s == "." || s.is_empty()) {
        return Err("the path must be relative, without empty, `.` or `..` parts".into());
    }
    if let Some(c) = template.chars().find(|c| *c == '\\' || c.is_control()) {
        return Err(format!("the path must not hold `{}` (folders are separated by `/`)", c.escape_default()));
    }
    let mut parts = Vec::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        if open > 0 {
            parts.push(TemplatePart::Text(rest[..open].to_string()));
        }
        let Some(close) = rest[open..].find('}') else {
            return Err("a `{` is not closed".into());
        };
        let placeholder = &rest[open + 1..open + close];
        let (placeholder, width) = match placeholder.split_once(':') {
            Some((p, w)) => {
                match w.strip_prefix('0').and_then(|w| w.parse::<usize>().ok()).filter(|w| (1..=20).contains(w)) {
                    Some(w) => (p, Some(w)),
                    None => {
                        return Err(format!(
                    "`{{{p}:{w}}}`: the format is `:0N`, the label zero-padded to N digits (1-20), e.g. `{{{p}:06}}`"
                ))
                    }
                }
            }
            None => (placeholder, None),
        };
        let (name, token) = match placeholder.split_once('.') {
            Some((dim, "token")) => (dim, true),
            Some((_, field)) => {
                return Err(format!("unknown field `.{field}` in `{{{placeholder}}}`; a dimension has `.token` (the dataset's id of the item)"))
            }
            None => (placeholder, false),
        };
        match dims.iter().position(|d| d.name == name) {
            Some(_) if token && width.is_some() => {
                return Err(format!("`{{{placeholder}:..}}`: a token is not a number to pad"))
            }
            Some(k) if k < grain && token => parts.push(TemplatePart::Token(k)),
            Some(k) if k < grain && width.is_some() => parts.push(TemplatePart::Padded(k, width.unwrap_or(0))),
            Some(k) if k < grain => parts.push(TemplatePart::Dim(k)),
            Some(_) => {
                let per = grain.checked_sub(1).and_then(|g| dims.get(g)).map_or("?", |d| d.name.as_str());
                return Err(format!("`{{{name}}}` is finer than the stage's grain (per {per})"));
            }
            None => {
                return Err(format!(
                    "unknown placeholder `{{{name}}}`; use {}",
                    dims[..grain].iter().map(|d| format!("{{{}}}", d.name)).collect::<Vec<_>>().join(", ")
                ))
            }
        }
        rest = &rest[open + close + 1..];
    }
    if !rest.is_empty() {
        parts.push(TemplatePart::Text(rest.to_string()));
    }
    for (k, d) in dims[..grain].iter().enumerate() {
        if !parts.iter().any(|p| p.dim() == Some(k)) {
            return Err(format!(
                "it must name `{{{}}}` (or `{{{}.token}}`) so that items do not overwrite each other",
                d.name, d.name
            ));
        }
    }
    Ok(parts)
}

fn describe_ports(ports: &[crate::catalog::PortSpec]) -> String {
    ports
        .iter()
        .map(|p| {
            format!(
                "{} ({}{})",
                p.name,
                p.ty,
                if p.many {
                    ", several"
                } else if p.optional {
                    ", optional"
                } else {
                    ""
                }
            )
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// A selector as a pipeline file writes it (`Window(frame, -1, 1)`).
fn describe_selector(s: Selector, dims: Option<&[Dim]>) -> String {
    let name =
        |dim: usize| dims.and_then(|d| d.get(dim)).map_or_else(|| format!("dimension {dim}"), |d| d.name.clone());
    match s {
        Selector::Same => "the same item".into(),
        Selector::Window { dim, before, after } => format!("Window({}, {before}, {after})", name(dim)),
        Selector::Offset { dim, by } => format!("Offset({}, {by})", name(dim)),
        Selector::Gather { dim } => format!("Gather({})", name(dim)),
        Selector::All => "every item under the outer item".into(),
        Selector::VariantOffset { dim } => format!("the variant's offset along {}", name(dim)),
        Selector::Across { dim } => format!("Across({})", name(dim)),
    }
}
