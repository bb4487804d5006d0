"""Plan tasks, execute them on any executor, write results, resume.

This is the edge of the package: it owns I/O, parallelism and progress bars.
The science happens in :func:`glaciar.engine.task.run_task`, a pure function
of a prepared :class:`FieldContext` and a :class:`~glaciar.engine.task.TaskSpec`.
"""
from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import hashlib
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from .version import __version__
from . import constants as C
from .config import Config, check_files, config_from_dict, config_hash, config_to_dict
from .engine.detect import (DetectionParams, background_model, builtin_filter, read_conv_file,
                            release_mapped, sanitize)
from .engine.measure import reference_extraction
from .engine.blocks import row_blocks
from .engine.classify import ClassificationParams
from .engine.coadd import coadd
from .engine import fieldcache
from .engine.context import R_EFF_LOG_STEP, FieldContext
from .engine.depth import depth_area_histogram, local_depth_map
from .engine.noise import (MAX_RISE_EXPONENT, CorrelatedNoise, background_excess, empty_aperture_scatter,
                           empty_sky, rise_exponent, source_margin, weight_rescale_factor)
from .engine.selection import compile_selection
from .engine.positions import placement_capacity
from .engine.task import TaskSpec, draw_task_sources, field_key, run_task
from .galaxy import population
from .galaxy.filters import get_filter
from .galaxy.psf import measure_fwhm, prepare_psf
from .galaxy.templates import TemplateCache
from .store import (StoreWarning, COMPACT_EVERY, compact, field_file_prefix, finished_task_names,
                    task_filename, task_key, verified_task_names, write_task_table)
from .rundir import (RunLock, StoreMismatchError, atomic_write_text, file_fingerprint,
                     manifest_text, read_manifest, store_format, write_manifest)
from .paths import check_run_tree, disk_full, run_subdir
from .survey import Survey, clear_cache as clear_survey_cache

__all__ = ["FieldContext", "band_pixels", "build_field_context", "open_field_context",
           "save_field_context", "field_depth", "plan_tasks", "simulate",
           "prepare_run_dir", "input_files", "check_inputs", "store_settings", "InputError",
           "R_EFF_LOG_STEP"]

def _resolve_filter(spec: str, base_dir: Path):
    p = Path(spec)
    if not p.is_absolute():
        p = base_dir / p
    return get_filter(str(p)) if p.is_file() else get_filter(spec)


