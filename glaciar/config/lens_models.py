"""The ``survey.lens:`` section: a foreground cluster lens in front of the fields.

Lens models are maps normalised to ``D_ls / D_s = 1`` (as public models are): either
convergence and shear (``kappa``, ``gamma1``, ``gamma2``) or deflections (``alpha_x``,
``alpha_y``), FITS files with a celestial WCS, named by templates with ``{field}`` filled
in, relative to ``survey.image_dir`` like ``survey.science``; or, for the demo and tests,
an analytic singular isothermal sphere plus external shear.  The first model drives the
injections; every model is kept for V_eff.  Conventions: docs/lensing.md and
:mod:`glaciar.galaxy.lensing`.
"""
from __future__ import annotations

import string

from pydantic import Field, model_validator

from .common import At, Choice, Float, show
from .section import MAX_REDSHIFT, Section

__all__ = ["LensConfig", "LensModelConfig", "AnalyticLensConfig", "SISConfig", "ShearConfig",
           "LENS_MAP_KEYS"]

#: The map keys of a model given as files: convergence + shear, or deflections.
LENS_MAP_KEYS = {"kappa": ("kappa", "gamma1", "gamma2"), "deflection": ("alpha_x", "alpha_y")}


def _template(value, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise At(f"expected a FITS file-name template such as '{{field}}_{key}.fits', got "
                 f"{show(value)}", key)
    try:
        parts = list(string.Formatter().parse(value))
    except ValueError as exc:
        raise At(f"invalid file-name template {value!r}: {exc}", key) from None
    for _, name, spec, conv in parts:
        if name is not None and (name != "field" or spec or conv):
            raise At(f"template {value!r}: only the placeholder {{field}} is allowed, found "
                     f"{{{name}}}", key)
    return value.strip()


class SISConfig(Section):
    """A singular isothermal sphere (Einstein radius for D_ls/D_s = 1)."""

    theta_e_arcsec: Float = Field(gt=0, le=1000, description="Einstein radius at D_ls/D_s = 1 "
                                                             "[arcsec]")
    center_ra_deg: Float | None = Field(None, ge=0, lt=360, description="centre RA [deg] "
                                        "(with center_dec_deg; or center_x_pix/center_y_pix)")
    center_dec_deg: Float | None = Field(None, ge=-90, le=90, description="centre Dec [deg]")
    center_x_pix: Float | None = Field(None, description="centre, 0-based pixel of each field's "
                                                         "detection image (axis 1)")
    center_y_pix: Float | None = Field(None, description="centre, 0-based pixel (axis 0)")

    @model_validator(mode="after")
    def _one_centre(self):
        sky = (self.center_ra_deg, self.center_dec_deg)
        pix = (self.center_x_pix, self.center_y_pix)
        has_sky, has_pix = any(v is not None for v in sky), any(v is not None for v in pix)
        if has_sky == has_pix:
            raise At("give the centre as center_ra_deg/center_dec_deg or as "
                     "center_x_pix/center_y_pix (one pair)", "center_ra_deg")
        pair = sky if has_sky else pix
        if any(v is None for v in pair):
            raise At("both coordinates of the centre are required",
                     "center_dec_deg" if has_sky else "center_y_pix")
        return self


class ShearConfig(Section):
    """A constant external shear (components along the image's pixel axes)."""

    gamma1: Float = Field(0.0, ge=-1, le=1, description="shear along x (axis 1) at D_ls/D_s = 1")
    gamma2: Float = Field(0.0, ge=-1, le=1, description="shear along the diagonal x = y")


class AnalyticLensConfig(Section):
    """An analytic lens: SIS + external shear."""

    sis: SISConfig = Field(description="{theta_e_arcsec, center_ra_deg/center_dec_deg or "
                                       "center_x_pix/center_y_pix}")
    shear: ShearConfig = Field(default_factory=ShearConfig, description="{gamma1, gamma2}")


class LensModelConfig(Section):
    """One lens model: kappa/gamma1/gamma2 maps, or alpha_x/alpha_y deflection maps."""

    name: str = Field(description="model name (manifest, V_eff per model)")
    kappa: str | None = Field(None, description="convergence map template ({field}), relative "
                                                "to survey.image_dir")
    gamma1: str | None = Field(None, description="shear component 1 map template")
    gamma2: str | None = Field(None, description="shear component 2 map template")
    alpha_x: str | None = Field(None, description="deflection along the map's x (axis 1) "
                                                  "template; with alpha_y instead of kappa/gamma")
    alpha_y: str | None = Field(None, description="deflection along the map's y (axis 0) template")
    deflection_unit: Choice("arcsec", "pixel") = Field(
        "arcsec", description="unit of the deflection maps: arcsec, or pixels of the map")

    @model_validator(mode="before")
    @classmethod
    def _templates(cls, data):
        if isinstance(data, dict):
            for key in ("kappa", "gamma1", "gamma2", "alpha_x", "alpha_y"):
                if data.get(key) is not None:
                    data = {**data, key: _template(data[key], key)}
        return data

    @model_validator(mode="after")
    def _one_kind(self):
        given = {k for k in ("kappa", "gamma1", "gamma2", "alpha_x", "alpha_y")
                 if getattr(self, k) is not None}
        for kind, keys in LENS_MAP_KEYS.items():
            if given == set(keys):
                return self
        raise At("give either kappa, gamma1 and gamma2, or alpha_x and alpha_y (file "
                 f"templates); got {', '.join(sorted(given)) or 'none'}", "kappa")

    @property
    def kind(self) -> str:
        """``"kappa"`` (convergence and shear maps) or ``"deflection"``."""
        return "kappa" if self.kappa is not None else "deflection"

    @property
    def map_keys(self) -> tuple[str, ...]:
        return LENS_MAP_KEYS[self.kind]


class LensConfig(Section):
    """A foreground lens in front of every field (docs/lensing.md)."""

    z_lens: Float = Field(ge=0, le=MAX_REDSHIFT, description="lens redshift",
                          json_schema_extra={"example": 0.308})
    models: tuple[LensModelConfig, ...] = Field(
        (), description="lens models as FITS maps with a WCS, normalised to D_ls/D_s = 1: "
                        "[{name, kappa, gamma1, gamma2} or {name, alpha_x, alpha_y, "
                        "deflection_unit}]; the first drives the injections")
    analytic: AnalyticLensConfig | None = Field(
        None, description="instead of models: {sis: {theta_e_arcsec, center_ra_deg, "
                          "center_dec_deg}, shear: {gamma1, gamma2}} (the demo's lens)")

    @model_validator(mode="after")
    def _models_or_analytic(self):
        if bool(self.models) == (self.analytic is not None):
            raise At("give either models (a list of lens maps) or analytic, not both or "
                     "neither", "models")
        names = [m.name for m in self.models]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise At(f"duplicate model name(s): {', '.join(dup)}", "models")
        return self

    @property
    def model_names(self) -> tuple[str, ...]:
        """Names of the models, the first driving the injections (``("analytic",)`` for the
        analytic lens)."""
        return tuple(m.name for m in self.models) if self.models else ("analytic",)
