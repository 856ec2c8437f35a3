//! `dist4d check` on a few hundred mutated copies of the shipped pipelines: deleted, duplicated
//! and swapped tokens, huge and negative numbers, NaN, empty strings, unbalanced brackets, stray
//! bytes. Whatever the input, check must not panic or hang, must exit 0 (ok) or 2 (refused), and
//! every error it prints must say where: `file:line:column`.
//!
//! The mutations are drawn from a fixed seed, so a failure reproduces; it prints the case number
//! and the mutation, and `DIST4D_FUZZ_KEEP=DIR` keeps every mutated file in DIR.

mod common;

use common::{bin, repo};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Mutated files per shipped pipeline.
const CASES_PER_PIPELINE: usize = 160;

/// How long one `check` may take: it parses one small file, so anything near this is a hang.
const TIMEOUT: Duration = Duration::from_secs(10);

/// Errors that concern the whole file and so have no line and column, matched against the message
/// after `error: `. Only a file that cannot be read at all: an empty file is reported at 1:1, a
/// file that is not UTF-8 at its first bad byte. The other spanless diagnostics of the loader are
/// fallbacks that should never show (`the pipeline is not valid`, a cycle or params error without
/// a place): if one does, this test fails and it needs a span.
const WHOLE_FILE_ERRORS: &[&str] = &["cannot read pipeline file"];

/// splitmix64: a small deterministic generator, so that the cases are the same on every machine.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }

    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }

    /// One of `items`, or `fallback` when there are none.
    fn pick_or<T: Copy>(&mut self, items: &[T], fallback: T) -> T {
        if items.is_empty() {
            fallback
        } else {
            *self.pick(items)
        }
    }
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum Kind {
    Number,
    Str,
    Ident,
    Punct,
}

/// A token of a pipeline file: its byte range and kind (comments and blanks are not tokens).
#[derive(Clone, Copy, Debug)]
struct Token {
    start: usize,
    end: usize,
    kind: Kind,
}

/// Splits RON text into tokens, roughly: enough to cut and paste at token boundaries.
fn tokens(text: &str) -> Vec<Token> {
    let b = text.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let start = i;
        let c = b[i];
        let kind = if c.is_ascii_whitespace() {
            i += 1;
            continue;
        } else if b[i..].starts_with(b"//") {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
            continue;
        } else if c == b'"' {
            i += 1;
            while i < b.len() && b[i] != b'"' {
                i += if b[i] == b'\\' { 2 } else { 1 };
            }
            i = (i + 1).min(b.len());
            Kind::Str
        } else if c.is_ascii_digit() || (c == b'-' && b.get(i + 1).is_some_and(u8::is_ascii_digit)) {
            i += 1;
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'.' || b[i] == b'_') {
                i += 1;
            }
            Kind::Number
        } else if c.is_ascii_alphabetic() || c == b'_' {
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'_') {
                i += 1;
            }
            Kind::Ident
        } else {
            // Multi-byte UTF-8 characters stay whole.
            i += text[i..].chars().next().map_or(1, char::len_utf8);
            Kind::Punct
        };
        // An escape skipped into a multi-byte character: end at the character's end.
        while !text.is_char_boundary(i) {
            i += 1;
        }
        out.push(Token { start, end: i, kind });
    }
    out
}

const NUMBERS: &[&str] = &[
    "0",
    "-1",
    "-0.0",
    "NaN",
    "inf",
    "-inf",
    "1e308",
    "1e-320",
    "-1e308",
    "4294967296",
    "-2147483649",
    "9223372036854775807",
    "-9223372036854775808",
    "18446744073709551616",
    "99999999999999999999999999999",
    "0.000000001",
    "1_000_000_000",
];
const BRACKETS: &[&str] = &["(", ")", "[", "]", "{", "}"];
const BYTES: &[u8] = &[0x00, 0x07, 0x1B, 0x7F, 0x80, 0xC3, 0xFE, 0xFF, b'"', b'\'', b'/', b'*', b'\\', b'#', b'r'];

