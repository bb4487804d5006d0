"""The engine's input: everything a task needs about one field.

A :class:`FieldContext` is built once per field by
:func:`glaciar.fieldprep.build_field_context` (which reads the images); the engine
(:func:`glaciar.engine.task.run_task`) only reads it.  In a run, its measured
arrays (:attr:`FieldContext.MEASURED`) are written once to the run's field cache
and every process maps them read-only (:mod:`glaciar.engine.fieldcache`): the
engine reads them by window, never whole.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field
from typing import ClassVar

import numpy as np

from ..galaxy import population
from ..galaxy.sersic import stamp_shape
from ..galaxy.templates import TemplateCache
from .classify import ClassificationParams
from .detect import DetectionParams

__all__ = ["FieldContext", "R_EFF_LOG_STEP"]


#: r_e is rounded to a logarithmic grid of this step (0.2 %) so that sources whose sizes
#: scatter still share cached templates; the rounded value is the one injected and stored.
R_EFF_LOG_STEP = math.log(1.002)


@dataclass
class FieldContext:
    """Everything a task needs about one field, built once per worker process."""

    field: str
    bands: tuple[str, ...]
    detection_band: str
    detection_index: int
    shape: tuple[int, int]
    pixel_scale_arcsec: float
    zeropoints: dict
    gains: dict
    filters: list
    bases: dict            #: background-subtracted original images (float32)
    rms: dict              #: per-pixel RMS maps (inf where no data)
    mask: np.ndarray       #: True where the detection band has no valid data
    footprint: np.ndarray
    depth: np.ndarray      #: local depth of the detection band [AB mag], NaN off the footprint
    reference: object
    cache: TemplateCache
    isolation_margin_pix: int    #: 2 x the widest PSF FWHM [pixels], added to each isolation box
    source_model: population.SourceModel
    cosmology: object
    magnitude_type: str
    n_galaxies: int
    detection_params: DetectionParams
    classification_params: ClassificationParams
    selection: object
    enclosed_fraction: float
    isolation_fraction: float
    #: band -> CorrelatedNoise applied to photometric errors (bands where it does not apply absent)
    noise_models: dict = dc_field(default_factory=dict)
    #: band -> CorrelatedNoise measured on the field, every band (the manifest's noise record)
    measured_noise: dict = dc_field(default_factory=dict)
    #: Bands stacked into the detection image (empty: the detection band's image), the
    #: stack (glaciar.engine.coadd) and its RMS map.
    coadd_bands: tuple = ()
    coadd_method: str = "ivw"
    detection_image_rms: np.ndarray | None = None
    #: sep background map subtracted from the detection band (SATUR_LEVEL flag); None = 0
    detection_background: np.ndarray | None = None
    #: number of True pixels of ``footprint`` (counted once: placement needs it per task)
    footprint_count: int | None = None
    #: survey.lens: callable (x, y) -> (kappa, gamma1, gamma2) at D_ls/D_s = 1 with attribute
    #: ``z_lens`` (glaciar.lensmaps.LazyFieldLens); None: no lens, today's unlensed path
    lens: object = None
    _shape_cache: dict = dc_field(default_factory=dict)
    #: glaciar.engine.fieldcache.Trimmer of the memory maps behind the arrays (None: in memory)
    _trimmer: object = None

    #: The fields measured from the images (what :mod:`glaciar.engine.fieldcache` stores);
    #: every other field follows from the configuration.
    MEASURED: ClassVar[tuple] = ("bases", "rms", "mask", "footprint", "footprint_count", "depth", "reference",
                "noise_models", "measured_noise", "coadd_bands", "coadd_method",
                "detection_image_rms", "detection_background")

    def measured(self) -> dict:
        """The measured fields (:data:`MEASURED`) by name."""
        return {name: getattr(self, name) for name in self.MEASURED}

    def detection_scene(self, scenes):
        """The detection image of band ``scenes`` (band -> Scene) and its RMS map: the stack of
        ``coadd_bands`` (:class:`~glaciar.engine.coadd.CoaddScene`) or the detection band's."""
        if self.coadd_bands:
            from .coadd import CoaddScene

            return (CoaddScene([scenes[b] for b in self.coadd_bands],
                               [self.rms[b] for b in self.coadd_bands], self.coadd_method),
                    self.detection_image_rms)
        return scenes[self.detection_band], self.rms[self.detection_band]

    @staticmethod
    def quantise_r_eff(r_eff_pix):
        """Round r_e [pixels] to the logarithmic grid of step :data:`R_EFF_LOG_STEP`."""
        r = np.asarray(r_eff_pix, dtype=float)
        return np.exp(np.round(np.log(r) / R_EFF_LOG_STEP) * R_EFF_LOG_STEP)

    def stamp_half_sizes(self, n, r_eff_pix, axis_ratio, pa_deg):
        """Half sizes (rows, cols) of each source's isolation box [pixels].

        The box holds ``isolation_fraction`` of the Sersic light, widened by two
        PSF FWHMs; boxes of two sources never intersect.  A box holding 99.5 % of
        an n = 4 profile spans ~55 r_e, which would leave room for only a handful
        of sources per field, while the light beyond the 95 % box is too faint to
        change a detection: the wings of neighbours may touch, and add.
        """
        hh = np.empty(len(n), dtype=np.int64)
        hw = np.empty(len(n), dtype=np.int64)
        for i, key in enumerate(zip(np.asarray(n, float), np.asarray(r_eff_pix, float),
                                    np.asarray(axis_ratio, float), np.asarray(pa_deg, float))):
            got = self._shape_cache.get(key)
            if got is None:
                ny, nx = stamp_shape(key[0], key[1], key[2], key[3],
                                     enclosed_fraction=self.isolation_fraction)
                got = ((ny - 1) // 2 + self.isolation_margin_pix,
                       (nx - 1) // 2 + self.isolation_margin_pix)
                self._shape_cache[key] = got
            hh[i], hw[i] = got
        return hh, hw
