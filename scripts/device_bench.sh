#!/usr/bin/env bash
# The GPU's figures in one run: the CUDA variant's tests (`pytest -m gpu`, and the render tests
# on it), `wai bench render` on cuda_ad_rgb, `wai dataset` throughput at 800x600 and 1600x1200, `wai experiment validate`
# at full spp, and inverse rendering's loss evaluations (`wai bench restore --method
# inverse-rendering`, Dr.Jit on CUDA); one table printed, the figures in OUT/device_bench.json (OUT: $1, else $OUT,
# else ./device_bench). Without a CUDA device it prints one "no GPU" line and exits 0.
#
# Python: $PYTHON, else .venv/bin/python, else python3 (on a bare GPU machine, the packages
# carried as docs/results.md "On a GPU" says, with PYTHONPATH set to them).
set -uo pipefail
cd "$(dirname "$0")/.."
py="${PYTHON:-}"
if [[ -z "$py" ]]; then
    if [[ -x .venv/bin/python ]]; then py=.venv/bin/python; else py=python3; fi
fi
out="${1:-${OUT:-device_bench}}"

why=$("$py" - <<'PY' 2>&1
import sys
try:
    import drjit as dr
except Exception as exc:  # noqa: BLE001 - any failure to load means no GPU here
    print(f"Dr.Jit does not load ({type(exc).__name__}: {exc})")
    sys.exit(1)
if not dr.has_backend(dr.JitBackend.CUDA):
    print("Dr.Jit finds no CUDA device")
    sys.exit(1)
PY
)
if [[ $? -ne 0 ]]; then
    echo "no GPU: ${why##*$'\n'}; nothing measured"
    exit 0
fi

mkdir -p "$out"
wai() { "$py" -c "import sys; from wai.cli import main; sys.exit(main())" "$@"; }
step() {  # step NAME LIMIT_S COMMAND...: run, keep its output and wall time
    local name=$1 limit=$2; shift 2
    local t0=$SECONDS
    timeout "$limit" "$@" > "$out/$name.log" 2>&1
    echo "$name $? $((SECONDS - t0))" >> "$out/steps.txt"
}
: > "$out/steps.txt"
export -f wai
export py
step tests 150 "$py" -m pytest -q -x -m "gpu or not slow" tests/test_gpu.py tests/mitsuba_wai/test_render.py tests/mitsuba_wai/test_lens.py tests/mitsuba_wai/test_warp_trace.py
step render 60 bash -c 'wai bench render --variant cuda_ad_rgb --runs 10 --json'
rm -rf "$out/ds800" "$out/ds1600"
step dataset_800x600 90 bash -c "wai dataset --frames 200 --size 800x600 --out '$out/ds800' --quiet"
step dataset_1600x1200 90 bash -c "wai dataset --frames 50 --size 1600x1200 --out '$out/ds1600' --quiet"
step validate 150 bash -c "wai experiment validate --out '$out/validate'"
step inverse_rendering 120 bash -c "wai bench restore --method inverse-rendering --runs 3 --workers 1 --dir '$out/bench_ir'"

"$py" - "$out" <<'PY'
import json, re, sys
from pathlib import Path
out = Path(sys.argv[1])
rows = {}
for line in (out / "steps.txt").read_text().splitlines():
    name, rc, seconds = line.split()
    rows[name] = {"rc": int(rc), "wall_s": int(seconds)}
    text = (out / f"{name}.log").read_text(errors="replace")
    if name == "render" and rc == "0":
        try:
            rows[name]["bench"] = json.loads(text[text.index("{"):])
        except ValueError:
            pass
    m = re.search(r"([\d.]+) frames/s", text)
    if name.startswith("dataset") and m:
        rows[name]["frames_per_s"] = float(m.group(1))
    m = re.search(r"(\d+) passed", text)
    if name == "tests" and m:
        rows[name]["passed"] = int(m.group(1))
    m = re.search(r"fit to the pattern image \((\w+)\): ([\d.]+) loss evaluations, "
                  r"([\d.]+) ms each", text)
    if name == "inverse_rendering" and m:
        rows[name].update(backend=m.group(1), evaluations=float(m.group(2)),
                          ms_per_evaluation=float(m.group(3)))
(out / "device_bench.json").write_text(json.dumps(rows, indent=2))
print(f"{'step':<20}{'rc':>4}{'wall s':>8}  figure")
for name, r in rows.items():
    fig = ""
    if "frames_per_s" in r:
        fig = f"{r['frames_per_s']:.1f} frames/s"
    elif "passed" in r:
        fig = f"{r['passed']} passed"
    elif "ms_per_evaluation" in r:
        fig = (f"inverse rendering {r['ms_per_evaluation']:.1f} ms an evaluation "
               f"({r['backend']}; Mitsuba's caustic tutorial 37.6 ms an iteration)")
    elif "bench" in r:
        b = r["bench"]
        fig = f"frame pair {b.get('frame_pair_ms', float('nan')):.1f} ms"
        if "waves" in b:
            fig += (f"; waves host {b['waves']['host']['median_ms']:.1f} ms,"
                    f" device {b['waves']['device']['median_ms']:.2f} ms")
    print(f"{name:<20}{r['rc']:>4}{r['wall_s']:>8}  {fig}")
print(f"figures: {out / 'device_bench.json'}")
PY
