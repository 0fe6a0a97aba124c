#!/usr/bin/env bash
# posediff's network on a device, checked and timed in one go (issue 21).
#
# Here (the CPU machine), after `cargo xtask cuda-build`:
#   scripts/device_check.sh stage [--binary target/cuda-build/posediff] [--shared ../shared] [--dir target/device]
# copies what travels to the GPU machine into the ignored folder target/device: the binary
# (xz-compressed: 68 MB of it are CUDA kernels and their PTX), the tiny fixtures' official
# outputs (the tiny model itself travels in the tree as fixtures/torch/model_tiny_module_prefix.pth,
# the same values; the full model is 78 MB, over the 64 MiB a call carries, so the timed
# official-size network is initialised there instead) and the 20 apple frames with their cameras.
#
# There (the device tool, carry ["target/device"]):
#   bash scripts/device_check.sh run --device cuda --out $OUT
# runs, well inside 10 minutes:
#   1. `posediff device-check`: the F32 parity checks (backbone, denoiser, sampling teacher-forced)
#      against the official outputs, timings of the backbone (1/10/20/100 images), one denoiser
#      step and the 100-step sampling, BF16/F16 against F32, and the training iteration of the
#      tiny and official presets;
#   2. `posediff estimate --device cuda` on the 20 apple frames with a random-weight
#      official-size checkpoint (GGS on real SIFT matches), and `posediff score` against the
#      ground truth (random weights: the accuracy is not the point, the run and its times are);
#   3. when python3 has torch: the official network in PyTorch on the same device
#      (`scripts/network_torch.py`, checked against the official outputs first), with the
#      official training iteration;
# and writes OUT/report.md and OUT/report.json (plus each step's own files).
#
# `run --device cpu` runs the same checks on the CPU (`--quick`: small sizes, for the tests).
# The CUDA libraries are found through LD_LIBRARY_PATH, set here from python3's
# nvidia/cu13/lib (PyTorch's CUDA wheels) and the usual driver and toolkit folders.
set -euo pipefail

mode=${1:-}
shift || true
root=$(cd "$(dirname "$0")/.." && pwd)
dir=$root/target/device
binary=""
shared=$root/../shared
device=cpu
out=""
quick=0
pytorch=auto

while [ $# -gt 0 ]; do
  case $1 in
    --binary) binary=$2; shift 2 ;;
    --shared) shared=$2; shift 2 ;;
    --dir) dir=$2; shift 2 ;;
    --device) device=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --quick) quick=1; shift ;;
    --no-pytorch) pytorch=no; shift ;;
    *) echo "device_check.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done

die() { echo "device_check.sh: $*" >&2; exit 1; }

stage() {
  [ -n "$binary" ] || binary=$root/target/cuda-build/posediff
  [ -x "$binary" ] || die "$binary: no binary (run \`cargo xtask cuda-build\`, or pass --binary)"
  local ref=$shared/reference/tiny apple=$shared/data/co3d_apple_posediffusion
  for f in "$ref/model_tiny.safetensors" "$ref/denoiser_io_tiny.safetensors" \
           "$ref/sampling_io_tiny.safetensors" "$apple/cameras.json"; do
    [ -f "$f" ] || die "$f: missing (--shared is the folder holding reference/ and data/)"
  done
  rm -rf "$dir"
  mkdir -p "$dir/reference/tiny" "$dir/data/co3d_apple_posediffusion"
  python3 - "$binary" "$dir/posediff.xz" <<'EOF'
import lzma, shutil, sys
with open(sys.argv[1], "rb") as src, lzma.open(sys.argv[2], "wb", preset=6) as dst:
    shutil.copyfileobj(src, dst, 1 << 20)
EOF
  cp "$ref/denoiser_io_tiny.safetensors" "$ref/sampling_io_tiny.safetensors" "$dir/reference/tiny/"
  cp -r "$apple/images" "$apple/cameras.json" "$dir/data/co3d_apple_posediffusion/"
  local bytes tree=0
  bytes=$(du -sb "$dir" | cut -f1)
  if git -C "$root" rev-parse --git-dir >/dev/null 2>&1; then
    tree=$(cd "$root" && git ls-files -z | du --files0-from=- -cb | tail -1 | cut -f1)
  fi
  echo "staged $dir: $((bytes / 1048576)) MiB + the tree's $((tree / 1048576)) MiB (a device call carries at most 64 MiB)"
  [ $((bytes + tree)) -lt $((62 * 1048576)) ] || die "$dir and the tree are too large to travel"
}

