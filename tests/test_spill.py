"""slam2d.spill: per-scan arrays on disk come back as they went in."""
import numpy as np
import pytest

from slam2d.spill import DTYPES, ArraySpill


def test_records_come_back_equal_in_order_with_their_dtypes_and_shapes():
    rng = np.random.default_rng(0)
    spill = ArraySpill(3)
    want = []
    for k in range(200):
        rec = (rng.random((int(rng.integers(0, 40)), 2)).astype(np.float32),
               None if k % 3 == 0 else rng.integers(0, 60000, int(rng.integers(0, 9))).astype(np.uint16),
               rng.random(int(rng.integers(1, 5))))
        spill.append(*rec)
        want.append(rec)
        if k == 77:  # read in the middle: appending goes on afterwards
            assert len(spill.records()) == 78
    got = spill.records()
    assert len(spill) == len(got) == 200
    for w, g in zip(want, got):
        for a, b in zip(w, g):
            if a is None:
                assert b is None
                continue
            assert b.dtype == a.dtype and b.shape == a.shape
            np.testing.assert_array_equal(a, b)
            assert b.flags.c_contiguous and b.flags.aligned and b.flags.writeable
    spill.close()


def test_an_empty_spill_and_empty_arrays():
    spill = ArraySpill(2)
    assert spill.records() == []
    spill.append(np.zeros((0, 2), np.float32), np.zeros(0, np.int64))
    (a, b), = spill.records()
    assert a.shape == (0, 2) and b.shape == (0,)


def test_what_it_does_not_take():
    spill = ArraySpill(1)
    with pytest.raises(ValueError):
        spill.append(np.zeros((2, 2)), np.zeros(2))  # two arrays for a record of one
    with pytest.raises(ValueError):
        spill.append(np.zeros((2, 2, 2)))
    with pytest.raises(ValueError):
        spill.append(np.zeros(3, np.int8))  # not one of DTYPES
    assert np.dtype(np.int8) not in DTYPES
