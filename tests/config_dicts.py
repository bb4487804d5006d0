"""A valid four-band configuration as a dict, and loading it: shared by the configuration tests.

``base()`` is a fresh copy of the BoRG-like survey section (Moffat PSFs); ``load`` validates a
dict as if read from ``tmp_path/config.yaml``; ``error_of`` returns the ConfigError's message.
"""
import copy

import pytest

from glaciar.config import ConfigError, config_from_dict


MOFFAT = {"profile": "moffat", "fwhm_arcsec": 0.18}
BASE = {
    "survey": {
        "fields": ["f1", "f2"],
        "image_dir": "images",
        "science": "{field}_{band}_drz.fits",
        "noise": "{field}_{band}_wht.fits",
        "detection_band": "f160w",
        "bands": {
            "f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.946, "psf": MOFFAT},
            "f098m": {"filter": "wfc3_ir_f098m", "zeropoint": 25.667, "psf": MOFFAT},
            "f125w": {"filter": "wfc3_ir_f125w", "zeropoint": 26.230, "psf": MOFFAT},
            "f606w": {"filter": "wfc3_uvis_f606w", "zeropoint": 26.069, "psf": MOFFAT},
        },
    },
}


def base():
    return copy.deepcopy(BASE)


def load(data, tmp_path, name="config.yaml"):
    return config_from_dict(data, tmp_path, name)


def error_of(data, tmp_path):
    with pytest.raises(ConfigError) as info:
        load(data, tmp_path)
    return str(info.value)
