"""Detect, classify and measure injected sources: the one entry point a task calls.

:func:`measure_injected` validates its inputs, chooses the segmentation
backend -- glaciar's exact windowed (or full-frame) sep segmentation
(:mod:`glaciar.engine.windows`) or the SExtractor binary on the full frame
(:mod:`glaciar.engine.sextractor_backend`) -- and runs classification and
photometry on the product either returns (:class:`~glaciar.engine.segmentation.SegmentedBatch`),
with the same code for every backend.  :func:`reference_extraction` segments
and measures the original image once per field.

Windowed ≡ full frame is kept exact for the default detection settings (and
``threshold_rms="filtered"``).  Settings whose exactness would cost more machinery
than their users gain run full frame whatever the mode asked for
(:func:`runs_full_frame`): a task-wide CLEAN (``clean_style`` other than
``"region"``, CLEAN on), whose outcome depends on the whole image's object list,
is the full-frame product of the injected image
(:func:`glaciar.engine.segmentation.sep_segmentation`), measured as the SExtractor
backend's; a matched filter (noise-aware: its detection mask is reproduced only
up to rounding) runs the full-frame sep path.

The reference (original-image) extraction is, for ``clean_style="region"``,
a plain full-frame sep run with CLEAN as configured; for the task-wide CLEAN
styles, glaciar's segmentation product of the original image
(:func:`~glaciar.engine.segmentation.sep_segmentation`: canonical deblending,
the same CLEAN); with ``backend="source-extractor"``, SExtractor's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy import ndimage

from glaciar.constants import COL_FLAGS, FLAG_SATURATED, FLAG_SEP_ERROR, STATUS_NOT_DETECTED, band_column
from glaciar.engine import sepscan
from glaciar.engine.blocks import row_tiles
from glaciar.engine.canvas import (Canvas, MeasureContext, ObjectBoxes, ellipse_boxes, ellipse_half_extent,
                                   safe_shape, window_groups)
from glaciar.engine import photometry as phot
from glaciar.engine.classify import ClassificationParams, classify, footprint_overlap, select_detection
from glaciar.engine.detect import DetectionError, DetectionParams, sep_extract, detection_rms, sanitize
from glaciar.engine.scene import Scene
from glaciar.engine.segmentation import SegmentedBatch, sep_extract_clean, sep_segmentation
from glaciar.engine.windows import REMOVED, segment_full, segment_windowed

__all__ = ["FieldReference", "MeasureSetup", "reference_extraction", "reference_boxes", "measure_injected",
           "output_columns", "total_magnitudes", "runs_full_frame"]


@dataclass(frozen=True, eq=False)
class FieldReference:
    """Extraction of the original detection image, once per field.

    Attributes
    ----------
    segmap : ndarray of int32
        Full-frame segmentation of the original detection image.
    flux : ndarray
        Detection-band AUTO flux per original id (index id - 1) [image units].
    mag : ndarray
        AUTO magnitude per original id (detection zeropoint); NaN for flux <= 0.
    catalog : structured ndarray or None
        sep's catalogue (row id - 1).
    objects : ObjectBoxes or None
        Per original id (row id - 1), image boxes (y0, y1, x0, x1): the
        connected above-threshold region holding the object, and that region
        widened by the object's Kron (6 a, 6 b) and AUTO ellipses.  Only used
        to size the first detection window of an injected source near it
        (:func:`glaciar.engine.windows.initial_windows`): a guess, never an
        answer.  None: first windows of the default size.
    """

    segmap: np.ndarray
    flux: np.ndarray
    mag: np.ndarray
    catalog: np.ndarray | None = None
    objects: ObjectBoxes | None = None


def reference_extraction(det_image_sub, det_rms, params: DetectionParams, zeropoint: float,
                         mask=None, photometry=None, backend: str | None = None) -> FieldReference:
    """Extract the original (un-injected) detection image once per field.

    Parameters
    ----------
    det_image_sub : ndarray
        Background-subtracted original detection image [image units].
    det_rms : ndarray
        Per-pixel RMS [image units].
    params : DetectionParams
    zeropoint : float
        AB zeropoint of the detection image.
    mask : ndarray of bool, optional
        True where there are no data.
    photometry : (image, rms), optional
        The band whose AUTO magnitudes the original sources get when it is not
        the detection image (a coadded detection image: fluxes in the
        detection *band*, the band ``zeropoint`` belongs to).
    backend : {"sep", "source-extractor"}, optional
        Default ``params.backend``.  Who segments the original image: glaciar's sep product
        (:func:`~glaciar.engine.segmentation.sep_segmentation`, whose CLEAN
        is task-wide for the styles other than ``"region"``) or the
        SExtractor binary (for ``mode="source-extractor"``).

    Returns
    -------
    FieldReference
        Segmentation map and AUTO flux/magnitude per original source
        (MAG_AUTO as SExtractor: Kron factor and minimum radius from
        ``params.phot_autoparams``; neighbours masked).
    """
    backend = params.backend if backend is None else backend
    if backend == "sep" and params.clean_style != "region":
        # sanitize is idempotent, so the segmentation may sanitize the inputs itself: the
        # copies the photometry needs are made after its full-frame peak, not during it.
        prod = sep_segmentation(det_image_sub, det_rms, params, mask=mask)
        cat = prod.cat[np.flatnonzero(prod.owner == np.arange(len(prod.owner)))] if len(prod.cat) else prod.cat
        data, err, nodata = sanitize(det_image_sub, det_rms, mask)
        geo = {f: np.asarray(getattr(prod, f), dtype=np.float64) for f in ("x", "y", "a", "b", "theta")}
        return _reference_photometry(data, err, nodata, prod.seg, geo, params, zeropoint, mask, photometry, cat)
    data, err, nodata = sanitize(det_image_sub, det_rms, mask)
    if backend == "sep" and params.clean_style == "region":
        # CLEAN within regions: the reference is a plain full-frame sep run with
        # CLEAN as configured (no pre-CLEAN object list: no task-wide CLEAN needs it).
        # sep's own CLEAN is quadratic in the number of objects: on large fields the same
        # result comes from sep without CLEAN plus glaciar's (sep_extract_clean).
        e = detection_rms(err, nodata, params)
        cat, seg = sep_extract_clean(data, e, nodata, params) if params.clean else \
            sep_extract(data, e, nodata, params, False)
        del e
        geo = {f: np.asarray(cat[f], dtype=np.float64) for f in ("x", "y", "a", "b", "theta")}
        return _reference_photometry(data, err, nodata, seg, geo, params, zeropoint, mask, photometry, cat)
    if backend == "source-extractor":
        from glaciar.engine.sextractor_backend import sextractor_segmentation
        prod = sextractor_segmentation(data, err, params, mask=nodata)
        cat = None
    else:
        raise ValueError(f"backend must be 'sep' or 'source-extractor', got {backend!r}")
    geo = {f: np.asarray(getattr(prod, f), dtype=np.float64) for f in ("x", "y", "a", "b", "theta")}
    return _reference_photometry(data, err, nodata, prod.seg, geo, params, zeropoint, mask, photometry, cat)


def _reference_photometry(data, err, nodata, seg, geo, params, zeropoint, mask, photometry, cat):
    """AUTO flux and magnitude of every object of an original image's segmentation."""
    n = geo["x"].size
    if n == 0:
        return FieldReference(seg, np.zeros(0), np.zeros(0), cat)
    ids = np.arange(1, n + 1, dtype=np.int32)
    a, b, th = safe_shape(geo["a"], geo["b"], geo["theta"])
    kr = phot.kron_radius(data, geo["x"], geo["y"], a, b, th, segmap=seg, seg_id=ids, mask=nodata)
    scale = phot.auto_scale(kr, params.phot_autoparams)
    data_det, err_det, nodata_det = data, err, nodata
    if photometry is not None:
        data, err, nodata = sanitize(photometry[0], photometry[1], mask)
    flux, _ = phot.auto_photometry(data, err, phot.Ellipses(geo["x"], geo["y"], a, b, th, scale),
                                   segmap=seg, seg_id=ids, mask=nodata)
    mag, _, _ = phot.magnitudes(flux, np.ones_like(flux), zeropoint)
    region_box, need_box = reference_boxes(data_det, err_det, nodata_det, seg, geo, a, b, th, scale, params)
    return FieldReference(seg, flux, mag, cat, ObjectBoxes.build(region_box, need_box, seg.shape))


