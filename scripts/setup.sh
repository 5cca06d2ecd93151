#!/usr/bin/env bash
# Idempotent set-up for a Debian 12 machine: virtual environment, Python packages, and — only when SAPIEN finds
# no Vulkan device it can render with — Mesa's software Vulkan driver from bookworm-backports (PLATFORM-NOTES).
# Prints every step it takes; a second run only checks and returns quickly.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PY=${PYTHON:-python3}
STAMP="$VENV/.ddvs-installed"
say() { printf '[setup] %s\n' "$*"; }

if [ ! -x "$VENV/bin/python" ]; then
    say "creating virtual environment $VENV with $($PY --version)"
    "$PY" -m venv "$VENV"
fi

# Reinstall only when the dependency declaration changed since the last install.
if [ ! -f "$STAMP" ] || [ pyproject.toml -nt "$STAMP" ]; then
    say "installing ddvs and its dependencies (pyproject.toml changed or first run)"
    "$VENV/bin/pip" install --quiet --disable-pip-version-check -e '.[dev,ray]'
    # sapien pulls in opencv-python (GUI build); both provide cv2. We want the headless build to own cv2.
    if "$VENV/bin/pip" show --quiet opencv-python >/dev/null 2>&1; then
        say "replacing opencv-python (pulled in by sapien) with opencv-python-headless"
        "$VENV/bin/pip" uninstall --quiet -y opencv-python
        hv=$("$VENV/bin/python" -c "import importlib.metadata as m; print(m.version('opencv-python-headless'))")
        "$VENV/bin/pip" install --quiet --disable-pip-version-check --force-reinstall --no-deps \
            "opencv-python-headless==$hv"
    fi
    touch "$STAMP"
else
    say "python packages up to date ($STAMP newer than pyproject.toml)"
fi
"$VENV/bin/python" -c "import cv2, taichi, zenoh, pinocchio, sapien, ray" 2>/dev/null \
    || { say "ERROR: an installed package fails to import"; exit 1; }
# The project's own bytecode: an editable install leaves it to the first import, which never writes it where the
# directory is read-only for the service's user or PYTHONDONTWRITEBYTECODE is set, so every start would compile
# some 80 modules again (~0.1 s of a restart: benchmarks/README.md, start-up). Up to date: a quick check.
"$VENV/bin/python" -m compileall -q ddvs ddvs_service kernels clients sim orchestration evaluation >/dev/null \
    || { say "ERROR: compiling the project's modules to bytecode failed"; exit 1; }

# Mesa's Vulkan drivers (lavapipe: Vulkan on the CPU) from bookworm-backports, for a machine without a GPU.
install_mesa() {
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    if ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
        say "adding the bookworm-backports suite to the Debian apt sources"
        echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] http://deb.debian.org/debian bookworm-backports main" \
            | $SUDO tee /etc/apt/sources.list.d/ddvs-backports.list >/dev/null
    fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq -t bookworm-backports \
        mesa-vulkan-drivers libvulkan1 >/dev/null
}

# SAPIEN rendering: probe in a subprocess (cached once it succeeded).
RSTAMP="$VENV/.ddvs-render-ok"
if [ -f "$RSTAMP" ]; then
    say "SAPIEN rendering already verified"
elif "$VENV/bin/python" -m sim.render_probe >/dev/null 2>&1; then
    say "SAPIEN finds a Vulkan rendering device"; touch "$RSTAMP"
else
    say "SAPIEN finds no Vulkan rendering device: installing Mesa (lavapipe) from bookworm-backports"
    install_mesa
    if "$VENV/bin/python" -m sim.render_probe; then
        say "SAPIEN renders now"; touch "$RSTAMP"
    else
        say "ERROR: SAPIEN still cannot render after installing Mesa from bookworm-backports"; exit 1
    fi
fi

# Taichi's Vulkan backend (the kernels' GPU path that `make test` checks, docs/gpu.md): a device or lavapipe.
VPROBE="from kernels.backend import init; import sys; sys.exit(init('vulkan') != 'vulkan')"
if "$VENV/bin/python" -c "$VPROBE" >/dev/null 2>&1; then
    say "Taichi starts on Vulkan"
else
    say "Taichi finds no Vulkan device: installing Mesa (lavapipe) from bookworm-backports"
    install_mesa
    "$VENV/bin/python" -c "$VPROBE" >/dev/null 2>&1 \
        || { say "ERROR: Taichi still cannot start on Vulkan after installing Mesa from bookworm-backports"; exit 1; }
fi

# Taichi's offline cache for the shipped service configurations: a first `ddvs serve --config configs/serve/…` loads
# its kernels instead of compiling them (README, The servo service). Redone when the code or a configuration changed.
KSTAMP="$VENV/.ddvs-kernels-cached"
ksum=$(find kernels ddvs_service configs/serve pyproject.toml -name '*.py' -o -name '*.json' -o -name '*.toml' \
       | LC_ALL=C sort | xargs cat | sha256sum | cut -d' ' -f1)
if [ -f "$KSTAMP" ] && [ "$(cat "$KSTAMP")" = "$ksum" ]; then
    say "kernels of configs/serve already in Taichi's offline cache"
else
    for config in configs/serve/*.json; do
        start=$SECONDS
        "$VENV/bin/ddvs" serve --config "$config" --warmup-only --log-level WARNING 2>/dev/null \
            || { say "ERROR: compiling the kernels of $config failed (run: ddvs serve --config $config --warmup-only)"; exit 1; }
        say "compiled the kernels of $config into Taichi's offline cache ($((SECONDS - start)) s)"
    done
    echo "$ksum" > "$KSTAMP"
fi
say "done"
