"""Every input file a run reads, checked and fingerprinted before anything is written."""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import Config, check_files, config_from_dict, config_to_dict
from .engine.noise import map_type_problem
from .fieldprep import band_psf, detection_params
from .galaxy.filters import get_filter
from .lensmaps import LensMapError, check_field_lens, lens_map_paths
from .rundir import file_fingerprint
from .survey import SAMPLE_PIXELS, Survey, read_array, strided_sample


class InputError(ValueError):
    """An input file of the configuration is unusable; the message names its key and path."""


@dataclass(frozen=True)
class InputFile:
    """One input file of a run, named by the configuration key it comes from."""

    key: str                  #: e.g. ``survey.bands.f160w.psf`` or ``survey.science (field 'a', band 'b')``
    path: Path
    kind: str                 #: science, noise, psf, filter, sex_file, conv or lens
    field: str | None = None  #: the field whose tasks read it (None: every task)
    band: str | None = None


def file_or_none(value, base_dir: Path) -> Path | None:
    """``value`` as an existing file (relative to ``base_dir``), or None (e.g. a built-in name)."""
    if not isinstance(value, str) or not value:
        return None
    p = Path(value).expanduser()
    if not p.is_absolute():
        p = Path(base_dir) / p
    return p.resolve() if p.is_file() else None


def input_files(cfg: Config) -> list[InputFile]:
    """Every input file of ``cfg``: images and noise maps, FITS PSFs, filter curves, .sex, .conv.

    Built-in filters, analytic PSFs and built-in detection kernels are not files
    (their definitions are in the configuration and the code).
    """
    s = cfg.survey
    out = []
    for f in s.fields:
        for b in s.bands:
            for kind, tmpl in (("science", s.science), ("noise", s.noise)):
                if tmpl is not None:
                    out.append(InputFile(f"survey.{kind} (field {f!r}, band {b.name!r})",
                                         Path(s.image_dir) / tmpl.format(field=f, band=b.name),
                                         kind, f, b.name))
    for b in s.bands:
        if isinstance(b.psf, str):
            p = Path(b.psf) if Path(b.psf).is_absolute() else Path(cfg.base_dir) / b.psf
            out.append(InputFile(f"survey.bands.{b.name}.psf", p, "psf", None, b.name))
        fp = file_or_none(b.filter, cfg.base_dir)
        if fp is not None:
            out.append(InputFile(f"survey.bands.{b.name}.filter", fp, "filter", None, b.name))
    for f in s.fields:
        for name, maps in lens_map_paths(cfg, f).items():
            for key, path in maps.items():
                out.append(InputFile(f"survey.lens.models.{name}.{key} (field {f!r})", path,
                                     "lens", f))
    det = config_to_dict(cfg).get("detection") or {}
    for key, kind in (("sex_file", "sex_file"), ("FILTER_NAME", "conv")):
        p = file_or_none(det.get(key), cfg.base_dir)
        if p is not None:
            out.append(InputFile(f"detection.{key}", p, kind))
    return out


def _reason(exc: BaseException, path: Path) -> str:
    """An exception's message without a leading copy of the path."""
    msg = str(exc).strip() or type(exc).__name__
    for prefix in (f"{path}: ", f"{path}:", "PSF file not found: "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    return msg.splitlines()[0]


#: Longest part of a one-line error given to folded foreign-library warnings [characters].
MAX_FOLDED_CHARS = 200


def _folded(caught) -> str:
    """Warnings recorded while a file was checked, as one parenthesised clause ("" if none).

    A foreign library (astropy) warns several times, over several lines, before it
    fails on a damaged file; the refusal stays one line and keeps what they said.
    """
    said = []
    for w in caught:
        text = " ".join(str(w.message).split())
        if text and text not in said:
            said.append(text)
    if not said:
        return ""
    text = "; ".join(said)
    if len(text) > MAX_FOLDED_CHARS:
        text = text[:MAX_FOLDED_CHARS - 3] + "..."
    return f" (warnings while reading it: {text})"


def _check_image(item: InputFile, samples: dict | None = None) -> None:
    """A science or noise image: a readable FITS file with a 2-D image holding finite pixels.

    ``samples``: if given, ``samples[path]`` is set to the image's
    :func:`~glaciar.survey.strided_sample` (the same pixels, taken from the array read
    here: the noise-map check then reads the file no more).
    """
    with warnings.catch_warnings():
        # astropy only warns about a file shorter than its header says; that is an error here.
        warnings.filterwarnings("error", message=".*truncated.*")
        arr = read_array(item.path)
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"expected a non-empty 2-D image, got shape {arr.shape}")
    if not np.isfinite(arr).any():
        raise ValueError("no finite pixel in the image")
    if samples is not None:
        # strided_sample's step; its rows 0, k, 2k, ... and columns 0, k, 2k, ...
        k = max(1, math.ceil(math.sqrt(arr.size / SAMPLE_PIXELS)))
        samples[str(item.path)] = arr if k == 1 else np.array(arr[::k, ::k])


