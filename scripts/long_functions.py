#!/usr/bin/env python3
"""The longest functions of some Rust files: `fn` items, their line counts (signature to closing
brace), longest first. Tests (`#[cfg(test)]` modules, `*tests.rs`) are left out.

    python3 scripts/long_functions.py [--over N] PATH...   (files or folders)
"""
import os, re, sys

def functions(path):
    lines = open(path).read().split('\n')
    out, i, test_depth, depth = [], 0, None, 0
    pending_test = False
    while i < len(lines):
        line = lines[i]
        s = line.strip()
        if s.startswith('#[cfg(test)]'):
            pending_test = True
        m = re.match(r'\s*(pub(\(\w+\))? )?(const )?(async )?(unsafe )?fn (\w+)', line)
        if m and test_depth is None and not s.startswith('//'):
            # Find the body's opening brace, then its match.
            j, d, started = i, 0, False
            while j < len(lines):
                code = re.sub(r'"(\\.|[^"\\])*"', '""', lines[j].split('//')[0])
                code = re.sub(r"'(\\.|[^'\\])'", "''", code)
                for c in code:
                    if c == '{':
                        d += 1; started = True
                    elif c == '}':
                        d -= 1
                if started and d == 0:
                    break
                if not started and code.rstrip().endswith(';'):
                    break
                j += 1
            if started:
                out.append((j - i + 1, path, i + 1, m.group(6)))
        code = re.sub(r'"(\\.|[^"\\])*"', '""', line.split('//')[0])
        if pending_test and re.match(r'(pub(\(\w+\))? )?mod ', s):
            test_depth = depth
            pending_test = False
        depth += code.count('{') - code.count('}')
        if test_depth is not None and depth <= test_depth and '}' in code:
            test_depth = None
        i += 1
    return out

def main():
    args = sys.argv[1:]
    over = 0
    if args[:1] == ['--over']:
        over, args = int(args[1]), args[2:]
    files = []
    for a in args:
        if os.path.isdir(a):
            for r, _, fs in os.walk(a):
                files += [os.path.join(r, f) for f in fs if f.endswith('.rs') and not f.endswith('tests.rs')]
        else:
            files.append(a)
    found = sorted((f for p in files for f in functions(p)), reverse=True)
    for n, p, line, name in found:
        if n > over:
            print(f"{n:5} {p}:{line} {name}")

main()
