#!/usr/bin/env bash
# A GPU sitting for model v4 (research/v4/README.md): the VAE trained on the CPU is fine-tuned on the GPU with a
# large batch, then three denoisers learn its latents side by side, all from files carried to a machine without
# internet.
#
#   research/v4/device_run.sh PACK TEXT_ENCODER_DIR VAE_DIR OUT [VAE_MINUTES] [DENOISER_MINUTES] [DEVICE]
#
# PACK and TEXT_ENCODER_DIR: scripts/pack_for_device.py's data.npz and minilm/; VAE_DIR: a model folder holding the
# VAE to continue (config.json, vae.safetensors), or `scratch` for a VAE from nothing (a model that must owe nothing
# to the bundled one, such as one trained on `data prepare cmu-joints --captions cmu` alone; vae_gpu.json's settings
# and the 2-token latent the denoisers expect). The denoisers: a, the bundled model's architecture; b, 9 layers
# (MLD's depth); c, conditioned on action labels (`generate --action`); DENOISER_MINUTES 0 trains the VAE alone.
# OUT gets the exported fp16 models and every log as one tar in parts of 15 MB (scripts and logs first, so a sitting
# cut short still brings back what ran). The runs themselves go to $V4_WORK (default runs/v4, the data beside it).
# The VAE's settings are $V4_VAE_CONFIG (default research/v4/vae_gpu.json; vae_gpu_boost.json adds kicks and throws
# drawn more often, for a pack of the merged folder).
# Put back together, a text model is export_den_a/ with vae_fp16.safetensors copied in as vae.safetensors.
set -uo pipefail
pack="${1:?pack file}"; text="${2:?text encoder folder}"; vae_init="${3:?VAE folder}"; out="${4:?output folder}"
vae_minutes="${5:-2.8}"; den_minutes="${6:-3.8}"; device="${7:-cuda}"
for m in "$vae_minutes" "$den_minutes"; do
    [[ "$m" =~ ^[0-9]+([.][0-9]+)?$ ]] || { echo "error: minutes must be a number >= 0, got '$m'" >&2; exit 2; }
done
if [ "$vae_init" = scratch ] && ! [[ "$vae_minutes" =~ [1-9] ]]; then
    echo "error: a VAE from scratch needs VAE_MINUTES above 0" >&2; exit 2
fi
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
vae_config="$(realpath -m "${V4_VAE_CONFIG:-$here/research/v4/vae_gpu.json}")"  # from the caller's folder
cd "$here"
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
PY="${PYTHON:-python3}"
work="${V4_WORK:-runs/v4}"
data="${work}_data"
# OUT and the run folders apart: the tar of the runs must not hold its own parts, nor OUT the train states.
w="$(realpath -m "$work")/"; o="$(realpath -m "$out")/"
if [[ "$o" == "$w"* || "$w" == "$o"* ]]; then
    echo "error: OUT ($out) and V4_WORK ($work) must not hold one another" >&2; exit 2
fi
[ -f "$vae_config" ] || { echo "error: no VAE config at $vae_config (V4_VAE_CONFIG)" >&2; exit 2; }
mkdir -p "$work" "$out"
log() { echo "[$(date +%H:%M:%S)] $*"; }
nvidia-smi -L 2>/dev/null; "$PY" -c "import torch; print('torch', torch.__version__, torch.cuda.is_available())"

# 1. The data: a folder to train on, rebuilt from the pack.
log "unpacking $pack"
[ -f "$data/Mean.npy" ] || "$PY" -m mld_core data unpack "$pack" --out "$data" --workers "$(nproc)" || exit 1

# train STAGE NAME ARGS...: one run, again in float32 if mixed precision fails on this GPU.
train() {
    local stage="$1" name="$2"
    shift 2
    "$PY" -m mld_core train "$stage" --data "$data" --out "$work/$name" --device "$device" "$@" \
        > "$work/$name.log" 2>&1 && return 0
    log "$name failed in mixed precision, again in float32"; tail -3 "$work/$name.log"
    rm -rf "${work:?}/$name"
    "$PY" -m mld_core train "$stage" --data "$data" --out "$work/$name" --device "$device" --fp32 "$@" \
        > "$work/${name}_fp32.log" 2>&1 || { log "$name failed"; tail -5 "$work/${name}_fp32.log"; return 1; }
}

# 2. The VAE, fine-tuned with a GPU's batch (no VAE minutes: the carried one as it is), or trained from scratch.
vae="$vae_init"
if [ "$vae_init" = scratch ]; then
    log "VAE: $vae_minutes minutes from scratch"
    train vae vae --minutes "$vae_minutes" --latent-tokens 2 --config "$vae_config" && vae="$work/vae" \
        || { log "no VAE: nothing for the denoisers to learn"; vae=""; }
elif "$PY" -c "import sys; sys.exit(0 if float('$vae_minutes') > 0 else 1)"; then
    log "VAE: $vae_minutes minutes from $vae_init"
    train vae vae --init "$vae_init" --minutes "$vae_minutes" --config "$vae_config" && vae="$work/vae"
fi

# 3. Three denoisers on that VAE's latents, side by side, each exported in fp16 when done.
denoiser() {  # denoiser NAME CONFIG COND
    local name="$1" config="$2" cond="$3"
    sed "s#device_pack/minilm#$text#" "$config" > "$work/$name.json"
    log "$name: denoiser"
    train denoiser "$name" --vae "$vae" --cond "$cond" --minutes "$den_minutes" --config "$work/$name.json" || return 1
    local encoder=()
    [ "$cond" = text ] && encoder=(--text-encoder '{"kind": "minilm", "path": null}')
    "$PY" scripts/export_model.py "$work/$name" --out "$work/export_$name" --overwrite --model-id "mld-v4-$name" \
        --hardware "one $("$PY" -c 'import torch; print(torch.cuda.get_device_name(0))' 2>/dev/null || echo CPU)" \
        "${encoder[@]}" > "$work/export_$name.log" 2>&1 || { log "$name: export failed"; tail -3 "$work/export_$name.log"; }
    log "$name: done"
}
if [ -z "$vae" ]; then
    log "no denoisers: there is no VAE for them to learn"
elif "$PY" -c "import sys; sys.exit(0 if float('$den_minutes') > 0 else 1)"; then
    denoiser den_a research/v4/denoiser_a.json text &
    denoiser den_b research/v4/denoiser_b.json text &
    denoiser den_c research/v4/denoiser_action.json action &
    wait
else
    log "no denoiser minutes: the sitting brings back the VAE alone"
fi

# 4. What comes back: the exports, the VAE in fp16 and the logs (train states stay: too large to bring back).
for run in vae den_a den_b den_c; do
    for f in log.jsonl train_config.json config.json; do
        [ -f "$work/$run/$f" ] && cp "$work/$run/$f" "$work/${run}_$f"
    done
done
[ -f "$work/vae/vae.safetensors" ] && "$PY" -c "
import sys
from safetensors.torch import load_file, save_file
d = load_file(sys.argv[1]); save_file({k: v.half() if v.is_floating_point() else v for k, v in d.items()}, sys.argv[2])
" "$work/vae/vae.safetensors" "$work/vae_fp16.safetensors"
tar cf - -C "$work" --exclude=vae --exclude='den_?' --exclude=coverage_index.npz --exclude='export_*/vae.safetensors' . | split -b 15M - "$out/v4.tar.part-"
ls -la "$out"
log "done"
