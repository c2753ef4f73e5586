"""SE(2) helpers: the single-pose fast paths agree with the batch formulas and with gtsam."""
import numpy as np

from slam2d.geometry import between, compose, inverse


def test_between_single_equals_batch_and_gtsam():
    import gtsam

    rng = np.random.default_rng(2)
    a = np.c_[rng.uniform(-20, 20, (200, 2)), rng.uniform(-np.pi, np.pi, 200)]
    b = np.c_[rng.uniform(-20, 20, (200, 2)), rng.uniform(-np.pi, np.pi, 200)]
    batch = between(a, b)
    for i in range(200):
        single = between(a[i], b[i])
        np.testing.assert_allclose(single, batch[i], atol=1e-12)
        ref = gtsam.Pose2(*a[i]).between(gtsam.Pose2(*b[i]))
        np.testing.assert_allclose(single, [ref.x(), ref.y(), ref.theta()], atol=1e-9)
        back = compose(a[i], single) - b[i]
        back[2] = (back[2] + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(back, 0.0, atol=1e-9)
    np.testing.assert_allclose(compose(inverse(a[0]), a[0]), [0, 0, 0], atol=1e-12)