def reference_boxes(data, err, nodata, seg, geo, a, b, th, scale, params):
    """Region box and Kron/AUTO-widened box of every original object (see
    :class:`FieldReference`'s ``objects``); the arrays are read by row slices only (they
    may be row readers)."""
    n = geo["x"].size
    region = _region_boxes(data, err, nodata, seg, params, n)
    need = region.copy()
    for r in (np.full(n, 6.0), np.nan_to_num(scale, nan=0.0)):    # the boxes _analyse checks
        box = ellipse_boxes(geo["x"], geo["y"], *ellipse_half_extent(a, b, th, r))
        need[:, 0::2] = np.minimum(need[:, 0::2], box[:, 0::2])
        need[:, 1::2] = np.maximum(need[:, 1::2], box[:, 1::2])
    return region, need


def _region_boxes(data, err, nodata, seg, params, n):
    """Per object id 1..n, the box (y0, y1, x0, x1) of the 8-connected component of
    (sep's detection mask | segmentation) holding its pixels; (0, 0, 0, 0) without pixels.

    By row tiles, with no full-frame mask or label image: the detection mask of a tile
    with the filter's half-height of rows around it is its rows' mask bit for bit; the
    tile's components are labelled on their own and joined across tile boundaries (a
    pixel of a tile's last row touches the three below it in the next tile's first row),
    so the components, and their boxes, are those of the whole frame.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nx = seg.shape[1]
    eight = np.ones((3, 3), dtype=bool)
    boxes = [np.zeros((1, 4), dtype=np.int64)]            # label 0: no component
    obj_label = np.zeros(n + 1, dtype=np.int64)
    join_a, join_b = [], []
    prev_last, offset = None, 0
    for y0, y1, ya, yb in row_tiles(seg.shape, params.filter_halfwidth):
        d, e, nd = np.asarray(data[ya:yb], dtype=np.float32), err[ya:yb], nodata[ya:yb]
        m = sepscan.detection_mask(d, detection_rms(e, nd, params), nd, params)[0][y0 - ya:y1 - ya]
        s = np.asarray(seg[y0:y1])
        m |= s > 0
        lab, k = ndimage.label(m, structure=eight)
        del m
        sl = ndimage.find_objects(lab)
        bx = np.array([(q[0].start + y0, q[0].stop + y0, q[1].start, q[1].stop) for q in sl],
                      dtype=np.int64).reshape(-1, 4)
        boxes.append(bx)
        np.add(lab, offset, out=lab, where=lab > 0)        # labels unique over the frame
        first = lab[0]
        if prev_last is not None:
            for dx in (-1, 0, 1):                          # previous row's x meets this row's x + dx
                p = prev_last[max(0, -dx):nx - max(0, dx)]
                c = first[max(0, dx):nx - max(0, -dx)]
                ok = (p > 0) & (c > 0)
                join_a.append(p[ok])
                join_b.append(c[ok])
        prev_last = lab[-1].copy()
        on = s > 0
        obj_label[s[on]] = lab[on]
        offset += k
    n_lab = offset + 1
    a = np.concatenate(join_a) if join_a else np.zeros(0, np.int64)
    b = np.concatenate(join_b) if join_b else np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(n_lab, n_lab))
    n_comp, comp = connected_components(graph, directed=False)
    lab_box = np.concatenate(boxes)
    big = np.iinfo(np.int64).max
    cb = np.empty((n_comp, 4), dtype=np.int64)
    cb[:, 0::2], cb[:, 1::2] = big, -big
    np.minimum.at(cb[:, 0], comp, lab_box[:, 0])
    np.maximum.at(cb[:, 1], comp, lab_box[:, 1])
    np.minimum.at(cb[:, 2], comp, lab_box[:, 2])
    np.maximum.at(cb[:, 3], comp, lab_box[:, 3])
    cb[comp[0]] = 0                                       # label 0 is alone in its component
    return cb[comp[obj_label[1:]]]


def output_columns(bands, n_apertures: int) -> list[str]:
    """Names of the per-source columns :func:`measure_injected` returns."""
    cols = ["status", "detection_id", COL_FLAGS, "overlap_fraction", "blend_original_id",
            "blend_original_mag", "x_det", "y_det", "flux_auto_template"]
    for b in bands:
        q = ["flux_iso", "fluxerr_iso", "flux_auto", "fluxerr_auto"]
        for k in range(n_apertures):
            q += [f"flux_aper{k}", f"fluxerr_aper{k}"]
        q += ["mag", "magerr", "sn", "maglim", "mag_auto", "magerr_auto"]
        cols += [band_column(x, b) for x in q]
    return cols


@dataclass(frozen=True, eq=False)
class MeasureSetup:
    """What every :func:`measure_injected` call on one field shares (read only).

    Attributes
    ----------
    band_rms : mapping band -> ndarray
        RMS map of every measured band, the detection band included [image units].
    reference : FieldReference
        Original-image extraction of this field.
    params : DetectionParams
    classification : ClassificationParams
    zeropoints : mapping band -> float
        AB zeropoints [mag].
    gains : mapping band -> float or None
        Gains [e-/image unit] (None: no Poisson term).
    detection_band : str
    mask : ndarray of bool, optional
        True where there are no data (all bands).
    noise_models : mapping band -> glaciar.engine.noise.CorrelatedNoise, optional
        Correlated-noise models: the background variance of every ISO,
        aperture and AUTO error in that band is scaled by ``r(N)^2``.
    det_background : ndarray, optional
        Background map of the detection band [image units] (what was
        subtracted from its image): a detection is flagged
        ``FLAG_SATURATED`` when its peak plus the background at its centre
        reaches ``params.satur_level`` (SExtractor's rule); None = 0.
    """

    band_rms: Mapping[str, np.ndarray]
    reference: FieldReference
    params: DetectionParams
    classification: ClassificationParams
    zeropoints: Mapping[str, float]
    gains: Mapping[str, float | None]
    detection_band: str
    mask: np.ndarray | None = None
    noise_models: Mapping | None = None
    det_background: np.ndarray | None = None

    @classmethod
    def of_field(cls, ctx) -> "MeasureSetup":
        """The setup of a :class:`~glaciar.engine.context.FieldContext` (tasks and the
        catalogue measure with the same one)."""
        return cls(band_rms=ctx.rms, reference=ctx.reference, params=ctx.detection_params,
                   classification=ctx.classification_params, zeropoints=ctx.zeropoints,
                   gains=ctx.gains, detection_band=ctx.detection_band, mask=ctx.mask,
                   noise_models=getattr(ctx, "noise_models", None),
                   det_background=getattr(ctx, "detection_background", None))


def measure_injected(setup: MeasureSetup, det_scene: Scene, det_rms: np.ndarray,
                     band_scenes: Mapping[str, Scene], x: np.ndarray, y: np.ndarray,
                     input_flux_det: np.ndarray, input_mag_det: np.ndarray, *,
                     mode: str = "windowed", diagnostics: dict | None = None, input_templates=None,
                     early_exit: bool = True) -> dict[str, np.ndarray]:
    """Detect, classify and measure N injected sources.

    Parameters
    ----------
    setup : MeasureSetup
        The field's RMS maps, reference extraction, settings, zeropoints, gains,
        mask, noise models and detection background.
    det_scene : Scene
        Background-subtracted original detection image + injected stamps.
    det_rms : ndarray
        RMS of the original detection image [image units] (detection threshold
        and ISO errors).
    band_scenes : mapping band -> Scene
        Every measured band, the detection band included.
    x, y : array of float, shape (N,)
        Input positions, 0-based pixels (x along numpy axis 1).
    input_flux_det, input_mag_det : array, shape (N,)
        Total input flux [image units] and AB magnitude in the detection band.
    mode : {"windowed", "full", "source-extractor"}
        ``full`` extracts the whole injected image once (validation; also what
        ``windowed`` runs for the settings of :func:`runs_full_frame`);
        ``source-extractor`` (or ``params.backend="source-extractor"``, which
        takes precedence) segments it with the SExtractor binary.
    diagnostics : dict, optional
        If given, filled with ``"window"``: (N, 4) int array, the last
        window of each source (y0, y1, x0, x1, image pixels; the whole image
        in ``full`` mode), and ``"rounds"``: number of extraction rounds
        (benchmarks; no effect on the results); in ``full`` mode also
        ``"segmap"``: the extraction's segmentation of the whole image (labels
        are ``detection_id``).
    input_templates : sequence of length N, optional
        Per source, its injected detection-band stamp ``(y0, x0, data, flux)``
        (pixels ``data * flux`` [image units] at image row/column y0, x0) or
        None if nothing was injected in that band.  Default: the stamps of
        ``det_scene``, one per source in order.  The status-2 flux test
        compares the detection's AUTO flux with this template's flux through
        the same Kron ellipse and masks (column ``flux_auto_template``; see
        :mod:`glaciar.engine.classify`).
    early_exit : bool
        Windowed mode: sources with no above-threshold pixel in their search
        box are reported as not detected without an extraction
        (:func:`~glaciar.engine.windows.undetectable`; exact, the table is the
        same with False).

    Returns
    -------
    dict of str -> ndarray, each of length N
        See :func:`output_columns`.  Measured quantities are NaN for
        undetected sources; ``detection_id`` is the label of the detection in
        this call's extraction (0 = none; not comparable between modes).
    """
    band_rms, reference, params = setup.band_rms, setup.reference, setup.params
    classification, zeropoints, gains = setup.classification, setup.zeropoints, setup.gains
    detection_band, mask = setup.detection_band, setup.mask
    noise_models, det_background = setup.noise_models, setup.det_background
    if mode not in ("windowed", "full", "source-extractor"):
        raise ValueError(f"mode must be 'windowed', 'full' or 'source-extractor', got {mode!r}")
    bands = list(band_scenes)
    if detection_band not in band_scenes:
        raise ValueError(f"detection band {detection_band!r} missing from band_scenes ({', '.join(bands)})")
    for b in bands:
        if b not in band_rms:
            raise ValueError(f"band_rms has no entry for band {b!r}")
        if b not in zeropoints:
            raise ValueError(f"zeropoints has no entry for band {b!r}")
        if band_scenes[b].shape != det_scene.shape:
            raise ValueError(f"band {b!r} image shape {band_scenes[b].shape} differs from the detection image {det_scene.shape}")
    if det_rms.shape != det_scene.shape or reference.segmap.shape != det_scene.shape:
        raise ValueError("det_rms and reference.segmap must have the detection image's shape")
    if classification.sn_definition == "aper" and classification.sn_aperture_index >= len(params.phot_apertures):
        raise ValueError(f"sn_aperture_index {classification.sn_aperture_index} but only "
                         f"{len(params.phot_apertures)} PHOT_APERTURES")
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    n = x.size
    if y.size != n or np.size(input_flux_det) != n or np.size(input_mag_det) != n:
        raise ValueError("x, y, input_flux_det and input_mag_det must have the same length")

    out = {c: np.full(n, np.nan) for c in output_columns(bands, len(params.phot_apertures))}
    out["status"] = np.full(n, STATUS_NOT_DETECTED, dtype=np.int8)
    out["detection_id"] = np.zeros(n, dtype=np.int64)
    out[COL_FLAGS] = np.zeros(n, dtype=np.int32)
    out["blend_original_id"] = np.zeros(n, dtype=np.int64)
    if n == 0:
        if diagnostics is not None:
            diagnostics.update(window=np.zeros((0, 4), dtype=np.int64), rounds=0)
        return out
    ny, nx = det_scene.shape
    sextractor = mode == "source-extractor" or params.backend == "source-extractor"
    if mode == "windowed" and runs_full_frame(params):
        mode = "full"
    hw = params.filter_halfwidth
    ctx = MeasureContext(
        det_scene=det_scene, det_rms=det_rms, band_scenes=band_scenes, band_rms=band_rms, mask=mask,
        ref_segmap=reference.segmap, ref_mag=reference.mag, params=params, cls=classification,
        zeropoints=zeropoints, gains=gains, det_band=detection_band, bands=bands,
        noise_models=dict(noise_models or {}), shape=det_scene.shape, margin=hw + 1, gap=max(hw + 1, 2),
        x=x, y=y, input_flux=np.asarray(input_flux_det, dtype=np.float64).ravel(),
        input_mag=np.asarray(input_mag_det, dtype=np.float64).ravel(),
        templates=_input_templates(det_scene, input_templates, n),
        out=out, at_max=np.zeros(n, dtype=bool), isolated={},
        det_background=det_background, ref_objects=reference.objects)
    whole = np.repeat(np.array([[0, ny, 0, nx]]), n, axis=0)
    if sextractor:
        from glaciar.engine.sextractor_backend import sextractor_segmentation
        prod = sextractor_segmentation(det_scene.full(), det_rms, params, mask=mask,
                                       gain=gains.get(detection_band), zeropoint=zeropoints[detection_band])
        _measure_product(ctx, prod)
        last, rounds = whole, 1
    elif mode == "full" and _task_wide_clean(params):
        # CLEAN through the injected image's whole object list: its full-frame product
        try:
            prod = sep_segmentation(det_scene.full(), det_rms, params, mask=mask)
        except DetectionError:
            out[COL_FLAGS] |= FLAG_SEP_ERROR
            prod = None
        if prod is not None:
            _measure_product(ctx, prod)
            if diagnostics is not None:
                diagnostics["segmap"] = prod.seg
        last, rounds = whole, 1
    elif mode == "full":
        finish = _finish
        if diagnostics is not None:
            def finish(c, batch):
                # The final full-frame segmentation (the canvas is the whole image): what
                # glaciar.engine.catalog reads the detections from.
                cv = batch.canvas
                oy, ox = int(cv.oy[0]), int(cv.ox[0])
                diagnostics["segmap"] = np.asarray(batch.seg)[oy:oy + ny, ox:ox + nx]
                _finish(c, batch)
        last, rounds = segment_full(ctx, finish), 1
    else:
        last, rounds = segment_windowed(ctx, _finish, early_exit=early_exit)
    total_magnitudes(out, bands, zeropoints)
    if diagnostics is not None:
        diagnostics.update(window=np.array(last, copy=True), rounds=rounds)
    return out


def _task_wide_clean(params: DetectionParams) -> bool:
    """CLEAN on, through the whole image's object list (a style other than ``"region"``)."""
    return bool(params.clean) and params.clean_style != "region"


