"""The interlopers: section: absent by default, validated with one-line errors naming the key."""
import pytest

from config_dicts import base, error_of, load
from glaciar.config import config_from_dict, config_hash, config_to_dict, store_hash, template_yaml


def test_absent_section_keeps_the_configuration_as_it_was(tmp_path):
    cfg = load(base(), tmp_path)
    assert cfg.interlopers is None
    assert "interlopers" not in config_to_dict(cfg)
    # the template keeps it off (its keys commented out)
    import yaml
    assert yaml.safe_load(template_yaml())["interlopers"] is None
    assert "#   z_range:" in template_yaml()


def test_section_defaults_and_round_trip(tmp_path):
    d = base()
    d["interlopers"] = {"z_range": [1.0, 2.0], "z_step": 0.5, "mag_range": [25, 26.5],
                        "mag_step": 0.5}
    cfg = load(d, tmp_path)
    assert cfg.interlopers.z_nodes() == [1.0, 1.5, 2.0]
    assert cfg.interlopers.mag_cells() == [25.25, 25.75, 26.25]
    assert config_from_dict(config_to_dict(cfg), tmp_path) == cfg
    # the run's identity names the interlopers; the target population's store does not
    assert config_hash(cfg) != config_hash(load(base(), tmp_path))
    assert store_hash(cfg) == store_hash(load(base(), tmp_path))


@pytest.mark.parametrize("section, where", [
    ({"z_range": [4.0, 1.0]}, "interlopers.z_range"),
    ({"z_range": [0.0, 3.0]}, "interlopers.z_range"),
    ({"mag_step": -1}, "interlopers.mag_step"),
    ({"n_per_task": 0}, "interlopers.n_per_task"),
    ({"dusty": {"a_v": [2.0]}}, "interlopers.dusty.a_v"),
    ({"dusty": {"a_v": [3.0, 1.0]}}, "interlopers.dusty.a_v"),
    ({"balmer": {"d4000": [0.5, 1.5]}}, "interlopers.balmer.d4000"),
    ({"counts": {"slope": 0.3}}, "interlopers.counts.slope"),
    ({"dusty": {"weight": 0}, "balmer": {"weight": 0}}, "interlopers.dusty.weight"),
    ({"dusty": {"weight": 0.6}, "balmer": {"weight": 0.6}}, "interlopers.dusty.weight"),
    ({"sersic_fractions": [0.5, 0.2]}, "interlopers.sersic_fractions"),
    ({"families": {}}, "interlopers.families"),
])
def test_bad_section_is_one_line_naming_the_key(tmp_path, section, where):
    d = base()
    d["interlopers"] = section
    msg = error_of(d, tmp_path)
    assert "\n" not in msg
    assert msg.startswith(f"config.yaml: {where}")
