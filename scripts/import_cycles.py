"""Import cycles between jaxbody's modules, including those that pass through a package's ``__init__``.

Every import counts, at module level or inside a function. An import of a module's own ancestor package
is ignored (a submodule reading its package), but a package's imports of its children are kept, so a
cycle such as ``a/__init__ -> a.x -> b -> a`` is found. Run from the repository root:
``.venv/bin/python scripts/import_cycles.py`` (exit status 1 when a cycle exists).
"""
import ast, os, sys
from collections import defaultdict
ROOT="jaxbody"
files={}
for dp,_,fs in os.walk(ROOT):
    for f in fs:
        if f.endswith(".py"):
            p=os.path.join(dp,f); m=os.path.relpath(p)[:-3].replace(os.sep,".")
            if m.endswith(".__init__"): m=m[:-9]
            files[m]=p
mods=set(files)
def owner(n):
    while n and n not in mods: n=n.rpartition(".")[0]
    return n
g=defaultdict(set)
for m,p in files.items():
    t=ast.parse(open(p).read()); ispkg=p.endswith("__init__.py")
    for n in ast.walk(t):
        if isinstance(n,ast.ImportFrom):
            if n.level:
                parts=m.split("."); base=parts if ispkg else parts[:-1]; base=base[:len(base)-(n.level-1)]
                b=".".join(base+([n.module] if n.module else []))
            else: b=n.module or ""
            if not b.startswith(ROOT): continue
            for a in n.names:
                full=f"{b}.{a.name}"
                tgt = full if full in mods else owner(b)
                if tgt and tgt!=m and not m.startswith(tgt+".") : g[m].add(tgt)
        elif isinstance(n,ast.Import):
            for a in n.names:
                if a.name.startswith(ROOT):
                    tgt=owner(a.name)
                    if tgt and tgt!=m and not m.startswith(tgt+"."): g[m].add(tgt)
# package -> child edges kept (real), child -> own ancestor package dropped
sys.setrecursionlimit(10000)
idx={};low={};st=[];on=set();comps=[];c=[0]
def sc(v):
    idx[v]=low[v]=c[0];c[0]+=1;st.append(v);on.add(v)
    for w in g.get(v,()):
        if w not in idx: sc(w);low[v]=min(low[v],low[w])
        elif w in on: low[v]=min(low[v],idx[w])
    if low[v]==idx[v]:
        comp=[]
        while True:
            w=st.pop();on.discard(w);comp.append(w)
            if w==v:break
        if len(comp)>1: comps.append(sorted(comp))
for v in sorted(mods):
    if v not in idx: sc(v)
for cc in comps: print("cycle:", " ".join(cc))
print(len(comps), "import cycles")
sys.exit(1 if comps else 0)