def runs_full_frame(params: DetectionParams) -> bool:
    """Do these settings run full frame even in ``mode="windowed"``?

    True for a task-wide CLEAN (``clean_style`` other than ``"region"``, CLEAN on:
    the outcome depends on every object of the image) and for the matched filter
    (``filter_type="matched"`` with a kernel: noise-aware, its detection mask is
    reproduced only up to rounding, so windows could not be proven exact).  Keeping
    them windowed took ~650 lines of task-wide CLEAN machinery for a full/windowed CPU
    ratio of 1.04-1.16 (CLEAN styles) and 0.29-0.81 (matched filter: windowed was
    slower) on the 1000^2 demo field at m = 26 (``benchmarks/fullframe_styles.py``).
    ``threshold_rms="filtered"`` stays windowed: exact with no machinery of its own
    (the filtered RMS of the canvas, gaps counting as outside the image) and 1.4-1.7x
    faster than full frame there.
    """
    matched = params.filter_kernel is not None and params.filter_type == "matched"
    return _task_wide_clean(params) or matched


def total_magnitudes(out: dict, bands, zeropoints: Mapping[str, float]) -> None:
    """Fill ``mag_auto_<band>`` and ``magerr_auto_<band>`` of ``out`` from its AUTO fluxes.

    The total magnitude of a detection (``OBS_MAG_QUANTITY``): every backend and the
    catalogue get it from the same flux columns (NaN where the flux is not positive).
    """
    for band in bands:
        mag, magerr, _ = phot.magnitudes(out[band_column("flux_auto", band)],
                                         out[band_column("fluxerr_auto", band)], zeropoints[band])
        out[band_column("mag_auto", band)] = mag
        out[band_column("magerr_auto", band)] = magerr