def _check_noise_maps(cfg: Config, items: list[InputFile], fingerprints: dict, cache: dict,
                      fail, errors, samples: dict | None = None) -> None:
    """Each noise map against its science image's pixel scatter
    (:func:`~glaciar.engine.noise.map_type_problem`).

    Not for a relative weight map (WEIGHT_TYPE MAP_WEIGHT: its scale is rescaled to the
    image) nor an unused one (BACKGROUND). A strided sample of <= 2^20 pixels of each
    image; checked once per (noise file version, noise_type, science file version):
    ``cache`` remembers it.  ``samples``: samples already taken (:func:`_check_image`), by path.
    """
    if cfg.detection.weight_type in ("map_weight", "background"):
        return
    science = {(it.field, it.band): it for it in items if it.kind == "science"}
    ntype = cfg.survey.noise_type
    for item in items:
        sci = science.get((item.field, item.band))
        if item.kind != "noise" or sci is None:
            continue
        entry = cache.get(str(item.path.resolve()), {})
        stamp = [ntype, fingerprints[sci.key].get("blake2b")]
        if entry.get("map_type_checked") == stamp:
            continue
        try:
            samples = {} if samples is None else samples
            sci_pixels, map_pixels = (samples[str(p)] if str(p) in samples else strided_sample(p)
                                      for p in (sci.path, item.path))
            # Shapes that differ are refused below, naming both (survey.shape).
            problem = None if sci_pixels.shape != map_pixels.shape else \
                map_type_problem(sci_pixels, map_pixels, ntype)
        except errors as exc:
            raise fail(item, exc) from None
        if problem is not None:
            raise InputError(f"{item.key}: {item.path}: {problem}")
        entry["map_type_checked"] = stamp


def check_inputs(cfg: Config, survey: Survey | None = None, cache: dict | None = None,
                 executor=None) -> dict:
    """Check every input file of ``cfg`` and return its fingerprint.

    Science and noise images must be readable FITS files with a 2-D image that
    has finite pixels (checked once per file version: ``cache`` remembers it by
    path, size and mtime); a noise map must state a pixel sigma within a factor
    :data:`~glaciar.engine.noise.MAP_TYPE_FACTOR` of its image's pixel scatter
    (a weight map declared as RMS, or the reverse, is refused with the fix:
    :func:`_check_noise_maps`); FITS PSFs must be finite with a positive sum and
    a pixel scale (checked at every field's pixel scale); filter curves and
    detection files must parse.  Nothing is written.

    Parameters
    ----------
    cfg : Config
    survey : Survey, optional
    cache : dict, optional
        ``{path: {"size", "mtime_ns", "blake2b", "checked"}}``, updated in place.
    executor : concurrent.futures.Executor, optional
        A process pool: each field's images and noise maps (the costly part: read,
        hashed and sampled) are checked there, one job per field
        (:func:`check_field_files`), while this process checks the other files.  The
        result, the cache, the warnings (their order too) and the error raised are
        those of the serial check: the first unusable file in the same order.

    Returns
    -------
    dict
        ``{key: {"path", "size", "blake2b"}}`` for every :func:`input_files` entry.

    Raises
    ------
    FileNotFoundError
        Missing files (all listed, by key).
    InputError
        The first unusable file: ``"<key>: <path>: <cause>"``.
    """
    check_files(cfg)
    survey = survey or Survey.from_config(cfg)
    cache = {} if cache is None else cache
    items = input_files(cfg)
    jobs = {}
    if executor is not None:
        args = (config_to_dict(cfg), str(cfg.base_dir))
        for f in cfg.survey.fields:
            paths = {str(it.path.resolve()) for it in items if it.field == f}
            jobs[f] = executor.submit(_field_files_job, *args, f,
                                      {p: cache[p] for p in paths if p in cache})
    # This process: the files of no field (PSFs, filters, detection files), then the fields
    # no job checks; field by field, so that no more than one field's samples are held.
    checked = _check_files([it for it in items if it.field is None], cache)
    noise = {}
    for f in cfg.survey.fields:
        if f not in jobs:
            done = check_field_files(cfg, f, cache)
            checked.update(done.items)
            noise[f] = done.noise_error
    for f, job in jobs.items():
        done, entries = job.result()
        checked.update(done.items)
        noise[f] = done.noise_error
        cache.update(entries)
    # In the serial check's order: every file's own check, then the noise maps by field.
    out = {}
    for item in items:
        if item.key not in checked:
            break                       # an earlier file of its group failed: raised below
        result = checked[item.key]
        if result.error is not None:
            raise InputError(result.error)
        for message in result.warnings:
            warnings.warn(f"{item.key}: {item.path}: {message}", stacklevel=2)
        out[item.key] = {"path": str(item.path), **result.fingerprint}
    for f in cfg.survey.fields:
        if noise[f] is not None:
            raise InputError(noise[f])
    _check_shared(cfg, survey)
    return out


@dataclass(frozen=True)
class FileCheck:
    """One input file's own check (:func:`_check_files`): its fingerprint, or the error."""

    fingerprint: dict | None        #: ``{"size", "blake2b"}``
    warnings: tuple = ()            #: what a library said while reading a file that passed
    error: str | None = None        #: the one-line refusal (``InputError``'s message)


