"""The ``survey:`` section's models: bands, their PSFs and the detection image.

Part of the schema of :mod:`glaciar.config.models` (which holds the other sections and
:class:`~glaciar.config.models.Config`); the shared base is :mod:`glaciar.config.section`.
"""
from __future__ import annotations

import difflib
import os
import re
import string
from collections.abc import Mapping
from pathlib import Path

from pydantic import Field, ValidationInfo, field_validator, model_validator

from ..galaxy import psf as _psf
from ..galaxy.filters import FILE_SUFFIXES as FILTER_FILE_SUFFIXES, get_filter, looks_like_path
from .common import At, Choice, Float, Int, resolve_path, show, yaml_bool_hint
from .lens_models import LensConfig
from .section import (arg_default, context_base_dir, MAX_ABS_MAGNITUDE, MAX_PIXEL_SCALE_ARCSEC,
                      PSF_FWHM_RANGE_ARCSEC, Section, validate_nested)

__all__ = ["PSF_PROFILES", "PsfProfile", "BandConfig", "DetectionImageConfig", "SurveyConfig",
           "read_fields_file"]

# ---------------------------------------------------------------------------
# survey
# ---------------------------------------------------------------------------
#: profile -> (required keys, optional keys with the defaults of glaciar.galaxy.psf)
PSF_PROFILES = {
    "gaussian": (("fwhm_arcsec",), {}),
    "moffat": (("fwhm_arcsec",), {"beta": arg_default(_psf.moffat_psf, "beta")}),
    "airy": (("wavelength_angstrom",), {"diameter_m": arg_default(_psf.airy_psf, "diameter_m"),
                                        "obscuration": arg_default(_psf.airy_psf, "obscuration")}),
}


class PsfProfile(Section):
    """An analytic PSF (the keys allowed depend on ``profile``)."""

    profile: Choice(*PSF_PROFILES) = Field(description="moffat | gaussian | airy")
    fwhm_arcsec: Float | None = Field(None, ge=PSF_FWHM_RANGE_ARCSEC[0],
                                      le=PSF_FWHM_RANGE_ARCSEC[1],
                                      description="FWHM [arcsec] (moffat, gaussian)")
    beta: Float | None = Field(None, gt=1, description="Moffat index")
    wavelength_angstrom: Float | None = Field(None, gt=0, description="wavelength [Å] (airy)")
    diameter_m: Float | None = Field(None, gt=0, description="telescope diameter [m] (airy)")
    obscuration: Float | None = Field(None, ge=0, lt=1,
                                      description="central obscuration, fraction of the diameter")
    size: Int | None = Field(None, ge=1, description="stamp side [pixels, odd]")

    @model_validator(mode="after")
    def _keys_of_profile(self):
        required, optional = PSF_PROFILES[self.profile]
        allowed = ("profile",) + required + tuple(optional) + ("size",)
        for name in type(self).model_fields:
            if getattr(self, name) is not None and name not in allowed:
                raise At(f"unknown key {name!r} for a {self.profile} PSF; allowed keys: "
                         f"{', '.join(allowed)}", name)
        for name in required:
            if getattr(self, name) is None:
                raise At(f"missing required key for a {self.profile} PSF", name)
        if self.size is not None and self.size % 2 == 0:
            raise At(f"must be odd (PSF centred on a pixel), got {self.size}", "size")
        return self

    def spec(self) -> dict:
        """The mapping :func:`glaciar.galaxy.psf.prepare_psf` takes (defaults filled in)."""
        required, optional = PSF_PROFILES[self.profile]
        out = {"profile": self.profile}
        for key in required + tuple(optional):
            value = getattr(self, key)
            out[key] = optional[key] if value is None else value
        if self.size is not None:
            out["size"] = self.size
        return out