def _measure_product(ctx, prod):
    """Classification and photometry of every source on a full-frame segmentation product.

    The same selection, Kron/AUTO, photometry and classification code as the
    sep modes (:func:`_finish`), on a full-frame segmentation
    (:class:`~glaciar.engine.segmentation.Segmentation`: the SExtractor
    backend's, or sep's with a task-wide CLEAN): its labels and geometry are
    taken as they are.  Pixels of objects CLEAN removed (``pre_seg`` labelled,
    ``seg`` not) are masked as neighbours for everyone, as in the windowed path
    (:data:`glaciar.engine.windows.REMOVED`).
    """
    ny, nx = ctx.shape
    n = ctx.x.size
    rects = np.array([[0, ny, 0, nx]], dtype=np.int64)
    cv = Canvas(ctx, rects, full=True)
    src = np.arange(n)
    src_win = np.zeros(n, dtype=np.int64)
    pseg = np.asarray(prod.seg, dtype=np.int64)
    tab = {f: np.r_[np.nan, np.asarray(getattr(prod, f), dtype=np.float64)]
           for f in ("x", "y", "a", "b", "theta")}
    pix = np.flatnonzero(pseg)
    lab_pix = pseg.ravel()[pix]
    seg_flux = np.bincount(lab_pix, weights=cv.det.ravel()[pix], minlength=len(prod) + 1)
    bounds = np.tile(np.array([0, ny, 0, nx], dtype=np.int64), (n, 1))
    label = select_detection(pseg, ctx.x, ctx.y, seg_flux, ctx.cls.search_box, bounds=bounds)
    det = label > 0
    xs, ys = tab["x"][label], tab["y"][label]
    a, b, th = safe_shape(tab["a"][label], tab["b"][label], tab["theta"][label])
    pseg32 = pseg.astype(np.int32)
    if getattr(prod, "pre_seg", None) is not None:
        pseg32[(pseg32 == 0) & (prod.pre_seg > 0)] = REMOVED
    kr = np.full(n, np.nan)
    ii = np.flatnonzero(det)
    if ii.size:
        kr[ii] = phot.kron_radius(cv.det, xs[ii], ys[ii], a[ii], b[ii], th[ii], segmap=pseg32,
                                  seg_id=label[ii], mask=cv.nodata)
    scale = phot.auto_scale(kr, ctx.params.phot_autoparams)
    zeros = np.zeros(n, dtype=np.int64)
    _finish(ctx, SegmentedBatch(cv, pseg, pseg32, label, xs, ys, a, b, th, scale, src, src_win,
                                np.ones(n, dtype=bool), rects[src_win], zeros, zeros, np.zeros(n, dtype=bool),
                                np.zeros((n, 4), dtype=np.int64), bounds, pix, lab_pix))


