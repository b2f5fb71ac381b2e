#!/usr/bin/env bash
# The measurements a GPU machine is wanted for, in one run (what it gives goes to docs/bench/,
# named and marked with the GPU): a wall tile's frame at 1920x1080 and 512x512 (`bench frame`:
# the frame on the GPU against the earlier round-trip path; at 1080p also a moving camera's),
# speed with error against a converged reference (`bench suite`: the default march and the
# hardware-filtered texture march), an occlusion AOV to compare with the same render on lavapipe,
# the local 2x2 wall's fps, and the 1080p object-space wall's daemon RSS over 200 frames.
#
#   scripts/measure-gpu.sh BIN_DIR CT_NRRD OUT_DIR
#
# BIN_DIR holds release builds of `isowalld` and `isowall`; CT_NRRD is the head CT of ../shared/data.
# Every step has its own time limit, so that one that hangs costs only its own rows. SMOKE=1 runs
# every step at toy sizes (a check of the script on any machine, lavapipe included).
set -uo pipefail
bin=$(cd "$1" && pwd)
ct=$2
out=$3
mkdir -p "$out"
d="$bin/isowalld"
scenes="procedural:engine,$ct@300"
tile=1920x1080 small=512x512 spp=32,64,256 frames=200
if [ "${SMOKE:-0}" = 1 ]; then
    tile=96x54 small=64x64 spp=4,8 frames=8
fi
step() {
    local limit=$1
    shift
    echo "== $(date +%T) $*"
    local t0=$SECONDS
    timeout "$limit" "$@"
    echo "== rc $? after $((SECONDS - t0)) s"
}

nvidia-smi --query-gpu=name,driver_version,clocks.max.sm,memory.total --format=csv 2>&1 || true

step 150 "$d" bench frame --scenes "$scenes" --size $tile --samples $spp --repeats 10 --paths screen,object,moving \
    --variants default,before --save "$out/frame-1080p.csv"
step 150 "$d" bench suite --scenes "$scenes" --sizes $tile,$small --samples $spp --repeats 10 \
    --reference-frames 4 --variants default,texture --save "$out/suite.csv"
step 30 "$d" render --volume procedural:engine --size $small --ao-samples 32 --frames 1 --aov occlusion \
    --out "$out/engine-occlusion.pfm"
step 30 "$d" render --volume "$ct" --iso 300 --size $small --ao-samples 32 --frames 1 --aov occlusion \
    --out "$out/ct-occlusion.pfm"

# The local 2x2 wall (scripts/run.sh's), its frame statistics.
cfg=wall-configs/local-2x2.toml
[ -f wall-configs/keys/ca.pem ] || "$bin/isowall" keygen --config "$cfg"
step 60 "$bin/isowall" up "$cfg" --frames $((frames + 40))

# The 1080p object-space wall over 200 frames; both daemons' VmRSS every second.
# (A copy of its config, so that its certificates are made outside the checkout.)
cfg=$(mktemp -d)/object-1080p-wall.toml
cp scripts/data/object-1080p-wall.toml "$cfg"
"$bin/isowall" keygen --config "$cfg" >/dev/null
(
    while sleep 1; do
        for p in $(pgrep -x isowalld); do
            echo "$SECONDS $p $(grep -E 'VmRSS|VmHWM' /proc/"$p"/status 2>/dev/null | tr -s ' \n' ' ')"
        done
    done
) >"$out/object-wall-rss.txt" &
sampler=$!
step 120 "$bin/isowall" up "$cfg" --frames $frames
kill "$sampler" 2>/dev/null
step 60 "$d" bench frame --scenes "$scenes" --size $small --samples $spp --repeats 10 \
    --variants default,before --save "$out/frame-512.csv"
exit 0
