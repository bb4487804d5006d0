"""``glaciar init``'s template and the documented schema (glaciar.config.schema): valid, generated from the
models, covering every key.
"""
from pathlib import Path

import yaml

from glaciar.config import template_yaml
from glaciar.engine.selection import DEFAULT_JDROPOUT

from config_dicts import base, load


REPO = Path(__file__).resolve().parents[2]


def test_template_is_valid_and_documents_defaults(tmp_path):
    text = template_yaml()
    assert text.lstrip().startswith("#")
    data = yaml.safe_load(text)
    cfg = load(data, tmp_path, "template.yaml")
    defaults = load(base(), tmp_path)
    # The template writes the defaults out explicitly.
    assert cfg.source == defaults.source
    assert cfg.detection == defaults.detection
    assert cfg.classification == defaults.classification
    assert cfg.simulation == defaults.simulation and cfg.grid == defaults.grid
    assert cfg.selection == DEFAULT_JDROPOUT


# ---------------------------------------------------------------------------
# One source of truth: the template, the documented schema and the engine defaults
# ---------------------------------------------------------------------------
def test_documented_schema_is_generated_from_the_models():
    from glaciar.config import schema_yaml

    committed = (REPO / "docs" / "config-schema.yaml").read_text()
    assert committed == schema_yaml(), (
        "docs/config-schema.yaml is stale; regenerate it with "
        "python -c \"import glaciar.config as c; print(c.schema_yaml(), end='')\" "
        "> docs/config-schema.yaml")


def test_template_and_schema_cover_every_key():
    from glaciar.config import schema_yaml
    from glaciar.config.models import SECTIONS
    from glaciar.config.survey_models import BandConfig

    template = yaml.safe_load(template_yaml())
    schema = yaml.safe_load(schema_yaml())
    for section, info in SECTIONS.items():
        assert section in template and section in schema
        model = info.annotation
        if not hasattr(model, "user_keys"):
            continue
        for key in model.user_keys():
            assert key in schema[section]["keys"], (section, key)
            if (section, key) != ("survey", "fields_file"):     # an alternative to fields
                assert key in template[section], (section, key)
    first_band = next(iter(template["survey"]["bands"].values()))
    assert set(first_band) == set(BandConfig.user_keys())