/// One mutation of `text`: the new bytes and what was done, for the failure message.
fn mutate(text: &str, rng: &mut Rng) -> (Vec<u8>, String) {
    let toks = tokens(text);
    if toks.len() < 2 {
        return (format!("{text}(").into_bytes(), "appended `(`".into());
    }
    let tok = *rng.pick(&toks);
    let of = |k: Kind| toks.iter().copied().filter(|t| t.kind == k).collect::<Vec<_>>();
    let splice = |t: Token, with: &str| -> Vec<u8> {
        let mut s = text[..t.start].to_string();
        s.push_str(with);
        s.push_str(&text[t.end..]);
        s.into_bytes()
    };
    let show = |t: Token| format!("`{}` at byte {}", &text[t.start..t.end], t.start);
    // Value-level mutations (3, 4, 7) are drawn twice as often: the others mostly break the syntax,
    // and the checks past the parser deserve as many cases.
    let which = match rng.below(12) {
        9 => 3,
        10 => 4,
        11 => 7,
        n => n,
    };
    match which {
        0 => (splice(tok, ""), format!("deleted {}", show(tok))),
        1 => (splice(tok, &format!("{0} {0}", &text[tok.start..tok.end])), format!("duplicated {}", show(tok))),
        2 => {
            let i = rng.below(toks.len() - 1);
            let (a, b) = (toks[i], toks[i + 1]);
            let mut s = text[..a.start].to_string();
            s.push_str(&text[b.start..b.end]);
            s.push_str(&text[a.end..b.start]);
            s.push_str(&text[a.start..a.end]);
            s.push_str(&text[b.end..]);
            (s.into_bytes(), format!("swapped {} and {}", show(a), show(b)))
        }
        3 => {
            let t = rng.pick_or(&of(Kind::Number), tok);
            let n = rng.pick(NUMBERS);
            (splice(t, n), format!("replaced {} by {n}", show(t)))
        }
        4 => {
            let t = rng.pick_or(&of(Kind::Str), tok);
            let with = *rng.pick(&["\"\"", "\"..\"", "\"/\"", "\"\\u{0}\"", "\"a\"", "\"stage.\"", "\".port\""]);
            (splice(t, with), format!("replaced {} by {with}", show(t)))
        }
        5 => {
            let brackets: Vec<Token> =
                toks.iter().copied().filter(|t| BRACKETS.contains(&&text[t.start..t.end])).collect();
            let t = rng.pick_or(&brackets, tok);
            if rng.below(2) == 0 {
                (splice(t, ""), format!("deleted bracket {}", show(t)))
            } else {
                let extra = rng.pick(BRACKETS);
                (
                    splice(t, &format!("{extra}{}", &text[t.start..t.end])),
                    format!("inserted `{extra}` before {}", show(t)),
                )
            }
        }
        6 => {
            let at = rng.below(text.len() + 1);
            // A byte inside a multi-byte character is fine: the result need not be UTF-8.
            let byte = *rng.pick(BYTES);
            let mut v = text.as_bytes().to_vec();
            v.insert(at, byte);
            (v, format!("inserted byte 0x{byte:02X} at byte {at}"))
        }
        7 => {
            let idents = of(Kind::Ident);
            let (a, b) = (rng.pick_or(&idents, tok), rng.pick_or(&idents, tok));
            (splice(a, &text[b.start..b.end]), format!("replaced {} by {}", show(a), show(b)))
        }
        _ => {
            // A token copied elsewhere: a value where a name goes, a name where a value goes.
            let other = *rng.pick(&toks);
            let with = format!("{} {}", &text[other.start..other.end], &text[tok.start..tok.end]);
            (splice(tok, &with), format!("inserted {} before {}", show(other), show(tok)))
        }
    }
}

struct Checked {
    code: Option<i32>,
    stdout: String,
    stderr: String,
    elapsed: Duration,
}

/// Runs `dist4d check path`, killing it after [`TIMEOUT`] (then `code` is `None`).
fn check(path: &Path) -> Checked {
    let t0 = Instant::now();
    let mut child = Command::new(bin())
        .args(["check", path.to_str().unwrap()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("dist4d runs");
    // The output of a check is small; reading it after the exit cannot block on a full pipe.
    let code = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status.code();
        }
        if t0.elapsed() > TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let out = child.wait_with_output().unwrap();
    Checked {
        code,
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        elapsed: t0.elapsed(),
    }
}

/// Every `error:` line of `stderr` followed by a `--> file:line:column` line, or one of the
/// [`WHOLE_FILE_ERRORS`]; the messages that are not.
fn errors_without_location(stderr: &str) -> Vec<String> {
    let lines: Vec<&str> = stderr.lines().collect();
    let located = |l: Option<&&str>| {
        l.and_then(|l| l.trim_start().strip_prefix("--> ")).is_some_and(|loc| {
            let mut parts = loc.rsplitn(3, ':');
            let (col, line) = (parts.next(), parts.next());
            parts.next().is_some_and(|file| !file.is_empty())
                && [col, line].iter().all(|n| n.is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit())))
        })
    };
    lines
        .iter()
        .enumerate()
        .filter_map(|(i, l)| l.strip_prefix("error: ").map(|m| (i, m)))
        .filter(|(i, m)| !located(lines.get(i + 1)) && !WHOLE_FILE_ERRORS.iter().any(|w| m.starts_with(w)))
        .map(|(_, m)| m.to_string())
        .collect()
}

