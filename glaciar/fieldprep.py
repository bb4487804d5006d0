"""Field preparation: a field's pixels read and measured once, before any task.

Band pixels (background-subtracted image and the noise RMS its WEIGHT_TYPE gives),
local depth, the correlated-noise model from empty apertures, and the
:class:`~glaciar.engine.context.FieldContext` a task runs on
(:func:`build_field_context`); the manifest's per-field depth and noise records.
Reads the survey's images; writes nothing (:mod:`glaciar.contexts` puts contexts on disk).
"""
from __future__ import annotations

import dataclasses
import math
import os
import warnings
from pathlib import Path

import numpy as np

from . import constants as C
from .config import Config
from .engine.detect import (DetectionParams, background_model, builtin_filter, read_conv_file,
                            release_mapped, sanitize)
from .engine.measure import reference_extraction
from .engine.reference import strip_reference, strip_reference_applies
from .engine.blocks import row_blocks
from .engine.classify import ClassificationParams
from .engine.coadd import coadd
from .engine import fieldcache
from .engine.context import FieldContext
from .engine.depth import depth_area_histogram, local_depth_map
from .engine.noise import (MAX_RISE_EXPONENT, CorrelatedNoise, background_excess, empty_aperture_scatter,
                           empty_sky, rise_exponent, source_margin, weight_rescale_factor)
from .config.user_selection import engine_selection
from .engine.task import field_key
from .galaxy import population
from .galaxy.filters import get_filter
from .galaxy.psf import measure_fwhm, prepare_psf
from .galaxy.templates import TemplateCache
from .lensmaps import LazyFieldLens
from .survey import Survey, clear_cache as clear_survey_cache


def resolve_filter(spec: str, base_dir: Path):
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
    base, r, from_background, back = band_pixels_with_background(
        survey, field, band, footprint, params, weight_type)
    if background is not None:
        background[band] = back()
    return base, r, from_background


def band_pixels_with_background(survey: Survey, field: str, band: str, footprint: np.ndarray,
                                params: DetectionParams, weight_type: str | None = None, keep=None):
    """:func:`band_pixels`, with the subtracted background map made only when asked for.

    ``keep`` (optional) puts a finished full-frame array away and returns what stands for
    it (a large field's spill to disk).  With it, and a noise map used as it is
    (WEIGHT_TYPE none or MAP_RMS), the noise map is read twice -- for the no-data mask
    before the image is read, for the RMS once the image is put away -- so the band never
    holds its image and its noise map at once (same values: the mask is the same
    pixelwise test, split in two passes).

    Returns
    -------
    base, rms, rms_from_background
        As :func:`band_pixels` (``base`` already kept when ``keep`` was used on it).
    background : callable
        Returns the subtracted sep background map (float32, image units); sep's
        Background keeps its meshes only, so a caller that first puts ``base`` and ``rms``
        away (a large field spills them) adds one full-frame array to a lower peak.
    """
    late_noise = keep is not None and weight_type in (None, "map_rms") \
        and survey.noise_path(field, band) is not None
    def usable_noise(nz):
        return np.isfinite(nz) & (nz > 0)

    # New arrays read for this call (not the survey's cached ones): worked on in place, so
    # the band costs its image, its noise map and the masks, with no full-frame copies.
    noise = survey.rms(field, band, cache=False)
    nodata = None
    if late_noise:
        # The noise map's part of the mask first; the map goes before the image comes.
        nodata = np.empty(noise.shape, dtype=bool)
        for y0, y1, _, _ in row_blocks(noise.shape, ROW_BLOCK_PIXELS):
            nz = noise[y0:y1]
            np.logical_not(usable_noise(nz), out=nodata[y0:y1])
        noise = nz = None               # (the last block's view would keep the map alive)
    img = survey.science(field, band, cache=False)
    # nodata = ~(footprint & finite image & finite, positive noise), by blocks of rows.
    if nodata is None:
        nodata = np.zeros(img.shape, dtype=bool)
    for y0, y1, _, _ in row_blocks(img.shape, ROW_BLOCK_PIXELS):
        ok = np.asarray(footprint[y0:y1], dtype=bool) & np.isfinite(img[y0:y1])
        if noise is not None:
            ok &= usable_noise(noise[y0:y1])
        nodata[y0:y1] |= ~ok
        release_mapped(footprint)       # a spilled footprint's pages, read once
    in_place = img.dtype == np.float32
    if in_place:
        # sanitize(img, None, nodata) on img itself: nodata holds every non-finite pixel.
        img[nodata] = 0.0
        data = img
    else:
        data = sanitize(img, None, nodata)[0]
    bkg = background_model(data, nodata, params)

    def rms_of(noise_map):
        r, from_background = noise_rms(noise_map, weight_type, lambda: bkg.rms(dtype=np.float32),
                                       nodata)
        r = np.asarray(r).astype(np.float32, copy=False)
        r[nodata] = np.float32(np.inf)          # = np.where(valid, r, inf), in place
        return r, from_background

    if not late_noise:
        r, from_background = rms_of(noise)
        del noise
    back = None if in_place else bkg.back(dtype=np.float32)
    if in_place:
        # data holds img where valid: the same float32 differences as img - background
        # (sep subtracts its own float32 map, row by row; no full-frame map is made here).
        bkg.subfrom(data)
        base = data
    else:
        base = np.subtract(img, back)
    del img, data
    base[nodata] = 0.0
    base = base.astype(np.float32, copy=False)
    if late_noise:
        base = keep(base)
        r, from_background = rms_of(survey.rms(field, band, cache=False))
    # sep's Background keeps its meshes only: the map is made when asked for.
    return base, r, from_background, (lambda: bkg.back(dtype=np.float32)) if back is None else (lambda: back)


