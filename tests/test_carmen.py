import bz2
import gzip
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slam2d.errors import InputError
from slam2d.io.carmen import CarmenLog, flaser_geometry
from slam2d.io.source import open_source


def write(tmp_path, text, name="log.clf", opener=open):
    p = tmp_path / name
    with opener(p, "wt") as f:
        f.write(text)
    return p


def test_flaser_fields_and_geometry(tmp_path, flaser_line):
    text = "# comment\nPARAM robot_frontlaser_offset 0.0 nohost 0\n"
    text += "ODOM 0.1 0.2 0.3 0 0 0 99.0 nohost 0.1\n"
    text += flaser_line([1.0, 2.0, 3.0, 4.0], pose=(1.0, 2.0, 0.5), odom=(0.9, 2.0, 0.5), ts="100.123456")
    text += flaser_line([1.5, 2.5, 3.5, 4.5], pose=(1.1, 2.0, 0.5), odom=(1.0, 2.0, 0.5), ts="100.323456")
    scans = list(CarmenLog(write(tmp_path, text)))
    assert len(scans) == 2
    s = scans[0]
    assert s.timestamp_text == "100.123456" and s.timestamp == pytest.approx(100.123456)
    np.testing.assert_array_equal(s.ranges, np.float32([1, 2, 3, 4]))
    np.testing.assert_allclose(s.odom_pose, [0.9, 2.0, 0.5])
    # mount = odom⁻¹ ∘ laser: a world offset of 0.1 m along x, seen from a robot heading 0.5 rad
    np.testing.assert_allclose(s.laser_offset, [0.1 * math.cos(0.5), -0.1 * math.sin(0.5), 0.0], atol=1e-6)
    assert s.angle_min == pytest.approx(-math.pi / 2)
    assert s.angle_increment == pytest.approx(math.pi / 4)
    assert scans[1].index == 1


@pytest.mark.parametrize("n, step_deg", [(180, 1.0), (181, 1.0), (360, 0.5), (361, 0.5)])
def test_flaser_beam_conventions(n, step_deg):
    a0, da = flaser_geometry(n)
    assert a0 == pytest.approx(-math.pi / 2)
    assert math.degrees(da) == pytest.approx(step_deg)


def test_records_spilled_to_disk_read_back_the_same(tmp_path, flaser_line, monkeypatch):
    """Past the memory budget the first pass's records go to a temporary file; the scans are the same."""
    import slam2d.io.carmen as carmen

    rng = np.random.default_rng(1)
    text = "".join(flaser_line(list(rng.uniform(0.5, 9.0, 8).round(3)), pose=(0.1 * i, 0.0, 0.0),
                               odom=(0.1 * i, 0.0, 0.0), ts=f"{100 + i}.5") for i in range(40))
    path = write(tmp_path, text)
    in_memory = list(CarmenLog(path))
    monkeypatch.setattr(carmen, "RECORD_MEMORY_BUDGET", 2000)  # spills after a few records
    log = CarmenLog(path)
    spilled = list(log)
    assert log._spool.file is not None and log._spool.in_memory() == 0
    assert len(spilled) == len(in_memory) == 40
    for a, b in zip(in_memory, spilled):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        np.testing.assert_array_equal(a.odom_pose, b.odom_pose)
        assert a.timestamp_text == b.timestamp_text and a.index == b.index
    assert len(list(log)) == 40  # the second pass can run again


def test_in_memory_records_are_handed_on_once_and_a_second_pass_reads_the_file_again(tmp_path, flaser_line,
                                                                                     monkeypatch):
    """The first pass's records leave memory block by block as the scans go out; a pass begun again,
    whole or after one broken off, gives the same scans."""
    import slam2d.io.carmen as carmen

    monkeypatch.setattr(carmen, "RECORD_BLOCK", 4)
    rng = np.random.default_rng(2)
    text = "".join(flaser_line(list(rng.uniform(0.5, 9.0, 8).round(3)), pose=(0.1 * i, 0.0, 0.0),
                               odom=(0.1 * i, 0.0, 0.0), ts=f"{100 + i}.5") for i in range(30))
    log = CarmenLog(write(tmp_path, text))
    first = []
    for scan in log:
        first.append(scan)
        if len(first) == 10:  # the third block is being handed on; the first two are gone
            assert log._spool.in_memory() == 30 - 12
    assert log._spool.file is None and log._spool.in_memory() == 0
    partial = [s for _, s in zip(range(5), log)]
    again = list(log)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        assert a.timestamp_text == b.timestamp_text and a.index == b.index
    assert len(again) == 30 and [s.index for s in partial] == list(range(5))


