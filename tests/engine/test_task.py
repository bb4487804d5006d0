"""One task: determinism, exact skipping of flux-less bands, injected flux bookkeeping."""
import numpy as np
import pandas as pd
import pytest

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.engine.task import TaskSpec, run_task, task_rng
from glaciar.fieldprep import build_field_context
from glaciar.survey import Survey


@pytest.fixture(scope="module")
def ctx(small_survey):
    cfg = load_config(small_survey)
    return build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])


def _spec(z=10.4, mag=25.0, it=0, zi=1, mi=0):
    return TaskSpec(field="demo01", field_index=0, z_index=zi, mag_index=mi, iteration=it, z=z, mag=mag)


def test_task_rng_depends_only_on_seed_and_cell():
    a, ia = task_rng(5, _spec(it=3))
    b, ib = task_rng(5, _spec(it=3))
    c, ic = task_rng(5, _spec(it=4))
    d, _ = task_rng(6, _spec(it=3))
    xa, xb, xc, xd = (g.random(4) for g in (a, b, c, d))
    np.testing.assert_array_equal(xa, xb)
    assert ia == ib and ia != ic
    assert not np.array_equal(xa, xc) and not np.array_equal(xa, xd)


def test_task_is_deterministic(ctx):
    t1 = run_task(ctx, _spec(), seed=1)
    t2 = run_task(ctx, _spec(), seed=1)
    pd.testing.assert_frame_equal(t1, t2)
    t3 = run_task(ctx, _spec(it=1), seed=1)
    assert not np.array_equal(t1[C.COL_X], t3[C.COL_X])


def test_skipping_fluxless_bands_is_exact(ctx):
    on = run_task(ctx, _spec(), seed=2, skip_faint_bands=True)
    off = run_task(ctx, _spec(), seed=2, skip_faint_bands=False)
    # z = 10.4: no flux in F606W and F098M, so the skip is exercised.
    assert (on[C.band_column("flux_in", "f606w")] == 0).all()
    pd.testing.assert_frame_equal(on, off)


def test_input_flux_matches_zeropoint_and_magnitude(ctx):
    t = run_task(ctx, _spec(z=8.0, zi=0), seed=3)
    for band, zp in ctx.zeropoints.items():
        mag = t[C.band_column("mag_in", band)].to_numpy()
        flux = t[C.band_column("flux_in", band)].to_numpy()
        ok = np.isfinite(mag)
        np.testing.assert_allclose(flux[ok], 10 ** (-0.4 * (mag[ok] - zp)), rtol=1e-12)
        assert (flux[~ok] == 0).all()


def test_injected_pixels_carry_the_in_stamp_flux(ctx):
    """The detection-band image gains exactly the in-stamp flux of every source: all of it
    for a stamp inside the image, the part on the image for a stamp the border clips.

    The expectation is two-sided and exact whether or not stamps are clipped (this task
    clips 4 of its 12 sources on the 320 px field, so both kinds are checked), and every
    source, and the clipped-off part of a stamp, exceed the tolerance, so a missing,
    doubled, unclipped or wrongly clipped source fails it.
    """
    from glaciar.engine import task as task_mod

    captured = {}
    real = task_mod.measure_injected

    def spy(setup, det_scene, *args, **kw):
        captured["scene"] = det_scene
        return real(setup, det_scene, *args, **kw)

    # Noiseless stamps (source.shot_noise false): the sums below are then exact.
    import dataclasses

    quiet = dataclasses.replace(ctx, source_model=dataclasses.replace(ctx.source_model, shot_noise=False))
    task_mod.measure_injected = spy
    try:
        t = run_task(quiet, _spec(z=8.0, zi=0, mag=24.0), seed=4)
    finally:
        task_mod.measure_injected = real
    det = ctx.detection_band
    added = captured["scene"].full().astype(np.float64) - ctx.bases[det].astype(np.float64)
    flux_in = t[C.band_column("flux_in", det)].to_numpy()
    in_stamp = 10 ** (-0.4 * (t[C.band_column("mag_in_stamp", det)].to_numpy() - ctx.zeropoints[det]))
    clipped = (t[C.COL_FLAGS].to_numpy() & C.FLAG_STAMP_CLIPPED) != 0
    assert clipped.any() and (~clipped).any()
    # Each source's stamp, re-read from the template cache at its recorded shape and
    # position: it holds the recorded in-stamp flux; only its part on the image is added.
    ny, nx = ctx.shape
    on_image = np.empty(len(t))
    for i, row in enumerate(t.itertuples(index=False)):
        r = row._asdict()
        ps = ctx.cache.stamp(det, r[C.COL_SERSIC_N], r[C.COL_AXIS_RATIO], r[C.COL_PA],
                             r[C.COL_R_EFF_PIX], r[C.COL_X], r[C.COL_Y])
        np.testing.assert_allclose(flux_in[i] * ps.data.sum(), in_stamp[i], rtol=1e-9)
        part = ps.data[max(0, -ps.y0):max(0, ny - ps.y0), max(0, -ps.x0):max(0, nx - ps.x0)]
        on_image[i] = flux_in[i] * part.sum()
        inside = (ps.y0 >= 0 and ps.x0 >= 0 and ps.y0 + ps.data.shape[0] <= ny
                  and ps.x0 + ps.data.shape[1] <= nx)
        assert inside != clipped[i]
        if inside:
            assert on_image[i] == pytest.approx(in_stamp[i], rel=1e-9)
        else:
            assert on_image[i] < in_stamp[i]
    expect = on_image.sum()
    rtol = 1e-9         # float64 sums of float32 images: measured 4e-16
    np.testing.assert_allclose(added.sum(), expect, rtol=rtol)
    # Power: every source, and the clipped-off part of some stamp, exceed the tolerance
    # (here the smallest source is 8 % of the total, the largest clipped part 5e-4).
    assert on_image.min() > 10 * rtol * expect
    assert (in_stamp - on_image)[clipped].max() > 10 * rtol * expect


