"""Per-call cost of the Python module against the CLI (docs/BENCHMARKS.md): run from the
repository root with the release binary built and the release wheel installed."""
import time, subprocess, shutil, statistics, sys
t0=time.perf_counter(); import posediff; t_import=time.perf_counter()-t0
sets={'temple':'../shared/data/middlebury_templeSR/images','apple':'../shared/data/co3d_apple_posediffusion/images'}
for name,folder in sets.items():
    cli=[];py=[];est=[]
    for k in range(3):
        shutil.rmtree('/tmp/ovh',ignore_errors=True)
        t=time.perf_counter(); subprocess.run(['target/release/posediff','estimate',folder,'--out','/tmp/ovh/cli','--quiet','--no-view'],check=True); cli.append(time.perf_counter()-t)
        t=time.perf_counter(); rec=posediff.estimate(folder,progress=False); t1=time.perf_counter(); rec.write('/tmp/ovh/py'); py.append(time.perf_counter()-t); est.append(t1-t)
    print(f"{name}: CLI {statistics.median(cli):.3f} s, Python estimate+write {statistics.median(py):.3f} s (estimate {statistics.median(est):.3f} s); difference {statistics.median(py)-statistics.median(cli):+.3f} s")
print(f"import posediff {t_import*1000:.0f} ms")