def test_robotlaser1(tmp_path):
    n = 5
    ranges = " ".join(["1.0", "2.0", "30.0", "4.0", "5.0"])
    line = (f"ROBOTLASER1 0 -1.5708 3.1416 0.785398 30.0 0.01 0 {n} {ranges} 0 "
            "1.0 2.0 0.1 0.8 2.0 0.1 0.0 0.0 0.5 0.5 0.0 55.5 host 1.0\n")
    line2 = ("ROBOTLASER1 0 -1.0 2.0 0.5 30.0 0.01 0 3 1 2 3 0 "
             "1.0 2.0 0.1 0.8 2.0 0.1 0.0 0.0 0.5 0.5 0.0 55.7 host 1.2\n")
    scans = list(CarmenLog(write(tmp_path, line + line2)))
    s = scans[0]
    assert s.num_beams == 5 and scans[1].num_beams == 3
    assert s.angle_min == pytest.approx(-1.5708) and s.angle_increment == pytest.approx(0.785398)
    assert not s.valid[2] and s.no_return[2]  # at the line's maximum range
    assert s.valid[[0, 1, 3, 4]].all()
    np.testing.assert_allclose(s.odom_pose, [0.8, 2.0, 0.1])
    np.testing.assert_allclose(s.laser_offset[:2], [0.2 * math.cos(0.1), -0.2 * math.sin(0.1)], atol=1e-9)
    assert s.timestamp == pytest.approx(55.5)


def test_no_return_value_is_the_repeated_maximum(tmp_path, flaser_line):
    lines = [flaser_line([1.0, 81.83, 2.0, 81.83], ts=f"{100 + i}.0") for i in range(10)]
    scans = list(CarmenLog(write(tmp_path, "".join(lines))))
    assert all((~s.valid[[1, 3]]).all() and s.valid[[0, 2]].all() for s in scans)
    assert scans[0].range_max == pytest.approx(81.83)


def _far_readings(rng, n):
    """Real far returns: continuous values (1 cm resolution) between 40 and 81.9 m, rarely equal."""
    return [f"{v:.2f}" for v in rng.uniform(40.0, 81.9, n)]


def test_several_no_return_values_near_the_maximum(tmp_path, flaser_line):
    """fr-clinic writes no-returns as 81.83 and as 81.91 m; both must be no-returns, far real returns must not."""
    rng = np.random.default_rng(3)
    lines = []
    for i in range(200):
        far = _far_readings(rng, 4)
        lines.append(flaser_line([1.0, "81.83", 2.0, "81.91", "81.91", *far], ts=f"{100 + i}.0"))
    log = CarmenLog(write(tmp_path, "".join(lines)))
    facts = log.facts()
    assert sorted(e["value"] for e in facts.no_return_evidence) == [81.83, 81.91]
    for s in log:
        assert s.no_return[[1, 3, 4]].all() and not s.valid[[1, 3, 4]].any()
        assert s.valid[[0, 2]].all()
        np.testing.assert_array_equal(s.valid[5:], s.ranges[5:] < 81.83)
    # readings below the lowest no-return value stay returns
    valid_far = sum(int(s.valid[5:].sum()) for s in log)
    assert valid_far >= 0.95 * 4 * 200


def test_a_frequent_near_reading_is_not_a_no_return(tmp_path, flaser_line):
    """A wall seen from a parked robot repeats one reading thousands of times; it is far below the maximum."""
    rng = np.random.default_rng(4)
    lines = [flaser_line(["3.21"] * 20 + _far_readings(rng, 3), ts=f"{100 + i}.0") for i in range(300)]
    log = CarmenLog(write(tmp_path, "".join(lines)))
    assert log.facts().no_return_value is None
    assert all(s.valid.all() for s in log)


def test_robotlaser1_max_range_and_spike_together(tmp_path):
    """ROBOTLASER1's max_range field is a no-return value; a spike below it lowers the threshold."""
    lines = []
    for i in range(50):
        ranges = "1.0 81.83 2.5 81.91 70.0"
        lines.append(f"ROBOTLASER1 0 -1.5708 3.1416 0.785398 81.9 0.01 0 5 {ranges} 0 "
                     f"0.22 0 0 0 0 0 0 0 0 0 0 {200 + i}.0 host {i}.0\n")
    log = CarmenLog(write(tmp_path, "".join(lines)))
    ev = log.facts().no_return_evidence
    assert {e["value"] for e in ev} == {81.83, 81.9, 81.91}
    assert log.facts().no_return_value == pytest.approx(81.83)
    s = next(iter(log))
    assert s.valid.tolist() == [True, False, True, False, True]