cuda_libraries() {
  local dirs=() d
  if d=$(python3 -c 'import nvidia, os; print(os.path.join(list(nvidia.__path__)[0], "cu13", "lib"))' 2>/dev/null) \
     && [ -d "$d" ]; then
    dirs+=("$d")
  fi
  for d in /usr/local/nvidia/lib64 /usr/local/nvidia/lib /usr/local/cuda/lib64 \
           /usr/local/cuda/targets/x86_64-linux/lib; do
    [ -d "$d" ] && dirs+=("$d")
  done
  local joined
  joined=$(IFS=:; echo "${dirs[*]}")
  export LD_LIBRARY_PATH=${joined}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
}

run_checks() {
  [ -n "$out" ] || die "run needs --out DIR"
  local reference=$dir/reference apple=$dir/data/co3d_apple_posediffusion
  [ -d "$reference/tiny" ] || die "$reference/tiny: missing (stage first)"
  mkdir -p "$out" "$dir/work"
  if [ -z "$binary" ] && [ -f "$dir/posediff.xz" ]; then
    binary=$dir/work/posediff
    python3 - "$dir/posediff.xz" "$binary" <<'EOF'
import lzma, os, shutil, sys
with lzma.open(sys.argv[1], "rb") as src, open(sys.argv[2], "wb") as dst:
    shutil.copyfileobj(src, dst, 1 << 20)
os.chmod(sys.argv[2], 0o755)
EOF
  fi
  [ -n "$binary" ] || binary=$dir/posediff
  [ -x "$binary" ] || die "$binary: no binary (stage first, or pass --binary)"
  local tiny_model=$reference/tiny/model_tiny.safetensors
  [ -f "$tiny_model" ] || tiny_model=$root/fixtures/torch/model_tiny_module_prefix.pth
  [ -f "$tiny_model" ] || die "$tiny_model: missing (the tiny fixtures' model)"
  local size
  size=$(stat -c %s "$binary")
  echo "binary $binary: $((size / 1048576)) MiB"
  if [ "$device" = cuda ]; then
    cuda_libraries
    command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv || true
  fi
  echo "shared libraries:"
  ldd "$binary" | tee "$out/ldd.txt"
  if grep -q "not found" "$out/ldd.txt"; then
    die "$binary: shared libraries not found (see $out/ldd.txt; set LD_LIBRARY_PATH to the CUDA 13 libraries)"
  fi

  local check_args=(--reference "$reference" --tiny-model "$tiny_model" --device "$device" --out "$out/network"
                    --save-model "$dir/work/model_official_random.safetensors")
  # BF16/F16 against F32 on the GPU (candle has no BF16 product on the CPU).
  [ "$device" = cuda ] && [ "$quick" = 0 ] && check_args+=(--half)
  local images=$apple/images gt=$apple/cameras.json
  if [ "$quick" = 1 ]; then
    check_args+=(--frames 1,2 --repeats 1 --train-iterations 1 --skip-official-training)
    # The first five frames and their ground truth.
    images=$dir/work/quick/images gt=$dir/work/quick/cameras.json
    rm -rf "$dir/work/quick" && mkdir -p "$images"
    find "$apple/images" -type f | sort | head -5 | xargs -I{} cp {} "$images/"
    python3 - "$apple/cameras.json" "$images" "$gt" <<'EOF'
import json, os, sys
cameras, images, out = sys.argv[1:]
keep = set(os.listdir(images))
json.dump([c for c in json.load(open(cameras)) if os.path.basename(c["image"]) in keep], open(out, "w"))
EOF
  fi
  echo "==> posediff device-check"
  "$binary" device-check "${check_args[@]}"

  echo "==> posediff estimate ($images, random-weight official-size checkpoint)"
  rm -rf "$dir/work/estimate"
  local start end
  start=$(date +%s.%N)
  "$binary" estimate "$images" --weights "$dir/work/model_official_random.safetensors" \
    --device "$device" --out "$dir/work/estimate"
  end=$(date +%s.%N)
  cp "$dir/work/estimate/run.json" "$out/estimate_run.json"
  "$binary" score "$dir/work/estimate/cameras.json" --gt "$gt" \
    --out "$out/estimate_score.json" | tee "$out/estimate_score.txt"
  python3 - "$out" "$start" "$end" <<'EOF'
import json, sys
out, start, end = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
json.dump({"wall_s": end - start}, open(f"{out}/estimate_wall.json", "w"))
EOF

  if [ "$pytorch" = auto ] && [ "$quick" = 0 ] && python3 -c 'import torch' 2>/dev/null; then
    echo "==> PyTorch, the official network on $device"
    local threads
    threads=$(nproc)
    python3 "$root/scripts/network_torch.py" --reference "$reference/tiny" --model "$tiny_model" --device "$device" \
      --frames 1,10,20,100 --threads "$threads" --repeats 5 --train-iterations 5 \
      --out "$out/pytorch.json" || echo "PyTorch timing failed (the posediff checks above stand)"
  fi
  python3 - "$out" "$device" <<'EOF'
import json, os, sys
out, device = sys.argv[1], sys.argv[2]
load = lambda name: json.load(open(os.path.join(out, name))) if os.path.exists(os.path.join(out, name)) else None
network = load("network/report.json")
run = load("estimate_run.json")
report = {
    "device": device,
    "network": network,
    "estimate": {"run": run, "wall": load("estimate_wall.json"), "score": load("estimate_score.json")},
    "pytorch": load("pytorch.json"),
}
json.dump(report, open(os.path.join(out, "report.json"), "w"), indent=1)
md = [open(os.path.join(out, "network/report.md")).read()]
md.append("\n## posediff estimate (apple frames, random-weight official-size checkpoint)\n")
md.append(f"Wall time {report['estimate']['wall']['wall_s']:.2f} s; stages (s): "
          + json.dumps((run or {}).get("seconds") or ((run or {}).get("report") or {}).get("seconds", {})) + "\n")
score = report["estimate"]["score"]
if score:
    md.append("Score against the ground truth (random weights: not an accuracy figure): " + json.dumps(score) + "\n")
pt = report["pytorch"]
if pt:
    md.append(f"\n## PyTorch {pt['torch']} on {pt['device']}, the official network (same machine, same run)\n")
    md.append(f"Checked against the official outputs first: {pt['checks']}\n\n")
    md.append("| frames | stage | PyTorch (s) | posediff (s) | PyTorch / posediff |\n|---:|---|---:|---:|---:|\n")
    ours = {r["frames"]: r for r in network["network"]}
    for r in pt["rows"]:
        o = ours.get(r["frames"])
        for key, label in [("features_s", "features, 3 scales"), ("denoiser_step_s", "one denoiser step"), ("sampling_100_s", "100-step sampling")]:
            if o:
                md.append(f"| {r['frames']} | {label} | {r[key]:.4f} | {o[key]:.4f} | {r[key] / o[key]:.2f}x |\n")
    tr = pt.get("training")
    ours_tr = [t for t in network["training"] if t.get("preset") == "official" and "seconds_per_iteration" in t]
    if tr and "seconds_per_iteration" in tr and ours_tr:
        md.append(f"| – | official training iteration | {tr['seconds_per_iteration']:.4f} | {ours_tr[0]['seconds_per_iteration']:.4f} | {tr['seconds_per_iteration'] / ours_tr[0]['seconds_per_iteration']:.2f}x |\n")
open(os.path.join(out, "report.md"), "w").write("".join(md))
print("".join(md))
EOF
}

case $mode in
  stage) stage ;;
  run) run_checks ;;
  *) echo "usage: scripts/device_check.sh stage|run [options] (see the header)" >&2; exit 2 ;;
esac
