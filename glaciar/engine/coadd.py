"""Coadded detection images: several bands combined pixel by pixel, injections included.

Deep surveys detect on a stack of bands rather than on one band. Two stacks:

* ``ivw`` -- inverse-variance weighted mean, ``C = sum(w_b I_b) / sum(w_b)`` with
  ``w_b = 1 / rms_b^2`` per pixel; its noise is ``1 / sqrt(sum w_b)``. Linear:
  an injected source adds the same weighted mean of its band stamps.
* ``chi2`` -- the chi-square image of Szalay, Connolly & Szokoly (1999),
  ``X = sum((I_b / rms_b)^2)`` over the k bands with data, *Gaussianised*: each
  pixel is replaced by the standard-normal deviate with the same upper-tail
  probability, ``z = Phi^-1(1 - F_k(X))`` (F_k: the chi-square CDF with k
  degrees of freedom). On pure noise z is exactly N(0, 1), so DETECT_THRESH
  keeps its meaning (sigma above the background) with an RMS of 1. Not linear:
  the injected image of each band is combined again wherever a window is read.

A band without data at a pixel (RMS infinite or not positive) drops out of
that pixel's stack; a pixel without data in every band has no data.

:class:`CoaddScene` reads the stack through windows of the band
:class:`~glaciar.engine.scene.Scene` objects, so the detection image of a task
is never materialised, as for a single band.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy import special

__all__ = ["COADD_METHODS", "coadd", "CoaddScene"]

#: Stacks glaciar builds.
COADD_METHODS = ("ivw", "chi2")
#: Largest |z| of the Gaussianised chi-square image (tail probabilities below ~1e-300
#: underflow; 37 sigma is far above any detection threshold).
_Z_MAX = 37.0


def _weights(rms: np.ndarray) -> np.ndarray:
    r = np.asarray(rms, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(r) & (r > 0), 1.0 / (r * r), 0.0)


#: Pixels per row block of :func:`coadd` on a large image (its float64 work takes
#: ~60 bytes per pixel and band: a block bounds it).
COADD_BLOCK_PIXELS = 1 << 20


def coadd(images: Sequence[np.ndarray], rms: Sequence[np.ndarray], method: str = "ivw",
          dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Stack band images (same shape, background-subtracted) into a detection image.

    Parameters
    ----------
    images : sequence of ndarray
        Band images [image units of each band].
    rms : sequence of ndarray
        Their per-pixel RMS (inf or <= 0 where there are no data).
    method : {"ivw", "chi2"}
    dtype : numpy dtype
        Of the results: computed in float64 and rounded to it (float32: a field's
        detection image without its float64 copy).

    Returns
    -------
    image, rms : ndarray
        The stack and its RMS (``ivw``: ``1/sqrt(sum w)``; ``chi2``: 1); RMS inf
        and image 0 where no band has data.  Pixel by pixel, so a large image is
        stacked by blocks of rows (:data:`COADD_BLOCK_PIXELS`) with the same values;
        the resident pages of memory-mapped inputs (a field's spilled bands) are
        dropped block by block.
    """
    from glaciar.engine.blocks import row_blocks
    from glaciar.engine.detect import release_mapped

    if method not in COADD_METHODS:
        raise ValueError(f"coadd method must be one of {', '.join(COADD_METHODS)}, got {method!r}")
    if len(images) != len(rms) or not images:
        raise ValueError("coadd needs one RMS map per image and at least one image")
    shape = np.shape(images[0])
    if len(shape) != 2 or shape[0] * shape[1] <= COADD_BLOCK_PIXELS:
        out, err = _coadd(images, rms, method)
        return out.astype(dtype, copy=False), err.astype(dtype, copy=False)
    out, err = np.empty(shape, dtype=dtype), np.empty(shape, dtype=dtype)
    for y0, y1, _, _ in row_blocks(shape, COADD_BLOCK_PIXELS):
        sl = slice(y0, y1)
        out[sl], err[sl] = _coadd([im[sl] for im in images], [r[sl] for r in rms], method)
        release_mapped(*images, *rms)
    return out, err