@pytest.mark.parametrize("strays", [1, 4])
def test_stray_readings_above_the_maximum_leave_the_no_return_value(tmp_path, flaser_line, strays):
    """A corrupt token far above every other reading (500 in a log whose returns end at 80 m) must not
    become the maximum the no-return spike is looked for under: up to SATURATION_MIN_COUNT - 1 of them."""
    rng = np.random.default_rng(5)
    lines = []
    for i in range(200):
        readings = [1.0, "81.83", 2.0, *_far_readings(rng, 4)]
        if i < strays:
            readings[2] = 500.0 + i
        lines.append(flaser_line(readings, ts=f"{100 + i}.0"))
    log = CarmenLog(write(tmp_path, "".join(lines)))
    assert log.facts().no_return_value == pytest.approx(81.83)
    assert all(s.no_return[1] and not s.valid[1] for s in log)


def test_one_line_with_another_max_range_does_not_set_the_threshold(tmp_path):
    """ROBOTLASER1's max_range field: the value most lines state (one corrupt line said 0.01 m and made
    every reading of the log a no-return)."""
    lines = []
    for i in range(50):
        max_range = "0.01" if i == 7 else "30.0"
        lines.append(f"ROBOTLASER1 0 -1.5708 3.1416 0.785398 {max_range} 0.01 0 5 1.0 2.0 3.0 4.0 30.0 0 "
                     f"0.22 0 0 0 0 0 0 0 0 0 0 {200 + i}.0 host {i}.0\n")
    log = CarmenLog(write(tmp_path, "".join(lines)))
    assert log.facts().no_return_value == pytest.approx(30.0)
    assert log.facts().no_return_evidence[-1]["why"] == "the max_range field of the ROBOTLASER1 lines (49 of 50 lines)"
    # each line's own max_range holds for its own readings: line 7's say it saw nothing within 0.01 m
    assert all(s.valid.tolist() == ([False] * 5 if s.index == 7 else [True] * 4 + [False]) for s in log)


def test_lines_stating_another_max_range_keep_their_own_no_returns(tmp_path):
    """40 % of the lines state max_range 8 and write 8.0 for no return, the rest 30: the log's threshold
    is 30, but the 8.0 readings of those lines must not become walls."""
    lines = []
    for i in range(50):
        mr = "8.0" if i % 5 < 2 else "30.0"
        lines.append(f"ROBOTLASER1 0 -1.5708 3.1416 0.785398 {mr} 0.01 0 5 1.0 2.0 8.0 4.0 {mr} 0 "
                     f"0.22 0 0 0 0 0 0 0 0 0 0 {200 + i}.0 host {i}.0\n")
    log = CarmenLog(write(tmp_path, "".join(lines)))
    assert log.facts().no_return_value == pytest.approx(30.0)
    for s in log:
        assert s.valid.tolist() == ([True, True, False, True, False] if s.index % 5 < 2 else [True] * 4 + [False])


def test_a_reading_beyond_any_laser_is_a_no_return_with_a_warning(tmp_path, flaser_line, caplog):
    """A huge value too rare to show as a spike (1e6 three times) refused the whole log; it is read as a
    no-return, with one warning."""
    import logging

    text = "".join(flaser_line([1.0, "1e6" if i in (3, 9, 20) else 2.0, 3.0], ts=f"{100 + i}.0") for i in range(40))
    with caplog.at_level(logging.WARNING):
        scans = list(CarmenLog(write(tmp_path, text)))
    assert [s.index for s in scans if not s.valid[1]] == [3, 9, 20] and all(scans[i].no_return[1] for i in (3, 9, 20))
    assert sum("beyond 100000 m read as a no-return" in r.getMessage() for r in caplog.records) == 1


def test_a_scan_without_any_reading_takes_the_log_s_farthest_as_its_range(tmp_path, flaser_line):
    """A scan all 0 or all inf in a log without a no-return value had range_max 0, which the run refused."""
    text = "".join(flaser_line(["inf", "inf", "inf"] if i == 5 else [1.0, 2.0 + 0.1 * i, 3.0], ts=f"{100 + i}.0")
                   for i in range(20))
    scans = list(CarmenLog(write(tmp_path, text)))
    assert scans[5].range_max == pytest.approx(3.9) and not scans[5].valid.any()
    scans[5].check()


