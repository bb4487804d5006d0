"""Shot noise of the injected sources (source.shot_noise, glaciar/engine/shotnoise.py).

* Acceptance: the scatter of bright isolated injections' aperture fluxes equals the
  expected total, background + the sources' own Poisson noise, within 5 % (computed
  here from the aperture's pixel weights, the background RMS and the gain).
* Without gains nothing is drawn and rows equal a shot_noise: false run; with gains the
  task's own draws (positions, shapes, SEDs) are those of a noiseless run.
* Reproducible across worker counts; the same pixels whichever window reads them.
* Changing shot_noise refuses a resume.
"""
import dataclasses
import json
import shutil

import numpy as np
import pandas as pd
import pytest
from astropy.io import fits

from glaciar import constants as C
from glaciar.config import config_from_dict, load_config
from glaciar.engine import shotnoise
from glaciar.engine import task as task_mod
from glaciar.engine.scene import Scene
from glaciar.engine.task import TaskSpec, field_key, run_task
from glaciar.execute import simulate
from glaciar.fieldprep import build_field_context
from glaciar.rundir import StoreMismatchError, read_manifest, write_manifest
from glaciar.store import read_results
from glaciar.survey import Survey
from tiny_runs import sorted_rows, write_yaml

SIGMA = 0.01        #: background RMS per pixel [image units], white Gaussian
GAIN = 1000.0       #: electrons per image unit
SIDE = 360          #: image side [pixels]
APER_DIAMETER = 6.0  #: PHOT_APERTURES [pixels]
MAG = 23.25         #: flux 5.0 image units (zeropoint 25): Poisson variance ~2x the background's
INPUT_COLUMNS = (C.COL_X, C.COL_Y, C.COL_SERSIC_N, C.COL_AXIS_RATIO, C.COL_PA, C.COL_R_EFF_PIX,
                 C.COL_BETA, C.COL_MAG_INPUT, C.COL_TASK_SEED)


def _white_noise_config(root, gain):
    """One band of white Gaussian noise (RMS map given), Gaussian PSF, near-point sources."""
    band = {"filter": "wfc3_ir_f160w", "zeropoint": 25.0,
            "psf": {"profile": "gaussian", "fwhm_arcsec": 0.2}}
    if gain is not None:
        band["gain"] = gain
    return {"survey": {"fields": ["f"], "image_dir": str(root), "science": "{field}_{band}_drz.fits",
                       "noise": "{field}_{band}_rms.fits", "noise_type": "rms",
                       "pixel_scale_arcsec": 0.1, "detection_band": "b", "bands": {"b": band}},
            "grid": {"z": {"values": [8.0]}, "mag": {"values": [MAG]}},
            "simulation": {"n_galaxies": 400, "n_iterations": 3, "seed": 3},
            "source": {"r_eff_kpc_z6": 0.05, "sersic_indices": [1.0], "sersic_fractions": [1.0]},
            "detection": {"PHOT_APERTURES": [APER_DIAMETER]},
            "noise": {"correlated": "off"}, "selection": []}


@pytest.fixture(scope="module")
def white(tmp_path_factory):
    """(config dict with gain, field context with gain, field context without gain)."""
    root = tmp_path_factory.mktemp("white")
    rng = np.random.default_rng(0)
    fits.writeto(root / "f_b_drz.fits", (SIGMA * rng.standard_normal((SIDE, SIDE))).astype(np.float32))
    fits.writeto(root / "f_b_rms.fits", np.full((SIDE, SIDE), SIGMA, np.float32))

    def context(gain):
        cfg = config_from_dict(_white_noise_config(root, gain), base_dir=root)
        return build_field_context(cfg, Survey.from_config(cfg), "f")

    return _white_noise_config(root, GAIN), context(GAIN), context(None)


def _spec(it, mag=MAG):
    return TaskSpec(field="f", field_index=0, z_index=0, mag_index=0, iteration=it, z=8.0, mag=mag)


def _quiet(ctx):
    """The same context with source.shot_noise false."""
    return dataclasses.replace(ctx, source_model=dataclasses.replace(ctx.source_model, shot_noise=False))


