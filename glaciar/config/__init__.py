"""Configuration: one typed source of truth for every key, default, unit and constraint.

- :mod:`glaciar.config.models` -- the schema as frozen pydantic models (the ``survey:``
  section in :mod:`glaciar.config.survey_models`, their base in :mod:`glaciar.config.section`);
- :mod:`glaciar.config.io` -- reading (bounded YAML), writing, hashing, file checks;
- :mod:`glaciar.config.sextractor` -- SExtractor ``.sex`` files;
- :mod:`glaciar.config.glaciar_compat` -- GLACiAR's ``parameters.yaml``;
- :mod:`glaciar.config.schema` -- ``glaciar init``'s template and the documented
  schema, both generated from the models.
"""
from .common import ConfigError
from .glaciar_compat import is_glaciar_parameters
from .io import (check_files, config_from_dict, config_hash, config_to_dict, load_config,
                 missing_files, store_hash)
from .models import (ClassificationConfig, Config, DetectionConfig, GridConfig, OutputConfig,
                     SimulationConfig, SourceConfig, selection_columns)
from .schema import schema_yaml, template_yaml
from .sextractor import read_sex_file
from .survey_models import BandConfig, SurveyConfig, read_fields_file

__all__ = ["ConfigError", "Config", "BandConfig", "SurveyConfig", "GridConfig", "SimulationConfig",
           "SourceConfig", "DetectionConfig", "ClassificationConfig", "OutputConfig",
           "load_config", "config_from_dict", "config_to_dict", "config_hash", "store_hash",
           "check_files", "missing_files", "template_yaml", "schema_yaml", "read_fields_file",
           "read_sex_file", "is_glaciar_parameters", "selection_columns"]
