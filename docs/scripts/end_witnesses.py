#!/usr/bin/env python3
"""How well each witness of a pose ranks the alignment ends of `asgreg eval --diagnose`
(docs/measurements.md, twenty-seventh session).

Per frame, the candidates are the output and the ends of the refinement's short schedule run
from every view's refined pose (`short_from_hypothesis`). Prints, per cell: mean δ (each frame
capped at 25 px) and frames within 2 / 5 px when each frame takes the candidate a rule picks
(the output; the most edge support; the highest region contrast at 6 or 12 px; the product;
the oracle), how many pairs (an end within 2 px, another 4 px or more off) each witness ranks
the right way, and on frames whose output is more than 3 px off, whether the truth's region
contrast exceeds the output's.

Usage: python3 docs/scripts/end_witnesses.py OUT/diagnosis.json [...]"""
import json, sys
CAP = 25.0
def value(candidate, witness):
    """A candidate's value for a witness: None = edge support, 0/1 = region contrast band,
    "c" = correlation, "c3"/"c6" = the coarse correlations."""
    if witness is None:
        return candidate["support"]
    if witness == "c":
        return candidate.get("corr")
    if witness in ("c3", "c6"):
        return (candidate.get("cc") or [None, None])[0 if witness == "c3" else 1]
    return candidate["rc"][witness]
def g(d, *ks):
    for k in ks:
        if d is None: return None
        d = d.get(k) if isinstance(d, dict) else None
    return d
for path in sys.argv[1:]:
    with open(path) as file:
        doc = json.load(file)
    for cell in doc["cells"]:
        rows = []
        t_vs_o = []
        for fr in cell["frames"]:
            d = fr["diagnosis"]
            out_delta = d.get("chosen_delta_px")
            ev = d.get("evidence") or {}
            out_support = g(ev, "edges", "at_pose")
            out_rc = d.get("output_region_contrast") or [None, None]
            cands = []
            if out_delta is not None:
                cands.append(dict(delta=out_delta, support=out_support or 0, rc=out_rc, who="out"))
            for v in d["views"]:
                e = v.get("short_from_hypothesis")
                if e and e.get("delta_px") is not None:
                    cands.append(dict(delta=e["delta_px"], support=e["support"], rc=e.get("region_contrast") or [None, None], corr=e.get("correlation"), cc=e.get("coarse_correlation") or [None, None], who="end"))
            if not cands: continue
            trc = d.get("truth_region_contrast") or [None, None]
            if out_rc[0] is not None and trc[0] is not None:
                t_vs_o.append((fr["name"], out_delta, out_rc[0], trc[0], out_rc[1], trc[1]))
            rows.append((fr["name"], cands))
        def score(rule):
            ds = []
            for name, cands in rows:
                c = rule(cands)
                ds.append(min(c["delta"], CAP))
            n = max(len(ds), 1)
            return f"{sum(ds)/n:6.2f}; {sum(x<=2 for x in ds):2d} / {sum(x<=5 for x in ds):2d}"
        rules = {
            "output": lambda cs: cs[0],
            "max support": lambda cs: max(cs, key=lambda c: c["support"]),
            "max rc6": lambda cs: max(cs, key=lambda c: c["rc"][0] if c["rc"][0] is not None else -1),
            "max rc12": lambda cs: max(cs, key=lambda c: c["rc"][1] if c["rc"][1] is not None else -1),
            "max support*rc6": lambda cs: max(cs, key=lambda c: c["support"]*(c["rc"][0] or 0)),
            "max correlation σ3": lambda cs: max(cs, key=lambda c: value(c, "c3") if value(c, "c3") is not None else -2),
            "oracle": lambda cs: min(cs, key=lambda c: c["delta"]),
        }
        print(f"== {path} level {cell['level_px']} frames {len(rows)}")
        for k, r in rules.items():
            print(f"  {k:18s} {score(r)}")
        # pairwise: among ends of the same frame, pairs where one is <2px and the other >4px:
        # how often does each witness rank the good one higher
        for wi, wname in [(None, "support"), (0, "rc6"), (1, "rc12"), ("c", "correlation σ1"), ("c3", "correlation σ3"), ("c6", "correlation σ6")]:
            good = tot = 0
            for name, cands in rows:
                for a in cands:
                    for b in cands:
                        if a["delta"] <= 2 and b["delta"] >= 4:
                            va, vb = (value(a, wi), value(b, wi))
                            if va is None or vb is None: continue
                            tot += 1; good += va > vb
            print(f"  pairs good<=2 vs bad>=4 ranked right by {wname}: {good}/{tot}")
        n_up = sum(1 for t in t_vs_o if t[1] is not None and t[1] > 3 and t[3] > t[2])
        n_off = sum(1 for t in t_vs_o if t[1] is not None and t[1] > 3)
        print(f"  truth rc6 > output rc6 on frames off >3px: {n_up}/{n_off}")
        for t in t_vs_o:
            if t[1] is not None and t[1] > 3:
                print("   ", t[0], f"out δ {t[1]:.1f} rc6 out {t[2]:.3f} truth {t[3]:.3f} | rc12 {t[4]:.3f} {t[5]:.3f}")