def _aperture_weights(xc, yc, y0, x0, ny, nx, radius, sub=20):
    """Overlap fraction of each pixel of the box [y0, y0+ny) x [x0, x0+nx) with a circle
    (pixel (iy, ix) covers [ix - 1/2, ix + 1/2] x [iy - 1/2, iy + 1/2]), by sub x sub sampling."""
    t = (np.arange(sub) + 0.5) / sub - 0.5
    yy = (np.arange(y0, y0 + ny)[:, None] + t[None, :]).ravel()
    xx = (np.arange(x0, x0 + nx)[:, None] + t[None, :]).ravel()
    inside = (yy[:, None] - yc) ** 2 + (xx[None, :] - xc) ** 2 <= radius ** 2
    return inside.reshape(ny, sub, nx, sub).mean(axis=(1, 3))


def test_bright_isolated_scatter_is_background_plus_poisson(white):
    """Acceptance: std of (aperture flux - expected) / expected sigma within 5 % of 1.

    Expected, per source, for the exact pixel/circle overlap weights w at the measured
    centre: mean sum(w p) and variance sum(w^2 (sigma^2 + p / gain)), with p the source's
    noiseless pixels.  The Poisson part is about 2/3 of the variance, so noiseless stamps
    give a scatter of ~0.58 (measured 0.575): this test fails without shot noise.
    """
    _, ctx, _ = white
    rows = pd.concat([run_task(ctx, _spec(it), seed=3) for it in range(3)], ignore_index=True)
    ok = (rows[C.COL_STATUS].to_numpy() == C.STATUS_ISOLATED) & (rows[C.COL_FLAGS].to_numpy() == 0)
    assert ok.sum() >= 1000
    radius, half = APER_DIAMETER / 2, int(APER_DIAMETER / 2) + 2
    z = []
    for r in rows[ok].to_dict("records"):
        ps = ctx.cache.stamp("b", r[C.COL_SERSIC_N], r[C.COL_AXIS_RATIO], r[C.COL_PA], r[C.COL_R_EFF_PIX],
                             r[C.COL_X], r[C.COL_Y])
        cy, cx = int(round(r["y_det"])), int(round(r["x_det"]))
        by0, bx0, n = cy - half, cx - half, 2 * half + 1
        w = _aperture_weights(r["x_det"], r["y_det"], by0, bx0, n, n, radius)
        p = np.zeros((n, n))                     # the stamp's noiseless pixels on the box
        sy0, sx0 = max(ps.y0, by0), max(ps.x0, bx0)
        sy1, sx1 = min(ps.y0 + ps.data.shape[0], by0 + n), min(ps.x0 + ps.data.shape[1], bx0 + n)
        p[sy0 - by0:sy1 - by0, sx0 - bx0:sx1 - bx0] = \
            r[C.band_column("flux_in", "b")] * ps.data[sy0 - ps.y0:sy1 - ps.y0, sx0 - ps.x0:sx1 - ps.x0]
        var = np.sum(w ** 2 * (SIGMA ** 2 + np.maximum(p, 0.0) / GAIN))
        z.append((r[C.band_column("flux_aper0", "b")] - np.sum(w * p)) / np.sqrt(var))
    z = np.asarray(z)
    assert abs(z.std() - 1.0) < 0.05, z.std()
    assert abs(z.mean()) < 0.1


def test_without_gains_nothing_is_drawn_and_rows_are_unchanged(white, monkeypatch):
    """No gain: rows equal those of shot_noise false, and the noise code is never called."""
    _, _, ctx = white
    quiet = run_task(_quiet(ctx), _spec(0, mag=26.0), seed=5)

    def refuse(*args, **kwargs):
        raise AssertionError("shot noise drawn without a gain")

    monkeypatch.setattr(task_mod, "add_shot_noise", refuse)
    monkeypatch.setattr(shotnoise, "noisy_pixels", refuse)
    default = run_task(ctx, _spec(0, mag=26.0), seed=5)
    pd.testing.assert_frame_equal(default, quiet, check_exact=True)


def test_noise_leaves_the_task_draws_alone(white):
    """With a gain, positions, shapes and SEDs are a noiseless run's; only measurements move."""
    _, ctx, _ = white
    noisy = run_task(ctx, _spec(1), seed=7)
    quiet = run_task(_quiet(ctx), _spec(1), seed=7)
    pd.testing.assert_frame_equal(noisy[list(INPUT_COLUMNS)], quiet[list(INPUT_COLUMNS)], check_exact=True)
    flux = C.band_column("flux_aper0", "b")
    both = noisy[flux].notna() & quiet[flux].notna()
    assert both.sum() > 100 and (noisy[flux][both] != quiet[flux][both]).mean() > 0.99


