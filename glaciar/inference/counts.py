"""Expected counts of selected sources per measured-magnitude bin: what a luminosity function predicts.

For a luminosity function phi(M_UV, z) [Mpc^-3 mag^-1] the number of sources that are
recovered, selected and measured with a detection-band magnitude in bin k is

    N_k = Σ_fields Σ_depth Ω(d) ∫ dz dV/dz/dΩ ∫ dM phi(M, z)
              < P(z, m | d) q(k | m, z) >_beta,       m = M + K(z, beta),

P = C S the selection probability (:class:`~glaciar.inference.SelectionFunction`), q the
transfer function p(m_obs in k | m_in = m, z, selected) (:mod:`glaciar.inference.transfer`),
K the map from M_UV to the detection band the injections used (:func:`kcorrection`), and
<.>_beta the Gauss-Hermite average over the injected beta distribution.  For an
absolute-magnitude fit P is evaluated at M itself (the fit already averages over beta) and
only the transfer function needs m.

Numerics (the kernel, :func:`count_kernel`): Simpson in z (``n_z`` = 61 nodes: going to
301 changes the counts by < 2e-5 for selection edges of logistic width 0.15); the midpoint
rule in M on cells of ``dM`` = 0.05 mag; P and q tabulated per z on one grid of m with
step 0.01 mag and read linearly at the points m = M + K(z, beta) (P: < 2e-5 for
completeness steps of width >= 0.25 mag), P per posterior draw and depth node, q per
transfer draw (:meth:`TransferFunction.slice_table`, linear in z between the slices).  The
map from the table to the M cells is one sparse matrix, shared by every draw.  Without
the transfer function (``transfer=False``: measured magnitude := input magnitude) a cell
of M contributes to bin k the fraction of its image [m - dM/2, m + dM/2] inside the bin,
so that the bin edges cost no quadrature error.

Accuracy (tests/inference/test_counts.py), for a step selection (P = 1 to m = 27.5) and a
constant phi, against the comoving volume times the bin width: < 1e-4 relative without
the transfer function; with a Gaussian transfer function (m_obs = m_in + 0.15 +
N(0, 0.2)) against the analytic convolution: < 2e-4 in bins 0.5 mag or more bright of
the step, < 6e-3 at the step, and everywhere within 0.5 % of a full bin's counts (the
tail beyond the step: a few per cent of a small number).

Magnitudes outside the simulated range.  P is the parametric surface's extrapolation
there and q the nearest row's offset distribution.  Neither is measured: the fraction of
each bin's counts that comes from such magnitudes is returned
(``ExpectedCounts.extrapolated_fraction``) and a warning names the bins where it exceeds
``COUNTS_EXTRAPOLATION_TOLERANCE`` (and a tenth of the bin's Poisson error).  Bright of
the range the surface's plateau is a fair guess; faint of it P ~ 0 only if the
simulations reached that far: that is what the warning is for (nothing is set to 0
silently).

Arrays in, arrays out; no file I/O.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .lensed import lensed_count_tables
from .products import beta_nodes, kcorrection
from .transfer import transfer_function

__all__ = ["CountKernel", "ExpectedCounts", "Quadrature", "SurveyVolume", "count_kernel",
           "expected_counts",
           "COUNTS_EXTRAPOLATION_TOLERANCE", "TRANSFER_MARGIN", "M_STEP", "M_TABLE_STEP"]

#: Warn when more than this fraction of a bin's expected counts comes from magnitudes
#: outside the simulated range (module docstring).
COUNTS_EXTRAPOLATION_TOLERANCE = 0.01
#: The default M_UV range reaches this far [mag] beyond the asked-for measured magnitudes
#: (the transfer matrix bins m_obs to 1.5 mag beyond the input range: sources farther
#: away do not scatter in).
TRANSFER_MARGIN = 1.5
#: Width of the M_UV cells of the kernel (midpoint rule) [mag].
M_STEP = 0.05
#: Step of the transfer-function table in input magnitude [mag]; q is linear between.
M_TABLE_STEP = 0.01
#: Simpson nodes in z of the kernel: dz = 0.033 over a redshift range of 2 (module docstring).
N_Z = 61
#: Posterior draws evaluated together (memory: ~ draws x n_z x table size floats).
_CHUNK = 16


@dataclass(frozen=True)
class SurveyVolume:
    """The comoving volume the counts are taken over: redshift range, sky area, cosmology.

    Every field None means the selection function's own (its simulated z range, its
    fit's area, the injections' cosmology).

    Attributes
    ----------
    z_min, z_max : float, optional
        Redshift range; default (and at most) the simulated one.
    area : float or Quantity, optional
        As :meth:`SelectionFunction.effective_volume` (float: arcmin^2).
    cosmology : astropy Cosmology or str, optional
        Default the injections' (``sed.cosmology``).
    """

    z_min: float | None = None
    z_max: float | None = None
    area: object = None
    cosmology: object = None


@dataclass(frozen=True)
class Quadrature:
    """The integration grid of the counts over z, the UV slope beta and M_UV.

    Attributes
    ----------
    n_z : int
        Simpson nodes in z (made odd).
    n_beta : int
        Gauss-Hermite nodes of the beta average.
    dM : float
        M_UV cell width of the default ``M_edges`` [mag].
    """

    n_z: int = N_Z
    n_beta: int = 7
    dM: float = M_STEP


@dataclass(frozen=True)
class CountKernel:
    """N_k = Σ_M phi(M) ``values[d, M, k]``: expected counts per draw as a linear map of phi(M_UV).

    Attributes
    ----------
    M_edges : ndarray (n_M + 1,)
        Cells of absolute UV magnitude [AB mag] (phi is taken at their centres).
    m_obs_edges : ndarray (n_k + 1,)
        Measured detection-band magnitude bins [AB mag].
    values : ndarray (n_d, n_M, n_k)
        Ω ∫ dz dV/dz/dΩ ∫_cell dM <P q>_beta [Mpc^3 mag], per posterior draw (with
        ``phi_z``: also weighted by it, see :func:`count_kernel`).
    extrapolated : ndarray (n_M, n_k)
        The part of ``values`` (mean over draws) from magnitudes outside the simulated range.
    z_range : tuple of float
        Redshift range integrated over.
    transfer : bool
        Whether the transfer function was used (else m_obs := m_in).
    draw_index : ndarray of int (n_d,)
        The selection function's draws used (-1: the pointwise median, ``draws=False``).
    """

    M_edges: np.ndarray
    m_obs_edges: np.ndarray
    values: np.ndarray
    extrapolated: np.ndarray
    z_range: tuple
    transfer: bool
    draw_index: np.ndarray

    @property
    def M_centres(self) -> np.ndarray:
        return 0.5 * (self.M_edges[:-1] + self.M_edges[1:])

    @property
    def n_draws(self) -> int:
        return int(self.values.shape[0])

    def counts(self, phi_values) -> np.ndarray:
        """Expected counts for phi at the cell centres, ``(..., n_M)`` -> ``(..., n_d, n_k)``."""
        phi = np.asarray(phi_values, float)
        return np.einsum("...m,dmk->...dk", phi, self.values)

    def extrapolated_fraction(self, phi_values) -> np.ndarray:
        """Fraction of each bin's (draw-mean) counts from outside the simulated magnitudes, (n_k,)."""
        phi = np.asarray(phi_values, float)
        tot = phi @ self.values.mean(axis=0)
        ext = phi @ self.extrapolated
        return np.where(tot > 0, ext / np.where(tot > 0, tot, 1.0), 0.0)