def noise_rms(noise: np.ndarray | None, weight_type: str | None, background_rms, nodata: np.ndarray
              ) -> tuple[np.ndarray, bool]:
    """The noise RMS a band is detected and measured with, by SExtractor's WEIGHT_TYPE.

    Parameters
    ----------
    noise : ndarray or None
        RMS from the band's noise map [image units] (a weight map already made
        ``1/sqrt(weight)`` by :meth:`glaciar.survey.Survey.rms`), or None without a map.
    weight_type : {None, "map_weight", "map_rms", "background"}
        None and ``map_rms``: the map is absolute; ``map_weight``: it is scaled by one
        factor to the pixel noise measured on the image
        (:func:`glaciar.engine.noise.weight_rescale_factor`); ``background``: not used.
    background_rms : callable
        Returns sep's background RMS map [image units] (called only when needed).
    nodata : ndarray of bool
        Pixels without data (left out of the MAP_WEIGHT factor).

    Returns
    -------
    rms : ndarray
        [image units]; ``noise`` itself for an absolute map.
    from_background : bool
        True when ``rms`` is sep's background RMS (:func:`rms_from_background`).
    """
    if noise is None or weight_type == "background":
        return background_rms(), True
    if weight_type == "map_weight":
        return noise * weight_rescale_factor(background_rms(), noise, ~nodata), False
    return noise, False


def rms_from_background(survey: Survey, field: str, band: str, weight_type: str | None) -> bool:
    """Whether a band's noise is sep's background RMS (no noise map, or WEIGHT_TYPE BACKGROUND):
    :func:`noise_rms`'s choice, known from the configuration alone."""
    return survey.noise_path(field, band) is None or weight_type == "background"


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


def detection_params(cfg: Config) -> DetectionParams:
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


def band_psf(cfg: Config, band, pixscale: float) -> np.ndarray:
    if band.psf is None:
        raise ValueError(f"survey.bands.{band.name}.psf: a PSF (FITS path or analytic profile) is required")
    return prepare_psf(band.psf, pixscale, base_dir=cfg.base_dir,
                       psf_pixel_scale_arcsec=band.psf_pixel_scale_arcsec)


#: Pixels around every detected original source left out of the empty apertures.
_EMPTY_SKY_MARGIN_PIX = 3


