#!/usr/bin/env bash
# Second CI leg: the newest torch release that pyproject.toml admits (.ci/newest-torch.txt), installed into its own
# virtual environment as a user following README's GPU set-up would (`pip install torch`, then `pip install -e .`
# without constraints.txt), the native op built for it (C++20 where its headers ask for it) and the README's test
# command run without data. PyPI's build of torch is a CUDA build; it runs on a machine without a GPU.
# Usage: bash .ci/newest_torch.sh   (NEWEST_TORCH_VENV overrides the environment's folder, kept between runs)
set -euo pipefail
cd "$(dirname "$0")/.."
spec=$(grep -v '^#' .ci/newest-torch.txt | head -1)
venv=${NEWEST_TORCH_VENV:-$HOME/.cache/nsplat/venv-newest-torch}
export PIP_DISABLE_PIP_VERSION_CHECK=1
[ -x "$venv/bin/python" ] || python -m venv "$venv"
"$venv/bin/python" -m pip install -q "$spec"
"$venv/bin/python" -m pip install -q -e '.[test]'
echo "== newest torch: $("$venv/bin/python" -c 'import torch; print(torch.__version__)') ($spec)"
"$venv/bin/python" -m nsplat.ops.build
empty="$(mktemp -d)"
trap 'rm -rf "$empty"' EXIT
NSPLAT_DATA="$empty" "$venv/bin/python" -m pytest -q