class BandConfig(Section):
    """One photometric band; its key in ``survey.bands`` is its name."""

    _internal = ("name",)
    name: str = Field(description="band name: column suffix (lower case) and {band} in templates")
    filter: str = Field(description="built-in filter (wfc3_ir_*, wfc3_uvis_*, acs_wfc_*, nircam_*) "
                                    "or a throughput curve file (.tab/.dat/.par/.fits)",
                        json_schema_extra={"example": "wfc3_ir_f160w"})
    zeropoint: Float = Field(ge=-MAX_ABS_MAGNITUDE, le=MAX_ABS_MAGNITUDE,
                             description="AB magnitude of one image unit (e.g. 1 e-/s) [mag]",
                             json_schema_extra={"example": 25.946})
    gain: Float | None = Field(None, gt=0, description="e- per image unit (e.g. the exposure "
                                                       "time [s] for e-/s images): flux errors' "
                                                       "source term and the injected sources' "
                                                       "shot noise (source.shot_noise); null = "
                                                       "unknown")
    psf: str | dict = Field(description="a FITS file, or {profile: moffat|gaussian|airy, "
                                        "fwhm_arcsec, beta, wavelength_angstrom, diameter_m, "
                                        "obscuration, size}",
                            json_schema_extra={"example": {"profile": "moffat",
                                                           "fwhm_arcsec": 0.18, "beta": 2.5}})
    psf_pixel_scale_arcsec: Float | None = Field(
        None, gt=0, lt=MAX_PIXEL_SCALE_ARCSEC,
        description="FITS PSF pixel scale [arcsec/pixel]; null = from its header "
                                "(PIXSCALE, CD/CDELT)")

    @field_validator("filter", mode="before")
    @classmethod
    def _filter(cls, value, info: ValidationInfo):
        if not isinstance(value, str) or not value.strip():
            raise At(f"expected a built-in filter name or a curve file, got {show(value)}"
                     f"{yaml_bool_hint(value)}")
        value = value.strip()
        if looks_like_path(value, FILTER_FILE_SUFFIXES):
            return resolve_path(context_base_dir(info), value)
        try:
            get_filter(value.lower())
        except (ValueError, KeyError, FileNotFoundError) as exc:
            raise At(str(exc)) from None
        return value.lower()

    @field_validator("psf", mode="before")
    @classmethod
    def _psf(cls, value, info: ValidationInfo):
        if isinstance(value, str) and value.strip():
            return resolve_path(context_base_dir(info), value.strip())
        if isinstance(value, Mapping):
            return validate_nested(PsfProfile, value, info).spec()
        raise At(f"expected a FITS path or a mapping {{profile, fwhm_arcsec, ...}}, "
                 f"got {show(value)}{yaml_bool_hint(value)}")


def read_fields_file(path) -> tuple[str, ...]:
    """Field names from a list file: the first token of each non-blank, non-comment line.

    Parameters
    ----------
    path : path-like
        Text file (GLACiAR's ``list_of_fields`` format), UTF-8.

    Returns
    -------
    tuple of str
    """
    fields = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            fields.append(line.split()[0])
    return tuple(fields)


def _template_names(template: str) -> set[str]:
    return {name for _, name, _, _ in string.Formatter().parse(template) if name}


def _check_template(value, what: str):
    if not isinstance(value, str) or not value.strip():
        raise At(f"expected a file-name template such as '{{field}}_{{band}}_{what}.fits', "
                 f"got {show(value)}{yaml_bool_hint(value)}")
    try:
        parts = list(string.Formatter().parse(value))
    except ValueError as exc:
        raise At(f"invalid file-name template {value!r}: {exc}") from None
    for _, name, spec, conv in parts:
        if name is not None and (name not in ("field", "band") or spec or conv):
            raise At(f"template {value!r}: only the placeholders {{field}} and {{band}} are "
                     f"allowed, found {{{name}}}")
    return value.strip()


class DetectionImageConfig(Section):
    """A coadded detection image instead of the detection band's own image."""

    coadd: tuple[str, ...] = Field(description="bands to stack (names of survey.bands)",
                                   json_schema_extra={"example": ["f125w", "f140w", "f160w"]})
    method: Choice("ivw", "chi2") = Field(
        "ivw", description="ivw: inverse-variance weighted mean; chi2: Szalay et al. (1999) "
                           "chi-square image, Gaussianised so DETECT_THRESH stays in sigma")

    @field_validator("coadd", mode="before")
    @classmethod
    def _bands(cls, value):
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, (list, tuple)) or not value:
            raise At(f"expected a non-empty list of band names, got {show(value)}")
        return value


