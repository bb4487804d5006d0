"""The lensed demo: the demo survey behind an analytic cluster lens (``glaciar demo --lensed``).

The same synthetic field and grid as :func:`glaciar.demo.build_demo_survey`, with
``survey.lens`` an SIS (Einstein radius 8" for D_ls/D_s = 1, ~7.6" at z = 9, its critical
curve inside the 80" field) plus an external shear, at the redshift of Abell 2744
(docs/lensing.md).  Nothing is downloaded.
"""
from __future__ import annotations

from pathlib import Path

from ..rundir import atomic_write_text
from .bands import CRVAL_DEG

__all__ = ["DEMO_LENS", "DEMO_LENSED_CONFIG_NAME", "write_lensed_demo_config"]

DEMO_LENSED_CONFIG_NAME = "demo_lensed.yaml"
#: The demo's lens: SIS 7.2" north and 3.4" east of the field's centre, plus external shear.
DEMO_LENS = {"z_lens": 0.308,
             "analytic": {"sis": {"theta_e_arcsec": 8.0,
                                  "center_ra_deg": round(CRVAL_DEG[0] + 0.0015, 6),
                                  "center_dec_deg": round(CRVAL_DEG[1] + 0.002, 6)},
                          "shear": {"gamma1": 0.05, "gamma2": -0.03}}}


def write_lensed_demo_config(demo_config) -> Path:
    """Write ``demo_lensed.yaml`` beside a demo configuration (as
    :func:`~glaciar.demo.build_demo_survey` wrote it): the same survey and settings with
    ``survey.lens`` = :data:`DEMO_LENS`.  Returns its path."""
    import yaml

    from .survey import config_dumper

    demo_config = Path(demo_config)
    text = demo_config.read_text(encoding="utf-8")
    header = "".join(line + "\n" for line in text.splitlines() if line.startswith("#"))
    config = yaml.safe_load(text)
    survey = config["survey"]
    # Keys in the schema's order: lens before detection_band.
    keys = list(survey)
    at = keys.index("detection_band") if "detection_band" in keys else len(keys)
    config["survey"] = {**{k: survey[k] for k in keys[:at]}, "lens": DEMO_LENS,
                        **{k: survey[k] for k in keys[at:]}}
    header += ("# Lensed: behind an SIS (theta_E = 8\" at D_ls/D_s = 1) + external shear at "
               "z = 0.308 (glaciar demo --lensed; docs/lensing.md).\n")
    path = demo_config.parent / DEMO_LENSED_CONFIG_NAME
    atomic_write_text(path, header + yaml.dump(config, Dumper=config_dumper(), sort_keys=False,
                                               default_flow_style=False, width=100))
    return path
