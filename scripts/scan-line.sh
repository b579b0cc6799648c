#!/usr/bin/env bash
# Scan a line of beams (paper's M scene) and decompose photos: `ilt run`, status, report.
# usage: scripts/scan-line.sh RIG.toml WORKSPACE [--quick] [PHOTO.exr ...]
#   RIG.toml   a rig config with a [plan] kind = "line" (configs/sim.toml runs on the emulated rig)
#   --quick    8 beams instead of the config's count (a smoke test of the rig)
#   PHOTO.exr  linear photos of the view (e.g. from `ilt merge --bracket`): decomposed and in the report
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
if (( $# )); then
    # Photos of your own go into the workspace config's [photos] files, so that `ilt run`
    # decomposes them into WS/decompose/ beside the simulated ones, the report shows them
    # and `ilt status` tracks them (a changed photo re-runs decompose).
    python3 - "$ws/rig.toml" "$@" <<'PY'
import json, pathlib, sys, tomllib
config = pathlib.Path(sys.argv[1])
lines = config.read_text().splitlines()
old = tomllib.loads("\n".join(lines)).get("photos", {}).get("files", [])
files = list(dict.fromkeys([str((config.parent / f).resolve()) for f in old]
                           + [str(pathlib.Path(p).resolve()) for p in sys.argv[2:]]))
entry = "files = [" + ", ".join(json.dumps(f) for f in files) + "]"  # JSON strings are TOML strings
headers = [i for i, line in enumerate(lines) if line.split("#")[0].strip() == "[photos]"]
if headers:
    start = headers[0] + 1
    end = next((i for i in range(start, len(lines)) if lines[i].lstrip().startswith("[")), len(lines))
    table = [line for line in lines[start:end] if not line.lstrip().startswith("files")]
    lines[start:end] = [entry, *table]
else:
    lines += ["", "[photos]", entry]
tomllib.loads("\n".join(lines))  # the edited config must still be valid TOML
config.write_text("\n".join(lines) + "\n")
PY
fi
ilt run -w "$ws"                    # capture -> merge -> centroids -> build-isf -> photos -> decompose
ilt status -w "$ws"
ilt report -w "$ws"                 # WS/report/index.html: every photo, the extra ones too
