import numpy as np

from glaciar.engine.positions import draw_positions


def _boxes_disjoint(x, y, hh, hw):
    iy, ix = np.rint(y).astype(int), np.rint(x).astype(int)
    for i in range(x.size):
        for j in range(i + 1, x.size):
            if abs(iy[i] - iy[j]) <= hh[i] + hh[j] and abs(ix[i] - ix[j]) <= hw[i] + hw[j]:
                return False
    return True


def test_positions_inside_footprint_and_disjoint():
    rng = np.random.default_rng(1)
    fp = np.zeros((300, 400), bool)
    fp[50:250, 20:380] = True
    fp[100:120, :] = False           # a chip gap
    hh = np.full(60, 6)
    hw = np.full(60, 9)
    x, y = draw_positions(rng, fp, hh, hw)
    assert x.size == 60
    assert fp[np.rint(y).astype(int), np.rint(x).astype(int)].all()
    assert _boxes_disjoint(x, y, hh, hw)


def test_positions_uniform_over_footprint():
    # Two disjoint valid regions of area ratio 3:1 receive centres in that ratio.
    fp = np.zeros((200, 200), bool)
    fp[:, :150] = True              # area 30000
    fp[:, 150:] = False
    fp[:50, 150:] = True            # area 2500... total right = 2500
    counts = np.zeros(2)
    rng = np.random.default_rng(7)
    for _ in range(300):
        x, y = draw_positions(rng, fp, np.zeros(5, int), np.zeros(5, int))
        counts += [np.sum(x < 149.5), np.sum(x >= 149.5)]
    frac_right = counts[1] / counts.sum()
    expect = 2500 / 32500
    sigma = np.sqrt(expect * (1 - expect) / counts.sum())
    assert abs(frac_right - expect) < 4 * sigma


def test_positions_subpixel_uniform_and_deterministic():
    fp = np.ones((100, 100), bool)
    a = draw_positions(np.random.default_rng(3), fp, np.full(10, 2), np.full(10, 2))
    b = draw_positions(np.random.default_rng(3), fp, np.full(10, 2), np.full(10, 2))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    fx = a[0] - np.rint(a[0])
    assert np.all(np.abs(fx) < 0.5)


def test_positions_crowded_returns_fewer():
    fp = np.ones((30, 30), bool)
    x, y = draw_positions(np.random.default_rng(0), fp, np.full(50, 10), np.full(50, 10), max_batches=20)
    assert 1 <= x.size < 50
    assert _boxes_disjoint(x, y, np.full(x.size, 10), np.full(x.size, 10))
