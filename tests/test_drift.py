"""The drift bound that sizes loop-search windows (slam2d/backend/drift.py), against a
Floyd–Warshall reference over every node of the trajectory."""
import math

import numpy as np

from slam2d.backend.drift import DriftBound


def _reference(budget, loops):
    """All-pairs shortest budget distances: the trajectory is a chain (edge = budget difference),
    each loop a free edge; per coordinate."""
    n = len(budget)
    out = []
    for c in range(2):
        d = np.full((n, n), np.inf)
        np.fill_diagonal(d, 0.0)
        for i in range(n - 1):
            w = budget[i + 1, c] - budget[i, c]
            d[i, i + 1] = d[i + 1, i] = w
        for a, j in loops:
            d[a, j] = d[j, a] = 0.0
        for k in range(n):
            d = np.minimum(d, d[:, k:k + 1] + d[k:k + 1, :])
        out.append(d)
    return out


def _random_run(rng, n):
    db = DriftBound(0.03, math.radians(0.3))
    steps = rng.uniform(0, 1.5, n)
    steps[rng.random(n) < 0.2] = 0.0  # standing still: zero-length runs
    doubt = np.zeros((n, 2))
    bad = rng.random(n) < 0.1
    doubt[bad] = [2.0, math.radians(45)]
    ids = list(range(100, 100 + 3 * n, 3))  # node ids are scan indices, not positions
    for i in range(n):
        db.add(ids[i], steps[i] if i else 0.0, *doubt[i])
    budget = np.cumsum(np.c_[0.03 * steps, math.radians(0.3) * steps] * (np.arange(n) > 0)[:, None] + doubt, axis=0)
    return db, ids, budget


def test_budget_adds_drift_per_metre_and_the_doubt_of_untrusted_steps():
    db = DriftBound(0.03, math.radians(0.3))
    db.add(0, 0.0)
    db.add(1, 10.0)
    db.add(2, 10.0, 2.0, math.radians(45))
    t, r = db.between(0, 2)
    assert math.isclose(t, 0.6 + 2.0) and math.isclose(r, math.radians(6 + 45))
    t, r = db.between(2, 1)
    assert math.isclose(t, 0.3 + 2.0) and math.isclose(r, math.radians(3 + 45))


def test_distances_from_the_newest_node_equal_all_pairs_shortest_paths():
    rng = np.random.default_rng(11)
    for trial in range(25):
        n = int(rng.integers(2, 40))
        db, ids, budget = _random_run(rng, n)
        m = int(rng.integers(0, 8))
        loops = [tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(m)] if n > 1 else []
        db.update([(ids[a], ids[j]) for a, j in loops])
        ref = _reference(budget, loops)
        last = n - 1
        for a in range(n):
            got = db.between(ids[a], ids[last])
            for c in range(2):
                assert math.isclose(got[c], ref[c][a, last], rel_tol=1e-9, abs_tol=1e-9), (trial, a, loops)
        # between any two nodes: never below the true graph distance (windows err on the wide
        # side), and exact when the cheapest way passes the newest node or no loop helps
        for a in range(n):
            for j in range(n):
                got = db.between(ids[a], ids[j])
                for c in range(2):
                    assert got[c] >= ref[c][a, j] - 1e-9
                    direct = abs(budget[a, c] - budget[j, c])
                    via = ref[c][a, last] + ref[c][last, j]
                    assert math.isclose(got[c], min(direct, via), rel_tol=1e-9, abs_tol=1e-9)


def test_only_loops_of_the_last_update_are_shortcuts_and_later_nodes_extend_the_run():
    db = DriftBound(0.1, 0.01)
    for i in range(5):
        db.add(i, 0.0 if i == 0 else 10.0)  # budgets 0, 1, 2, 3, 4 (m)
    db.update([(0, 4)])  # the estimates reflect a loop from node 4 back to node 0
    assert math.isclose(db.between(0, 4)[0], 0.0, abs_tol=1e-9)
    assert math.isclose(db.between(1, 4)[0], 1.0)
    db.add(5, 20.0)  # 2 m of budget after the update; a loop found now is not in the estimates yet
    assert math.isclose(db.between(0, 5)[0], 2.0)
    assert math.isclose(db.between(2, 5)[0], 2.0 + 2.0)  # through node 4 and the loop, or straight: 4 m
    assert math.isclose(db.between(3, 5)[0], 3.0)        # straight back along the run
    db.update([(0, 4), (3, 5)])
    assert math.isclose(db.between(3, 5)[0], 0.0, abs_tol=1e-9)
    assert math.isclose(db.between(0, 5)[0], 1.0)  # 5 → 3 free, 3 → 4 one metre, 4 → 0 free


def test_shortest_distances_kernel_matches_scipy():
    """The drift bound's Dijkstra against scipy's on random undirected graphs: parallel edges (the
    lightest counts), zero weights (free loops), vertices nothing reaches."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    from slam2d.backend._kernels import shortest_distances

    rng = np.random.default_rng(3)
    for trial in range(40):
        n = int(rng.integers(1, 60))
        m = int(rng.integers(0, 3 * n))
        heads, tails = rng.integers(0, n, m), rng.integers(0, n, m)
        w = np.where(rng.random(m) < 0.2, 0.0, rng.uniform(0, 5, m))
        src = int(rng.integers(0, n))
        got = shortest_distances(n, heads.astype(np.int64), tails.astype(np.int64), w, src)
        # scipy sums parallel entries and drops zero ones: give it the lightest of each pair, zero as tiny
        best = {}
        for a, b, x in zip(heads, tails, w):
            key = (min(a, b), max(a, b))
            best[key] = min(best.get(key, np.inf), x)
        keys = [k for k in best if k[0] != k[1]]
        g = coo_matrix(([best[k] + 1e-300 for k in keys], ([k[0] for k in keys], [k[1] for k in keys])), shape=(n, n))
        want = dijkstra(g.tocsr(), directed=False, indices=src)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-200)
        assert got[src] == 0.0