def band_pixels(survey: Survey, field: str, band: str, footprint: np.ndarray,
                params: DetectionParams, weight_type: str | None = None, background: dict | None = None
                ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Background-subtracted image and noise map of one band of a field.

    Parameters
    ----------
    survey : Survey
    field, band : str
    footprint : ndarray of bool
        Where the detection band has valid data (:meth:`Survey.footprint`).
    params : DetectionParams
        Background mesh settings.
    weight_type : {None, "map_weight", "map_rms", "background"}
        SExtractor's WEIGHT_TYPE (config ``detection.WEIGHT_TYPE``): None or
        ``map_rms`` use the noise map as absolute; ``map_weight`` rescales it
        by one factor to the pixel noise measured on the image
        (:func:`glaciar.engine.noise.weight_rescale_factor`); ``background``
        ignores it for the noise (it still marks pixels without data).
    background : dict, optional
        If given, ``background[band]`` is set to the subtracted sep background
        map (float32, image units; SATUR_LEVEL compares pixels with it added back).

    Returns
    -------
    base : ndarray, float32
        Science image minus the sep background [image units]; 0 where not valid.
    rms : ndarray, float32
        Per-pixel noise RMS [image units] used for detection and errors; inf
        where not valid.
    rms_from_background : bool
        True when ``rms`` is sep's background RMS (no noise map, or BACKGROUND).
    """
    # New arrays read for this call (not the survey's cached ones): worked on in place, so
    # the band costs its image, its noise map and the masks, with no full-frame copies.
    img = survey.science(field, band, cache=False)
    noise = survey.rms(field, band, cache=False)
    # nodata = ~(footprint & finite image & finite, positive noise), by blocks of rows.
    nodata = np.empty(img.shape, dtype=bool)
    for y0, y1, _, _ in row_blocks(img.shape, ROW_BLOCK_PIXELS):
        ok = np.asarray(footprint[y0:y1], dtype=bool) & np.isfinite(img[y0:y1])
        if noise is not None:
            nz = noise[y0:y1]
            ok &= np.isfinite(nz) & (nz > 0)
        np.logical_not(ok, out=nodata[y0:y1])
        release_mapped(footprint)       # a spilled footprint's pages, read once
    in_place = img.dtype == np.float32
    if in_place:
        # sanitize(img, None, nodata) on img itself: nodata holds every non-finite pixel.
        img[nodata] = 0.0
        data = img
    else:
        data = sanitize(img, None, nodata)[0]
    bkg = background_model(data, nodata, params)
    from_background = noise is None or weight_type == "background"
    if from_background:
        r = bkg.rms(dtype=np.float32)
    elif weight_type == "map_weight":
        r = noise * weight_rescale_factor(bkg.rms(dtype=np.float32), noise, ~nodata)
    else:
        r = noise
    del noise
    r = np.asarray(r).astype(np.float32, copy=False)
    r[nodata] = np.float32(np.inf)          # = np.where(valid, r, inf), in place
    back = None
    if background is not None or not in_place:
        back = bkg.back(dtype=np.float32)
    if in_place:
        # data holds img where valid: the same float32 differences as img - background.
        if back is None:
            bkg.subfrom(data)
        else:
            np.subtract(data, back, out=data)
        base = data
    else:
        base = np.subtract(img, back)
    del img, data, bkg
    base[nodata] = 0.0
    base = base.astype(np.float32, copy=False)
    if background is not None:
        background[band] = back
    return base, r, from_background


def field_depth(rms: np.ndarray, zeropoint: float, psf: np.ndarray) -> tuple[np.ndarray, float]:
    """Local depth map of a field from its detection band's noise and PSF.

    Parameters
    ----------
    rms : ndarray
        Detection-band RMS map [image units], inf where there are no data (:func:`band_pixels`).
    zeropoint : float
        Detection-band AB zeropoint.
    psf : ndarray
        Detection PSF resampled to the image pixels.

    Returns
    -------
    depth : ndarray, float32
        :data:`~glaciar.constants.DEPTH_NSIGMA`-sigma limit [AB mag] in a circle of
        radius :data:`~glaciar.constants.DEPTH_APERTURE_RADIUS_FWHM` x FWHM; NaN off the footprint.
    radius_pix : float
        That aperture radius [image pixels].
    """
    radius_pix = C.DEPTH_APERTURE_RADIUS_FWHM * measure_fwhm(psf, 1.0)
    # valid=None: the footprint is where the rms is finite and > 0, taken tile by tile.
    return local_depth_map(rms, None, zeropoint, radius_pix, nsigma=C.DEPTH_NSIGMA), radius_pix


def _detection_params(cfg: Config) -> DetectionParams:
    """The engine's detection settings from the validated ``detection:`` section.

    The config has merged any ``.sex`` file and made a ``.conv`` FILTER_NAME absolute.
    """
    d = cfg.detection
    if not d.filter:
        kernel, name = None, "none"
    elif os.path.isabs(d.filter_name):
        kernel, name = read_conv_file(d.filter_name), d.filter_name
    else:
        kernel, name = builtin_filter(d.filter_name), d.filter_name
    return DetectionParams(
        detect_thresh=d.detect_thresh, detect_minarea=d.detect_minarea, filter_kernel=kernel,
        filter_type=d.filter_type, deblend_nthresh=d.deblend_nthresh,
        deblend_mincont=d.deblend_mincont, clean=d.clean, clean_param=d.clean_param,
        clean_style=d.clean_style, threshold_rms=d.threshold_rms, backend=d.backend,
        back_size=d.back_size, back_filtersize=d.back_filtersize,
        phot_apertures=d.phot_apertures, phot_autoparams=d.phot_autoparams, filter_name=name,
        backphoto_type=d.backphoto_type, backphoto_thick=d.backphoto_thick, mask_type=d.mask_type,
        satur_level=d.satur_level)


def _band_psf(cfg: Config, band, pixscale: float) -> np.ndarray:
    if band.psf is None:
        raise ValueError(f"survey.bands.{band.name}.psf: a PSF (FITS path or analytic profile) is required")
    return prepare_psf(band.psf, pixscale, base_dir=cfg.base_dir,
                       psf_pixel_scale_arcsec=band.psf_pixel_scale_arcsec)


#: Pixels around every detected original source left out of the empty apertures.
_EMPTY_SKY_MARGIN_PIX = 3


def correlated_noise(cfg: Config, field: str, band: str, base: np.ndarray, rms: np.ndarray,
                     segmap: np.ndarray, sky: dict | None = None,
                     release=None) -> CorrelatedNoise:
    """The correlated-noise model of one band of a field, from empty apertures.

    Empty sky: pixels with data, more than a few pixels from every source the
    detection band finds in the original image. Aperture positions come from a
    generator keyed by the field and band names only (not the run's seed): the
    model is a measurement of the image, the same in every run and worker.

    ``sky``: an empty dict shared by the calls for the bands of one field (same
    ``segmap``); it keeps the dilated source mask and the last usable mask with its
    candidate aperture centres, so bands with the same usable pixels pay for one
    distance transform. Every full-frame step is made by row tiles (the dilation,
    the usable mask, the distance transform); the distance map itself is never
    kept, only the centres each aperture radius may take (:func:`~glaciar.engine.noise.empty_sky`).
    ``release``: called as ``segmap`` and ``rms`` are read through (a caller with
    memory-mapped arrays drops their resident pages there; the apertures read few).
    """
    release = release or (lambda: None)
    sky = {} if sky is None else sky
    if "sources" not in sky:
        sky["sources"] = source_margin(segmap, _EMPTY_SKY_MARGIN_PIX)
        release()
    sources = sky["sources"]
    usable = np.empty(sources.shape, dtype=bool)
    same = "usable" in sky
    for y0, y1, _, _ in row_blocks(usable.shape, ROW_BLOCK_PIXELS):
        np.isfinite(rms[y0:y1], out=usable[y0:y1])
        usable[y0:y1] &= ~sources[y0:y1]
        same = same and np.array_equal(sky["usable"][y0:y1], usable[y0:y1])
        release()
    radii = cfg.noise.empty_aperture_radii_pix
    if not same:
        sky.pop("usable", None), sky.pop("centres", None)
        # The centres beyond r + 1 of every radius r: what the apertures read of the distance map.
        sky["usable"], sky["centres"] = usable, empty_sky(usable, [float(r) + 1.0 for r in radii])
    else:
        usable = sky["usable"]
    seq = np.random.SeedSequence([field_key(field), field_key(band)])
    # The same apertures are also summed about their own local backgrounds: a background
    # mesh too coarse for the image (a large galaxy in a small cutout) leaves residuals
    # that the sums about the mesh would read as correlated noise.
    npix, ratio, n, local = empty_aperture_scatter(base, rms, usable, radii,
                                                   cfg.noise.n_empty_apertures,
                                                   np.random.default_rng(seq), sky=sky["centres"],
                                                   local=True)
    if len(npix) < 2:
        return CorrelatedNoise()        # too little empty sky to say: no correction
    model = CorrelatedNoise.fit(npix, ratio, n)
    excess = background_excess(ratio, local, n, cfg.noise.identity_tolerance)
    if excess.any():
        # The local-background scatter at the areas where the mesh's is in excess.
        model = dataclasses.replace(CorrelatedNoise.fit(npix, np.where(excess, local, ratio), n),
                                    mesh_ratio=model.ratio)
    if cfg.noise.correlated != "off":
        rise = rise_exponent(model.npix, model.ratio)
        if rise > MAX_RISE_EXPONENT and not model.is_identity(cfg.noise.identity_tolerance):
            raise ValueError(
                f"field {field!r}, band {band!r}: the empty-aperture noise ratio r(N) = "
                f"{model.ratio[-1]:.2f} at N = {model.npix[-1]:.0f} pixels rises like N^{rise:.2f}, "
                "as a background varying across the apertures does (e.g. a large galaxy's "
                "faint wings), not like correlated noise (which levels off); mask that region "
                f"(survey.mask), set a smaller detection.BACK_SIZE (now {cfg.detection.back_size}) "
                "or set noise.correlated: 'off'")
    return model


def noise_warning(field: str, band: str, model: CorrelatedNoise, back_size) -> str | None:
    """The one-line warning for a model measured about local backgrounds (at the area where
    the mesh's scatter exceeded it most), or None."""
    if not model.mesh_ratio:
        return None
    k = int(np.argmax(np.asarray(model.mesh_ratio) / np.asarray(model.ratio)))
    return (f"field {field!r}, band {band!r}: empty apertures scatter r({model.npix[k]:.0f} pixels) = "
            f"{model.mesh_ratio[k]:.2f} about the background mesh (detection.BACK_SIZE "
            f"{back_size}) but {model.ratio[k]:.2f} about their local background: background "
            "residuals, not correlated noise; r(N) is taken about local backgrounds there (a "
            "smaller detection.BACK_SIZE follows this image's background better)")


def noise_summary(noise_record: dict) -> list[str]:
    """One line per field and band of a manifest's ``noise`` record: the factors applied.

    The map scale (MAP_WEIGHT rescaling, 1 for an absolute map) and the range of
    r(N), with whether it is applied to the errors and where it was measured.
    """
    lines = []
    for field, bands in (noise_record or {}).items():
        for band, rec in bands.items():
            table = rec.get("correlated") or {}
            npix, ratio = table.get("npix") or [], table.get("ratio") or []
            if ratio:
                span = " ".join(f"{r:.2f}" for r in ratio)
                rn = (f"r(N) for N = {npix[0]:.0f}..{npix[-1]:.0f} pixels: {span}")
            else:
                rn = "r(N): not measured"
            how = "applied" if rec.get("applied") else "not applied"
            if table.get("mesh_ratio"):
                how += (", about local backgrounds (about the mesh: up to "
                        f"{max(table['mesh_ratio']):.2f})")
            lines.append(f"noise {field} {band}: {rec.get('weight_type')}, map scale "
                         f"{rec.get('weight_scale', 1.0):.3g}; {rn} ({how})")
    return lines


#: Pixels per block of the set-up's elementwise full-frame work (:func:`~glaciar.engine.blocks.row_blocks`).
ROW_BLOCK_PIXELS = 1 << 22


def field_noise_record(cfg: Config, survey: Survey, field: str,
                       ctx: FieldContext | None = None) -> dict:
    """How each band's noise of a field is used, for the run's manifest.

    Per band: the WEIGHT_TYPE, the MAP_WEIGHT rescaling factor (1 otherwise),
    the empty-aperture table r(N) and whether it is applied to the errors.
    Warns (one line per band) where r(N) had to be measured about local
    backgrounds (:func:`noise_warning`).
    ``ctx``: the field's context, if built (without a stacked detection image its
    noise maps and models are the ones measured here: nothing is measured twice).
    """
    if ctx is not None and cfg.survey.detection_image is None:
        out = {}
        for b in cfg.survey.bands:
            from_background = survey.noise_path(field, b.name) is None or \
                cfg.detection.weight_type == "background"
            out[b.name] = _noise_entry(cfg, survey, field, b.name, ctx.rms[b.name],
                                       from_background, ctx.measured_noise[b.name])
        return out
    params = _detection_params(cfg)
    footprint = survey.footprint(field)
    det = cfg.survey.detection_band
    out = {}
    # One band's pixels at a time (the detection band's until its turn), not every band's.
    pixels = {det: band_pixels(survey, field, det, footprint, params, cfg.detection.weight_type)}
    base_det, rms_det, _ = pixels[det]
    reference = reference_extraction(base_det, rms_det, params, float(cfg.survey.band(det).zeropoint),
                                     mask=~footprint)
    del base_det, rms_det
    sky: dict = {}
    for band in cfg.survey.bands:
        b = band.name
        base, rms, from_background = pixels.pop(b) if b in pixels else \
            band_pixels(survey, field, b, footprint, params, cfg.detection.weight_type)
        model = correlated_noise(cfg, field, b, base, rms, reference.segmap, sky)
        out[b] = _noise_entry(cfg, survey, field, b, rms, from_background, model)
        del base, rms
    return out


def _noise_entry(cfg: Config, survey: Survey, field: str, band: str, rms: np.ndarray,
                 from_background: bool, model: CorrelatedNoise) -> dict:
    # Said here, once per field and run (the manifest's record), not in every worker.
    message = noise_warning(field, band, model, cfg.detection.back_size)
    if message is not None and cfg.noise.correlated != "off":
        warnings.warn(message, UserWarning)
    scale = 1.0
    if cfg.detection.weight_type == "map_weight" and not from_background:
        raw = survey.rms(field, band)
        ok = np.isfinite(rms) & np.isfinite(raw) & (raw > 0)
        scale = float(np.median(rms[ok] / raw[ok])) if ok.any() else float("nan")
    return {"weight_type": cfg.detection.weight_type or
            ("background" if from_background else f"absolute {cfg.survey.noise_type} map"),
            "weight_scale": scale, "correlated": model.to_dict(), "applied": _applies(cfg, model)}


def _applies(cfg: Config, model: CorrelatedNoise) -> bool:
    mode = cfg.noise.correlated
    return mode == "on" or (mode == "auto" and not model.is_identity(cfg.noise.identity_tolerance))


def _field_settings(cfg: Config, survey: Survey, field: str) -> tuple[dict, dict]:
    """The context fields that follow from the configuration (no pixel is read), and the PSFs.

    Everything of a :class:`FieldContext` but its measured fields
    (:attr:`FieldContext.MEASURED`): what a process that opens a field cache
    (:func:`open_field_context`) sets up itself.
    """
    bands = tuple(b.name for b in cfg.survey.bands)
    det = cfg.survey.detection_band
    pixscale = survey.pixel_scale_arcsec(field)
    psfs = {b.name: _band_psf(cfg, b, pixscale) for b in cfg.survey.bands}
    model = population.SourceModel(**cfg.source.model_dump())
    settings = dict(
        field=field, bands=bands, detection_band=det, detection_index=bands.index(det),
        shape=survey.shape(field), pixel_scale_arcsec=pixscale,
        zeropoints={b.name: float(b.zeropoint) for b in cfg.survey.bands},
        gains={b.name: (None if b.gain is None else float(b.gain)) for b in cfg.survey.bands},
        filters=[_resolve_filter(b.filter, cfg.base_dir) for b in cfg.survey.bands],
        cache=TemplateCache(psfs, enclosed_fraction=model.stamp_flux_fraction),
        isolation_margin_pix=int(math.ceil(2.0 * max(measure_fwhm(p, 1.0) for p in psfs.values()))),
        source_model=model, cosmology=population.get_cosmology(model.cosmology),
        magnitude_type=cfg.grid.magnitude_type, n_galaxies=cfg.simulation.n_galaxies,
        detection_params=_detection_params(cfg),
        classification_params=ClassificationParams(**cfg.classification.model_dump()),
        selection=compile_selection(cfg.selection) if cfg.selection else None,
        enclosed_fraction=model.stamp_flux_fraction,
        isolation_fraction=cfg.simulation.isolation_fraction)
    return settings, psfs


#: A field whose images and RMS maps (float32, every band) exceed this [bytes] is measured
#: with each finished full-frame array spilled to disk (glaciar.engine.fieldcache.spill):
#: the measuring process then holds one step's work arrays, not the whole context
#: (~45 bytes per pixel for 4 bands, 11 GB on a 16000^2 mosaic).
SPILL_MIN_BYTES = 1 << 30

#: Callables ``hook(step)`` told when each step of :func:`build_field_context` ends (its
#: name, e.g. ``"band_pixels f160w"``): how benchmarks/setup_memory.py takes each step's
#: peak memory and time. Empty in a run.
SETUP_STEP_HOOKS: list = []


def _step_done(name: str) -> None:
    for hook in SETUP_STEP_HOOKS:
        hook(name)


def build_field_context(cfg: Config, survey: Survey, field: str) -> FieldContext:
    """Read a field's images once, measure backgrounds, extract the original image, set up caches.

    On a large field (:data:`SPILL_MIN_BYTES`) every finished full-frame array is
    moved to an unnamed temporary file and memory-mapped (same values): the
    context's arrays are then read-only maps.
    """
    settings, psfs = _field_settings(cfg, survey, field)
    _step_done("settings")
    bands = settings["bands"]
    det = cfg.survey.detection_band
    params = settings["detection_params"]
    ny, nx = settings["shape"]
    spilled: list = []

    def keep(a):
        """``a`` itself, or on a large field ``a`` on disk (its pages dropped until read)."""
        if not isinstance(a, np.ndarray) or 8 * len(bands) * ny * nx <= SPILL_MIN_BYTES:
            return a
        m = fieldcache.spill(a)
        spilled.append(m._mmap)
        return m

    def drop():
        # Mapped pages the last step read: resident in this process until dropped.
        fieldcache.release(spilled)

    footprint = keep(survey.footprint(field))
    if isinstance(footprint, np.memmap):
        # Large field: the images and validity maps the footprint read (cached by the survey,
        # up to its 2 GiB budget) go; band_pixels reads each band again, one at a time.
        clear_survey_cache()
    mask = keep(~footprint)
    _step_done("footprint")
    bases, rms = {}, {}
    backgrounds = {}
    for b in cfg.survey.bands:
        base, noise, _ = band_pixels(survey, field, b.name, footprint, params,
                                     cfg.detection.weight_type,
                                     background=backgrounds if b.name == det else None)
        bases[b.name], rms[b.name] = keep(base), keep(noise)
        del base, noise
        if b.name == det:
            backgrounds[det] = keep(backgrounds[det])
        # The context holds its own background-subtracted copies: the survey's cached
        # images would only double the memory (at this peak and in every task after it).
        survey.release_pixels(field, (b.name,))
        drop()
        _step_done(f"band_pixels {b.name}")
    if spilled:
        # The survey's cached footprint/mask arrays: the context has its own (on disk).
        clear_survey_cache()
    zps = settings["zeropoints"]
    coadd_bands, coadd_method, det_image_rms = (), "ivw", None
    if cfg.survey.detection_image is not None:
        coadd_bands = cfg.survey.detection_image.coadd
        coadd_method = cfg.survey.detection_image.method
        # float32 straight from the stack's blocks: the values of its float64 result's .astype.
        det_image, det_image_rms = coadd([bases[b] for b in coadd_bands],
                                         [rms[b] for b in coadd_bands], coadd_method,
                                         dtype=np.float32)
        det_image_rms = keep(det_image_rms)
        det_image = keep(det_image)
        drop()
        reference = reference_extraction(det_image, det_image_rms, params,
                                         zps[det], mask=mask, photometry=(bases[det], rms[det]))
        del det_image
    else:
        reference = reference_extraction(bases[det], rms[det], params, zps[det], mask=mask)
    if spilled and isinstance(getattr(reference, "segmap", None), np.ndarray):
        reference = dataclasses.replace(reference, segmap=keep(reference.segmap))
    drop()
    _step_done("reference_extraction" if cfg.survey.detection_image is None else
               "coadd + reference_extraction")
    sky: dict = {}
    noise_models = {}
    for b in bands:
        # drop(): the mapped pages of the segmentation and the band's RMS, read whole for the
        # usable mask, go before the distance transform; then those the apertures read.
        noise_models[b] = correlated_noise(cfg, field, b, bases[b], rms[b], reference.segmap, sky,
                                           release=drop)
        drop()
    del sky
    _step_done("correlated_noise")
    depth, _ = field_depth(rms[det], zps[det], psfs[det])
    depth = keep(depth)
    drop()
    _step_done("field_depth")
    return FieldContext(
        **settings, bases=bases, rms=rms, mask=mask, footprint=footprint,
        footprint_count=int(np.count_nonzero(footprint)), depth=depth, reference=reference,
        noise_models={b: m for b, m in noise_models.items() if _applies(cfg, m)},
        measured_noise=noise_models,
        coadd_bands=coadd_bands, coadd_method=coadd_method, detection_image_rms=det_image_rms,
        detection_background=backgrounds[det])


def open_field_context(cfg: Config, survey: Survey, field: str, path) -> FieldContext:
    """A field's context from its cache directory (:func:`save_field_context`): the measured
    arrays memory-mapped read-only, the rest set up from the configuration (no image read)."""
    settings, _ = _field_settings(cfg, survey, field)
    items, maps = fieldcache.load(path)
    return FieldContext(**settings, **items, _trimmer=fieldcache.Trimmer(maps))


def _cache_items(ctx: FieldContext) -> dict:
    """A context's measured fields as its cache stores them.

    When the field's mapped arrays exceed a worker's resident budget
    (:data:`glaciar.engine.fieldcache.RESIDENT_BUDGET_BYTES`: their pages will be
    dropped and faulted in again during the run), the images the engine reads by
    window (images, RMS maps, mask, reference segmentation) are stored as tiles: a window then
    reads the tiles under it with positional reads, nothing mapped (benchmarks/window_reads.py).
    Smaller fields stay row-major (their pages stay resident, a plain slice is cheapest).
    """
    items = ctx.measured()
    arrays = [a for a in (*ctx.bases.values(), *ctx.rms.values(), ctx.mask, ctx.footprint,
                          ctx.depth, getattr(ctx.reference, "segmap", None),
                          ctx.detection_image_rms, ctx.detection_background)
              if isinstance(a, np.ndarray)]
    if not fieldcache.TILED_CACHE or \
            sum(a.nbytes for a in arrays) <= fieldcache.RESIDENT_BUDGET_BYTES:
        return items

    def tiled(a):
        return fieldcache.Tiled(a) if isinstance(a, np.ndarray) and a.ndim == 2 else a

    items["bases"] = {b: tiled(a) for b, a in ctx.bases.items()}
    items["rms"] = {b: tiled(a) for b, a in ctx.rms.items()}
    items["mask"] = tiled(ctx.mask)
    items["detection_image_rms"] = tiled(ctx.detection_image_rms)
    if isinstance(getattr(ctx.reference, "segmap", None), np.ndarray):
        items["reference"] = dataclasses.replace(ctx.reference, segmap=tiled(ctx.reference.segmap))
    return items


def save_field_context(ctx: FieldContext, path) -> FieldContext:
    """Write a context's measured fields to ``path`` (unless a cache is there already) and
    return the context with them memory-mapped from it (the in-memory arrays can go).

    If the cache cannot be written (e.g. the disk is full), warns and returns ``ctx``
    unchanged: the run goes on with the field in memory (forked workers inherit it,
    spawned ones measure it again).
    """
    try:
        if not fieldcache.exists(path):
            fieldcache.save(_cache_items(ctx), path)
        items, maps = fieldcache.load(path)
    except (OSError, ValueError) as exc:     # ValueError: fieldcache.load's unreadable cache
        # One reason, not DiskFullError's whole advice: the run goes on.
        why = os.strerror(exc.errno) if getattr(exc, "errno", None) else str(exc)
        warnings.warn(f"{path}: field cache not written ({why}); the field's arrays stay in "
                      "memory", UserWarning)
        return ctx
    return dataclasses.replace(ctx, **items, _trimmer=fieldcache.Trimmer(maps))


def _context_dir(run_dir, cfg_hash: str, field: str, inputs: dict | None = None) -> Path | None:
    """Cache directory of a field's context in a run (None: no manifest yet).

    Keyed on everything the measurement depends on: the config's hash, the field,
    the run's input files (size and BLAKE2b: ``inputs``, by default the manifest's),
    glaciar's version and the cache's format; a changed config or input gets a new
    directory.
    """
    if inputs is None:
        manifest = read_manifest(run_dir)
        if manifest is None:
            return None
        inputs = manifest.get("inputs") or {}
    ident = json.dumps({"format": fieldcache.FORMAT, "glaciar": __version__, "config": cfg_hash,
                        "field": field, "inputs": inputs}, sort_keys=True)
    return Path(run_dir) / C.CONTEXT_DIRNAME / hashlib.sha256(ident.encode("utf-8")).hexdigest()[:24]


def _prepare_context_cache(run_dir: Path, cfg: Config, cfg_hash: str, fields) -> None:
    """Before tasks run (lock held, no worker yet): remove caches of other configs or inputs
    and half-written ones, and put the context this process built (for the manifest) on disk,
    so its tasks, forked workers and spawned workers all map the same files."""
    keep = {_context_dir(run_dir, cfg_hash, f) for f in cfg.survey.fields}
    root = run_subdir(run_dir, C.CONTEXT_DIRNAME, create=False)     # refused if a link
    if root.is_dir():
        for entry in root.iterdir():
            if entry.is_symlink():
                entry.unlink()          # the link only: nothing outside the run is touched
            elif entry not in keep:
                shutil.rmtree(entry, ignore_errors=True)
            elif fieldcache.exists(entry):
                try:                    # mapping only: a truncated file would fail the workers
                    fieldcache.load(entry)
                except fieldcache.UnreadableCache:
                    shutil.rmtree(entry, ignore_errors=True)      # written again below
    for key, ctx in list(_CONTEXTS.items()):
        if key[0] == cfg_hash and key[2] in fields:
            _CONTEXTS[key] = save_field_context(ctx, _context_dir(run_dir, cfg_hash, key[2]))
            # The masks the build left in the survey's cache: forked workers would inherit them.
            clear_survey_cache()


def _finish_context_cache(run_dir: Path, complete: bool) -> None:
    """A run with no task left pending removes its field caches; an unfinished one keeps them
    for its resume (they are as large as the images)."""
    if complete:
        shutil.rmtree(Path(run_dir) / C.CONTEXT_DIRNAME, ignore_errors=True)


def box_cells(cfg: Config) -> list[dict]:
    """The points of ``grid.box`` as cells (plain JSON, fields resolved); [] without a box.

    The points depend on ``simulation.seed`` (:func:`glaciar.box.box_points`;
    :func:`simulate` puts a ``seed`` override into the config first).
    """
    box = cfg.grid.box
    if box is None:
        return []
    fields = list(box.fields or cfg.survey.fields)
    return [{"z": z, "mag": m, "n_iterations": int(box.n_iterations), "fields": fields}
            for z, m in box.points(cfg.simulation.seed)]


def task_cells(cfg: Config) -> dict[tuple[str, float, float], int]:
    """Every simulated cell of a run: ``{(field, z, mag): n_iterations}``.

    The Cartesian grid (``simulation.n_iterations`` each) united with
    ``grid.cells`` and the points of ``grid.box``; a cell given twice (or also
    on the grid) runs the largest of its iteration counts, so re-applying a
    proposal adds nothing.
    """
    n_it = cfg.simulation.n_iterations
    cells: dict[tuple[str, float, float], int] = {}
    for f in cfg.survey.fields:
        for z in cfg.grid.z_values:
            for m in cfg.grid.mag_values:
                cells[(f, float(z), float(m))] = n_it
    for cell in manifest_cells(cfg):
        for f in cell["fields"]:
            key = (f, cell["z"], cell["mag"])
            cells[key] = max(cells.get(key, 0), cell["n_iterations"])
    return cells


def plan_tasks(cfg: Config) -> list[TaskSpec]:
    """All tasks of a run, ordered field → z → mag → iteration (so per-process caches stay warm).

    Tasks are keyed by exact values (field name, z, mag, iteration); the
    indices are positions in the sorted values the run simulates.
    """
    cells = task_cells(cfg)
    field_index = {f: i for i, f in enumerate(cfg.survey.fields)}
    zs = sorted({z for _, z, _ in cells})
    ms = sorted({m for _, _, m in cells})
    zi, mi = {z: i for i, z in enumerate(zs)}, {m: i for i, m in enumerate(ms)}
    out = []
    for (f, z, m), n in sorted(cells.items(), key=lambda kv: (field_index[kv[0][0]],) + kv[0][1:]):
        for it in range(n):
            out.append(TaskSpec(field=f, field_index=field_index[f], z_index=zi[z],
                                mag_index=mi[m], iteration=it, z=z, mag=m))
    return out


def manifest_cells(cfg: Config) -> list[dict]:
    """``grid.cells`` and the points of ``grid.box`` as the manifest records them.

    Plain JSON, fields resolved: the rows of every listed cell are current
    (:func:`glaciar.store.current_rows_mask`).
    """
    return [{"z": float(c.z), "mag": float(c.mag),
             "n_iterations": int(c.n_iterations or cfg.simulation.n_iterations),
             "fields": list(c.fields or cfg.survey.fields)} for c in cfg.grid.cells] \
        + box_cells(cfg)


def spec_filename(spec: TaskSpec) -> str:
    """File name of a task's rows (:func:`glaciar.store.task_filename`)."""
    return task_filename(spec.field, spec.z, spec.mag, spec.iteration)


def spec_key(spec: TaskSpec) -> str:
    """Exact identity of a task (:func:`glaciar.store.task_key`)."""
    return task_key(spec.field, spec.z, spec.mag, spec.iteration)


# --------------------------------------------------------------------------
# Worker side: a per-process cache of configs, surveys and field contexts.
# --------------------------------------------------------------------------
_CONTEXTS: dict = {}


def _context(cfg_dict: dict, base_dir: str, cfg_hash: str, field: str,
             run_dir: str | None = None) -> FieldContext:
    """The field's context in this process: kept from an earlier call, opened from the run's
    field cache, or built (and then cached for the other workers)."""
    key = (cfg_hash, base_dir, field)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        cfg = config_from_dict(cfg_dict, base_dir)
        _CONTEXTS.clear()          # one field at a time per process bounds memory
        path = None if run_dir is None else _context_dir(run_dir, cfg_hash, field)
        survey = Survey.from_config(cfg)
        if path is not None and fieldcache.exists(path):
            ctx = open_field_context(cfg, survey, field, path)
        else:
            ctx = build_field_context(cfg, survey, field)
            if path is not None:
                ctx = save_field_context(ctx, path)
        _CONTEXTS[key] = ctx
    return ctx


def _context_of(cfg: Config, survey: Survey, field: str, cached: Path | None = None) -> FieldContext:
    """The field's context from the main process's config, under :func:`_context`'s key.

    ``cached``: the field's cache directory in the run, if known: a complete cache
    there (an interrupted run's, for its resume) is mapped instead of measuring the
    field again.
    """
    key = (config_hash(cfg), str(cfg.base_dir), field)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        _CONTEXTS.clear()
        if cached is not None and fieldcache.exists(cached):
            try:
                ctx = open_field_context(cfg, survey, field, cached)
            except fieldcache.UnreadableCache as exc:
                # A copy of measurements: measured again (the run replaces it, under its lock).
                warnings.warn(f"{exc.path}: unreadable field cache ({exc.why}); the field is "
                              "measured again", StoreWarning)
        if ctx is None:
            ctx = build_field_context(cfg, survey, field)
        _CONTEXTS[key] = ctx
    return ctx


def _run_chunk(cfg_dict: dict, base_dir: str, cfg_hash: str, run_dir: str, seed: int,
               specs: list[TaskSpec], mode: str = "windowed") -> list[tuple[str, int, float]]:
    """Run a chunk of tasks of one field and write each task's file; return (name, rows, seconds)."""
    done = []
    ctx = None
    try:
        for spec in specs:
            t0 = time.process_time()
            ctx = _context(cfg_dict, base_dir, cfg_hash, spec.field, run_dir)
            # Image pages the tasks touch stay resident while mapped: dropped past a budget.
            fieldcache.trim(ctx, watch=True)
            table = run_task(ctx, spec, seed, mode=mode)
            name = spec_filename(spec)
            # The task's counts go in its file's footer, keyed on the fit's magnitude covariate.
            mag_column = C.COL_M_UV if ctx.magnitude_type == "absolute" else C.COL_MAG_INPUT
            # And the histograms of the measured detection-band magnitude (transfer matrices).
            write_task_table(run_dir, name, table, key=spec_key(spec), mag_column=mag_column,
                             obs_column=C.band_column(C.OBS_MAG_QUANTITY, ctx.detection_band))
            done.append((name, len(table), time.process_time() - t0))
    finally:
        if ctx is not None:
            fieldcache.trim(ctx, watch=False)
    return done


#: Guided scheduling: each chunk holds 1 / (this x workers) of the tasks not yet chunked.
_GUIDED_CHUNK_DIVISOR = 4


def _chunks(specs: list[TaskSpec], n_workers: int) -> list[list[TaskSpec]]:
    """Cut the ordered tasks into chunks of one (field, z) each, large ones first.

    Guided self-scheduling: a chunk takes ``1 / (4 x n_workers)`` of the tasks
    not yet chunked, so the first chunks are large (few submissions) and the
    last ones single tasks, which the workers share as they free up: the run's
    tail is about one task, not one chunk.  A chunk never spans two (field, z)
    pairs, so a worker renders a chunk's templates once (a process caches them
    across chunks too), and the plan's field order is kept (one field's
    context per process at a time).
    """
    groups: dict = {}
    for s in specs:
        groups.setdefault((s.field_index, s.z_index), []).append(s)
    divisor = _GUIDED_CHUNK_DIVISOR * max(1, n_workers)
    remaining = len(specs)
    out = []
    for g in groups.values():
        i = 0
        while i < len(g):
            chunk = g[i:i + max(1, math.ceil(remaining / divisor))]
            out.append(chunk)
            i += len(chunk)
            remaining -= len(chunk)
    return out


def _run_chunk_measured(*args) -> tuple[list[tuple[str, int, float]], int, float]:
    """:func:`_run_chunk`, and the worker's pid and process CPU [s] it used (set-up included)."""
    c0 = process_cpu_seconds(children=False)
    done = _run_chunk(*args)
    return done, os.getpid(), process_cpu_seconds(children=False) - c0


def _depth_area(cfg: Config, survey: Survey, field: str, ctx: FieldContext | None = None) -> dict:
    """The manifest's footprint area by local depth of one field (one FFT; main process only).

    Warns when the depth comes from sep's background RMS (no noise map): once
    per field and run, here, rather than in every worker that builds the field.
    ``ctx``: the field's context, if built (its depth map is this one).
    """
    det = cfg.survey.detection_band
    band = cfg.survey.band(det)
    pixscale = survey.pixel_scale_arcsec(field)
    if ctx is not None:
        from_background = survey.noise_path(field, det) is None or \
            cfg.detection.weight_type == "background"
    else:
        _, rms, from_background = band_pixels(survey, field, det, survey.footprint(field),
                                              _detection_params(cfg), cfg.detection.weight_type)
    if from_background:
        warnings.warn(f"field {field!r}: no noise map for the detection band {det!r}; its local "
                      "depth (column depth_local, manifest depth_area) comes from sep's background "
                      "RMS mesh", UserWarning)
    psf = _band_psf(cfg, band, pixscale)
    if ctx is not None:
        depth = ctx.depth
        radius_pix = C.DEPTH_APERTURE_RADIUS_FWHM * measure_fwhm(psf, 1.0)
    else:
        depth, radius_pix = field_depth(rms, float(band.zeropoint), psf)
    edges, area = depth_area_histogram(depth, pixscale, C.DEPTH_BIN_MAG)
    return {"band": det, "nsigma": C.DEPTH_NSIGMA, "aperture_radius_arcsec": radius_pix * pixscale,
            "rms_source": "background" if from_background else "noise_map",
            "bin_edges_mag": [round(float(e), 10) for e in edges],
            "area_arcmin2": [float(a) for a in area]}


# --------------------------------------------------------------------------
# Inputs: every file a run reads, checked and fingerprinted before anything is written
# --------------------------------------------------------------------------
class InputError(ValueError):
    """An input file of the configuration is unusable; the message names its key and path."""


@dataclass(frozen=True)
class InputFile:
    """One input file of a run, named by the configuration key it comes from."""

    key: str                  #: e.g. ``survey.bands.f160w.psf`` or ``survey.science (field 'a', band 'b')``
    path: Path
    kind: str                 #: science, noise, psf, filter, sex_file or conv
    field: str | None = None  #: the field whose tasks read it (None: every task)
    band: str | None = None


def _file_or_none(value, base_dir: Path) -> Path | None:
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
        fp = _file_or_none(b.filter, cfg.base_dir)
        if fp is not None:
            out.append(InputFile(f"survey.bands.{b.name}.filter", fp, "filter", None, b.name))
    det = config_to_dict(cfg).get("detection") or {}
    for key, kind in (("sex_file", "sex_file"), ("FILTER_NAME", "conv")):
        p = _file_or_none(det.get(key), cfg.base_dir)
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


def _check_image(item: InputFile) -> None:
    """A science or noise image: a readable FITS file with a 2-D image holding finite pixels."""
    from .survey import _read_array

    with warnings.catch_warnings():
        # astropy only warns about a file shorter than its header says; that is an error here.
        warnings.filterwarnings("error", message=".*truncated.*")
        arr = _read_array(item.path)
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"expected a non-empty 2-D image, got shape {arr.shape}")
    if not np.isfinite(arr).any():
        raise ValueError("no finite pixel in the image")


def _check_noise_maps(cfg: Config, items: list[InputFile], fingerprints: dict, cache: dict,
                      fail, errors) -> None:
    """Each noise map against its science image's pixel scatter (:func:`~glaciar.engine.noise.map_type_problem`).

    Not for a relative weight map (WEIGHT_TYPE MAP_WEIGHT: its scale is rescaled to the
    image) nor an unused one (BACKGROUND). A strided sample of <= 2^20 pixels of each
    image; checked once per (noise file version, noise_type, science file version):
    ``cache`` remembers it.
    """
    from .engine.noise import map_type_problem
    from .survey import strided_sample

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
            sci_pixels, map_pixels = strided_sample(sci.path), strided_sample(item.path)
            # Shapes that differ are refused below, naming both (survey.shape).
            problem = None if sci_pixels.shape != map_pixels.shape else \
                map_type_problem(sci_pixels, map_pixels, ntype)
        except errors as exc:
            raise fail(item, exc) from None
        if problem is not None:
            raise InputError(f"{item.key}: {item.path}: {problem}")
        entry["map_type_checked"] = stamp


def check_inputs(cfg: Config, survey: Survey | None = None, cache: dict | None = None) -> dict:
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
    by_path: dict[str, list[InputFile]] = {}
    for it in items:
        by_path.setdefault(str(it.path.resolve()), []).append(it)

    def fail(item, exc, caught=()):
        return InputError(f"{item.key}: {item.path}: {_reason(exc, item.path)}{_folded(caught)}")

    def reissue(key, path, caught):
        # A check that passes keeps the library's warnings, each on one line naming the file.
        for w in caught:
            warnings.warn(f"{key}: {path}: {' '.join(str(w.message).split())}", stacklevel=3)

    out = {}
    errors = (OSError, ValueError, TypeError, KeyError, IndexError, EOFError, UnicodeDecodeError,
              Warning)
    for item in items:
        try:
            fp = file_fingerprint(item.path, cache)
        except OSError as exc:
            raise fail(item, exc) from None
        entry = cache.get(str(item.path.resolve()), {})
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                if item.kind in ("science", "noise") and not entry.get("checked"):
                    _check_image(item)
                elif item.kind == "filter":
                    get_filter(str(item.path))
            except errors as exc:
                raise fail(item, exc, caught) from None
        reissue(item.key, item.path, caught)
        if item.kind in ("science", "noise"):
            entry["checked"] = True
        out[item.key] = {"path": str(item.path), **fp}
    _check_noise_maps(cfg, items, out, cache, fail, errors)
    # Shapes agree within each field, pixel scales are known, PSFs resample at every scale.
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
                    _band_psf(cfg, b, scale)
                except errors as exc:
                    if where is None:
                        raise InputError(f"{key}: {_reason(exc, Path('.'))}"
                                         f"{_folded(caught)}") from None
                    raise InputError(f"{key}: {where}: {_reason(exc, where)}"
                                     f"{_folded(caught)}") from None
            reissue(key, where if where is not None else "(analytic)", caught)
    try:
        _detection_params(cfg)
    except errors as exc:
        raise InputError(f"detection: {str(exc).splitlines()[0]}") from None
    return out


def _load_fingerprint_cache(run_dir: Path) -> dict:
    p = run_dir / C.FINGERPRINT_CACHE_NAME
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


# --------------------------------------------------------------------------
# Store identity: the settings that fix every task's rows (no paths, no task list)
# --------------------------------------------------------------------------
_FILE = "<file>"   #: stands for a path in the store settings (its content is fingerprinted)


def store_settings(cfg: Config) -> dict:
    """The configuration's settings that fix every task's rows, as plain data.

    ``config_to_dict(cfg)`` without ``output``, the field list, the grid's z
    and magnitude values, ``simulation.n_iterations`` and ``simulation.seed``
    (the run's seed is compared on its own), and with every path replaced by
    ``"<file>"``: files are identified by content (the manifest's ``inputs``),
    so a run directory's own ``config.yaml`` (absolute paths) or a moved project
    is the same store.
    """
    d = config_to_dict(cfg)
    d.pop("output", None)
    # Definitions that change rows without a config key: a store made under another
    # definition is another store.
    d["classification"]["flux_test"] = "auto_vs_template"
    sv = d["survey"]
    sv.pop("fields", None)
    sv.pop("image_dir", None)
    sv.pop("science", None)
    sv["noise"] = _FILE if sv.get("noise") is not None else None
    sv["band_order"] = list(sv["bands"])
    for b in sv["bands"].values():
        if isinstance(b.get("psf"), str):
            b["psf"] = _FILE
        if _file_or_none(b.get("filter"), cfg.base_dir) is not None:
            b["filter"] = _FILE
    d["grid"].pop("z", None)
    d["grid"].pop("mag", None)
    d["grid"].pop("cells", None)
    d["grid"].pop("box", None)       # box points are cells: they only add tasks
    d["simulation"].pop("n_iterations", None)
    d["simulation"].pop("seed", None)
    det = d.get("detection") or {}
    for key in ("sex_file", "FILTER_NAME"):
        if _file_or_none(det.get(key), cfg.base_dir) is not None:
            det[key] = _FILE
    return json.loads(json.dumps(d, sort_keys=True))


def _settings_hash(settings: dict) -> str:
    import hashlib

    text = json.dumps(settings, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _flatten(d, prefix=""):
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: d}


def _flat_defaults() -> dict:
    """Every default of the sections that have one for each key, flattened like the settings."""
    from .config.models import SECTIONS

    out = {}
    for name, field in SECTIONS.items():
        try:
            section = field.annotation()
        except Exception:  # noqa: BLE001 - sections with required keys (survey) or no model
            continue
        out.update(_flatten(json.loads(json.dumps(section.model_dump(mode="json", by_alias=True))),
                            f"{name}."))
    return out


def _settings_differences(old: dict, new: dict) -> list[str]:
    """What differs between two stores' settings, one ``key: old -> new`` string each.

    A key the older store does not record (added to glaciar since) counts as the
    same when its value now is its default: a new key's default keeps the rows
    glaciar made before the key existed, so the older store stays extendable.
    """
    a, b = _flatten(old), _flatten(new)
    defaults = _flat_defaults()
    diffs = []
    for k in sorted(set(a) | set(b)):
        if k not in a and k in defaults and b[k] == defaults[k]:
            continue
        if a.get(k, "<unset>") != b.get(k, "<unset>"):
            diffs.append(f"{k}: {str(a.get(k, '<unset>'))[:40]} -> {str(b.get(k, '<unset>'))[:40]}")
    return diffs


def _summary(diffs: list[str], limit: int = 3) -> str:
    more = f" and {len(diffs) - limit} more" if len(diffs) > limit else ""
    return "; ".join(diffs[:limit]) + more


def detection_z_limit(cfg: Config, z_max: float = 30.0) -> float | None:
    """Lowest z (to 0.005) where the detection band receives no flux (apparent-magnitude grids).

    Beyond it no source of an apparent detection-band magnitude exists, so the
    selection function is 0 there (:func:`glaciar.galaxy.sed.band_magnitudes`
    refuses such tasks). None for absolute-magnitude grids or below ``z_max``.
    """
    if cfg.grid.magnitude_type != "apparent":
        return None
    from .galaxy import sed

    det = cfg.survey.detection_band
    filters = [_resolve_filter(cfg.survey.band(det).filter, cfg.base_dir)]
    beta = np.array([cfg.source.beta_mean])

    def ok(z):
        try:
            sed.band_magnitudes(z, beta, filters, mag=np.array([26.0]), detection_index=0,
                                igm=cfg.source.igm)
            return True
        except ValueError:
            return False

    lo = max(z for _, z, _ in task_cells(cfg))
    if not ok(lo):
        return float(lo)
    hi = lo
    while ok(hi):
        lo, hi = hi, hi + 0.25
        if hi > z_max:
            return None
    while hi - lo > 0.005:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return round(hi, 3)


def _manifest(cfg: Config, survey: Survey, seed: int, z_limit=None, cached: dict | None = None) -> dict:
    """The run's manifest; ``z_limit``: a future of :func:`detection_z_limit` (None: computed here);
    ``cached``: field -> its context's cache directory in the run (:func:`_context_of`)."""
    area = {}
    pixscale = {}
    settings = store_settings(cfg)
    depth_area, noise = {}, {}
    for f in cfg.survey.fields:
        # The field's context is built here once, in this process (or mapped from an
        # interrupted run's cache): the area, depth and noise records read it, a serial
        # run's tasks use it (glaciar.run._context), and forked pool workers inherit it
        # instead of measuring the field again.
        ctx = _context_of(cfg, survey, f, (cached or {}).get(f))
        ps = survey.pixel_scale_arcsec(f)
        pixscale[f] = ps
        area[f] = float(ctx.footprint_count) * ps ** 2 / 3600.0
        depth_area[f] = _depth_area(cfg, survey, f, ctx)
        noise[f] = field_noise_record(cfg, survey, f, ctx)
    return {
        "store_format": C.STORE_FORMAT,
        "glaciar_version": __version__,
        "glaciar_versions": [__version__],
        "config_hash": config_hash(cfg),
        "store_hash": _settings_hash(settings),
        "store_settings": settings,
        "seed": int(seed),
        "fields": list(cfg.survey.fields),
        "bands": [b.name for b in cfg.survey.bands],
        "detection_band": cfg.survey.detection_band,
        "selection": list(cfg.selection),
        "z_values": list(map(float, cfg.grid.z_values)),
        "mag_values": list(map(float, cfg.grid.mag_values)),
        "magnitude_type": cfg.grid.magnitude_type,
        "n_galaxies": cfg.simulation.n_galaxies,
        "n_iterations": cfg.simulation.n_iterations,
        "cells": manifest_cells(cfg),
        **({} if cfg.grid.box is None else
           {"box": {"z": list(cfg.grid.box.z), "mag": list(cfg.grid.box.mag),
                    "n_points": cfg.grid.box.n_points}}),
        "pixel_scale_arcsec": pixscale,
        "area_arcmin2": area,
        "area_arcmin2_total": float(sum(area.values())),
        "depth_area": depth_area,
        "noise": noise,
        "detection_z_limit": detection_z_limit(cfg) if z_limit is None else z_limit.result(),
    }


def _check_same_store(run_dir: Path, old: dict, manifest: dict, items: list[InputFile],
                      finished: set[str]) -> None:
    """Refuse to add tasks to a store whose finished tasks were made differently."""
    what = []
    if old.get("seed") != manifest["seed"]:
        what.append(f"seed: {old.get('seed')} -> {manifest['seed']}")
    if old.get("store_hash") != manifest["store_hash"]:
        diffs = _settings_differences(old.get("store_settings") or {}, manifest["store_settings"])
        if diffs:
            what.append(_summary(diffs))
    if what:
        raise StoreMismatchError(
            f"{run_dir}: results were made with a different configuration or seed "
            f"({'; '.join(what)}); only fields, grid values and n_iterations may change between "
            "runs into one directory; use another --out")
    old_inputs = old.get("inputs") or {}
    for item in items:
        prev, now = old_inputs.get(item.key), manifest["inputs"][item.key]
        if not isinstance(prev, dict) or (prev.get("size"), prev.get("blake2b")) == \
                (now["size"], now["blake2b"]):
            continue
        if item.field is None:
            used = bool(finished)
        else:
            prefix = field_file_prefix(item.field)
            used = any(n.startswith(prefix) for n in finished)
        if used:
            raise StoreMismatchError(f"{item.key}: {item.path} changed since the run started "
                                     "(content differs); use another --out")


def _open_run(cfg: Config, run_dir: Path, seed: int, parallel: str | cf.Executor | None = None,
              warm: int = 1) -> tuple[dict, RunLock]:
    """Validate everything, then create or update the run directory under its lock.

    Every check (inputs, store identity, lock) runs before anything is
    created or modified: a refused start leaves an existing run directory
    byte-identical and creates no new one.  Returns the manifest and the held
    lock (the caller releases it).

    ``parallel``: where the set-up steps that need neither the checked inputs'
    results nor the field's context run while this process checks the inputs
    and measures the field (:class:`_SetupJobs`): None (here, in order),
    ``"fork"`` (a forked helper process) or an executor (the run's own, of
    which ``warm`` workers are asked to import glaciar and warm their caches meanwhile).
    """
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise FileExistsError(f"{run_dir}: exists and is not a directory")
    if run_dir.is_dir():
        # A results/, .context/, summary/, ... that is a symbolic link would receive task
        # files, caches and reports outside the run: refused before anything is written.
        check_run_tree(run_dir)
    lock = RunLock(run_dir)
    lock.check_free()
    old = read_manifest(run_dir) if run_dir.is_dir() else None
    finished = finished_task_names(run_dir)
    if finished and old is None:
        raise StoreMismatchError(f"{run_dir / C.RESULTS_DIRNAME}: holds task files but "
                                 f"{run_dir / C.MANIFEST_NAME} is missing; use another --out")
    if finished and store_format(old) != C.STORE_FORMAT:
        raise StoreMismatchError(
            f"{run_dir}: made by glaciar {old.get('glaciar_version', '?')} (store format "
            f"{store_format(old)}, whose task file names can collide); glaciar {__version__} "
            f"(format {C.STORE_FORMAT}) does not add to it; use another --out "
            "(fit and report still read it)")
    cache = _load_fingerprint_cache(run_dir) if run_dir.is_dir() else {}
    cache_before = json.dumps(cache, sort_keys=True)
    survey = Survey.from_config(cfg)
    # An interrupted run left its fields' contexts on disk: with the inputs checked first
    # (the cache's key holds their fingerprints), the resume maps them, not measuring again.
    resuming = old is not None and (run_dir / C.CONTEXT_DIRNAME).is_dir()
    with _SetupJobs(cfg, survey, cache, parallel, warm) as jobs:
        cached = None
        if not jobs.in_background or resuming:
            inputs = jobs.inputs()
            jobs.preflight()        # before the field is measured: a field nothing fits fails fast
        if resuming:
            recorded, chash = _recorded_inputs(old, finished, inputs), config_hash(cfg)
            cached = {f: _context_dir(run_dir, chash, f, recorded) for f in cfg.survey.fields}
        # Measuring the fields reads every input while the check runs beside it: a
        # damaged file makes astropy warn here first.  Held back until the inputs are
        # known to be good, so a refusal is the check's one line, not warnings and a line.
        with warnings.catch_warnings(record=True) as measured:
            warnings.simplefilter("always")
            try:
                manifest = _manifest(cfg, survey, seed, z_limit=jobs.z_limit, cached=cached)
            except Exception:
                if jobs.in_background:  # an unusable input or an empty field explains it
                    jobs.inputs()
                    jobs.preflight()
                raise
        if jobs.in_background and not resuming:
            inputs = jobs.inputs()
            jobs.preflight()
    for w in {(str(w.message), w.category): w for w in measured}.values():
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    items = input_files(cfg)
    manifest["inputs"] = _recorded_inputs(old, finished, inputs)
    if old is not None and finished:
        _check_same_store(run_dir, old, manifest, items, finished)
        versions = old.get("glaciar_versions") or [old.get("glaciar_version", "?")]
        if __version__ not in versions:
            warnings.warn(f"{run_dir}: started with glaciar {', '.join(map(str, versions))}; "
                          f"glaciar {__version__} adds its tasks", StoreWarning)
        manifest["glaciar_version"] = old.get("glaciar_version", __version__)
        manifest["glaciar_versions"] = sorted(set(map(str, versions)) | {__version__})
    elif old is not None:
        manifest["glaciar_version"] = old.get("glaciar_version", __version__)
    config_text = yaml.safe_dump(config_to_dict(cfg), sort_keys=False, allow_unicode=True)
    # ---- everything is checked: from here on the directory is created or modified ----
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise (disk_full(run_dir, exc) or exc) from None
    lock.acquire()
    try:
        if read_manifest(run_dir) != old or finished_task_names(run_dir) - finished:
            raise StoreMismatchError(f"{run_dir}: changed while this run was starting (another "
                                     "glaciar run?); run the command again")
        mpath = run_dir / C.MANIFEST_NAME
        if not mpath.exists() or mpath.read_text(encoding="utf-8") != manifest_text(manifest):
            write_manifest(run_dir, manifest)
        cpath = run_dir / C.RUN_CONFIG_NAME
        if not cpath.exists() or cpath.read_text(encoding="utf-8") != config_text:
            atomic_write_text(cpath, config_text)
        if json.dumps(cache, sort_keys=True) != cache_before:
            atomic_write_text(run_dir / C.FINGERPRINT_CACHE_NAME,
                              json.dumps(cache, sort_keys=True, indent=1))
        # Temporary files of tasks that were in flight when an earlier run was killed:
        # removed only while holding the lock, so never those of a live run.
        for stale in (run_dir / C.RESULTS_DIRNAME).glob(".task_*.tmp"):
            stale.unlink(missing_ok=True)
    except BaseException:
        lock.release()
        raise
    return manifest, lock


def _recorded_inputs(old: dict | None, finished, inputs: dict) -> dict:
    """The manifest's input fingerprints: a store with finished tasks keeps the inputs of
    fields no longer listed (they are checked if the field returns)."""
    if old is not None and finished:
        return {**(old.get("inputs") or {}), **inputs}
    return inputs


def _setup_job(cfg_dict: dict, base_dir: str, steps: tuple[str, ...], cache: dict | None = None):
    """Set-up steps of a run in another process: ``({step: result}, warnings)``.

    ``steps``: any of ``"check"`` (:func:`check_inputs` with the fingerprint
    ``cache``: the result is ``(inputs, cache)``), ``"preflight"``
    (:func:`placement_preflight`'s messages) and ``"z_limit"``
    (:func:`detection_z_limit`), run in that order; the first to fail raises.
    The warnings come back as ``(message, category)`` pairs for the run's own
    process to raise.
    """
    cfg = config_from_dict(cfg_dict, base_dir)
    out = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        survey = Survey.from_config(cfg) if {"check", "preflight"} & set(steps) else None
        for step in steps:
            if step == "check":
                cache = {} if cache is None else cache
                out[step] = (check_inputs(cfg, survey, cache), cache)
            elif step == "preflight":
                out[step] = placement_preflight(cfg, survey)
            elif step == "z_limit":
                out[step] = detection_z_limit(cfg)
            else:
                raise ValueError(f"unknown set-up step {step!r}")
    return out, [(str(w.message), w.category) for w in caught]


class _Later:
    """A future computed when its result is first asked for."""

    def __init__(self, fn, *args):
        self._call, self._done, self._value = (fn, args), False, None

    def result(self):
        if not self._done:
            fn, args = self._call
            self._value, self._done = fn(*args), True
        return self._value


def _preimport() -> None:
    """Import what measuring a field needs (before forking: the children share the modules)."""
    import astropy.cosmology  # noqa: F401
    import astropy.io.fits  # noqa: F401
    import astropy.wcs  # noqa: F401


def _prewarm(cfg_dict: dict, base_dir: str) -> None:
    """In a spawned worker, during the run's set-up: what its first task would do before its
    sources -- imports, the first field's settings (PSFs, filters, cosmology) and the SED
    colour tables of the run's redshifts (each cached per process, ~0.7 s for the demo)."""
    from .galaxy import sed

    cfg = config_from_dict(cfg_dict, base_dir)
    survey = Survey.from_config(cfg)
    settings, _ = _field_settings(cfg, survey, cfg.survey.fields[0])
    igm = settings["source_model"].igm
    for z in sorted({float(s.z) for s in plan_tasks(cfg)}):
        if cfg.grid.magnitude_type == "absolute":
            sed.band_magnitudes(z, np.zeros(1), settings["filters"], M_uv=np.full(1, -20.0),
                                cosmology=settings["cosmology"], igm=igm)
        else:
            sed.band_magnitudes(z, np.zeros(1), settings["filters"], mag=np.full(1, 25.0),
                                detection_index=settings["detection_index"], igm=igm)


class _SetupJobs:
    """A run's set-up steps that do not need the field's context, beside the one that does.

    :func:`check_inputs` (fingerprints and reads every input file),
    :func:`placement_preflight` (reads the footprints, draws sources) and
    :func:`detection_z_limit` (a bisection over the SED) are pure functions of
    the configuration and the input files: where ``where`` allows, they run,
    exactly as they would here, while this process measures the field for the
    manifest (:func:`_open_run`), the rest of a run's serial start.

    ``where``: None (serial: each runs here, in the order above, when its
    result is asked for, before the field is measured); ``"fork"`` (all three,
    in one forked helper process started after the file-existence check and
    reaped at the end: its CPU counts in :func:`process_cpu_seconds`); or an
    executor (the z limit only, on one of the run's workers, which then also
    imports glaciar before its first task, and ``warm - 1`` jobs that set up
    what a first task needs (:func:`_prewarm`), for other workers; the checks
    and the preflight read images,
    which a worker otherwise reads once, for its tasks).  Errors and
    warnings are raised here; the input check's error first.  Nothing is
    written either way.
    """

    def __init__(self, cfg: Config, survey: Survey, cache: dict, where: str | cf.Executor | None,
                 warm: int = 1):
        self._cfg, self._survey, self._cache = cfg, survey, cache
        self._own = self._job = self.z_limit = None
        self._steps: tuple[str, ...] = ()
        self.in_background = where == "fork"        #: the checks run beside the field's measurement
        self._results: dict = {}
        if where is None:
            return
        args = (config_to_dict(cfg), str(cfg.base_dir))
        if where == "fork":
            import multiprocessing

            check_files(cfg)           # missing files: the one-line error at once, as serially
            _preimport()               # this process needs them too: imported once, before the fork
            self._own = cf.ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("fork"),
                initializer=_worker_init, initargs=(os.getpid(),))
            self._steps = ("check", "preflight", "z_limit")
            self._job = self._own.submit(_setup_job, *args, self._steps, dict(cache))
        else:
            self._steps = ("z_limit",)
            self._job = where.submit(_setup_job, *args, self._steps)
            # Spawned workers import glaciar and set up a field's settings and colour tables
            # when their first task arrives (~2 s each): jobs that only do that let up to
            # ``warm`` workers do it now, beside the set-up.
            for _ in range(max(0, warm - 1)):
                where.submit(_prewarm, *args)
        self.z_limit = _Later(self._step, "z_limit")

    def _step(self, name: str):
        if name in self._steps and not self._results:
            results, caught = self._job.result()
            self._results = results
            for message, category in caught:
                warnings.warn(message, category)
        if name in self._results:
            return self._results[name]
        if name == "check":
            return check_inputs(self._cfg, self._survey, self._cache), self._cache
        if name == "preflight":
            return placement_preflight(self._cfg, self._survey)
        return detection_z_limit(self._cfg)

    def inputs(self) -> dict:
        """:func:`check_inputs`'s result (raises its error); updates the fingerprint cache."""
        inputs, cache = self._step("check")
        if cache is not self._cache:
            self._cache.clear()
            self._cache.update(cache)
        return inputs

    def preflight(self) -> None:
        """Raise the preflight's error (no source fits a field) or warn its messages."""
        for message in self._step("preflight"):
            if "no source fits" in message:
                raise ValueError(message)
            warnings.warn(message, UserWarning)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if self._own is not None:
            if exc_type is not None:
                _terminate_workers(self._own)
            self._own.shutdown(wait=True, cancel_futures=True)
        return False


def prepare_run_dir(cfg: Config, run_dir: Path, seed: int) -> dict:
    """Create or validate the run directory and return its manifest.

    A store made with other science settings, another seed, changed input
    files (by content) or an older store format is refused.  A config that
    only adds (or drops) fields, grid values or iterations is accepted:
    finished tasks keep their rows, and the manifest and the stored config are
    updated to describe the run as now configured.  Nothing is created or
    modified unless every check passes.
    """
    manifest, lock = _open_run(cfg, Path(run_dir), seed)
    lock.release()
    return manifest


# --------------------------------------------------------------------------
# Worker processes: they die with the parent and leave interrupts to it
# --------------------------------------------------------------------------
_PR_SET_PDEATHSIG = 1


def _watch_parent(parent_pid: int, period: float = 0.5) -> None:
    while True:
        time.sleep(period)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGKILL)


