"""Completeness and selection surfaces, their priors, and the binomial likelihood.

Covariates
----------
``m`` is the total input magnitude of a source in the detection band (AB, or
M_UV for an absolute-magnitude run), ``z`` its redshift and ``d`` the local
depth under it (``depth_local``: the 5-sigma aperture limit of the detection
band's noise map at its position, :mod:`glaciar.engine.depth`).  Completeness
of a faint source is set by the noise under it: scaling the noise by a factor
k scales every flux threshold by k, which moves the completeness curve by
2.5 log10 k in magnitude without changing its shape.  A *depth-aware* model
(``depth_ref`` set) therefore uses the depth-relative magnitude

    m_rel = m - (d - depth_ref)

in place of ``m`` everywhere below: C(m, z | d) = C(m_rel, z).  A field of
uniform depth d = depth_ref has m_rel = m and the model is the plain one.

Surfaces
--------
The probability that an injected source is *recovered* is

    C(m, z) = C_max(z) * F((m - m50(z)) / w(z))

and the probability that it is *selected*, given that it is recovered, is

    S(z, m) = S_max * sigma(a) * sigma(b),
    a = eta_lo(m) + (z - z_min) / dz_lo(m),   b = eta_hi(m) + (z_max - z) / dz_hi(m)

so that P(selected | z, m) = C(m, z) * S(z, m).  ``sigma`` is the logistic
function, [z_min, z_max] = [z_ref - z_scale, z_ref + z_scale] the simulated
redshift range, and ``eta_lo`` (``eta_hi``) the logit of the rising (falling)
edge *at the lower (upper) end of that range*: the 50 % point of the edge is
z_min - eta_lo dz_lo (z_max + eta_hi dz_hi).  Parametrising an edge by its
value at the range's end rather than by its position keeps it identifiable
when it lies outside the simulated range: the data then bound eta from one
side and leave dz to its prior, a rectangle the sampler crosses in a few
steps, where (position, width) would form an unbounded curved ridge.

``F`` is a decreasing step with F(-inf) = 1 and F(+inf) = 0:

- ``"logistic"``: F(u) = 1 / (1 + exp(u))                      (w: e-folding width)
- ``"erf"``:      F(u) = erfc(u / sqrt 2) / 2                   (w: Gaussian sigma)
- ``"fleming"``:  F(u) = (1 - u / sqrt(1 + u^2)) / 2            (Fleming et al. 1995
  form as used by Pritchet; w = 1/alpha; power-law tails ~ 1/(4 u^2))
- ``"sas"``:      F(u) = Phi(-sinh(delta asinh(u) - eps))       (sinh-arcsinh step,
  Jones & Pewsey 2009: a flexible monotone family with skewness ``eps`` and
  tail weight ``delta`` = exp(sas_log_delta) > 0; erf at eps = 0, delta = 1;
  for eps != 0, m50 is the location, not the 50 % point)

The smooth dependences are polynomials in normalised coordinates
``zc = (z - z_ref) / z_scale`` and ``mc = (m - m_ref) / m_scale``::

    logit C_max(z) = sum_k logit_c_max_k zc^k  (degree ``c_max_degree``)
    m50(z)         = sum_k m50_k   zc^k        (degree ``m50_degree``)
    ln w(z)        = sum_k log_w_k zc^k        (degree ``log_w_degree``; w > 0)
    eta_lo(m)      = sum_k eta_lo_k mc^k,  ln dz_lo(m) = sum_k log_dz_lo_k mc^k
    eta_hi(m)      = sum_k eta_hi_k mc^k,  ln dz_hi(m) = sum_k log_dz_hi_k mc^k   (``edge_degree``)
    S_max = sigma(logit_s_max)

Priors: every parameter has an independent normal prior (see
:meth:`SurfaceModel.prior_mean` / :meth:`SurfaceModel.prior_sd` and the file
docs), which is proper.  The likelihood is a product of probabilities, so it is
bounded by 1, and the posterior is bounded by the (normalisable) prior: it
stays proper and its maximum finite when the data are separable.

Likelihood: ``recovered ~ Bernoulli(C)`` and ``selected | recovered ~
Bernoulli(S)`` (the same as ``selected ~ Bernoulli(C S)``, since selected
implies recovered).  Per aggregated cell of ``n`` sources with ``k_rec``
recovered and ``k_sel`` selected the log-likelihood is (binomial coefficients
dropped): ``k_rec ln C + (n - k_rec) ln(1 - C) + k_sel ln S + (k_rec - k_sel) ln(1 - S)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import log_ndtr

__all__ = ["COMPLETENESS_SHAPES", "SurfaceModel", "Cells", "BlockPosterior", "step_function",
           "log_step"]

COMPLETENESS_SHAPES = ("logistic", "erf", "fleming", "sas")

# Prior constants (documented in docs/selection-function-file.md).  Logit
# N(2, 2) puts the median of C_max and S_max at 0.88 with 95 % in [0.12, 0.998].
_LOGIT_MAX_PRIOR = (2.0, 2.0)
_LOGIT_MAX_SLOPE_SD = 1.0
# ln w ~ N(ln 0.3 mag, 1): 95 % of widths in 0.04 .. 2.1 mag.
_LOG_W_PRIOR = (np.log(0.3), 1.0)
_LOG_W_SLOPE_SD = 0.5
# eta (logit of an edge at the end of the simulated z range) ~ N(0, 6): from an
# edge well inside the range (eta = -(distance inside) / dz, e.g. -10 for an edge
# 1 in z inside with dz = 0.1) to one well outside it (eta >~ 5: S there is flat).
_ETA_PRIOR = (0.0, 3.0)
_ETA_SLOPE_SD = 1.5
# ln dz ~ N(ln 0.2, 1): edge widths 0.03 .. 1.4 in z at 95 %; the slopes in m are
# left wide (sd 1): the demo's J-dropout edges move with magnitude by more than
# an sd-0.5 prior allows, which biased the lower-edge intervals.
_LOG_DZ_PRIOR = (np.log(0.2), 1.0)
_LOG_DZ_SLOPE_SD = 1.0
# sinh-arcsinh step: skewness eps ~ N(0, 1), ln delta ~ N(0, 0.5).
_SAS_PRIORS = {"sas_eps": (0.0, 1.0), "sas_log_delta": (0.0, 0.5)}
# Floor on log-probabilities so that 0 * log(0) terms are 0, not NaN.
_LOG_FLOOR = -1e200
# |u| beyond which the steps are 0 or 1 to double precision; keeps exp() finite.
_U_CLIP = 700.0


def _log_sigmoid(x):
    """ln(1 / (1 + exp(-x))), exact and overflow-free for any x."""
    return -np.logaddexp(0.0, -x)


def _sas_transform(u, eps, log_delta):
    """sinh(delta asinh(u) - eps): maps the sas step onto the erf step."""
    t = np.exp(log_delta) * np.arcsinh(u) - eps
    return np.sinh(np.clip(t, -40.0, 40.0))


def log_step(u, shape):
    """ln F(u) for the completeness step ``shape``, stable at both tails.

    Parameters
    ----------
    u : array_like
        Standardised magnitude (m - m50) / w (dimensionless); for ``"sas"``
        the already transformed argument sinh(delta asinh(u) - eps).
    shape : {"logistic", "erf", "fleming", "sas"}

    Returns
    -------
    ndarray
        ln F(u); ln(1 - F(u)) is ``log_step(-u, shape)``.
    """
    u = np.asarray(u, dtype=float)
    if shape == "logistic":
        return -np.logaddexp(0.0, u)
    if shape in ("erf", "sas"):
        return log_ndtr(-u)
    if shape == "fleming":
        a = np.abs(u)
        s = np.sqrt(1.0 + a * a)
        # F(|u|) = (1 - a/s)/2 = 1 / (2 s (s + a)): no cancellation at large |u|.
        t = 0.5 / (s * (s + a))
        return np.where(u >= 0, np.log(t), np.log1p(-t))
    raise ValueError(f"unknown completeness shape {shape!r}; expected one of {COMPLETENESS_SHAPES}")


def step_function(u, shape):
    """F(u): the completeness step (1 at bright u -> -inf, 0 at faint u -> +inf)."""
    return np.exp(log_step(u, shape))


@dataclass(frozen=True)
class Cells:
    """Aggregated binomial counts: sources sharing (z, magnitude) covariates.

    Attributes
    ----------
    z : ndarray
        Input redshift of the cell.
    mag : ndarray
        The model's magnitude covariate of the cell [mag]: the mean input
        magnitude, depth-relative (m - (d - depth_ref)) for a depth-aware model.
    n, k_rec, k_sel : ndarray of int
        Sources in the cell, recovered ones, selected ones (k_sel <= k_rec <= n).
    """

    z: np.ndarray
    mag: np.ndarray
    n: np.ndarray
    k_rec: np.ndarray
    k_sel: np.ndarray

    def __post_init__(self):
        n, kr, ks = (np.asarray(a) for a in (self.n, self.k_rec, self.k_sel))
        if not (len(self.z) == len(self.mag) == len(n) == len(kr) == len(ks)):
            raise ValueError("Cells: z, mag, n, k_rec, k_sel must have the same length")
        if np.any(ks > kr) or np.any(kr > n) or np.any(ks < 0):
            raise ValueError("Cells: counts must satisfy 0 <= k_sel <= k_rec <= n "
                             "(a selected source must be recovered)")

    @property
    def n_sources(self) -> int:
        return int(np.sum(self.n))

    def __len__(self):
        return len(self.z)


def _poly(x, ref, scale, degree):
    """Powers of the normalised coordinate, shape x.shape + (degree + 1,)."""
    xc = (np.asarray(x, float) - ref) / scale
    return xc[..., None] ** np.arange(degree + 1)


@dataclass(frozen=True)
class SurfaceModel:
    """The parametric C(m, z) and S(z, m) surfaces with their priors.

    Parameters
    ----------
    shape : {"logistic", "erf", "fleming", "sas"}
        Completeness step shape.
    z_ref, z_scale : float
        Redshift normalisation, zc = (z - z_ref) / z_scale; the simulated range
        is z_ref -+ z_scale (the selection edges are anchored at its ends).
    m_ref, m_scale : float
        Magnitude normalisation, mc = (m - m_ref) / m_scale [mag].
    m50_degree, log_w_degree, edge_degree, c_max_degree : int
        Polynomial degrees of m50(z), ln w(z), of the selection edges in m and
        of logit C_max(z).
    depth_ref : float or None
        Reference depth [AB mag]: with a value, the model is depth-aware and
        every magnitude is taken relative to the local depth, m - (d - depth_ref).
    selection : bool
        False for a detection-only run (no selection criteria): S is 1 exactly,
        the model has no selection parameters and no "s" block.
    """

    shape: str = "logistic"
    z_ref: float = 0.0
    z_scale: float = 1.0
    m_ref: float = 0.0
    m_scale: float = 1.0
    m50_degree: int = 2
    log_w_degree: int = 1
    edge_degree: int = 1
    c_max_degree: int = 1
    depth_ref: float | None = None
    selection: bool = True
    _slices: dict = field(default=None, init=False, repr=False, compare=False)
    _cache: dict = field(default=None, init=False, repr=False, compare=False)
    _n_total: int = field(default=0, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.shape not in COMPLETENESS_SHAPES:
            raise ValueError(f"unknown completeness model {self.shape!r}; "
                             f"expected one of {COMPLETENESS_SHAPES}")
        if not (self.z_scale > 0 and self.m_scale > 0):
            raise ValueError("SurfaceModel: z_scale and m_scale must be positive")
        for name in ("m50_degree", "log_w_degree", "edge_degree", "c_max_degree"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"SurfaceModel: {name} must be >= 0")
        if self.depth_ref is not None and not np.isfinite(self.depth_ref):
            raise ValueError(f"SurfaceModel: depth_ref must be finite, not {self.depth_ref}")
        e = self.edge_degree + 1
        sizes = [("logit_c_max", self.c_max_degree + 1), ("m50", self.m50_degree + 1),
                 ("log_w", self.log_w_degree + 1)]
        if self.shape == "sas":
            sizes += [("sas_eps", 1), ("sas_log_delta", 1)]
        if self.selection:
            sizes += [("logit_s_max", 1), ("eta_lo", e), ("log_dz_lo", e), ("eta_hi", e),
                      ("log_dz_hi", e)]
        sl, i = {}, 0
        for name, k in sizes:
            sl[name] = slice(i, i + k)
            i += k
        object.__setattr__(self, "selection", bool(self.selection))
        object.__setattr__(self, "_slices", sl)
        object.__setattr__(self, "_n_total", i)
        # Names and priors are fixed by the model; computed once because the
        # log prior is evaluated at every sampler step.
        names = []
        for name, sl_ in sl.items():
            k = sl_.stop - sl_.start
            single = name in ("logit_s_max",) or name.startswith("sas_")
            names += [name] if single else [f"{name}_{j}" for j in range(k)]
        object.__setattr__(self, "_cache", {"names": tuple(names), "mean": self._prior_mean(),
                                            "sd": self._prior_sd()})

    # ------------------------------------------------------------------ setup
    @classmethod
    def for_data(cls, z, mag, shape="logistic", depth_ref=None, selection=True,
                 **degrees) -> "SurfaceModel":
        """Model normalised to the covariate ranges of the data.

        Parameters
        ----------
        z, mag : array_like
            Input redshifts and the magnitude covariate [mag] of the sources
            (or cells; depth-relative for a depth-aware model).
        shape : str
            Completeness step shape.
        depth_ref : float, optional
            Reference depth [AB mag] of a depth-aware model.
        selection : bool
            False: detection only, S = 1 exactly (no selection parameters).
        """
        z = np.asarray(z, float)
        mag = np.asarray(mag, float)
        if z.size == 0:
            raise ValueError("SurfaceModel.for_data: no sources")
        zlo, zhi = float(np.min(z)), float(np.max(z))
        mlo, mhi = float(np.min(mag)), float(np.max(mag))
        # A polynomial in z of degree >= the number of distinct z is not identified by
        # the data (its value between the simulated redshifts is the prior's): cap the
        # degrees of the z terms at n_z - 1 (and of the edges' m terms at n_m - 1).
        n_z = len(np.unique(np.round(z, 6)))
        n_m = len(np.unique(np.round(mag, 2)))
        defaults = {f.name: f.default for f in cls.__dataclass_fields__.values()}
        for name in ("m50_degree", "log_w_degree", "c_max_degree"):
            degrees[name] = min(int(degrees.get(name, defaults[name])), n_z - 1)
        degrees["edge_degree"] = min(int(degrees.get("edge_degree", defaults["edge_degree"])), n_m - 1)
        # A single z (or magnitude) gives no lever arm: unit scale, the prior rules.
        return cls(shape=shape, z_ref=0.5 * (zlo + zhi), z_scale=0.5 * (zhi - zlo) or 1.0,
                   m_ref=0.5 * (mlo + mhi), m_scale=0.5 * (mhi - mlo) or 1.0,
                   depth_ref=None if depth_ref is None else float(depth_ref),
                   selection=bool(selection), **degrees)

    @property
    def depth_aware(self) -> bool:
        return self.depth_ref is not None

    @property
    def z_range(self) -> tuple[float, float]:
        """The simulated redshift range the edges are anchored to."""
        return self.z_ref - self.z_scale, self.z_ref + self.z_scale

    def relative_magnitude(self, m, depth=None) -> np.ndarray:
        """The model's magnitude covariate: m - (depth - depth_ref), or m.

        ``depth=None`` (or a model that is not depth-aware) means the reference depth.
        """
        m = np.asarray(m, float)
        if depth is None or self.depth_ref is None:
            return m
        return m - (np.asarray(depth, float) - self.depth_ref)

    @property
    def param_names(self) -> list[str]:
        """Names of the parameters, in the order of the parameter vector."""
        return list(self._cache["names"])

    @property
    def n_params(self) -> int:
        return len(self._cache["names"])

    @property
    def prior_mean(self) -> np.ndarray:
        """Means of the independent normal priors (see module docstring)."""
        return self._cache["mean"].copy()

    @property
    def prior_sd(self) -> np.ndarray:
        """Standard deviations of the independent normal priors."""
        return self._cache["sd"].copy()

    def _prior_mean(self) -> np.ndarray:
        s = self._slices
        mu = np.zeros(self._n_total)
        mu[s["logit_c_max"].start] = _LOGIT_MAX_PRIOR[0]
        mu[s["m50"].start] = self.m_ref                      # centre of the magnitude range
        mu[s["log_w"].start] = _LOG_W_PRIOR[0]
        if self.selection:
            mu[s["logit_s_max"]] = _LOGIT_MAX_PRIOR[0]
            for e in ("eta_lo", "eta_hi"):
                mu[s[e].start] = _ETA_PRIOR[0]
            for e in ("log_dz_lo", "log_dz_hi"):
                mu[s[e].start] = _LOG_DZ_PRIOR[0]
        for name, (m, _) in _SAS_PRIORS.items():
            if name in s:
                mu[s[name]] = m
        return mu

    def _prior_sd(self) -> np.ndarray:
        s = self._slices
        sd = np.ones(self._n_total)
        sd[s["logit_c_max"]] = _LOGIT_MAX_SLOPE_SD
        sd[s["logit_c_max"].start] = _LOGIT_MAX_PRIOR[1]
        sd[s["m50"]] = self.m_scale                     # m50 may move by the half range per zc
        sd[s["m50"].start] = 2.0 * self.m_scale         # anywhere within +-1 full range
        sd[s["log_w"]] = _LOG_W_SLOPE_SD
        sd[s["log_w"].start] = _LOG_W_PRIOR[1]
        if self.selection:
            sd[s["logit_s_max"]] = _LOGIT_MAX_PRIOR[1]
            for e in ("eta_lo", "eta_hi"):
                sd[s[e]] = _ETA_SLOPE_SD
                sd[s[e].start] = _ETA_PRIOR[1]
            for e in ("log_dz_lo", "log_dz_hi"):
                sd[s[e]] = _LOG_DZ_SLOPE_SD
                sd[s[e].start] = _LOG_DZ_PRIOR[1]
        for name, (_, v) in _SAS_PRIORS.items():
            if name in s:
                sd[s[name]] = v
        return sd

    def sample_prior(self, n, rng) -> np.ndarray:
        """``n`` parameter vectors drawn from the prior, shape (n, n_params)."""
        return self.prior_mean + self.prior_sd * rng.standard_normal((n, self.n_params))

    def log_prior(self, theta) -> np.ndarray:
        """Normalised log prior density, shape theta.shape[:-1]."""
        mu, sd = self._cache["mean"], self._cache["sd"]
        t = (np.asarray(theta, float) - mu) / sd
        return (-0.5 * np.sum(t * t, axis=-1) - np.sum(np.log(sd))
                - 0.5 * self.n_params * np.log(2 * np.pi))

    # ---------------------------------------------------------- evaluation
    def _c_terms(self, theta, z):
        """Per-z terms of C: logit C_max, m50 and 1/w, each (W, n_z); theta (W, P)."""
        s = self._slices
        deg = max(self.m50_degree, self.log_w_degree, self.c_max_degree)
        zp = _poly(z, self.z_ref, self.z_scale, deg)
        lcm = theta[:, s["logit_c_max"]] @ zp[:, :self.c_max_degree + 1].T
        m50 = theta[:, s["m50"]] @ zp[:, :self.m50_degree + 1].T
        inv_w = np.exp(-(theta[:, s["log_w"]] @ zp[:, :self.log_w_degree + 1].T))
        return lcm, m50, inv_w

    def _sas(self, theta, u):
        """The sas transform of u (W, N) with the draws' shape parameters."""
        s = self._slices
        return _sas_transform(u, theta[:, s["sas_eps"]], theta[:, s["sas_log_delta"]])

    def _log_c(self, theta, m, z):
        """ln C and ln(1 - C); theta (W, P), m and z 1-D (N,) -> two (W, N) arrays."""
        lcm, m50, inv_w = self._c_terms(theta, z)
        u = (np.asarray(m, float)[None, :] - m50) * inv_w
        return _log_c_terms(self, theta, lcm, u)

    def _s_args(self, theta, z, m):
        """Arguments a, b of the rising and falling edge, (W, N) each."""
        s = self._slices
        mp = _poly(m, self.m_ref, self.m_scale, self.edge_degree)
        z = np.asarray(z, float)[None, :]
        zmin, zmax = self.z_range
        a = theta[:, s["eta_lo"]] @ mp.T + (z - zmin) * np.exp(-(theta[:, s["log_dz_lo"]] @ mp.T))
        b = theta[:, s["eta_hi"]] @ mp.T + (zmax - z) * np.exp(-(theta[:, s["log_dz_hi"]] @ mp.T))
        return a, b

    def _log_s(self, theta, z, m):
        """ln S and ln(1 - S); theta (W, P), z and m 1-D (N,) -> two (W, N) arrays."""
        if not self.selection:                       # detection only: S = 1 exactly
            shape = (len(theta), np.size(z))
            return np.zeros(shape), np.full(shape, -np.inf)
        a, b = self._s_args(theta, z, m)
        # S = S_max / D with D = (1 + e^-a)(1 + e^-b), and 1 - S = (D - S_max) / D where
        # D - S_max = (1 - S_max) + ea + eb + ea eb is a sum of positives.  Clipping a, b
        # at -300 only matters where S < 1e-130, i.e. nowhere a posterior can sit.
        ea = np.exp(-np.clip(a, -300.0, _U_CLIP))
        eb = np.exp(-np.clip(b, -300.0, _U_CLIP))
        log_d = np.log1p(ea + eb + ea * eb)
        lsm = theta[:, self._slices["logit_s_max"]]
        with np.errstate(divide="ignore"):
            log_1ms = np.log(np.exp(_log_sigmoid(-lsm)) + ea + eb + ea * eb) - log_d
        return _log_sigmoid(lsm) - log_d, log_1ms

    @staticmethod
    def _theta2d(theta):
        theta = np.asarray(theta, float)
        return theta[None, :] if theta.ndim == 1 else theta

    def completeness(self, theta, m, z, depth=None) -> np.ndarray:
        """C(m, z | depth) for parameter vector(s) ``theta``.

        Parameters
        ----------
        theta : array_like, shape (P,) or (D, P)
        m, z : array_like
            Input magnitude [mag] and redshift, broadcast together.
        depth : array_like, optional
            Local depth [AB mag] (broadcast with m, z); default the reference
            depth.  Ignored by a model that is not depth-aware.

        Returns
        -------
        ndarray
            Shape ``broadcast(m, z).shape`` for one theta, else ``(D,) + that``.
        """
        th = self._theta2d(theta)
        m, z = np.broadcast_arrays(self.relative_magnitude(m, depth), np.asarray(z, float))
        log_c, _ = self._log_c(th, m.ravel(), z.ravel())
        out = np.exp(log_c).reshape((len(th),) + m.shape)
        return out[0] if np.ndim(theta) == 1 else out

    def selection_given_recovered(self, theta, z, m, depth=None) -> np.ndarray:
        """S(z, m | depth): probability that a *recovered* source is selected.

        Same arguments as :meth:`completeness`; the probability that a source
        is recovered and selected is ``completeness * selection_given_recovered``.
        """
        th = self._theta2d(theta)
        z, m = np.broadcast_arrays(np.asarray(z, float), self.relative_magnitude(m, depth))
        log_s, _ = self._log_s(th, z.ravel(), m.ravel())
        out = np.exp(log_s).reshape((len(th),) + z.shape)
        return out[0] if np.ndim(theta) == 1 else out

    def completeness_per_draw(self, theta, m, z, depth=None) -> np.ndarray:
        """C for draw i at magnitudes m[i]: theta (D, P), m (D, K), z scalar -> (D, K).

        The per-draw counterpart of :meth:`completeness` (which evaluates every
        draw at every point), for root finding along m draw by draw.
        """
        th = self._theta2d(theta)
        lcm, m50, inv_w = self._c_terms(th, np.atleast_1d(float(z)))          # (D, 1)
        u = (self.relative_magnitude(m, depth) - m50) * inv_w
        return np.exp(_log_c_terms(self, th, lcm, u)[0])

    def surfaces_on_grid(self, theta, z, m):
        """C(m, z) and S(z, m) on the outer grid ``z`` x ``m`` (model covariates), many draws.

        Same values as :meth:`completeness` and :meth:`selection_given_recovered`
        (tested to 1e-12), but the z terms are evaluated per z and the edges per
        m, so a grid point costs a few array operations (V_eff integrals).

        Parameters
        ----------
        theta : array_like, shape (P,) or (D, P)
        z : array_like, shape (n_z,)
        m : array_like, shape (n_m,)
            Magnitude covariate [mag] (depth-relative for a depth-aware model).

        Returns
        -------
        C, S : ndarray
            Shape (D, n_z, n_m), or (n_z, n_m) for one theta.
        """
        from scipy.special import expit

        th = self._theta2d(theta)
        s = self._slices
        z = np.asarray(z, float).ravel()
        m = np.asarray(m, float).ravel()
        lcm, m50, inv_w = self._c_terms(th, z)                                   # (D, n_z)
        # The (D, n_z, n_m) arrays are computed in place: the same operations in the same
        # order (so the same bits) without a temporary per step; V_eff integrals call this
        # for thousands of draws, where the temporaries' memory traffic was most of its time.
        u = np.subtract(m[None, None, :], m50[:, :, None])
        u *= inv_w[:, :, None]
        if self.shape == "sas":
            u = _sas_transform(u, th[:, s["sas_eps"]][:, :, None],
                               th[:, s["sas_log_delta"]][:, :, None])
        if self.shape == "logistic":
            c = expit(np.negative(u, out=u), out=u)
        else:
            c = step_function(u, self.shape)
        c *= expit(lcm)[:, :, None]
        if not self.selection:                       # detection only: S = 1 exactly
            sel = np.ones_like(c)
            return (c[0], sel[0]) if np.ndim(theta) == 1 else (c, sel)
        mp = _poly(m, self.m_ref, self.m_scale, self.edge_degree)                 # (n_m, k)
        edge = {k: th[:, s[k]] @ mp.T for k in ("eta_lo", "log_dz_lo", "eta_hi", "log_dz_hi")}
        zmin, zmax = self.z_range
        a = np.multiply((z - zmin)[None, :, None], np.exp(-edge["log_dz_lo"])[:, None, :])
        a += edge["eta_lo"][:, None, :]
        b = np.multiply((zmax - z)[None, :, None], np.exp(-edge["log_dz_hi"])[:, None, :])
        b += edge["eta_hi"][:, None, :]
        sel = expit(a, out=a)
        sel *= expit(th[:, s["logit_s_max"]])[:, :, None]
        sel *= expit(b, out=b)
        if np.ndim(theta) == 1:
            return c[0], sel[0]
        return c, sel

    @np.errstate(over="ignore", invalid="ignore")
    def cell_log_likelihood(self, theta, cells: Cells, part: str = "both",
                            coefficients: bool = True) -> np.ndarray:
        """Binomial log-likelihood of every cell.

        Parameters
        ----------
        theta : array_like, shape (P,) or (W, P)
        cells : Cells
        part : {"both", "c", "s"}
            The recovered term (C), the selected-given-recovered term (S), or both.
        coefficients : bool
            Include the log binomial coefficients (needed for predictive
            densities; constant in theta).

        Returns
        -------
        ndarray, shape (W, n_cells) (or (n_cells,) for one theta)
        """
        from scipy.special import gammaln

        if part not in ("both", "c", "s"):
            raise ValueError(f"part must be 'both', 'c' or 's', not {part!r}")
        th = self._theta2d(theta)
        f = _LOG_FLOOR
        out = np.zeros((len(th), len(cells)))
        # (probability, trials, successes) of the two binomial terms
        terms = []
        if part in ("both", "c"):
            terms.append((self._log_c(th, cells.mag, cells.z), cells.n, cells.k_rec))
        if part in ("both", "s") and self.selection:   # S = 1 exactly: no S term
            terms.append((self._log_s(th, cells.z, cells.mag), cells.k_rec, cells.k_sel))
        for (log_p, log_1mp), n, k in terms:
            n, k = np.asarray(n, float), np.asarray(k, float)
            out += np.maximum(log_p, f) * k + np.maximum(log_1mp, f) * (n - k)
            if coefficients:
                out += gammaln(n + 1) - gammaln(k + 1) - gammaln(n - k + 1)
        return out[0] if np.ndim(theta) == 1 else out

    def log_likelihood(self, theta, cells: Cells, part: str = "both") -> np.ndarray:
        """Binomial log-likelihood of the cells (coefficients dropped).

        The recovered term (C) and the selected-given-recovered term (S) depend
        on disjoint parameters, so the posterior factorises (``part``).

        Returns
        -------
        ndarray, shape theta.shape[:-1]
        """
        return self.cell_log_likelihood(theta, cells, part, coefficients=False).sum(axis=-1)

    def log_posterior(self, theta, cells: Cells, part: str = "both") -> np.ndarray:
        """Unnormalised log posterior (prior over all parameters); NaN -> -inf."""
        lp = self.log_prior(theta) + self.log_likelihood(theta, cells, part)
        return np.where(np.isfinite(lp), lp, -np.inf)

    def block_indices(self, part: str) -> np.ndarray:
        """Indices of the parameters of ``part`` ("c": completeness, "s": selection)."""
        i = self._slices["logit_s_max"].start if self.selection else self.n_params
        return np.arange(i) if part == "c" else np.arange(i, self.n_params)

    @property
    def parts(self) -> tuple[str, ...]:
        """The parameter blocks: ("c", "s"), or ("c",) for a detection-only model."""
        return ("c", "s") if self.selection else ("c",)

    def block_log_posterior(self, cells: Cells, part: str) -> "BlockPosterior":
        """The fast vectorised log posterior of one parameter block (see :class:`BlockPosterior`)."""
        return BlockPosterior(self, cells, part)

    # -------------------------------------------------------------- header
    def to_header_dict(self) -> dict:
        """FITS-header keywords that fully specify the model (see the file docs).

        ``SELFIT = False`` marks a detection-only model (S = 1); it is left out when
        S is fitted, so such files (and saved-chain keys) are what they were before.
        """
        h = {"CSHAPE": self.shape, "ZREF": self.z_ref, "ZSCALE": self.z_scale,
             "MREF": self.m_ref, "MSCALE": self.m_scale, "DEGM50": self.m50_degree,
             "DEGLOGW": self.log_w_degree, "DEGEDGE": self.edge_degree,
             "DEGCMAX": self.c_max_degree,
             "DEPTHREF": float("nan") if self.depth_ref is None else self.depth_ref}
        if not self.selection:
            h["SELFIT"] = False
        return h

    @classmethod
    def from_header_dict(cls, h) -> "SurfaceModel":
        try:
            dref = float(h["DEPTHREF"])
            return cls(shape=str(h["CSHAPE"]), z_ref=float(h["ZREF"]), z_scale=float(h["ZSCALE"]),
                       m_ref=float(h["MREF"]), m_scale=float(h["MSCALE"]),
                       m50_degree=int(h["DEGM50"]), log_w_degree=int(h["DEGLOGW"]),
                       edge_degree=int(h["DEGEDGE"]), c_max_degree=int(h["DEGCMAX"]),
                       depth_ref=dref if np.isfinite(dref) else None,
                       # files written before detection-only models all fitted S
                       selection=bool(h.get("SELFIT", True)))
        except KeyError as exc:
            raise ValueError(f"selection-function header lacks model keyword {exc}") from exc


