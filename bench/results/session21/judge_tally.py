# Tallies judge.py's trials: one step along the selection path, each rule's wrong joins and refusals.
# Usage: bench/.venv/bin/python bench/results/session21/judge_tally.py trials.jsonl
import json, sys, collections, numpy as np
rows=[json.loads(l) for l in open(sys.argv[1])]
by=collections.defaultdict(list)
for r in rows: by[r['case']].append(r)
pts=[]
for c,rs in by.items():
    kept=None
    for r in rs:
        if r['bar'] is None: kept=r; continue
        dq=r['q']-r['bar']
        d={k: 10*np.log10(kept[k]/r[k]) for k in ('g15','g30','g60')}
        pts.append(dict(c=c, v=r['views'], dq=dq, dp=r['psnr']-kept['psnr'], **d))
        if dq >= -0.005: kept=r
P=pts
print("n", len(P))
def score(decide, name):
    # loss = sum of |dp| for wrong decisions where |dp|>0.1
    wrong=[p for p in P if (decide(p) != (p['dp']>0)) and abs(p['dp'])>0.1]
    bad_join=[p for p in wrong if decide(p)]; bad_refuse=[p for p in wrong if not decide(p)]
    print(f"{name:28s} wrong {len(wrong):3d} (joins that lose {len(bad_join)}: {sum(-p['dp'] for p in bad_join):.2f} dB; refusals that lose {len(bad_refuse)}: {sum(p['dp'] for p in bad_refuse):.2f} dB); joins>0.3 loss: {sum(p['dp']<-0.3 for p in bad_join)}")
score(lambda p: p['dq']>=-0.005, "head (q, margin .005)")
score(lambda p: p['dq']>=0, "q margin 0")
score(lambda p: p['dq']>=0.005, "q margin -.005")
for k in ('g15','g30','g60'):
    for m in (0, 0.02, 0.05, 0.1):
        score(lambda p, k=k, m=m: p[k]>=m, f"{k} >= {m}")
    score(lambda p, k=k: (p['dq']>=0.005) or (p['dq']>=-0.005 and p[k]>=0), f"q band, tie by {k}")
    score(lambda p, k=k: (p['dq']>=-0.005) and p[k]>=0, f"q >= -.005 and {k}>=0")
    score(lambda p, k=k: (p['dq']>=-0.005) and p[k]>=-0.05, f"q >= -.005 and {k}>=-0.05")
print()
for p in sorted(P, key=lambda p: p['dp']):
    if abs(p['dp'])>0.3: print(f"{p['c']:28s} {str(p['v']):14s} dp {p['dp']:+6.2f} dq {p['dq']:+.4f} g15 {p['g15']:+.3f} g30 {p['g30']:+.3f} g60 {p['g60']:+.3f}")
