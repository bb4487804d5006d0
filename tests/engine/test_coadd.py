"""Coadded detection images: the stacks against hand formulas and scipy, windows against full frames."""
import numpy as np
import pandas as pd
import pytest
import yaml
from scipy import stats

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.engine.coadd import CoaddScene, coadd
from glaciar.engine.scene import Scene


def test_ivw_stack_is_the_weighted_mean_and_its_noise():
    a = np.array([[1.0, 2.0], [3.0, 4.0]])
    b = np.array([[3.0, 6.0], [5.0, 0.0]])
    ra = np.array([[1.0, 1.0], [2.0, 1.0]])
    rb = np.array([[1.0, 2.0], [np.inf, 0.0]])       # b has no data in the bottom row
    img, rms = coadd([a, b], [ra, rb], "ivw")
    np.testing.assert_allclose(img, [[2.0, (2 + 6 / 4) / 1.25], [3.0, 4.0]])
    np.testing.assert_allclose(rms, [[1 / np.sqrt(2), 1 / np.sqrt(1.25)], [2.0, 1.0]])
    # no band with data -> no data
    img, rms = coadd([a], [np.full((2, 2), np.inf)], "ivw")
    assert np.all(img == 0) and np.all(np.isinf(rms))


def test_ivw_noise_matches_the_measured_scatter():
    rng = np.random.default_rng(1)
    sig = (1.0, 2.0, 0.5)
    imgs = [rng.normal(scale=s, size=(300, 300)) for s in sig]
    img, rms = coadd(imgs, [np.full((300, 300), s) for s in sig], "ivw")
    assert img.std() == pytest.approx(rms[0, 0], rel=0.01)
    assert rms[0, 0] == pytest.approx(1 / np.sqrt(sum(1 / s ** 2 for s in sig)))


def test_chi2_stack_is_standard_normal_on_noise_and_matches_scipy():
    rng = np.random.default_rng(2)
    sig = (1.0, 3.0, 0.2)
    imgs = [rng.normal(scale=s, size=(200, 200)) for s in sig]
    z, rms = coadd(imgs, [np.full((200, 200), s) for s in sig], "chi2")
    assert np.all(rms == 1.0)
    assert stats.kstest(z.ravel(), "norm").pvalue > 0.01
    # one pixel by hand: chi2 with 3 dof, then the normal deviate of the same upper tail
    x = sum((im[5, 7] / s) ** 2 for im, s in zip(imgs, sig))
    assert z[5, 7] == pytest.approx(stats.norm.isf(stats.chi2.sf(x, 3)), rel=1e-9)
    # a bright pixel is far out in the tail, finite
    imgs[0][0, 0] = 1e3
    z, _ = coadd(imgs, [np.full((200, 200), s) for s in sig], "chi2")
    assert np.isfinite(z[0, 0]) and z[0, 0] > 30


@pytest.mark.parametrize("method", ["ivw", "chi2"])
def test_coadd_scene_windows_are_the_stack_of_the_injected_bands(method):
    rng = np.random.default_rng(3)
    shape = (60, 80)
    bases = [rng.normal(size=shape), rng.normal(scale=2.0, size=shape)]
    rms = [np.ones(shape), np.full(shape, 2.0)]
    rms[1][:, :10] = np.inf
    stamp = np.outer(np.hanning(9), np.hanning(11))
    scenes = [Scene(bases[0], [(20, 30, stamp, 50.0), (-3, 70, stamp, 10.0)]),
              Scene(bases[1], [(20, 30, stamp, 80.0)])]
    full = coadd([s.full() for s in scenes], rms, method)[0]
    cs = CoaddScene(scenes, rms, method)
    np.testing.assert_allclose(cs.window(15, 40, 5, 50), full[15:40, 5:50], rtol=0, atol=1e-12)
    rects = np.array([[15, 40, 5, 50], [0, 10, 60, 80]])
    canvas = np.full((40, 70), -7.0)
    cs.paste_windows(canvas, rects, [0, 28], [0, 48])
    np.testing.assert_allclose(canvas[:25, :45], full[15:40, 5:50], atol=1e-12)
    np.testing.assert_allclose(canvas[28:38, 48:68], full[0:10, 60:80], atol=1e-12)
    assert np.all(canvas[25:28, :] == -7.0)            # outside the windows: untouched


