"""Detection by the SExtractor binary: the same segmentation product, made by SExtractor.

:func:`sextractor_segmentation` runs ``source-extractor`` (Debian/Ubuntu
package ``source-extractor``; ``sex`` elsewhere) on a full image in
dual-image mode -- detection image + one measurement band -- with the
settings of a :class:`~glaciar.engine.detect.DetectionParams`, and returns a
:class:`~glaciar.engine.segmentation.Segmentation` built from its
SEGMENTATION check-image and catalogue.  glaciar's classification and
photometry then run on it unchanged (``mode="source-extractor"`` in
:func:`glaciar.engine.measure.measure_injected`), so any difference from the
sep backends is a difference of detection, deblending or CLEAN.

How the settings map (the images are background-subtracted and carry a
per-pixel RMS map, as everywhere in glaciar):

=====================  =====================================================
DetectionParams        SExtractor
=====================  =====================================================
detect_thresh          DETECT_THRESH = ANALYSIS_THRESH, THRESH_TYPE RELATIVE
detect_minarea         DETECT_MINAREA
filter_kernel          FILTER Y + a ``CONV NORM`` file with the same kernel
                       (written to full precision; None: FILTER N)
deblend_*, clean*      DEBLEND_NTHRESH, DEBLEND_MINCONT, CLEAN, CLEAN_PARAM
                       (SExtractor's CLEAN is ``clean_style="sextractor"``;
                       ``clean_style`` itself has no SExtractor key)
phot_apertures, auto   PHOT_APERTURES, PHOT_AUTOPARAMS
RMS maps               WEIGHT_TYPE MAP_RMS,MAP_RMS (WEIGHT_GAIN N); pixels
                       without data get RMS 1e10, above WEIGHT_THRESH 1e9.
                       With a filter, SExtractor thresholds against the
                       *filtered* variance map (sep: each pixel's RMS), so
                       where the RMS varies the two masks differ slightly
background             BACK_TYPE MANUAL, BACK_VALUE 0 (already subtracted)
=====================  =====================================================

INTERP_TYPE NONE (no interpolation over bad weights), MASK_TYPE CORRECT.
``filter_type="matched"`` has no SExtractor equivalent and is refused.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass

import numpy as np

from glaciar.engine.detect import DetectionParams
from glaciar.engine.segmentation import Segmentation

__all__ = ["SExtractorError", "find_sextractor", "sextractor_segmentation", "SExtractorRun",
           "run_sextractor", "CATALOG_PARAMS"]

#: Environment variable naming the SExtractor executable (overrides the PATH search).
ENV_BINARY = "GLACIAR_SEXTRACTOR"
#: RMS given to pixels without data, and the weight threshold above which SExtractor ignores them
_NODATA_RMS = 1e10
_WEIGHT_THRESH = 1e9

#: Catalogue columns requested (``FLUX_APER`` and ``FLUXERR_APER`` get one entry per aperture).
CATALOG_PARAMS = ("NUMBER", "X_IMAGE", "Y_IMAGE", "A_IMAGE", "B_IMAGE", "THETA_IMAGE", "FLUX_ISO",
                  "FLUXERR_ISO", "ISOAREA_IMAGE", "FLUX_AUTO", "FLUXERR_AUTO", "KRON_RADIUS",
                  "XMIN_IMAGE", "XMAX_IMAGE", "YMIN_IMAGE", "YMAX_IMAGE", "FLAGS")


class SExtractorError(RuntimeError):
    """The SExtractor binary is missing or failed."""


def find_sextractor(binary: str | None = None) -> str | None:
    """Path of the SExtractor executable, or None.

    Order: ``binary`` if given, ``$GLACIAR_SEXTRACTOR``, then ``source-extractor``
    and ``sex`` on the PATH.
    """
    for cand in (binary, os.environ.get(ENV_BINARY), "source-extractor", "sex"):
        if cand:
            path = shutil.which(cand)
            if path:
                return path
    return None


@dataclass
class SExtractorRun:
    """Raw output of one SExtractor run.

    Attributes
    ----------
    catalog : structured ndarray
        The FITS_1.0 catalogue (:data:`CATALOG_PARAMS`); pixel coordinates as
        SExtractor writes them (1-based).
    segmap : ndarray of int32
        SEGMENTATION check-image (label = NUMBER).
    command : list of str
    version : str
    """

    catalog: np.ndarray
    segmap: np.ndarray
    command: list
    version: str


def _conv_text(kernel) -> str:
    k = np.asarray(kernel, dtype=np.float64)
    rows = "\n".join(" ".join(repr(float(v)) for v in row) for row in k)
    return f"CONV NORM\n# glaciar detection kernel ({k.shape[0]}x{k.shape[1]})\n{rows}\n"


def _fits_image(path, data):
    from astropy.io import fits
    fits.PrimaryHDU(np.ascontiguousarray(data, dtype=np.float32)).writeto(path, overwrite=True)


def _clean_maps(image, rms, mask):
    data = np.array(image, dtype=np.float64)
    e = np.array(rms, dtype=np.float64)
    bad = ~np.isfinite(data) | ~np.isfinite(e) | ~(e > 0)
    if mask is not None:
        bad |= np.asarray(mask, dtype=bool)
    data[bad] = 0.0
    e[bad] = _NODATA_RMS
    return data, e


def run_sextractor(det_image, det_rms, params: DetectionParams, meas_image=None, meas_rms=None, *,
                   mask=None, gain: float | None = None, zeropoint: float = 0.0,
                   binary: str | None = None, workdir=None, timeout: float = 600.0) -> SExtractorRun:
    """Run SExtractor in dual-image mode and read its catalogue and segmentation.

    Parameters
    ----------
    det_image, det_rms : ndarray
        Background-subtracted detection image and its per-pixel RMS [image units].
    params : DetectionParams
    meas_image, meas_rms : ndarray, optional
        Measurement band (default: the detection image itself) [image units].
    mask : ndarray of bool, optional
        True where there are no data (both images).
    gain : float or None
        Measurement band's electrons per image unit (SExtractor GAIN; None: 0,
        no Poisson term).
    zeropoint : float
        MAG_ZEROPOINT of the measurement band.
    binary : str, optional
        Executable (default :func:`find_sextractor`).
    workdir : path, optional
        Where to write the temporary files (a fresh temporary directory by
        default, removed afterwards).
    timeout : float
        Seconds before the run is abandoned.

    Returns
    -------
    SExtractorRun

    Raises
    ------
    SExtractorError
        Binary not found, non-zero exit, or unreadable output.
    ValueError
        For settings SExtractor cannot reproduce (``filter_type="matched"``).
    """
    if params.filter_kernel is not None and params.filter_type != "conv":
        raise ValueError("filter_type 'matched' (sep's matched filter) has no SExtractor equivalent")
    exe = find_sextractor(binary)
    if exe is None:
        raise SExtractorError("SExtractor not found: install the 'source-extractor' package "
                              f"(binary 'source-extractor' or 'sex') or set ${ENV_BINARY}")
    from astropy.io import fits

    own = workdir is None
    wd = tempfile.mkdtemp(prefix="glaciar-sex-") if own else os.fspath(workdir)
    try:
        det, drms = _clean_maps(det_image, det_rms, mask)
        if meas_image is None:
            meas, mrms = det, drms
        else:
            meas, mrms = _clean_maps(meas_image, det_rms if meas_rms is None else meas_rms, mask)
        p = lambda name: os.path.join(wd, name)  # noqa: E731
        _fits_image(p("det.fits"), det)
        _fits_image(p("det_rms.fits"), drms)
        _fits_image(p("meas.fits"), meas)
        _fits_image(p("meas_rms.fits"), mrms)
        naper = len(params.phot_apertures)
        cols = list(CATALOG_PARAMS) + [f"FLUX_APER({naper})", f"FLUXERR_APER({naper})"]
        with open(p("glaciar.param"), "w") as fh:
            fh.write("\n".join(cols) + "\n")
        if params.filter_kernel is not None:
            with open(p("glaciar.conv"), "w") as fh:
                fh.write(_conv_text(params.filter_kernel))
        cfg = {
            "CATALOG_NAME": p("cat.fits"), "CATALOG_TYPE": "FITS_1.0", "PARAMETERS_NAME": p("glaciar.param"),
            "DETECT_TYPE": "CCD", "DETECT_MINAREA": str(int(params.detect_minarea)),
            "THRESH_TYPE": "RELATIVE", "DETECT_THRESH": repr(float(params.detect_thresh)),
            "ANALYSIS_THRESH": repr(float(params.detect_thresh)),
            "FILTER": "Y" if params.filter_kernel is not None else "N",
            "FILTER_NAME": p("glaciar.conv"),
            "DEBLEND_NTHRESH": str(int(params.deblend_nthresh)),
            "DEBLEND_MINCONT": repr(float(params.deblend_mincont)),
            "CLEAN": "Y" if params.clean else "N", "CLEAN_PARAM": repr(float(params.clean_param)),
            "MASK_TYPE": "CORRECT",
            "WEIGHT_TYPE": "MAP_RMS,MAP_RMS", "WEIGHT_IMAGE": f"{p('det_rms.fits')},{p('meas_rms.fits')}",
            "WEIGHT_GAIN": "N,N", "WEIGHT_THRESH": f"{_WEIGHT_THRESH:g},{_WEIGHT_THRESH:g}",
            "INTERP_TYPE": "NONE,NONE",
            "PHOT_APERTURES": ",".join(repr(float(a)) for a in params.phot_apertures),
            "PHOT_AUTOPARAMS": ",".join(repr(float(a)) for a in params.phot_autoparams),
            "SATUR_LEVEL": "1e29", "MAG_ZEROPOINT": repr(float(zeropoint)),
            "GAIN": repr(float(gain)) if gain else "0.0", "PIXEL_SCALE": "1.0",
            "BACK_TYPE": "MANUAL,MANUAL", "BACK_VALUE": "0.0,0.0",
            "CHECKIMAGE_TYPE": "SEGMENTATION", "CHECKIMAGE_NAME": p("seg.fits"),
            "MEMORY_OBJSTACK": "30000", "MEMORY_PIXSTACK": str(max(3_000_000, int(det.size) + 1024)),
            "MEMORY_BUFSIZE": str(max(1024, int(det.shape[0]) + 1)),
            "VERBOSE_TYPE": "QUIET", "WRITE_XML": "N", "NTHREADS": "1",
        }
        with open(p("glaciar.sex"), "w") as fh:
            for k, v in cfg.items():
                fh.write(f"{k:<18s} {v}\n")
        cmd = [exe, f"{p('det.fits')},{p('meas.fits')}", "-c", p("glaciar.sex")]
        try:
            res = subprocess.run(cmd, cwd=wd, capture_output=True, text=True, timeout=timeout)
        except (OSError, subprocess.SubprocessError) as exc:
            raise SExtractorError(f"{exe} could not be run: {exc}") from exc
        if res.returncode != 0 or not os.path.exists(p("cat.fits")) or not os.path.exists(p("seg.fits")):
            tail = (res.stderr or res.stdout or "").strip().splitlines()[-5:]
            raise SExtractorError(f"{exe} failed (exit {res.returncode}): {' | '.join(tail)}")
        with fits.open(p("cat.fits")) as hl:
            cat = np.asarray(hl[1].data).copy() if len(hl) > 1 and hl[1].data is not None else None
        if cat is None:
            cat = np.zeros(0, dtype=[(c, "f8") for c in CATALOG_PARAMS])
        segmap = np.asarray(fits.getdata(p("seg.fits")), dtype=np.int32)
        ver = subprocess.run([exe, "-v"], capture_output=True, text=True).stdout.strip()
        return SExtractorRun(catalog=cat, segmap=segmap, command=cmd, version=ver)
    finally:
        if own:
            shutil.rmtree(wd, ignore_errors=True)


def sextractor_segmentation(det_image, det_rms, params: DetectionParams, meas_image=None, meas_rms=None,
                            **kw) -> Segmentation:
    """The ``source-extractor`` backend's product for a full image.

    Parameters
    ----------
    det_image, det_rms, params, meas_image, meas_rms, **kw
        As :func:`run_sextractor`.

    Returns
    -------
    Segmentation
        ``seg``: SExtractor's check-image renumbered 1..n in catalogue order;
        geometry from X_IMAGE - 1, Y_IMAGE - 1 (0-based), A_IMAGE, B_IMAGE and
        THETA_IMAGE (degrees -> radians); ``flux_iso``: FLUX_ISO of the
        measurement band.
    """
    run = run_sextractor(det_image, det_rms, params, meas_image, meas_rms, **kw)
    cat = run.catalog
    n = len(cat)
    number = np.asarray(cat["NUMBER"], dtype=np.int64) if n else np.zeros(0, dtype=np.int64)
    lut = np.zeros(int(max(number.max(initial=0), run.segmap.max(initial=0))) + 1, dtype=np.int32)
    lut[number] = np.arange(1, n + 1, dtype=np.int32)
    seg = lut[run.segmap]
    f = lambda c: np.asarray(cat[c], dtype=np.float64) if n else np.zeros(0)  # noqa: E731
    return Segmentation(seg=seg, x=f("X_IMAGE") - 1.0, y=f("Y_IMAGE") - 1.0, a=f("A_IMAGE"), b=f("B_IMAGE"),
                        theta=np.deg2rad(f("THETA_IMAGE")), flux_iso=f("FLUX_ISO"))
