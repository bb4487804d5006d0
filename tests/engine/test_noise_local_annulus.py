"""Empty apertures summed about their local background (issue 24): the annulus pixels of an
aperture are found from its centre's flat index and fixed offsets, with per-pixel bounds
only near an edge.  Checked against an independent per-aperture computation in which
every annulus pixel is tested against the frame, on an image small enough that most
annuli are cut by an edge and large enough that some are not."""
import numpy as np
import pytest
from scipy import ndimage

from glaciar.engine.noise import (ANNULUS_AREA_FACTOR, ANNULUS_GAP_PIX, ANNULUS_MIN_PIXELS,
                                  MIN_EMPTY_APERTURES, empty_aperture_scatter,
                                  empty_sky_distance, robust_sigma)

RADII = (1.2, 3.2, 6.2)
N_PER_RADIUS = 150


def _reference_local_ratios(image, rms, usable, radii, n_per_radius, seed):
    """The ratios about local planes, aperture by aperture, every pixel bounds-checked."""
    ny, nx = usable.shape
    rng = np.random.default_rng(seed)
    dist = empty_sky_distance(usable).ravel()
    out = []
    for r in radii:
        k = int(np.ceil(r))
        ap = [(dy, dx) for dy in range(-k, k + 1) for dx in range(-k, k + 1) if dy * dy + dx * dx < r * r]
        centres = np.flatnonzero(dist > r + 1.0)
        if centres.size < MIN_EMPTY_APERTURES:
            continue
        drawn = centres[rng.choice(centres.size, size=min(n_per_radius, centres.size), replace=False)]
        npix = len(ap)
        r_in = r + ANNULUS_GAP_PIX
        r_out = np.sqrt(max(ANNULUS_AREA_FACTOR * npix, ANNULUS_MIN_PIXELS) / np.pi + r_in * r_in)
        ko = int(np.ceil(r_out))
        ring = [(dy, dx) for dy in range(-ko, ko + 1) for dx in range(-ko, ko + 1)
                if r_in * r_in <= dy * dy + dx * dx < r_out * r_out]
        ts, vs = [], []
        for c in drawn:
            cy, cx = divmod(int(c), nx)
            s = sum(float(image[cy + dy, cx + dx]) for dy, dx in ap)
            v = sum(float(rms[cy + dy, cx + dx]) ** 2 for dy, dx in ap)
            rows, ws, bs = [], [], []
            for dy, dx in ring:
                y, x = cy + dy, cx + dx
                if 0 <= y < ny and 0 <= x < nx and usable[y, x]:
                    rows.append((1.0, dx / (r + 1.0), dy / (r + 1.0)))
                    ws.append(1.0 / float(rms[y, x]) ** 2)
                    bs.append(float(image[y, x]))
            if 2 * len(rows) < len(ring):
                continue                        # less than half the annulus usable
            X, w, b = np.array(rows), np.array(ws), np.array(bs)
            normal = X.T @ (w[:, None] * X)
            cov = np.linalg.inv(normal)
            level = (cov @ (X.T @ (w * b)))[0]
            ts.append(s - npix * level)
            vs.append(v + npix * npix * cov[0, 0])
        ts, vs = np.array(ts), np.array(vs)
        out.append(robust_sigma(ts / np.sqrt(vs)) if ts.size >= MIN_EMPTY_APERTURES else np.nan)
    return np.array(out)


@pytest.mark.parametrize("shape", [(70, 80), (160, 150)])
def test_local_ratios_match_a_per_aperture_computation(shape):
    rng = np.random.default_rng(11)
    holes = rng.random(shape) < 0.003
    usable = ~ndimage.binary_dilation(holes, iterations=2)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    # A gradient (what the local plane removes) on correlated noise, and a varying map.
    image = (ndimage.uniform_filter(rng.normal(size=shape), 2) + 0.01 * xx - 0.02 * yy)
    rms = 0.6 + 0.2 * rng.random(shape)
    got = empty_aperture_scatter(image, rms, usable, RADII, N_PER_RADIUS,
                                 np.random.default_rng(5), local=True)
    want = _reference_local_ratios(image, rms, usable, RADII, N_PER_RADIUS, 5)
    assert got[0].size == want.size == len(RADII)
    assert np.all(np.isfinite(want))
    np.testing.assert_allclose(got[3], want, rtol=1e-9)
