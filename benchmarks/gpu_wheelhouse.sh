#!/usr/bin/env bash
# Wheels for a GPU machine without a package registry (the lent H100/H200 image: Python 3.12, JAX
# 0.11 with the CUDA 13 plugin, flax, optax, numpy, grpcio, httpx, typer, rich, ... already there).
#
#   bash benchmarks/gpu_wheelhouse.sh            # here, with internet: fills .whl/ (git ignores it)
#
# It takes every package uv.lock pins for `quicknav[service]` on Python 3.12, leaves out the ones the
# image already holds (IMAGE_HAS below, from the image's package list), downloads the rest as
# manylinux x86-64 wheels for CPython 3.12 without their dependencies (each one is pinned here), and
# builds the SDK's wheel (its gRPC stubs are generated at build time). On the GPU machine, from the
# repository root, with .whl carried along:
#
#   python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl \
#     && export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 \
#     && python3 benchmarks/gpu_suite.py --minutes 25 --out "$OUT" --readme
#
# The project itself runs from the checkout (PYTHONPATH); the image's own jax, jaxlib and CUDA
# plugin are used as they are.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT_DIR=.whl
PY=3.12

# the image's packages (normalised names) that the project needs and must not be replaced
IMAGE_HAS="absl-py anyio certifi charset-normalizer chex click cloudpickle contourpy cycler etils
filelock flatbuffers flax fonttools fsspec grpcio h11 httpcore httpx humanize idna imageio jax
jaxlib jinja2 kiwisolver markdown-it-py markupsafe matplotlib mdurl ml-dtypes msgpack numpy
opt-einsum optax orbax-checkpoint packaging pillow prometheus-client protobuf psutil pygments
pyparsing python-dateutil pyyaml requests rich scipy shellingham six tensorstore toolz treescope
typer typing-extensions urllib3 uvloop wrapt zipp tqdm sympy mpmath attrs pandas seaborn simplejson"

mkdir -p "$OUT_DIR"
rm -f "$OUT_DIR"/*.whl
export PATH="$HOME/.local/bin:$PATH"
uv export --format requirements-txt --extra service --no-dev --no-hashes --no-emit-project \
  --no-emit-workspace --no-annotate --no-header > "$OUT_DIR/all.txt"  # markers select 3.12 below

python3 - "$OUT_DIR/all.txt" "$IMAGE_HAS" > "$OUT_DIR/needed.txt" <<'EOF'
import re, sys
from packaging.markers import Marker
have = {re.sub(r"[-_.]+", "-", n.lower()) for n in sys.argv[2].split()}
env = {"python_version": "3.12", "python_full_version": "3.12.3", "sys_platform": "linux",
       "platform_system": "Linux", "platform_machine": "x86_64", "implementation_name": "cpython",
       "platform_python_implementation": "CPython", "os_name": "posix", "extra": ""}
for line in open(sys.argv[1]):
    line = line.strip()
    if not line or line.startswith(("#", "-")):
        continue
    req, _, marker = line.partition(";")
    if marker.strip() and not Marker(marker.strip()).evaluate(env):
        continue
    name = re.sub(r"[-_.]+", "-", req.split("==")[0].strip().lower())
    if name.startswith(("nvidia-", "jax-cuda")) or name in have:
        continue
    print(req.strip())
EOF

echo "downloading $(wc -l < "$OUT_DIR/needed.txt") wheels for CPython $PY"
PLATFORMS=""
for n in 17 24 27 28 31 34 35; do PLATFORMS="$PLATFORMS --platform manylinux_2_${n}_x86_64"; done
python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version "$PY" \
  --implementation cp $PLATFORMS --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  --platform any -d "$OUT_DIR" -r "$OUT_DIR/needed.txt"
uv build --quiet --wheel --out-dir "$OUT_DIR" clients
rm -f "$OUT_DIR/all.txt"
echo "$OUT_DIR: $(ls "$OUT_DIR"/*.whl | wc -l) wheels, $(du -sh "$OUT_DIR" | cut -f1)"
