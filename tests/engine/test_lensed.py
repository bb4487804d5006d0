"""Lensed injections (glaciar.engine.lensed via run_task) against an analytic lens.

One field context of the small demo survey behind an SIS + external shear (module
fixture); its tasks' rows are compared with the lens, the size law and the distance
ratio written out here.
"""
import dataclasses
import math

import numpy as np
import pytest

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.engine.task import TaskSpec, run_task
from glaciar.execute import simulate
from glaciar.fieldprep import build_field_context
from glaciar.galaxy.lensing import SISLens
from glaciar.galaxy.sersic import sersic_stamp
from glaciar.lensmaps import LazyFieldLens
from glaciar.store import read_results
from glaciar.survey import Survey
from lens_maps import write_maps
from tiny_runs import tiny_config, write_yaml

Z_LENS, THETA_E, CENTRE, SHEAR = 0.35, 3.0, (190.0, 140.0), (0.06, -0.03)
Z, MAG = 8.0, 24.0
R6, SIZE_EVOLUTION, SLOPE = 1.075, -1.0, 0.25


def _config(small_survey_dict, root, lens):
    d = tiny_config(small_survey_dict, z=(Z,), mag=(MAG, 25.0), n_gal=10)
    d["survey"]["lens"] = lens
    d["source"] = {"sersic_indices": [1.0], "sersic_fractions": [1.0], "ellipticity_bins": 4,
                   "position_angle_bins": 6, "size_luminosity_slope": SLOPE}
    d["noise"] = {"correlated": "off"}
    return load_config(write_yaml(d, root / "lensed.yaml"))


ANALYTIC = {"z_lens": Z_LENS, "analytic": {
    "sis": {"theta_e_arcsec": THETA_E, "center_x_pix": CENTRE[0], "center_y_pix": CENTRE[1]},
    "shear": {"gamma1": SHEAR[0], "gamma2": SHEAR[1]}}}


def _ratio(z_lens, z_source):
    """D_ls / D_s in the flat Planck18 cosmology: 1 - chi_l / chi_s."""
    from astropy.cosmology import Planck18

    return 1.0 - (Planck18.comoving_distance(z_lens) / Planck18.comoving_distance(z_source)).value


@pytest.fixture(scope="module")
def lensed(small_survey_dict, tmp_path_factory):
    root = tmp_path_factory.mktemp("lensed")
    cfg = _config(small_survey_dict, root, ANALYTIC)
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    ctx = build_field_context(cfg, survey, field)
    rows = run_task(ctx, TaskSpec(field, 0, 0, 0, 0, Z, MAG), cfg.simulation.seed)
    scale = survey.pixel_scale_arcsec(field)
    lens = SISLens(THETA_E / scale, *CENTRE, *SHEAR)
    return dict(cfg=cfg, survey=survey, field=field, ctx=ctx, rows=rows, lens=lens, scale=scale,
                root=root)


def test_magnification_is_the_analytic_one_at_the_injected_positions(lensed):
    rows = lensed["rows"]
    assert len(rows) == 10
    r = _ratio(Z_LENS, Z)
    k, g1, g2 = lensed["lens"].convergence_shear(rows[C.COL_X], rows[C.COL_Y])
    mu = 1.0 / ((1 - r * k) ** 2 - r * r * (g1 ** 2 + g2 ** 2))
    np.testing.assert_allclose(rows[C.COL_MAGNIFICATION], mu, rtol=0.01)
    np.testing.assert_allclose(rows[C.COL_KAPPA], r * k, rtol=0.01)
    np.testing.assert_allclose(rows[C.COL_GAMMA], r * np.hypot(g1, g2), rtol=0.01)
    assert np.ptp(rows[C.COL_MAGNIFICATION]) > 0.3          # positions really differ in mu


