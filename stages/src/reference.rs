//! The generated part of `docs/stages.md`: every stage's and dataset's ports, types and params,
//! written from the registry so that the reference cannot drift from the code (a test compares
//! the committed file with what the registry says now).

use crate::Registry;
use dist4d_graph::{PortSpec, StageSchema};
use std::fmt::Write;

/// The markers between which `docs/stages.md` holds the generated reference.
pub const BEGIN: &str = "<!-- BEGIN GENERATED REFERENCE: edit the stage modules, then re-run `DIST4D_BLESS=1 cargo test -p dist4d-stages reference` -->";
pub const END: &str = "<!-- END GENERATED REFERENCE -->";

/// Markdown tables of every dataset and stage kind of `registry`, in registry order.
pub fn markdown(registry: &Registry) -> String {
    let mut out = String::from("## Reference: ports and params\n\n");
    for d in registry.dataset_schemas() {
        let _ = writeln!(out, "### Dataset `{}`\n\n{}\n", d.kind, d.summary);
        let dims: Vec<&str> = d.dims.iter().map(|d| d.name).collect();
        let _ = writeln!(out, "Items: {}.\n", dims.join(" > "));
        out.push_str("| port | type | per | what |\n| --- | --- | --- | --- |\n");
        for p in &d.ports {
            let _ = writeln!(out, "| `{}` | {} | {} | {} |", p.name, p.ty, p.grain, cell(p.doc));
        }
        params(&mut out, &d.config.fields);
    }
    for def in registry.stage_defs() {
        stage(&mut out, &def.schema);
    }
    out
}

fn stage(out: &mut String, s: &StageSchema) {
    let _ = writeln!(out, "### `{}` (version {}, per {})\n\n{}\n", s.kind, s.version, s.grains.join(" or "), s.summary);
    ports(out, "input", &s.inputs);
    ports(out, "output", &s.outputs);
    params(out, &s.params.fields);
}

fn ports(out: &mut String, what: &str, list: &[PortSpec]) {
    let _ = writeln!(out, "| {what} | type | takes | what |\n| --- | --- | --- | --- |");
    for p in list {
        let takes = if p.many && p.optional {
            "several, optional"
        } else if p.many {
            "several"
        } else if p.optional {
            "one, optional"
        } else {
            "one"
        };
        let _ = writeln!(out, "| `{}` | {} | {takes} | {} |", p.name, p.ty, cell(p.doc));
    }
    out.push('\n');
}

fn params(out: &mut String, fields: &[dist4d_graph::ParamInfo]) {
    if fields.is_empty() {
        out.push_str("No params.\n\n");
        return;
    }
    out.push_str("| param | default |\n| --- | --- |\n");
    for f in fields {
        let _ = writeln!(out, "| `{}` | `{}` |", f.name, cell(&f.default));
    }
    out.push('\n');
}

/// Text safe inside a table cell.
fn cell(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// docs/stages.md holds the reference the registry generates now (DIST4D_BLESS=1 rewrites it).
    #[test]
    fn the_committed_stage_reference_is_current() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/stages.md");
        let doc = std::fs::read_to_string(&path).unwrap();
        let generated = markdown(&Registry::default());
        let (start, end) = (doc.find(BEGIN), doc.find(END));
        let current = match (start, end) {
            (Some(s), Some(e)) if s < e => &doc[s + BEGIN.len()..e],
            _ => "",
        };
        let want = format!("\n{generated}");
        if current == want {
            return;
        }
        if std::env::var_os("DIST4D_BLESS").is_some() {
            let head = start.map_or(doc.as_str(), |s| &doc[..s]).trim_end();
            let tail = end.map_or("", |e| &doc[e + END.len()..]);
            std::fs::write(&path, format!("{head}\n\n{BEGIN}{want}{END}{tail}")).unwrap();
            return;
        }
        panic!(
            "{} is stale: its generated reference differs from the registry; re-run with DIST4D_BLESS=1",
            path.display()
        );
    }
}