def test_no_saturation_means_every_reading_is_a_hit(tmp_path, flaser_line):
    lines = [flaser_line([1.0 + i, 2.0, 3.0], ts=f"{100 + i}.0") for i in range(3)]
    assert all(s.valid.all() for s in CarmenLog(write(tmp_path, "".join(lines))))


@pytest.mark.parametrize("opener, name", [(gzip.open, "log.clf.gz"), (bz2.open, "log.clf.bz2"), (open, "log.log")])
def test_compressed_round_trip(tmp_path, flaser_line, opener, name):
    text = "".join(flaser_line([1.0, 2.0, 3.0], ts=f"{100 + i}.5") for i in range(4))
    plain = list(CarmenLog(write(tmp_path, text, "plain.clf")))
    other = list(open_source(write(tmp_path, text, name, opener)))
    assert [s.timestamp_text for s in plain] == [s.timestamp_text for s in other]
    for a, b in zip(plain, other):
        np.testing.assert_array_equal(a.ranges, b.ranges)


def test_odd_reading_is_invalid_not_fatal(tmp_path, flaser_line):
    scans = list(CarmenLog(write(tmp_path, flaser_line([1.0, "nan", 2.0]))))
    assert scans[0].valid.tolist() == [True, False, True]


def test_small_timestamp_reordering_is_tolerated(tmp_path, flaser_line):
    text = flaser_line([1.0], ts="100.5") + flaser_line([1.0], ts="100.2") + flaser_line([1.0], ts="100.9")
    assert [s.timestamp for s in CarmenLog(write(tmp_path, text))] == [100.5, 100.2, 100.9]