class SurveyConfig(Section):
    """Fields, bands and where their images are."""

    fields: tuple[str, ...] = Field(description="field names (quote them in YAML); or fields_file",
                                    json_schema_extra={"example": ["field1"]})
    fields_file: str | None = Field(None, description="a list file instead of fields: the first "
                                                      "token of each non-comment line")
    image_dir: Path = Field(Path("."), description="directory holding the images",
                            json_schema_extra={"example": "images"})
    science: str = Field(description="science image name inside image_dir ({field}, {band} are "
                                     "filled in)",
                         json_schema_extra={"example": "{field}_{band}_drz.fits"})
    noise: str | None = Field(None, description="weight or RMS map name; null = no noise map "
                                                "(RMS from the image)",
                              json_schema_extra={"example": "{field}_{band}_wht.fits"})
    noise_type: Choice("weight", "rms") = Field("weight", description="weight (inverse variance) "
                                                                      "| rms")
    pixel_scale_arcsec: Float | None = Field(None, gt=0, lt=MAX_PIXEL_SCALE_ARCSEC,
                                             description="[arcsec/pixel]; null = from the "
                                                         "detection image's WCS")
    mask: str | None = Field(None, description="mask per field inside image_dir ({field} is "
                                               "filled in): a FITS image (non-zero = masked) or "
                                               "a DS9 region file (.reg; inside = masked, image "
                                               "or sky coordinates); null = none")
    coverage: Choice("selection_bands", "detection_band", "all_bands") = Field(
        "selection_bands", description="where sources are placed and area is counted: where "
        "the detection band and every band the selection reads have data (selection_bands), "
        "or every band (all_bands), or the detection band only (detection_band: sources on "
        "holes of other bands are kept and flagged)")
    detection_image: DetectionImageConfig | None = Field(
        None, description="detect on a stack of bands ({coadd: [bands], method: ivw | chi2}); "
                          "null = on the detection band; S/N, magnitudes and depth stay those "
                          "of detection_band")
    negative_weights: Choice("error", "mask") = Field(
        "error", description="weight maps with negative pixels: error, or mask those pixels")
    lens: LensConfig | None = Field(
        None, description="a foreground lens: {z_lens, models: [{name, kappa, gamma1, gamma2} | "
        "{name, alpha_x, alpha_y}] or analytic: {sis, shear}} (docs/lensing.md); null = none")
    detection_band: str = Field(description="band in which sources are detected (default: the "
                                            "only band)", json_schema_extra={"example": "f160w"})
    bands: tuple[BandConfig, ...] = Field(
        description="ordered mapping band name -> settings (names become column suffixes)",
        json_schema_extra={"example": {
            "f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.946,
                      "psf": {"profile": "moffat", "fwhm_arcsec": 0.18}},
            "f125w": {"filter": "wfc3_ir_f125w", "zeropoint": 26.230,
                      "psf": {"profile": "moffat", "fwhm_arcsec": 0.17}},
            "f098m": {"filter": "wfc3_ir_f098m", "zeropoint": 25.667,
                      "psf": {"profile": "moffat", "fwhm_arcsec": 0.16}},
            "f606w": {"filter": "wfc3_uvis_f606w", "zeropoint": 26.080,
                      "psf": {"profile": "moffat", "fwhm_arcsec": 0.10}}}})

    @classmethod
    def _prepare(cls, data: dict, info: ValidationInfo) -> dict:
        base = context_base_dir(info)
        if "fields" in data and "fields_file" in data:
            raise At("give either fields or fields_file, not both", "fields")
        if "fields_file" in data:
            ff = data["fields_file"]
            if not isinstance(ff, str) or not ff.strip():
                raise At(f"expected a file name, got {show(ff)}{yaml_bool_hint(ff)}", "fields_file")
            path = resolve_path(base, ff.strip())
            if not Path(path).is_file():
                raise At(f"file not found: {path}", "fields_file")
            try:
                fields = read_fields_file(path)
            except UnicodeDecodeError as exc:
                raise At(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})",
                         "fields_file") from None
            if not fields:
                raise At(f"no field names in {path}", "fields_file")
            # The fields are the resolved truth; the list file is not kept (a run's stored
            # config lists them, so it does not depend on the file staying unchanged).
            del data["fields_file"]
        elif "fields" in data:
            raw = data["fields"]
            raw = [raw] if isinstance(raw, str) else raw
            if not isinstance(raw, (list, tuple)) or not raw:
                raise At(f"expected a non-empty list of field names, got {show(raw)}", "fields")
            fields = []
            for i, f in enumerate(raw):
                if not isinstance(f, str) or not f.strip():
                    # YAML reads 0123 as an octal integer: ask for quotes rather than guess.
                    raise At(f"expected a field name string, got {show(f)} (quote names in YAML)",
                             "fields", i)
                fields.append(f.strip())
        else:
            raise At("missing required key (a list of field names, or fields_file: a list "
                     "file)", "fields")
        dup = sorted({f for f in fields if fields.count(f) > 1})
        if dup:
            raise At(f"duplicate field name(s): {', '.join(dup)}", "fields")
        data["fields"] = tuple(fields)

        image_dir = data.get("image_dir", ".")
        if not isinstance(image_dir, (str, os.PathLike)) or not str(image_dir).strip():
            raise At(f"expected a directory name, got {show(image_dir)}"
                     f"{yaml_bool_hint(image_dir)}", "image_dir")
        data["image_dir"] = Path(resolve_path(base, str(image_dir).strip()))
        if "science" not in data:
            raise At("missing required key (file-name template, e.g. "
                     "'{field}_{band}_drz.fits')", "science")
        data["science"] = _at(_check_template, data["science"], "drz", loc=("science",))
        if "noise" in data:
            data["noise"] = _at(_check_template, data["noise"], "wht", loc=("noise",))
        if "mask" in data:
            data["mask"] = _at(_check_template, data["mask"], "mask", loc=("mask",))
            if "band" in _template_names(data["mask"]):
                raise At(f"template {data['mask']!r}: a mask is per field, {{band}} is not "
                         "allowed", "mask")

        bands_raw = data.get("bands")
        if bands_raw is None:
            raise At("missing required key (mapping band -> settings)", "bands")
        if not isinstance(bands_raw, Mapping) or not bands_raw:
            raise At(f"expected a non-empty mapping band -> settings, got {show(bands_raw)}",
                     "bands")
        bands, lower = [], set()
        for name, bdata in bands_raw.items():
            if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_]+", name):
                raise At("band names must be strings of letters, digits and '_' (they become "
                         "column names)", "bands", str(name))
            if name.lower() in lower:
                raise At("duplicate band name (case-insensitive)", "bands", name)
            lower.add(name.lower())
            if isinstance(bdata, Mapping) and "name" in bdata:
                raise At("unknown key 'name' (the band's name is its key)", "bands", name, "name")
            bdata = {} if bdata is None else bdata
            if isinstance(bdata, Mapping):
                bdata = {**bdata, "name": name}
            bands.append(validate_nested(BandConfig, bdata, info, "bands", name))
        data["bands"] = tuple(bands)

        names = [b.name for b in bands]
        det = data.get("detection_band")
        if det is None:
            if len(bands) != 1:
                raise At(f"missing required key (one of {', '.join(names)})", "detection_band")
            det = names[0]
        if not isinstance(det, str) or not det.strip():
            raise At(f"expected a band name, got {show(det)}{yaml_bool_hint(det)}",
                     "detection_band")
        match = [n for n in names if n.lower() == det.strip().lower()]
        if not match:
            close = difflib.get_close_matches(det, names, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise At(f"{det!r} is not one of the bands ({', '.join(names)}){hint}",
                     "detection_band")
        data["detection_band"] = match[0]
        if "detection_image" in data:
            di = validate_nested(DetectionImageConfig, data["detection_image"], info, "detection_image")
            lower = {n.lower(): n for n in names}
            canon = []
            for i, band in enumerate(di.coadd):
                if band.lower() not in lower:
                    raise At(f"{band!r} is not one of the bands ({', '.join(names)})",
                             "detection_image", "coadd", i)
                canon.append(lower[band.lower()])
            if len(set(canon)) != len(canon):
                raise At("a band is listed twice", "detection_image", "coadd")
            data["detection_image"] = di.model_copy(update={"coadd": tuple(canon)})

        for key in ("science", "noise", "mask"):
            tmpl = data.get(key)
            if tmpl is None:
                continue
            placeholders = _template_names(tmpl)
            if len(bands) > 1 and "band" not in placeholders and key != "mask":
                raise At(f"template {tmpl!r} has no {{band}} but there are {len(bands)} bands",
                         key)
            if len(fields) > 1 and "field" not in placeholders:
                raise At(f"template {tmpl!r} has no {{field}} but there are {len(fields)} "
                         "fields", key)
        return data

    @property
    def band_names(self) -> tuple[str, ...]:
        """Band names in configuration order."""
        return tuple(b.name for b in self.bands)

    def band(self, name: str) -> BandConfig:
        """The :class:`BandConfig` called ``name`` (KeyError if absent)."""
        for b in self.bands:
            if b.name == name:
                return b
        raise KeyError(f"no band {name!r}; bands are {list(self.band_names)}")


def _at(func, value, *args, loc):
    try:
        return func(value, *args)
    except At as exc:
        raise At(exc.message, *loc, *exc.loc) from None
