"""GLACiAR's flat ``parameters.yaml`` (Carrasco et al. 2018, appendix) mapped onto the schema.

A GLACiAR user's file runs as it is: :func:`glaciar_to_schema` turns its flat
keys into glaciar's sections, and every choice made on the way (filter
curves, PSFs, the spectrum model, grid labels) is recorded as a warning. The
schema key each GLACiAR key became is remembered, so a later validation error
names the GLACiAR key the user actually wrote.

GLACiAR's inputs are read as GLACiAR's *code* uses them (reference notes,
sections 1, 4 and 7), where the paper says otherwise:

* ``R_eff`` is the half-light radius in *pixels* at z = 6 (the code draws
  Re = 7 R_eff / (1+z) px and has no cosmology), so it becomes
  ``source.r_eff_kpc_z6 = R_eff * size_pix / (arcsec per proper kpc at z = 6)``
  in the source model's cosmology (Planck18); the warning gives r_e in kpc and
  arcsec, and how far glaciar's (1+z)^-1 scaling of the proper size departs
  from GLACiAR's (1+z)^-1 scaling of the angle over the grid's redshifts.
* Images are ``<path_to_images><image_name><field>_<band>.fits`` and
  ``..._rms.fits``, or the same names gzipped (``.fits.gz``), whichever exist.
* ``Files/psf_<band>.fits`` (or ``.fits.gz``) without a pixel scale in its
  header is at ``size_pix`` (GLACiAR placed its stamps without resampling
  anything); a header scale, where there is one, is used instead.
"""
from __future__ import annotations

import difflib
import math
import os
import re
from pathlib import Path
from typing import Mapping

from .common import At, parse_bool, show

__all__ = ["is_glaciar_parameters", "glaciar_to_schema", "GLACIAR_TO_SCHEMA", "TOP_KEYS"]

#: Sections of a glaciar configuration (a GLACiAR file has none of them).
TOP_KEYS = ("survey", "grid", "simulation", "source", "detection", "classification",
            "noise", "selection", "output", "interlopers")


class _Ctx:
    """Warnings and key origins collected while mapping one file."""

    def __init__(self):
        self.origins: dict[str, str] = {}    # schema key path -> GLACiAR key
        self.warnings: list[str] = []

    @staticmethod
    def error(path: str, message: str) -> At:
        return At(message, *([path] if path else []))


def _show(value) -> str:
    return show(value)


def _check_keys(ctx: _Ctx, path: str, data, allowed, hints: Mapping[str, str] | None = None):
    if not isinstance(data, Mapping):
        raise ctx.error(path or "<top level>", f"expected a mapping of keys, got {_show(data)}")
    for key in data:
        if key in allowed:
            continue
        where = f"{path}.{key}" if path else str(key)
        msg = f"unknown key {key!r}"
        if hints and key in hints:
            msg += f" ({hints[key]})"
        else:
            close = difflib.get_close_matches(str(key), [str(a) for a in allowed], n=1, cutoff=0.6)
            if close:
                msg += f"; did you mean {close[0]!r}?"
            else:
                msg += f"; allowed keys: {', '.join(map(str, allowed))}"
        raise ctx.error(where, msg)


def _float(ctx, path, value, *, gt=None, ge=None, le=None, lt=None) -> float:
    # PyYAML (YAML 1.1) reads `1e-3` (no dot) as a string: accept numeric strings.
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ctx.error(path, f"expected a number, got {_show(value)}")
    try:
        x = float(value)
    except ValueError:
        raise ctx.error(path, f"expected a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ctx.error(path, f"expected a finite number, got {value!r}")
    if gt is not None and not x > gt:
        raise ctx.error(path, f"must be > {gt}, got {x:g}")
    if ge is not None and not x >= ge:
        raise ctx.error(path, f"must be >= {ge}, got {x:g}")
    if lt is not None and not x < lt:
        raise ctx.error(path, f"must be < {lt}, got {x:g}")
    if le is not None and not x <= le:
        raise ctx.error(path, f"must be <= {le}, got {x:g}")
    return x


def _int(ctx, path, value, *, ge=None) -> int:
    if isinstance(value, bool):
        raise ctx.error(path, f"expected an integer, got {_show(value)}")
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int):
        raise ctx.error(path, f"expected an integer, got {_show(value)}")
    if ge is not None and value < ge:
        raise ctx.error(path, f"must be >= {ge}, got {value}")
    return value


