"""The numerical core imports no transport, file-format or plotting library."""

import subprocess
import sys

# (numba itself imports yaml and socket, so those cannot be told apart here)
FORBIDDEN = (
    "pymavlink",
    "zenoh",
    "mavsdk",
    "open3d",
    "matplotlib",
    "onboard.config",
    "onboard.comm",
    "gcs",
)


def test_planner_core_imports_no_io_libraries() -> None:
    code = (
        "import sys\n"
        "import onboard.planner.planner, onboard.planner.objective, onboard.world\n"
        f"bad = [m for m in {FORBIDDEN!r} if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"core pulled in: {out.stdout.strip()}"
