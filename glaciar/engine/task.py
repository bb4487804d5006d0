"""One task, from random draws to per-source rows: the pure function workers call.

A task is (field, z, nominal magnitude, iteration).  Everything random in it
comes from one stream, ``numpy.random.SeedSequence(seed, spawn_key=(field key,
z key, mag key, iteration))``, so a task's rows do not depend on which worker
ran it, in which order, or whether the run was resumed.  The keys are derived
from the field's name and the exact z and magnitude values, not from grid
positions, so adding cells or iterations to a run leaves every finished task's
stream, and rows, as they were.  The injected sources' shot noise (bands with a
gain) comes from child streams of that ``SeedSequence``, one per band
(:mod:`glaciar.engine.shotnoise`): it leaves the task's own draws as they are.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from .. import constants as C
from ..galaxy import population, sed
from .depth import depth_at
from .interlopers import draw_interlopers
from .lensed import draw_lensed_sources
from .measure import MeasureSetup, measure_injected
from .positions import draw_positions
from .scene import Scene
from .shotnoise import add_shot_noise, shot_noise_gains, shot_noise_rng
from .user_selection import apply_selection

__all__ = ["TaskSpec", "task_rng", "field_key", "grid_key", "run_task", "task_columns", "SourceDraws",
           "draw_task_sources"]


@dataclass(frozen=True)
class TaskSpec:
    """Identity of one task on the simulation grid."""

    field: str
    field_index: int
    z_index: int
    mag_index: int
    iteration: int
    z: float
    mag: float
    #: "" for the target population; "interloper-<settings hash>" for interloper tasks
    #: (glaciar.plan.interloper_tasks, glaciar.engine.interlopers).
    population: str = ""

    def spawn_key(self) -> tuple[int, ...]:
        key = (field_key(self.field), grid_key(self.z), grid_key(self.mag), self.iteration)
        # Another population, another stream; the target's keys are unchanged.
        return key + (field_key(self.population),) if self.population else key


def field_key(field: str) -> int:
    """A stable 63-bit integer for a field name (independent of the field list's order)."""
    return int.from_bytes(hashlib.sha256(field.encode("utf-8")).digest()[:8], "big") >> 1


def grid_key(value: float) -> int:
    """A non-negative integer that identifies a grid value exactly (its float64 bits).

    Injective: two values that differ in any bit (z = 9.0 and 9.00004) get different
    random streams, as their task files differ (a rounded key gave them the same draws).
    """
    return int(np.array(float(value) + 0.0, dtype=np.float64).view(np.uint64))


def task_rng(seed: int, spec: TaskSpec) -> tuple[np.random.Generator, int]:
    """The task's random generator and a 63-bit integer that identifies its stream."""
    ss = np.random.SeedSequence(int(seed), spawn_key=spec.spawn_key())
    ident = int(ss.generate_state(2, dtype=np.uint32).view(np.uint64)[0] >> np.uint64(1))
    return np.random.default_rng(ss), ident


@dataclass(frozen=True)
class SourceDraws:
    """Intrinsic properties of the sources of one task (arrays of length n)."""

    beta: np.ndarray
    mag_in: np.ndarray          #: (n, n_bands) total input AB magnitudes (+inf: no flux)
    M_uv: np.ndarray
    sersic_n: np.ndarray
    axis_ratio: np.ndarray
    position_angle_deg: np.ndarray
    r_eff_kpc: np.ndarray
    r_eff_arcsec: np.ndarray
    r_eff_pix: np.ndarray


def draw_task_sources(rng: np.random.Generator, n: int, z: float, mag: float, ctx) -> SourceDraws:
    """Draw the spectra, brightness, shapes and sizes of ``n`` sources at redshift ``z``.

    ``mag`` is the apparent AB magnitude in the detection band, or M_UV at rest
    1600 A when the grid's magnitude type is ``absolute``.
    """
    model = ctx.source_model
    beta, mag_in, M_uv = sed.draw_spectra(rng, n, z, mag, model, ctx.filters,
                                          detection_index=ctx.detection_index,
                                          cosmology=ctx.cosmology,
                                          absolute=ctx.magnitude_type == "absolute")
    shapes = population.draw_shapes(rng, n, model)
    r_kpc = population.r_eff_kpc(z, model, M_uv=M_uv, rng=rng)
    r_arcsec = population.kpc_to_arcsec(r_kpc, z, ctx.cosmology)
    r_pix = ctx.quantise_r_eff(r_arcsec / ctx.pixel_scale_arcsec)
    r_arcsec = r_pix * ctx.pixel_scale_arcsec
    return SourceDraws(beta=np.asarray(beta, float), mag_in=mag_in, M_uv=np.asarray(M_uv, float),
                       sersic_n=shapes["sersic_n"], axis_ratio=shapes["axis_ratio"],
                       position_angle_deg=shapes["position_angle_deg"],
                       r_eff_kpc=np.asarray(r_kpc, float) * np.ones(n),
                       r_eff_arcsec=np.asarray(r_arcsec, float) * np.ones(n),
                       r_eff_pix=np.asarray(r_pix, float) * np.ones(n))


def _interloper_sources(rng, spec: TaskSpec, ctx, interlopers) -> tuple[SourceDraws, dict]:
    """The draws of an interloper task (:func:`glaciar.engine.interlopers.draw_interlopers`)."""
    if interlopers is None:
        raise ValueError(f"task of population {spec.population!r} needs the run's interloper "
                         "model (config section interlopers:)")

    def quantise(r_arcsec):
        r_pix = ctx.quantise_r_eff(r_arcsec / ctx.pixel_scale_arcsec)
        return r_pix, r_pix * ctx.pixel_scale_arcsec
    d = draw_interlopers(rng, interlopers, spec.z, spec.mag, ctx.filters, ctx.detection_index,
                         ctx.cosmology, quantise)
    extra = d.pop("extra")
    return SourceDraws(**d), extra


def run_task(ctx, spec: TaskSpec, seed: int, *, mode: str = "windowed",
             skip_faint_bands: bool = True, interlopers=None):
    """Run one task on a prepared field context and return its per-source rows.

    A pandas DataFrame of :func:`task_columns` (same parameters), one row per source.
    """
    import pandas as pd     # not on the workers' path (task_columns): its import costs ~22 MB

    return pd.DataFrame(task_columns(ctx, spec, seed, mode=mode,
                                     skip_faint_bands=skip_faint_bands, interlopers=interlopers))


def task_columns(ctx, spec: TaskSpec, seed: int, *, mode: str = "windowed",
                 skip_faint_bands: bool = True, interlopers=None) -> dict[str, np.ndarray]:
    """Run one task on a prepared field context and return its per-source columns.

    The rows of :func:`run_task` without the DataFrame: a dict of 1-d arrays of one length
    (one element per source), in the table's column order.  What the workers write
    (:func:`glaciar.store.write_task_table` takes it as it is), so that a run's tasks
    import no pandas (~22 MB resident in every worker, and in ``simulate``'s own process
    with one worker).

    Parameters
    ----------
    ctx : glaciar.engine.context.FieldContext
        Images, noise, local depth map, reference extraction, template cache and settings
        of the field.
    spec : TaskSpec
        The (field, z, mag, iteration) cell.
    seed : int
        The run's seed.
    mode : {"windowed", "full"}
        Detection mode (``"full"`` re-extracts the whole frame; for validation).
    skip_faint_bands : bool
        Render no stamp in a band where the source has no flux or is fainter
        than FAINT_MAG_LIMIT (blueward of the break).  The skip is exact: with
        it off, those bands receive stamps of zero or < 1e-9 counts, and the
        rows are the same (tests/engine/test_task.py).  Shot noise is never drawn
        for those stamps either, so it holds with shot noise too.
    interlopers : glaciar.engine.interlopers.InterloperModel, optional
        The run's interloper population: needed by tasks whose ``spec.population`` is set.
    """
    rng, ident = task_rng(seed, spec)
    extra = {}
    lensed = None
    if spec.population:
        # Interlopers are injected unlensed, even in a lensed field (docs/lensing.md).
        src, extra = _interloper_sources(rng, spec, ctx, interlopers)
        n = src.beta.size
    else:
        n = ctx.n_galaxies
    if not spec.population and getattr(ctx, "lens", None) is not None:
        # Behind a lens: drawn, placed and shaped by glaciar.engine.lensed (docs/lensing.md).
        lensed = draw_lensed_sources(rng, n, spec.z, spec.mag, ctx)
        src, x, y = SourceDraws(**lensed.draws), lensed.x, lensed.y
    else:
        if not spec.population:
            src = draw_task_sources(rng, n, spec.z, spec.mag, ctx)
        # Isolation boxes (most of the light + 2 PSF FWHM) decide how close two sources may sit.
        hh, hw = ctx.stamp_half_sizes(src.sersic_n, src.r_eff_pix, src.axis_ratio, src.position_angle_deg)
        x, y = draw_positions(rng, ctx.footprint, hh, hw,
                              n_footprint=getattr(ctx, "footprint_count", None))
    m = x.size
    if m < n:
        src = SourceDraws(**{k: v[:m] for k, v in src.__dict__.items()})
        extra = {k: v[:m] for k, v in extra.items()}

    bands = ctx.bands
    flags = np.zeros(m, dtype=np.int64) if lensed is None else lensed.flags.copy()
    iy = np.clip(np.floor(y + 0.5).astype(np.int64), 0, ctx.shape[0] - 1)
    ix = np.clip(np.floor(x + 0.5).astype(np.int64), 0, ctx.shape[1] - 1)
    for band in bands:
        # Only reachable with survey.coverage narrower than the bands (holes kept and flagged).
        flags[~np.isfinite(ctx.rms[band][iy, ix])] |= C.FLAG_NO_DATA
    flux_in = np.empty((m, len(bands)))
    mag_stamp = np.empty((m, len(bands)))
    stamps = {b: [] for b in bands}
    templates = [None] * m      # each source's own detection-band stamp (status-2 flux test)
    shot_gains = shot_noise_gains(ctx.source_model.shot_noise, ctx.gains)
    # A redshift's stamps make way for the next one's (sizes follow z): one z's stamps cached.
    ctx.cache.begin_group((spec.z, spec.population))
    for j, band in enumerate(bands):
        flux = sed.mag_to_flux(src.mag_in[:, j], ctx.zeropoints[band])
        faint = sed.bands_to_skip(src.mag_in[:, j:j + 1])[:, 0]
        skip = faint if skip_faint_bands else np.zeros(m, dtype=bool)
        flux_in[:, j] = np.where(skip, 0.0, flux)
        frac = np.zeros(m)
        for i in np.flatnonzero(~skip):
            ps = ctx.cache.stamp(band, src.sersic_n[i], src.axis_ratio[i], src.position_angle_deg[i],
                                 src.r_eff_pix[i], x[i], y[i])
            frac[i] = ps.in_stamp_fraction
            # Scaled lazily, only where a detection window reads it.
            stamps[band].append((ps.y0, ps.x0, ps.data, flux_in[i, j]))
            if j == ctx.detection_index:
                templates[i] = stamps[band][-1]
            if (ps.y0 < 0 or ps.x0 < 0 or ps.y0 + ps.data.shape[0] > ctx.shape[0]
                    or ps.x0 + ps.data.shape[1] > ctx.shape[1]):
                flags[i] |= C.FLAG_STAMP_CLIPPED
        mag_stamp[:, j] = sed.flux_to_mag(flux_in[:, j] * frac, ctx.zeropoints[band])
        if band in shot_gains:
            # Noise fixed once per stamp, from the band's own child stream: the task's
            # stream (above) and the noiseless templates of the status-2 test are untouched.
            stamps[band] = add_shot_noise(stamps[band], shot_gains[band],
                                          shot_noise_rng(seed, spec.spawn_key(), field_key(band)),
                                          noisy=~faint[~skip])

    scenes = {b: Scene(ctx.bases[b], stamps[b]) for b in bands}
    jd = ctx.detection_index
    det_scene, det_rms = ctx.detection_scene(scenes)
    meas = measure_injected(MeasureSetup.of_field(ctx), det_scene, det_rms, scenes, x, y,
                            flux_in[:, jd], src.mag_in[:, jd], mode=mode, input_templates=templates)

    cols: dict[str, np.ndarray] = {
        C.COL_FIELD: np.full(m, spec.field, dtype=object),
        C.COL_Z: np.full(m, spec.z),
        C.COL_MAG: np.full(m, spec.mag),
        C.COL_ITERATION: np.full(m, spec.iteration, dtype=np.int64),
        C.COL_TASK_SEED: np.full(m, ident, dtype=np.int64),
        C.COL_SOURCE: np.arange(m, dtype=np.int64),
        C.COL_X: x, C.COL_Y: y,
        C.COL_DEPTH: depth_at(ctx.depth, x, y),
        C.COL_SERSIC_N: src.sersic_n, C.COL_AXIS_RATIO: src.axis_ratio,
        C.COL_PA: src.position_angle_deg, C.COL_R_EFF_KPC: src.r_eff_kpc,
        C.COL_R_EFF_ARCSEC: src.r_eff_arcsec, C.COL_R_EFF_PIX: src.r_eff_pix,
        C.COL_BETA: src.beta, C.COL_M_UV: src.M_uv,
        C.COL_MAG_INPUT: src.mag_in[:, jd],
        **({} if lensed is None else lensed.columns),
    }
    for j, band in enumerate(bands):
        cols[C.band_column("mag_in", band)] = src.mag_in[:, j]
        cols[C.band_column("mag_in_stamp", band)] = mag_stamp[:, j]
        cols[C.band_column("flux_in", band)] = flux_in[:, j]
    for key, val in meas.items():
        if key == C.COL_FLAGS:
            flags |= np.asarray(val, dtype=np.int64)
        else:
            cols[key] = np.asarray(val)
    cols[C.COL_FLAGS] = flags
    cols.update(extra)
    status = np.asarray(cols[C.COL_STATUS])
    recovered = np.isin(status, C.RECOVERED_STATUSES)
    cols[C.COL_RECOVERED] = recovered
    # A probabilistic user selection draws from the task's own stream id: reproducible.
    # (Selections read a mapping of columns as they read a DataFrame: the same values.)
    passed, probability = apply_selection(ctx.selection, cols, (ident,))
    cols[C.COL_SELECTED] = recovered & passed
    if probability is not None:
        cols[C.COL_P_SELECTED] = probability
    return cols
