#!/usr/bin/env bash
# Scan a 2D grid of beams (paper's box, Fig. 7-9), stage by stage, with the stage commands.
# usage: scripts/scan-grid.sh RIG.toml WORKSPACE
#   RIG.toml  a rig config with [plan] kind = "grid" (e.g. the box config `ilt demo` writes to DIR/box/rig.toml)
# Every command prints the directory it wrote; `ilt status -w WORKSPACE` says what is up to date.
set -euo pipefail
rig=${1:?usage: scan-grid.sh RIG.toml WORKSPACE}
ws=${2:?usage: scan-grid.sh RIG.toml WORKSPACE}
mkdir -p "$ws"
# the workspace keeps its config, as `ilt run` does, so that `ilt status -w WS` works
if [[ "$(realpath "$rig")" != "$(realpath -m "$ws/rig.toml")" ]]; then
    cp "$rig" "$ws/rig.toml"
fi
resume=()
[[ -f "$ws/capture/capture.jsonl" ]] && resume=(--resume)
[[ -f "$ws/capture/manifest.json" ]] || ilt capture "$rig" -o "$ws/capture" "${resume[@]}"
ilt merge "$ws/capture" -o "$ws/hdr" --force
ilt centroids "$ws/hdr" -o "$ws/spots" --force
ilt build-isf "$ws/hdr" "$ws/spots" -o "$ws/isf" --force
echo "ISF: $ws/isf (decompose photos with scripts/redecompose.sh $ws PHOTO.exr ...)" >&2
