"""The lensed demo's configuration (glaciar.demo.lensed, `glaciar demo --lensed`)."""
import shutil
from pathlib import Path

import yaml

from glaciar.config import load_config
from glaciar.demo.lensed import write_lensed_demo_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_demo_lensed_config_is_the_demo_plus_the_lens_glaciar_demo_writes(tmp_path):
    """configs/demo_lensed.yaml = what `glaciar demo --lensed` writes beside demo.yaml (from
    configs/demo.yaml, which a test keeps equal to the demo's): the demo plus an analytic
    SIS + shear lens whose Einstein ring lies inside the 80" field."""
    shutil.copyfile(CONFIGS / "demo.yaml", tmp_path / "demo.yaml")
    written = write_lensed_demo_config(tmp_path / "demo.yaml")
    ours = yaml.safe_load((CONFIGS / "demo_lensed.yaml").read_text(encoding="utf-8"))
    assert yaml.safe_load(written.read_text(encoding="utf-8")) == ours
    plain = yaml.safe_load((CONFIGS / "demo.yaml").read_text(encoding="utf-8"))
    lens = ours["survey"].pop("lens")
    assert ours == plain
    cfg = load_config(written)
    sis = cfg.survey.lens.analytic.sis
    # The lens centre within 10" of the demo field's centre (RA 219.21135, Dec 50.72650).
    offset = (((sis.center_ra_deg - 219.21135) * 0.6334) ** 2
              + (sis.center_dec_deg - 50.72650) ** 2) ** 0.5 * 3600
    assert offset < 10 and sis.theta_e_arcsec + offset < 40 and lens["z_lens"] > 0