def test_task_stream_keyed_by_values_not_grid_position():
    """The same (field, z, mag, iteration) draws the same stream wherever it sits in the grid."""
    a, _ = task_rng(9, TaskSpec(field="f", field_index=0, z_index=0, mag_index=3, iteration=2, z=9.2, mag=26.5))
    b, _ = task_rng(9, TaskSpec(field="f", field_index=4, z_index=7, mag_index=0, iteration=2, z=9.2, mag=26.5))
    c, _ = task_rng(9, TaskSpec(field="g", field_index=0, z_index=0, mag_index=3, iteration=2, z=9.2, mag=26.5))
    d, _ = task_rng(9, TaskSpec(field="f", field_index=0, z_index=0, mag_index=3, iteration=2, z=9.2, mag=-20.5))
    xa, xb, xc, xd = (g.random(3) for g in (a, b, c, d))
    np.testing.assert_array_equal(xa, xb)
    assert not np.array_equal(xa, xc) and not np.array_equal(xa, xd)


def test_holes_in_a_band_kept_and_flagged_or_left_out(small_survey, tmp_path):
    """coverage detection_band: sources on a hole of another band carry FLAG_NO_DATA;
    the default coverage (selection bands) leaves the hole out of the footprint."""
    import shutil

    import yaml
    from astropy.io import fits

    src = small_survey.parent
    dst = tmp_path / "s"
    shutil.copytree(src, dst)
    cfg_data = yaml.safe_load(small_survey.read_text())
    wht_path = dst / cfg_data["survey"]["image_dir"] / cfg_data["survey"]["noise"].format(
        field="demo01", band="f606w")
    with fits.open(wht_path) as h:
        data = h[0].data.copy()
        hdr = h[0].header
    data[:, :160] = 0.0                                    # no f606w data in the left half
    fits.writeto(wht_path, data, hdr, overwrite=True)
    flagged = None
    for coverage in ("detection_band", "selection_bands"):
        cfg_data["survey"]["coverage"] = coverage
        cfg_data["simulation"]["n_galaxies"] = 40
        p = dst / f"{coverage}.yaml"
        p.write_text(yaml.safe_dump(cfg_data, sort_keys=False))
        cfg = load_config(p)
        survey = Survey.from_config(cfg)
        context = build_field_context(cfg, survey, "demo01")
        rows = pd.concat([run_task(context, _spec(it=i, mag=27.5), seed=3) for i in range(3)])
        left = rows[C.COL_X].to_numpy() < 159.5
        no_data = (rows[C.COL_FLAGS].to_numpy() & C.FLAG_NO_DATA) != 0
        if coverage == "detection_band":
            assert left.any() and no_data[left].all() and not no_data[~left].any()
            flagged = int(no_data.sum())
        else:
            # The default J-dropout selection reads f606w: the hole is not in the footprint.
            assert "f606w" in survey.coverage_bands()
            assert not survey.footprint("demo01")[:, :160].any()
            assert not left.any() and not no_data.any()
    assert flagged > 0


# ------------------------------------------------------------------------------
# Task identity under hostile grids (issue 10): near-equal values are different tasks
# ------------------------------------------------------------------------------
def test_near_equal_grid_values_get_their_own_random_streams():
    """z = 9.0 and 9.00004 are different tasks with different files *and* different draws."""
    from glaciar.engine.task import TaskSpec, task_rng

    a = TaskSpec("f", 0, 0, 0, 0, 9.0, 25.0)
    b = TaskSpec("f", 0, 1, 0, 0, 9.00004, 25.0)
    c = TaskSpec("f", 0, 0, 1, 0, 9.0, 25.0 + 1e-12)
    ra, ia = task_rng(1, a)
    rb, ib = task_rng(1, b)
    rc, ic = task_rng(1, c)
    assert len({ia, ib, ic}) == 3
    assert len({tuple(r.random(3)) for r in (ra, rb, rc)}) == 3
    assert task_rng(1, a)[1] == ia                     # and each is reproducible
