"""Lens maps of a field (glaciar.lensmaps): FITS maps through two WCSs against the analytic
lens they were written from, and unusable maps refused before anything is written."""
import numpy as np
import pytest

from glaciar.config import load_config
from glaciar.galaxy.lensing import SISLens
from glaciar.lensmaps import field_lens
from glaciar.survey import Survey
from lens_maps import write_maps
from tiny_runs import cli, one_error, tiny_config, write_yaml

LENS = SISLens(40.0, -60.0, 100.0, 0.05, -0.03)      # image pixels, centre off the field


@pytest.fixture(scope="module")
def image(small_survey_dict, tmp_path_factory):
    root = tmp_path_factory.mktemp("lensmaps")
    d = tiny_config(small_survey_dict)
    cfg = load_config(write_yaml(d, root / "plain.yaml"))
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    return dict(d=d, root=root, field=field, header=survey.header(field, cfg.survey.detection_band),
                shape=survey.shape(field), scale=survey.pixel_scale_arcsec(field))


def _lensed_config(image, where, models):
    d = {**image["d"], "survey": {**image["d"]["survey"], "lens": {"z_lens": 0.3, "models": models}}}
    return write_yaml(d, where / "c.yaml")


def _maps(image, name, **kw):
    where = image["root"] / name
    where.mkdir()
    model = write_maps(where, image["field"], LENS, image["header"], image["shape"], image["scale"], **kw)
    return where, model


@pytest.mark.parametrize("kind,rotation,flip", [("kappa", 0.0, False), ("kappa", 33.0, False),
                                                ("kappa", 50.0, True), ("deflection", 33.0, True)])
def test_fits_maps_give_the_analytic_lens_at_image_pixels(image, kind, rotation, flip):
    """kappa, gamma1, gamma2 along the image's axes, to 1 % of kappa, from maps on a grid
    rotated (gamma turns by twice the angle) or flipped (gamma2 changes sign)."""
    where, model = _maps(image, f"{kind}{rotation}{flip}", kind=kind, rotation_deg=rotation, flip=flip)
    cfg = load_config(_lensed_config(image, where, [model]))
    provider = field_lens(cfg, Survey.from_config(cfg), image["field"])
    rng = np.random.default_rng(3)
    ny, nx = image["shape"]
    x, y = rng.uniform(0, nx - 1, 300), rng.uniform(0, ny - 1, 300)
    want = LENS.convergence_shear(x, y)
    for got, w in zip(provider(x, y), want):
        assert np.max(np.abs(got - w) / want[0]) < 0.01


@pytest.mark.parametrize("case,pattern", [
    ("no_wcs", r"survey\.lens \(field 'demo01'\): .*demo01_kappa\.fits: the lens map has no celestial WCS"),
    ("short", r"survey\.lens \(field 'demo01'\): .*demo01_kappa\.fits.*: does not cover the field"),
    ("nan", r"survey\.lens \(field 'demo01'\): .*demo01_kappa\.fits.*: NaN or inf inside the footprint"),
    ("grids", r"survey\.lens \(field 'demo01'\): .*demo01_gamma1\.fits: not on the grid of"),
], ids=["no_wcs", "not_covering", "nan_inside", "two_grids"])
def test_unusable_lens_maps_are_refused_before_anything_is_written(image, capsys, case, pattern):
    if case == "grids":
        where, model = _maps(image, case)
        _, other = _maps(image, case + "_rotated", rotation_deg=10.0)
        model["gamma1"] = other["gamma1"]
    else:
        kw = {"no_wcs": {"wcs": False}, "short": {"crop": 0.5},
              "nan": {"nan_at": (150.0, 170.0)}}[case]
        where, model = _maps(image, case, **kw)
    out = where / "run"
    code, lines = cli(capsys, "simulate", _lensed_config(image, where, [model]), "--out", out,
                      "--workers", 1)
    assert code == 2
    one_error(lines, "simulate", pattern)
    assert not out.exists()


def test_lens_config_needs_one_kind_of_model(image, capsys):
    where = image["root"] / "config"
    where.mkdir()
    for lens, says in (({"z_lens": 0.3}, "give either models"),
                       ({"z_lens": 0.3, "models": [{"name": "a", "kappa": "k.fits"}]},
                        "give either kappa, gamma1 and gamma2, or alpha_x and alpha_y"),
                       ({"z_lens": 0.3, "analytic": {"sis": {"theta_e_arcsec": 2.0}}},
                        "give the centre")):
        d = {**image["d"], "survey": {**image["d"]["survey"], "lens": lens}}
        code, lines = cli(capsys, "simulate", write_yaml(d, where / "c.yaml"), "--out", where / "run",
                          "--workers", 1)
        assert code == 2 and says in " ".join(lines), lines
        assert not (where / "run").exists()