def correlated_noise(cfg: Config, field: str, band: str, base: np.ndarray, rms: np.ndarray,
                     segmap: np.ndarray, sky: dict | None = None,
                     release=None, keep=None) -> CorrelatedNoise:
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
    ``keep``: maps the dilated source mask to what ``sky`` holds (a large field's caller
    spills it to disk: it is read by row blocks, and would otherwise stay resident beside
    the distance transform's buffers and the aperture centres).
    """
    release = release or (lambda: None)
    sky = {} if sky is None else sky
    if "sources" not in sky:
        sources = source_margin(segmap, _EMPTY_SKY_MARGIN_PIX)
        sky["sources"] = sources if keep is None else keep(sources)
        del sources
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
            from_background = rms_from_background(survey, field, b.name,
                                                  cfg.detection.weight_type)
            out[b.name] = _noise_entry(cfg, survey, field, b.name, ctx.rms[b.name],
                                       from_background, ctx.measured_noise[b.name])
        return out
    params = detection_params(cfg)
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


#: The last :class:`~glaciar.galaxy.templates.TemplateCache` :func:`shared_template_cache` made
#: in this process, with what it was made from: ``(enclosed_fraction, psfs, cache)``.
_LAST_TEMPLATES: list = []


def shared_template_cache(psfs: dict, enclosed_fraction: float) -> TemplateCache:
    """A :class:`~glaciar.galaxy.templates.TemplateCache` for these PSFs, shared by the fields
    of a process that have the same ones.

    A stamp is a pure function of its band's PSF, the source's shape and its sub-pixel
    offset (the cache's exact key), so fields with the same PSF arrays (value for value,
    e.g. one pixel scale) can use one cache: the stamps one field rendered serve the next
    (each (field, z) chunk of tasks used to fill a cache of its own, ~0.8 s of CPU per chunk
    on the demo), with the same bits.  Only the last cache is kept (a process holds one
    field's context at a time; the cache's own byte budget bounds it).

    Parameters
    ----------
    psfs : dict of str to ndarray
        Band -> PSF at the image pixel scale (:func:`band_psf`).
    enclosed_fraction : float
        The stamps' light fraction (``SourceModel.stamp_flux_fraction``).
    """
    frac = float(enclosed_fraction)
    if _LAST_TEMPLATES:
        last_frac, last_psfs, cache = _LAST_TEMPLATES
        if last_frac == frac and list(last_psfs) == list(psfs) and all(
                last_psfs[b].dtype == psfs[b].dtype and last_psfs[b].shape == psfs[b].shape
                and np.array_equal(last_psfs[b], psfs[b]) for b in psfs):
            return cache
    cache = TemplateCache(psfs, enclosed_fraction=frac)
    _LAST_TEMPLATES[:] = [frac, {b: np.array(a, copy=True) for b, a in psfs.items()}, cache]
    return cache


def release_template_cache() -> None:
    """Forget the cache :func:`shared_template_cache` keeps (its stamps and, with them, their
    shot-noise splits: :mod:`glaciar.engine.shotnoise`); the next call makes a new one."""
    _LAST_TEMPLATES.clear()


def field_settings(cfg: Config, survey: Survey, field: str) -> tuple[dict, dict]:
    """The context fields that follow from the configuration (no pixel is read), and the PSFs.

    Everything of a :class:`~glaciar.engine.context.FieldContext` but its measured fields
    (:attr:`FieldContext.MEASURED`): what a process that opens a field cache
    (:func:`glaciar.contexts.open_field_context`) sets up itself.
    """
    bands = tuple(b.name for b in cfg.survey.bands)
    det = cfg.survey.detection_band
    pixscale = survey.pixel_scale_arcsec(field)
    psfs = {b.name: band_psf(cfg, b, pixscale) for b in cfg.survey.bands}
    model = population.SourceModel(**cfg.source.model_dump())
    settings = dict(
        field=field, bands=bands, detection_band=det, detection_index=bands.index(det),
        shape=survey.shape(field), pixel_scale_arcsec=pixscale,
        zeropoints={b.name: float(b.zeropoint) for b in cfg.survey.bands},
        gains={b.name: (None if b.gain is None else float(b.gain)) for b in cfg.survey.bands},
        filters=[resolve_filter(b.filter, cfg.base_dir) for b in cfg.survey.bands],
        cache=shared_template_cache(psfs, model.stamp_flux_fraction),
        isolation_margin_pix=int(math.ceil(2.0 * max(measure_fwhm(p, 1.0) for p in psfs.values()))),
        source_model=model, cosmology=population.get_cosmology(model.cosmology),
        magnitude_type=cfg.grid.magnitude_type, n_galaxies=cfg.simulation.n_galaxies,
        detection_params=detection_params(cfg),
        classification_params=ClassificationParams(**cfg.classification.model_dump()),
        selection=engine_selection(cfg),
        enclosed_fraction=model.stamp_flux_fraction,
        isolation_fraction=cfg.simulation.isolation_fraction)
    if cfg.survey.lens is not None:     # the lens maps are read on a task's first use
        settings["lens"] = LazyFieldLens(cfg, survey, field)
    return settings, psfs


#: A field whose images and RMS maps (float32, every band) exceed this [bytes] is measured
#: with each finished full-frame array spilled to disk (glaciar.engine.fieldcache.spill):
#: the measuring process then holds one step's work arrays, not the whole context
#: (~45 bytes per pixel for 4 bands, 11 GB on a 16000^2 mosaic).
SPILL_MIN_BYTES = 1 << 30

#: Run a large (spilled) field's reference extraction by row strips
#: (:func:`glaciar.engine.reference.strip_reference`, bit for bit the whole-frame result)
#: when its settings allow (sep, CLEAN within regions or off, the convolution filter or
#: none, the per-pixel RMS threshold).  On the 16000^2 demo its step peaks at 1.8 GB against
#: 3.8-3.9 GB for sep on the whole frame, for 2.2-2.5x its CPU (issue 24; docs/limitations.md).
REFERENCE_BY_STRIPS = True


def _reference(spilled, image, rms, params, zeropoint, mask, photometry=None):
    """The field's reference extraction: by row strips on a large (spilled) field whose
    settings they reproduce bit for bit when :data:`REFERENCE_BY_STRIPS`
    (:func:`glaciar.engine.reference.strip_reference`: sep with CLEAN within regions or off,
    the convolution filter), else sep on the whole frame."""
    if REFERENCE_BY_STRIPS and spilled and strip_reference_applies(params):
        return strip_reference(image, rms, params, zeropoint, mask=mask, photometry=photometry)
    return reference_extraction(image, rms, params, zeropoint, mask=mask, photometry=photometry)


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
    settings, psfs = field_settings(cfg, survey, field)
    _step_done("settings")
    bands = settings["bands"]
    det = cfg.survey.detection_band
    params = settings["detection_params"]
    ny, nx = settings["shape"]
    spilled: list = []

    def keep(a):
        """``a`` itself, or on a large field ``a`` on disk (its pages dropped until read)."""
        if not isinstance(a, np.ndarray) or isinstance(a, np.memmap) \
                or 8 * len(bands) * ny * nx <= SPILL_MIN_BYTES:
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
        base, noise, _, back = band_pixels_with_background(
            survey, field, b.name, footprint, params, cfg.detection.weight_type,
            keep=keep if isinstance(footprint, np.memmap) else None)
        bases[b.name], rms[b.name] = keep(base), keep(noise)
        del base, noise
        if b.name == det:
            # Made now, the band's image and RMS put away (on disk for a large field).
            backgrounds[det] = keep(back())
        del back
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
        reference = _reference(spilled, det_image, det_image_rms, params, zps[det], mask,
                               photometry=(bases[det], rms[det]))
        del det_image
    else:
        reference = _reference(spilled, bases[det], rms[det], params, zps[det], mask)
    seg = getattr(reference, "segmap", None)
    if isinstance(seg, np.memmap) and getattr(seg, "_mmap", None) is not None:
        spilled.append(seg._mmap)       # written on disk by strips: dropped with the others
    elif spilled and isinstance(seg, np.ndarray):
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
                                           release=drop, keep=keep)
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


def field_depth_area(cfg: Config, survey: Survey, field: str, ctx: FieldContext | None = None) -> dict:
    """The manifest's footprint area by local depth of one field (one FFT; main process only).

    Warns when the depth comes from sep's background RMS (no noise map): once
    per field and run, here, rather than in every worker that builds the field.
    ``ctx``: the field's context, if built (its depth map is this one).
    """
    det = cfg.survey.detection_band
    band = cfg.survey.band(det)
    pixscale = survey.pixel_scale_arcsec(field)
    if ctx is not None:
        from_background = rms_from_background(survey, field, det, cfg.detection.weight_type)
    else:
        _, rms, from_background = band_pixels(survey, field, det, survey.footprint(field),
                                              detection_params(cfg), cfg.detection.weight_type)
    if from_background:
        warnings.warn(f"field {field!r}: no noise map for the detection band {det!r}; its local "
                      "depth (column depth_local, manifest depth_area) comes from sep's background "
                      "RMS mesh", UserWarning)
    psf = band_psf(cfg, band, pixscale)
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