def _coadd(images, rms, method):
    """:func:`coadd` of whole arrays, in float64."""
    w = [_weights(r) for r in rms]
    wsum = np.sum(w, axis=0)
    has = wsum > 0
    if method == "ivw":
        num = np.sum([wi * np.where(wi > 0, np.asarray(im, np.float64), 0.0)
                      for wi, im in zip(w, images)], axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.where(has, num / wsum, 0.0)
            err = np.where(has, 1.0 / np.sqrt(wsum), np.inf)
        return out, err
    x = np.sum([wi * np.where(wi > 0, np.asarray(im, np.float64), 0.0) ** 2
                for wi, im in zip(w, images)], axis=0)
    k = np.sum([wi > 0 for wi in w], axis=0)
    z = np.zeros(x.shape)
    ok = k > 0
    # Upper-tail probability of chi2_k at x, then the normal deviate with that tail.
    tail = special.chdtrc(k[ok], x[ok])
    z[ok] = np.clip(-special.ndtri(np.clip(tail, 1e-300, 1.0)), -_Z_MAX, _Z_MAX)
    return z, np.where(ok, 1.0, np.inf)


class CoaddScene:
    """The stack of several band scenes, read through windows like a :class:`Scene`.

    Parameters
    ----------
    scenes : sequence of Scene
        The injected band scenes to stack (same shape).
    rms : sequence of ndarray
        Their RMS maps.
    method : {"ivw", "chi2"}
    """

    def __init__(self, scenes, rms, method: str = "ivw"):
        if method not in COADD_METHODS:
            raise ValueError(f"coadd method must be one of {', '.join(COADD_METHODS)}, got {method!r}")
        self.scenes = list(scenes)
        self.rms = list(rms)
        self.method = method
        self.shape = self.scenes[0].shape
        # No stamps of its own: windows combine the band scenes' stamps.
        self.stamps = []

    def templates(self) -> list:
        """No templates of its own (as :meth:`glaciar.engine.scene.Scene.templates`)."""
        return []

    def window(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """The stack of the injected band windows (clipped to the image)."""
        ny, nx = self.shape
        y0, x0, y1, x1 = max(int(y0), 0), max(int(x0), 0), min(int(y1), ny), min(int(x1), nx)
        images = [s.window(y0, y1, x0, x1) for s in self.scenes]
        return coadd(images, [r[y0:y1, x0:x1] for r in self.rms], self.method)[0]

    def paste_windows(self, canvas: np.ndarray, rects, oy, ox) -> None:
        """Write many stacked windows into one tiled array (as :meth:`Scene.paste_windows`)."""
        rects = np.asarray(rects, dtype=np.int64).reshape(-1, 4)
        oy = np.asarray(oy, dtype=np.int64).ravel()
        ox = np.asarray(ox, dtype=np.int64).ravel()
        bands = [np.zeros(canvas.shape) for _ in self.scenes]
        rms = [np.full(canvas.shape, np.inf) for _ in self.scenes]
        for s, img in zip(self.scenes, bands):
            s.paste_windows(img, rects, oy, ox)
        for r, out in zip(self.rms, rms):
            for (y0, y1, x0, x1), cy, cx in zip(rects.tolist(), oy.tolist(), ox.tolist()):
                out[cy:cy + y1 - y0, cx:cx + x1 - x0] = r[y0:y1, x0:x1]
        stacked = coadd(bands, rms, self.method)[0]
        for (y0, y1, x0, x1), cy, cx in zip(rects.tolist(), oy.tolist(), ox.tolist()):
            sl = (slice(cy, cy + y1 - y0), slice(cx, cx + x1 - x0))
            canvas[sl] = stacked[sl]

    def clipped(self) -> np.ndarray:
        """Stamps partly outside the image (from the first band scene)."""
        return self.scenes[0].clipped()

    def full(self) -> np.ndarray:
        """The whole stacked injected image (float64); for validation mode."""
        return self.window(0, self.shape[0], 0, self.shape[1])
