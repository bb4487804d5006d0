"""``grid.box``: injection points drawn continuously over a (z, m) box.

The points are checked against an independent construction (scipy's unscrambled
Halton sequence, shifted by the BLAKE2b rotation the docs define), and a small
box is simulated, interrupted, resumed and fitted on the tiny demo survey.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.config import ConfigError, config_from_dict, config_to_dict, load_config
from glaciar.plan import plan_tasks, task_cells

BOX = {"z": [8.2, 10.1], "mag": [24.5, 27.0], "n_points": 3}


def BOX_N_GALAXIES(cfg):
    """Sources of one box point in one field (n_iterations 1 by default)."""
    return cfg.simulation.n_galaxies


def _config_with(base_config: Path, tmp_path: Path, name="cfg.yaml", n_iterations=None,
                 **grid) -> Path:
    d = yaml.safe_load(base_config.read_text())
    d["grid"].update(grid)
    if n_iterations is not None:
        d["simulation"]["n_iterations"] = n_iterations
    out = tmp_path / name
    out.write_text(yaml.safe_dump(d, sort_keys=False))
    return out


def _expected_points(z, mag, n, seed):
    """The documented construction, rebuilt from scipy.stats.qmc and hashlib."""
    from scipy.stats import qmc

    h = hashlib.blake2b(f"glaciar.box:{seed}".encode(), digest_size=16).digest()
    shift = np.array([int.from_bytes(h[:8], "little") >> 12,
                      int.from_bytes(h[8:], "little") >> 12]) / 2.0 ** 52
    u = np.mod(qmc.Halton(d=2, scramble=False).random(n) + shift, 1.0)
    zz = z[0] + u[:, 0] * (z[1] - z[0])
    mm = mag[0] + u[:, 1] * (mag[1] - mag[0])
    return np.round(zz, 4), np.round(mm, 4)


@pytest.mark.parametrize("seed", [0, 12345, 2 ** 62 + 7])
def test_points_are_a_shifted_halton_sequence_rounded_inside_the_box(seed):
    from glaciar.box import box_points

    z, mag, n = (9.0, 11.5), (24.0, 28.3), 576
    pts = np.array(box_points(z, mag, n, seed))
    ez, em = _expected_points(z, mag, n, seed)
    # Equal up to a rounding tie (scipy sums the digits in floating point).
    assert np.mean(np.abs(pts[:, 0] - ez) < 1e-9) > 0.99
    assert np.mean(np.abs(pts[:, 1] - em) < 1e-9) > 0.99
    assert np.all(np.abs(pts - np.c_[ez, em]) <= 1e-4 + 1e-9)
    assert np.all((pts[:, 0] >= z[0]) & (pts[:, 0] <= z[1]))
    assert np.all((pts[:, 1] >= mag[0]) & (pts[:, 1] <= mag[1]))
    # Multiples of the resolution, written as short decimals (exact keys, YAML/JSON round-trip).
    assert all(float(repr(float(v))) == v and len(repr(float(v)).split(".")[-1]) <= 4
               for v in pts.ravel())
    assert len({tuple(p) for p in pts}) == n
    # Low discrepancy: each of 8 x 9 sub-boxes holds 8 points within 3 (independent
    # uniform draws give 3 to 15).
    h, _, _ = np.histogram2d(pts[:, 0], pts[:, 1], bins=(8, 9), range=[z, mag])
    assert h.min() >= 5 and h.max() <= 11


def test_points_depend_on_the_seed_and_a_larger_box_keeps_the_first_points():
    from glaciar.box import box_points

    a = box_points((8, 10), (25, 27), 40, 1)
    assert box_points((8, 10), (25, 27), 40, 1) == a
    assert box_points((8, 10), (25, 27), 17, 1) == a[:17]
    assert box_points((8, 10), (25, 27), 40, 2) != a


def test_box_cells_join_the_grid_and_do_not_change_the_store_identity(small_survey, tmp_path):
    from glaciar.config import store_hash
    from glaciar.manifest import store_settings

    plain = load_config(small_survey)
    cfg = load_config(_config_with(small_survey, tmp_path, box=dict(BOX, n_iterations=2)))
    assert store_hash(plain) == store_hash(cfg)
    assert store_settings(plain) == store_settings(cfg)
    again = config_from_dict(config_to_dict(cfg), base_dir=cfg.base_dir)
    assert again == cfg
    n_f = len(cfg.survey.fields)
    ez, em = _expected_points(BOX["z"], BOX["mag"], 3, cfg.simulation.seed)
    cells = task_cells(cfg)
    for z, m in zip(ez, em):
        assert all(cells[(f, float(z), float(m))] == 2 for f in cfg.survey.fields)
    # 2 z x 2 mag x 2 iterations on the grid, plus 3 points x 2 iterations, per field.
    assert len(plan_tasks(cfg)) == n_f * (8 + 6)


@pytest.mark.parametrize("box, where", [
    ({"z": [10.0, 9.0], "mag": [25, 26], "n_points": 4}, "grid.box.z"),
    ({"z": [9.0, 10.0], "mag": [26, 26], "n_points": 4}, "grid.box.mag"),
    ({"z": [-1.0, 10.0], "mag": [25, 26], "n_points": 4}, "grid.box.z"),
    ({"z": [9.0, 10.0, 11.0], "mag": [25, 26], "n_points": 4}, "grid.box.z"),
    ({"z": [9.0, 10.0], "mag": [25, 26], "n_points": 0}, "grid.box.n_points"),
    ({"z": [9.0, 10.0], "mag": [25, 26]}, "grid.box.n_points"),
    ({"z": [9.0, 10.0], "mag": [25, "x"], "n_points": 3}, "grid.box.mag"),
    ({"z": [9.0, 10.0], "mag": [25, 26], "n_points": 3, "fields": ["nope"]}, "grid.box.fields"),
])
def test_bad_boxes_are_refused_in_one_line_with_exit_2(small_survey, tmp_path, box, where, capsys):
    from glaciar.cli import main

    with pytest.raises(ConfigError) as err:
        load_config(_config_with(small_survey, tmp_path, box=box))
    assert where in str(err.value)
    out = tmp_path / "run"
    capsys.readouterr()
    code = main(["simulate", str(tmp_path / "cfg.yaml"), "--out", str(out), "--quiet"])
    err_text = capsys.readouterr().err.strip()
    assert code == 2 and where in err_text and len(err_text.splitlines()) == 1
    assert not out.exists()


def _table(run_dir: Path) -> pd.DataFrame:
    files = sorted((run_dir / C.RESULTS_DIRNAME).rglob("*.parquet"))
    df = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    return df.sort_values([C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION,
                           C.COL_SOURCE]).reset_index(drop=True)


@pytest.mark.filterwarnings("ignore::glaciar.inference.sampling.ConvergenceWarning")
@pytest.mark.filterwarnings("ignore:fit 'all'")
def test_box_simulates_resumes_to_the_same_table_grows_by_a_prefix_and_fits(small_survey,
                                                                            tmp_path):
    from glaciar.inference.sampling import SamplerSettings
    from glaciar.pipeline.fit import run_fit
    from glaciar.execute import simulate
    from glaciar.rundir import read_manifest

    # Written beside the survey: its paths are relative to the config.
    # One grid cell of one task beside the box keeps the test short.
    here = small_survey.parent
    one = {"z": {"values": [8.0]}, "mag": {"values": [24.0]}, "n_iterations": 1}
    cfg = load_config(_config_with(small_survey, here, name="box_run.yaml", box=BOX, **one))
    a, b = tmp_path / "a", tmp_path / "b"
    simulate(cfg, a, progress=False)
    simulate(cfg, b, progress=False, max_tasks=2)          # interrupted ...
    simulate(cfg, b, progress=False)                       # ... and resumed
    ta, tb = _table(a), _table(b)
    pd.testing.assert_frame_equal(ta, tb)
    ez, em = _expected_points(BOX["z"], BOX["mag"], 3, cfg.simulation.seed)
    box_rows = ta[ta[C.COL_Z].isin(ez)]
    assert sorted(set(zip(box_rows[C.COL_Z], box_rows[C.COL_MAG]))) == sorted(zip(ez, em))
    # Growing the box runs only the new points: the first three are a prefix.
    grown = load_config(_config_with(small_survey, here, name="box_grown.yaml",
                                     box=dict(BOX, n_points=5), **one))
    stats = simulate(grown, a, progress=False)
    assert stats["n_run"] == len(grown.survey.fields) * 2
    manifest = read_manifest(a)
    assert manifest["box"]["n_points"] == 5
    # The fit reads every point of grid and box at its own z (1 grid z + 5 box z).
    from glaciar.pipeline.inputs import fit_inputs
    from glaciar.counting import COUNTS_MAG_RESOLUTION

    fi = fit_inputs(a, C.COL_MAG_INPUT, COUNTS_MAG_RESOLUTION)
    assert sorted(np.unique(fi.z)) == sorted({8.0, *ez, *_expected_points(
        BOX["z"], BOX["mag"], 5, cfg.simulation.seed)[0]})
    run_fit(a, model="logistic", plots=False, sampler=SamplerSettings(max_steps=300))
    from glaciar.inference import SelectionFunction

    sf = SelectionFunction.read(a / C.SELECTION_FUNCTION_NAME)
    # Inside the simulated box (the points' own extent; outside it grids are NaN, issue 21).
    (zlo, zhi), (mlo, mhi) = sf.domain["z"], sf.domain["mag"]
    p = sf.grid_draws(np.linspace(zlo, zhi, 3), np.linspace(mlo, mhi, 3))["P"]
    assert np.all(np.isfinite(p)) and np.all((p >= 0) & (p <= 1))

    # report: the box's points binned (one bin for 5 points), every box source counted once.
    from glaciar.cli import main

    assert main(["report", str(a), "--html"]) == 0
    from astropy.table import Table

    binned = Table.read(a / C.SUMMARY_DIRNAME / "box_summary_all.ecsv").to_pandas()
    pts = set(zip(*_expected_points(BOX["z"], BOX["mag"], 5, cfg.simulation.seed)))
    rows = _table(a)
    r = rows[[(z, m) in pts for z, m in zip(rows[C.COL_Z], rows[C.COL_MAG])]]
    assert binned["n_input"].sum() == len(r) == 5 * len(cfg.survey.fields) * BOX_N_GALAXIES(cfg)
    assert binned["n_selected"].sum() == r[C.COL_SELECTED].sum()
    assert (a / "report.html").stat().st_size > 0

    # next: candidates are a lattice over the box (3 values per axis for 5 points: ceil
    # sqrt 5) united with the grid's axes, and the midpoints; never the points' own values.
    from glaciar.pipeline.adaptive import proposal_cells

    _, stats = proposal_cells(sf, grown, 100)
    zax = np.union1d(np.linspace(*BOX["z"], 3), [8.0])
    max_ = np.union1d(np.linspace(*BOX["mag"], 3), [24.0])
    zc = np.union1d(zax, 0.5 * (zax[1:] + zax[:-1]))
    mc = np.union1d(max_, 0.5 * (max_[1:] + max_[:-1]))
    got = {(round(c["z"], 6), round(c["mag"], 6)) for c in stats["ranked"]}
    want = {(round(z, 6), round(m, 6)) for z in zc for m in mc
            if z < (read_manifest(a)["detection_z_limit"] or np.inf)}
    assert got == want


def test_box_summary_bins_the_box_points_only_as_a_histogram_does():
    from glaciar.tables import box_summary_table

    rng = np.random.default_rng(3)
    pts = [(round(z, 4), round(m, 4)) for z, m in rng.uniform((8, 24), (10, 28), (40, 2))]
    n = 400
    k = rng.integers(0, 40, n)
    rows = pd.DataFrame({C.COL_FIELD: "f", C.COL_Z: [pts[i][0] for i in k],
                         C.COL_MAG: [pts[i][1] for i in k],
                         C.COL_STATUS: rng.choice(C.STATUS_CODES, n)})
    rows[C.COL_RECOVERED] = rows[C.COL_STATUS].isin(C.RECOVERED_STATUSES)
    rows[C.COL_SELECTED] = rows[C.COL_RECOVERED] & (rng.random(n) < 0.5)
    grid = pd.DataFrame({C.COL_FIELD: "f", C.COL_Z: 9.0, C.COL_MAG: 25.0, C.COL_STATUS: 0,
                         C.COL_RECOVERED: True, C.COL_SELECTED: True}, index=range(7))
    ze, me = np.linspace(8, 10, 4), np.linspace(24, 28, 5)
    out = box_summary_table(pd.concat([rows, grid], ignore_index=True), pts, ze, me)
    for col, w in (("n_input", None), ("n_recovered", rows[C.COL_RECOVERED]),
                   ("n_selected", rows[C.COL_SELECTED])):
        h, _, _ = np.histogram2d(rows[C.COL_Z], rows[C.COL_MAG], bins=(ze, me),
                                 weights=None if w is None else w.to_numpy(float))
        got = np.zeros_like(h)
        for _, b in out.iterrows():
            iz, im = np.searchsorted(ze, b["z_lo"]), np.searchsorted(me, b["mag_lo"])
            assert np.isclose(b["z"], 0.5 * (ze[iz] + ze[iz + 1]))
            got[iz, im] = b[col]
        assert np.array_equal(got, h), col
    z_of = np.array([p[0] for p in pts])
    h, _, _ = np.histogram2d(z_of, [p[1] for p in pts], bins=(ze, me))
    assert out["n_points"].sum() == 40 and set(out["n_points"]) <= set(h.ravel().astype(int))


# ---------------------------------------------------------------------------
# band colours at many redshifts (glaciar.galaxy.sed: z lattice + interpolation)
# ---------------------------------------------------------------------------
def _direct_mags(z, beta, filters):
    """AB magnitudes of (lambda / 1600 A (1+z))^beta x T_IGM by numpy's trapezoid rule on a
    fine wavelength grid (nodes either side of the IGM's line onsets), up to a common offset."""
    from glaciar.constants import C_ANGSTROM_PER_S
    from glaciar.galaxy.igm import igm_transmission

    lo = min(f.wave_angstrom[0] for f in filters)
    hi = max(f.wave_angstrom[-1] for f in filters)
    wave = np.exp(np.arange(np.log(lo), np.log(hi), 2e-5))
    edges = np.array([1215.67, 1025.72, 972.537, 949.743, 911.75]) * (1 + z)
    wave = np.union1d(wave, np.concatenate([edges * (1 - 1e-10), edges * (1 + 1e-10)]))
    t_igm = igm_transmission(wave, z, "inoue14")
    out = np.empty((len(beta), len(filters)))
    for j, f in enumerate(filters):
        thr = np.interp(wave, f.wave_angstrom, f.throughput, left=0.0, right=0.0)
        den = np.trapezoid(thr * C_ANGSTROM_PER_S / wave, wave)
        for k, b in enumerate(beta):
            num = np.trapezoid((wave / (1600.0 * (1 + z))) ** b * t_igm * thr * wave, wave)
            out[k, j] = -2.5 * np.log10(num / den) if num > 0 else np.inf
    return out


def test_band_magnitudes_off_the_z_lattice_match_direct_integration_to_1e_3_mag():
    from glaciar.galaxy.filters import get_filter
    from glaciar.galaxy.sed import Z_LATTICE_STEP, _band_table, band_magnitudes

    names = ["wfc3_uvis_f606w", "wfc3_ir_f098m", "wfc3_ir_f125w", "wfc3_ir_f160w",
             "nircam_f200w"]
    filters = [get_filter(n) for n in names]
    det = names.index("nircam_f200w")
    rng = np.random.default_rng(8)
    # Where the Lyman-alpha break crosses the bands (kinks in z) and where it does not.
    zs = np.round(rng.uniform(7.0, 13.0, 8), 4)
    zs = zs[np.abs(zs / Z_LATTICE_STEP - np.round(zs / Z_LATTICE_STEP)) > 1e-6]
    betas = np.array([-2.6, -1.7])
    worst, interpolated = 0.0, 0
    for z in zs:
        got = band_magnitudes(float(z), betas, filters, mag=26.0, detection_index=det)
        exact = np.array([_band_table(float(z), f, "inoue14").colour(betas) for f in filters]).T
        exact = exact - exact[:, det:det + 1] + 26.0
        interpolated += int(np.any(got[np.isfinite(got)] != exact[np.isfinite(got)]))
        ref = _direct_mags(float(z), betas, filters)
        ref = ref - ref[:, det:det + 1] + 26.0
        ok = ref < 26.0 + 10.0                # bands with >= 1e-4 of the detection flux
        worst = max(worst, float(np.max(np.abs(got[ok] - ref[ok]))))
    assert worst < 1e-3, worst
    assert interpolated >= len(zs) // 2         # the lattice served most of them


def test_a_seed_override_moves_the_box_points_and_the_stored_config_says_so(small_survey):
    from glaciar.execute import simulate
    from glaciar.rundir import read_manifest

    here = small_survey.parent
    cfg = load_config(_config_with(small_survey, here, name="box_seed.yaml", box=BOX))
    run = here / "box_seed_run"
    simulate(cfg, run, seed=7, progress=False, max_tasks=0)
    ez, em = _expected_points(BOX["z"], BOX["mag"], 3, 7)
    listed = {(c["z"], c["mag"]) for c in read_manifest(run)["cells"]}
    assert listed == set(zip(ez.tolist(), em.tolist()))
    stored = load_config(run / C.RUN_CONFIG_NAME)
    assert stored.simulation.seed == 7 and task_cells(stored) == task_cells(
        cfg.model_copy(update={"simulation": cfg.simulation.model_copy(update={"seed": 7})}))
