"""The detection band's background map made after the band's arrays are put away (issue 24,
point 1): band_pixels_with_background gives band_pixels' arrays and, when asked, its map."""
import numpy as np
import sep

from glaciar.config import load_config
from glaciar.fieldprep import band_pixels, band_pixels_with_background, detection_params
from glaciar.survey import Survey


def test_deferred_background_is_band_pixels_map(small_survey):
    cfg = load_config(small_survey)
    survey = Survey.from_config(cfg)
    field, det = cfg.survey.fields[0], cfg.survey.detection_band
    params = detection_params(cfg)
    footprint = survey.footprint(field)
    d = {}
    want = band_pixels(survey, field, det, footprint, params, cfg.detection.weight_type, background=d)
    base, rms, from_background, back = band_pixels_with_background(
        survey, field, det, footprint, params, cfg.detection.weight_type)
    assert callable(back)
    assert np.array_equal(base, want[0]) and np.array_equal(rms, want[1]) and from_background == want[2]
    got = back()
    assert got.dtype == np.float32 and np.array_equal(got, d[det])
    # Independently: sep's background of the image with the no-data pixels zeroed and masked;
    # the base is the image minus it where there are data.
    img = survey.science(field, det, cache=False).astype(np.float32)
    valid = np.isfinite(rms)
    data = np.where(valid, img, 0).astype(np.float32)
    bs, fs = params.back_size, params.back_filtersize
    model = sep.Background(data, mask=~valid, bw=bs, bh=bs, fw=fs, fh=fs)
    assert np.array_equal(got, model.back(dtype=np.float32))
    assert np.array_equal(base, np.where(valid, img - got, 0).astype(np.float32))
