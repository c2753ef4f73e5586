"""trajectory.txt: one line per scan, stamps ascending and unique (evo's check), scan order back."""
from decimal import Decimal

import numpy as np
import pytest

from slam2d.errors import InputError
from slam2d.io.trajectory import ascending_stamps, read_tum, write_tum


def _poses(n):
    return np.column_stack([np.arange(n) * 1.0, -np.arange(n) * 0.5, np.linspace(-3, 3, n)])


def _evo_check(path):
    file_interface = pytest.importorskip("evo.tools.file_interface", reason="evo not installed (pip install -e .[dev])")
    traj = file_interface.read_tum_trajectory_file(str(path))
    ok, details = traj.check()
    assert ok, details
    return traj


def test_reordered_and_repeated_stamps(tmp_path):
    stamps = ["976052857.337530", "976052857.948000", "976052857.348896", "976052857.348896", "976052857.348897",
              "976052858.000000"]
    p = tmp_path / "trajectory.txt"
    write_tum(p, stamps, _poses(6))
    lines = p.read_text().splitlines()
    assert lines[0] == "# scans 0 2-4 1 5"
    written = [line.split()[0] for line in lines[1:]]
    # sorted; the repeated stamp and the one a microsecond after it both move on by 1 µs
    assert written == ["976052857.337530", "976052857.348896", "976052857.348897", "976052857.348898",
                       "976052857.948000", "976052858.000000"]
    t, poses, texts = read_tum(p)
    np.testing.assert_allclose(poses, _poses(6), atol=1e-6)  # back in scan order
    assert texts == ["976052857.337530", "976052857.948000", "976052857.348896", "976052857.348897",
                     "976052857.348898", "976052858.000000"]
    traj = _evo_check(p)
    assert traj.num_poses == 6


def test_in_order_files_have_no_comment_and_keep_stamps_verbatim(tmp_path):
    p = tmp_path / "t.txt"
    write_tum(p, ["1.5", "2", "1e3"], _poses(3))
    assert [line.split()[0] for line in p.read_text().splitlines()] == ["1.5", "2", "1e3"]


def test_logs_whose_stamps_are_all_equal(tmp_path):
    for same in ("0", "1.01893e+09"):
        order, texts = ascending_stamps([same] * 4)
        assert order == [0, 1, 2, 3]
        assert [Decimal(x) - Decimal(same) for x in texts] == [Decimal(k) / 1_000_000 for k in range(4)]
        p = tmp_path / "t.txt"
        write_tum(p, [same] * 4, _poses(4))
        _evo_check(p)


def test_nanosecond_stamps_closer_than_float_resolution():
    order, texts = ascending_stamps(["1700000000.000000002", "1700000000.000000001"])
    assert order == [1, 0] and texts == ["1700000000.000000001", "1700000000.000001001"]
    assert float(texts[1]) > float(texts[0])


def test_a_broken_scans_comment_is_an_error(tmp_path):
    p = tmp_path / "t.txt"
    write_tum(p, ["2.0", "1.0"], _poses(2))
    p.write_text(p.read_text().replace("# scans 1 0", "# scans 1 1"))
    with pytest.raises(InputError, match="does not list each of the 2 lines once"):
        read_tum(p)


def test_an_eight_column_file_that_is_no_trajectory_is_refused(tmp_path):
    """A .relations file (t1 t2 x y z roll pitch yaw) has a TUM file's eight numbers a line; read as one, it
    gave an ATE of 677 m. Its 'quaternions' are not of unit length."""
    p = tmp_path / "intel.relations"
    p.write_text("976052857.3 976052858.1 0.1 0.0 0.0 0.0 0.0 -1.68221\n")
    with pytest.raises(InputError, match=r"not a TUM trajectory: the quaternion of pose 0 \(0, 0, 0, -1.68221\) is not of "
                                         r"unit length"):
        read_tum(p)
    write_tum(tmp_path / "ok.txt", ["1.0", "2.0"], np.array([[0.0, 0.0, 0.3], [1.0, 0.0, -2.0]]))
    assert read_tum(tmp_path / "ok.txt")[1][:, 2] == pytest.approx([0.3, -2.0])
