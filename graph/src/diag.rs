//! Diagnostics: a problem in a pipeline, rendered as `file:line:column` with a caret snippet.

use crate::source::{Sources, Span};
use std::fmt::Write;

#[derive(Clone, Debug, PartialEq)]
pub struct Diagnostic {
    pub message: String,
    /// Where the problem is; `None` for problems with no place (an empty pipeline file).
    pub span: Option<Span>,
    /// Short text printed under the carets.
    pub label: Option<String>,
    /// Extra lines: what exists, what was meant.
    pub notes: Vec<String>,
}

impl Diagnostic {
    pub fn error(message: impl Into<String>, span: Span) -> Diagnostic {
        Diagnostic { message: message.into(), span: Some(span), label: None, notes: Vec::new() }
    }

    pub fn without_span(message: impl Into<String>) -> Diagnostic {
        Diagnostic { message: message.into(), span: None, label: None, notes: Vec::new() }
    }

    pub fn with_label(mut self, label: impl Into<String>) -> Diagnostic {
        self.label = Some(label.into());
        self
    }

    pub fn with_note(mut self, note: impl Into<String>) -> Diagnostic {
        self.notes.push(note.into());
        self
    }

    /// Renders like rustc:
    ///
    /// ```text
    /// error: unknown param `min_dept` of stage `project` (Project)
    ///   --> pipelines/example.ron:12:13
    ///    |
    /// 12 |             min_dept: 1.0,
    ///    |             ^^^^^^^^ not a param of this kind
    ///    = note: params: min_depth (default 1.0)
    /// ```
    pub fn render(&self, sources: &Sources) -> String {
        let mut out = format!("error: {}\n", self.message);
        let mut gutter = 1;
        if let Some(span) = self.span {
            let file = sources.get(span.source);
            let loc = sources.location(span);
            let line_text = file.line_text(loc.line);
            gutter = loc.line.to_string().len();
            let pad = " ".repeat(gutter);
            let _ = writeln!(out, "{pad}--> {loc}");
            let _ = writeln!(out, "{pad} |");
            let (shown, column) = clip_line(line_text, loc.column);
            let _ = writeln!(out, "{} | {}", loc.line, shown);
            // Carets under the span, clipped to the first line it covers (and to what is shown).
            let text_from_col: String = shown.chars().skip(column - 1).collect();
            let span_chars = sources.slice(span).chars().take_while(|c| *c != '\n').count();
            let width = span_chars.clamp(1, text_from_col.chars().count().max(1));
            let _ = write!(out, "{pad} | {}{}", " ".repeat(column - 1), "^".repeat(width));
            if let Some(label) = &self.label {
                let _ = write!(out, " {label}");
            }
            out.push('\n');
        }
        for note in &self.notes {
            let _ = writeln!(out, "{} = note: {}", " ".repeat(gutter), note);
        }
        out
    }
}

/// Longest line a snippet shows whole, in characters.
const MAX_SHOWN: usize = 120;

/// The part of `line` a snippet shows (all of it, or `MAX_SHOWN` characters around `column`
/// between `...` marks: a generated file may hold one line of megabytes) and the 1-based
/// column of the same character in it.
fn clip_line(line: &str, column: usize) -> (String, usize) {
    let chars: Vec<char> = line.chars().collect();
    if chars.len() <= MAX_SHOWN {
        return (line.to_string(), column);
    }
    let start = column.saturating_sub(1 + MAX_SHOWN / 3).min(chars.len() - MAX_SHOWN);
    let end = start + MAX_SHOWN;
    let mut shown = String::new();
    if start > 0 {
        shown.push_str("...");
    }
    shown.extend(&chars[start..end]);
    if end < chars.len() {
        shown.push_str("...");
    }
    (shown, column - start + if start > 0 { 3 } else { 0 })
}

/// Renders every diagnostic, then a count line.
pub fn render_all(diags: &[Diagnostic], sources: &Sources) -> String {
    let mut out = String::new();
    for d in diags {
        out.push_str(&d.render(sources));
        out.push('\n');
    }
    let n = diags.len();
    let _ = writeln!(out, "{} problem{} found; nothing was run", n, if n == 1 { "" } else { "s" });
    out
}

/// The candidate closest to `word` by edit distance, if it is close enough to be a likely typo.
pub fn did_you_mean<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    candidates
        .into_iter()
        .map(|c| (edit_distance(word, c), c))
        .filter(|(d, c)| *d <= (c.len().max(word.len()) / 3).max(1))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            let sub = prev[j] + usize::from(ca != *cb);
            cur[j + 1] = sub.min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_location_and_carets_under_the_span() {
        let mut s = Sources::default();
        let id = s.add("p.ron", "(\n  stages: {\n    \"a\": Foo(),\n  },\n)\n");
        let d = Diagnostic::error("unknown stage kind `Foo`", Span::new(id, 23, 26))
            .with_label("not a stage kind")
            .with_note("known kinds: Bar");
        let text = d.render(&s);
        assert_eq!(
            text,
            "error: unknown stage kind `Foo`\n --> p.ron:3:10\n  |\n3 |     \"a\": Foo(),\n  |          ^^^ not a stage kind\n  = note: known kinds: Bar\n"
        );
    }

    #[test]
    fn long_lines_are_shown_around_the_position() {
        let mut s = Sources::default();
        let line = format!("{}X{}", "a".repeat(5000), "b".repeat(5000));
        let id = s.add("p.ron", line.clone());
        let text = Diagnostic::error("here", Span::new(id, 5000, 5001)).render(&s);
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[1].ends_with("p.ron:1:5001"), "{text}");
        let (shown, carets) = (lines[3], lines[4]);
        assert!(shown.len() < 140 && shown.contains("...a") && shown.ends_with("b..."), "{text}");
        assert_eq!(shown.find('X'), carets.find('^'), "{text}");
        // Near the start, nothing is cut before.
        let text = Diagnostic::error("here", Span::new(id, 3, 4)).render(&s);
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[3].starts_with("1 | aaa") && lines[3].ends_with("..."), "{text}");
        assert_eq!(lines[4].find('^'), Some("1 | aaa".len()), "{text}");
    }

    #[test]
    fn suggests_close_names_only() {
        assert_eq!(did_you_mean("min_dept", ["min_depth", "border"]), Some("min_depth"));
        assert_eq!(did_you_mean("zzz", ["min_depth", "border"]), None);
    }
}
