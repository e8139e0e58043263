"""The fresh-seed table of docs/RESULTS.md from scripts/dev/confirm.sh's runs."""
import glob
import json
import os
import statistics as st
import sys
os.chdir(sys.argv[1] if len(sys.argv) > 1 else 'runs/confirm')
def last(p):
    return json.loads(open(p).read().strip().splitlines()[-1])
def pick(prefix, kind):
    fs=[f for f in glob.glob(prefix) if kind in f or (kind == '400' and 'uniform400' in f)]
    return last(fs[0]) if fs else None
rows=[]; ratios=[]; gaps=[]
for s in range(5):
    d=f'default-s{s}'; l=f'lfp-s{s}'
    if not os.path.exists(d+'.done'): continue
    lu=pick(d+'.eval_lfp_*','400'); fu=pick(d+'.eval_final_*','400'); le=pick(d+'.eval_lfp_*','edges'); fe=pick(d+'.eval_final_*','edges')
    tr=last(d+'.train.json')
    L=pick(l+'.eval_final_*','400') if os.path.exists(l+'.done') else None
    Le=pick(l+'.eval_final_*','edges') if os.path.exists(l+'.done') else None
    r=fu['within_30cm']/lu['within_30cm']; ratios.append(r)
    if L: gaps.append(fu['within_30cm']-L['within_30cm'])
    f=lambda x: f"{100*x:.1f}%"
    rows.append(f"| {s} | {f(lu['within_30cm'])} | {f(fu['within_30cm'])} / {f(fu['within_20cm'])} | **{r:.2f}x** | "
                f"{(f(L['within_30cm'])+' / '+f(L['within_20cm'])) if L else 'not run'} | {f(le['within_30cm'])} -> {f(fe['within_30cm'])} | "
                f"{f(Le['within_30cm']) if Le else 'not run'} | {f(tr['eval_within_30cm'])} |")
print("| seed | LFP point, 400 uniform goals, <= 30 cm | new default at 7,000, <= 30 / 20 cm | final / LFP point | LFP at equal updates (8,000), <= 30 / 20 cm | edges-and-net goals (200), LFP point -> final | edges-and-net, LFP at equal updates | in-run final evaluation (200 goals) |")
print("| --- | --- | --- | --- | --- | --- | --- | --- |")
print("\n".join(rows))
print(f"\nratios {ratios} mean {st.mean(ratios):.3f}; gaps vs lfp {gaps}")