def test_stamp_flux_is_mu_times_the_intrinsic_flux(lensed):
    """The observed (injected) flux is |mu| x the intrinsic flux; the task's magnitude is the
    observed one; the intrinsic size follows the size law at the intrinsic M_UV."""
    rows, ctx = lensed["rows"], lensed["ctx"]
    det = ctx.detection_band
    zp = ctx.zeropoints[det]
    intrinsic = 10 ** (-0.4 * (rows[C.COL_MAG_INTRINSIC] - zp))
    np.testing.assert_allclose(rows[C.band_column("flux_in", det)],
                               np.abs(rows[C.COL_MAGNIFICATION]) * intrinsic, rtol=1e-4)
    np.testing.assert_allclose(rows[C.COL_MAG_INPUT], MAG, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rows[C.COL_M_UV_INTRINSIC] - rows[C.COL_M_UV],
                               2.5 * np.log10(np.abs(rows[C.COL_MAGNIFICATION])), atol=1e-9)
    want = R6 * ((1 + Z) / 7) ** SIZE_EVOLUTION * 10 ** (-0.4 * SLOPE * (rows[C.COL_M_UV_INTRINSIC] + 21))
    np.testing.assert_allclose(rows[C.COL_R_EFF_KPC_INTRINSIC], want, rtol=1e-9)


def test_image_second_moments_show_the_analytic_stretch(lensed):
    """The rendered (unconvolved) profile of each source, at its image shape: second moments
    Q_image = A^-1 Q_source A^-T of the analytic Jacobian at its position (axis ratio to 1 %,
    major axis within 1 deg)."""
    rows, ctx = lensed["rows"], lensed["ctx"]
    r = _ratio(Z_LENS, Z)
    k, g1, g2 = lensed["lens"].convergence_shear(rows[C.COL_X], rows[C.COL_Y])
    checked = 0
    for i in range(len(rows)):
        row = rows.iloc[i]
        if row[C.COL_FLAGS] & C.FLAG_LENS_EXTREME:
            continue
        a = np.array([[1 - r * k[i] - r * g1[i], -r * g2[i]], [-r * g2[i], 1 - r * k[i] + r * g1[i]]])
        q, pa = row[C.COL_AXIS_RATIO_INTRINSIC], math.radians(row[C.COL_PA_INTRINSIC])
        rot = np.array([[math.cos(pa), -math.sin(pa)], [math.sin(pa), math.cos(pa)]])
        ainv = np.linalg.inv(a)
        q_img = ainv @ (rot @ np.diag([1.0, q * q]) @ rot.T) @ ainv.T
        size = 2 * int(12 * row[C.COL_R_EFF_PIX]) + 1
        stamp = sersic_stamp(1.0, row[C.COL_R_EFF_PIX], row[C.COL_AXIS_RATIO],
                             row[C.COL_PA], shape=(size, size))
        yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2
        w = stamp / stamp.sum()
        qm = np.array([[np.sum(w * xx * xx), np.sum(w * xx * yy)],
                       [np.sum(w * xx * yy), np.sum(w * yy * yy)]]) - np.eye(2) / 12.0
        ev_m, vec_m = np.linalg.eigh(qm)
        ev_a, vec_a = np.linalg.eigh(q_img)
        assert math.sqrt(ev_m[0] / ev_m[1]) == pytest.approx(math.sqrt(ev_a[0] / ev_a[1]), rel=0.01)
        assert abs(vec_m[:, 1] @ vec_a[:, 1]) > math.cos(math.radians(1.0))
        # Image size: det Q_image = det Q_source / mu^2 (area x |mu|) on the intrinsic scale.
        r_int = row[C.COL_R_EFF_ARCSEC_INTRINSIC] / lensed["scale"]
        assert row[C.COL_R_EFF_PIX] == pytest.approx(r_int * math.sqrt(ev_a[1]), rel=0.005)
        checked += 1
    assert checked >= 8


