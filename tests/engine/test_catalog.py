"""The observed catalogue (glaciar.engine.catalog); ``glaciar catalog`` is in tests/pipeline.

Acceptance: a source injected by hand gets, in the catalogue of the injected image, the row
the engine measured for it in a simulation (to float precision); on a white-noise field
without CLEAN the catalogue's detections are plain ``sep.extract``'s with the same settings.
"""
from __future__ import annotations

import numpy as np
import pytest

from glaciar import constants as C
from glaciar.engine import task as task_module
from glaciar.engine.catalog import INJECTION_ONLY_COLUMNS, measure_catalog, segment_pixels


@pytest.fixture(scope="module")
def small_context(small_survey):
    from glaciar.config import load_config
    from glaciar.fieldprep import build_field_context
    from glaciar.survey import Survey

    cfg = load_config(small_survey)
    return cfg, build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])


def test_segment_pixels_one_pixel_of_each_label():
    seg = np.array([[0, 2, 2], [0, 0, 5], [5, 5, 0]])
    x, y, lab = segment_pixels(seg)
    np.testing.assert_array_equal(lab, [2, 5])
    np.testing.assert_array_equal(seg[y.astype(int), x.astype(int)], lab)
    x, y, lab = segment_pixels(seg, labels=[5])
    assert lab.tolist() == [5] and (x[0], y[0]) == (2.0, 1.0)


@pytest.mark.parametrize("mag", [24.0, 26.0])
def test_hand_injected_source_gets_its_engine_row(small_context, monkeypatch, mag):
    """Sources injected by a task (windowed engine) and the catalogue of that same injected
    image (full frame, every detection): each detected source's detection has the same
    photometry, errors, magnitudes, S/N, maglim and flags, to 1e-9 relative."""
    from glaciar.engine.task import TaskSpec, run_task

    cfg, ctx = small_context
    seen = {}
    real = task_module.measure_injected

    def spy(setup, det_scene, det_rms, band_scenes, *args, **kwargs):
        out = real(setup, det_scene, det_rms, band_scenes, *args, **kwargs)
        seen.update(scenes=band_scenes, out=out)
        return out

    monkeypatch.setattr(task_module, "measure_injected", spy)
    spec = TaskSpec(ctx.field, 0, 0, 0, 0, 8.0, mag)
    rows = run_task(ctx, spec, seed=7)
    out = seen["out"]
    detected = np.flatnonzero(out["detection_id"] > 0)
    assert detected.size >= 5
    cat = measure_catalog(ctx, seen["scenes"], positions=(rows[C.COL_X], rows[C.COL_Y]))
    key = {(round(a, 9), round(b, 9)): i for i, (a, b) in enumerate(zip(cat[C.COL_X], cat[C.COL_Y]))}
    measured = [c for c in out if c not in INJECTION_ONLY_COLUMNS]
    assert C.band_column("mag_auto", ctx.detection_band) in measured
    for i in detected:
        j = key[(round(out["x_det"][i], 9), round(out["y_det"][i], 9))]
        for c in measured:
            a, b = cat[c].to_numpy()[j], out[c][i]
            if np.issubdtype(np.asarray(b).dtype, np.floating):
                assert (np.isnan(a) and np.isnan(b)) or abs(a - b) <= 1e-9 * abs(b), (c, a, b)
            else:
                assert a == b, (c, a, b)


def test_catalog_of_original_field(small_context):
    """Every detection once, on the footprint's images; S/N and selection as the injections'."""
    cfg, ctx = small_context
    cat = measure_catalog(ctx)
    assert len(cat) > 20
    assert cat["id"].is_unique and (cat["id"] > 0).all()
    det = ctx.detection_band
    sn = cat[C.band_column("sn", det)].to_numpy()
    np.testing.assert_array_equal(cat[C.COL_RECOVERED].to_numpy(),
                                  sn >= ctx.classification_params.min_sn)
    # selected implies recovered, in the footprint and passing the selection expression.
    sel = cat[C.COL_SELECTED].to_numpy()
    assert not (sel & ~cat[C.COL_RECOVERED].to_numpy()).any()
    assert not (sel & ~cat["in_footprint"].to_numpy()).any()
    # The total magnitude is the AUTO flux's.
    f = cat[C.band_column("flux_auto", det)].to_numpy()
    ok = f > 0
    np.testing.assert_allclose(cat[C.band_column("mag_auto", det)].to_numpy()[ok],
                               ctx.zeropoints[det] - 2.5 * np.log10(f[ok]), rtol=0, atol=1e-12)