def _bool(ctx, path, value) -> bool:
    # GLACiAR files use YAML 1.1 words (yes/No), sometimes quoted: the models' one reader.
    parsed = parse_bool(value)
    if parsed is None:
        raise ctx.error(path, f"expected true/false, got {_show(value)}")
    return parsed


def _str(ctx, path, value, *, choices=None) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ctx.error(path, f"expected a non-empty string, got {_show(value)}")
    if choices is not None:
        v = value.strip().lower()
        if v not in choices:
            close = difflib.get_close_matches(v, choices, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ctx.error(path, f"expected one of {', '.join(choices)}, got {value!r}{hint}")
        return v
    return value.strip()


_GLACIAR_KEYS = (
    "n_galaxies", "n_iterations", "mag_bins", "min_mag", "max_mag", "z_bins", "min_z", "max_z",
    "n_bands", "detection_band", "lambda_detection", "bands", "list_of_fields", "R_eff",
    "beta_mean", "beta_sd", "size_pix", "path_to_images", "image_name", "types_galaxies",
    "sersic_indices", "sersic_indexes", "fraction_type_galaxies", "fractions", "ibins", "ebins",
    "zeropoints", "gain_values", "min_sn", "dropouts", "de_Vacouleur")
GLACIAR_TO_SCHEMA = {
    "n_galaxies": "simulation.n_galaxies", "n_iterations": "simulation.n_iterations",
    "mag_bins": "grid.mag", "min_mag": "grid.mag", "max_mag": "grid.mag", "z_bins": "grid.z",
    "min_z": "grid.z", "max_z": "grid.z", "bands": "survey.bands",
    "detection_band": "survey.detection_band", "list_of_fields": "survey.fields_file",
    "R_eff": "source.r_eff_kpc_z6", "beta_mean": "source.beta_mean", "beta_sd": "source.beta_sd",
    "size_pix": "survey.pixel_scale_arcsec", "path_to_images": "survey.image_dir",
    "image_name": "survey.science", "sersic_indices": "source.sersic_indices",
    "fraction_type_galaxies": "source.sersic_fractions", "ibins": "source.position_angle_bins",
    "ebins": "source.ellipticity_bins", "min_sn": "classification.min_sn",
    "dropouts": "selection", "de_Vacouleur": "source.round_de_vaucouleurs"}

# HST-like PSF FWHM of drizzled images [arcsec], for GLACiAR files (which have no PSF key).
_HST_FWHM_ARCSEC = {"f098m": 0.16, "f105w": 0.16, "f110w": 0.17, "f125w": 0.17, "f140w": 0.18,
                    "f160w": 0.18}
_HST_OPTICAL_FWHM_ARCSEC = 0.10
_ACS_ONLY = ("f435w", "f502n", "f550m", "f625w", "f658n", "f660n", "f775w", "f850lp", "f892n")


def is_glaciar_parameters(data) -> bool:
    """True if ``data`` (a parsed YAML mapping) is a GLACiAR ``parameters.yaml``."""
    return isinstance(data, Mapping) and "survey" not in data and \
        bool(set(map(str, data)) & set(_GLACIAR_KEYS))


def _glaciar_hst_name(ctx, b: str) -> str | None:
    m = re.fullmatch(r"f(\d{3})([a-z]+)", b)
    if not m:
        return None
    if 90 <= int(m.group(1)) < 200:
        return f"wfc3_ir_{b}"
    if b == "f606w":
        # BoRG is a WFC3 pure-parallel survey; GLACiAR's own Files/f606w.tab is the
        # WFC3/UVIS curve (it matches sedpy's wfc3_uvis_f606w to 3e-4 of the peak,
        # acs_wfc_f606w only to 0.39) and its zeropoint (26.07) the UVIS one. Only its
        # (never applied) PSF file is ACS.
        ctx.warnings.append("bands: f606w is ambiguous (WFC3/UVIS or ACS/WFC); mapped to "
                            "wfc3_uvis_f606w like GLACiAR's Files/f606w.tab (BoRG is a WFC3 "
                            "survey). Set survey.bands.f606w.filter: acs_wfc_f606w in a "
                            "schema config if your images are ACS.")
        return "wfc3_uvis_f606w"
    if b in _ACS_ONLY:
        return f"acs_wfc_{b}"
    if b in ("f475w", "f555w", "f814w"):
        ctx.warnings.append(f"bands: {b} is ambiguous (WFC3/UVIS or ACS/WFC); mapped to "
                            f"wfc3_uvis_{b}")
    return f"wfc3_uvis_{b}"


def _glaciar_filter(ctx, band: str, base_dir: Path) -> str:
    """Built-in HST filter for a GLACiAR band name, else GLACiAR's Files/<band>.tab."""
    name = _glaciar_hst_name(ctx, band.lower())
    try:
        from ..galaxy.filters import BUILTIN_FILTERS
        shipped = name is not None and BUILTIN_FILTERS.get(name) is not None
    except ImportError:
        shipped = name is not None
    if shipped:
        return name
    tab = base_dir / "Files" / f"{band}.tab"
    if tab.is_file():
        ctx.warnings.append(f"bands: {band}: no built-in curve; using GLACiAR's {tab}")
        return str(tab)
    what = f"the built-in {name!r} curve is not shipped" if name else \
        f"{band!r} is not an HST filter name"
    raise ctx.error("bands", f"band {band!r}: {what} and there is no {tab}; use a schema "
                             f"config with survey.bands.{band}.filter: <curve file>")


def _read_field_names(path: Path) -> list[str]:
    """First token of each non-blank, non-comment line (GLACiAR's list_of_fields); [] if unreadable."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    return [ln.split()[0] for ln in (x.strip() for x in lines) if ln and not ln.startswith("#")]


def _fits_suffix(ctx, what: str, directory: Path, names: list[str]) -> str:
    """``.fits`` or ``.fits.gz``: how the files ``names`` (without suffix) exist in ``directory``.

    GLACiAR's code opened ``.fits`` only; gzipped copies are common and astropy
    reads them as they are.  With no file found (images not there yet) the
    GLACiAR name ``.fits`` is kept, and the run's input check names what is
    missing.
    """
    plain = sum((directory / f"{n}.fits").is_file() for n in names)
    gz = sum((directory / f"{n}.fits.gz").is_file() for n in names)
    suffix = ".fits.gz" if gz > plain else ".fits"
    if plain and gz:
        found = max(plain, gz)
        ctx.warnings.append(f"{what}: {plain} file(s) are .fits and {gz} .fits.gz; glaciar reads "
                            f"one naming, {suffix} ({len(names) - found} file(s) not found with "
                            f"it: gzip or gunzip them alike)")
    elif gz:
        ctx.warnings.append(f"{what}: read gzipped ({directory / names[0]}.fits.gz, ...); "
                            f"GLACiAR's code opened .fits only")
    return suffix


def _existing_fits(base: Path) -> Path | None:
    """``base.fits`` or ``base.fits.gz``, whichever exists (the plain name first)."""
    for suffix in (".fits", ".fits.gz"):
        p = base.parent / (base.name + suffix)
        if p.is_file():
            return p
    return None


def _r_eff_kpc_z6(r_eff_pix: float, pixel_scale: float, z_values) -> tuple[float, str]:
    """GLACiAR's R_eff [pixels at z = 6] as proper kpc at z = 6, and the warning that says so.

    GLACiAR's code gives a source at z a half-light radius of 7 R_eff / (1+z)
    pixels: R_eff is the size in pixels at z = 6, and pixels are ``size_pix``
    arcsec.  glaciar's source model takes proper kpc at z = 6 and converts with
    the cosmology of the source model (its default, Planck18: a GLACiAR file
    has no cosmology key), so r_kpc = R_eff size_pix / (arcsec per kpc at z = 6).
    """
    from ..galaxy.population import SourceModel, kpc_to_arcsec

    cosmology = SourceModel().cosmology
    r_arcsec = r_eff_pix * pixel_scale
    arcsec_per_kpc = float(kpc_to_arcsec(1.0, 6.0, cosmology))
    r_kpc = r_arcsec / arcsec_per_kpc
    note = (f"R_eff: {r_eff_pix:g} is GLACiAR's half-light radius in pixels at z = 6 (its code "
            f"draws Re = 7 R_eff/(1+z) px, no cosmology; the paper's 'kpc' is not what it does): "
            f"at size_pix = {pixel_scale:.4g}\"/px, r_e = {r_arcsec:.4g}\" = {r_kpc:.4g} proper "
            f"kpc at z = 6 ({cosmology}), used as source.r_eff_kpc_z6")
    z = [float(v) for v in z_values if float(v) > 0]
    if z:
        # glaciar scales the proper size as (1+z)^-1, GLACiAR the angle: they differ by the
        # ratio of the angular scales, arcsec/kpc(z) / arcsec/kpc(6).
        lo, hi = min(z), max(z)
        ratio = [float(kpc_to_arcsec(1.0, v, cosmology)) / arcsec_per_kpc for v in (lo, hi)]
        span = f"z = {lo:g}" if lo == hi else f"z = {lo:g}-{hi:g}"
        rr = f"{ratio[0]:.3f}" if lo == hi else f"{ratio[0]:.3f}-{ratio[1]:.3f}"
        note += (f"; glaciar scales the proper size as (1+z)^-1, GLACiAR the angle, so at {span} "
                 f"r_e is {rr} x GLACiAR's")
        # The proper-size power law closest to GLACiAR's angles on the grid (least squares in
        # log r): r_kpc(z)/r_kpc(6) = (7/(1+z)) a(6)/a(z) ~ ((1+z)/7)^s.
        x = [math.log((1 + v) / 7.0) for v in z]
        y = [math.log(7.0 / (1 + v) * arcsec_per_kpc / float(kpc_to_arcsec(1.0, v, cosmology)))
             for v in z]
        if any(abs(xi) > 1e-9 for xi in x):
            slope = sum(a * b for a, b in zip(x, y)) / sum(a * a for a in x)
            worst = max(abs(math.exp(slope * a - b) - 1) for a, b in zip(x, y))
            note += (f" (source.size_evolution: {slope:.2f} in a schema config follows them to "
                     f"{100 * worst:.0f} %)")
    return r_kpc, note


def glaciar_to_schema(data: Mapping, base_dir: Path) -> tuple[dict, dict[str, str], list[str]]:
    """Map a GLACiAR ``parameters.yaml`` onto the schema.

    Returns
    -------
    data : dict
        Schema sections.
    origins : dict
        Schema key path -> the GLACiAR key it came from.
    warnings : list of str
        The choices made in the mapping.

    Raises
    ------
    At
        An invalid GLACiAR key (its location is the GLACiAR key).
    """
    ctx = _Ctx()
    base_dir = Path(base_dir)
    hints = {k: f"not a GLACiAR key; GLACiAR files cannot be mixed with the `{k}:` section"
             for k in TOP_KEYS}
    _check_keys(ctx, "", data, _GLACIAR_KEYS, hints)
    ctx.origins.update({v: k for k, v in GLACIAR_TO_SCHEMA.items()})
    warn = ctx.warnings.append
    missing = object()

    def get(key, default=missing):
        # GLACiAR: a key present with an empty value takes the default.
        value = data.get(key)
        if value is None:
            if default is missing:
                raise ctx.error(key, "missing required GLACiAR key")
            return default
        return value

    bands = get("bands")
    if isinstance(bands, str):
        bands = [bands]
    if not isinstance(bands, list) or not all(isinstance(b, str) for b in bands):
        raise ctx.error("bands", f"expected a list of band names, got {_show(bands)}")
    nb = len(bands)
    n_bands = _int(ctx, "n_bands", get("n_bands", nb), ge=1)
    if n_bands != nb:
        raise ctx.error("n_bands", f"is {n_bands} but bands lists {nb} band(s)")
    det = _str(ctx, "detection_band", get("detection_band"))
    if det not in bands:
        raise ctx.error("detection_band", f"{det!r} is not in bands ({', '.join(bands)})")

    zps = data.get("zeropoints")
    if zps is None or not isinstance(zps, list) or len(zps) < nb:
        warn("zeropoints: missing or shorter than bands; GLACiAR's default 25.0 is used for "
             "every band")
        zps = [25.0] * nb
    gains = data.get("gain_values")
    if gains is not None and (not isinstance(gains, list) or len(gains) < nb):
        raise ctx.error("gain_values", f"expected a list of {nb} gains (one per band), "
                                       f"got {_show(gains)}")

    # Science: <path_to_images><image_name><field>_<band>.fits (string concatenation),
    # or the same name gzipped.
    prefix = _str(ctx, "path_to_images", get("path_to_images")) + \
        _str(ctx, "image_name", get("image_name"))
    image_dir, raw_stem = os.path.split(prefix)
    stem = raw_stem.replace("{", "{{").replace("}", "}}")
    img_dir = base_dir / (image_dir or ".")          # relative to the file, as the schema's
    fields_file = _str(ctx, "list_of_fields", get("list_of_fields"))
    fields = _read_field_names(base_dir / fields_file)
    sci_suffix = _fits_suffix(ctx, "path_to_images", img_dir,
                              [f"{raw_stem}{f}_{b}" for f in fields for b in bands])
    rms_suffix = _fits_suffix(ctx, "path_to_images (_rms maps)", img_dir,
                              [f"{raw_stem}{f}_{b}_rms" for f in fields for b in bands])

    # size_pix: the images' pixel scale [arcsec/px], the unit of R_eff and of header-less PSFs.
    size_pix = data.get("size_pix")
    if size_pix is not None:
        pixel_scale = _float(ctx, "size_pix", size_pix, gt=0)
    else:
        # GLACiAR's code defaults to 0.08; the detection image's own header is better.
        from ..galaxy.psf import fits_pixel_scale
        pixel_scale = None
        det_image = img_dir / f"{raw_stem}{fields[0]}_{det}{sci_suffix}" if fields else None
        try:
            pixel_scale = fits_pixel_scale(det_image) if det_image is not None else None
        except (OSError, ValueError):
            pass
        if pixel_scale is not None:
            warn(f"size_pix: missing; {pixel_scale:.4g}\"/px from {det_image.name}'s header is "
                 f"used for R_eff and PSFs")
            size_pix = None        # the survey reads the same scale from the WCS
        else:
            pixel_scale = size_pix = 0.08
            warn("size_pix: missing and no detection image header to read; GLACiAR's default "
                 "0.08\"/px is used (pixel scale, R_eff, PSFs)")

    band_cfg = {}
    for i, b in enumerate(bands):
        psf_file = _existing_fits(base_dir / "Files" / f"psf_{b}")
        psf_scale = None
        if psf_file is not None:
            psf = str(psf_file)
            from ..galaxy.psf import fits_pixel_scale
            try:
                header_scale, readable = fits_pixel_scale(psf_file), True
            except (OSError, ValueError):
                header_scale, readable = None, False      # the run's input check reports it
            if header_scale is not None:
                how = f"resampled from its header pixel scale {header_scale:.4g}\"/px"
            elif readable:
                # GLACiAR convolved (and discarded) its PSFs at the image grid: a PSF without a
                # scale is taken at size_pix rather than refused.
                psf_scale = pixel_scale
                ctx.origins[f"survey.bands.{b}.psf_pixel_scale_arcsec"] = "size_pix"
                how = (f"no pixel scale in its header, so taken at size_pix = {pixel_scale:.4g}\"/px "
                       f"(GLACiAR's shipped Tiny Tim PSFs are 0.13\"/px IR, 0.0495\"/px UVIS: "
                       f"if yours are, set survey.bands.{b}.psf_pixel_scale_arcsec in a schema "
                       f"config)")
            else:
                how = "not readable as FITS"
            warn(f"bands: {b}: using the PSF file {psf_file} (GLACiAR computed but never "
                 f"applied its PSF convolution; glaciar applies it): {how}")
        else:
            fwhm = _HST_FWHM_ARCSEC.get(b.lower(), _HST_OPTICAL_FWHM_ARCSEC)
            psf = {"profile": "moffat", "fwhm_arcsec": fwhm, "beta": 2.5}
            warn(f"bands: {b}: parameters.yaml has no PSF; using an analytic Moffat PSF with "
                 f"HST-like FWHM {fwhm}\" (set survey.bands.{b}.psf in a schema config)")
        band_cfg[b] = {"filter": _glaciar_filter(ctx, b, base_dir), "zeropoint": zps[i],
                       "gain": None if gains is None else gains[i], "psf": psf}
        if psf_scale is not None:
            band_cfg[b]["psf_pixel_scale_arcsec"] = psf_scale
        ctx.origins[f"survey.bands.{b}.zeropoint"] = f"zeropoints[{i}]"
        ctx.origins[f"survey.bands.{b}.gain"] = f"gain_values[{i}]"
    if gains is None:
        warn("gain_values: missing; no source Poisson noise is added")

    survey = {"fields_file": fields_file,
              "image_dir": image_dir or ".",
              "science": stem + "{field}_{band}" + sci_suffix,
              "noise": stem + "{field}_{band}_rms" + rms_suffix,
              "noise_type": "rms",
              "pixel_scale_arcsec": size_pix if size_pix is None else pixel_scale,
              "detection_band": det,
              "bands": band_cfg}

    def centres(kmin, kmax, kbins, dmin, dmax, dbins):
        lo = _float(ctx, kmin, get(kmin, dmin))
        hi = _float(ctx, kmax, get(kmax, dmax))
        n = _int(ctx, kbins, get(kbins, dbins), ge=1)
        if lo > hi:
            raise ctx.error(kmin, f"{kmin} ({lo:g}) > {kmax} ({hi:g})")
        if n == 1:
            return {"values": [lo]}
        step = (hi - lo) / (n - 1)
        if abs(step - 0.2) > 1e-9:
            warn(f"{kbins}: GLACiAR simulates {kmin} + 0.2k but labels its tables "
                 f"{kmin} + k({kmax}-{kmin})/({kbins}-1) (step {step:.4g}); glaciar simulates "
                 f"the labelled values")
        return {"values": [round(lo + k * step, 10) for k in range(n)]}

    grid = {"z": centres("min_z", "max_z", "z_bins", 9.0, 11.9, 15),
            "mag": centres("min_mag", "max_mag", "mag_bins", 24.1, 27.9, 20),
            "magnitude_type": "apparent"}
    simulation = {"n_galaxies": get("n_galaxies", 100), "n_iterations": get("n_iterations", 100)}

    indices = data.get("sersic_indices", data.get("sersic_indexes"))
    fractions = data.get("fraction_type_galaxies", data.get("fractions"))
    indices = [1.0, 4.0] if indices is None else indices
    fractions = [0.5, 0.5] if fractions is None else fractions
    types = data.get("types_galaxies")
    if types is not None and isinstance(indices, list) and _int(ctx, "types_galaxies", types,
                                                                 ge=1) != len(indices):
        raise ctx.error("types_galaxies", f"is {types} but sersic_indices lists "
                                          f"{len(indices)} value(s)")
    ctx.origins["source.sersic_fractions"] = "fraction_type_galaxies" \
        if "fraction_type_galaxies" in data else "fractions"
    r_eff_pix = _float(ctx, "R_eff", get("R_eff", 1.075), gt=0)
    r_eff, r_eff_note = _r_eff_kpc_z6(r_eff_pix, pixel_scale, grid["z"]["values"])
    warn(r_eff_note)
    ibins = _int(ctx, "ibins", get("ibins", 1), ge=1)
    ebins = _int(ctx, "ebins", get("ebins", 1), ge=1)
    if ibins > 1:
        warn(f"ibins: {ibins} position angles spread over 0-180 deg (GLACiAR: k*90/ibins deg, "
             f"0-90 deg)")
    if ebins > 1:
        warn(f"ebins: ellipticities e = k/{ebins}, k = 0..{ebins - 1}, including round "
             f"(GLACiAR's code never drew k = 0)")
    source = {"r_eff_kpc_z6": r_eff, "beta_mean": get("beta_mean", -2.2),
              "beta_sd": get("beta_sd", 0.4), "sersic_indices": indices,
              "sersic_fractions": fractions, "position_angle_bins": ibins,
              "ellipticity_bins": ebins,
              "round_de_vaucouleurs": _bool(ctx, "de_Vacouleur", get("de_Vacouleur", False)),
              "beta_per": "iteration", "igm": "sharp"}
    warn("source: beta_per = iteration and igm = sharp reproduce the paper's spectrum model "
         "(one beta per iteration, zero flux below rest 1216 A)")

    sex = base_dir / "SExtractor_files" / "parameters.sex"
    if sex.is_file():
        detection = {"sex_file": str(sex)}
    else:
        # GLACiAR's SExtractor template (SExtractor_files/parameters.sex).
        detection = {"DETECT_THRESH": 0.7, "DETECT_MINAREA": 9, "FILTER": True,
                     "FILTER_NAME": "gauss_2.0_5x5", "DEBLEND_NTHRESH": 32,
                     "DEBLEND_MINCONT": 0.005, "CLEAN": True, "CLEAN_PARAM": 1.0,
                     "BACK_SIZE": 64, "BACK_FILTERSIZE": 3,
                     "PHOT_APERTURES": [2.0, 4.0, 6.0, 8.0, 10.0],
                     "PHOT_AUTOPARAMS": [1.5, 3.5]}
    min_sn = _float(ctx, "min_sn", get("min_sn", 8.0), ge=0)

    selection: list[str] = []
    if _bool(ctx, "dropouts", get("dropouts", False)):
        if nb < 4:
            raise ctx.error("dropouts", f"the J-dropout selection needs 4 bands ordered "
                                        f"[H, Y, J, V] as in GLACiAR, got {nb}")
        h, y, j, v = (b.lower() for b in bands[:4])
        selection = [f"sn_{h} >= {min_sn:g}", f"sn_{v} < 1.5", f"sn_{y} < 1.5",
                     f"maglim_{j} - mag_{h} > 1.5"]
        if (h, y, j, v) != ("f160w", "f098m", "f125w", "f606w"):
            warn(f"dropouts: GLACiAR's band order is [H, Y, J, V]; the J-dropout cuts use "
                 f"H={h}, Y={y}, J={j}, V={v}")
    return {"survey": survey, "grid": grid, "simulation": simulation, "source": source,
            "detection": detection, "classification": {"min_sn": min_sn},
            "selection": selection}, ctx.origins, ctx.warnings