def test_scene_pixels_do_not_depend_on_the_window(white):
    """Overlapping noisy stamps (one clipped by the border): every window, the tiled windows
    and the full image carry the same pixels, those of the noisy stamps placed here by hand;
    the noise comes from the band's child stream of the task's SeedSequence."""
    _, ctx, _ = white
    seed, task_key, band = 11, _spec(0).spawn_key(), "b"
    tpl = ctx.cache.stamp(band, 1.0, 1.0, 0.0, 2.0, 20.3, 20.6)
    ny, nx = tpl.data.shape
    places = [(3, 4), (6, 9), (10, 5), (-8, 30)]
    fluxes = [40.0, 3.0, 0.5, 2e3]                    # up to ~1e5 e- per pixel
    lazy = [(y0, x0, tpl.data, f) for (y0, x0), f in zip(places, fluxes)]
    noisy = shotnoise.add_shot_noise(lazy, GAIN, shotnoise.shot_noise_rng(seed, task_key, field_key(band)))
    # The same draws from a generator built here from the documented key.
    rng = np.random.default_rng(np.random.SeedSequence(
        seed, spawn_key=tuple(task_key) + (shotnoise.SHOT_NOISE_STREAM_KEY, field_key(band))))
    for (y0, x0, pix), f in zip(noisy, fluxes):
        np.testing.assert_array_equal(pix, shotnoise.noisy_pixels(tpl.data, f, GAIN, rng))
    base = np.zeros((50, 60))
    pad = 40
    want = np.zeros((base.shape[0] + 2 * pad, base.shape[1] + 2 * pad))
    for y0, x0, pix in noisy:
        want[pad + y0:pad + y0 + ny, pad + x0:pad + x0 + nx] += pix
    want = want[pad:-pad, pad:-pad]
    scene = Scene(base, noisy)
    np.testing.assert_array_equal(scene.full(), want)
    rects = np.array([[0, 50, 0, 60], [5, 12, 7, 20], [0, 9, 25, 50], [8, 30, 2, 33]])
    for y0, y1, x0, x1 in rects:
        np.testing.assert_array_equal(scene.window(y0, y1, x0, x1), want[y0:y1, x0:x1])
    oy = np.array([0, 51, 60, 70])
    canvas = np.full((95, 60), np.nan)
    scene.paste_windows(canvas, rects, oy, np.zeros(4, dtype=np.int64))
    for (y0, y1, x0, x1), o in zip(rects, oy):
        np.testing.assert_array_equal(canvas[o:o + y1 - y0, :x1 - x0], want[y0:y1, x0:x1])
    # The shared template is left as it was, and the noise is there: the residual from the
    # noiseless stamps has the Poisson variance sum(p) / gain over the stamps' pixels.
    assert np.array_equal(tpl.data, ctx.cache.stamp(band, 1.0, 1.0, 0.0, 2.0, 20.3, 20.6).data)
    mean = np.stack([tpl.data * f for f in fluxes])
    resid = np.stack([pix for _, _, pix in noisy]) - mean
    assert np.sum(resid ** 2) == pytest.approx(np.sum(np.maximum(mean, 0)) / GAIN, rel=0.1)


def test_windowed_and_full_detection_agree_with_shot_noise(white, assert_same_outputs):
    """A task with shot noise gives the same rows whether detected by window or full frame."""
    _, ctx, _ = white
    win = run_task(ctx, _spec(2, mag=25.0), seed=9, mode="windowed")
    full = run_task(ctx, _spec(2, mag=25.0), seed=9, mode="full")
    measured = [c for c in win.columns if c not in (C.COL_FIELD,) and win[c].dtype.kind in "fib"]
    assert_same_outputs({c: win[c].to_numpy() for c in measured},
                        {c: full[c].to_numpy() for c in measured}, "windowed vs full")
    assert (win[C.COL_STATUS] == C.STATUS_ISOLATED).mean() > 0.5