BAD = {
    "truncated": ("FLASER 3 1.0 2.0\n", 1, "needs"),
    "non-numeric range": ("FLASER 3 1.0 abc 2.0 0 0 0 0 0 0 100.0 nohost 0.1\n", 1, "non-numeric range reading 'abc'"),
    "non-numeric count": ("FLASER x 1.0\n", 1, "beam count must be an integer"),
    "negative range": ("FLASER 3 1.0 -2.0 2.0 0 0 0 0 0 0 100.0 nohost 0.1\n", 1, "negative range"),
    "-inf range": ("FLASER 3 1.0 -inf 2.0 0 0 0 0 0 0 100.0 nohost 0.1\n", 1, "negative range"),
    "all nan": ("FLASER 2 nan nan 0 0 0 0 0 0 100.0 nohost 0.1\n", 1, "NaN"),
    "beam count mismatch": ("FLASER 4 1.0 2.0 3.0 0 0 0 0 0 0 100.0 nohost 0.1\n", 1, "beam count mismatch"),
    "nan timestamp": ("FLASER 1 1.0 0 0 0 0 0 0 nan nohost 0.1\n", 1, "not finite"),
    "inf pose": ("FLASER 1 1.0 inf 0 0 0 0 0 100.0 nohost 0.1\n", 1, "pose field is not finite"),
    "time backwards": ("FLASER 1 1.0 0 0 0 0 0 0 100.0 nohost 0.1\nFLASER 1 1.0 0 0 0 0 0 0 90.0 nohost 0.2\n", 2,
                       "goes back"),
    # the message names the line whose stamp jumped ahead, not only the one that comes back
    "time jumps ahead": ("FLASER 1 1.0 0 0 0 0 0 0 100.0 nohost 0.1\nFLASER 1 1.0 0 0 0 0 0 0 9e8 nohost 0.1\n"
                         "FLASER 1 1.0 0 0 0 0 0 0 100.2 nohost 0.1\n", 3, "goes back 9e+08 s (more than 1.0 s) "
                         "behind the scan of line 2"),
    "huge pose": ("FLASER 1 1.0 1e300 0 0 0 0 0 100.0 nohost 0.1\n", 1, "pose field beyond 1e+09 m"),
    "nan start angle": ("ROBOTLASER1 0 nan 3.1416 0.785398 30.0 0.01 0 2 1 2 0 0 0 0 0 0 0 0 0 0 0 0 100.0 h 0\n", 1,
                        "start angle must be a number, found nan"),
    "resolution in degrees": ("ROBOTLASER1 0 -90 180 1 30.0 0.01 0 181 " + "1 " * 181 +
                              "0 0 0 0 0 0 0 0 0 0 0 0 100.0 h 0\n", 1,
                              "181 beams 1.0 rad apart span 10313°, more than a full turn"),
    "bad odom": ("ODOM 1 2\nFLASER 1 1.0 0 0 0 0 0 0 100.0 nohost 0.1\n", 1, "truncated ODOM"),
    "rawlaser count mismatch": ("RAWLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 4 1 2 3 0 100.0 nohost 0.1\n", 1,
                                "remission count must be an integer, found '100.0'"),
    "rawlaser truncated": ("RAWLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 4 1 2\n", 1,
                           "RAWLASER1 declares 4 readings but the line is truncated"),
    "rawlaser extra fields": ("RAWLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 2 1 2 0 100.0 nohost 0.1 x y\n", 1,
                              "needs 13..15 fields"),
    "empty": ("", None, "no laser scans"),
    "comments only": ("# nothing\nPARAM a b\n", None, "no laser scans"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_names_file_and_line(tmp_path, case):
    text, line, needle = BAD[case]
    p = write(tmp_path, text)
    with pytest.raises(InputError) as e:
        list(CarmenLog(p))
    msg = str(e.value)
    assert needle in msg
    assert msg.startswith(str(p))
    if line is not None:
        assert e.value.line == line and f"{p}:{line}:" in msg
    assert "\n" not in msg


def test_corrupt_compressed_files(tmp_path, flaser_line):
    text = "".join(flaser_line([1.0, 2.0], ts=f"{100 + i}.0") for i in range(2000))
    for opener, name in ((gzip.open, "x.clf.gz"), (bz2.open, "x.clf.bz2")):
        p = write(tmp_path, text, name, opener)
        data = p.read_bytes()
        p.write_bytes(data[: len(data) // 2])
        with pytest.raises(InputError) as e:
            list(CarmenLog(p))
        assert "corrupt or truncated" in str(e.value) and str(p) in str(e.value)
        p.write_bytes(b"garbage that is not compressed at all")
        with pytest.raises(InputError):
            list(CarmenLog(p))


def test_binary_garbage(tmp_path):
    p = tmp_path / "x.clf"
    p.write_bytes(bytes(range(256)) * 10)
    with pytest.raises(InputError):
        list(CarmenLog(p))


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        open_source(tmp_path / "missing.clf")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(InputError, match="unknown file type"):
        open_source(tmp_path / "x.txt")


token = st.one_of(
    st.sampled_from(["FLASER", "ODOM", "PARAM", "ROBOTLASER1", "nan", "inf", "-inf", "nohost", "#", "1e400", ""]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-5, 400).map(str),
    st.text(alphabet="abc0123456789.-e+ ", max_size=8),
)
line = st.lists(token, max_size=30).map(" ".join)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lines=st.lists(line, max_size=8))
def test_fuzz_parser_fails_only_with_input_errors(tmp_path, lines):
    p = tmp_path / "fuzz.clf"
    p.write_text("\n".join(lines) + "\n")
    try:
        scans = list(CarmenLog(p))
    except InputError as e:
        assert str(e).startswith(str(p)) and "\n" not in str(e)
        return
    for s in scans:
        assert s.ranges.dtype == np.float32 and s.valid.shape == s.ranges.shape
        assert np.all(s.ranges[s.valid] > 0) and np.all(np.isfinite(s.ranges[s.valid]))
        assert math.isfinite(s.timestamp)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ranges=st.lists(st.floats(0.01, 80.0), min_size=1, max_size=50),
       pose=st.tuples(*[st.floats(-100, 100)] * 3))
def test_fuzz_valid_flaser_round_trips(tmp_path, flaser_line, ranges, pose):
    p = tmp_path / "ok.clf"
    p.write_text(flaser_line([f"{r:.3f}" for r in ranges], pose=pose))
    (s,) = list(CarmenLog(p))
    np.testing.assert_array_equal(s.ranges, np.float32([float(f"{r:.3f}") for r in ranges]))


def test_packed_records_give_back_exactly_what_was_parsed():
    """The in-memory store packs records into flat buffers; every field comes back bit for bit,
    remissions and a line's own max_range included (and their absence)."""
    from slam2d.io.carmen import _Block, _Parsed

    rng = np.random.default_rng(3)
    parsed = []
    for i in range(7):
        n = 5 + i
        inten = rng.random(n).astype(np.float32) if i % 2 else None
        parsed.append(_Parsed("ROBOTLASER1" if i % 3 else "FLASER", 1e9 + i / 3, f"{1e9 + i / 3:.6f}", rng.random(n) * 80,
                              -math.pi / 2 + i * 1e-3, math.pi / 180 * (1 + i), rng.random(3), rng.random(3),
                              None if i % 2 == 0 else 81.9 - i, inten))
    block = _Block()
    for i, p in enumerate(parsed):
        block.append(100 + i, p)
    for i, p in enumerate(parsed):
        lineno, q = block.record(i)
        assert lineno == 100 + i and q.kind == p.kind and q.timestamp == p.timestamp
        assert q.timestamp_text == p.timestamp_text and q.max_range == p.max_range
        assert (q.angle_min, q.angle_increment) == (p.angle_min, p.angle_increment)
        for a, b in ((q.ranges, p.ranges), (q.laser_pose, p.laser_pose), (q.robot_pose, p.robot_pose)):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        assert (q.intensities is None) == (p.intensities is None)
        if p.intensities is not None:
            assert q.intensities.dtype == np.float32 and np.array_equal(q.intensities, p.intensities)


def _rawlaser(ranges, ts, start=-math.pi / 2, res=math.pi / 4, kind="RAWLASER1"):
    r = " ".join(f"{v}" for v in ranges)
    return f"{kind} 0 {start!r} {math.pi!r} {res!r} 30.0 0.01 0 {len(ranges)} {r} 0 {ts} nohost 0.5\n"


def test_rawlaser_with_odom_reads_as_the_flaser_log_of_the_same_scans(tmp_path, flaser_line):
    """A log of RAWLASER1 and ODOM lines (no laser message with a pose) is read with the robot pose
    of the ODOM lines: where they are stamped like the scans, the scans are those of the FLASER log
    that holds the same readings and poses (laser at the robot's origin)."""
    rng = np.random.default_rng(0)
    poses = [(0.1 * k, 0.05 * k, 0.2 * k - 1.0) for k in range(6)]
    ranges = [np.round(rng.uniform(0.5, 9.0, 5), 2) for _ in poses]
    fl, raw = "", ""
    for k, (pose, r) in enumerate(zip(poses, ranges)):
        ts = f"{100 + 0.2 * k:.6f}"
        fl += flaser_line(list(r), pose=pose, ts=ts)
        raw += f"ODOM {pose[0]:.6f} {pose[1]:.6f} {pose[2]:.6f} 0 0 0 {ts} nohost 0.5\n" + _rawlaser(list(r), ts)
    a = list(CarmenLog(write(tmp_path, raw, "raw.clf")))
    b = list(CarmenLog(write(tmp_path, fl, "fl.clf")))
    assert len(a) == len(b) == 6
    for x, y in zip(a, b):
        assert x.timestamp_text == y.timestamp_text
        np.testing.assert_array_equal(x.ranges, y.ranges)
        np.testing.assert_array_equal(x.valid, y.valid)
        np.testing.assert_allclose(x.odom_pose, y.odom_pose, atol=1e-12)
        np.testing.assert_array_equal(x.laser_offset, np.zeros(3))
        assert x.angle_min == y.angle_min and x.angle_increment == y.angle_increment
    f = CarmenLog(tmp_path / "raw.clf").facts()
    assert f.laser_messages == "RAWLASER1" and "ODOM" in f.odometry


def test_rawlaser_odometry_is_interpolated_and_held_at_the_ends(tmp_path):
    text = ("ODOM 0 0 3.0 0 0 0 10.0 nohost 0\n"
            "ODOM 1 2 -3.0 0 0 0 11.0 nohost 0\n")  # θ crosses ±π: the short way is +0.28 rad
    text += "".join(_rawlaser([1.0, 2.0, 3.0], ts) for ts in ("9.5", "10.25", "10.5", "12.0"))
    scans = list(CarmenLog(write(tmp_path, text)))
    np.testing.assert_allclose(scans[0].odom_pose, [0, 0, 3.0])  # before the first ODOM: held
    short = math.remainder(-3.0 - 3.0, 2 * math.pi)
    np.testing.assert_allclose(scans[1].odom_pose, [0.25, 0.5, math.remainder(3.0 + 0.25 * short, 2 * math.pi)])
    np.testing.assert_allclose(scans[2].odom_pose, [0.5, 1.0, math.remainder(3.0 + 0.5 * short, 2 * math.pi)])
    np.testing.assert_allclose(scans[3].odom_pose, [1, 2, -3.0])  # after the last: held
    # no ODOM lines: scans without odometry
    bare = list(CarmenLog(write(tmp_path, _rawlaser([1.0, 2.0], "5.0") + _rawlaser([1.0, 2.0], "5.1"), "bare.clf")))
    assert len(bare) == 2 and all(s.odom_pose is None for s in bare)
    assert "none" in CarmenLog(tmp_path / "bare.clf").facts().odometry


def test_rawlaser_lines_beside_laser_lines_with_poses_are_skipped(tmp_path, flaser_line):
    """A log holds RAWLASER1 and FLASER lines for the same scans when the robot module ran: the
    FLASER lines are read, once each."""
    text = ""
    for k in range(4):
        ts = f"{50 + 0.1 * k:.6f}"
        text += _rawlaser([1.0, 2.0, 3.0], ts) + flaser_line([1.0, 2.0, 3.0], pose=(0.1 * k, 0, 0), ts=ts)
    log = CarmenLog(write(tmp_path, text))
    assert len(list(log)) == 4 and log.facts().laser_messages == "FLASER"


def test_of_several_raw_lasers_the_one_with_the_most_lines_is_read(tmp_path):
    text = "".join(_rawlaser([1.0, 2.0], f"{k}.0", kind="RAWLASER1") for k in range(2))
    text += "".join(_rawlaser([4.0, 5.0, 6.0], f"{k}.5", kind="RAWLASER2") for k in range(5))
    scans = list(CarmenLog(write(tmp_path, text)))
    assert len(scans) == 5 and all(s.num_beams == 3 for s in scans)


def test_no_return_survey_batches_end_as_scan_by_scan(monkeypatch):
    """The survey runs its kernel over batches of scans; its histogram, maximum and no-return values
    must be those of surveying one scan at a time, including when the log's maximum rises late (the
    early scans' bands were cut against a lower maximum) and when the histogram compacts midway."""
    from slam2d.io import carmen

    rng = np.random.default_rng(3)
    scans = []
    for i in range(400):
        top = 20.0 if i < 150 else 81.9  # the maximum rises late
        r = rng.uniform(0.5, top, 181)
        r[rng.random(181) < 0.2] = 81.83 if i >= 150 else 19.5  # two spikes, the first one early
        r[rng.random(181) < 0.05] = np.inf
        r[rng.random(181) < 0.02] = np.nan
        scans.append(r)

    def survey(batch, compact_every):
        monkeypatch.setattr(carmen.NoReturnSurvey, "BATCH", batch)
        monkeypatch.setattr(carmen.NoReturnSurvey, "COMPACT_EVERY", compact_every)
        s = carmen.NoReturnSurvey()
        for r in scans:
            s.add(r)
        spikes = s.spikes(400 * 181)
        return s.max_reading, s.values.copy(), s.counts.copy(), spikes

    for compact_every in (1 << 20, 500):
        one = survey(1, compact_every)  # every add flushes: scan by scan
        for batch in (7 * 181, 1 << 16):
            many = survey(batch, compact_every)
            assert many[0] == one[0]
            np.testing.assert_array_equal(many[1], one[1])
            np.testing.assert_array_equal(many[2], one[2])
            assert many[3] == one[3]
    assert [s["value"] for s in one[3]] == [81.83]


def test_range_tokens_parse_as_python_floats():
    """Readings are parsed by numpy in one call: the values must be those of ``float`` for every
    spelling a log may hold, and a bad token must still name itself."""
    from slam2d.errors import InputError
    from slam2d.io.carmen import _float_array

    tokens = ["1.5", "81.83", "1e-3", "-0", "+2.25", "1.", ".5", "nan", "inf", "1e500", "0.1000000000000000055511151231257827"]
    got = _float_array("x.clf", 3, tokens, "range reading")
    want = np.array([float(t) for t in tokens])
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, want)
    assert _float_array("x.clf", 3, tokens[:2], "remission", np.float32).tolist() == np.array([1.5, 81.83], np.float32).tolist()
    with pytest.raises(InputError, match="x.clf:3: non-numeric range reading '0x10'"):
        _float_array("x.clf", 3, ["1.0", "0x10"], "range reading")


def test_scan_period_restamps_a_log_whose_timestamps_are_unusable(tmp_path, flaser_line):
    """The MIT Infinite Corridor's corrected log: a few negative stamps, then 4.29497e+09 on every scan (a
    32-bit wrap). Read as it is, the jump back is an error that names the way out; with
    ``scan_period`` the scans are stamped that far apart in file order, and nothing else changes."""
    stamps = ["-1.392", "-0.446", "-1.82", "4.29497e+09", "4.29497e+09"]
    text = "".join(flaser_line([1.0 + k, 2.0], ts=t) for k, t in enumerate(stamps))
    p = write(tmp_path, text)
    with pytest.raises(InputError) as e:
        list(CarmenLog(p))
    assert e.value.line == 3 and "--scan-period" in str(e.value) and "\n" not in str(e.value)
    scans = list(CarmenLog(p, scan_period=0.2))
    assert [s.timestamp for s in scans] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8], abs=1e-12)
    assert [s.timestamp_text for s in scans] == ["0.000000", "0.200000", "0.400000", "0.600000", "0.800000"]
    assert [float(s.ranges[0]) for s in scans] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert [s.index for s in scans] == list(range(5))