/// What is wrong with the outcome of one check, if anything.
fn judge(c: &Checked) -> Option<String> {
    if c.code.is_none() && c.elapsed >= TIMEOUT {
        return Some(format!("no answer within {TIMEOUT:?}"));
    }
    if c.stderr.contains("panicked") || c.code == Some(101) {
        return Some(format!("panicked (exit {:?}):\n{}", c.code, c.stderr));
    }
    match c.code {
        Some(0) if c.stdout.contains(": ok (") => None,
        Some(0) => Some(format!("exit 0 without `ok`:\n{}{}", c.stdout, c.stderr)),
        Some(2) => {
            let bare = errors_without_location(&c.stderr);
            if !c.stderr.contains("error: ") {
                Some(format!("exit 2 without an error:\n{}", c.stderr))
            } else if !bare.is_empty() {
                Some(format!("errors without file:line:column: {bare:?}\n{}", c.stderr))
            } else {
                None
            }
        }
        other => Some(format!("exit {other:?} (want 0 or 2):\n{}{}", c.stdout, c.stderr)),
    }
}

fn shipped() -> Vec<PathBuf> {
    let mut all: Vec<PathBuf> = std::fs::read_dir(repo().join("pipelines"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "ron"))
        .collect();
    all.sort();
    assert!(!all.is_empty(), "no shipped pipelines");
    all
}

#[test]
fn check_survives_mutated_pipelines_and_locates_every_error() {
    let t0 = Instant::now();
    let tmp = tempfile::tempdir().unwrap();
    let dir = std::env::var_os("DIST4D_FUZZ_KEEP").map(PathBuf::from).unwrap_or_else(|| tmp.path().to_path_buf());
    std::fs::create_dir_all(&dir).unwrap();
    let mut rng = Rng(0x00d1_5744_d000_0013);
    let (mut failures, mut refused, mut ran) = (Vec::new(), 0, 0);
    for pipeline in shipped() {
        let text = std::fs::read_to_string(&pipeline).unwrap();
        let stem = pipeline.file_stem().unwrap().to_string_lossy().into_owned();
        for case in 0..CASES_PER_PIPELINE {
            // One or two mutations on top of each other.
            let mut bytes = text.clone().into_bytes();
            let mut what = Vec::new();
            for _ in 0..1 + rng.below(2) {
                let current = String::from_utf8_lossy(&bytes).into_owned();
                let (b, w) = mutate(&current, &mut rng);
                bytes = b;
                what.push(w);
            }
            // Written beside the others, so that relative paths in it resolve the same way.
            let path = dir.join(format!("{stem}-{case:03}.ron"));
            std::fs::write(&path, &bytes).unwrap();
            let c = check(&path);
            ran += 1;
            refused += (c.code == Some(2)) as usize;
            if let Some(problem) = judge(&c) {
                failures.push(format!("{stem} case {case} ({}): {problem}", what.join("; ")));
            }
        }
    }
    eprintln!("{ran} mutated pipelines checked in {:.1}s, {refused} refused", t0.elapsed().as_secs_f64());
    assert!(failures.is_empty(), "{} of {ran} cases failed:\n\n{}", failures.len(), failures.join("\n\n"));
    // The mutations must mostly break the file, or the test proves little.
    assert!(refused * 2 > ran, "only {refused} of {ran} mutated pipelines were refused");
}

/// Inputs that crashed `check` once, kept as fixed cases.
#[test]
fn known_crashers_are_diagnostics() {
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo().join("pipelines/lidar_depth.ron")).unwrap();
    // An exported stage with a grain its kind refuses: the export template was read against grain 0.
    let from = r#""encode": EncodeDepth("#;
    assert_eq!(text.matches(from).count(), 1);
    let path = tmp.path().join("bad_grain.ron");
    std::fs::write(&path, text.replace(from, &format!("{from}grain: nosuch, "))).unwrap();
    let c = check(&path);
    assert_eq!(judge(&c), None);
    assert_eq!(c.code, Some(2), "{}", c.stderr);
    assert!(c.stderr.contains("cannot run per `nosuch`"), "{}", c.stderr);
}
