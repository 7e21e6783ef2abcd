#!/usr/bin/env bash
# Idempotent set-up of a fresh Debian 12 machine for vla-ladder:
#   1. system packages: a Vulkan loader + Mesa >= 25 lavapipe (SAPIEN rejects Debian 12's 22.x
#      lavapipe) from the bookworm-backports suite of the machine's own mirror, and FFmpeg's libraries;
#   2. uv, then one Python 3.12 venv at .venv with the pinned simulator, LeRobot and this package.
# The second run only checks stamps and returns in a few seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)

log() { printf '[setup] %s\n' "$*" >&2; }
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"

# Debian packages: the renderer (Vulkan loader, lavapipe), FFmpeg for video, Chromium for the HTML report tests.
APT_PKGS="libvulkan1 vulkan-tools ffmpeg chromium chromium-driver"
BACKPORTS_PKGS="mesa-vulkan-drivers libdrm2 libdrm-amdgpu1"

system_ok() {
  local v p
  v=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
  [ -n "$v" ] && dpkg --compare-versions "$v" ge 25 || return 1
  for p in $APT_PKGS; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || return 1
  done
}

# The mirror comes from the machine's apt sources, so nothing here names a host.
debian_mirror() {
  local uri=""
  if [ -f /etc/apt/sources.list.d/debian.sources ]; then
    uri=$(awk '/^URIs:/{u=$2} /^Suites:/{ if ($0 ~ /bookworm( |$)/) {print u; exit} }' /etc/apt/sources.list.d/debian.sources)
  fi
  if [ -z "$uri" ] && [ -f /etc/apt/sources.list ]; then
    uri=$(awk '$1=="deb" && $3=="bookworm" {print $2; exit}' /etc/apt/sources.list)
  fi
  [ -n "$uri" ] || { echo "cannot find a bookworm mirror in the apt sources" >&2; exit 1; }
  echo "$uri"
}

if ! system_ok; then
  mirror=$(debian_mirror)
  log "system packages: Mesa 25 lavapipe (bookworm-backports from $mirror), $APT_PKGS"
  echo "deb $mirror bookworm-backports main" | $SUDO tee /etc/apt/sources.list.d/vla-ladder-backports.list >/dev/null
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
    -t bookworm-backports $BACKPORTS_PKGS >/dev/null
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $APT_PKGS >/dev/null
fi

UV="$(command -v uv || true)"
if [ -z "$UV" ]; then
  [ -x "$HOME/.local/bin/uv" ] || { log "installing uv"; python3 -m pip install -q --user uv; }
  UV="$HOME/.local/bin/uv"
fi

# A stamp holds the hash of what decides the environment; unchanged hash -> nothing to do.
want=$(cat pyproject.toml scripts/setup.sh plugins/lerobot_env_grasp_object/pyproject.toml | sha256sum | cut -c1-16)
if [ ! -f .venv/.vla-ladder-stamp ] || [ "$(cat .venv/.vla-ladder-stamp)" != "$want" ]; then
  # pyenv's shim refuses 3.12 unless it is selected, so take the interpreter itself.
  py=$(ls -d "$HOME"/.pyenv/versions/3.12*/bin/python3.12 2>/dev/null | tail -n1 || true)
  [ -n "$py" ] || py=$(command -v python3.12 || true)
  [ -n "$py" ] || { log "need Python 3.12 (pyenv or system)"; exit 1; }
  [ -x .venv/bin/python ] || "$UV" venv -q --python "$py" .venv
  log "installing Python packages into .venv (first time: a few minutes)"
  # The second distribution is the LeRobot env plugin: LeRobot imports installed lerobot_env_* distributions,
  # so `lerobot-eval --env.type=grasp_object` works without --env.discover_packages_path.
  # --compile-bytecode: where PYTHONDONTWRITEBYTECODE is set (CI runners often set it), nothing would ever
  # cache bytecode and every process (each simulation worker and server) would compile torch, LeRobot and
  # transformers from source again: ~70 s of CPU each, measured on 2 busy cores.
  VIRTUAL_ENV="$ROOT/.venv" "$UV" pip install -q --compile-bytecode -e ".[dev]" -e plugins/lerobot_env_grasp_object
  # openpi's own client, for the test that it talks to `vla-ladder serve-policy` (tests/test_remote_policy.py).
  # Without its dependencies: it pins numpy < 2, which nothing it runs here needs (its WebSocket client uses
  # websockets, msgpack and numpy, all already installed); dm-tree is for its own tests only.
  VIRTUAL_ENV="$ROOT/.venv" "$UV" pip install -q --compile-bytecode --no-deps "openpi-client==0.1.2"
  echo "$want" > .venv/.vla-ladder-stamp
fi
log "ready: $ROOT/.venv"