@dataclass(frozen=True)
class ExpectedCounts:
    """Expected numbers of selected sources per measured-magnitude bin.

    Attributes
    ----------
    m_obs_edges : ndarray (n_k + 1,)
        [AB mag].
    median, lower, upper : ndarray (n_k,)
        Posterior median and central credible interval over the draws.
    draws : ndarray (n_d, n_k) or None
        Per draw (selection-function draw i with transfer draw i mod n_t); None for
        ``draws=False``.
    extrapolated_fraction : ndarray (n_k,)
        Fraction of each bin's counts from magnitudes outside the simulated range.
    M_uv_range, z_range : tuple of float
        Integration ranges.
    transfer : bool
    """

    m_obs_edges: np.ndarray
    median: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    draws: np.ndarray | None
    extrapolated_fraction: np.ndarray
    M_uv_range: tuple
    z_range: tuple
    transfer: bool


def _simpson_weights(x):
    """Composite Simpson weights of an odd number of equally spaced nodes."""
    n = len(x)
    h = (x[-1] - x[0]) / (n - 1)
    w = np.ones(n)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return w * h / 3.0


def _draw_index(n_draws, draws):
    """Indices of the selection function's draws: all (True), ``n`` evenly spaced, or [-1]."""
    if draws is True:
        return np.arange(n_draws)
    if draws is False or draws is None:
        return np.array([-1])
    n = int(draws)
    if n < 1:
        raise ValueError(f"draws must be True, False or a positive number, not {draws!r}")
    if n >= n_draws:
        return np.arange(n_draws)
    return np.unique(np.round(np.linspace(0, n_draws - 1, n)).astype(int))


