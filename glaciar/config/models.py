"""The configuration schema as typed models: every key, default, unit and constraint once.

The ``survey:`` section lives in :mod:`glaciar.config.survey_models`, the base model and
the plausibility bounds every section shares in :mod:`glaciar.config.section`.

Each section of a glaciar YAML file is a frozen pydantic model. Defaults of
the science settings are taken from the engine's own dataclasses
(:class:`~glaciar.galaxy.population.SourceModel`,
:class:`~glaciar.engine.detect.DetectionParams`,
:class:`~glaciar.engine.classify.ClassificationParams`) so they cannot drift;
``glaciar init``'s template and ``docs/config-schema.yaml`` are generated from
these models (:mod:`glaciar.config.schema`). Paths in a file are relative to
the file's directory, passed as the validation context ``base_dir``.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar

from pydantic import BeforeValidator, Field, ValidationInfo, field_validator, model_validator

from .. import constants
from ..box import box_points
from ..engine import noise as _noise
from ..engine.classify import ClassificationParams
from ..engine.detect import BACKENDS, CLEAN_STYLES, THRESHOLD_RMS, DetectionParams, builtin_filter_names
from ..engine.selection import DEFAULT_JDROPOUT, MAX_EXPRESSIONS, SelectionError, compile_selection
from ..engine.user_selection import load_selection_function
from ..galaxy.filters import looks_like_path
from ..galaxy.population import SourceModel
from ..galaxy.sersic import Q_MIN
from .common import (At, Choice, ConfigError, Float, Int, add_warning, read_yaml,
                     resolve_filter_name, resolve_path, show, yaml_bool_hint)
from .sextractor import detection_keys_from_sex
from .section import (Bool, context_base_dir, engine_default, float_list, MAX_ABS_MAGNITUDE,
                      MAX_APERTURE_PIX, MAX_BOX_POINTS, MAX_DETECT_THRESH, MAX_GRID_VALUES,
                      MAX_R_EFF_KPC, MAX_REDSHIFT, MAX_TASKS, Section, validate_nested)
from .interlopers import InterloperConfig
from .survey_models import SurveyConfig
from .user_selection import SelectionFunctionConfig

__all__ = ["AxisSpec", "GridCell", "GridConfig", "GridBox", "SimulationConfig", "SourceConfig",
           "DetectionConfig", "ClassificationConfig", "OutputConfig", "NoiseConfig", "Config", "SECTIONS",
           "selection_columns", "read_cells_file"]

# ---------------------------------------------------------------------------
# grid
# ---------------------------------------------------------------------------
class AxisSpec(Section):
    """One grid axis: ``{min, max, step}`` (max included within step/1000),
    ``{min, max, n_bins}`` or ``{values: [...]}``; validated to ``{values}``."""

    #: Smallest and largest allowed values (None: any).
    _lower: ClassVar[float | None] = None
    _upper: ClassVar[float | None] = None
    min: Float | None = Field(None, description="first value")
    max: Float | None = Field(None, description="last value (included within step/1000)")
    step: Float | None = Field(None, gt=0, description="spacing")
    n_bins: Int | None = Field(None, ge=1, description="number of values from min to max")
    values: tuple[Float, ...] | None = Field(None, description="explicit, strictly increasing")

    @model_validator(mode="after")
    def _canonical(self):
        lower, upper = type(self)._lower, type(self)._upper
        if self.values is not None:
            for key in ("min", "max", "step", "n_bins"):
                if getattr(self, key) is not None:
                    raise At("cannot be combined with values", key)
            values = self.values
            if not values:
                raise At("expected at least 1 value(s), got 0", "values")
            for i, v in enumerate(values):
                if lower is not None and v < lower:
                    raise At(f"must be >= {lower:g}, got {v:g}", "values", i)
                if upper is not None and v > upper:
                    raise At(f"must be <= {upper:g}, got {v:g}", "values", i)
            if any(b <= a for a, b in zip(values, values[1:])):
                raise At("must be strictly increasing", "values")
        else:
            for key in ("min", "max"):
                if getattr(self, key) is None:
                    raise At("missing required key", key)
                if lower is not None and getattr(self, key) < lower:
                    raise At(f"must be >= {lower:g}, got {getattr(self, key):g}", key)
                if upper is not None and getattr(self, key) > upper:
                    raise At(f"must be <= {upper:g}, got {getattr(self, key):g}", key)
            lo, hi = self.min, self.max
            if lo > hi:
                raise At(f"min ({lo:g}) > max ({hi:g})")
            if (self.step is None) == (self.n_bins is None):
                raise At("give exactly one of step and n_bins")
            if self.step is not None:
                n = math.floor((hi - lo + self.step / 1000.0) / self.step) + 1
                if n > MAX_GRID_VALUES:
                    raise At(f"{n} grid values (more than {MAX_GRID_VALUES}): is the step too "
                             "small?")
                values = [lo + k * self.step for k in range(n)]
            else:
                n = self.n_bins
                if n > MAX_GRID_VALUES:
                    raise At(f"must be <= {MAX_GRID_VALUES}, got {n}", "n_bins")
                if n == 1 and hi != lo:
                    raise At("n_bins = 1 needs min == max", "n_bins")
                values = [lo + k * (hi - lo) / (n - 1) for k in range(n)] if n > 1 else [lo]
            # Round away binary noise (9.0 + 3*0.2 = 9.600000000000001).
            values = tuple(round(v, 10) for v in values)
        if len(values) > MAX_GRID_VALUES:
            raise At(f"{len(values)} grid values (more than {MAX_GRID_VALUES})", "values")
        # Canonical form: only `values` (so equal grids compare equal however written).
        for key in ("min", "max", "step", "n_bins"):
            object.__setattr__(self, key, None)
        object.__setattr__(self, "values", tuple(float(v) for v in values))
        return self


class RedshiftAxis(AxisSpec):
    _lower, _upper = 0.0, MAX_REDSHIFT


class MagnitudeAxis(AxisSpec):
    _lower, _upper = -MAX_ABS_MAGNITUDE, MAX_ABS_MAGNITUDE


#: The paper's default z range is 9.0-11.9 in 15 bins (not an even step); we keep
#: 15 bins at the even 0.2 step the code actually simulates.
_Z_DEFAULT = {"min": 9.0, "max": 11.8, "step": 0.2}
_MAG_DEFAULT = {"min": 24.1, "max": 27.9, "step": 0.2}


class GridCell(Section):
    """One extra simulation cell outside (or on) the Cartesian grid.

    ``n_iterations`` is the cell's total number of iterations (tasks per
    field): a cell that is also on the grid runs the larger of the two, so a
    proposal can be re-applied without duplicating work.
    """

    z: Float = Field(ge=0, le=MAX_REDSHIFT, description="redshift")
    mag: Float = Field(ge=-MAX_ABS_MAGNITUDE, le=MAX_ABS_MAGNITUDE,
                       description="magnitude [AB mag]")
    n_iterations: Int | None = Field(None, ge=1, description="total iterations of the cell "
                                                             "(default simulation.n_iterations)")
    fields: tuple[str, ...] | None = Field(None, description="fields to simulate it in "
                                                             "(default: all)")


def read_cells_file(path) -> list:
    """The ``cells:`` list of a YAML file written by ``glaciar next --write``."""
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise At(str(exc), "cells_file") from None
    if isinstance(data, Mapping) and "cells" in data:
        data = data["cells"]
    if not isinstance(data, list):
        raise At(f"{path}: expected a list of cells (or a mapping with key 'cells'), got "
                 f"{show(data)}", "cells_file")
    return data


def _range(lower, upper):
    """A ``[lo, hi]`` pair of finite numbers in [lower, upper] (the order: the model's check)."""
    item = Annotated[Float, Field(ge=lower, le=upper)]
    return tuple[item, item]


class GridBox(Section):
    """Injection points drawn continuously over a (z, m) box (:mod:`glaciar.box`).

    ``n_points`` points of a randomly shifted Halton sequence (the shift derived
    from ``simulation.seed``), rounded to 1e-4 in z and mag; each point is a
    cell of ``n_iterations`` tasks per field. Growing ``n_points`` keeps the
    first points (a prefix of the sequence), so a store is extended, not redone.
    """

    z: _range(0.0, MAX_REDSHIFT) = Field(description="[z_lo, z_hi]: redshift range, z_lo < z_hi")
    mag: _range(-MAX_ABS_MAGNITUDE, MAX_ABS_MAGNITUDE) = Field(
        description="[m_lo, m_hi]: magnitude range [AB mag], m_lo < m_hi")
    n_points: Int = Field(ge=1, le=MAX_BOX_POINTS, description="number of (z, mag) points")
    n_iterations: Int = Field(1, ge=1, description="iterations (tasks of simulation.n_galaxies "
                                                   "sources) per point and field")
    fields: tuple[str, ...] | None = Field(None, description="fields to simulate it in "
                                                             "(default: all)")

    @model_validator(mode="after")
    def _ordered(self):
        for key in ("z", "mag"):
            lo, hi = getattr(self, key)
            if not lo < hi:
                raise At(f"expected [lo, hi] with lo < hi, got [{lo:g}, {hi:g}]", key)
        return self

    def points(self, seed: int) -> list[tuple[float, float]]:
        """The box's (z, mag) points for a run seed (:func:`glaciar.box.box_points`)."""
        return box_points(self.z, self.mag, self.n_points, seed)


class GridConfig(Section):
    """Simulation grid: one task per (field, z, mag, iteration).

    The Cartesian product of ``z`` and ``mag`` plus any explicit ``cells``
    (e.g. the proposals of ``glaciar next --write``) plus the points of a
    ``box``; tasks are keyed by their exact values, so grid, cells and box can
    grow between runs into one store.
    """

    z: RedshiftAxis = Field(default_factory=lambda: RedshiftAxis(**_Z_DEFAULT),
                            description="redshifts: {min, max, step}, {min, max, n_bins} or "
                                        "{values: [...]}; max included",
                            json_schema_extra={"template": _Z_DEFAULT})
    mag: MagnitudeAxis = Field(default_factory=lambda: MagnitudeAxis(**_MAG_DEFAULT),
                               description="magnitudes of the injected sources [AB mag]",
                               json_schema_extra={"template": _MAG_DEFAULT})
    magnitude_type: Choice("apparent", "absolute") = Field(
        "apparent", description="apparent (detection band, AB) | absolute (M_UV at 1600 A)")
    cells: tuple[GridCell, ...] = Field((), description="extra cells [{z, mag, n_iterations, "
                                        "fields}] besides the Cartesian grid",
                                        max_length=MAX_GRID_VALUES)
    cells_file: str | None = Field(None, description="a YAML file of cells (as written by "
                                                     "`glaciar next --write`), added to cells")
    box: GridBox | None = Field(None, description="points drawn continuously over a (z, mag) "
                                "box: {z: [lo, hi], mag: [lo, hi], n_points, n_iterations, "
                                "fields}; added to the grid and cells")

    @classmethod
    def _prepare(cls, data: dict, info: ValidationInfo) -> dict:
        if "cells_file" in data:
            cf = data.pop("cells_file")
            if not isinstance(cf, str) or not cf.strip():
                raise At(f"expected a file name, got {show(cf)}{yaml_bool_hint(cf)}", "cells_file")
            path = resolve_path(context_base_dir(info), cf.strip())
            if not Path(path).is_file():
                raise At(f"file not found: {path}", "cells_file")
            extra = read_cells_file(path)
            given = data.get("cells") or []
            if not isinstance(given, (list, tuple)):
                raise At(f"expected a list of cells, got {show(given)}", "cells")
            # Resolved into `cells` (as fields_file into fields): the run's stored config
            # lists the cells and does not depend on the file staying unchanged.
            data["cells"] = list(given) + list(extra)
        return data

    @property
    def z_values(self) -> tuple[float, ...]:
        """Redshifts of the grid."""
        return self.z.values

    @property
    def mag_values(self) -> tuple[float, ...]:
        """Magnitudes of the grid."""
        return self.mag.values


# ---------------------------------------------------------------------------
# simulation, source
# ---------------------------------------------------------------------------
class SimulationConfig(Section):
    """How many sources, how many iterations, which seed."""

    n_galaxies: Int = Field(100, ge=1, description="sources injected per iteration (they never "
                                                   "overlap)")
    n_iterations: Int = Field(100, ge=1, description="iterations per (field, z, mag) (paper: "
                                                     "100; 10 for a quick look)")
    seed: Int = Field(12345, ge=0, lt=2 ** 63, description="master seed: results are identical "
                                                           "for any number of workers")
    isolation_fraction: Float = Field(0.95, gt=0, le=1, description="sources never overlap "
                                      "within the box holding this light fraction + 2 PSF FWHM")


# astropy's realisations; importing astropy.cosmology to list them takes seconds.
_KNOWN_COSMOLOGIES = ("WMAP1", "WMAP3", "WMAP5", "WMAP7", "WMAP9", "Planck13", "Planck15",
                      "Planck18")


def _src(name):
    return engine_default(SourceModel, name)


class SourceConfig(Section):
    """The artificial galaxies (fields of :class:`~glaciar.galaxy.population.SourceModel`)."""

    r_eff_kpc_z6: Float = Field(_src("r_eff_kpc_z6"), gt=0, le=MAX_R_EFF_KPC,
                                description="half-light radius "
                                "(semi-major axis) at z = 6 [proper kpc]")
    size_evolution: Float = Field(_src("size_evolution"), description="r_e ∝ (1+z)^size_evolution")
    r_eff_scatter_dex: Float = Field(_src("r_eff_scatter_dex"), ge=0,
                                     description="log-normal scatter of r_e [dex]")
    size_luminosity_slope: Float = Field(_src("size_luminosity_slope"),
                                         description="r_e ∝ L^slope (pivot M_UV = -21)")
    sersic_indices: float_list(ge=0.2, le=10.0) = Field(_src("sersic_indices"),
                                                         description="Sersic indices n ...")
    sersic_fractions: float_list(ge=0.0, le=1.0) = Field(
        _src("sersic_fractions"), description="... and their fractions (sum to 1)")
    ellipticity_bins: Int = Field(_src("ellipticity_bins"), ge=1, le=int(round(1 / Q_MIN)),
                                  description="e = 1 - q in {0, 1/ebins, ...}; 1 = all round "
                                              f"(at most {int(round(1 / Q_MIN))}: q >= {Q_MIN})")
    position_angle_bins: Int = Field(_src("position_angle_bins"), ge=1, le=3600,
                                     description="PA in {0, 180/pbins, ...} [deg]")
    round_de_vaucouleurs: Bool = Field(_src("round_de_vaucouleurs"),
                                       description="n = 4 sources stay round")
    beta_mean: Float = Field(_src("beta_mean"), description="UV slope beta ~ N(beta_mean, "
                                                            "beta_sd), f_lambda ∝ lambda^beta")
    beta_sd: Float = Field(_src("beta_sd"), ge=0, description="scatter of beta")
    beta_per: Choice("source", "iteration") = Field(
        _src("beta_per"), description="draw beta per source | per iteration (GLACiAR's choice)")
    igm: Choice("inoue14", "madau95", "sharp") = Field(
        _src("igm"), description="IGM attenuation: inoue14 | madau95 | sharp (zero below "
                                 "1216 A rest)")
    cosmology: str = Field(_src("cosmology"), description="an astropy.cosmology realisation")
    stamp_flux_fraction: Float = Field(_src("stamp_flux_fraction"), gt=0, lt=1,
                                       description="stamps hold this fraction of the total flux")
    shot_noise: Bool | None = Field(_src("shot_noise"),
                                    description="Poisson noise of the injected sources' own "
                                                "electrons in every band with a gain "
                                                "(survey.bands.<band>.gain); null = on where "
                                                "gains are given, true = on (a gain required), "
                                                "false = noiseless stamps")

    @model_validator(mode="after")
    def _consistent(self):
        n_idx, n_frac = len(self.sersic_indices), len(self.sersic_fractions)
        if n_idx != n_frac:
            raise At(f"has {n_frac} value(s) but sersic_indices has {n_idx}", "sersic_fractions")
        total = sum(self.sersic_fractions)
        if abs(total - 1.0) > 1e-6:
            raise At(f"must sum to 1, got {total:g}", "sersic_fractions")
        names = _KNOWN_COSMOLOGIES
        if self.cosmology not in names:
            from astropy.cosmology import realizations
            names = tuple(realizations.available)
        if self.cosmology not in names:
            close = difflib.get_close_matches(self.cosmology, names, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise At(f"unknown astropy cosmology {self.cosmology!r} (available: "
                     f"{', '.join(names)}){hint}", "cosmology")
        return self


# ---------------------------------------------------------------------------
# detection (SExtractor vocabulary), classification, output
# ---------------------------------------------------------------------------
def _det(name):
    return engine_default(DetectionParams, name)


def _square(value):
    # SExtractor allows "64,64"; sep's meshes are square.
    if isinstance(value, (list, tuple)):
        vals = set(value)
        if len(vals) != 1:
            raise At(f"different values per axis ({list(value)}) are not supported")
        return vals.pop()
    return value


SquareInt = Annotated[Int, BeforeValidator(_square)]


def _first(value):
    # SExtractor allows e.g. DETECT_THRESH <sigma>,<zeropoint>: sigma is the first value.
    if isinstance(value, (list, tuple)) and value:
        return value[0]
    return value


class DetectionConfig(Section):
    """Detection and photometry in SExtractor's vocabulary (run with sep)."""

    sex_file: str | None = Field(None, alias="sex_file", description="read these keys from a "
                                 "SExtractor .sex file; keys given here win")
    detect_thresh: Annotated[Float, BeforeValidator(_first)] = Field(
        _det("detect_thresh"), gt=0, le=MAX_DETECT_THRESH, alias="DETECT_THRESH",
        description="threshold above the background [sigma]")
    detect_minarea: Int = Field(_det("detect_minarea"), ge=1, alias="DETECT_MINAREA",
                                description="minimum area above threshold [pixels]")
    filter: Bool = Field(True, alias="FILTER", description="filter the detection image")
    filter_name: str = Field(_det("filter_name"), alias="FILTER_NAME",
                             description="built-in kernel name or a .conv file")
    filter_type: Choice("conv", "matched", aliases={"convolve": "conv"}) = Field(
        _det("filter_type"), alias="FILTER_TYPE",
        description="CONVOLVE (SExtractor's) | MATCHED (sep's noise-aware filter; "
                    "runs full frame, not windowed)")
    deblend_nthresh: Int = Field(_det("deblend_nthresh"), ge=1, alias="DEBLEND_NTHRESH",
                                 description="deblending sub-thresholds")
    deblend_mincont: Float = Field(_det("deblend_mincont"), ge=0, le=1, alias="DEBLEND_MINCONT",
                                   description="minimum contrast for deblending")
    clean: Bool = Field(_det("clean"), alias="CLEAN", description="clean spurious detections")
    clean_param: Float = Field(_det("clean_param"), gt=0, alias="CLEAN_PARAM",
                               description="cleaning efficiency")
    clean_style: Choice(*CLEAN_STYLES) = Field(
        _det("clean_style"), alias="CLEAN_STYLE",
        description="glaciar's key (not SExtractor's; a .sex file's CLEAN and CLEAN_PARAM "
                    "set CLEAN and CLEAN_PARAM): region = sep's CLEAN inside each "
                    "deblended region only (fast); sextractor = SExtractor 2.x's CLEAN on "
                    "the whole injected image, cleaned pixels handed to the absorbing "
                    "object; sep = plain sep's CLEAN on the whole image; sep-merge = sep's "
                    "decisions with SExtractor's hand-over.  With CLEAN on, the three last "
                    "run full frame, not windowed")
    threshold_rms: Choice(*THRESHOLD_RMS) = Field(
        _det("threshold_rms"), alias="THRESHOLD_RMS",
        description="glaciar's key: the RMS DETECT_THRESH multiplies (THRESH_TYPE RELATIVE): "
                    "pixel = each pixel's RMS (sep); filtered = the RMS of the filtered "
                    "image (SExtractor with a weight map)")
    backend: Choice(*BACKENDS) = Field(
        _det("backend"), alias="BACKEND",
        description="glaciar's key: who segments the detection image: sep (glaciar's "
                    "windowed extraction, exact) or source-extractor (the SExtractor "
                    "binary on the full injected image, dual-image mode; slower, a reference)")
    back_size: SquareInt = Field(_det("back_size"), ge=1, alias="BACK_SIZE",
                                 description="background mesh [pixels]")
    back_filtersize: SquareInt = Field(_det("back_filtersize"), ge=1, alias="BACK_FILTERSIZE",
                                       description="background median filter [meshes]")
    phot_apertures: float_list(gt=0, le=MAX_APERTURE_PIX) = Field(
        _det("phot_apertures"), alias="PHOT_APERTURES",
        description="aperture diameters [pixels] (columns flux_aper0_<band>, ...)")
    phot_autoparams: float_list(gt=0, min_length=2, max_length=2) = Field(
        _det("phot_autoparams"), alias="PHOT_AUTOPARAMS",
        description="Kron factor, minimum radius")
    weight_type: Choice("map_weight", "map_rms", "background") | None = Field(
        None, alias="WEIGHT_TYPE",
        description="how the noise map is used: null = as an absolute map (survey.noise_type "
                    "says weight or rms); MAP_WEIGHT = a relative weight map rescaled to the "
                    "pixel noise measured on the image (drizzled, correlated noise); MAP_RMS = "
                    "an absolute RMS map; BACKGROUND = ignore the map, use the measured "
                    "background RMS")
    weight_gain: Bool = Field(False, alias="WEIGHT_GAIN",
                              description="Y (gain scaled by the weights) only without band "
                                          "gains: the gain is per band (survey.bands.<band>.gain)")
    backphoto_type: Choice("global", "local") = Field(
        _det("backphoto_type"), alias="BACKPHOTO_TYPE",
        description="GLOBAL = fluxes above the background map; LOCAL = minus a background "
                    "re-estimated per object and band (SExtractor's mode of the pixels of no "
                    "object in a rectangular annulus around its isophotal box)")
    backphoto_thick: Int = Field(_det("backphoto_thick"), ge=1, alias="BACKPHOTO_THICK",
                                 description="thickness of the LOCAL background annulus [pixels]")
    mask_type: Choice("none", "blank", "correct") | None = Field(
        _det("mask_type"), alias="MASK_TYPE",
        description="neighbours' pixels in aperture and AUTO fluxes, as SExtractor: NONE = "
                    "kept; BLANK = set to 0; CORRECT = replaced by the pixels symmetric about "
                    "the object's centre (0 if those are a neighbour's or without data); null = "
                    "sep's masking (apertures: none; AUTO: excluded and the sum scaled by the "
                    "total/unmasked area)")
    satur_level: Float = Field(_det("satur_level"), gt=0, alias="SATUR_LEVEL",
                               description="pixel value (background included) of the detection "
                                           "band from which a detection is flagged saturated "
                                           f"(source_flags bit {constants.FLAG_SATURATED}) "
                                           "[image units: ADU, e-/s, ...]")

    @classmethod
    def _normalise_keys(cls, data: dict) -> dict:
        return {(k if str(k) == "sex_file" else str(k).upper()): v for k, v in data.items()}

    @classmethod
    def _prepare(cls, data: dict, info: ValidationInfo) -> dict:
        base = context_base_dir(info)
        merged: dict[str, Any] = {}
        if "sex_file" in data:
            sex = data["sex_file"]
            if not isinstance(sex, str) or not sex.strip():
                raise At(f"expected a file name, got {show(sex)}{yaml_bool_hint(sex)}", "sex_file")
            path = resolve_path(base, sex.strip())
            if not Path(path).is_file():
                raise At(f"file not found: {path}", "sex_file")
            from_sex = detection_keys_from_sex(path, base, info)
            merged.update(from_sex)
            merged["sex_file"] = path
            origins = (info.context or {}).setdefault("origins", {})
            for key in from_sex:
                if key not in data:
                    origins[f"detection.{key}"] = f"from {path}"
        for key, value in data.items():
            if key == "FILTER_NAME":
                value = resolve_filter_name(value, [base])
            if key != "sex_file":
                merged[key] = value
        return merged

    @field_validator("filter_name")
    @classmethod
    def _builtin_or_file(cls, value: str):
        if not looks_like_path(value, (".conv",)) and value not in builtin_filter_names():
            close = difflib.get_close_matches(value, builtin_filter_names(), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise At(f"unknown built-in filter {value!r} (and not a .conv file){hint}")
        return value


def _cls(name):
    return engine_default(ClassificationParams, name)


class ClassificationConfig(Section):
    """Recovery status of each injected source (paper Sect. 2.4)."""

    min_sn: Float = Field(_cls("min_sn"), ge=0, description="detections below this S/N in the "
                                                            "detection band are status -2")
    sn_definition: Choice("iso", "aper", "auto") = Field(
        _cls("sn_definition"), description="iso (FLUX_ISO/FLUXERR_ISO) | aper | auto")
    sn_aperture_index: Int = Field(_cls("sn_aperture_index"), ge=0,
                                   description="which PHOT_APERTURES entry `aper` uses")
    search_box: Int = Field(_cls("search_box"), ge=1, description="side of the box centred on "
                                                                  "the input position [pixels, odd]")
    max_overlap_fraction: Float = Field(_cls("max_overlap_fraction"), ge=0, le=1,
                                        description="blended with a brighter source: recovered "
                                                    "if overlap < this ...")
    flux_tolerance: Float = Field(_cls("flux_tolerance"), gt=0, description="... and "
                                  "|F_AUTO - T_AUTO| / T_AUTO <= this (T_AUTO: the injected "
                                  "template's flux through the detection's Kron ellipse; the "
                                  "same whatever sn_definition)")

    @field_validator("search_box")
    @classmethod
    def _odd(cls, value: int):
        if value % 2 == 0:
            raise At(f"must be odd so the box is centred on the input position, got {value}")
        return value


class NoiseConfig(Section):
    """Correlated noise: a model of photometric errors fitted from empty apertures."""

    correlated: Choice("auto", "on", "off") = Field(
        "auto", description="fit r(N) = scatter of sums over N empty pixels / noise-map "
                            "prediction per field and band (recorded in the run); auto = "
                            "apply it to photometric errors and S/N where it differs from 1, "
                            "on = always, off = never")
    empty_aperture_radii_pix: float_list(gt=0) = Field(
        tuple(_noise.DEFAULT_EMPTY_APERTURE_RADII_PIX),
        description="radii of the empty apertures [pixels]")
    n_empty_apertures: Int = Field(1000, ge=_noise.MIN_EMPTY_APERTURES, le=100_000,
                                   description="empty apertures per radius")
    identity_tolerance: Float = Field(0.05, ge=0, le=1, description="auto: r(N) within this of "
                                      "1 (beyond its noise) counts as uncorrelated")


class OutputConfig(Section):
    """Optional outputs."""

    regions: Bool = Field(False, description="DS9 region files coloured by status")


# ---------------------------------------------------------------------------
# The whole configuration
# ---------------------------------------------------------------------------
def selection_columns(band_names, n_apertures: int) -> tuple[str, ...]:
    """Names of the per-source columns a selection expression may use.

    Parameters
    ----------
    band_names : iterable of str
        Survey bands.
    n_apertures : int
        Number of photometric apertures (``flux_aper{k}_<band>``, k = 0..n-1).

    Returns
    -------
    tuple of str
        Every ``COL_*`` column of :mod:`glaciar.constants` and every per-band
        quantity (``BAND_QUANTITIES`` plus aperture fluxes) for every band.
    """
    cols = [getattr(constants, n) for n in dir(constants) if n.startswith("COL_")]
    for b in band_names:
        cols += [constants.band_column(q, b) for q in constants.BAND_QUANTITIES]
        for k in range(n_apertures):
            cols += [constants.band_column(f"flux_aper{k}", b),
                     constants.band_column(f"fluxerr_aper{k}", b)]
    return tuple(dict.fromkeys(cols))


def _selection_list(value, info: ValidationInfo):
    if isinstance(value, str):
        return [value]
    if isinstance(value, SelectionFunctionConfig):
        return value
    if isinstance(value, Mapping):
        # A user function (glaciar.engine.user_selection); imported once every band is known.
        return validate_nested(SelectionFunctionConfig, value, info)
    if not isinstance(value, (list, tuple)):
        raise At(f"expected a list of expression strings or {{function: "
                 f"'package.module:callable'}}, got {show(value)}")
    for i, e in enumerate(value):
        if not isinstance(e, str):
            raise At(f"expected an expression string, got {show(e)} (quote expressions in YAML)",
                     i)
    return [e.strip() for e in value]


class Config(Section):
    """A complete, validated configuration.

    ``path`` (the file it came from), ``base_dir`` (what relative paths were
    relative to) and ``warnings`` (choices made while reading it, e.g. in a
    GLACiAR file) do not take part in equality.
    """

    _internal = ("path", "base_dir", "warnings")
    _keep_none = ("selection",)
    survey: SurveyConfig = Field(description="fields, bands and images")
    grid: GridConfig = Field(default_factory=GridConfig, description="simulation grid")
    simulation: SimulationConfig = Field(default_factory=SimulationConfig,
                                         description="sources, iterations, seed")
    source: SourceConfig = Field(default_factory=SourceConfig, description="the artificial "
                                                                           "galaxies")
    detection: DetectionConfig = Field(default_factory=DetectionConfig,
                                       description="SExtractor vocabulary (run with sep)")
    classification: ClassificationConfig = Field(default_factory=ClassificationConfig,
                                                 description="recovery status")
    noise: NoiseConfig = Field(default_factory=NoiseConfig, description="correlated noise of "
                                                                        "real images")
    selection: Annotated[tuple[str, ...] | SelectionFunctionConfig,
                         BeforeValidator(_selection_list)] | None = Field(
        None, description="all must hold; expressions over per-source columns (default: the "
                          "BoRG J125-dropout of Bernard et al. 2016 when its bands exist; "
                          "[] = selected means recovered), or {function: "
                          "'package.module:callable'} (docs/configuration.md)")
    output: OutputConfig = Field(default_factory=OutputConfig, description="optional outputs")
    interlopers: InterloperConfig | None = Field(None, description="a low-z interloper "
                                                 "population for contamination (absent: none)")
    path: Path | None = None
    base_dir: Path = Path(".")
    warnings: tuple[str, ...] = ()

    @classmethod
    def _prepare(cls, data: dict, info: ValidationInfo) -> dict:
        # An explicit `selection: null` or [] means "no selection", unlike a missing key.
        if "selection" not in data:
            data["selection"] = None
        elif data["selection"] is None:
            data["selection"] = ()
        return data

    @model_validator(mode="after")
    def _cross_checks(self, info: ValidationInfo):
        wt, nt = self.detection.weight_type, self.survey.noise_type
        if wt in ("map_weight", "map_rms"):
            wanted = {"map_weight": "weight", "map_rms": "rms"}[wt]
            if self.survey.noise is None:
                raise At(f"{wt.upper()} needs a noise map (survey.noise)", "detection",
                         "WEIGHT_TYPE")
            if nt != wanted:
                raise At(f"{wt.upper()} needs survey.noise_type: {wanted}, got {nt}",
                         "detection", "WEIGHT_TYPE")
        gains = [b.name for b in self.survey.bands if b.gain is not None]
        if self.detection.weight_gain and gains:
            raise At(f"WEIGHT_GAIN Y (gain proportional to the weight) is not supported with band "
                     f"gains ({', '.join(gains)}): the gain is per band; set WEIGHT_GAIN N",
                     "detection", "WEIGHT_GAIN")
        if self.source.shot_noise and not gains:
            raise At("is true but no band has a gain (survey.bands.<band>.gain, electrons per "
                     "image unit): give the gains, or set it to false", "source", "shot_noise")
        n_ap = len(self.detection.phot_apertures)
        if self.classification.sn_aperture_index >= n_ap:
            raise At(f"is {self.classification.sn_aperture_index} but detection.PHOT_APERTURES "
                     f"has {n_ap} aperture(s)", "classification", "sn_aperture_index")
        fields = set(self.survey.fields)
        n_cell_tasks = 0
        for i, cell in enumerate(self.grid.cells):
            unknown = [f for f in (cell.fields or ()) if f not in fields]
            if unknown:
                raise At(f"field(s) {unknown} not in survey.fields", "grid", "cells", i, "fields")
            n_cell_tasks += ((cell.n_iterations or self.simulation.n_iterations)
                             * len(cell.fields or fields))
        box = self.grid.box
        n_box_tasks = 0
        if box is not None:
            unknown = [f for f in (box.fields or ()) if f not in fields]
            if unknown:
                raise At(f"field(s) {unknown} not in survey.fields", "grid", "box", "fields")
            n_box_tasks = box.n_points * box.n_iterations * len(box.fields or fields)
        n_tasks = (len(self.survey.fields) * len(self.grid.z_values) * len(self.grid.mag_values)
                   * self.simulation.n_iterations) + n_cell_tasks + n_box_tasks
        if n_tasks > MAX_TASKS:
            cells = f" + {n_cell_tasks} of grid.cells" if n_cell_tasks else ""
            cells += f" + {n_box_tasks} of grid.box" if n_box_tasks else ""
            raise At(f"{self.simulation.n_iterations} iterations x {len(self.survey.fields)} "
                     f"field(s) x {len(self.grid.z_values)} z x {len(self.grid.mag_values)} mag"
                     f"{cells} = {n_tasks:.3g} tasks, more than the {MAX_TASKS:.0e} one run can "
                     "plan",
                     "simulation", "n_iterations")
        if isinstance(self.selection, SelectionFunctionConfig):
            try:
                self.selection.resolved(load_selection_function(
                    self.selection.function, self.selection.kwargs, self.survey.band_names,
                    {b.name: float(b.zeropoint) for b in self.survey.bands}, n_ap))
            except SelectionError as exc:
                raise At(str(exc), "selection", "function") from None
            return self
        columns = selection_columns(self.survey.band_names, n_ap)
        if self.selection is None:
            try:
                compile_selection(DEFAULT_JDROPOUT, columns)
                selection = DEFAULT_JDROPOUT
            except SelectionError:
                add_warning(info, "selection: no selection given and the default BoRG J-dropout "
                            "criteria need bands f160w, f125w, f098m and f606w; no selection "
                            "is applied (selected = recovered)")
                selection = ()
            object.__setattr__(self, "selection", tuple(selection))
        if len(self.selection) > MAX_EXPRESSIONS:
            raise At(f"{len(self.selection)} expressions (at most {MAX_EXPRESSIONS})", "selection")
        for i, e in enumerate(self.selection):
            try:
                compile_selection([e], columns)
            except SelectionError as exc:
                raise At(str(exc), "selection", i) from None
        return self

    def __eq__(self, other):
        if not isinstance(other, Config):
            return NotImplemented
        skip = set(self._internal)
        return all(getattr(self, k) == getattr(other, k)
                   for k in type(self).model_fields if k not in skip)

    __hash__ = None


#: Top-level sections in file order, with their models.
SECTIONS = {name: f for name, f in Config.model_fields.items() if name not in Config._internal}
