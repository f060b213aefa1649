#!/usr/bin/env python3
"""Fails when the modules of a crate import each other in a circle.

Usage: python3 scripts/module_cycles.py [REPO_ROOT]

Each crate's modules (one per .rs file under src/) are nodes; a `crate::a::b`, `crate::{a, b}` or
`super::x` reference outside comments and unit-test modules is an edge. A module is allowed to
name its parent's items (the parent declares it); circles between siblings are not. Crates
themselves cannot import each other in a circle (cargo refuses it), so this is the module level
of ARCHITECTURE.md's "no circles".
"""
import os, re, sys
root = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), '..')
found = 0
def modpath(crate_src, f):
    rel = os.path.relpath(f, crate_src)[:-3].split(os.sep)
    if rel[-1] in ('lib','main','mod'): rel = rel[:-1]
    return rel
for crate in sorted(os.listdir(os.path.join(root,'crates'))):
    src = os.path.join(root,'crates',crate,'src')
    files = [os.path.join(d,f) for d,_,fs in os.walk(src) for f in fs if f.endswith('.rs')]
    mods = {tuple(modpath(src,f)): f for f in files}
    graph = {m:set() for m in mods}
    for m,f in mods.items():
        text = open(f).read()
        text = re.sub(r'#\[cfg\(test\)\]\s*mod tests \{.*', '', text, flags=re.S)
        text = '\n'.join(l for l in text.split('\n') if not l.strip().startswith('//'))
        for ref in re.findall(r'crate((?:::[a-z_0-9]+)+)', text):
            parts = ref.strip(':').split('::')
            for k in range(len(parts),0,-1):
                if tuple(parts[:k]) in mods: 
                    if tuple(parts[:k]) != m and tuple(parts[:k]) != (): graph[m].add(tuple(parts[:k]))
                    break
        base = m if f.endswith('mod.rs') else m[:-1]
        for ref in re.findall(r'super((?:::[a-z_0-9]+)+)', text):
            parts = list(base) + ref.strip(':').split('::')
            for k in range(len(parts),len(base),-1):
                if tuple(parts[:k]) in mods and tuple(parts[:k]) != m: graph[m].add(tuple(parts[:k])); break
        # use of {a, b} groups under crate::
        for grp in re.findall(r'crate::\{([^}]*)\}', text):
            for name in re.findall(r'([a-z_0-9]+)(?:::|\s*[,}]|$)', grp):
                if (name,) in mods and (name,) != m: graph[m].add((name,))
    # Tarjan SCC
    index={}; low={}; st=[]; on=set(); out=[]; c=[0]
    def sc(v):
        index[v]=low[v]=c[0]; c[0]+=1; st.append(v); on.add(v)
        for w in graph[v]:
            if w not in index: sc(w); low[v]=min(low[v],low[w])
            elif w in on: low[v]=min(low[v],index[w])
        if low[v]==index[v]:
            comp=[]
            while True:
                w=st.pop(); on.discard(w); comp.append(w)
                if w==v: break
            if len(comp)>1: out.append(comp)
    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index: sc(v)
    for comp in out:
        found += 1
        print(crate, 'circle:', ' -> '.join('::'.join(x) or 'lib' for x in comp))
if found:
    sys.exit(1)
print('module_cycles: no circles')