def test_a_coadd_detects_what_one_band_misses(small_survey, tmp_path):
    """Flat-spectrum sources at z = 8 have flux in J and H: stacking them detects more."""
    from glaciar.engine.task import TaskSpec, run_task
    from glaciar.fieldprep import build_field_context
    from glaciar.survey import Survey

    data = yaml.safe_load(small_survey.read_text())
    data["simulation"]["n_galaxies"] = 40
    detected = {}
    for name, image in (("band", None), ("coadd", {"coadd": ["f160w", "f125w"], "method": "ivw"})):
        if image is not None:
            data["survey"]["detection_image"] = image
        p = small_survey.parent / f"coadd_{name}.yaml"
        p.write_text(yaml.safe_dump(data, sort_keys=False))
        cfg = load_config(p)
        ctx = build_field_context(cfg, Survey.from_config(cfg), "demo01")
        rows = pd.concat([run_task(ctx, TaskSpec("demo01", 0, 0, 0, i, 8.0, 27.5), seed=2)
                          for i in range(4)])
        detected[name] = np.mean(rows[C.COL_STATUS] != C.STATUS_NOT_DETECTED)
    assert detected["coadd"] > detected["band"]


# ------------------------------------------------------------------------------
# Field set-up with bounded memory gives the same answers.
# ------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["ivw", "chi2"])
def test_coadd_by_row_blocks_is_the_pixelwise_stack(monkeypatch, tmp_path, method):
    """The stack of a large image by blocks of 2 rows (inputs memory-mapped, float32 output)
    against its definition on whole arrays: inverse-variance mean and 1/sqrt(sum w), or the
    Gaussianised chi-square deviate of the bands with data."""
    from scipy import special

    from glaciar.engine import coadd as co

    rng = np.random.default_rng(12)
    shape = (41, 23)
    images = [rng.standard_normal(shape).astype(np.float32) * s for s in (1.0, 2.0, 0.5)]
    rms = [np.full(shape, s, np.float32) for s in (1.0, 2.0, 0.5)]
    rms[0][3:9, 4:6] = np.inf
    rms[1][3:7, 4:5] = 0.0
    rms[2][3:5, 4:5] = np.nan                            # (3..4, 4): no band has data
    images[1][10, 10] = 1e3                              # a bright pixel: large chi2
    maps = []
    for k, a in enumerate(images + rms):
        np.save(tmp_path / f"{k}.npy", a)
        maps.append(np.load(tmp_path / f"{k}.npy", mmap_mode="r"))
    with np.errstate(divide="ignore"):
        w = [np.where(np.isfinite(r) & (r > 0), 1.0 / np.square(r.astype(np.float64)), 0.0)
             for r in rms]
    wsum = sum(w)
    has = wsum > 0
    if method == "ivw":
        with np.errstate(divide="ignore", invalid="ignore"):
            want = (np.where(has, sum(wi * np.where(wi > 0, im, 0.0) for wi, im in zip(w, images)) / wsum, 0),
                    np.where(has, 1.0 / np.sqrt(wsum), np.inf))
    else:
        x = sum(wi * np.where(wi > 0, im.astype(np.float64), 0.0) ** 2 for wi, im in zip(w, images))
        k = sum((wi > 0).astype(int) for wi in w)
        z = np.zeros(shape)
        z[has] = np.clip(-special.ndtri(np.clip(special.chdtrc(k[has], x[has]), 1e-300, 1)), -37, 37)
        want = (z, np.where(has, 1.0, np.inf))
    monkeypatch.setattr(co, "COADD_BLOCK_PIXELS", 2 * shape[1])
    got = co.coadd(maps[:3], maps[3:], method)
    got32 = co.coadd(maps[:3], maps[3:], method, dtype=np.float32)
    for g, g32, wnt in zip(got, got32, want):
        assert g.dtype == np.float64 and g32.dtype == np.float32
        assert np.allclose(g, wnt, rtol=1e-12, atol=0) or np.array_equal(g, wnt)
        assert np.array_equal(g32, g.astype(np.float32))
    monkeypatch.setattr(co, "COADD_BLOCK_PIXELS", 1 << 20)
    for g, whole in zip(got, co.coadd(images, rms, method)):
        assert np.array_equal(g, whole)                  # bit for bit: the same pixelwise ops
    assert (~has).sum() == 2 and np.isinf(got[1][~has]).all()
