"""Field preparation (glaciar.fieldprep): a field's pixels read and measured once, as defined."""
from __future__ import annotations

import numpy as np


def test_noise_rms_follows_weight_type():
    from glaciar.fieldprep import noise_rms

    noise = np.full((4, 4), 0.5, np.float32)       # the map's RMS
    nodata = np.zeros((4, 4), bool)
    nodata[0, 0] = True
    measured = np.full((4, 4), 2.0, np.float32)     # sep's background RMS
    measured[0, 0] = 100.0                          # no data there: left out of the factor
    calls = []

    def background():
        calls.append(1)
        return measured

    # An absolute map (no WEIGHT_TYPE, MAP_RMS) is used as it is; the background is not measured.
    for weight_type in (None, "map_rms"):
        rms, from_background = noise_rms(noise, weight_type, background, nodata)
        assert rms is noise and not from_background
    assert calls == []
    # MAP_WEIGHT: one factor, median(2.0 / 0.5) = 4 over the pixels with data.
    rms, from_background = noise_rms(noise, "map_weight", background, nodata)
    np.testing.assert_array_equal(rms, np.full((4, 4), 2.0, np.float32))
    assert not from_background
    # BACKGROUND, or no map: sep's background RMS.
    for args in ((noise, "background"), (None, None), (None, "map_weight")):
        rms, from_background = noise_rms(*args, background, nodata)
        assert rms is measured and from_background
