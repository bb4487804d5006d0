"""Fields with the same PSFs share one template cache per process (issue 24, point 2): the
stamps one field rendered serve the next, with the same bits as a fresh cache's."""
import dataclasses

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar.config import config_from_dict, load_config
from glaciar.engine.task import run_task
from glaciar.fieldprep import build_field_context, field_settings
from glaciar.galaxy.templates import TemplateCache
from glaciar.plan import plan_tasks
from glaciar.survey import Survey


@pytest.fixture(scope="module")
def cfg(small_survey):
    return load_config(small_survey)


def test_fields_with_the_same_psfs_share_one_cache(cfg):
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    first, psfs = field_settings(cfg, survey, field)
    again, _ = field_settings(cfg, survey, field)
    assert again["cache"] is first["cache"]
    # The cache renders with the field's own PSFs (value for value).
    s = first["cache"].stamp(cfg.survey.detection_band, 1.0, 0.7, 30.0, 2.5, 100.2, 80.7)
    fresh = TemplateCache(psfs, enclosed_fraction=first["enclosed_fraction"])
    want = fresh.stamp(cfg.survey.detection_band, 1.0, 0.7, 30.0, 2.5, 100.2, 80.7)
    assert np.array_equal(s.data, want.data) and (s.y0, s.x0) == (want.y0, want.x0)


def test_other_psfs_get_their_own_cache(cfg, small_survey):
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    shared, _ = field_settings(cfg, survey, field)
    data = yaml.safe_load(small_survey.read_text())
    name = cfg.survey.detection_band
    # The same PSF file declared at another pixel scale: resampled to other pixels.
    data["survey"]["bands"][name]["psf_pixel_scale_arcsec"] = 0.1
    other_cfg = config_from_dict(data, base_dir=small_survey.parent)
    other, other_psfs = field_settings(other_cfg, Survey.from_config(other_cfg), field)
    assert other["cache"] is not shared["cache"]
    s = other["cache"].stamp(name, 1.0, 0.7, 30.0, 2.5, 100.2, 80.7)
    fresh = TemplateCache(other_psfs, enclosed_fraction=other["enclosed_fraction"])
    assert np.array_equal(s.data, fresh.stamp(name, 1.0, 0.7, 30.0, 2.5, 100.2, 80.7).data)


def test_a_warm_shared_cache_gives_a_fresh_caches_rows(cfg):
    """A task run after others filled the shared cache: rows bit-identical to the same task
    run with a new, empty cache."""
    survey = Survey.from_config(cfg)
    specs = plan_tasks(cfg)
    ctx = build_field_context(cfg, survey, specs[0].field)
    _, psfs = field_settings(cfg, survey, specs[0].field)
    run_task(ctx, specs[0], 5)                        # fills the shared cache
    assert ctx.cache.stats.misses > 0
    warm = run_task(ctx, specs[1], 5)
    assert ctx.cache.stats.hits > 0
    fresh_ctx = dataclasses.replace(ctx, cache=TemplateCache(psfs, enclosed_fraction=ctx.enclosed_fraction))
    fresh = run_task(fresh_ctx, specs[1], 5)
    assert fresh_ctx.cache.stats.misses > 0
    pd.testing.assert_frame_equal(warm, fresh, check_exact=True)