def _log_c_terms(model, theta, lcm, u):
    """ln C and ln(1 - C) from logit C_max (W, N or broadcastable) and u (W, N)."""
    log_cmax = _log_sigmoid(lcm)
    if model.shape == "logistic":
        # Two logs per element (logs dominate the cost): with e = exp(u),
        # C = C_max / (1 + e) and 1 - C = ((1 - C_max) + e) / (1 + e), both
        # sums of positives.  |u| <= 700 keeps exp finite; beyond it C is
        # below 1e-304 or equal to C_max to double precision anyway.
        e = np.exp(np.clip(u, -_U_CLIP, _U_CLIP))
        log1pe = np.log1p(e)
        with np.errstate(divide="ignore"):
            log_1mc = np.log(np.exp(_log_sigmoid(-lcm)) + e) - log1pe
        return log_cmax - log1pe, log_1mc
    if model.shape == "sas":
        u = model._sas(theta, u)
    lf = log_step(u, model.shape)
    # 1 - C_max F(u) = (1 - C_max) + C_max F(-u): a sum of positives, no cancellation.
    log_1mc = np.logaddexp(_log_sigmoid(-lcm), log_cmax + log_step(-u, model.shape))
    return log_cmax + lf, log_1mc


class BlockPosterior:
    """Log posterior of one parameter block on fixed cells, for the sampler.

    The posterior factorises into the completeness block ("c": recovered
    flags) and the selection block ("s": selected-given-recovered flags).
    Calling the object with block parameter vectors ``x`` (shape (W, P_block)
    or (P_block,)) returns

        ln p_block(x) = ln prior_block(x) + ln L_part(x),

    which equals ``SurfaceModel.log_posterior(theta, cells, part)`` minus the
    (constant) prior of the other block, to rounding (tested to 1e-10).

    Why it is faster than :meth:`SurfaceModel.log_posterior` (same formulas):

    - C_max(z), m50(z) and w(z) depend on z only, the edges on m only.  When
      the cells share few distinct z (or m) values -- a simulation grid -- the
      cells are sorted by that value, the terms (and the exponentials of the
      widths) are evaluated once per value and repeated over its cells;
      otherwise they are evaluated per cell;
    - the binomial sum is rearranged so that each cell needs one ``log1p`` and
      one ``log``: with e = exp(u),
      ``k ln C + (n - k) ln(1 - C) = k ln C_max - n ln(1 + e) + (n - k) ln((1 - C_max) + e)``
      (logistic; the selection term is the same with D - 1 = e_a + e_b + e_a e_b);
    - cells without a recovered source carry no selection information and are
      dropped from the "s" block;
    - the normal prior of the block is a few array operations.

    Parameters
    ----------
    model : SurfaceModel
    cells : Cells
    part : {"c", "s"}
    """

    def __init__(self, model: SurfaceModel, cells: Cells, part: str):
        if part not in ("c", "s"):
            raise ValueError(f"part must be 'c' or 's', not {part!r}")
        self.model, self.part = model, part
        self.index = model.block_indices(part)
        mu, sd = model._cache["mean"][self.index], model._cache["sd"][self.index]
        self._mu, self._isd = mu, 1.0 / sd
        self._prior_const = -np.sum(np.log(sd)) - 0.5 * len(sd) * np.log(2 * np.pi)
        off = self.index[0]
        self._sl = {k: slice(v.start - off, v.stop - off) for k, v in model._slices.items()
                    if v.start >= off and v.stop <= off + len(self.index)}
        n = np.asarray(cells.n, float)
        kr = np.asarray(cells.k_rec, float)
        ks = np.asarray(cells.k_sel, float)
        z, m = np.asarray(cells.z, float), np.asarray(cells.mag, float)
        if part == "c":
            trials, succ, group, x = n, kr, z, m
            ref, scale = model.z_ref, model.z_scale
            deg = max(model.m50_degree, model.log_w_degree, model.c_max_degree)
        else:
            keep = kr > 0
            trials, succ, group, x = kr[keep], ks[keep], m[keep], z[keep]
            ref, scale, deg = model.m_ref, model.m_scale, model.edge_degree
        order = np.argsort(group, kind="stable")
        ug, inv, counts = np.unique(group[order], return_inverse=True, return_counts=True)
        # Repeating per-value terms pays only when values are shared by several cells.
        self._counts = counts if 4 * len(ug) <= len(group) else None
        g = ug if self._counts is not None else group[order]
        self._trials, self._succ = trials[order], succ[order]
        self._fail = self._trials - self._succ
        # Successes per value (or per cell): the k ln C_max term is summed per value.
        self._succ_g = (np.bincount(inv, weights=self._succ, minlength=len(ug))
                        if self._counts is not None else self._succ)
        self._x = x[order]
        self._gp = ((g - ref) / scale)[:, None] ** np.arange(deg + 1)   # (n_values, deg + 1)

    @property
    def n_params(self) -> int:
        return len(self.index)

    def _prior(self, x):
        t = (x - self._mu) * self._isd
        return -0.5 * np.einsum("ij,ij->i", t, t) + self._prior_const

    def _lin(self, x, name):
        s = self._sl[name]
        return x[:, s] @ self._gp[:, :s.stop - s.start].T                # (W, n_values)

    def _expand(self, a):
        return a if self._counts is None else np.repeat(a, self._counts, axis=1)

    @np.errstate(over="ignore", invalid="ignore")
    def __call__(self, x) -> np.ndarray:
        x = np.asarray(x, float)
        one = x.ndim == 1
        x = np.atleast_2d(x)
        if len(self._x) == 0:
            ll = np.zeros(len(x))
        else:
            ll = self._log_like_c(x) if self.part == "c" else self._log_like_s(x)
        lp = self._prior(x) + ll
        lp = np.where(np.isfinite(lp), lp, -np.inf)
        return lp[0] if one else lp

    def _log_like_c(self, x):
        lcm = self._lin(x, "logit_c_max")                          # (W, n_values)
        inv_w = np.exp(-self._lin(x, "log_w"))
        u = self._x - self._expand(self._lin(x, "m50"))
        u *= self._expand(inv_w)                                  # (m - m50) / w, (W, N)
        log_cmax = _log_sigmoid(lcm)
        if self.model.shape == "logistic":
            # e = exp(u); C = C_max / (1 + e), 1 - C = ((1 - C_max) + e) / (1 + e).
            # |u| <= 700 keeps e finite and > 0, so no log(0) (see _log_c_terms).
            np.clip(u, -_U_CLIP, _U_CLIP, out=u)
            e = np.exp(u, out=u)
            ll = log_cmax @ self._succ_g - np.log1p(e) @ self._trials
            e += self._expand(np.exp(_log_sigmoid(-lcm)))
            return ll + np.log(e, out=e) @ self._fail
        if self.model.shape == "sas":
            u = _sas_transform(u, x[:, self._sl["sas_eps"]], x[:, self._sl["sas_log_delta"]])
        f = _LOG_FLOOR
        lf = log_step(u, self.model.shape)
        log_1mc = np.logaddexp(self._expand(_log_sigmoid(-lcm)),
                               self._expand(log_cmax) + log_step(-u, self.model.shape))
        return (log_cmax @ self._succ_g + np.maximum(lf, f) @ self._succ
                + np.maximum(log_1mc, f) @ self._fail)

    def _log_like_s(self, x):
        lsm = x[:, self._sl["logit_s_max"].start]
        z, ex = self._x, self._expand
        zmin, zmax = self.model.z_range
        # Minus the edge arguments: -a = -eta_lo - (z - z_min) / dz_lo, -b likewise.
        na = (zmin - z) * ex(np.exp(-self._lin(x, "log_dz_lo")))
        na -= ex(self._lin(x, "eta_lo"))
        nb = (z - zmax) * ex(np.exp(-self._lin(x, "log_dz_hi")))
        nb -= ex(self._lin(x, "eta_hi"))
        # S = S_max / D, D = (1 + e^-a)(1 + e^-b); D - 1 = ea + eb + ea eb, a sum of
        # positives, > 0 after the clipping (same as SurfaceModel._log_s), so no log(0).
        np.clip(na, -_U_CLIP, 300.0, out=na)
        np.clip(nb, -_U_CLIP, 300.0, out=nb)
        ea = np.exp(na, out=na)
        eb = np.exp(nb, out=nb)
        t = ea * eb
        t += ea
        t += eb
        ll = np.sum(self._succ) * _log_sigmoid(lsm) - np.log1p(t) @ self._trials
        t += np.exp(_log_sigmoid(-lsm))[:, None]
        return ll + np.log(t, out=t) @ self._fail