def test_fits_maps_give_the_analytic_kappa_and_gamma_per_source(lensed):
    """Convergence/shear maps and deflection maps of an analytic lens on grids rotated
    (and flipped) relative to the image: per-source kappa and gamma as the analytic lens."""
    ctx, survey, field = lensed["ctx"], lensed["survey"], lensed["field"]
    lens = SISLens(45.0, -80.0, 120.0, 0.04, 0.07)        # centre off the field
    header = survey.header(field, ctx.detection_band)
    r = _ratio(Z_LENS, Z)
    for kind, rotation, flip in (("kappa", 35.0, True), ("deflection", -20.0, False)):
        where = lensed["root"] / kind
        where.mkdir()
        model = write_maps(where, field, lens, header, ctx.shape, lensed["scale"], kind=kind,
                           rotation_deg=rotation, flip=flip)
        cfg = load_config(write_yaml({**_dict(lensed["cfg"]), "survey": {
            **_dict(lensed["cfg"])["survey"], "lens": {"z_lens": Z_LENS, "models": [model]}}},
            where / "c.yaml"))
        fits_ctx = dataclasses.replace(ctx, lens=LazyFieldLens(cfg, Survey.from_config(cfg), field))
        rows = run_task(fits_ctx, TaskSpec(field, 0, 0, 1, 0, Z, 25.0), 5)
        k, g1, g2 = lens.convergence_shear(rows[C.COL_X], rows[C.COL_Y])
        np.testing.assert_allclose(rows[C.COL_KAPPA], r * k, rtol=0.01)
        np.testing.assert_allclose(rows[C.COL_GAMMA], r * np.hypot(g1, g2), rtol=0.01)
        mu = 1.0 / ((1 - r * k) ** 2 - r * r * (g1 ** 2 + g2 ** 2))
        np.testing.assert_allclose(rows[C.COL_MAGNIFICATION], mu, rtol=0.01)


def _dict(cfg):
    from glaciar.config import config_to_dict

    return config_to_dict(cfg)


def test_run_with_two_workers_gives_the_serial_rows_and_the_lens_nodes(lensed):
    """simulate with 2 workers: the rows of run_task in this process (same seed, spec), and
    the manifest's lens record with nodes covering the footprint's area."""
    cfg, field = lensed["cfg"], lensed["field"]
    run = lensed["root"] / "run"
    simulate(cfg, run, workers=2, progress=False)
    got = read_results(run)
    got = got[got[C.COL_MAG] == MAG].sort_values(C.COL_SOURCE).reset_index(drop=True)
    want = lensed["rows"]
    for c in want.columns:
        a, b = got[c].to_numpy(), want[c].to_numpy()
        if a.dtype.kind == "f":
            assert np.array_equal(a, b, equal_nan=True), c
        else:
            assert (a == b).all(), c
    import json

    manifest = json.loads((run / C.MANIFEST_NAME).read_text())
    assert manifest["lens"]["z_lens"] == Z_LENS and manifest["lens"]["models"] == ["analytic"]
    nodes = manifest["lens_nodes"][field]["analytic"]
    assert sum(nodes["area_arcmin2"]) == pytest.approx(manifest["area_arcmin2"][field], rel=1e-9)
    assert manifest["store_settings"]["survey"]["lens"]["z_lens"] == Z_LENS


def test_lensed_isolation_boxes_never_intersect(lensed):
    """Each source's box, from its image shape at its own position (the light holding
    isolation_fraction, plus the PSF margin), meets no other source's box."""
    from glaciar.galaxy.sersic import stamp_shape

    rows, ctx = lensed["rows"], lensed["ctx"]
    half = []
    for _, row in rows.iterrows():
        ny, nx = stamp_shape(row[C.COL_SERSIC_N], row[C.COL_R_EFF_PIX], row[C.COL_AXIS_RATIO],
                             row[C.COL_PA], enclosed_fraction=ctx.isolation_fraction)
        half.append(((ny - 1) // 2 + ctx.isolation_margin_pix, (nx - 1) // 2 + ctx.isolation_margin_pix))
    iy = np.floor(rows[C.COL_Y].to_numpy() + 0.5).astype(int)
    ix = np.floor(rows[C.COL_X].to_numpy() + 0.5).astype(int)
    for i in range(len(rows)):
        for j in range(i):
            apart = (abs(iy[i] - iy[j]) > half[i][0] + half[j][0]
                     or abs(ix[i] - ix[j]) > half[i][1] + half[j][1])
            assert apart, (i, j)
    assert ctx.footprint[iy, ix].all()