def _check_edges(edges, who):
    e = np.asarray(edges, float)
    if e.ndim != 1 or len(e) < 2 or np.any(np.isnan(e)) or np.any(np.diff(e) <= 0):
        raise ValueError(f"{who}: m_obs_edges must be >= 2 increasing values (+-inf allowed "
                         "at the ends)")
    if np.any(np.isinf(e[1:-1])):
        raise ValueError(f"{who}: only the first and last m_obs edge may be infinite")
    return e


def _overlap(m, half, E):
    """Fraction of [m - half, m + half] inside each bin of ``E``: (...,) -> (..., n_k)."""
    half = np.broadcast_to(half, m.shape)[..., None]
    lo = np.clip(m[..., None] - half, E[:-1], E[1:])
    hi = np.clip(m[..., None] + half, E[:-1], E[1:])
    return (hi - lo) / (2 * half)


def count_kernel(sf, m_obs_edges, M_edges=None, *, volume: SurveyVolume = SurveyVolume(),
                 sed=None, transfer: bool = True, draws=True, transfer_draws: int | None = None,
                 field: str | None = None, quadrature: Quadrature = Quadrature(), phi_z=None,
                 who: str = "count_kernel") -> CountKernel:
    """The linear map from phi(M_UV) to the expected counts per measured-magnitude bin, per draw.

    Parameters
    ----------
    sf : SelectionFunction
        With an injection SED (``sf.sed`` or ``sed``) and, for ``transfer=True``, a
        transfer matrix.
    m_obs_edges : array_like (n_k + 1,)
        Measured detection-band magnitude bins [AB mag]; the first may be -inf and the
        last +inf.
    M_edges : array_like (n_M + 1,), optional
        Cells of M_UV [AB mag], equally wide.  Default: cells of ``quadrature.dM`` covering every
        M_UV whose image (at any z, beta) lies within ``TRANSFER_MARGIN`` of the asked-for
        m_obs range (open ends: the simulated magnitude range).
    volume : SurveyVolume
        Redshift range, area and cosmology (default the selection function's own).
    sed : InjectionSED, optional
        Default ``sf.sed``.
    transfer : bool
        Use the transfer function (else the measured magnitude is the input magnitude).
    draws : bool or int
        True: every posterior draw; an int: that many, evenly spaced; False: one
        evaluation with the pointwise posterior median of P and the transfer matrix's
        counts estimate.
    transfer_draws : int, optional
        Use the first this many of the transfer matrix's draws (default all); the k-th
        selection-function draw used is paired with transfer draw k mod that number.
    field : str, optional
        One field's area and depths.
    quadrature : Quadrature
        Nodes in z and beta, default M_UV cell width.
    phi_z : ndarray (quadrature.n_z, n_M), optional
        phi(M, z) [Mpc^-3 mag^-1] at the z nodes and cell centres, folded into the kernel
        (then ``values.sum(axis=1)`` are the counts; used by :func:`expected_counts`
        for a phi that evolves with z).

    Returns
    -------
    CountKernel

    Raises
    ------
    ValueError
        No SED, no transfer matrix (``transfer=True``), no area, no redshift range, bad edges.
    """
    import astropy.units as u
    from scipy import sparse

    from ..galaxy.population import get_cosmology

    z_min, z_max, area, cosmology = volume.z_min, volume.z_max, volume.area, volume.cosmology
    n_z, n_beta, dM = quadrature.n_z, quadrature.n_beta, quadrature.dM
    E = _check_edges(m_obs_edges, who)
    sed = sf.sed if sed is None else sed
    if sed is None:
        raise ValueError(f"{who}: this fit records no injection SED (detection filter, beta, "
                         "IGM); pass sed=InjectionSED(...)")
    tm = sf.transfer_matrix
    if transfer and tm is None:
        raise ValueError(f"{who}: this selection function has no transfer matrix; "
                         "pass transfer=False to count input magnitudes")
    cosmology = get_cosmology(sed.cosmology if cosmology is None else cosmology)
    nodes, node_sr = sf._area_nodes(area, field, who)
    lens_fields, plain_fields = sf._lensed_fields(field) if sf.lens_nodes and area is None \
        else ([], None)
    if lens_fields and sf.magnitude_type == "absolute":
        raise ValueError(f"{who}: lensed fields need a fit in apparent (observed) magnitude")
    z_lo, z_hi = sf._z_limits(z_min, z_max, who)
    zz = np.linspace(z_lo, z_hi, int(n_z) | 1)
    n_z = len(zz)
    wz = _simpson_weights(zz) * cosmology.differential_comoving_volume(zz).to_value(
        u.Mpc ** 3 / u.sr)
    bnodes, bw = beta_nodes(sed.beta_mean, sed.beta_sd, n_beta)
    K = kcorrection(zz, bnodes, sed.detection_filter, igm=sed.igm, cosmology=cosmology)
    flux = np.isfinite(K)                                                     # (n_z, n_b)
    if not flux.any():
        raise ValueError(f"{who}: the detection band receives no flux at z = {z_lo:g}-{z_hi:g}")
    if M_edges is None:
        M_edges = default_M_edges(sf, E, K, transfer, dM)
    Me = np.asarray(M_edges, float)
    width = np.diff(Me)
    if (Me.ndim != 1 or len(Me) < 2 or not np.all(np.isfinite(Me)) or np.any(width <= 0)
            or np.ptp(width) > 1e-6 * width[0]):
        raise ValueError(f"{who}: M_edges must be >= 2 finite, equally spaced increasing values")
    Mc, dm = 0.5 * (Me[:-1] + Me[1:]), float(width[0])
    n_M, n_k = len(Mc), len(E) - 1
    mag_lo, mag_hi = sf.domain.get("mag", (sf.model.m_ref - sf.model.m_scale,
                                           sf.model.m_ref + sf.model.m_scale))
    tol = 1e-9 * max(1.0, abs(mag_hi))
    absolute = sf.magnitude_type == "absolute"
    phi_zm = np.ones((n_z, n_M)) if phi_z is None else np.asarray(phi_z, float).reshape(n_z, n_M)

    # The points (z, M, beta) with flux, their images m = M + K and quadrature weights.
    zi, ji, bi = np.nonzero(np.broadcast_to(flux[:, None, :], (n_z, n_M, len(bnodes))))
    m_pt = Mc[ji] + K[zi, bi]
    w_pt = wz[zi] * bw[bi] * phi_zm[zi, ji] * dm           # Simpson x beta x phi x cell width
    m_model = Mc[ji] if absolute else m_pt
    ext_pt = (m_model < mag_lo - tol) | (m_model > mag_hi + tol)
    # One table in m (step M_TABLE_STEP) for every z: P (apparent fits) and q are
    # tabulated on it and read linearly between its nodes at the points.
    h = M_TABLE_STEP
    m0 = np.floor(m_pt.min() / h) * h - h
    n_tab = int(np.ceil((m_pt.max() - m0) / h)) + 2
    m_tab = m0 + h * np.arange(n_tab)
    pos = (m_pt - m0) / h
    i0 = np.clip(np.floor(pos).astype(int), 0, n_tab - 2)
    f = np.clip(pos - i0, 0.0, 1.0)
    col = np.concatenate([zi * n_tab + i0, zi * n_tab + i0 + 1])

    def spread(rows, n_rows, weights):
        """Sparse map from the (z, m_tab) table to ``rows``: linear interpolation at each point."""
        data = np.concatenate([weights * (1 - f), weights * f])
        return sparse.csr_matrix((data, (np.concatenate([rows, rows]), col)),
                                 shape=(n_rows, n_z * n_tab))

    idx = _draw_index(sf.n_draws, draws)
    point = idx[0] < 0
    if transfer:
        tf = transfer_function(tm, "selected", draws=not point)
        n_t = tf.n_draws if transfer_draws is None else max(1, min(int(transfer_draws),
                                                                   tf.n_draws))
        si, ss = tf._z_pairs(zz)
        si2 = np.minimum(si + 1, len(tf.z_nodes) - 1)
        cache = {}

        def q_on(grid, a):
            """q(k | grid, z) [(n_z, len(grid), n_k)] of the transfer draw paired with draw a."""
            dt = 0 if point else a % n_t
            key = (dt, len(grid), float(grid[0]))
            if key not in cache:
                cache.clear()
                tab = tf.slice_table(grid, E, draws=[dt])[0]                   # (n_s, n_grid, n_k)
                cache[key] = (1 - ss)[:, None, None] * tab[si] + ss[:, None, None] * tab[si2]
            return cache[key]

        def q_table(a):
            """q(k | m_tab, z) [(n_z n_tab, n_k)] of the transfer draw paired with draw a."""
            return q_on(m_tab, a).reshape(n_z * n_tab, n_k)

    elif lens_fields:
        # Behind a lens "measured = input" means the magnified input magnitude, so the
        # counts go through the lensed tables with q = the bin holding that magnitude.
        def q_on(grid, a):
            k = np.searchsorted(E, grid, side="right") - 1
            one = (k[:, None] == np.arange(n_k)[None, :]).astype(float)
            return np.broadcast_to(one[None], (n_z,) + one.shape)

        def q_table(a):
            return q_on(m_tab, a).reshape(n_z * n_tab, n_k)

    # Draws that share a transfer draw one after the other: each table is made once.
    order = sorted(range(len(idx)), key=lambda a: a % n_t) if transfer else range(len(idx))
    values = np.zeros((len(idx), n_M, n_k))
    extrap = np.zeros((n_M, n_k))
    if not absolute:
        if lens_fields:
            # Lensed fields through their source-plane tables, the others by depth nodes.
            P_tab = sum(_selection_table(sf, idx, zz, m_tab, *sf._area_nodes(None, f, who))
                        for f in plain_fields) if plain_fields else np.zeros((len(idx), n_z, n_tab))
        else:
            P_tab = _selection_table(sf, idx, zz, m_tab, nodes, node_sr)       # (n_d, n_z, n_tab)
        if transfer or lens_fields:
            A = spread(ji, n_M, w_pt)
            A_ext = spread(ji, n_M, np.where(ext_pt, w_pt, 0.0)) if ext_pt.any() else None
            lensed_h = (lensed_count_tables(sf, idx, zz, m_tab, field, cosmology, q_on, order=order)
                        if lens_fields else None)
            for a in order:
                H = P_tab[a].reshape(-1, 1) * q_table(a)
                if lensed_h is not None:
                    _, h_l = next(lensed_h)
                    H = H + h_l.reshape(n_z * n_tab, n_k)
                values[a] = A @ H
                if A_ext is not None:
                    extrap += A_ext @ H
        else:
            # The cell [m - dM/2, m + dM/2] of each point spread over the bins it overlaps
            # (exact bin edges); one sparse product for every draw.
            ov = _overlap(m_pt, dm / 2, E)                                     # (n_pt, n_k)
            p_i, k_i = np.nonzero(ov > 0)
            rows = np.concatenate([ji[p_i] * n_k + k_i] * 2)
            c = np.concatenate([col[:len(m_pt)][p_i], col[len(m_pt):][p_i]])
            wk = w_pt[p_i] * ov[p_i, k_i]
            flat = P_tab.reshape(len(idx), -1).T                               # (n_z n_tab, n_d)

            def apply(wts):
                T = sparse.csr_matrix((np.concatenate([wts * (1 - f[p_i]), wts * f[p_i]]),
                                       (rows, c)), shape=(n_M * n_k, n_z * n_tab))
                return (T @ flat).T.reshape(len(idx), n_M, n_k)
            values[:] = apply(wk)
            if ext_pt.any():
                extrap += apply(np.where(ext_pt[p_i], wk, 0.0)).sum(axis=0)
    else:
        # P depends on M_UV itself: the beta average acts on q alone, per (z, M).
        P_zm = _selection_table(sf, idx, zz, Mc, nodes, node_sr)               # (n_d, n_z, n_M)
        rows_zj = zi * n_M + ji
        wq = bw[bi] / np.where(flux, bw[None, :], 0.0).sum(axis=1)[zi]         # beta weights with flux
        ext_zm = ((Mc < mag_lo - tol) | (Mc > mag_hi + tol))[None, :]
        has_flux = flux.any(axis=1)[:, None]
        wzm = wz[:, None] * phi_zm * dm * has_flux                             # (n_z, n_M)
        if transfer:
            B = spread(rows_zj, n_z * n_M, wq)
        else:
            Qd = np.zeros((n_z * n_M, n_k))
            np.add.at(Qd, rows_zj, wq[:, None] * _overlap(m_pt, dm / 2, E))
            Qd = Qd.reshape(n_z, n_M, n_k)
        last_dt = None
        for a in order:
            if transfer and a % n_t != last_dt:
                Qd = (B @ q_table(a)).reshape(n_z, n_M, n_k)
                last_dt = a % n_t
            pw = P_zm[a] * wzm
            values[a] = np.einsum("zm,zmk->mk", pw, Qd)
            extrap += np.einsum("zm,zmk->mk", np.where(ext_zm, pw, 0.0), Qd)
    return CountKernel(M_edges=Me, m_obs_edges=E, values=values,
                       extrapolated=extrap / len(idx), z_range=(z_lo, z_hi),
                       transfer=bool(transfer), draw_index=idx)