def _white_noise_survey(small_survey, tmp_path, *, clean=False):
    """The small demo config on new images: white noise (sigma 1 in every band, exact inverse-
    variance weight maps) plus a few Gaussian blobs, some touching (deblending); CLEAN off."""
    import yaml
    from astropy.io import fits

    from glaciar.config import load_config

    cfg0 = load_config(small_survey)
    d = yaml.safe_load(small_survey.read_text())
    rng = np.random.default_rng(3)
    img_dir = tmp_path / "images"
    img_dir.mkdir()
    field = cfg0.survey.fields[0]
    ny, nx = 200, 240
    yy, xx = np.mgrid[0:ny, 0:nx]
    blobs = np.zeros((ny, nx))
    for x0, y0, amp, s in [(50, 60, 6.0, 2.0), (57, 63, 4.0, 1.5), (150, 120, 3.0, 2.5),
                           (190, 40, 2.0, 1.8), (100, 170, 8.0, 1.2)]:
        blobs += amp * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s))
    for b in cfg0.survey.bands:
        src = cfg0.survey.image_dir / cfg0.survey.science.format(field=field, band=b.name)
        header = fits.getheader(src)
        data = (rng.normal(0.0, 1.0, (ny, nx)) + blobs).astype(np.float32)
        fits.writeto(img_dir / f"wn_{b.name}_drz.fits", data, header)
        fits.writeto(img_dir / f"wn_{b.name}_wht.fits", np.ones((ny, nx), np.float32), header)
    d["survey"]["fields"] = ["wn"]
    d["survey"]["image_dir"] = str(img_dir)
    for b in d["survey"]["bands"].values():
        if isinstance(b.get("psf"), str) and not b["psf"].startswith("/"):
            b["psf"] = str((small_survey.parent / b["psf"]).resolve())
    d["detection"]["CLEAN"] = bool(clean)
    path = tmp_path / "wn.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def test_white_noise_catalog_equals_plain_sep(small_survey, tmp_path):
    """On white noise without CLEAN, the catalogue's detections are sep.extract's: the same
    number and centroids, and the ISO fluxes of objects not deblended, with sep's own background (mesh and filter of the
    config) and threshold DETECT_THRESH x the weight map's RMS."""
    import sep
    from astropy.io import fits

    import glaciar

    path = _white_noise_survey(small_survey, tmp_path)
    cfg = glaciar.load_config(path)
    cat = glaciar.catalog(cfg)
    det = cfg.survey.detection_band
    from glaciar.fieldprep import detection_params

    p = detection_params(cfg)
    data = fits.getdata(tmp_path / "images" / f"wn_{det}_drz.fits").astype(np.float32)
    rms = (1.0 / np.sqrt(fits.getdata(tmp_path / "images" / f"wn_{det}_wht.fits"))).astype(np.float32)
    bkg = sep.Background(data, bw=cfg.detection.back_size, bh=cfg.detection.back_size,
                         fw=cfg.detection.back_filtersize, fh=cfg.detection.back_filtersize)
    objs = sep.extract(data - bkg.back(), cfg.detection.detect_thresh, err=rms,
                       minarea=cfg.detection.detect_minarea, filter_kernel=p.filter_kernel,
                       filter_type=p.filter_type, deblend_nthresh=cfg.detection.deblend_nthresh,
                       deblend_cont=cfg.detection.deblend_mincont, clean=False)
    assert len(cat) == len(objs) >= 5
    got = cat.sort_values([C.COL_Y, C.COL_X])
    order = np.lexsort((objs["x"], objs["y"]))
    np.testing.assert_allclose(got[C.COL_X].to_numpy(), objs["x"][order], atol=1e-6)
    np.testing.assert_allclose(got[C.COL_Y].to_numpy(), objs["y"][order], atol=1e-6)
    # ISO fluxes: equal for objects sep did not deblend.  sep hands the faint pixels of a
    # split region to its children at random (its stream runs over the whole frame), so
    # glaciar re-extracts deblended regions on their own (glaciar.engine.detect): the
    # children's pixel shares differ, their sum does not.
    flux = got[C.band_column("flux_iso", det)].to_numpy()
    want = objs["flux"][order]
    merged = (objs["flag"][order] & sep.OBJ_MERGED) != 0
    assert (~merged).sum() >= 5 and merged.sum() >= 2
    np.testing.assert_allclose(flux[~merged], want[~merged], rtol=1e-5)
    np.testing.assert_allclose(flux[merged].sum(), want[merged].sum(), rtol=1e-5)


def test_missed_segments_measured_windowed_equal_full_frame(small_context, monkeypatch):
    """Segments the first positions miss (their region re-extracted around a sibling) are
    measured in windowed mode with their neighbours; their rows equal those of a second
    full-frame extraction given a pixel of them, to 1e-9 relative."""
    from glaciar.engine import catalog as K
    from glaciar.engine.scene import Scene

    cfg, ctx = small_context
    scenes = {b: Scene(ctx.bases[b]) for b in ctx.bases}
    x0, y0 = K._first_positions(ctx, scenes)
    diag = {}
    full = K._measure(ctx, scenes, x0, y0, diag)
    seg = diag["segmap"]
    # Leave out the positions of a few detections that share an 8-connected region with
    # another detection (so their region is still re-extracted around the sibling).
    from scipy import ndimage

    comp, _ = ndimage.label(seg > 0, structure=np.ones((3, 3)))
    ids = full["detection_id"]
    comp_of = {int(i): int(comp[seg == i][0]) for i in np.unique(ids[ids > 0])}
    by_comp = {}
    for i, c in comp_of.items():
        by_comp.setdefault(c, []).append(i)
    drop_ids = [v[-1] for v in by_comp.values() if len(v) >= 2][:3]
    assert drop_ids, "the small field has deblended neighbours"
    keep = ~np.isin(ids, drop_ids)
    monkeypatch.setattr(K, "_first_positions", lambda c, s: (x0[keep], y0[keep]))
    calls = []
    real = K._measure
    monkeypatch.setattr(K, "_measure", lambda *a, **k: calls.append(k.get("mode", "full")) or real(*a, **k))
    cat = K.measure_catalog(ctx, scenes).set_index("id")
    assert calls == ["full", "windowed"]
    for i in drop_ids:
        j = np.flatnonzero(ids == i)[0]
        for c in cat.columns:
            if c in full and np.issubdtype(np.asarray(full[c]).dtype, np.floating):
                a, b = cat.loc[i, c], full[c][j]
                assert (np.isnan(a) and np.isnan(b)) or abs(a - b) <= 1e-9 * abs(b), (i, c, a, b)
