"""A band image plus sparse injected stamps, read through windows.

The injected image of a task is never materialised: ``Scene.window`` adds the
stamps that overlap a cut-out to a float64 copy of the original pixels.  Stamps
are *added* (GLACiAR assigned them, erasing 13 % of its sources).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from glaciar.engine.compiled import KERNELS as KERNEL

__all__ = ["Scene", "KERNEL"]


class Scene:
    """Background-subtracted band image with injected stamps.

    Parameters
    ----------
    base : ndarray, shape (ny, nx)
        Background-subtracted original band image [image units].  Any float
        dtype and byte order; it may be a memmap-derived view and is never
        copied whole except by :meth:`full`.
    stamps : sequence of (y0, x0, data) or (y0, x0, data, flux)
        ``data`` (2-d, image units) is added to ``base[y0:y0+ny, x0:x0+nx]``;
        with ``flux``, ``data * flux`` is added, multiplied only where a
        window reads it (``data`` may then be a shared unit-flux template; the
        pixels equal those of a stamp pre-multiplied by ``flux``, bit for
        bit).  Stamps may lie partly (or wholly) outside the image; the
        outside part is dropped.  Stamps are added in the order given, so
        overlapping stamps sum and the result is the same whichever window
        reads it.  Stamp arrays are never modified.
    """

    def __init__(self, base: np.ndarray, stamps: Sequence[tuple[int, int, np.ndarray]] = ()):
        if np.ndim(base) != 2:
            raise ValueError(f"Scene base must be a 2-d image, got {np.ndim(base)} dimensions")
        self.base = base
        self.shape = tuple(int(s) for s in base.shape)
        stamp_list = []
        scales = []
        for k, st in enumerate(stamps):
            try:
                if len(st) == 4:
                    y0, x0, data, flux = st
                    flux = float(flux)
                else:
                    (y0, x0, data), flux = st, None
            except (TypeError, ValueError):
                raise ValueError(f"stamp {k} must be a (y0, x0, data) or (y0, x0, data, flux) tuple") from None
            data = np.asarray(data, dtype=np.float64)
            if data.ndim != 2:
                raise ValueError(f"stamp {k} must be 2-d, got shape {data.shape}")
            stamp_list.append((int(y0), int(x0), data))
            scales.append(flux)
        self.stamps = stamp_list
        self._flux = scales
        n = len(stamp_list)
        # Stamp bounding boxes as arrays so a window finds its stamps without a
        # Python loop over all of them.
        self._y0 = np.array([s[0] for s in stamp_list], dtype=np.int64).reshape(n)
        self._x0 = np.array([s[1] for s in stamp_list], dtype=np.int64).reshape(n)
        self._y1 = self._y0 + np.array([s[2].shape[0] for s in stamp_list], dtype=np.int64).reshape(n)
        self._x1 = self._x0 + np.array([s[2].shape[1] for s in stamp_list], dtype=np.int64).reshape(n)

    def templates(self) -> list:
        """Each stamp as ``(y0, x0, data, flux)``, in order (flux 1.0 for a stamp given
        pre-multiplied): what was injected, for the status-2 template flux test."""
        return [(y0, x0, d, 1.0 if f is None else f) for (y0, x0, d), f in zip(self.stamps, self._flux)]

    def clipped(self) -> np.ndarray:
        """Boolean array: True for stamps that are partly or wholly outside the image."""
        ny, nx = self.shape
        return (self._y0 < 0) | (self._x0 < 0) | (self._y1 > ny) | (self._x1 > nx)

    def window(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """Float64 copy of ``base[y0:y1, x0:x1]`` plus every overlapping stamp.

        The window is clipped to the image, so the result may be smaller than
        requested.  Non-finite base pixels are returned as they are.
        """
        ny, nx = self.shape
        y0 = max(int(y0), 0)
        x0 = max(int(x0), 0)
        y1 = min(int(y1), ny)
        x1 = min(int(x1), nx)
        if y1 <= y0 or x1 <= x0:
            return np.zeros((max(y1 - y0, 0), max(x1 - x0, 0)))
        out = np.array(self.base[y0:y1, x0:x1], dtype=np.float64)
        if len(self.stamps):
            hit = np.flatnonzero((self._y0 < y1) & (self._y1 > y0) & (self._x0 < x1) & (self._x1 > x0))
            for k in hit:
                self._add(out, k, y0, y1, x0, x1)
        return out

    def _add(self, out, k, y0, y1, x0, x1):
        sy0, sx0, data = self.stamps[k]
        ay0 = max(sy0, y0)
        ax0 = max(sx0, x0)
        ay1 = min(sy0 + data.shape[0], y1)
        ax1 = min(sx0 + data.shape[1], x1)
        part = data[ay0 - sy0:ay1 - sy0, ax0 - sx0:ax1 - sx0]
        flux = self._flux[k]
        out[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0] += part if flux is None else part * flux

    def paste_windows(self, canvas: np.ndarray, rects, oy, ox) -> None:
        """Write many windows of the injected image into one tiled array.

        Window ``k`` (image rows ``rects[k, 0]:rects[k, 1]``, columns
        ``rects[k, 2]:rects[k, 3]``, inside the image) goes to
        ``canvas[oy[k]:, ox[k]:]``.  Each written window is bit-identical to
        :meth:`window` (base cast to float64, then the overlapping stamps added
        in their order), but the overlap search is done once for all windows.
        """
        rects = np.asarray(rects, dtype=np.int64).reshape(-1, 4)
        oy = np.asarray(oy, dtype=np.int64).ravel()
        ox = np.asarray(ox, dtype=np.int64).ravel()
        base = self.base
        rl, ol = rects.tolist(), np.stack([oy, ox], axis=1).tolist()
        for (y0, y1, x0, x1), (cy, cx) in zip(rl, ol):
            canvas[cy:cy + y1 - y0, cx:cx + x1 - x0] = base[y0:y1, x0:x1]
        if not self.stamps or not len(rl):
            return
        hit = ((self._y0[:, None] < rects[None, :, 1]) & (self._y1[:, None] > rects[None, :, 0])
               & (self._x0[:, None] < rects[None, :, 3]) & (self._x1[:, None] > rects[None, :, 2]))
        ks, ws = np.nonzero(hit)            # stamp-major: each pixel gets its stamps in order
        if KERNEL is not None and canvas.dtype == np.float64 and canvas.flags.c_contiguous:
            # One compiled loop over the pairs: the same products and sums, in the same order.
            KERNEL.add_stamp_parts(canvas, [st[2] for st in self.stamps], self._flux, self._box_array(),
                                   np.ascontiguousarray(rects), np.stack([oy, ox], axis=1), ks, ws)
            return
        boxes = self.__dict__.get("_boxes")
        if boxes is None:       # stamp boxes as Python ints: the loop below is per pair
            boxes = self._boxes = self._box_array().tolist()
        stamps, fluxes = self.stamps, self._flux
        for k, w in zip(ks.tolist(), ws.tolist()):
            sy0, sy1, sx0, sx1 = boxes[k]
            y0, y1, x0, x1 = rl[w]
            cy, cx = ol[w]
            ay0 = sy0 if sy0 > y0 else y0
            ax0 = sx0 if sx0 > x0 else x0
            ay1 = sy1 if sy1 < y1 else y1
            ax1 = sx1 if sx1 < x1 else x1
            part = stamps[k][2][ay0 - sy0:ay1 - sy0, ax0 - sx0:ax1 - sx0]
            flux = fluxes[k]
            canvas[cy + ay0 - y0:cy + ay1 - y0, cx + ax0 - x0:cx + ax1 - x0] += \
                part if flux is None else part * flux

    def _box_array(self) -> np.ndarray:
        """(n, 4) int64: each stamp's y0, y1, x0, x1 in the image (exclusive ends)."""
        return np.stack([self._y0, self._y1, self._x0, self._x1], axis=1)

    def full(self) -> np.ndarray:
        """The whole injected image (float64 copy); for validation mode."""
        return self.window(0, self.shape[0], 0, self.shape[1])