@dataclass(frozen=True)
class FieldCheck:
    """:func:`check_field_files`'s result for one field."""

    items: tuple                    #: ``((key, FileCheck), ...)`` in input order, to the first error
    noise_error: str | None         #: the first noise map refused against its image, if any


_ERRORS = (OSError, ValueError, TypeError, KeyError, IndexError, EOFError, UnicodeDecodeError,
           Warning)


def _fail(item: InputFile, exc: BaseException, caught=()) -> str:
    return f"{item.key}: {item.path}: {_reason(exc, item.path)}{_folded(caught)}"


def _check_files(items: list[InputFile], cache: dict, samples: dict | None = None) -> dict:
    """Each file's own check, in order, up to the first that fails: ``{key: FileCheck}``
    (``samples``: :func:`_check_image`'s)."""
    out = {}
    for item in items:
        try:
            fp = file_fingerprint(item.path, cache)
        except OSError as exc:
            out[item.key] = FileCheck(None, (), _fail(item, exc))
            return out
        entry = cache.get(str(item.path.resolve()), {})
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                if item.kind in ("science", "noise") and not entry.get("checked"):
                    _check_image(item, samples)
                elif item.kind == "filter":
                    get_filter(str(item.path))
            except _ERRORS as exc:
                out[item.key] = FileCheck(None, (), _fail(item, exc, caught))
                return out
        if item.kind in ("science", "noise"):
            entry["checked"] = True
        # A check that passes keeps the library's warnings, each said on one line naming the file.
        out[item.key] = FileCheck(fp, tuple(" ".join(str(w.message).split()) for w in caught))
    return out


def _noise_map_error(cfg: Config, items: list[InputFile], checked: dict, cache: dict,
                     samples: dict | None = None) -> str | None:
    """:func:`_check_noise_maps` on files that passed their own check: its refusal, or None."""
    if any(checked.get(it.key) is None or checked[it.key].error is not None for it in items):
        return None                     # a file's own check failed first
    fingerprints = {k: c.fingerprint for k, c in checked.items()}
    try:
        _check_noise_maps(cfg, items, fingerprints, cache, lambda item, exc: InputError(_fail(item, exc)),
                          _ERRORS, samples)
    except InputError as exc:
        return str(exc)
    return None


def check_field_files(cfg: Config, field: str, cache: dict) -> FieldCheck:
    """The checks of :func:`check_inputs` of one field's images and noise maps (its costly
    part: each file read, hashed and sampled); ``cache`` updated in place."""
    items = [it for it in input_files(cfg) if it.field == field]
    samples: dict = {}
    checked = _check_files(items, cache, samples)
    return FieldCheck(tuple(checked.items()), _noise_map_error(cfg, items, checked, cache, samples))


def _field_files_job(cfg_dict: dict, base_dir: str, field: str, cache: dict) -> tuple:
    """:func:`check_field_files` in a pool's worker: ``(FieldCheck, cache entries)``."""
    cfg = config_from_dict(cfg_dict, base_dir)
    return check_field_files(cfg, field, cache), cache


def _check_shared(cfg: Config, survey: Survey) -> None:
    """Shapes agree within each field, pixel scales are known, PSFs resample at every scale,
    the detection settings build."""
    def reissue(key, path, caught):
        for w in caught:
            warnings.warn(f"{key}: {path}: {' '.join(str(w.message).split())}", stacklevel=4)

    errors = _ERRORS
    scales = set()
    for f in cfg.survey.fields:
        survey.shape(f)
        scales.add(survey.pixel_scale_arcsec(f))
    for b in cfg.survey.bands:
        key = f"survey.bands.{b.name}.psf"
        where = Path(b.psf) if isinstance(b.psf, str) else None
        if where is not None and not where.is_absolute():
            where = Path(cfg.base_dir) / where
        for scale in sorted(scales):
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    band_psf(cfg, b, scale)
                except errors as exc:
                    if where is None:
                        raise InputError(f"{key}: {_reason(exc, Path('.'))}"
                                         f"{_folded(caught)}") from None
                    raise InputError(f"{key}: {where}: {_reason(exc, where)}"
                                     f"{_folded(caught)}") from None
            reissue(key, where if where is not None else "(analytic)", caught)
    try:
        detection_params(cfg)
    except errors as exc:
        raise InputError(f"detection: {str(exc).splitlines()[0]}") from None
    _check_lens(cfg, survey)


def _check_lens(cfg: Config, survey: Survey) -> None:
    """Lens maps readable, with a celestial WCS, on one grid per model, covering each field's
    footprint and finite there (:func:`glaciar.lensmaps.check_field_lens`)."""
    if cfg.survey.lens is None:
        return
    if cfg.grid.magnitude_type != "apparent":
        raise InputError("survey.lens: lensed fields need grid.magnitude_type: apparent (the "
                         "grid is in observed, magnified magnitude; docs/lensing.md)")
    for f in cfg.survey.fields:
        try:
            check_field_lens(cfg, survey, f)
        except LensMapError as exc:
            raise InputError(f"survey.lens (field {f!r}): {exc}") from None
