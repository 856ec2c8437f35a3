#!/usr/bin/env python3
"""Module cycles of the workspace's crates: which module files name each other, both ways.

Reads every `crate::a::b` and `super::a` path outside comments and tests (`#[cfg(test)]` modules
and `*tests.rs` files; grouped imports `use crate::{a::x, b::y}` are split, one level deep), maps it to the module
file it names (the longest existing module prefix), and prints the strongly connected components
with more than one module, at two levels: module files, and each crate's top-level modules.
Exits 1 when it finds any. It also lists, as information, each place where one stage family (a
top-level module whose mod.rs declares `stage_modules!`) names another.

    python3 scripts/module_cycles.py [crate_src_dir ...]   (default: every crate of the workspace)
"""
import os, re, sys
from collections import defaultdict

def modules(src):
    """module path (tuple) -> file, for one crate's src/."""
    out = {}
    for root, _, files in os.walk(src):
        for f in files:
            if not f.endswith('.rs'):
                continue
            rel = os.path.relpath(os.path.join(root, f), src)[:-3].split(os.sep)
            if rel[-1] in ('mod', 'lib', 'main'):
                rel = rel[:-1]
            out[tuple(rel)] = os.path.join(root, f)
    return out

def code_lines(path):
    """The file's lines outside comments and `#[cfg(test)] mod` blocks."""
    text = open(path).read()
    lines, skip_depth, depth, pending_test = [], None, 0, False
    for line in text.split('\n'):
        stripped = line.strip()
        if stripped.startswith('//'):
            continue
        if stripped.startswith('#[cfg(test)]'):
            pending_test = True
            continue
        opens, closes = line.count('{'), line.count('}')
        if pending_test and re.match(r'(pub(\(\w+\))? )?mod ', stripped) and '{' in line:
            skip_depth = depth
        pending_test = pending_test and not re.match(r'(pub(\(\w+\))? )?mod ', stripped)
        if skip_depth is None:
            lines.append(line)
        depth += opens - closes
        if skip_depth is not None and depth <= skip_depth:
            skip_depth = None
    return lines

def paths_in(line):
    """(head, [names]) of every `crate::`/`super::` path of a line; `crate::a::{b, c::d}` gives
    one path per leaf (the first name of each)."""
    out = []
    for m in re.finditer(r'\b(crate|super(?:::super)*)((?:::\w+)*)::\{([^{}]*)\}', line):
        prefix = m.group(2).split('::')[1:]
        for item in m.group(3).split(','):
            item = item.strip()
            if item and item != 'self':
                out.append((m.group(1), prefix + re.findall(r'\w+', item.split(' as ')[0])[:1]))
            elif item == 'self':
                out.append((m.group(1), prefix))
    rest = re.sub(r'\b(crate|super(?:::super)*)((?:::\w+)*)::\{[^{}]*\}', '', line)
    for m in re.finditer(r'\b(crate|super(?:::super)*)((?:::\w+)+)', rest):
        out.append((m.group(1), m.group(2).split('::')[1:]))
    return out

def edges(src):
    mods = modules(src)
    graph = defaultdict(set)
    for mod, path in mods.items():
        if os.path.basename(path).endswith('tests.rs') or 'testing' in os.path.basename(path):
            continue
        for line in code_lines(path):
            for head, parts in paths_in(line):
                if head == 'crate':
                    base = ()
                else:
                    base = mod[:len(mod) - head.count('super')]
                target = base + tuple(parts)
                while target and target not in mods:
                    target = target[:-1]
                if not target or target == mod:
                    continue
                # A parent naming its children (or a child its parent's items) is the tree itself.
                if target[:len(mod)] == mod or mod[:len(target)] == target:
                    continue
                graph[mod].add(target)
    return graph

def sccs(graph):
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]
    def visit(v):
        index[v] = low[v] = n[0]; n[0] += 1; stack.append(v); on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w); low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop(); on.discard(w); comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))
    sys.setrecursionlimit(10000)
    for v in list(graph):
        if v not in index:
            visit(v)
    return out

def main():
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    srcs = sys.argv[1:] or sorted(
        os.path.join(r, 'src') for r, d, f in os.walk(here)
        if 'Cargo.toml' in f and os.path.isdir(os.path.join(r, 'src')) and '/target' not in r and '/.' not in r)
    found = 0
    for src in srcs:
        g = edges(src)
        name = os.path.relpath(src, here)
        families = {m[0] for m, p in modules(src).items()
                    if len(m) == 1 and p.endswith('mod.rs') and 'stage_modules!' in open(p).read()}
        for a in sorted(g):
            for b in sorted(g[a]):
                if a[0] in families and b[0] in families and a[0] != b[0]:
                    print(f"{name}: family use (information): {'::'.join(a)} -> {'::'.join(b)}")
        for comp in sccs(g):
            found += 1
            print(f"{name}: module cycle: {' <-> '.join('::'.join(c) for c in comp)}")
        families = defaultdict(set)
        for a, bs in g.items():
            for b in bs:
                if a[0] != b[0]:
                    families[(a[0],)].add((b[0],))
        for comp in sccs(families):
            found += 1
            print(f"{name}: family cycle: {' <-> '.join(c[0] for c in comp)}")
    print(f"{len(srcs)} crates, {found} cycle(s)")
    sys.exit(1 if found else 0)

main()
