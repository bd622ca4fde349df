#!/usr/bin/env python3
"""Module dependency graph of src/ (`crate::` and `super::` paths as edges) and its cycles:
  python3 tools/module_cycles.py src 1   # top-level modules; 2 for their submodules
"""
import os, re, sys
root = sys.argv[1] if len(sys.argv) > 1 else 'src'
level = int(sys.argv[2]) if len(sys.argv) > 2 else 1
def modname(path):
    rel = os.path.relpath(path, root)[:-3].split(os.sep)
    if rel[-1] in ('mod', 'lib', 'main'): rel = rel[:-1]
    return tuple(rel)
files = [os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs if f.endswith('.rs')]
mods = {modname(f): f for f in files}
def key(m): return '::'.join(m[:level]) or 'crate'
edges = {}
for m, f in mods.items():
    text = open(f).read()
    text = text.split('#[cfg(test)]')[0]
    text = re.sub(r'//.*', '', text)
    deps = set()
    for g in re.finditer(r'crate::([a-z_][a-z0-9_]*(?:::[a-z_][a-z0-9_]*)*)', text):
        parts = tuple(g.group(1).split('::'))
        # longest module prefix
        for n in range(len(parts), 0, -1):
            if parts[:n] in mods: deps.add(parts[:n]); break
    for g in re.finditer(r'\bsuper::([a-z_][a-z0-9_]*)', text):
        parent = m[:-1] if not f.endswith('mod.rs') else m[:-1]
        cand = parent + (g.group(1),)
        if cand in mods: deps.add(cand)
        else: deps.add(parent)
    a = key(m)
    for d in deps:
        b = key(d)
        if a != b and b != 'crate': edges.setdefault(a, set()).add(b)
# SCCs (Tarjan)
index = {}; low = {}; stack = []; on = set(); sccs = []; i = [0]
nodes = set(edges) | {b for bs in edges.values() for b in bs}
def strong(v):
    index[v] = low[v] = i[0]; i[0] += 1; stack.append(v); on.add(v)
    for w in edges.get(v, ()):
        if w not in index: strong(w); low[v] = min(low[v], low[w])
        elif w in on: low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        c = []
        while True:
            w = stack.pop(); on.discard(w); c.append(w)
            if w == v: break
        if len(c) > 1: sccs.append(sorted(c))
sys.setrecursionlimit(10000)
for v in sorted(nodes):
    if v not in index: strong(v)
for c in sccs: print('cycle:', ' <-> '.join(c))
print(len(sccs), 'cycles among', len(nodes), 'modules at level', level)
if '-v' in sys.argv:
    for a in sorted(edges): print(a, '->', ', '.join(sorted(edges[a])))
sys.exit(1 if sccs else 0)