def _selection_table(sf, idx, zz, m, nodes, node_sr):
    """Ω-weighted P̄(z, m) [sr] on the outer grid zz x m, for the draws ``idx`` (n_d, n_z, n_m).

    ``idx == [-1]``: the pointwise posterior median over every draw (one entry).  A
    depth-aware model on an evenly spaced ``m`` is evaluated once, at the reference
    depth, on the same grid extended by the depth offsets, and each depth node read from
    it linearly (a depth offset shifts the magnitude, :mod:`~glaciar.inference.models`):
    at the 0.01 mag table step that is < 2e-5 in P for steps of width w >= 0.25 mag
    (h^2/8 P'').
    """
    mdl = sf.model
    m = np.asarray(m, float)
    h = (m[1] - m[0]) if len(m) > 1 else 0.0
    reads = None
    if mdl.depth_aware and len(m) > 1 and np.allclose(np.diff(m), h):
        shifts = np.asarray(nodes, float) - mdl.depth_ref
        lo = int(np.floor(-shifts.max() / h)) - 1
        hi = int(np.ceil(-shifts.min() / h)) + 2
        g = m[0] + h * np.arange(lo, len(m) + hi)               # reference-depth grid
        reads = []
        for sh in shifts:
            pos = (m[0] - sh - g[0]) / h
            k = int(np.floor(pos))
            reads.append((k, pos - k))

    def table(th, z):
        if reads is not None:
            c, s = mdl.surfaces_on_grid(th, z, g)
            p_ref = c * s
            out = 0.0
            for (k, fr), sr in zip(reads, node_sr):
                out = out + sr * ((1 - fr) * p_ref[:, :, k:k + len(m)]
                                  + fr * p_ref[:, :, k + 1:k + 1 + len(m)])
            return out
        out = 0.0
        for dj, sr in zip(nodes, node_sr):
            c, s = mdl.surfaces_on_grid(th, z, mdl.relative_magnitude(m, dj if mdl.depth_aware
                                                                       else None))
            out = out + sr * c * s
        return out

    if idx[0] < 0:
        out = np.empty((1, len(zz), len(m)))
        step = max(1, int(4e6 // max(1, sf.n_draws * len(m))))
        for z0 in range(0, len(zz), step):
            out[0, z0:z0 + step] = np.median(table(sf.draws, zz[z0:z0 + step]), axis=0)
        return out
    out = np.empty((len(idx), len(zz), len(m)))
    for c0 in range(0, len(idx), _CHUNK):
        out[c0:c0 + _CHUNK] = table(sf.draws[idx[c0:c0 + _CHUNK]], zz)
    return out


def expected_counts(sf, phi, m_obs_edges, *, volume: SurveyVolume = SurveyVolume(),
                    M_uv_range=None, sed=None, draws=True, transfer: bool = True,
                    field: str | None = None, quadrature: Quadrature = Quadrature(),
                    interval: float = 0.68, warn: bool = True) -> ExpectedCounts:
    """Expected numbers of selected sources per measured-magnitude bin for a luminosity function.

    N_k of the module docstring, per posterior draw (selection-function draw i with
    transfer-matrix draw i mod n_t).

    Parameters
    ----------
    sf : SelectionFunction
    phi : callable
        ``phi(M, z)`` [Mpc^-3 mag^-1] on broadcastable arrays of M_UV [AB mag] and z.
    m_obs_edges : array_like (n_k + 1,)
        Measured detection-band magnitude bins [AB mag] (first may be -inf, last +inf).
    volume : SurveyVolume
        Redshift range (default and at most the simulated one), area and cosmology, as
        :func:`count_kernel`.  Sources outside the redshift range are not counted:
        where P is not ~0 at the simulated range's ends, the counts miss them
        (:meth:`SelectionFunction.effective_volume` warns about that).
    M_uv_range : (float, float), optional
        M_UV range integrated over (phi = 0 outside it); default that of
        :func:`count_kernel`.
    sed, field, quadrature
        As :func:`count_kernel`.
    draws : bool or int
        As :func:`count_kernel`.
    transfer : bool
        False: the measured magnitude is taken to be the input magnitude.
    interval : float
        Central credible-interval probability.
    warn : bool
        Warn when a bin draws more than ``COUNTS_EXTRAPOLATION_TOLERANCE`` of its counts,
        and more than a tenth of its Poisson error, from magnitudes outside the
        simulated range.

    Returns
    -------
    ExpectedCounts
    """
    who = "expected_counts"
    z_min, z_max, cosmology = volume.z_min, volume.z_max, volume.cosmology
    n_z, n_beta, dM = quadrature.n_z, quadrature.n_beta, quadrature.dM
    E = _check_edges(m_obs_edges, who)
    M_edges = None
    if M_uv_range is not None:
        lo, hi = map(float, M_uv_range)
        if not hi > lo:
            raise ValueError(f"{who}: M_uv_range must be (lo, hi) with hi > lo, not {M_uv_range}")
        n = max(1, int(np.ceil((hi - lo) / dM - 1e-9)))
        M_edges = np.linspace(lo, hi, n + 1)
    Me = (_default_M_edges(sf, E, z_min, z_max, cosmology, sed, transfer, n_z, n_beta, dM)
          if M_edges is None else M_edges)
    zr = sf._z_limits(z_min, z_max, who)
    zz = np.linspace(zr[0], zr[1], int(n_z) | 1)
    Mc = 0.5 * (Me[:-1] + Me[1:])
    phi_zm = np.asarray(phi(Mc[None, :], zz[:, None]), float) * np.ones((len(zz), len(Mc)))
    if not np.all(np.isfinite(phi_zm)):
        raise ValueError(f"{who}: phi(M, z) is not finite everywhere on M_UV "
                         f"{Me[0]:g}-{Me[-1]:g}, z {zr[0]:g}-{zr[1]:g}")
    ker = count_kernel(sf, E, Me, volume=volume, sed=sed, transfer=transfer, draws=draws,
                       field=field, quadrature=quadrature, phi_z=phi_zm, who=who)
    ones = np.ones(len(Mc))
    per = ker.counts(ones)                                                  # (n_d, n_k)
    frac = ker.extrapolated_fraction(ones)
    if warn:
        # Only where it could matter: over the tolerance and over a tenth of the bin's
        # Poisson error (a faint bin expecting 0.01 sources is not worth a warning).
        n_mean = per.mean(axis=0)
        bad = ((frac > COUNTS_EXTRAPOLATION_TOLERANCE)
               & (frac * n_mean > 0.1 * np.sqrt(np.maximum(n_mean, 1.0))))
        if bad.any():
            k = np.flatnonzero(bad)
            warnings.warn(f"{who}: {len(k)} m_obs bin(s) ({E[k[0]]:g}-{E[k[0] + 1]:g} ...) draw "
                          f"up to {frac[bad].max():.0%} of their counts from magnitudes outside "
                          f"the simulated range {sf.domain.get('mag', ('?', '?'))}, where P and "
                          "the transfer function are extrapolated", stacklevel=2)
    q = np.quantile(per, [0.5, 0.5 - interval / 2, 0.5 + interval / 2], axis=0)
    return ExpectedCounts(m_obs_edges=E, median=q[0], lower=q[1], upper=q[2],
                          draws=None if ker.draw_index[0] < 0 else per,
                          extrapolated_fraction=frac, M_uv_range=(float(Me[0]), float(Me[-1])),
                          z_range=tuple(map(float, ker.z_range)), transfer=bool(transfer))


def _default_M_edges(sf, E, z_min, z_max, cosmology, sed, transfer, n_z, n_beta, dM):
    """The M_UV cells :func:`count_kernel` uses by default (without evaluating anything)."""
    from ..galaxy.population import get_cosmology

    sed = sf.sed if sed is None else sed
    if sed is None:
        raise ValueError("expected_counts: this fit records no injection SED (detection "
                         "filter, beta, IGM); pass sed=InjectionSED(...)")
    cosmology = get_cosmology(sed.cosmology if cosmology is None else cosmology)
    z_lo, z_hi = sf._z_limits(z_min, z_max, "expected_counts")
    zz = np.linspace(z_lo, z_hi, int(n_z) | 1)
    b, _ = beta_nodes(sed.beta_mean, sed.beta_sd, n_beta)
    K = kcorrection(zz, b, sed.detection_filter, igm=sed.igm, cosmology=cosmology)
    return default_M_edges(sf, E, K, transfer, dM)


def default_M_edges(sf, E, K, transfer, dM):
    """M_UV cells whose images m = M + K (any finite K) reach the m_obs range +- the margin."""
    fin = np.isfinite(K)
    if not fin.any():
        raise ValueError("the detection band receives no flux in the redshift range")
    k_lo, k_hi = float(K[fin].min()), float(K[fin].max())
    mag_lo, mag_hi = sf.domain.get("mag", (sf.model.m_ref - sf.model.m_scale,
                                           sf.model.m_ref + sf.model.m_scale))
    if sf.magnitude_type == "absolute":
        mag_lo, mag_hi = mag_lo + k_lo, mag_hi + k_hi
    lo = E[0] if np.isfinite(E[0]) else mag_lo
    hi = E[-1] if np.isfinite(E[-1]) else mag_hi
    margin = TRANSFER_MARGIN if transfer else 0.0
    a = np.floor((lo - margin - k_hi) / dM) * dM
    b = np.ceil((hi + margin - k_lo) / dM) * dM
    return np.round(a + dM * np.arange(int(round((b - a) / dM)) + 1), 6)
