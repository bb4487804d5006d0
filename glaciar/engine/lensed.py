"""The sources of a task behind a lens: intrinsic draws, positions and lensed shapes.

The task grid stays in observed (lensed) detection-band magnitude (docs/lensing.md):
a source's nominal magnitude is the one it has in the image, so its stamp flux is the
observed flux and the intrinsic magnitude is ``mag + 2.5 log10 |mu|``; the intrinsic
M_UV follows from it, the intrinsic size from the size law at that M_UV, and the image's
shape from :func:`glaciar.galaxy.lensing.lensed_shape` with kappa and gamma of the field's
lens model (``ctx.lens``, normalised to ``D_ls/D_s = 1``) scaled to the task's redshift.

Placement (random sequential, by rejection)
-------------------------------------------
A lensed source's isolation box depends on where it sits (its magnification and shear),
so the positions cannot be drawn by :func:`glaciar.engine.positions.draw_positions`,
which needs the box sizes first.  Every per-source random number (UV slope, shape, size
deviate) is drawn first, in the order :func:`glaciar.engine.task.draw_task_sources` draws
them; then sources are placed in index order: a candidate pixel uniform over the image
(and a uniform offset inside it) is accepted when it lies in the footprint, the lens is
finite there and the source's lensed box there meets none of the placed boxes (the rule of
:mod:`glaciar.engine.positions`).  Candidates come from one stream consumed in order, so
the positions are a function of the task's seed.  A source that finds no place in
:data:`MAX_TRIES` candidates ends the placement (the first m sources are kept).  Accepted
positions are uniform over the free footprint in the image plane, as V_eff assumes
(uniform source-plane positions weighted by 1/|mu|).

Extreme magnification
---------------------
Where ``|mu| > LENS_MAX_MAGNIFICATION`` or the image's axis ratio falls below the
renderer's ``Q_MIN``, the source is injected with its axis ratio clipped to ``Q_MIN``
and its semi-major axis to ``LENS_MAX_MAGNIFICATION`` x the intrinsic one, and flagged
``FLAG_LENS_EXTREME``; its columns keep the true magnification.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .. import constants as C
from ..galaxy import population, sed
from ..galaxy.lensing import distance_ratio, lensed_shape
from ..galaxy.sersic import Q_MIN, stamp_shape

__all__ = ["LensedSources", "draw_lensed_sources", "MAX_TRIES", "CHUNK"]

#: Candidates tried for one source before the placement stops.
MAX_TRIES = 4096
#: Candidates drawn from the stream at once, and evaluated at once for one source.
CHUNK = 32


@dataclasses.dataclass(frozen=True)
class LensedSources:
    """A lensed task's sources (the first m placed).

    ``draws``: the :class:`glaciar.engine.task.SourceDraws` fields with the image's
    (observed) values; ``x``, ``y``: positions [pixels]; ``columns``: the lensing columns
    (names in :mod:`glaciar.constants`); ``flags``: FLAG_LENS_EXTREME where it applies.
    """

    draws: dict
    x: np.ndarray
    y: np.ndarray
    columns: dict
    flags: np.ndarray


def _half_sizes(ctx, n, r_pix, q, pa):
    ny, nx = stamp_shape(n, r_pix, q, pa, enclosed_fraction=ctx.isolation_fraction)
    return (ny - 1) // 2 + ctx.isolation_margin_pix, (nx - 1) // 2 + ctx.isolation_margin_pix


class _Candidates:
    """The task's stream of candidate positions, consumed in order."""

    def __init__(self, rng, shape):
        self.rng, self.ny, self.nx = rng, int(shape[0]), int(shape[1])
        self.pix = np.empty(0, np.int64)
        self.off = np.empty((0, 2))

    def take(self, start: int, count: int):
        while self.pix.size < start + count:
            self.pix = np.concatenate([self.pix, self.rng.integers(0, self.ny * self.nx, CHUNK)])
            self.off = np.concatenate([self.off, self.rng.random((CHUNK, 2)) - 0.5])
        p = self.pix[start:start + count]
        iy, ix = np.divmod(p, self.nx)
        return p, iy, ix, ix + self.off[start:start + count, 0], iy + self.off[start:start + count, 1]


def _image_of(ctx, k, src, x, y, ratio, size):
    """Lensed properties of source ``k`` at candidate positions (x, y) (arrays)."""
    kap, g1, g2 = (np.asarray(v, float) * ratio for v in ctx.lens(x, y))
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = 1.0 / ((1.0 - kap) ** 2 - g1 ** 2 - g2 ** 2)
        shift = 2.5 * np.log10(np.abs(mu))
    ok = np.isfinite(mu) & np.isfinite(shift)
    shift = np.where(ok, shift, 0.0)
    M_int = src["M_uv"][k] + shift
    r_kpc = size(M_int) * src["scatter"][k]
    r_pix = r_kpc * src["arcsec_per_kpc"] / ctx.pixel_scale_arcsec
    img = lensed_shape(r_pix, src["axis_ratio"][k], src["position_angle_deg"][k],
                       np.where(ok, kap, 0.0), np.where(ok, g1, 0.0), np.where(ok, g2, 0.0))
    with np.errstate(invalid="ignore"):
        extreme = ~(np.abs(mu) <= C.LENS_MAX_MAGNIFICATION) | ~(img.axis_ratio >= Q_MIN)
    r_img = np.minimum(np.where(np.isfinite(img.r_eff), img.r_eff, np.inf),
                       C.LENS_MAX_MAGNIFICATION * r_pix)
    q_img = np.clip(np.nan_to_num(img.axis_ratio, nan=Q_MIN), Q_MIN, 1.0)
    r_img = ctx.quantise_r_eff(r_img)
    return dict(ok=ok, kappa=kap, gamma=np.hypot(g1, g2), mu=mu, shift=shift, M_int=M_int,
                r_kpc=r_kpc, r_pix_int=r_pix, r_img=r_img, q_img=q_img,
                pa_img=np.nan_to_num(img.position_angle_deg), extreme=extreme & ok)