def _worker_init(parent_pid: int) -> None:
    """Initializer of the process pool's workers.

    SIGINT is ignored (the parent handles Ctrl-C and terminates the workers),
    SIGTERM kills; on Linux the kernel sends SIGKILL when the parent dies
    (``PR_SET_PDEATHSIG``), and a watchdog thread checking the parent pid
    does the same elsewhere or if that call fails.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no libc prctl
            pass
    if os.getppid() != parent_pid:        # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True,
                     name="glaciar-parent-watchdog").start()


def _terminate_workers(ex: cf.ProcessPoolExecutor) -> None:
    """Stop a process pool's workers now (on an interrupt: their tasks are redone on resume)."""
    stop = getattr(ex, "terminate_workers", None)        # Python >= 3.14
    if stop is not None:
        stop()
        return
    for p in list((getattr(ex, "_processes", None) or {}).values()):
        try:
            p.terminate()
        except (OSError, ValueError, AttributeError):    # already gone
            pass


def _check_count(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def simulate(cfg: Config, run_dir, *, workers: int = 1, seed: int | None = None,
             executor: cf.Executor | None = None, progress: bool = True, mode: str = "windowed",
             max_tasks: int | None = None) -> dict:
    """Run (or resume) the injection-recovery simulation of a configuration.

    Parameters
    ----------
    cfg : Config
        Loaded configuration.
    run_dir : path
        Output directory (results store); finished tasks found there are skipped.
        While the run writes, it holds the directory's lock: a second run into
        the same directory is refused.
    workers : int
        Number of worker processes (>= 1; 1: run in this process).  Workers die
        with this process.  With ``executor``: how many of its workers to have
        import glaciar while this process checks the inputs (default 1).
    seed : int, optional
        Overrides ``simulation.seed`` (>= 0).
    executor : concurrent.futures.Executor, optional
        Any executor (e.g. a Dask ``Client.get_executor()``): it runs the tasks instead of a
        pool of ``workers`` processes.
    progress : bool
        Show a progress bar with ETA.
    mode : {"windowed", "full"}
        Detection mode.
    max_tasks : int, optional
        Run at most this many of the pending tasks (the rest stay pending for a resume).

    Returns
    -------
    dict
        ``n_tasks``, ``n_done_before``, ``n_run``, ``n_sources``; ``cpu_seconds`` [s]: inside
        the tasks (a worker's field set-up counted in its first task); ``process_cpu_seconds``
        [s]: this process and its pool workers, set-up, scheduling and compaction included (with
        ``executor``: this process plus its workers' CPU during their chunks, their imports
        excepted); ``wall_seconds`` [s]: the whole call, of which ``setup_seconds`` (inputs
        checked, field measured, manifest written: before the first task is submitted) and
        ``task_seconds`` (first submission to last result; the rest is the final compaction);
        ``remote_cpu_seconds`` [s]: the part of ``process_cpu_seconds`` measured in the
        workers of ``executor`` (0 without one).

    Raises
    ------
    ValueError
        Bad arguments or input files (:class:`InputError`), checked before anything is written.
    StoreMismatchError
        The run directory holds tasks made differently.
    glaciar.rundir.RunLockedError
        Another run is writing into ``run_dir``.
    """
    from tqdm.auto import tqdm

    run_dir = Path(run_dir)
    seed = _check_count("seed", cfg.simulation.seed if seed is None else seed, 0)
    if seed != cfg.simulation.seed:
        # The override is the run's seed everywhere, the box's points included (and the
        # run's stored config.yaml says so).
        cfg = cfg.model_copy(update={"simulation": cfg.simulation.model_copy(
            update={"seed": seed})})
    workers = _check_count("workers", workers, 1)
    if mode not in ("windowed", "full"):
        raise ValueError(f"mode: expected 'windowed' or 'full', got {mode!r}")
    if max_tasks is not None:
        max_tasks = _check_count("max_tasks", max_tasks, 0)
    c0, t0 = process_cpu_seconds(), time.perf_counter()
    _, lock = _open_run(cfg, run_dir, seed, parallel=_setup_parallelism(workers, executor),
                        warm=workers)
    try:
        stats = _simulate_locked(cfg, run_dir, seed, workers, executor, progress, mode,
                                 max_tasks, tqdm, t0)
    finally:
        lock.release()
    # Whole-process CPU: this process (checks, manifest, scheduling) and its pool workers
    # (reaped at the pool's shutdown, field set-up included); with another executor its
    # workers' CPU inside the chunks (tasks and field set-up; not their imports).
    stats["process_cpu_seconds"] = process_cpu_seconds() - c0 + stats["remote_cpu_seconds"]
    stats["wall_seconds"] = time.perf_counter() - t0
    return stats


def _setup_parallelism(workers: int, executor: cf.Executor | None) -> str | cf.Executor | None:
    """Where :func:`_open_run`'s side steps run (:class:`_SetupJobs`).

    A forked helper when >= 2 worker processes will run and forking is the
    default (the run's own pool, or a caller's process pool: submitting to it
    now would fork its workers before the field context exists, which they then
    inherit no longer); another executor (Dask) itself; serially otherwise (one
    worker: the steps would only compete with this process for the CPU; threads
    share one interpreter).
    """
    import multiprocessing

    method = multiprocessing.get_start_method(allow_none=True) or \
        multiprocessing.get_all_start_methods()[0]        # the default, without fixing it
    if isinstance(executor, cf.ProcessPoolExecutor):
        workers = getattr(executor, "_max_workers", 2)
        executor = None
    if isinstance(executor, cf.ThreadPoolExecutor):
        return None
    if executor is not None:
        return executor
    return "fork" if workers >= 2 and method == "fork" else None


def process_cpu_seconds(children: bool = True) -> float:
    """CPU [s] used so far by this process and (``children``) its terminated (reaped) child processes."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF)
    if not children:
        return own.ru_utime + own.ru_stime
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def placement_preflight(cfg: Config, survey: Survey) -> list[str]:
    """Fields where ``n_galaxies`` sources will not fit, one message each (before any task runs).

    Sizes are drawn as a task at the grid's lowest redshift and brightest
    magnitude would draw them (the largest sources of the run); the count that
    fits is :func:`glaciar.engine.positions.placement_capacity`'s random fill
    of that footprint. Tasks then place fewer sources; those that fit lean
    slightly toward small sizes when a crowded field ends the sequence early.
    """
    n = cfg.simulation.n_galaxies
    cells = task_cells(cfg)
    z, mag = min(z for _, z, _ in cells), min(m for _, _, m in cells)
    model = population.SourceModel(**cfg.source.model_dump())
    out = []
    for field in cfg.survey.fields:
        pixscale = survey.pixel_scale_arcsec(field)
        psfs = [_band_psf(cfg, b, pixscale) for b in cfg.survey.bands]
        bands = tuple(b.name for b in cfg.survey.bands)
        lite = FieldContext(
            field=field, bands=bands, detection_band=cfg.survey.detection_band,
            detection_index=bands.index(cfg.survey.detection_band), shape=survey.shape(field),
            pixel_scale_arcsec=pixscale, zeropoints={}, gains={},
            filters=[_resolve_filter(b.filter, cfg.base_dir) for b in cfg.survey.bands],
            bases={}, rms={}, mask=None, footprint=None, depth=None, reference=None, cache=None,
            isolation_margin_pix=int(math.ceil(2.0 * max(measure_fwhm(p, 1.0) for p in psfs))),
            source_model=model, cosmology=population.get_cosmology(model.cosmology),
            magnitude_type=cfg.grid.magnitude_type, n_galaxies=n, detection_params=None,
            classification_params=None, selection=None, enclosed_fraction=model.stamp_flux_fraction,
            isolation_fraction=cfg.simulation.isolation_fraction)
        src = draw_task_sources(np.random.default_rng(0), n, z, mag, lite)
        hh, hw = lite.stamp_half_sizes(src.sersic_n, src.r_eff_pix, src.axis_ratio,
                                       src.position_angle_deg)
        cap = placement_capacity(survey.footprint(field), hh, hw)
        if cap.upper_bound == 0:
            out.append(f"field {field!r}: no source fits in its footprint (no pixel with data in "
                       f"every band of survey.coverage, outside survey.mask)")
        elif cap.random_fill < n:
            out.append(f"field {field!r}: about {cap.random_fill} of simulation.n_galaxies = {n} "
                       f"sources fit per task at z = {z:g}, mag = {mag:g} (at most "
                       f"{cap.upper_bound}); tasks will place fewer (lower n_galaxies and raise "
                       "n_iterations to keep the count)")
    return out


def _simulate_locked(cfg, run_dir, seed, workers, executor, progress, mode, max_tasks, tqdm,
                     t_start):
    specs = plan_tasks(cfg)
    wanted = {spec_filename(s): spec_key(s) for s in specs}
    finished = verified_task_names(run_dir, wanted, quarantine=True)
    pending = [s for s in specs if spec_filename(s) not in finished]
    n_done_before = len(specs) - len(pending)
    if max_tasks is not None:
        pending = pending[:max_tasks]
    cfg_dict = config_to_dict(cfg)
    base_dir = str(cfg.base_dir)
    cfg_hash = config_hash(cfg)
    _prepare_context_cache(run_dir, cfg, cfg_hash, {s.field for s in pending})
    n_workers = 1 if executor is None and workers <= 1 else max(1, workers)
    chunks = _chunks(pending, n_workers)
    stats = {"n_tasks": len(specs), "n_done_before": n_done_before, "n_run": 0, "n_sources": 0,
             "cpu_seconds": 0.0, "remote_cpu_seconds": 0.0}
    bar = tqdm(total=len(pending), unit="task", disable=not progress, desc="simulate")

    def account(result):
        for _name, rows, cpu in result:
            stats["n_run"] += 1
            stats["n_sources"] += rows
            stats["cpu_seconds"] += cpu
        bar.update(len(result))
        # Bound the number of loose task files of a long run (glaciar.store: Compaction).
        if stats["n_run"] // COMPACT_EVERY > account.compactions:
            account.compactions = stats["n_run"] // COMPACT_EVERY
            compact(run_dir, min_tasks=COMPACT_EVERY)
    account.compactions = 0

    t0 = time.perf_counter()
    try:
        if executor is None and n_workers == 1:
            for ch in chunks:
                account(_run_chunk(cfg_dict, base_dir, cfg_hash, str(run_dir), seed, ch, mode))
        elif chunks:
            own = executor is None
            ex = executor or cf.ProcessPoolExecutor(max_workers=n_workers, initializer=_worker_init,
                                                    initargs=(os.getpid(),))
            try:
                futs = [ex.submit(_run_chunk_measured, cfg_dict, base_dir, cfg_hash, str(run_dir),
                                  seed, ch, mode) for ch in chunks]
                # The workers exist now (a forked pool starts them all at the first
                # submission, with this process's field context): this process runs no
                # task, so it lets its copy go.
                _CONTEXTS.clear()
                for fut in cf.as_completed(futs):
                    done, pid, cpu = fut.result()
                    # Our own pool's workers are reaped (RUSAGE_CHILDREN) and a thread's CPU
                    # is this process's: only other executors' processes are added.
                    if not own and pid != os.getpid():
                        stats["remote_cpu_seconds"] += cpu
                    account(done)
            except KeyboardInterrupt:
                if own:
                    _terminate_workers(ex)
                raise
            finally:
                if own:
                    ex.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()
    stats["setup_seconds"] = t0 - t_start
    stats["task_seconds"] = time.perf_counter() - t0
    compact(run_dir, min_tasks=COMPACT_EVERY)
    _finish_context_cache(run_dir, n_done_before + stats["n_run"] == len(specs))
    return stats


def default_workers() -> int:
    """Worker processes to use by default: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)
