#!/usr/bin/env bash
# Decompose new photos with an existing ISF (no rescan): n-bounce images and a report page.
# usage: scripts/redecompose.sh WORKSPACE PHOTO.exr [PHOTO.exr ...]
#   PHOTOS must be linear EXR frames of the same camera view and size as the scan's HDR frames
#   (e.g. merged with `ilt merge --bracket RAW... -o photo.exr`).
set -euo pipefail
ws=${1:?usage: redecompose.sh WORKSPACE PHOTO.exr ...}
shift
(( $# )) || { echo "redecompose.sh: give at least one photo" >&2; exit 2; }
ilt decompose --isf "$ws/isf" -o "$ws/decompose" --force "$@"
ilt report -w "$ws"