def test_scan_period_is_refused_where_it_cannot_be_right(tmp_path):
    from conftest import BUNDLED

    log = write(tmp_path, "ODOM 0 0 0 0 0 0 100.0 nohost 0.1\n"
                          "RAWLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 4 1 2 3 4 0 100.0 nohost 0.1\n")
    with pytest.raises(InputError, match="RAWLASER lines"):  # odometry found by timestamp
        list(CarmenLog(log, scan_period=0.1))
    with pytest.raises(InputError, match="CARMEN logs only"):  # ROS input: odometry and TF by stamp
        open_source(BUNDLED, scan_period=0.1)
    for bad in (0.0, -0.1, float("nan")):
        with pytest.raises(InputError, match="positive number of seconds"):
            CarmenLog(log, scan_period=bad)


def _front_and_rear(tmp_path, n_front=300, n_rear=300):
    """A 20 m front laser (FLASER, no-return 20.0) and an 81.9 m rear one (RLASER, no-return 81.9)."""
    rng = np.random.default_rng(0)
    lines, front = [], []
    for k in range(max(n_front, n_rear)):
        if k < n_front:
            f = np.round(rng.uniform(0.5, 18.0, 180), 2)
            f[rng.random(180) < 0.2] = 20.0
            front.append(f)
            lines.append("FLASER 180 " + " ".join(f"{v:.2f}" for v in f) + f" 0.2 0 0 0 0 0 {100 + 0.2 * k:.3f} h 0")
        if k < n_rear:
            r = np.round(rng.uniform(0.3, 40.0, 180), 2)
            r[rng.random(180) < 0.3] = 81.9
            lines.append("RLASER 180 " + " ".join(f"{v:.2f}" for v in r) + f" -0.2 0 3.141593 0 0 0 {100.1 + 0.2 * k:.3f} h 0")
    return write(tmp_path, "\n".join(lines) + "\n"), front