@pytest.mark.parametrize("scale", [5e3, 4e4])
def test_noisy_pixels_mean_variance_and_independence(scale):
    """Per pixel, mean p and variance p / gain (Poisson) in the core, in the wings drawn by
    Poisson splitting (scale 5e3) or pixel by pixel (4e4, with the Gaussian limit in the
    brightest pixel); wing pixels uncorrelated; whole electrons below the Gaussian limit."""
    rng = np.random.default_rng(1)
    gain = 2.0
    data = np.array([[0.0, 2e-5, 8e-5], [5e-4, 0.02, 0.5]])
    flux = scale / gain                                 # expected electrons = data * scale
    p = (data * flux).ravel()
    draws = np.stack([shotnoise.noisy_pixels(data, flux, gain, rng).ravel() for _ in range(8000)])
    assert (np.abs(draws.mean(axis=0) - p) <= 5 * np.sqrt(p / gain / len(draws))).all()
    np.testing.assert_allclose(draws.var(axis=0)[1:], p[1:] / gain, rtol=0.07)
    assert (draws[:, 0] == 0).all()
    assert abs(np.corrcoef(draws[:, 1], draws[:, 2])[0, 1]) < 0.05
    electrons = draws[:, p * gain < shotnoise.GAUSSIAN_ABOVE_COUNTS] * gain
    assert np.allclose(electrons, np.round(electrons), atol=1e-9)
    wings = data.ravel() < shotnoise.CORE_FRACTION
    per_pixel = p[wings].sum() * gain > shotnoise.DENSE_WINGS_COUNTS * wings.sum()
    assert per_pixel == (scale > 1e4)                   # both ways of drawing the wings are tested


def test_gains_per_band_and_setting():
    assert shotnoise.shot_noise_gains(None, {"a": 2.0, "b": None}) == {"a": 2.0}
    assert shotnoise.shot_noise_gains(True, {"a": 2.0, "b": None}) == {"a": 2.0}
    assert shotnoise.shot_noise_gains(False, {"a": 2.0}) == {}
    assert shotnoise.shot_noise_gains(None, {"a": None}) == {}


def test_shot_noise_true_without_any_gain_is_refused(white, tmp_path):
    from glaciar.config import ConfigError

    d = json.loads(json.dumps(white[0]))
    del d["survey"]["bands"]["b"]["gain"]
    d["source"]["shot_noise"] = True
    with pytest.raises(ConfigError, match=r"source\.shot_noise: is true but no band has a gain"):
        config_from_dict(d, tmp_path)


def test_same_rows_with_one_or_two_workers(two_task_run, tmp_path):
    """The demo survey has gains: shot noise is on, and 2 workers give the 1-worker rows."""
    cfg_path, run1 = two_task_run
    assert read_manifest(run1)["store_settings"]["source"]["shot_noise"] is True
    simulate(load_config(cfg_path), tmp_path / "run2", workers=2, progress=False)
    a, b = (sorted_rows(read_results(r)) for r in (run1, tmp_path / "run2"))
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def test_changing_shot_noise_refuses_a_resume(two_task_run, tmp_path):
    import yaml

    cfg_path, run = two_task_run
    shutil.copytree(run, tmp_path / "run", ignore=shutil.ignore_patterns(C.LOCK_NAME))
    d = yaml.safe_load(cfg_path.read_text())
    d["source"]["shot_noise"] = False
    off = load_config(write_yaml(d, tmp_path / "off.yaml"))
    with pytest.raises(StoreMismatchError, match=r"source\.shot_noise: True -> None"):
        simulate(off, tmp_path / "run", workers=1, progress=False)
    # A store made before the key (noiseless stamps, gains given) resumes with it off only.
    manifest = read_manifest(tmp_path / "run")
    del manifest["store_settings"]["source"]["shot_noise"]
    manifest["store_hash"] = "made before source.shot_noise"
    write_manifest(tmp_path / "run", manifest)
    with pytest.raises(StoreMismatchError, match=r"source\.shot_noise: <unset> -> True"):
        simulate(load_config(cfg_path), tmp_path / "run", workers=1, progress=False)
    simulate(off, tmp_path / "run", workers=1, progress=False)


