#!/usr/bin/env bash
# Packs what a lent GPU machine needs beside the working tree, in parts that fit its per-call upload
# (64 MiB with the tree): Warp and trimesh (../shared/device/warp-bundle), the pure-Python and binary
# wheels of our own dependencies that machine lacks (svgelements, isal; pyroomacoustics and the Cython
# it imports, for the crossengine test set), py-spy, and with --ray, Ray and its dependencies unpacked
# into one xz archive split across the calls. Writes .device/ (ignored by git)
# and prints the calls in order. Run from the repository root, with benchmarks/results moved aside (the
# tracked tree travels on every call and those results are ~50 MB):
#
#   mv benchmarks/results ../results_hold && python benchmarks/provenance.py source --left-behind benchmarks/results
#   bash benchmarks/device/lease_bundle.sh [--ray]
#   ... the calls it prints, back to back (the machine goes cold ~30 s after a call) ...
#   mv ../results_hold benchmarks/results && rm .provenance.json
set -euo pipefail
ray=0; [ "${1:-}" = --ray ] && ray=1
[ -e benchmarks/results ] && { echo "move benchmarks/results aside first (see the top of this script)" >&2; exit 2; }
../shared/device/warp-bundle svgelements isal pyroomacoustics Cython py-spy >/dev/null
mib() { du -sm "$@" | awk '{s += $1} END {print s}'; }
bytes=$( (git ls-files -z | xargs -0 du -cb 2>/dev/null || true) | tail -1 | cut -f1) # the results moved aside are missing
tree=$(((bytes + 1048575) / 1048576))
room=$((62 - tree)) # MiB a call may carry beside the tree, with a margin
a=$(mib .device/a) b=$(mib .device/b)
echo "tree ${tree} MiB; warp halves ${a} and ${b} MiB"
((a <= room && b <= room)) || { echo "the tree is too large for warp's halves beside it" >&2; exit 2; }
if ((ray)); then
  tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
  python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$tmp/whl" "ray>=2.9" 2>/dev/null
  mkdir "$tmp/site" && for w in "$tmp"/whl/*.whl; do unzip -qo "$w" -d "$tmp/site"; done
  tar -C "$tmp/site" -cf - . | xz -T0 -9 >"$tmp/ray.tar.xz"
  bytes=$(stat -c %s "$tmp/ray.tar.xz") first=$((room - a)) second=$((room - b)) # MiB
  mkdir -p .device/r0 .device/r1 .device/r2
  dd if="$tmp/ray.tar.xz" of=.device/r0/ray.p0 bs=1M count="$first" status=none
  dd if="$tmp/ray.tar.xz" of=.device/r1/ray.p1 bs=1M skip="$first" count="$second" status=none
  dd if="$tmp/ray.tar.xz" of=.device/r2/ray.p2 bs=1M skip=$((first + second)) status=none
  sha256sum "$tmp/ray.tar.xz" | cut -d' ' -f1 >.device/r2/ray.sha256
  (($(mib .device/r2) <= room)) || { echo "Ray's last part does not fit one call" >&2; exit 2; }
  echo "Ray and its dependencies ($(ls "$tmp"/whl | wc -l) wheels): $((bytes / 1048576)) MiB in three parts"
fi
cat <<MSG
Calls (kind nvidia-h100-x2 or as needed), each carrying .provenance.json too:
  1: mkdir -p \$HOME/warp-parts \$HOME/ray-parts && cp .device/a/* \$HOME/warp-parts/$( ((ray)) && echo ' && cp .device/r0/* $HOME/ray-parts/')
     carry [".device/a"$( ((ray)) && echo ', ".device/r0"')]
  2: $( ((ray)) && echo 'cp .device/r1/* $HOME/ray-parts/ && ')bash .device/b/install.sh && export PYTHONPATH=\$HOME/site:\$PWD PATH=\$HOME/site/bin:\$PATH && <command>
     carry [".device/b"$( ((ray)) && echo ', ".device/r1"')]
MSG
((ray)) && cat <<'MSG'
  3: cat $HOME/ray-parts/ray.p0 $HOME/ray-parts/ray.p1 .device/r2/ray.p2 > $HOME/ray.tar.xz &&
     echo "$(cat .device/r2/ray.sha256)  $HOME/ray.tar.xz" | sha256sum -c --quiet && mkdir -p $HOME/raysite &&
     tar -xJf $HOME/ray.tar.xz -C $HOME/raysite && RAY_SITE=$HOME/raysite <command>
     carry [".device/r2"]
MSG
echo "Later calls: export PYTHONPATH=\$HOME/site:\$PWD PATH=\$HOME/site/bin:\$PATH (no carry). Results under \$OUT come back"
echo "only as files at most two folders below \$OUT: pack deeper ones (tar -cf \$OUT/results.tar -C \$OUT ...) in the call."
