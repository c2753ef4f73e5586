"""The recording as users see it: the real Rerun viewer (headless, software Vulkan) reports no error in any view."""
import glob
import re
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


@pytest.mark.parametrize("at", ["scan=150", None])
def test_no_view_reports_an_error(recording, at):
    png = recording / f"shot_{at or 'end'}.png".replace("=", "_")
    args = ["bash", str(SCRIPT), str(recording / "run.rrd"), str(png), "15"] + ([at] if at else [])
    r = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    views = [line for line in r.stdout.splitlines() if line.startswith("view ")]
    names = {re.match(r"view '([^']*)'", v).group(1) for v in views}
    assert {"map", "timings [ms]", "match scores", "events"} <= names, r.stdout
    bad = [v for v in views if "'error'" in v.lower() or "error" in v.split(":", 1)[1].lower()]
    assert not bad, "\n".join(bad)
    assert png.exists() and png.stat().st_size > 10_000