def _documented_draws(data, flux, gain, rng):
    """noisy_pixels' draws as its docstring states them, written out electron by electron
    (core: Poisson per pixel; wings: Poisson total, each electron placed by bisection)."""
    import bisect

    scale = flux * gain
    flat = data.ravel()
    core = flat >= shotnoise.CORE_FRACTION
    want = np.zeros(flat.size)
    want[core] = rng.poisson(flat[core] * scale) / gain
    cum = np.cumsum(np.where(core, 0.0, np.maximum(flat, 0.0)))
    edges = cum.tolist()
    for u in rng.random(rng.poisson(cum[-1] * scale)) * cum[-1]:
        i = min(bisect.bisect_right(edges, u), flat.size - 1)
        want[i] += 1.0 / gain
    return want.reshape(data.shape)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled kernel", "numpy"])
def test_noisy_pixels_are_the_documented_draws_and_stamps_share_one_block(compiled, monkeypatch):
    """Bit for bit the documented draws, whatever order the wing electrons are placed in, with
    the compiled kernel and with the numpy code; add_shot_noise writes a band's noisy stamps
    into one block, on one stream, templates and quiet stamps untouched."""
    if compiled and shotnoise.KERNEL is None:
        pytest.skip("glaciar.engine.kernels is not built here (no C compiler at install)")
    if not compiled:
        monkeypatch.setattr(shotnoise, "KERNEL", None)
    yy, xx = np.mgrid[-12:13, -12:13]
    data = np.exp(-0.5 * (xx ** 2 + yy ** 2) / 2.5 ** 2) + 1e-7 * ((xx + yy) % 3)
    data /= data.sum()
    gain = 3.0
    for seed, flux in ((1, 40.0), (2, 400.0), (3, 0.3)):
        got = shotnoise.noisy_pixels(data, flux, gain, np.random.default_rng(seed))
        assert got.tobytes() == _documented_draws(data, flux, gain, np.random.default_rng(seed)).tobytes()
    small = data[5:20, 3:22].copy()
    before = data.copy()
    stamps = [(0, 1, data, 50.0), (4, 5, small, 80.0), (7, 8, data, 20.0)]
    out = shotnoise.add_shot_noise(stamps, gain, np.random.default_rng(9), noisy=[True, False, True])
    rng = np.random.default_rng(9)
    want = [_documented_draws(data, 50.0, gain, rng), _documented_draws(data, 20.0, gain, rng)]
    assert out[1] == stamps[1]
    assert [o[:2] for o in out] == [(0, 1), (4, 5), (7, 8)]
    assert out[0][2].tobytes() == want[0].tobytes() and out[2][2].tobytes() == want[1].tobytes()
    assert np.shares_memory(out[0][2], out[2][2]) is False and out[0][2].base is out[2][2].base
    assert np.array_equal(data, before)
    with pytest.raises(ValueError, match="out must be"):
        shotnoise.noisy_pixels(data, 1.0, gain, rng, out=np.zeros(data.size - 1))


def test_the_compiled_kernel_is_built_where_a_compiler_is():
    """pip install builds glaciar.engine.kernels where a C compiler exists (it is optional only
    for machines without one), the import-time check accepts it, and every module that has a
    kernel uses it."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler on this machine: the numpy code runs")
    from glaciar.engine import compiled, kernels, scene, sepscan
    assert compiled.KERNELS is kernels
    assert shotnoise.KERNEL is kernels and scene.KERNEL is kernels and sepscan.KERNEL is kernels
    assert shotnoise.kernel_agrees(kernels)


class _KernelOfAnotherNumpy:
    """A stamp_shot_noise whose Poisson draws are those of another algorithm (inversion): what
    a build against a numpy with other C distributions would give."""

    @staticmethod
    def stamp_shot_noise(bit_generator, core, core_values, cum, scale, gain, out):
        rng = np.random.Generator(bit_generator)
        lam = core_values * scale
        u = rng.random(lam.size)
        k = np.zeros(lam.size, dtype=np.int64)
        term = np.exp(-lam)
        acc = term.copy()
        while (more := u > acc).any():
            k += more
            term = term * lam / np.maximum(k, 1)
            acc = np.where(more, acc + term, acc)
        out[core] = k / gain


def test_a_kernel_with_other_draws_is_refused():
    assert not shotnoise.kernel_agrees(_KernelOfAnotherNumpy())
