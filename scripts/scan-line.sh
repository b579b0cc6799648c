#!/usr/bin/env bash
# Scan a line of beams (paper's M scene) and decompose photos, one stage at a time.
# usage: scripts/scan-line.sh RIG.toml WORKSPACE [--quick] [PHOTO.exr ...]
#   RIG.toml   a rig config with a [plan] kind = "line" (configs/sim.toml runs on the emulated rig)
#   --quick    8 beams instead of the config's count (a smoke test of the rig)
# Each stage is skipped when up to date; re-run the script to resume after a failure.
set -euo pipefail
rig=${1:?usage: scan-line.sh RIG.toml WORKSPACE [--quick] [PHOTO.exr ...]}
ws=${2:?usage: scan-line.sh RIG.toml WORKSPACE [--quick] [PHOTO.exr ...]}
shift 2
mkdir -p "$ws"
if [[ "${1:-}" == "--quick" ]]; then
    shift
    sed -e 's/^count = .*/count = 8/' -e 's/^px_per_beam = .*/px_per_beam = 8.0/' "$rig" > "$ws/rig.toml"
elif [[ "$(realpath "$rig")" != "$(realpath -m "$ws/rig.toml")" ]]; then
    cp "$rig" "$ws/rig.toml"
fi
ilt run -w "$ws"                    # capture -> merge -> centroids -> build-isf -> photos -> decompose
ilt status -w "$ws"
if (( $# )); then                   # photos of your own, with the ISF just built
    ilt decompose --isf "$ws/isf" -o "$ws/decompose-extra" --force "$@"
fi
ilt report -w "$ws"
