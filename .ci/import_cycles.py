#!/usr/bin/env python3
"""Import cycles between modules of src/ (one node per file), from `use crate::`,
`use super::` and inline `crate::a::b` / `super::x` paths."""
import os, re, sys
args = [a for a in sys.argv[1:] if not a.startswith('--')]
root = args[0] if args else 'src'
mods = {}
for d, _, fs in os.walk(root):
    for f in fs:
        if not f.endswith('.rs'): continue
        p = os.path.join(d, f)
        rel = os.path.relpath(p, root)[:-3].split(os.sep)
        if rel[-1] in ('mod', 'lib', 'main'): rel = rel[:-1]
        mods[tuple(rel)] = p
def resolve(cur, path):
    # cur: module path tuple of file; path: list of segments after crate/super
    best = None
    for n in range(len(path), 0, -1):
        if tuple(path[:n]) in mods: return tuple(path[:n])
    return None
edges = {m: set() for m in mods}
for m, p in mods.items():
    src = open(p).read()
    src = re.sub(r'(?s)#\[cfg\(test\)\]\s*mod tests.*', '', src)  # test modules do not count
    src = re.sub(r'//[^\n]*', '', src)
    for mt in re.finditer(r'\b((?:crate|super)(?:::(?:super|[A-Za-z_][A-Za-z0-9_]*))*)(?:::\{([^;]*?)\})?', src):
        segs = mt.group(1).split('::')
        if segs[0] == 'crate':
            base = []; segs = segs[1:]
        else:
            base = list(m)
            while segs and segs[0] == 'super':
                base = base[:-1]; segs = segs[1:]
        groups = [segs]
        if mt.group(2):
            for item in re.split(r',', mt.group(2)):
                item = item.strip().split('::')[0].strip()
                if item and item != 'self': groups.append(segs + [item])
        pass
        for g in groups:
            t = resolve(m, base + g)
            if t is not None and t != m and not (len(t) < len(m) and m[:len(t)] == t and len(base + g) == len(t)):
                edges[m].add(t)
# Paths relative to the file's own child modules (`worker::spawn` in daemon/mod.rs).
for m, p in mods.items():
    src = open(p).read()
    src = re.sub(r'(?s)#\[cfg\(test\)\]\s*mod tests.*', '', src)
    src = re.sub(r'//[^\n]*', '', src)
    children = set(re.findall(r'^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+([a-z_][a-z0-9_]*)\s*;', src, re.M))
    for c in children:
        if re.search(r'(?<![A-Za-z0-9_:])' + c + r'::', src) and m + (c,) in mods:
            edges[m].add(m + (c,))
# a module's own parent is the module that declares it: `use super::Item` of an item
# defined in the parent *is* an edge (parent -> child by declaration makes it a cycle).
decl = {m: {c for c in mods if len(c) == len(m) + 1 and c[:len(m)] == m} for m in mods}
strict = '--strict' in sys.argv
if not strict:
    # A module and its own descendants are one unit (a parent re-exporting or calling its
    # private child modules, children using their parent's items): only edges between
    # modules neither of which contains the other are import edges here.
    for m in edges:
        edges[m] = {t for t in edges[m] if not (t[:len(m)] == m or m[:len(t)] == t)}
# Tarjan SCC
idx = {}; low = {}; st = []; on = set(); out = []; i = [0]
sys.setrecursionlimit(10000)
def sc(v):
    idx[v] = low[v] = i[0]; i[0] += 1; st.append(v); on.add(v)
    for w in edges[v]:
        if w not in idx: sc(w); low[v] = min(low[v], low[w])
        elif w in on: low[v] = min(low[v], idx[w])
    if low[v] == idx[v]:
        comp = []
        while True:
            w = st.pop(); on.discard(w); comp.append(w)
            if w == v: break
        if len(comp) > 1: out.append(comp)
for v in mods:
    if v not in idx: sc(v)
n_edges = sum(len(e) for e in edges.values())
print(f"{len(mods)} modules, {n_edges} import edges")
for c in out:
    print("cycle:", sorted('::'.join(x) or 'crate' for x in c))
print("no import cycles" if not out else f"{len(out)} cycle(s)")
