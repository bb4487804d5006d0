"""Selection behind a lensing cluster: the source-plane tables and V_eff of lensed fields.

A lensed field's injections are made at their observed (magnified) magnitude, so the
fitted surfaces are P(z, m_obs | depth) as for any field (docs/lensing.md).  A source of
intrinsic magnitude m seen through magnification mu has ``m_obs = m - 2.5 log10 |mu|``,
and the image-plane area A behind which it can lie covers ``A / |mu|`` of the source
plane.  Summed over a field's lens area nodes (:func:`glaciar.galaxy.lensing.lens_area_nodes`:
depth, kappa, ``kappa^2 - |gamma|^2``, area, of the lens model normalised to D_ls/D_s = 1)
at each source redshift,

    P_lens(z, m) = sum_n Omega_n |det A_n(z)| P(z, m + 2.5 log10 |det A_n(z)| | d_n),
    det A_n(z) = 1 - 2 r kappa_n + r^2 (kappa^2 - gamma^2)_n,   r = D_ls(z) / D_s(z),

is the source-plane solid angle [sr] times the selection probability; V_eff(m) is its
integral with dV/dz/dOmega over z, and count tables (:mod:`glaciar.inference.counts`) read
it in place of the depth-weighted table of an unlensed field.

How it is computed: for every z, the nodes' magnitude offsets (lensing shift plus the
depth offset of a depth-aware model) are spread linearly onto a lattice of step
:data:`LENS_TABLE_STEP` with their weights ``Omega_n |det A_n|`` (a kernel per z), the
surfaces are evaluated once per z on a lattice in the model's magnitude, and the table is
the correlation of the two (FFT).  Error: the kernel's linear spreading and the linear
read-back at the asked magnitudes, each ~ h^2/8 P'' (< 1e-4 in P for completeness widths
>= 0.2 mag at h = 0.02; tests/inference/test_lensed.py compares with a direct per-node
sum).  The source-plane area itself is exact at every z (the kernel's total weight is
``sum_n Omega_n |det A_n(z)|``).  Lensing shifts beyond :data:`MAX_LENS_SHIFT_MAG` (on a
critical curve, where ``|det A|`` -> 0 and so does the node's weight) are clipped to it.

Magnification as a covariate.  At fixed observed magnitude a more magnified source is more
stretched (lower surface brightness), so C depends on |mu| as well; the image-plane
injections average over the field's image-plane |mu| distribution, the source plane
weights it by 1/|mu|.  A fit with the ``magnification`` covariate
(:mod:`glaciar.inference.covariates`, x = log10|mu|; ``glaciar fit`` adds it to lensed runs)
gives theta(x); each lens node then reads P at its own ``x_n(z) = -log10|det A_n(z)|``,
interpolated linearly between covariate nodes x_j (:func:`magnification_draws`: the bins'
centres and steps of at most :data:`MU_NODE_STEP` between the outer ones):

    P_lens(z, m) = sum_j sum_n Omega_n |det A_n| hat_j(x_n(z)) P(z, m + l_n | d_n, theta(x_j)),

one kernel per covariate node j, each correlated with the surfaces at theta(x_j) over the
part of the lattice its kernel covers (a node's lens nodes share nearly one |mu|, so one
lensing shift).  An x_n beyond the end nodes takes the end node's selection; outside the
injected range this is warned about when more than
:data:`~glaciar.inference.covariates.OUTSIDE_WARN` of the source-plane area at some z lies
there).  Without the covariate (unlensed fits, older files) the tables are the ones above.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import warnings

from ..galaxy.lensing import NODE_KEYS, distance_ratio, node_inverse_magnification
from .covariates import OUTSIDE_WARN
from .volume import group_linearly

__all__ = ["LensNodes", "LENS_TABLE_STEP", "MAX_LENS_SHIFT_MAG", "lens_kernel", "lensed_table",
           "lensed_volume_draws", "lensed_muv_volume_draws",
           "LensModelVolumes", "LensedSelection", "NodeDraws", "magnification_draws",
           "MU_NODE_STEP"]

#: Lattice step of the lensed tables [mag].
LENS_TABLE_STEP = 0.02
#: |2.5 log10 mu| is clipped to this (|mu| = 250) [mag].
MAX_LENS_SHIFT_MAG = 6.0
#: Posterior draws evaluated at a time (memory: draws x n_z x lattice floats).
_BATCH = 16
#: Largest spacing of the magnification-covariate nodes of the lensed tables [dex of |mu|].
MU_NODE_STEP = 0.1


@dataclass(frozen=True)
class NodeDraws:
    """Posterior draws of the surfaces at nodes of the magnification covariate.

    Attributes
    ----------
    x : ndarray (J,)
        The nodes, log10|mu|, increasing.
    covered : tuple of float
        The injected range of log10|mu| (beyond it the fit says nothing).
    draws : ndarray (J, n_draws, n_params)
        Node j's parameters: the pooled fit's draws with the covariate's block interpolated
        at x_j (draw i of every node belongs to draw i of the pooled fit).
    """

    x: np.ndarray
    draws: np.ndarray
    covered: tuple = (-np.inf, np.inf)

    def __len__(self) -> int:
        return self.draws.shape[1]


def magnification_draws(sf, step: float = MU_NODE_STEP):
    """:class:`NodeDraws` of a fit with the ``magnification`` covariate, else None.

    Nodes: equally spaced at no more than ``step`` between the outer bins' centres (where
    theta(x) is held constant beyond: :attr:`CovariateSpec.extrapolate`), plus the centres
    (where theta(x) bends).  A covariate with fewer draws than the pooled fit is cycled
    (draw i uses the covariate's draw i mod its count).
    """
    cov = (getattr(sf, "covariates", None) or {}).get("magnification")
    if cov is None:
        return None
    lo, hi = cov.covered
    if not cov.spec.extrapolate:
        lo, hi = float(cov.centres[0]), float(cov.centres[-1])
    n = max(2, int(np.ceil((hi - lo) / float(step) - 1e-9)) + 1)
    centres = np.clip(cov.centres, lo, hi)
    even = np.linspace(lo, hi, n)
    # Equal steps that nearly coincide with a centre add cost, not accuracy.
    even = even[np.min(np.abs(even[:, None] - centres[None, :]), axis=1) > 0.25 * float(step)]
    x = np.unique(np.concatenate([even, centres]))
    idx = sf.model.block_indices(cov.spec.block)
    k = np.arange(len(sf.draws)) % cov.draws.shape[1]
    out = np.repeat(np.asarray(sf.draws, float)[None], len(x), axis=0)
    for j, xj in enumerate(x):
        out[j][:, idx] = cov.theta_at(xj)[k][:, idx]
    return NodeDraws(x, out, cov.covered)


def _hat(x_nodes, x):
    """Linear-interpolation weights of ``x`` on ``x_nodes`` (clamped to the end nodes):
    (lower node index, weight of the upper node)."""
    xn = np.asarray(x_nodes, float)
    x = np.asarray(x, float)
    if len(xn) == 1:
        return np.zeros(x.shape, np.int64), np.zeros(x.shape)
    xc = np.clip(np.nan_to_num(x, nan=xn[0], posinf=xn[-1], neginf=xn[0]), xn[0], xn[-1])
    j = np.clip(np.searchsorted(xn, xc, side="right") - 1, 0, len(xn) - 2)
    return j, (xc - xn[j]) / (xn[j + 1] - xn[j])


def _warn_outside(x, w, covered):
    """Warn when the source-plane area with |mu| outside the injected range is large."""
    lo, hi = covered
    tol = 1e-9 * max(1.0, abs(hi))
    outside = (x < lo - tol) | (x > hi + tol)
    share = np.max(np.sum(w * outside, axis=1) / np.maximum(np.sum(w, axis=1), 1e-300))
    if share > OUTSIDE_WARN:
        warnings.warn(f"V_eff behind the lens: up to {share:.0%} of the source-plane area has "
                      f"|mu| outside the injected range {10 ** lo:.3g}-{10 ** hi:.3g}; it is "
                      "given the completeness of the nearest "
                      "end of that range", stacklevel=4)


def _node_terms(nodes, zz, cosmology):
    """Per (z, lens node): lensing shift [mag], weight Omega |det A| [sr], x = log10|mu|,
    and the nodes' image-plane solid angles [sr]."""
    import astropy.units as u

    det = nodes.inverse_magnification(zz, cosmology)                         # (n_z, n)
    sr = (nodes.area_arcmin2 * u.arcmin ** 2).to_value(u.sr)
    with np.errstate(divide="ignore"):
        lg = np.log10(np.abs(det))
    shift = np.clip(2.5 * lg, -MAX_LENS_SHIFT_MAG, MAX_LENS_SHIFT_MAG)
    return shift, np.abs(det) * sr[None, :], -lg, sr


def _spread(pos, w, cls, n_cls):
    """Weights ``w`` at lattice positions ``pos`` (n_z, N) of classes ``cls`` (n_z, N),
    spread linearly onto the lattice: (k0, kernels (n_cls, n_z, n_k))."""
    i0 = np.floor(pos).astype(np.int64)
    f = pos - i0
    k0 = int(i0.min())
    n_k = int(i0.max()) - k0 + 2
    kernels = np.zeros((n_cls,) + (pos.shape[0], n_k))
    zi = np.broadcast_to(np.arange(pos.shape[0])[:, None], i0.shape)
    np.add.at(kernels, (cls, zi, i0 - k0), w * (1 - f))
    np.add.at(kernels, (cls, zi, i0 - k0 + 1), w * f)
    return k0, kernels


def _with_covariate(pos, w, cls, x, nd, n_base):
    """Each (z, node) entry split between its two covariate nodes (of :class:`NodeDraws`
    ``nd``): class ``cls * J + j``."""
    if nd is None:
        return pos, w, cls, n_base
    j, t = _hat(nd.x, x)
    _warn_outside(x, w, nd.covered)
    J = len(nd.x)
    jj = np.minimum(j + 1, J - 1)
    return (np.concatenate([pos, pos], axis=1), np.concatenate([w * (1 - t), w * t], axis=1),
            np.concatenate([cls * J + j, cls * J + jj], axis=1), n_base * J)


@dataclass(frozen=True)
class LensNodes:
    """One field's footprint behind one lens model, grouped into area nodes.

    Attributes
    ----------
    field, model : str
        The field and the lens model's name.
    z_lens : float
        Lens redshift.
    depth : ndarray
        Local depth of each node [AB mag].
    kappa, gamma, kappa2_minus_gamma2 : ndarray
        Area-weighted means of the normalised model (D_ls/D_s = 1) over each node.
    area_arcmin2 : ndarray
        Image-plane area of each node [arcmin^2].
    """

    field: str
    model: str
    z_lens: float
    depth: np.ndarray
    kappa: np.ndarray
    gamma: np.ndarray
    kappa2_minus_gamma2: np.ndarray
    area_arcmin2: np.ndarray

    @classmethod
    def from_dict(cls, field: str, model: str, z_lens: float, nodes: dict) -> "LensNodes":
        """From :func:`glaciar.galaxy.lensing.lens_area_nodes`'s dict (as the manifest holds it)."""
        missing = [k for k in NODE_KEYS if k not in nodes]
        if missing:
            raise ValueError(f"lens nodes of field {field!r}, model {model!r}: missing {missing}")
        arr = {k: np.asarray(nodes[k], dtype=float) for k in NODE_KEYS}
        if len({a.shape for a in arr.values()}) != 1:
            raise ValueError(f"lens nodes of field {field!r}, model {model!r}: columns of "
                             "different lengths")
        return cls(field, model, float(z_lens), **arr)

    def to_dict(self) -> dict:
        return {k: np.asarray(getattr(self, k)).tolist() for k in NODE_KEYS}

    def inverse_magnification(self, z, cosmology) -> np.ndarray:
        """Signed mean ``1/mu`` per node for sources at redshift(s) ``z``: shape ``z.shape + (n,)``."""
        return node_inverse_magnification(self.to_arrays(), distance_ratio(self.z_lens, z, cosmology))

    def to_arrays(self) -> dict:
        return {k: getattr(self, k) for k in NODE_KEYS}

    def source_plane_area(self, z, cosmology) -> np.ndarray:
        """Source-plane area behind the field at redshift(s) ``z`` [arcmin^2]."""
        return np.abs(self.inverse_magnification(z, cosmology)) @ self.area_arcmin2


def _depth_offset(model, nodes) -> np.ndarray:
    """Each node's shift of the model's magnitude covariate for its depth (0 if not depth-aware)."""
    if not model.depth_aware:
        return np.zeros(len(nodes.depth))
    return model.relative_magnitude(0.0, nodes.depth)


def lens_kernel(model, nodes_list, zz, cosmology, h: float = LENS_TABLE_STEP, nd=None):
    """Per-z weights [sr] of the nodes' magnitude offsets on a lattice of step ``h``.

    Parameters
    ----------
    model, nodes_list, zz, cosmology, h
        The surface model, the lens nodes, redshifts, cosmology and the lattice step [mag].
    nd : NodeDraws, optional
        Draws at the magnification covariate's nodes x_j (log10|mu|): one kernel per node,
        each lens node's weight shared between the two nodes around its x by linear
        interpolation (clamped to the end nodes).

    Returns
    -------
    k0 : int
        Lattice index of the first offset (offset = (k0 + k) h).
    kernel : ndarray, shape (n_z, n_k), or (J, n_z, n_k) with ``nd``
        ``kernel[i, k]``: the source-plane solid angle at ``zz[i]`` whose model magnitude is
        ``m + (k0 + k) h`` for intrinsic magnitude m (linearly spread between lattice nodes).
    """
    zz = np.asarray(zz, dtype=float)
    pos_all, w_all, x_all = [], [], []
    for nodes in nodes_list:
        shift, w, x, _ = _node_terms(nodes, zz, cosmology)
        pos_all.append((shift + _depth_offset(model, nodes)[None, :]) / h)
        w_all.append(w)
        x_all.append(x)
    pos = np.concatenate(pos_all, axis=1)
    w = np.concatenate(w_all, axis=1)
    pos, w, cls, n_cls = _with_covariate(pos, w, np.zeros(pos.shape, np.int64),
                                         np.concatenate(x_all, axis=1), nd, 1)
    k0, kernels = _spread(pos, w, cls, n_cls)
    return k0, (kernels[0] if nd is None else kernels)


def _lattice(m_lo: float, m_hi: float, k0: int, n_k: int, h: float):
    """Intrinsic-magnitude lattice covering [m_lo, m_hi] and the model-magnitude grid it reads."""
    j_lo = int(np.floor(m_lo / h)) - 1
    j_hi = int(np.ceil(m_hi / h)) + 1
    return h * np.arange(j_lo, j_hi + 1), h * np.arange(j_lo + k0, j_hi + k0 + n_k)


def _support(kernel):
    """First and one-past-last lattice column where ``kernel`` (..., n_z, n_k) is non-zero."""
    cols = np.flatnonzero(kernel.reshape(-1, kernel.shape[-1]).any(axis=0))
    return (int(cols[0]), int(cols[-1]) + 1) if cols.size else (0, 1)


def _terms(draws, kernel):
    """(draws, kernel (n_z, n_k_j), first column a_j) triples to sum: one, or one per
    magnification node in use, each cut to its kernel's support (a node's lens nodes share
    nearly one |mu|, so its lensing shifts span a narrow part of the lattice)."""
    if not isinstance(draws, NodeDraws):
        return [(draws, kernel, 0)]
    out = []
    for j in range(len(draws.x)):
        if kernel[j].any():
            a, b = _support(kernel[j])
            out.append((draws.draws[j], kernel[j][:, a:b], a))
    return out


def _lattice_tables(model, draws, zz, kernel, grid, points):
    """``P_lens`` at the lattice indices ``points``, per batch of draws: yields
    (start, table (b, n_z, len(points))).

    ``draws``: an array (n_d, n_params) with ``kernel`` (n_z, n_k), or :class:`NodeDraws`
    with one kernel per node (J, n_z, n_k), summed over the nodes.  Few points: the kernel
    times the lattice window of each point (cost ~ points x kernel); many: one FFT
    correlation along the lattice (cost ~ lattice log lattice).
    """
    from scipy.signal import fftconvolve

    terms = _terms(draws, kernel)
    n_lat = len(grid) - kernel.shape[-1] + 1
    use_fft = len(points) * 4 > n_lat
    for b in range(0, len(draws), _BATCH):
        out = 0.0
        for th, ker, a in terms:
            n_k = ker.shape[1]
            c, s = model.surfaces_on_grid(th[b:b + _BATCH], zz, grid[a:a + n_lat + n_k - 1])
            p = c * s
            if use_fft:
                out = out + fftconvolve(p, ker[None, :, ::-1], mode="valid", axes=2)[:, :, points]
                continue
            part = np.empty((len(p), len(zz), len(points)))
            for i, ip in enumerate(points):           # a window of the lattice per point
                part[:, :, i] = np.einsum("dzk,zk->dz", p[:, :, ip:ip + n_k], ker)
            out = out + part
        yield b, out


def _node_draws(draws):
    return draws if isinstance(draws, NodeDraws) else None


def _read(lattice, m, h):
    """Linear read-back positions: (lower index, fraction) of ``m`` on ``lattice``."""
    pos = (np.asarray(m, dtype=float) - lattice[0]) / h
    i = np.clip(np.floor(pos).astype(np.int64), 0, len(lattice) - 2)
    return i, pos - i


def lensed_table(model, draws, zz, m, nodes_list, cosmology, h: float = LENS_TABLE_STEP):
    """``P_lens(z, m)`` [sr] of the module docstring on the outer grid ``zz x m``, per draw.

    Parameters
    ----------
    model : SurfaceModel
    draws : ndarray (n_d, n_params) or NodeDraws
        Posterior draws, or draws at the magnification covariate's nodes
        (:func:`magnification_draws`).
    zz : ndarray (n_z,)
    m : array_like (n_m,)
        Intrinsic magnitudes [mag] (any order and spacing).
    nodes_list : list of LensNodes
        The fields (of one lens model) to sum over.
    cosmology : astropy Cosmology
    h : float
        Lattice step [mag].

    Returns
    -------
    ndarray, shape (n_d, n_z, n_m)
    """
    m = np.asarray(m, dtype=float).ravel()
    k0, kernel = lens_kernel(model, nodes_list, zz, cosmology, h, _node_draws(draws))
    lattice, grid = _lattice(m.min(), m.max(), k0, kernel.shape[-1], h)
    i, f = _read(lattice, m, h)
    points, back = np.unique(np.concatenate([i, i + 1]), return_inverse=True)
    lo, hi = back[:len(m)], back[len(m):]
    out = np.empty((len(draws), len(zz), len(m)))
    for b, q in _lattice_tables(model, draws, zz, kernel, grid, points):
        out[b:b + len(q)] = q[:, :, lo] * (1 - f) + q[:, :, hi] * f
    return out


def lensed_volume_draws(model, draws, nodes_list, zz, dvdz, mm, cosmology):
    """V_eff(m) [Mpc^3] per draw behind the lens: Simpson's rule over ``zz`` of
    ``P_lens(z, m) dV/dz/dOmega``; shape (n_draws, len(mm)).  ``draws``: as
    :func:`lensed_table` (an array, or :class:`NodeDraws` for the magnification covariate)."""
    from scipy.integrate import simpson

    table = lensed_table(model, draws, zz, mm, nodes_list, cosmology)
    return simpson(table * np.asarray(dvdz)[None, :, None], x=zz, axis=1)


def lensed_muv_volume_draws(model, draws, nodes_list, zz, dvdz, m, flux, bw, cosmology,
                            h: float = LENS_TABLE_STEP):
    """V_eff(M_UV) [Mpc^3] per draw behind the lens, averaged over the UV slope.

    ``m`` (n_z, n_beta, n_M) are the intrinsic apparent magnitudes of the M_UV values
    through the K-corrections, ``flux`` where the band receives flux and ``bw`` the slope
    weights (:func:`glaciar.inference.volume.muv_magnitudes`); ``P_lens`` is tabulated
    once per z on a lattice and read linearly at them.  ``draws``: as :func:`lensed_table`.
    Returns (n_draws, n_M).
    """
    from scipy.integrate import simpson

    k0, kernel = lens_kernel(model, nodes_list, zz, cosmology, h, _node_draws(draws))
    ok = np.broadcast_to(flux, m.shape)
    lattice, grid = _lattice(m[ok].min(), m[ok].max(), k0, kernel.shape[-1], h)
    i, f = _read(lattice, np.where(ok, m, lattice[0]), h)                       # (n_z, n_b, n_M)
    wb = np.where(ok, np.asarray(bw, dtype=float)[None, :, None], 0.0)
    iz = np.arange(len(zz))[:, None, None]
    points, back = np.unique(np.concatenate([i.ravel(), i.ravel() + 1]), return_inverse=True)
    lo, hi = back[:i.size].reshape(i.shape), back[i.size:].reshape(i.shape)
    out = np.zeros((len(draws), m.shape[2]))
    for b, q in _lattice_tables(model, draws, zz, kernel, grid, points):
        p = q[:, iz, lo] * (1 - f) + q[:, iz, hi] * f                           # (b, n_z, n_b, n_M)
        p = np.einsum("dzbm,zbm->dzm", p, wb)
        out[b:b + len(q)] = simpson(p * np.asarray(dvdz)[None, :, None], x=zz, axis=1)
    return out


def _magnified(m, magnification):
    mu = np.abs(np.asarray(magnification, dtype=float))
    if np.any(~(mu > 0)):
        raise ValueError("magnification must be non-zero")
    return np.asarray(m, dtype=float) - 2.5 * np.log10(mu)


@dataclass(frozen=True)
class LensModelVolumes:
    """V_eff behind the lens per lens model, their average and spread.

    Attributes
    ----------
    per_model : dict
        Lens-model name -> :class:`~glaciar.inference.products.EffectiveVolume`.
    average : EffectiveVolume
        The models' mean V_eff, per posterior draw (equal weights).
    spread : Quantity
        Standard deviation across the models of their median V_eff [Mpc^3] (0 for one model).
    """

    per_model: dict
    average: object
    spread: object


class LensedSelection:
    """V_eff of lensed fields, for :class:`~glaciar.inference.selection_function.SelectionFunction`.

    ``lens_nodes`` ({field: {model name: LensNodes}}) is attached after construction
    (``glaciar fit`` copies it from the run's manifest; the file keeps it in ``LENS``).
    Fields without a lens model keep their area-by-depth nodes.
    """

    lens_nodes = None

    @property
    def lens_models(self) -> list:
        """Names of the lens models, in the order of the first lensed field."""
        names = []
        for per in (self.lens_nodes or {}).values():
            names += [n for n in per if n not in names]
        return names

    def _lensed_fields(self, field):
        """(lensed fields, unlensed fields) a V_eff over ``field`` (None: all) sums."""
        lensed = set(self.lens_nodes or {})
        if field is not None:
            return ([field], []) if field in lensed else ([], [field])
        others = sorted(set(self.depth_area or {}) - lensed)
        return sorted(lensed), others

    def lens_theta(self):
        """The draws V_eff behind the lens uses: :class:`NodeDraws` of the magnification
        covariate when fitted (:func:`magnification_draws`), else the pooled draws."""
        nd = magnification_draws(self)
        return self.draws if nd is None else nd

    def _at_magnification(self, which, m_intrinsic, z, magnification, depth, kw):
        m = _magnified(m_intrinsic, magnification)
        if "magnification" not in (getattr(self, "covariates", None) or {}):
            if which == "C":
                return self.completeness(m, z, depth, **kw)
            return self.selection_probability(z, m, depth, **kw)
        from .covariates import evaluate

        opts = {k: kw.pop(k) for k in ("field", "draws", "outside") if k in kw}
        return evaluate(self, which, m, z, depth, opts.get("field"), opts.get("draws", False),
                        opts.get("outside", "nan"), magnification=magnification, **kw)

    def completeness_lensed(self, m_intrinsic, z, magnification, depth=None, **kw):
        """C of a source of intrinsic magnitude ``m_intrinsic`` seen through ``magnification``
        (signed mu; |mu| is used): :meth:`completeness` at ``m - 2.5 log10 |mu|`` and, for a
        fit with the ``magnification`` covariate, at that |mu| (NaN outside its injected
        range unless ``outside="extrapolate"``)."""
        return self._at_magnification("C", m_intrinsic, z, magnification, depth, dict(kw))

    def selection_probability_lensed(self, z, m_intrinsic, magnification, depth=None, **kw):
        """P = C S of a source of intrinsic magnitude ``m_intrinsic`` seen through
        ``magnification``: :meth:`selection_probability` at ``m - 2.5 log10 |mu|`` (and at
        that |mu| with the ``magnification`` covariate, as :meth:`completeness_lensed`)."""
        return self._at_magnification("P", m_intrinsic, z, magnification, depth, dict(kw))

    def for_lens_model(self, name: str):
        """This selection function with only lens model ``name`` kept (a shallow copy)."""
        import copy

        if name not in self.lens_models:
            raise ValueError(f"no lens model {name!r} (have {self.lens_models})")
        out = copy.copy(self)
        out.lens_nodes = {f: {name: per[name]} for f, per in self.lens_nodes.items() if name in per}
        return out

    def lensed_draws(self, per_nodes, per_field, field):
        """V_eff draws summed over fields: ``per_nodes(nodes_list)`` for the lensed fields
        (averaged over the lens models) plus ``per_field(f)`` for the others."""
        lensed, others = self._lensed_fields(field)
        out = 0.0
        if lensed:
            models = self.lens_models
            out = sum(per_nodes([self.lens_nodes[f][mname] for f in lensed
                                 if mname in self.lens_nodes[f]]) for mname in models) / len(models)
        for f in others:
            out = out + per_field(f)
        return out

    def lens_model_volumes(self, m, *, absolute: bool = False, interval: float = 0.68,
                           **kw) -> LensModelVolumes:
        """V_eff per lens model, their average and spread.

        Parameters
        ----------
        m : float or array_like
            Intrinsic apparent magnitudes (``absolute=False``, :meth:`effective_volume`)
            or M_UV (``absolute=True``, :meth:`effective_volume_muv`) [AB mag].
        absolute : bool
        interval : float
        **kw
            Passed on (``field``, ``cosmology``, ``z_min``, ``z_max``, ...).
        """
        import astropy.units as u

        from .volume import summarise_volume

        if not self.lens_nodes:
            raise ValueError("lens_model_volumes: this selection function has no lensed field")
        fn = "effective_volume_muv" if absolute else "effective_volume"
        per = {name: getattr(self.for_lens_model(name), fn)(m, interval=interval, **kw)
               for name in self.lens_models}
        draws = np.mean([v.draws.to_value(u.Mpc ** 3) for v in per.values()], axis=0)
        medians = np.array([v.median.to_value(u.Mpc ** 3) for v in per.values()])
        return LensModelVolumes(per_model=per, average=summarise_volume(draws, interval),
                                spread=medians.std(axis=0) * u.Mpc ** 3)


def _kernel_sets(sf, field, zz, cosmology, h, n_classes, nd=None):
    """Lens-shift kernels of the lensed fields, per class, averaged over the lens models.

    Returns (k0, kernels (n_c, n_z, n_k) [sr], class offsets (n_c,) [mag of the model's
    magnitude covariate], class covariate nodes (n_c,) [index into ``nd.x``, 0 without]).
    A depth-aware model's nodes are merged into at most ``n_classes`` classes of their
    depth offset, each at its area-weighted mean offset (the approximation unlensed fields
    make with their depth nodes); the lens shift of every node is kept on the lattice.  With
    ``nd`` (:class:`NodeDraws` of the magnification covariate), a class is a (depth class,
    covariate node).
    """
    lensed, _ = sf._lensed_fields(field)
    models = sf.lens_models
    parts = []
    for name in models:
        for f in lensed:
            nodes = sf.lens_nodes[f].get(name)
            if nodes is None:
                continue
            shift, w, x, sr = _node_terms(nodes, zz, cosmology)
            parts.append((shift / h, w / len(models), _depth_offset(sf.model, nodes), sr, x))
    pos = np.concatenate([p[0] for p in parts], axis=1)
    w = np.concatenate([p[1] for p in parts], axis=1)
    off = np.concatenate([p[2] for p in parts])
    sr = np.concatenate([p[3] for p in parts])
    cls, offsets, _ = group_linearly(off, sr, n_classes)
    pos, w, ci, n_all = _with_covariate(pos, w, np.broadcast_to(cls[None, :], pos.shape),
                                        np.concatenate([p[4] for p in parts], axis=1), nd,
                                        len(offsets))
    k0, kernels = _spread(pos, w, ci, n_all)
    J = 1 if nd is None else len(nd.x)
    keep = np.flatnonzero(kernels.reshape(n_all, -1).any(axis=1))
    return k0, kernels[keep], offsets[keep // J], keep % J


def lensed_count_tables(sf, idx, zz, m_tab, field, cosmology, q_on=None, n_classes: int = 12,
                        order=None):
    """The lensed fields' part of a count kernel's table on ``zz x m_tab`` (evenly spaced).

    Parameters
    ----------
    sf : SelectionFunction
        With ``lens_nodes``.
    idx : ndarray of int
        Draw indices (``[-1]``: the pointwise posterior median of the surface).
    zz, m_tab : ndarray
        Redshift nodes and the intrinsic-magnitude table (step h, evenly spaced).
    field : str or None
    cosmology : astropy Cosmology
    q_on : callable, optional
        ``q_on(grid, a) -> (n_z, len(grid), n_k)``: the transfer function q(k | m_in, z) of
        the transfer draw paired with draw ``a`` at *observed* injected magnitudes ``grid``.
        Given, the tables hold ``sum_n Omega_n |det A_n| P(z, m + l_n | d_n) q(k | m + l_n, z)``
        (the measured magnitude of a lensed source follows its magnified magnitude).
    n_classes : int
        Depth classes of a depth-aware model (see :func:`_kernel_sets`); with the
        magnification covariate each is split further by covariate node (:func:`magnification_draws`).
    order : iterable of int, optional
        The positions in ``idx`` in the order to yield them (default 0, 1, ...).

    Yields
    ------
    (a, table)
        ``a`` the position in ``idx`` and ``table`` of shape (n_z, n_tab) [sr] or, with
        ``q_on``, (n_z, n_tab, n_k).
    """
    from scipy.signal import fftconvolve

    h = float(m_tab[1] - m_tab[0])
    theta = sf.lens_theta()
    k0, kernels, offsets, node = _kernel_sets(sf, field, zz, cosmology, h, n_classes,
                                              _node_draws(theta))
    per_class = [theta.draws[j] if isinstance(theta, NodeDraws) else theta for j in node]
    n_k = kernels.shape[2]
    grid = m_tab[0] + h * np.arange(k0, len(m_tab) + k0 + n_k - 1)        # observed magnitudes
    # Each class only reads the part of the grid its kernel covers.
    cut = [_support(k) for k in kernels]
    flipped = [kernels[c][:, a:b][:, ::-1] for c, (a, b) in enumerate(cut)]
    mdl = sf.model
    n_tab = len(m_tab)
    for a in (range(len(idx)) if order is None else order):
        d = idx[a]
        q = None if q_on is None else q_on(grid, a)
        out = 0.0
        for c, oc in enumerate(offsets):
            lo, hi = cut[c]
            g = slice(lo, hi + n_tab - 1)
            th = per_class[c] if d < 0 else per_class[c][d:d + 1]
            cc, ss = mdl.surfaces_on_grid(th, zz, grid[g] + oc)
            p = np.median(cc * ss, axis=0) if d < 0 else (cc * ss)[0]        # (n_z, G_c)
            if q is None:
                out = out + fftconvolve(p, flipped[c], mode="valid", axes=1)
            else:
                out = out + fftconvolve(p[:, :, None] * q[:, g], flipped[c][:, :, None],
                                        mode="valid", axes=1)
        yield a, out
