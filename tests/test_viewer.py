"""The recording as users see it: the real Rerun viewer (headless, software Vulkan) reports no error in any view."""
import glob
import os
import re
import socket
import subprocess
import sys

import pytest

from conftest import BUNDLED, ROOT

SCRIPT = ROOT.parent / "shared" / "tools" / "rerun_screenshot.sh"


def _skip_reason():
    if not SCRIPT.exists():
        return f"{SCRIPT} not found (../shared is not beside the repo)"
    if not glob.glob("/usr/share/vulkan/icd.d/lvp_icd.*.json"):
        return "no software Vulkan driver (apt-get install -y mesa-vulkan-drivers libvulkan1; .ci/run installs it)"
    return None


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    out = tmp_path_factory.mktemp("viewer")
    r = subprocess.run([sys.executable, "-m", "slam2d.cli", "run", str(BUNDLED), "--out", str(out / "run"),
                        "--rerun", str(out / "run.rrd"), "--no-progress"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _screenshot(args):
    """The script, on a port of its own; once more if the viewer was not up when the client connected
    (the script waits a fixed 4 s, which a loaded machine can exceed)."""
    for attempt in range(2):
        r = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600,
                           env={**os.environ, "PORT": str(_free_port())})
        if r.returncode == 0 or "ConnectionError" not in r.stderr:
            return r
    return r


@pytest.mark.parametrize("at", ["scan=150", None])
def test_no_view_reports_an_error(recording, at):
    png = recording / f"shot_{at or 'end'}.png".replace("=", "_")
    r = _screenshot(["bash", str(SCRIPT), str(recording / "run.rrd"), str(png), "15"] + ([at] if at else []))
    assert r.returncode == 0, r.stdout + r.stderr
    views = [line for line in r.stdout.splitlines() if line.startswith("view ")]
    names = {re.match(r"view '([^']*)'", v).group(1) for v in views}
    assert {"map", "timings [ms]", "match scores", "events"} <= names, r.stdout
    bad = [v for v in views if "'error'" in v.lower() or "error" in v.split(":", 1)[1].lower()]
    assert not bad, "\n".join(bad)
    assert png.exists() and png.stat().st_size > 10_000