def test_a_log_with_a_front_and_a_rear_laser_is_read_from_one(tmp_path):
    """slam2d maps with one laser: of a front and a rear laser with as many lines the front is read, and
    the rear skipped and said so. The front is judged by its own readings: its no-return value 20.0 lies
    below 0.9 × the rear's 81.9, where a survey of both lasers' readings never looked."""
    log, front = _front_and_rear(tmp_path)
    facts = CarmenLog(log).facts()
    assert facts.laser_messages == "FLASER" and facts.skipped_lasers == {"RLASER": 300}
    assert facts.num_scans == 300 and facts.no_return_value == 20.0
    scans = list(CarmenLog(log))
    assert len(scans) == 300 and [s.index for s in scans] == list(range(300))
    for s, f in zip(scans, front):
        np.testing.assert_array_equal(s.ranges, np.float32(f))
        np.testing.assert_array_equal(s.no_return, f >= 20.0)
    # more rear lines than front ones: the rear is read
    log, _ = _front_and_rear(tmp_path, n_front=100, n_rear=300)
    facts = CarmenLog(log).facts()
    assert facts.laser_messages == "RLASER" and facts.skipped_lasers == {"FLASER": 100}
    assert facts.no_return_value == 81.9 and len(list(CarmenLog(log))) == 300


def test_a_stamp_far_ahead_is_warned_about_once(tmp_path, flaser_line, caplog):
    import logging

    text = "".join(flaser_line([1.0, 2.0], ts=ts) for ts in ("100.0", "100.2", "2000000000.0", "2000000000.2"))
    with caplog.at_level(logging.WARNING):
        scans = list(CarmenLog(write(tmp_path, text)))
    assert len(scans) == 4
    msgs = [r.getMessage() for r in caplog.records if "jumps" in r.getMessage()]
    assert len(msgs) == 1 and ":3: timestamp 2000000000.0 jumps 2e+09 s ahead of the scan of line 2" in msgs[0], msgs


def test_a_no_return_value_beyond_float32_reads_as_inf_without_a_warning(tmp_path, flaser_line):
    import warnings

    text = "".join(flaser_line([1.0, "1e300", 2.0, "1e300"], ts=f"{100 + i}.0") for i in range(20))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = list(CarmenLog(write(tmp_path, text)))
    assert all(s.no_return[[1, 3]].all() and s.valid[[0, 2]].all() for s in scans)