def _band_boxes(width, pix, lab_pix, labels, phot_box, bounds):
    """Per detected source, the part of its window the band photometry reads (canvas
    coordinates): its segment (ISO) and its AUTO / aperture box, inside the window.
    Band pixels elsewhere are never read, so they need not be pasted.

    ``pix``, ``lab_pix``: flat canvas indices and labels of the segment pixels
    (at least those of ``labels``)."""
    boxes = np.array(phot_box, dtype=np.int64).reshape(-1, 4)
    if labels.size and pix.size:
        nl = int(max(labels.max(), lab_pix.max())) + 1
        order = np.argsort(lab_pix, kind="stable")
        ls = lab_pix[order]
        rows, cols = np.divmod(pix[order], width)
        start = np.flatnonzero(np.r_[True, ls[1:] != ls[:-1]])
        present = ls[start]
        seg = np.zeros((nl, 4), dtype=np.int64)
        seg[:, 0] = seg[:, 2] = np.iinfo(np.int64).max // 4
        seg[:, 1] = seg[:, 3] = -(np.iinfo(np.int64).max // 4)
        seg[present, 0] = np.minimum.reduceat(rows, start)
        seg[present, 1] = np.maximum.reduceat(rows, start) + 1
        seg[present, 2] = np.minimum.reduceat(cols, start)
        seg[present, 3] = np.maximum.reduceat(cols, start) + 1
        sb = seg[labels]
        boxes[:, 0] = np.minimum(boxes[:, 0], sb[:, 0])
        boxes[:, 1] = np.maximum(boxes[:, 1], sb[:, 1])
        boxes[:, 2] = np.minimum(boxes[:, 2], sb[:, 2])
        boxes[:, 3] = np.maximum(boxes[:, 3], sb[:, 3])
    boxes[:, 0] = np.maximum(boxes[:, 0], bounds[:, 0])
    boxes[:, 1] = np.minimum(boxes[:, 1], bounds[:, 1])
    boxes[:, 2] = np.maximum(boxes[:, 2], bounds[:, 2])
    boxes[:, 3] = np.minimum(boxes[:, 3], bounds[:, 3])
    return boxes


def _finish(ctx: MeasureContext, batch: SegmentedBatch):
    """Classification and photometry of the finished (``batch.done``) sources of a canvas."""
    cv, pseg, pseg32, label = batch.canvas, batch.seg, batch.seg32, batch.label
    xs, ys, a, b, th, scale = batch.x, batch.y, batch.a, batch.b, batch.theta, batch.kron_scale
    src, src_win, fin, rect, wy0, wx0 = batch.src, batch.src_win, batch.done, batch.rect, batch.wy0, batch.wx0
    edge, phot_box, bounds, pix, lab_all = batch.edge, batch.phot_box, batch.bounds, batch.pix, batch.lab_pix
    out, params, cls = ctx.out, ctx.params, ctx.cls
    idx = np.flatnonzero(fin)
    if idx.size == 0:
        return
    lab = label[idx]
    det = lab > 0
    s = src[idx]
    out["detection_id"][s] = lab
    # classification geometry
    n_fp, n_ov, blend = footprint_overlap(pseg, lab, cv.ref, ctx.ref_mag)
    # photometry in every band
    di = np.flatnonzero(det)
    # Pixels of the measured segments only: ISO sums per label are the same
    # (bincount adds each label's pixels in the same row-major order).
    wanted = np.zeros(int(max(lab_all.max(initial=0), lab.max(initial=0))) + 1, dtype=bool)
    wanted[lab[det]] = True
    keep = wanted[lab_all]
    pix, lab_all = pix[keep], lab_all[keep]
    if cv.full:
        windows, boxes = np.zeros(1, dtype=np.int64), None
    else:
        j = idx[di]
        windows = src_win[j]
        boxes = _band_boxes(cv.shape[1], pix, lab_all, lab[di], phot_box[j], bounds[j])
    flux_sn = err_sn = None
    auto_det = tpl_det = None
    pos = np.full(label.size, -1, dtype=np.int64)
    pos[idx] = np.arange(idx.size)          # canvas source index -> row of this finish
    jd = idx[di]
    # The cut-outs and which of them hold no neighbour: one segmentation, so once for every band.
    plan = (phot.CutoutPlan.of(pseg32, lab[pos[jd]], phot.Ellipses(xs[jd], ys[jd], a[jd], b[jd], th[jd], scale[jd]),
                               params.phot_apertures, params.mask_type, bounds=bounds[jd])
            if params.mask_type is not None and jd.size else None)
    for band in ctx.bands:
        data, rms, bad = cv.band(band, windows, boxes)
        gain = ctx.gains.get(band)
        noise = ctx.noise_models.get(band)
        fi, fei = phot.iso_photometry(data, rms, pseg, lab, gain=gain, pixels=pix, noise=noise)
        fa = np.full((len(params.phot_apertures), lab.size), np.nan)
        fea = fa.copy()
        fau = np.full(lab.size, np.nan)
        feau = fau.copy()
        dbkg = None
        if params.backphoto_type == "local" and jd.size:
            # BACKPHOTO_TYPE LOCAL: per band, from the annulus around each segment's box
            sbox = phot.segment_boxes(pix, lab_all, cv.shape[1], int(lab.max()) + 1)[lab[di]]
            dbkg = phot.local_background(data, pseg32, bad, sbox, params.backphoto_thick,
                                         shape=ctx.shape, bounds=bounds[jd])
            npix = np.bincount(lab_all, minlength=int(lab.max()) + 1)[lab[di]]
            fi[di] = fi[di] - npix * dbkg
        if params.mask_type is not None and jd.size:
            r = pos[jd]
            fa[:, r], fea[:, r], fau[r], feau[r] = plan.measure(data, rms, bad, gain=gain, dbkg=dbkg,
                                                                noise=noise)
        else:
            for j, sl in window_groups(cv, jd, edge, src_win):
                oy, ox = sl[0].start, sl[1].start
                r = pos[j]
                fa[:, r], fea[:, r] = phot.aperture_photometry(data[sl], rms[sl], xs[j] - ox, ys[j] - oy,
                                                               params.phot_apertures, gain=gain, mask=bad[sl],
                                                               noise=noise)
                ell = phot.Ellipses(xs[j] - ox, ys[j] - oy, a[j], b[j], th[j], scale[j])
                fau[r], feau[r] = phot.auto_photometry(data[sl], rms[sl], ell, gain=gain, segmap=pseg32[sl],
                                                       seg_id=lab[r], mask=bad[sl], noise=noise)
            if dbkg is not None:
                # sep's sums stand for the whole aperture inside the image (masked pixels are
                # scaled up), so the area to subtract is the aperture's area inside the image
                r = pos[jd]
                ca, ea = phot.aperture_area(cv.shape, xs[jd], ys[jd], params.phot_apertures, a[jd], b[jd],
                                            th[jd], scale[jd], bounds=bounds[jd])
                fa[:, r] -= ca * dbkg
                fau[r] -= ea * dbkg
        if cls.sn_definition == "iso":
            f, fe = fi, fei
        elif cls.sn_definition == "auto":
            f, fe = fau, feau
        else:
            f, fe = fa[cls.sn_aperture_index], fea[cls.sn_aperture_index]
        f = np.where(det, f, np.nan)
        fe = np.where(det, fe, np.nan)
        zp = ctx.zeropoints[band]
        mag, magerr, sn = phot.magnitudes(f, fe, zp)
        col = lambda q: band_column(q, band)  # noqa: E731
        out[col("flux_iso")][s] = fi
        out[col("fluxerr_iso")][s] = fei
        out[col("flux_auto")][s] = fau
        out[col("fluxerr_auto")][s] = feau
        for kk in range(len(params.phot_apertures)):
            out[col(f"flux_aper{kk}")][s] = fa[kk]
            out[col(f"fluxerr_aper{kk}")][s] = fea[kk]
        out[col("mag")][s] = mag
        out[col("magerr")][s] = magerr
        out[col("sn")][s] = sn
        out[col("maglim")][s] = phot.limiting_magnitude(f, fe, zp)
        if band == ctx.det_band:
            flux_sn, err_sn = f, fe
            if jd.size:
                _flag_saturated(ctx, data, pix, lab_all, lab, di, s, xs[jd] - wx0[jd] + rect[jd, 2],
                                ys[jd] - wy0[jd] + rect[jd, 0])
            # The status-2 flux test: AUTO flux vs the injected template through the same ellipse.
            auto_det = fau
            tpl_det = _template_auto_flux(ctx, batch, lab, idx, di, s, rms, bad)
    with np.errstate(divide="ignore", invalid="ignore"):
        sn_det = flux_sn / err_sn
    bmag = np.full(lab.size, np.nan)
    has = blend > 0
    bmag[has] = ctx.ref_mag[blend[has] - 1]
    status = classify(lab, sn_det, n_fp, n_ov, bmag, ctx.input_mag[s], auto_det, tpl_det, cls)
    out["status"][s] = status
    with np.errstate(divide="ignore", invalid="ignore"):
        out["overlap_fraction"][s] = np.where(det, n_ov / np.maximum(n_fp, 1), np.nan)
    out["blend_original_id"][s] = blend
    out["flux_auto_template"][s] = tpl_det
    out["blend_original_mag"][s] = bmag
    # detection centroid in image coordinates
    j = idx
    out["x_det"][s] = np.where(det, xs[j] - wx0[j] + rect[j, 2], np.nan)
    out["y_det"][s] = np.where(det, ys[j] - wy0[j] + rect[j, 0], np.nan)


def _flag_saturated(ctx, data, pix, lab_all, lab, di, s, x_img, y_img):
    """FLAG_SATURATED where a detection's peak in the detection band plus the background at
    its centre reaches SATUR_LEVEL (SExtractor's FLAGS bit 4)."""
    thr = np.full(di.size, float(ctx.params.satur_level))
    if ctx.det_background is not None:
        ny, nx = ctx.shape
        iy = np.clip((y_img + 0.5).astype(np.int64), 0, ny - 1)
        ix = np.clip((x_img + 0.5).astype(np.int64), 0, nx - 1)
        # index first: converting the whole map (float32) to float64 on every call cost
        # ~90 ms per round on a 4000^2 field; the gathered values are the same
        thr -= np.asarray(ctx.det_background)[iy, ix].astype(np.float64)
    n = int(max(lab_all.max(initial=0), lab.max(initial=0))) + 1
    t = np.full(n, np.inf)
    t[lab[di]] = thr
    sat = phot.saturated(data, pix, lab_all, t, n)[lab[di]]
    ctx.out[COL_FLAGS][s[di][sat]] |= FLAG_SATURATED


def _input_templates(det_scene, templates, n):
    """Per-source (y0, x0, data, flux) of the injected detection-band stamps (see measure_injected)."""
    if templates is None:
        templates = det_scene.templates()          # one stamp per source
    templates = list(templates)
    if len(templates) != n:
        raise ValueError(f"input_templates (default: the detection scene's stamps) has "
                         f"{len(templates)} entries for {n} sources")
    return templates


def _template_auto_flux(ctx, batch: SegmentedBatch, lab, idx, di, s, rms, bad):
    """AUTO flux of each finished source's own noiseless template (NaN if undetected).

    Each template is pasted alone into a zero canvas (clipped to its window,
    which holds its whole Kron ellipse) and measured with the source's ellipse,
    neighbour segments and no-data mask, exactly as its data were: so a
    windowed and a full-frame extraction give the same value, and other
    injected sources never enter it.

    ``lab``, ``idx``, ``di``, ``s``: as in :func:`_finish` (labels, canvas source indices,
    detected rows and call source indices of the finished sources); ``rms``, ``bad``: the
    detection band's RMS and no-data mask on the canvas.
    """
    cv, pseg32, xs, ys = batch.canvas, batch.seg32, batch.x, batch.y
    a, b, th, scale = batch.a, batch.b, batch.theta, batch.kron_scale
    rect, wy0, wx0, edge, src_win = batch.rect, batch.wy0, batch.wx0, batch.edge, batch.src_win
    out = np.full(lab.size, np.nan)
    tcv = np.zeros(cv.shape)
    pos = np.full(src_win.size, -1, dtype=np.int64)      # canvas source index -> row of lab
    pos[idx] = np.arange(idx.size)
    params = ctx.params
    for jj, sl in window_groups(cv, idx[di], edge, src_win):
        oy, ox = sl[0].start, sl[1].start
        # Sources with windows of their own are measured in one call: each template is
        # clipped to its window and every ellipse lies inside its window, so no
        # template reaches another's ellipse.  A shared window (the full frame) would
        # mix them: one source at a time then.
        jl = jj.tolist()
        batches = [jl] if np.unique(src_win[jj]).size == jj.size else [[j] for j in jl]
        for group in batches:
            pasted, boxes = [], []
            for j in group:
                r = pos[j]
                t = ctx.templates[s[r]]
                if t is None:
                    out[r] = 0.0
                    continue
                ty0, tx0, data, flux = t
                ry0, ry1, rx0, rx1 = rect[j].tolist()
                y0, y1 = max(ty0, ry0), min(ty0 + data.shape[0], ry1)
                x0, x1 = max(tx0, rx0), min(tx0 + data.shape[1], rx1)
                if y1 <= y0 or x1 <= x0:
                    out[r] = 0.0
                    continue
                cy, cx = y0 - ry0 + wy0[j], x0 - rx0 + wx0[j]
                box = (slice(cy, cy + y1 - y0), slice(cx, cx + x1 - x0))
                tcv[box] = data[y0 - ty0:y1 - ty0, x0 - tx0:x1 - tx0] * flux
                pasted.append(j)
                boxes.append(box)
            if not pasted:
                continue
            j = np.array(pasted, dtype=np.int64)
            r = pos[j]
            if params.mask_type is not None:
                bnd = np.stack([wy0[j], wy0[j] + rect[j, 1] - rect[j, 0], wx0[j], wx0[j] + rect[j, 3] - rect[j, 2]],
                               axis=1)
                ell = phot.Ellipses(xs[j], ys[j], a[j], b[j], th[j], scale[j])
                out[r] = phot.sextractor_photometry(tcv, rms, pseg32, lab[r], bad, ell, params.phot_apertures,
                                                    params.mask_type, bounds=bnd)[2]
            else:
                ell = phot.Ellipses(xs[j] - ox, ys[j] - oy, a[j], b[j], th[j], scale[j])
                out[r], _ = phot.auto_photometry(tcv[sl], rms[sl], ell, segmap=pseg32[sl], seg_id=lab[r],
                                                 mask=bad[sl])
            for box in boxes:
                tcv[box] = 0.0
    return out
