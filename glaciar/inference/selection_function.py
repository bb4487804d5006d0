"""The exported selection function: evaluate, sample, effective volume.

Three quantities, each with one name (so that nothing is multiplied twice):

* :meth:`SelectionFunction.completeness` -- C = P(recovered | m, z);
* :meth:`SelectionFunction.selection_given_recovered` -- S = P(selected | recovered, z, m);
* :meth:`SelectionFunction.selection_probability` -- P = P(recovered and selected | z, m),
  what a luminosity-function code multiplies by.

Without a ``depth`` argument each is the *area-weighted survey average* over the
fields' area-by-depth distributions (the one the file's grids tabulate):
C̄ = Σ_j A_j C(m | d_j) / Σ A_j, P̄ likewise, and S̄ = P̄ / C̄, so that C̄ S̄ = P̄
draw by draw.  With ``depth`` they are the surfaces at that local depth.

For luminosity-function codes also V_eff as a function of M_UV
(:meth:`SelectionFunction.effective_volume_muv`, mapping M_UV to the detection band with
the injections' spectra, :class:`InjectionSED` and :func:`kcorrection`), the
photometric transfer function p(m_obs | m_in, z) (:meth:`SelectionFunction.transfer`,
counted by :func:`glaciar.tables.transfer_matrix`; anywhere in the box:
:meth:`SelectionFunction.transfer_function`), and the expected counts per measured-magnitude
bin of a luminosity function (:meth:`SelectionFunction.expected_counts`).

The file (layout in ``docs/selection-function-file.md``, so that it can be read
without glaciar) is encoded and decoded on bytes by
:mod:`glaciar.inference.selection_format`; ``SelectionFunction.read`` and ``write``
are the inference layer's one file access: they move the whole file's bytes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..rundir import atomic_write_bytes
from . import covariates, selection_format
from .contamination import ContaminationMixin
from .counts import SurveyVolume, count_kernel, expected_counts
from .lensed import LensedSelection, lensed_muv_volume_draws, lensed_volume_draws
from .models import SurfaceModel
from .products import (GRID_QUANTILES, EffectiveVolume, MagnitudeAt, TransferSlice,
                       beta_nodes, kcorrection)
from .transfer import transfer_function
from .volume import (merge_depth_nodes, muv_magnitudes, muv_volume_draws, summarise_volume,
                     volume_draws, warn_if_cut, detection_z_limit)

__all__ = ["SelectionFunction", "MAX_DEPTH_NODES", "EXTRAPOLATION_TOLERANCE"]

#: The area-by-depth histogram (0.05 mag bins) is merged into at most this many
#: depth nodes, each at the area-weighted mean depth of its bins: the surfaces
#: are smooth in depth on the scale of w (~0.3 mag), so the error of the mixture
#: is second order in the node width (< 2e-3 in P for a 1.3 mag depth range, tested).
MAX_DEPTH_NODES = 12
#: V_eff(M_UV) is NaN (``outside="nan"``) when more than this fraction of it would come
#: from (z, m) points outside the simulated magnitude range (the surface's extrapolation).
EXTRAPOLATION_TOLERANCE = 1e-3


class SelectionFunction(ContaminationMixin, LensedSelection):
    """Posterior draws of C and S, evaluable anywhere inside the simulated box.

    Parameters
    ----------
    model : SurfaceModel
    draws : ndarray, shape (n_draws, n_params)
        Posterior draws of the parameters.
    z_grid, m_grid : ndarray, optional
        Grid of the tabulated quantiles in the file.
    meta : dict, optional
        Metadata (fields, area_arcmin2, area_arcmin2_field, bands, selection,
        magnitude_type, config_hash, ...).
    field : str
        Which field the fit describes ("all" when pooled).
    ppc : numpy structured array, optional
        Posterior-predictive check table.
    fit_info : dict, optional
        Scalar diagnostics (written to the DRAWS header).
    depth_area : dict, optional
        ``{field: (bin_edges_mag, area_arcmin2)}``: the area-by-depth
        distribution of each field this fit describes.
    domain : dict, optional
        The simulated box: ``{"z": (lo, hi), "mag": (lo, hi), "depth": (lo, hi)}``;
        evaluations outside it are NaN unless ``outside="extrapolate"``.
    diagnostics : dict of arrays, optional
        Per-parameter ``tau``, ``ess``, ``rhat`` (written to PARAMS).
    sed : InjectionSED, optional
        The injections' spectra (maps M_UV to the detection band for
        :meth:`effective_volume_muv`).

    Attributes
    ----------
    veff_muv : VeffTable or None
        V_eff(M_UV) tabulated by ``glaciar fit`` (file extension ``VEFF_MUV``); set by
        :func:`glaciar.pipeline.selection_file.add_lf_products` and by :meth:`read`.
    transfer_matrix : glaciar.tables.TransferMatrix or None
        The photometric transfer function of this fit's sources (``TRANSFER``); set
        likewise.  Both are products of a run's rows, not of the fitted surface, so they
        are attached after construction rather than passed in.
    """

    def __init__(self, model: SurfaceModel, draws, z_grid=None, m_grid=None, *, meta=None,
                 field: str = "all", ppc=None, fit_info=None, depth_area=None, domain=None,
                 diagnostics=None, sed=None):
        self.model = model
        self.draws = np.atleast_2d(np.asarray(draws, float))
        if self.draws.shape[1] != model.n_params:
            raise ValueError(f"draws have {self.draws.shape[1]} columns, model {model.shape!r} "
                             f"needs {model.n_params}")
        self.z_grid = None if z_grid is None else np.asarray(z_grid, float)
        self.m_grid = None if m_grid is None else np.asarray(m_grid, float)
        self.meta = dict(meta or {})
        self.field = str(field)
        self.ppc = ppc
        self.fit_info = dict(fit_info or {})
        self.depth_area = {str(k): (np.asarray(e, float), np.asarray(a, float))
                           for k, (e, a) in (depth_area or {}).items()}
        self.domain = {k: (float(v[0]), float(v[1])) for k, v in (domain or {}).items()}
        self.diagnostics = dict(diagnostics or {})
        self.sed = sed
        self.veff_muv = None
        self.transfer_matrix = None
        self.covariates = {}    # {name: CovariateNodes}: size/beta covariates (glaciar.inference.covariates)

    @property
    def n_draws(self) -> int:
        return len(self.draws)

    @property
    def param_names(self) -> list[str]:
        return self.model.param_names

    @property
    def magnitude_type(self) -> str:
        """"apparent" (m is the detection-band AB magnitude) or "absolute" (M_UV at 1600 A)."""
        return str(self.meta.get("magnitude_type", "apparent"))

    @property
    def detection_z_limit(self) -> float | None:
        """Lowest redshift [to 0.005] at which the detection band receives no flux, or None.

        Beyond it nothing is detected, so P = 0 there whatever the fitted surface
        extrapolates.  From the metadata (``detection_z_limit``, as the run's manifest
        records it) when present, else from the injection SED (:attr:`sed`: a source of
        the central beta is fainter than ``FAINT_MAG_LIMIT`` in the band, the rule of
        :func:`kcorrection` and of the injections), searched up to z = 30.  None without
        either, or when the band receives flux up to z = 30.
        """
        if not hasattr(self, "_z_limit"):
            self._z_limit = self._find_z_limit()
        return self._z_limit

    def _find_z_limit(self):
        v = self.meta.get("detection_z_limit")
        if v is not None:
            try:
                v = float(v)
            except (TypeError, ValueError):
                v = None
            if v is not None and np.isfinite(v):
                return v
        if self.sed is None:
            return None
        zr = self.domain.get("z", self._z_range())
        return detection_z_limit(self.sed, max(zr[0], 0.01), zr[1])

    def z_edge_is_physical(self, z_top: float, within: float = 0.1) -> bool:
        """Whether a redshift range ending at ``z_top`` reaches the detection band's flux limit.

        True when ``z_top`` is within ``within`` of :attr:`detection_z_limit` (or above
        it): P is 0 beyond, so a selection that is still high at ``z_top`` loses no
        volume (the tolerance :func:`glaciar.pipeline.fit` uses for its edge check).
        """
        zl = self.detection_z_limit
        return zl is not None and float(z_top) >= zl - within

    @property
    def fields(self) -> list[str]:
        """Fields this fit describes (those with a depth distribution, else from the metadata)."""
        if self.depth_area:
            return sorted(self.depth_area)
        return [self.field] if self.field != "all" else list(self.meta.get("fields", []))

    def area_arcmin2(self, field: str | None = None) -> float | None:
        """Area [arcmin^2] of ``field``, or of all fields this fit describes.

        From the depth distributions when present, else from the metadata:
        ``area_arcmin2_field`` (or an ``area_arcmin2`` mapping) per field, or
        one ``area_arcmin2`` number for the whole fit.
        """
        if self.depth_area:
            if field is None:
                return float(sum(np.sum(a) for _, a in self.depth_area.values()))
            return float(np.sum(self.depth_area[field][1])) if field in self.depth_area else None
        total = self.meta.get("area_arcmin2")
        per = self.meta.get("area_arcmin2_field")
        if per is None and isinstance(total, dict):
            per, total = total, None
        per = per or {}
        key = field if field is not None else (self.field if self.field != "all" else None)
        if key is not None:
            return float(per[key]) if key in per else None
        if total is not None:
            return float(total)
        return float(sum(map(float, per.values()))) if per else None

    # ------------------------------------------------------------- depth mixture
    def depth_nodes(self, field: str | None = None):
        """(depths [AB mag], areas [arcmin^2]) over which survey averages are taken.

        A model that is not depth-aware (or a fit without depth distributions)
        has one node at the reference depth carrying the whole area (or 1); a
        model that is not depth-aware ignores the depth it is given (NaN here).
        """
        if not self.model.depth_aware or not self.depth_area:
            a = self.area_arcmin2(field)
            ref = self.model.depth_ref if self.model.depth_aware else np.nan
            return np.array([ref]), np.array([a if a else 1.0])
        if field is not None:
            if field not in self.depth_area:
                raise ValueError(f"no depth distribution for field {field!r} "
                                 f"(have {sorted(self.depth_area)})")
            items = [self.depth_area[field]]
        else:
            items = list(self.depth_area.values())
        # Fields share the 0.05 mag lattice: sum their histograms bin by bin.
        bins = {}
        for e, a in items:
            c = np.round(0.5 * (e[:-1] + e[1:]), 6)
            w = np.round(e[1:] - e[:-1], 6)
            for ci, wi, ai in zip(c, w, a):
                key = (ci, wi)
                bins[key] = bins.get(key, 0.0) + ai
        keys = sorted(bins)
        centres = np.array([k[0] for k in keys])
        widths = np.array([k[1] for k in keys])
        edges = np.concatenate([centres - widths / 2, centres[-1:] + widths[-1:] / 2])
        if len(keys) > 1 and not np.allclose(edges[1:-1], (centres + widths / 2)[:-1]):
            # Not contiguous: treat each bin as its own node.
            return centres, np.array([bins[k] for k in keys])
        return merge_depth_nodes(edges, np.array([bins[k] for k in keys]), MAX_DEPTH_NODES)

    def _mask(self, m, z, depth):
        """True where (m, z[, depth]) lies outside the simulated box."""
        bad = np.zeros(np.broadcast(m, z).shape, bool)
        for key, v in (("mag", m), ("z", z), ("depth", depth)):
            if key in self.domain and v is not None:
                lo, hi = self.domain[key]
                tol = 1e-9 * max(1.0, abs(hi))
                bad = bad | (np.asarray(v) < lo - tol) | (np.asarray(v) > hi + tol)
        return bad

    def _evaluate(self, which, m, z, depth, field, draws, outside, **cov):
        if any(v is not None for v in cov.values()):     # at given r_e / beta: covariates.py
            return covariates.evaluate(self, which, m, z, depth, field, draws, outside, **cov)
        if outside not in ("nan", "extrapolate"):
            raise ValueError(f"outside must be 'nan' or 'extrapolate', not {outside!r}")
        m = np.asarray(m, float)
        z = np.asarray(z, float)
        mdl, th = self.model, self.draws
        if not mdl.selection and which != "C":
            # Detection only: S = 1 and P = C exactly (no selection was applied).
            c = self._evaluate("C", m, z, depth, field, True, "extrapolate")
            out = c if which == "P" else np.ones_like(c)
        elif depth is not None or not mdl.depth_aware:
            c = mdl.completeness(th, m, z, depth)
            if which == "C":
                out = c
            else:
                s = mdl.selection_given_recovered(th, z, m, depth)
                out = s if which == "S" else c * s
        else:
            nodes, area = self.depth_nodes(field)
            w = area / area.sum()
            cbar = pbar = 0.0
            for dj, wj in zip(nodes, w):
                c = mdl.completeness(th, m, z, dj)
                cbar = cbar + wj * c
                if which != "C":
                    pbar = pbar + wj * c * mdl.selection_given_recovered(th, z, m, dj)
            if which == "C":
                out = cbar
            elif which == "P":
                out = pbar
            else:
                with np.errstate(invalid="ignore", divide="ignore"):
                    out = pbar / cbar
        if outside == "nan":
            bad = self._mask(m, z, depth)
            if bad.any():
                out = np.where(bad, np.nan, out)
        return out if draws else np.median(out, axis=0)

    # ---------------------------------------------------------------- evaluate
    def completeness(self, m, z, depth=None, *, field: str | None = None, draws: bool = False,
                     outside: str = "nan", r_eff_arcsec=None) -> np.ndarray:
        """Completeness C = P(recovered | m, z).

        Parameters
        ----------
        m : array_like
            Total input magnitude [mag]: AB in the detection band, or M_UV for
            an absolute-magnitude fit (:attr:`magnitude_type`).
        z : array_like
            Redshift; broadcast against ``m``.
        depth : array_like, optional
            Local depth [AB mag, 5 sigma]: C at that depth.  Default: the
            area-weighted average over the survey's (or ``field``'s) depths.
        field : str, optional
            Average over this field's area only (depth=None).
        draws : bool
            Return every posterior draw, shape ``(n_draws,) + shape``, instead
            of the pointwise posterior median.
        outside : {"nan", "extrapolate"}
            Outside the simulated (z, m[, depth]) box the value is NaN, unless
            "extrapolate" asks for the parametric form's extrapolation.
        r_eff_arcsec : array_like, optional
            C at this half-light radius [arcsec] (a fit with ``--covariates r_eff``); without
            it C is marginalised over the injected sizes (the pooled fit, as without covariates).
        """
        return self._evaluate("C", m, z, depth, field, draws, outside, r_eff_arcsec=r_eff_arcsec)

    def selection_given_recovered(self, z, m, depth=None, *, field: str | None = None,
                                  draws: bool = False, outside: str = "nan", beta=None) -> np.ndarray:
        """S = P(selected | recovered, z, m): the colour/S-N selection of a recovered source.

        Survey averages are P̄ / C̄, so ``completeness * selection_given_recovered``
        equals :meth:`selection_probability` draw by draw.  Arguments as
        :meth:`completeness`; ``beta``: S at this UV slope (a fit with ``--covariates beta``).
        """
        return self._evaluate("S", m, z, depth, field, draws, outside, beta=beta)

    def selection_probability(self, z, m, depth=None, *, field: str | None = None, draws: bool = False,
                              outside: str = "nan", r_eff_arcsec=None, beta=None) -> np.ndarray:
        """P = P(recovered and selected | z, m) = C S: what an LF code multiplies by.

        Arguments as :meth:`completeness` and :meth:`selection_given_recovered`.
        """
        return self._evaluate("P", m, z, depth, field, draws, outside, r_eff_arcsec=r_eff_arcsec,
                              beta=beta)

    def sample(self, n: int, seed=None) -> list["SelectionFunction"]:
        """``n`` posterior draws, each a one-draw SelectionFunction.

        Fitting a luminosity function once per returned object propagates the
        selection-function uncertainty.  Draws are taken without replacement
        when ``n <= n_draws``.
        """
        rng = np.random.default_rng(seed)
        idx = rng.choice(self.n_draws, size=int(n), replace=int(n) > self.n_draws)
        return [SelectionFunction(self.model, self.draws[i:i + 1], self.z_grid, self.m_grid,
                                  meta=self.meta, field=self.field, depth_area=self.depth_area,
                                  domain=self.domain, sed=self.sed) for i in idx]

    def magnitude_at(self, completeness: float, z, *, field: str | None = None,
                     interval: float = 0.68) -> MagnitudeAt:
        """The magnitude where the survey-averaged C falls to ``completeness``, per draw.

        C is monotone in m for every draw (and so is its area-weighted depth
        average), so each draw's root is found by bisection, to 1e-6 mag, within
        the simulated magnitude range +- 5 mag.  NaN where the level is not
        reached there (e.g. above C_max), and wherever the answer would be an
        extrapolation: a quantile outside the simulated magnitude range, or a
        redshift outside the simulated one (like :meth:`completeness`).

        Parameters
        ----------
        completeness : float
            Level in (0, 1), e.g. 0.5 for m50.
        z : float or 1-D array_like
            Redshift(s).
        """
        level = float(completeness)
        if not 0 < level < 1:
            raise ValueError(f"completeness level must be in (0, 1), not {level}")
        z = np.atleast_1d(np.asarray(z, float))
        lo_m, hi_m = self.domain.get("mag", (self.model.m_ref - self.model.m_scale,
                                             self.model.m_ref + self.model.m_scale))
        nodes, area = self.depth_nodes(field)
        w = area / area.sum()

        def cbar(m, zj):                                       # (D,) per-draw mixture C
            return sum(wj * self.model.completeness_per_draw(
                self.draws, m[:, None], zj, dj)[:, 0]
                for dj, wj in zip(nodes, w))

        out = np.full((self.n_draws, len(z)), np.nan)
        for j, zj in enumerate(z):
            lo = np.full(self.n_draws, lo_m - 5.0)
            hi = np.full(self.n_draws, hi_m + 5.0)
            ok = (cbar(lo, zj) >= level) & (cbar(hi, zj) < level)
            for _ in range(45):                                # 30 mag / 2^45 < 1e-12 mag
                mid = 0.5 * (lo + hi)
                above = cbar(mid, zj) >= level
                lo = np.where(above, mid, lo)
                hi = np.where(above, hi, mid)
            out[:, j] = np.where(ok, 0.5 * (lo + hi), np.nan)
        if "mag" in self.domain:
            # A root outside the simulated range is an extrapolation of the parametric
            # step: kept as -inf / +inf (its side), so that the quantiles count the draw
            # but no number outside the range is reported.
            tol = 1e-9 * max(1.0, abs(hi_m))
            out = np.where(out < lo_m - tol, -np.inf, np.where(out > hi_m + tol, np.inf, out))
        with np.errstate(all="ignore"):
            fin = ~np.isnan(out)
            q = np.full((3, len(z)), np.nan)
            for j in range(len(z)):
                if fin[:, j].any():
                    q[:, j] = np.quantile(out[fin[:, j], j],
                                          [0.5, 0.5 - interval / 2, 0.5 + interval / 2])
        q[~np.isfinite(q)] = np.nan
        if "z" in self.domain:
            zlo, zhi = self.domain["z"]
            tol = 1e-9 * max(1.0, abs(zhi))
            q[:, (z < zlo - tol) | (z > zhi + tol)] = np.nan
        return MagnitudeAt(median=q[0], lower=q[1], upper=q[2], draws=out)

    def effective_volume(self, m, area=None, cosmology=None, *, field: str | None = None,
                         z_min=None, z_max=None, n_z: int = 2001, interval: float = 0.68,
                         size_relation=None, beta_distribution=None) -> EffectiveVolume:
        """V_eff(m) = Σ_fields Σ_depth A(d) ∫ C(m, z | d) S(z, m | d) dV/dz/dΩ dz.

        Lensed fields (:mod:`glaciar.inference.lensed`) sum their source-plane area
        instead, ``m`` being the intrinsic magnitude, averaged over the lens models
        (:meth:`for_lens_model` picks one; :meth:`lens_model_volumes` gives each and the spread).

        Parameters
        ----------
        m : float or array_like
            Input magnitude(s) [mag].
        area : astropy Quantity (solid angle) or float, optional
            Survey area; a float is in arcmin^2.  Default: the fields' areas
            (their area-by-depth distributions).  Given explicitly, it rescales
            the depth distribution of the fields to this total area.
        cosmology : astropy.cosmology.Cosmology, optional
            Default Planck18.
        field : str, optional
            One field's V_eff (its area and depths); the fields' V_eff add up
            to the survey's.
        z_min, z_max : float, optional
            Integration range; default (and at most) the simulated range.
        n_z : int
            Simpson nodes (odd).  With 2001 nodes the integral is accurate to
            < 1e-4 relative for edges wider than dz = 0.02 (tested against
            scipy.integrate.quad to 1e-3).
        interval : float
            Credible-interval probability (central).
        size_relation, beta_distribution : optional
            :class:`~glaciar.inference.covariates.SizeRelation` / ``BetaDistribution``: C
            (S) averaged over that law instead of the injected one (fits with covariates).

        Returns
        -------
        EffectiveVolume
            Quantities in Mpc^3.

        Raises
        ------
        ValueError
            No area known or given, or no redshift range (a single-z fit).
        """
        import astropy.units as u

        if cosmology is None:
            from astropy.cosmology import Planck18 as cosmology
        nodes, node_sr = self._area_nodes(area, field, "effective_volume")
        zr = self.domain.get("z", self._z_range())
        z_min, z_max = self._z_limits(z_min, z_max, "effective_volume")
        n_z = int(n_z) | 1
        zz = np.linspace(z_min, z_max, n_z)
        dvdz = cosmology.differential_comoving_volume(zz).to_value(u.Mpc ** 3 / u.sr)
        m = np.asarray(m, float)
        mm = m.reshape(-1)
        if self.lens_nodes and area is None:
            out = self.lensed_draws(
                lambda nl: lensed_volume_draws(self.model, self.lens_theta(), nl, zz, dvdz, mm,
                                                   cosmology),
                lambda f: volume_draws(self.model, self.draws, *self._area_nodes(None, f, "V_eff"),
                                       zz, dvdz, mm)[0], field)
        else:
            out, ends = volume_draws(self.model, self.draws, nodes, node_sr, zz, dvdz, mm)
            if size_relation is not None or beta_distribution is not None:
                out = covariates.reweighted_volume_draws(self, nodes, node_sr, zz, dvdz, mm,
                                                         size_relation, beta_distribution)
            # V_eff counts only the simulated z range: say so when C*S is not ~0 at its ends
            # (but not at a top where the detection band receives no flux).
            if (z_min, z_max) == tuple(zr):
                warn_if_cut(ends, zr, self.z_edge_is_physical(zr[1]), mm)
        if "mag" in self.domain:
            out[:, self._mask(mm, np.full(mm.shape, zz[0]), None)] = np.nan
        return summarise_volume(out.reshape((len(out),) + m.shape), interval)

    def _area_nodes(self, area, field, who):
        """(depth nodes, their solid angles [sr]) for a V_eff integral."""
        import astropy.units as u

        nodes, node_area = self.depth_nodes(field)
        if area is not None:
            if not isinstance(area, u.Quantity):
                area = float(area) * u.arcmin ** 2
            total = area.to_value(u.arcmin ** 2)
            if not (np.isfinite(total) and total > 0):
                raise ValueError(f"{who}: area must be a positive finite number, not {area}")
            node_area = node_area / node_area.sum() * total
        elif self.area_arcmin2(field) is None:
            raise ValueError(f"{who}: give `area` (the file records no survey area)")
        return nodes, (node_area * u.arcmin ** 2).to_value(u.sr)

    def _z_limits(self, z_min, z_max, who):
        """The integration range: the simulated one, or inside it."""
        zr = self.domain.get("z", self._z_range())
        z_min = zr[0] if z_min is None else max(float(z_min), zr[0])
        z_max = zr[1] if z_max is None else min(float(z_max), zr[1])
        if not z_max > z_min:
            raise ValueError(f"{who}: no redshift range to integrate over "
                             f"(z_min = {z_min}, z_max = {z_max}); simulate more than one redshift")
        return z_min, z_max

    def effective_volume_muv(self, M_uv, area=None, cosmology=None, *, sed=None, beta=None,
                             field: str | None = None, z_min=None, z_max=None, n_z: int = 201,
                             n_beta: int = 7, interval: float = 0.68,
                             outside: str = "nan") -> EffectiveVolume:
        """V_eff as a function of absolute UV magnitude, per posterior draw.

        V_eff(M) = Σ_fields Σ_depth Ω(d) ∫ dz dV/dz/dΩ <P̄(z, M + K(z, beta) | d)>_beta,
        with K = m_det - M_UV the map the injections used (:func:`kcorrection`:
        same detection filter, IGM and beta distribution) and the average over
        beta taken by Gauss-Hermite quadrature (``n_beta`` nodes) of N(beta_mean,
        beta_sd), or over the given ``beta`` values with equal weights.  Where
        the band receives no flux, P = 0.  For a fit made in absolute magnitudes
        (:attr:`magnitude_type` "absolute") the fit is already in M_UV and this is
        :meth:`effective_volume` (``sed`` and ``beta`` are not needed).

        The fitted P̄(z, m) is already an average over the injected betas at fixed
        m; the average here is over the spread in m of sources of one M_UV.  A
        dependence of the colour selection on beta at fixed m (beyond that
        average) is not modelled.

        Parameters
        ----------
        M_uv : float or array_like
            Absolute magnitude(s) at rest 1600 A [AB mag].
        area : astropy Quantity or float, optional
            As :meth:`effective_volume` (float in arcmin^2).
        cosmology : astropy Cosmology or str, optional
            For dV/dz and the distance modulus; default the injections'
            (``sed.cosmology``), else Planck18.
        sed : InjectionSED, optional
            Default :attr:`sed` (recorded by ``glaciar fit``).
        beta : array_like, optional
            Explicit beta samples (equal weights) instead of the quadrature of
            the sed's normal distribution.
        field : str, optional
            One field's V_eff.
        z_min, z_max : float, optional
            Integration range; default (and at most) the simulated range.
        n_z : int
            Simpson nodes in z (odd).
        n_beta : int
            Gauss-Hermite nodes of the beta average.
        interval : float
            Central credible-interval probability.
        outside : {"nan", "extrapolate"}
            "nan": NaN for an M_UV that draws more than
            ``EXTRAPOLATION_TOLERANCE`` of its (median) V_eff from magnitudes
            outside the simulated range (at the central beta); "extrapolate"
            keeps the parametric surface's extrapolation (always, behind a lens).

        Returns
        -------
        EffectiveVolume
            Quantities in Mpc^3, shape of ``M_uv`` (draws: ``(n_draws,) + shape``).

        Raises
        ------
        ValueError
            No SED recorded or given (apparent-magnitude fit), no area, no
            redshift range, a bad ``outside``.
        """
        import astropy.units as u

        from ..galaxy.population import get_cosmology

        if outside not in ("nan", "extrapolate"):
            raise ValueError(f"outside must be 'nan' or 'extrapolate', not {outside!r}")
        sed = self.sed if sed is None else sed
        if cosmology is None:
            cosmology = sed.cosmology if sed is not None else None
        cosmology = get_cosmology(cosmology)
        if self.magnitude_type == "absolute":
            return self.effective_volume(M_uv, area, cosmology, field=field, z_min=z_min,
                                         z_max=z_max, n_z=max(int(n_z), 2001), interval=interval)
        if sed is None:
            raise ValueError("effective_volume_muv: this fit records no injection SED (detection "
                             "filter, beta, IGM); pass sed=InjectionSED(...)")
        if beta is None:
            bnodes, bw = beta_nodes(sed.beta_mean, sed.beta_sd, n_beta)
            b_centre = float(sed.beta_mean)
        else:
            bnodes = np.atleast_1d(np.asarray(beta, float))
            if bnodes.ndim != 1 or not np.all(np.isfinite(bnodes)) or not bnodes.size:
                raise ValueError("effective_volume_muv: beta must be finite values")
            bw = np.full(bnodes.size, 1.0 / bnodes.size)
            b_centre = float(np.median(bnodes))
        nodes, node_sr = self._area_nodes(area, field, "effective_volume_muv")
        z_min, z_max = self._z_limits(z_min, z_max, "effective_volume_muv")
        zz = np.linspace(z_min, z_max, int(n_z) | 1)
        dvdz = cosmology.differential_comoving_volume(zz).to_value(u.Mpc ** 3 / u.sr)
        kw = dict(igm=sed.igm, cosmology=cosmology)
        K = kcorrection(zz, bnodes, sed.detection_filter, **kw)                  # (n_z, n_b)
        k0 = kcorrection(zz, [b_centre], sed.detection_filter, **kw)[:, 0]      # (n_z,)
        M = np.asarray(M_uv, float)
        MM = M.reshape(-1)
        m, flux, ext = muv_magnitudes(MM, K, k0, self.domain["mag"] if "mag" in self.domain else None)
        tol = EXTRAPOLATION_TOLERANCE if outside == "nan" else None
        if self.lens_nodes and area is None:
            out = self.lensed_draws(lambda nl: lensed_muv_volume_draws(
                self.model, self.lens_theta(), nl, zz, dvdz, m, flux, bw, cosmology), lambda f: muv_volume_draws(
                self.model, self.draws, *self._area_nodes(None, f, "V_eff"), zz, dvdz, m, flux, bw,
                ext, tol), field)
        else:
            out = muv_volume_draws(self.model, self.draws, nodes, node_sr, zz, dvdz, m, flux, bw,
                                   ext, tol)
        return summarise_volume(out.reshape((self.n_draws,) + M.shape), interval)

    def muv_grid(self, step: float = 0.1, sed=None, cosmology=None):
        """M_UV grid [AB mag] covering the simulated magnitude range at the z where it maps brightest.

        Every M_UV of the grid maps (at the central beta) into the simulated range
        or fainter at every z; where the fainter images matter,
        :meth:`effective_volume_muv` gives NaN.  For an absolute-magnitude fit, the
        simulated range itself.  Used by ``glaciar fit`` for the file's ``VEFF_MUV``
        table.
        """
        from ..galaxy.population import get_cosmology

        lo, hi = self.domain.get("mag", (self.model.m_ref - self.model.m_scale,
                                         self.model.m_ref + self.model.m_scale))
        if self.magnitude_type != "absolute":
            sed = self.sed if sed is None else sed
            if sed is None:
                raise ValueError("muv_grid: this fit records no injection SED")
            cosmo = get_cosmology(sed.cosmology if cosmology is None else cosmology)
            zr = self.domain.get("z", self._z_range())
            zz = np.linspace(zr[0], zr[1], 1001)
            k = kcorrection(zz, [sed.beta_mean], sed.detection_filter, igm=sed.igm,
                            cosmology=cosmo)[:, 0]
            k = k[np.isfinite(k)]
            if not k.size:
                raise ValueError("muv_grid: the detection band receives no flux in the z range")
            # From the M_UV whose brightest image (smallest K) is the bright end of the
            # range, 1e-3 mag inside so that no z between these nodes maps outside it, to
            # the M_UV whose brightest image is the faint end: fainter images at other z
            # are extrapolations that effective_volume_muv blanks when they matter.
            lo, hi = lo - k.min() + 1e-3, hi - k.min()
        if not hi > lo:
            return np.array([])
        n = int(np.floor((hi - lo) / step + 1e-9)) + 1
        return np.round(lo + step * np.arange(n), 6)

    def transfer(self, z, kind: str = "recovered") -> TransferSlice:
        """p(m_obs | m_in) of the redshift slice holding ``z`` (the file's ``TRANSFER``).

        Parameters
        ----------
        z : float
            Redshift inside one of the slices (``transfer_matrix.z_edges``).
        kind : {"recovered", "selected"}
            Column 0 is "not recovered" or "not selected"; the other columns
            are the measured-magnitude bins of recovered (selected) sources.

        Raises
        ------
        ValueError
            No transfer matrix in this fit, a bad ``kind``, or ``z`` outside every slice.
        """
        tm = self.transfer_matrix
        if tm is None:
            raise ValueError("transfer: this selection function has no transfer matrix "
                             "(a file written before glaciar recorded one?)")
        if kind not in tm.kinds:
            raise ValueError(f"transfer: kind must be one of {tm.kinds}, not {kind!r}")
        z = float(z)
        i = int(np.searchsorted(tm.z_edges, z, side="right") - 1)
        if not 0 <= i < len(tm.z_edges) - 1:
            raise ValueError(f"transfer: z = {z:g} is outside the slices "
                             f"{tm.z_edges[0]:g}-{tm.z_edges[-1]:g}")
        k = tm.kinds.index(kind)
        return TransferSlice(m_in_edges=tm.m_in_edges, m_obs_edges=tm.m_obs_edges,
                             matrix=tm.matrix[k, i], draws=tm.draws[:, k, i],
                             counts=tm.counts[k, i], z_lo=float(tm.z_edges[i]),
                             z_hi=float(tm.z_edges[i + 1]), kind=kind)

    def transfer_function(self, kind: str = "selected", *, draws: bool = False, **kw):
        """The transfer function p(m_obs | m_in, z) anywhere in the simulated box.

        :func:`glaciar.inference.transfer.transfer_function` of :attr:`transfer_matrix`
        (keywords forwarded): interpolated between the matrix's rows and slices, per
        posterior draw with ``draws=True``.

        Raises
        ------
        ValueError
            No transfer matrix in this fit, or a bad ``kind``.
        """
        if self.transfer_matrix is None:
            raise ValueError("transfer_function: this selection function has no transfer "
                             "matrix (a file written before glaciar recorded one?)")
        return transfer_function(self.transfer_matrix, kind, draws=draws, **kw)

    def count_kernel(self, m_obs_edges, M_edges=None, **kw):
        """The linear map phi(M_UV) -> expected counts per measured-magnitude bin, per draw.

        :func:`glaciar.inference.counts.count_kernel` (keywords and defaults there).
        """
        return count_kernel(self, m_obs_edges, M_edges, **kw)

    def expected_counts(self, phi, m_obs_edges, *, z_min=None, z_max=None, M_uv_range=None,
                        area=None, cosmology=None, draws=True, transfer: bool = True, **kw):
        """Expected numbers of selected sources per measured-magnitude bin for an LF phi(M_UV, z).

        N_k = Σ_fields Σ_depth Ω(d) ∫ dz dV/dz/dΩ ∫ dM phi(M, z) <P(z, m | d) q(k | m, z)>_beta,
        m = M + K(z, beta) (M itself for an absolute-magnitude fit), q the transfer
        function conditional on selection (:meth:`transfer_function`).  Magnitudes
        outside the simulated range use the surface's extrapolation and the nearest
        transfer row; the share of each bin's counts that comes from them is returned and
        warned about where it matters.  Method, accuracy and the remaining keywords
        (``sed``, ``field``, ``quadrature``, ``interval``, ``warn``):
        :func:`glaciar.inference.counts.expected_counts`.

        Parameters
        ----------
        phi : callable
            ``phi(M, z)`` [Mpc^-3 mag^-1] on broadcastable arrays.
        m_obs_edges : array_like
            Measured detection-band magnitude bins [AB mag] (first may be -inf, last +inf).
        z_min, z_max : float, optional
            Redshift range; default (and at most) the simulated one.
        M_uv_range : (float, float), optional
            M_UV range integrated over [AB mag] (phi = 0 outside).
        area : float or Quantity, optional
            Survey area (float: arcmin^2); default the fit's.
        cosmology : astropy Cosmology or str, optional
            Default the injections'.
        draws : bool or int
            True: every posterior draw (selection draw i with transfer draw i mod n_t);
            an int: that many; False: one evaluation at the pointwise median of P.
        transfer : bool
            False: the measured magnitude is taken to be the input magnitude.
        interlopers : bool, optional (keyword)
            Add the expected interlopers (:meth:`with_interlopers`); default: when the file
            holds a contamination (docs/contamination.md).

        Returns
        -------
        glaciar.inference.counts.ExpectedCounts
        """
        volume = SurveyVolume(z_min=z_min, z_max=z_max, area=area, cosmology=cosmology)
        add = kw.pop("interlopers", None)
        return self.with_interlopers(expected_counts(
            self, phi, m_obs_edges, volume=volume, M_uv_range=M_uv_range, draws=draws,
            transfer=transfer, **kw), add, area, kw.get("interval", 0.68))

    def _z_range(self):
        if self.z_grid is not None:
            return float(self.z_grid[0]), float(self.z_grid[-1])
        return self.model.z_range

    # ------------------------------------------------------------------- grids
    def grid_draws(self, z_grid=None, m_grid=None, field: str | None = None, *,
                   outside: str = "nan"):
        """Draws of the survey-averaged C̄, S̄ = P̄/C̄ and P̄ on the outer grid z x m.

        ``outside`` as :meth:`completeness`: NaN outside the simulated (z, m) box,
        unless "extrapolate" (where to simulate next looks just beyond the data).

        Returns
        -------
        dict of ndarray, each (n_draws, n_z, n_m), keys "C", "S", "P".
        """
        if outside not in ("nan", "extrapolate"):
            raise ValueError(f"outside must be 'nan' or 'extrapolate', not {outside!r}")
        zg = self.z_grid if z_grid is None else np.asarray(z_grid, float)
        mg = self.m_grid if m_grid is None else np.asarray(m_grid, float)
        if zg is None or mg is None:
            raise ValueError("grid_draws: no z/m grid given or stored")
        nodes, area = self.depth_nodes(field)
        w = area / area.sum()
        cbar = np.zeros((self.n_draws, len(zg), len(mg)))
        pbar = np.zeros_like(cbar)
        for dj, wj in zip(nodes, w):
            mrel = self.model.relative_magnitude(mg, dj)
            c, s = self.model.surfaces_on_grid(self.draws, zg, mrel)
            cbar += wj * c
            pbar += wj * c * s
        if not self.model.selection:
            # Detection only: S = 1 and P = C exactly, also where C = 0.
            sbar, pbar = np.ones_like(cbar), cbar.copy()
        else:
            with np.errstate(invalid="ignore", divide="ignore"):
                sbar = pbar / cbar
        if self.domain and outside == "nan":
            # Outside the simulated box nothing is a measurement: NaN, as everywhere else.
            bad = self._mask(mg[None, :], zg[:, None], None)
            for a in (cbar, sbar, pbar):
                a[:, bad] = np.nan
        return {"C": cbar, "S": sbar, "P": pbar}

    def grid_quantiles(self, which: str, z_grid=None, m_grid=None, quantiles=GRID_QUANTILES,
                       field: str | None = None, *, outside: str = "nan"):
        """Pointwise posterior quantiles on the (z, m) grid, shape (n_q, n_z, n_m).

        Parameters
        ----------
        which : {"C", "S", "P"}
            Completeness, selection given recovery, or selection probability
            (survey averages, see the module docstring).
        """
        if which not in ("C", "S", "P"):
            raise ValueError(f"which must be 'C', 'S' or 'P', not {which!r}")
        return np.quantile(self.grid_draws(z_grid, m_grid, field, outside=outside)[which],
                           quantiles, axis=0)

    # ------------------------------------------------------------------ the file
    # The FITS layout (docs/selection-function-file.md) is encoded and decoded on bytes by
    # glaciar.inference.selection_format; ``read``/``write`` only move those bytes, because
    # ``glaciar.SelectionFunction.read(path)`` is how a luminosity-function code reads it.
    @staticmethod
    def to_bytes(fits_list: list["SelectionFunction"], meta: dict | None = None) -> bytes:
        """One or more fits as the bytes of one FITS file (:func:`selection_format.encode`)."""
        return selection_format.encode(fits_list, meta)

    @classmethod
    def from_bytes(cls, data: bytes, source: str = "<bytes>") -> dict[str, "SelectionFunction"]:
        """All fits in the bytes of a file, keyed by field (``source`` names it in errors);
        ValueError if not a file of :data:`glaciar.inference.selection_format.FILE_FORMAT`."""
        out = {}
        for field, kw in selection_format.decode(data, source).items():
            tables = {k: kw.pop(k) for k in ("veff_muv", "transfer_matrix", "interlopers",
                                             "lens_nodes", "covariates")}
            out[field] = sf = cls(**kw)
            sf.veff_muv, sf.transfer_matrix = tables["veff_muv"], tables["transfer_matrix"]
            sf.interlopers, sf.lens_nodes = tables["interlopers"], tables["lens_nodes"]
            sf.covariates = tables["covariates"]
        return out

    def write(self, path) -> None:
        """This fit alone, to ``path`` (written atomically: temp file + rename)."""
        atomic_write_bytes(Path(path), self.to_bytes([self]))

    @classmethod
    def read_all(cls, path) -> dict[str, "SelectionFunction"]:
        """All fits in the file at ``path``, keyed by field name (FileNotFoundError, ValueError)."""
        return cls.from_bytes(Path(path).read_bytes(), str(path))

    @classmethod
    def read(cls, path, field: str | None = None) -> "SelectionFunction":
        """One fit of the selection-function file at ``path``.

        Parameters
        ----------
        path : str or path-like
        field : str, optional
            Which fit to return when the file holds one per field.

        Raises
        ------
        FileNotFoundError
            No file at ``path``.
        ValueError
            Not a selection-function file, several fits and no ``field``, or no
            fit for ``field``.
        """
        if not Path(path).exists():
            raise FileNotFoundError(f"{path}: no such selection-function file")
        fits_ = cls.read_all(path)
        if field is None:
            if len(fits_) == 1:
                return next(iter(fits_.values()))
            raise ValueError(f"{path} holds fits for fields {sorted(fits_)}; pass field=")
        if field not in fits_:
            raise ValueError(f"{path}: no fit for field {field!r} (have {sorted(fits_)})")
        return fits_[field]

    def __repr__(self):
        return (f"SelectionFunction(model={self.model.shape!r}, field={self.field!r}, "
                f"depth_aware={self.model.depth_aware}, n_draws={self.n_draws})")

