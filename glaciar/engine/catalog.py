"""The survey's own detections, measured and selected exactly as the injected sources are.

A luminosity function counts the candidates of the survey's images; the selection
function says which galaxies that *same* measurement misses.  Both must therefore come
from one field measurement (background, RMS and noise maps, correlated-noise model,
masks) and one code path: :func:`measure_catalog` runs :func:`glaciar.engine.measure
.measure_injected` on the field's images with nothing injected (or with given stamps),
in full-frame mode, with one input position inside every segment of the extraction, so
every detection gets the row an injected source gets when it selects that detection:
the same ISO, aperture and AUTO photometry in every band, the same errors (correlated
noise included), magnitudes, S/N, ``maglim`` and flags.  A real detection has no input
to be blended with, so the classification columns of injections (status, overlap,
template flux) have no meaning here; "recovered" is its S/N part (``min_sn``,
:func:`~glaciar.engine.classify.passes_sn`) and ``selected`` is recovered, inside the
footprint the selection function's area counts, and passing the selection.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np
import pandas as pd

from .. import constants as C
from .classify import passes_sn
from .depth import depth_at
from .detect import DetectionError, sep_extract, detection_rms, sanitize
from .measure import MeasureSetup, measure_injected, output_columns
from .scene import Scene
from .task import field_key
from .user_selection import apply_selection

__all__ = ["measure_catalog", "segment_pixels", "CATALOG_ID", "CATALOG_IN_FOOTPRINT",
           "CATALOG_RECOVERED", "INJECTION_ONLY_COLUMNS"]

#: Column names of the catalogue beyond the per-source columns of injections.
CATALOG_ID = "id"                      #: label of the detection in the field's segmentation
CATALOG_IN_FOOTPRINT = "in_footprint"  #: centre pixel inside the area the selection function counts
CATALOG_RECOVERED = C.COL_RECOVERED    #: S/N (sn_definition) >= min_sn
#: Columns of :func:`measure_injected` that describe an injected source's classification
#: against the original image: left out of a catalogue.
#: Full-frame extractions :func:`measure_catalog` may take to reach a segmentation in which
#: every segment holds an input position (1 on the demo field).
MAX_CATALOG_PASSES = 6
#: First positions within this many pixels of a missed segment are measured with it
#: (:func:`_measure_missing`): the regions whose segments its window and apertures meet.
MISSING_NEIGHBOUR_RADIUS = 128
INJECTION_ONLY_COLUMNS = ("status", "detection_id", "overlap_fraction", "blend_original_id",
                          "blend_original_mag", "flux_auto_template", "x_det", "y_det")


def segment_pixels(segmap: np.ndarray, labels=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pixel of every segment: the first in row-major order.

    Parameters
    ----------
    segmap : ndarray of int, shape (ny, nx)
        Segmentation (0 = background).
    labels : array_like of int, optional
        Only these labels (default: every label present).

    Returns
    -------
    x, y : ndarray of float
        Pixel centres (0-based; x along axis 1).  Any pixel of a segment selects it
        (:func:`~glaciar.engine.classify.select_detection`: the central pixel's segment wins).
    label : ndarray of int64
    """
    flat = np.asarray(segmap).ravel()
    nz = np.flatnonzero(flat)
    lab, first = np.unique(flat[nz], return_index=True)
    pix = nz[first]
    if labels is not None:
        keep = np.isin(lab, np.asarray(labels))
        lab, pix = lab[keep], pix[keep]
    ny, nx = np.shape(segmap)
    return (pix % nx).astype(np.float64), (pix // nx).astype(np.float64), lab.astype(np.int64)


def _first_positions(ctx, scenes) -> tuple[np.ndarray, np.ndarray]:
    """A guess of one pixel inside every final segment (only the number of extractions
    depends on it): one pixel of every segment of the reference extraction, and the
    filtered-image peak of every object of a raw sep extraction (no CLEAN) of the
    detection image, a pixel of the object's core whatever the deblending does to its
    faint pixels."""
    x, y, _ = segment_pixels(ctx.reference.segmap)
    if getattr(ctx, "coadd_bands", ()):
        return x, y
    params = ctx.detection_params
    data, err, nodata = sanitize(scenes[ctx.detection_band].full(), ctx.rms[ctx.detection_band],
                                 ctx.mask)
    try:
        cat, raw = sep_extract(data, detection_rms(err, nodata, params), nodata, params, False)
    except DetectionError:
        return x, y
    # Photometry is per position: a reference pixel inside a raw object (whose core is
    # already given) would measure that detection twice.
    outside = raw[y.astype(np.int64), x.astype(np.int64)] == 0
    return (np.concatenate([np.asarray(cat["xcpeak"], np.float64), x[outside]]),
            np.concatenate([np.asarray(cat["ycpeak"], np.float64), y[outside]]))


def _measure(ctx, scenes: Mapping[str, Scene], x, y, diagnostics: dict | None,
             mode: str = "full"):
    det_scene, det_rms = ctx.detection_scene(scenes)
    n = x.size
    nan = np.full(n, np.nan)
    return measure_injected(MeasureSetup.of_field(ctx), det_scene, det_rms, scenes, x, y, nan, nan,
                            mode=mode, diagnostics=diagnostics, input_templates=[None] * n)


def _measure_missing(ctx, scenes, seg, missing, x, y) -> dict | None:
    """Rows of the segments no position reached, measured in windowed mode (None: not exact).

    A segment is missed when the canonical deblending of its region (which did hold a
    position) differs from the raw extraction's the first positions came from (on a
    4000^2 demo field: 1 of 24 434).  Its row is measured with a pixel of it and every
    first position within ``MISSING_NEIGHBOUR_RADIUS`` pixels, so the regions around it
    are re-extracted as in the full frame (windowed = full frame for the same positions),
    without a second full-frame extraction.  Accepted only if each one's ISO flux in the
    detection band equals the sum of its segment's pixels in the full-frame segmentation
    (the same pixels), else None (the caller extracts the frame again).
    """
    mx, my, _ = segment_pixels(seg, missing)
    r = MISSING_NEIGHBOUR_RADIUS
    near = np.zeros(x.size, dtype=bool)
    for xi, yi in zip(mx, my):
        near |= (np.abs(x - xi) <= r) & (np.abs(y - yi) <= r)
    got = _measure(ctx, scenes, np.concatenate([mx, x[near]]), np.concatenate([my, y[near]]),
                   None, mode="windowed")
    k = missing.size
    det = ctx.detection_band
    if getattr(ctx, "coadd_bands", ()):
        return None                # the ISO check needs the detection band's own pixels
    want = np.empty(k)
    for i, label in enumerate(missing):
        yy, xx = np.nonzero(seg == label)
        y0, x0 = yy.min(), xx.min()
        win = scenes[det].window(int(y0), int(yy.max()) + 1, int(x0), int(xx.max()) + 1)
        want[i] = np.sum(np.asarray(win, np.float64)[yy - y0, xx - x0])
    flux = got[C.band_column("flux_iso", det)][:k]
    if not np.allclose(flux, want, rtol=1e-9, atol=0):
        return None
    rows = {c: np.asarray(v)[:k] for c, v in got.items()}
    rows["detection_id"] = missing.astype(np.int64)
    return rows


def measure_catalog(ctx, scenes: Mapping[str, Scene] | None = None, *,
                    positions=None, seed: int = 0) -> pd.DataFrame:
    """Detect, measure and select every source of a field's images.

    Parameters
    ----------
    ctx : glaciar.engine.context.FieldContext
        The field's measurement (the one its injections use).
    scenes : mapping band -> Scene, optional
        Background-subtracted images to catalogue; default the field's own
        (``Scene(ctx.bases[band])``, nothing injected).  Given stamps, the catalogue
        of the injected image (tests: a hand-injected source gets its engine row).
    positions : (x, y) arrays, optional
        Extra input pixels (e.g. where stamps were added).  The first extraction is
        given these and :func:`_first_positions`; each further one adds a pixel of
        every segment no input reached, until every segment is reached.
    seed : int
        The run's seed: with the field's name, the stream from which a probabilistic
        selection function's ``selected`` is drawn (else unused).

    Returns
    -------
    pandas.DataFrame
        One row per detection, ordered by ``id`` (its label in the field's
        full-frame segmentation): ``field``, ``id``, ``x``, ``y`` (the detection's
        centroid, 0-based pixels), every band's measured columns
        (:func:`~glaciar.engine.measure.output_columns` less
        :data:`INJECTION_ONLY_COLUMNS`: ISO, AUTO and aperture fluxes and errors,
        ``mag``, ``magerr``, ``sn``, ``maglim``, ``mag_auto``, ``magerr_auto``),
        ``source_flags``, ``depth_local`` [AB mag], ``in_footprint``,
        ``recovered`` and ``selected`` (and ``p_selected`` for a probabilistic
        selection function).
    """
    if scenes is None:
        scenes = {b: Scene(ctx.bases[b]) for b in ctx.bases}
    x, y = _first_positions(ctx, scenes)
    if positions is not None:
        px, py = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in positions)
        x, y = np.concatenate([x, np.floor(px + 0.5)]), np.concatenate([y, np.floor(py + 0.5)])
    # The engine re-extracts canonically (deblending and CLEAN of the region on its own) the
    # regions that hold an input position, as it does around an injected source; elsewhere
    # the frame keeps sep's raw segments.  So the segmentation depends on the positions, and
    # it is the one every injected source would see once every segment holds a position:
    # then every region with a segment was re-extracted, and more positions inside those
    # regions change nothing.  The first positions (every raw object's core) reach that on
    # the demo field; otherwise each further extraction adds a pixel of each segment missed.
    parts = []
    for _ in range(MAX_CATALOG_PASSES):
        diag: dict = {}
        out = _measure(ctx, scenes, x, y, diag)
        seg = diag["segmap"]
        present = np.flatnonzero(np.bincount(np.asarray(seg).ravel()))
        missing = np.setdiff1d(present[present > 0], out["detection_id"])
        if not missing.size:
            break
        extra = _measure_missing(ctx, scenes, seg, missing, x, y)
        if extra is not None:
            parts.append(extra)
            break
        mx, my, _ = segment_pixels(seg, missing)
        x, y = np.concatenate([x, mx]), np.concatenate([y, my])
    else:
        raise RuntimeError(f"field {ctx.field}: the catalogue's segmentation did not settle in "
                           f"{MAX_CATALOG_PASSES} extractions")
    parts.insert(0, out)
    cols = [c for c in output_columns(ctx.bands, len(ctx.detection_params.phot_apertures))
            if c not in INJECTION_ONLY_COLUMNS]
    merged = {c: np.concatenate([p[c] for p in parts]) for c in cols + ["detection_id", "x_det", "y_det"]}
    ids = merged["detection_id"]
    _, first = np.unique(ids, return_index=True)
    keep = first[ids[first] > 0]                       # one row per detection, in label order
    n = keep.size
    xd, yd = merged["x_det"][keep], merged["y_det"][keep]
    table = {C.COL_FIELD: np.full(n, ctx.field, dtype=object),
             CATALOG_ID: ids[keep].astype(np.int64), C.COL_X: xd, C.COL_Y: yd}
    for c in cols:
        table[c] = merged[c][keep]
    ny, nx = ctx.shape
    iy = np.clip(np.floor(yd + 0.5).astype(np.int64), 0, ny - 1)
    ix = np.clip(np.floor(xd + 0.5).astype(np.int64), 0, nx - 1)
    table[C.COL_DEPTH] = depth_at(ctx.depth, xd, yd)
    table[CATALOG_IN_FOOTPRINT] = np.asarray(ctx.footprint[iy, ix], dtype=bool)
    frame = pd.DataFrame(table)
    sn = frame[C.band_column("sn", ctx.detection_band)].to_numpy(float)
    recovered = passes_sn(sn, ctx.classification_params.min_sn)
    frame[CATALOG_RECOVERED] = recovered
    # A probabilistic user selection draws from the run's seed and the field (not the order
    # fields are catalogued in).
    passed, probability = apply_selection(ctx.selection, frame, (int(seed), field_key(ctx.field)))
    frame[C.COL_SELECTED] = recovered & frame[CATALOG_IN_FOOTPRINT].to_numpy() & passed
    if probability is not None:
        frame[C.COL_P_SELECTED] = probability
    return frame