def draw_lensed_sources(rng: np.random.Generator, n: int, z: float, mag: float, ctx) -> LensedSources:
    """Draw and place the ``n`` sources of a lensed task at redshift ``z``, observed magnitude
    ``mag`` (detection band, AB).

    Parameters
    ----------
    rng : numpy.random.Generator
        The task's stream.
    n : int
        Sources requested.
    z, mag : float
        The task's redshift and nominal observed magnitude.
    ctx : glaciar.engine.context.FieldContext
        The field, with ``ctx.lens``: a callable ``(x, y) -> (kappa, gamma1, gamma2)``
        normalised to ``D_ls/D_s = 1`` with attribute ``z_lens``.

    Returns
    -------
    LensedSources
    """
    if ctx.magnitude_type != "apparent":
        raise ValueError("survey.lens: lensed fields need grid.magnitude_type: apparent (the "
                         "grid is in observed, magnified magnitude; docs/lensing.md)")
    model = ctx.source_model
    beta, mag_obs, M_obs = sed.draw_spectra(rng, n, z, mag, model, ctx.filters,
                                            detection_index=ctx.detection_index,
                                            cosmology=ctx.cosmology)
    shapes = population.draw_shapes(rng, n, model)
    eps = rng.standard_normal(n) if model.r_eff_scatter_dex > 0 else np.zeros(n)
    law = dataclasses.replace(model, r_eff_scatter_dex=0.0)

    def size(M_uv):
        return population.r_eff_kpc(z, law, M_uv=M_uv)

    src = dict(M_uv=np.asarray(M_obs, float), axis_ratio=shapes["axis_ratio"],
               position_angle_deg=shapes["position_angle_deg"],
               scatter=10.0 ** (model.r_eff_scatter_dex * eps),
               arcsec_per_kpc=float(population.kpc_to_arcsec(1.0, z, ctx.cosmology)))
    ratio = float(distance_ratio(ctx.lens.z_lens, z, ctx.cosmology))

    footprint = ctx.footprint.reshape(-1)
    stream = _Candidates(rng, ctx.shape)
    cursor = 0
    placed: list[tuple[int, int, int, int]] = []
    boxes = np.empty((0, 4), np.int64)
    chosen: list[dict] = []
    for k in range(n):
        got = None
        tried = 0
        while got is None and tried < MAX_TRIES:
            p, iy, ix, x, y = stream.take(cursor, CHUNK)
            inside = np.asarray(footprint[p], dtype=bool)
            idx = np.flatnonzero(inside)
            if idx.size:
                im = _image_of(ctx, k, src, x[idx], y[idx], ratio, size)
                for j, c in enumerate(idx):
                    if not im["ok"][j]:
                        continue
                    h, w = _half_sizes(ctx, shapes["sersic_n"][k], im["r_img"][j],
                                       im["q_img"][j], im["pa_img"][j])
                    if boxes.size and np.any((np.abs(iy[c] - boxes[:, 0]) <= h + boxes[:, 2])
                                             & (np.abs(ix[c] - boxes[:, 1]) <= w + boxes[:, 3])):
                        continue
                    got = (c, j, h, w)
                    break
            if got is None:
                cursor += CHUNK
                tried += CHUNK
        if got is None:
            break
        c, j, h, w = got
        cursor += c + 1
        placed.append((int(iy[c]), int(ix[c]), int(h), int(w)))
        boxes = np.asarray(placed, np.int64)
        chosen.append({key: (v[j] if np.ndim(v) else v) for key, v in im.items()}
                      | {"x": x[c], "y": y[c]})
    m = len(chosen)

    def col(key):
        return np.array([d[key] for d in chosen], dtype=float).reshape(m)

    r_img_pix = col("r_img")
    r_img_arcsec = r_img_pix * ctx.pixel_scale_arcsec
    shift = col("shift")
    draws = dict(beta=np.asarray(beta, float)[:m], mag_in=mag_obs[:m], M_uv=src["M_uv"][:m],
                 sersic_n=shapes["sersic_n"][:m], axis_ratio=col("q_img"),
                 position_angle_deg=col("pa_img"),
                 r_eff_kpc=r_img_arcsec / src["arcsec_per_kpc"], r_eff_arcsec=r_img_arcsec,
                 r_eff_pix=r_img_pix)
    columns = {
        C.COL_MAGNIFICATION: col("mu"), C.COL_KAPPA: col("kappa"), C.COL_GAMMA: col("gamma"),
        C.COL_MAG_INTRINSIC: mag_obs[:m, ctx.detection_index] + shift,
        C.COL_M_UV_INTRINSIC: col("M_int"),
        C.COL_R_EFF_ARCSEC_INTRINSIC: col("r_pix_int") * ctx.pixel_scale_arcsec,
        C.COL_R_EFF_KPC_INTRINSIC: col("r_kpc"),
        C.COL_AXIS_RATIO_INTRINSIC: shapes["axis_ratio"][:m],
        C.COL_PA_INTRINSIC: shapes["position_angle_deg"][:m],
    }
    flags = np.where(np.array([bool(d["extreme"]) for d in chosen], dtype=bool).reshape(m),
                     C.FLAG_LENS_EXTREME, 0).astype(np.int64)
    return LensedSources(draws, col("x"), col("y"), columns, flags)
