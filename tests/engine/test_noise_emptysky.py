"""Empty-aperture draws read only the drawn candidates (issue 24, point 1): EmptySky's
counts and picks by chunks equal those of the whole candidate array."""
import numpy as np
import pytest
from scipy import ndimage

from glaciar.engine.noise import empty_aperture_scatter, empty_sky, empty_sky_distance


@pytest.fixture(scope="module")
def usable():
    rng = np.random.default_rng(4)
    holes = rng.random((150, 170)) < 0.004
    return ~ndimage.binary_dilation(holes, iterations=3)


LIMITS = (2.0, 3.0, 5.5, 9.0)


@pytest.mark.parametrize("chunk", [1, 7, 1000, None])
def test_counts_and_picks_by_chunks(usable, chunk):
    sky = empty_sky(usable, LIMITS)
    dist = empty_sky_distance(usable).ravel()         # independent: the whole map, uncapped
    rng = np.random.default_rng(1)
    for lim in LIMITS:
        want = np.flatnonzero(dist > lim)
        assert want.size > 50
        assert sky.count_beyond(lim, chunk=chunk) == want.size
        pos = rng.choice(want.size, size=40, replace=False)    # unsorted, as a draw is
        got = sky.take_beyond(lim, pos, chunk=chunk)
        assert np.array_equal(got, want[pos]), lim
    with pytest.raises(IndexError):
        sky.take_beyond(LIMITS[-1], [sky.count_beyond(LIMITS[-1])], chunk=chunk)


def test_apertures_are_those_of_the_distance_map(usable):
    """The same apertures and ratios from the EmptySky (drawn candidates gathered) as from the
    full distance map (every candidate listed)."""
    rng = np.random.default_rng(3)
    image = rng.normal(size=usable.shape)
    rms = np.ones(usable.shape)
    radii = (1.0, 2.0, 4.5)
    a = empty_aperture_scatter(image, rms, usable, radii, 200, np.random.default_rng(9),
                               sky=empty_sky(usable, [r + 1.0 for r in radii]), local=True)
    b = empty_aperture_scatter(image, rms, usable, radii, 200, np.random.default_rng(9),
                               distance=empty_sky_distance(usable), local=True)
    assert len(a[0]) == 3
    for x, y in zip(a, b):
        assert np.array_equal(x, y, equal_nan=True)


def test_empty_sky_holds_only_its_candidates(usable):
    """The indices and levels own exactly the candidates (not views of buffers sized for every
    usable pixel)."""
    sky = empty_sky(usable, LIMITS)
    n = np.count_nonzero(empty_sky_distance(usable) > LIMITS[0])
    assert n < np.count_nonzero(usable)
    for a in (sky.indices, sky.level):
        assert a.size == n and a.base is None and a.nbytes == n * a.itemsize


def test_memory_mapped_images_give_the_same_ratios(usable, tmp_path):
    """Images given as memory maps (a large field's spilled arrays, read by row blocks in the
    apertures and their local-background annuli) give the in-memory arrays' ratios."""
    rng = np.random.default_rng(5)
    image = rng.normal(size=usable.shape).astype(np.float32)
    rms = np.full(usable.shape, 1.3, dtype=np.float32)
    maps = []
    for name, a in (("img", image), ("rms", rms)):
        m = np.lib.format.open_memmap(tmp_path / f"{name}.npy", mode="w+", dtype=a.dtype, shape=a.shape)
        m[:] = a
        m.flush()
        maps.append(np.load(tmp_path / f"{name}.npy", mmap_mode="r"))
    radii = (1.0, 3.0)
    sky = empty_sky(usable, [r + 1.0 for r in radii])
    a = empty_aperture_scatter(image, rms, usable, radii, 150, np.random.default_rng(2), sky=sky, local=True)
    b = empty_aperture_scatter(*maps, usable, radii, 150, np.random.default_rng(2), sky=sky, local=True)
    assert isinstance(maps[0], np.memmap) and np.isfinite(a[3]).all()
    for x, y in zip(a, b):
        assert np.array_equal(x, y, equal_nan=True)
