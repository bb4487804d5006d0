"""Luminosity-function models phi(M_UV), their parameters and priors.

Every phi is in Mpc^-3 mag^-1 and M_UV is the absolute magnitude at rest 1600 A [AB mag].

* :func:`schechter` -- phi(M) = 0.4 ln 10 phi* x^(alpha + 1) exp(-x), x = 10^(-0.4 (M - M*))
  (Schechter 1976 in magnitudes);
* :func:`double_power_law` -- phi(M) = phi* / (10^(0.4 (alpha + 1) (M - M*))
  + 10^(0.4 (beta + 1) (M - M*))), alpha the faint-end and beta the bright-end slope
  (e.g. Bowler et al. 2014; no 0.4 ln 10 factor: phi* is the value at M* times 2);
* :func:`stepwise` -- phi constant in each bin of M_UV, 10^(log_phi_k) in bin k, 0 outside.

Parameters are sampled with independent **uniform priors** (:data:`PRIORS`): log10 phi*
[Mpc^-3 mag^-1] in (-8, 0) (double power law (-9, 0)), M* in (-25, -16), alpha in
(-3.5, 0.5), beta in (-8, -1) with beta < alpha (the two slopes of a double power law
are otherwise interchangeable), and each step's log10 phi in (-10, 0).  A fixed
parameter (``fix``) is held at its value, whatever the prior's range.

Arrays in, arrays out; no file I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["schechter", "double_power_law", "stepwise", "LFModel", "get_model", "parse_fix",
           "MODELS", "PRIORS", "STEP_PRIOR"]

_LN10_04 = 0.4 * np.log(10.0)

#: Uniform prior ranges of the parametric models' parameters.
PRIORS = {
    "schechter": {"log_phi_star": (-8.0, 0.0), "M_star": (-25.0, -16.0),
                  "alpha": (-3.5, 0.5)},
    "double_power_law": {"log_phi_star": (-9.0, 0.0), "M_star": (-25.0, -16.0),
                         "alpha": (-3.5, 0.5), "beta": (-8.0, -1.0)},
}
#: Uniform prior range of each stepwise bin's log10 phi [Mpc^-3 mag^-1].
STEP_PRIOR = (-10.0, 0.0)
#: Model names (``"dpl"`` is accepted for the double power law).
MODELS = ("schechter", "double_power_law", "stepwise")
_ALIASES = {"dpl": "double_power_law", "double-power-law": "double_power_law"}


def schechter(M, log_phi_star, M_star, alpha):
    """Schechter function in absolute magnitude [Mpc^-3 mag^-1].

    Parameters
    ----------
    M : array_like
        M_UV [AB mag].
    log_phi_star : float or array_like
        log10 phi* [Mpc^-3] (per unit L/L*, so phi(M) peaks near 0.4 ln 10 phi* / e).
    M_star : float or array_like
        Characteristic magnitude [AB mag].
    alpha : float or array_like
        Faint-end slope.

    Returns
    -------
    ndarray
        phi(M), broadcast over the arguments.
    """
    x = 10.0 ** (-0.4 * (np.asarray(M, float) - M_star))
    with np.errstate(over="ignore", under="ignore"):
        return _LN10_04 * 10.0 ** np.asarray(log_phi_star, float) * x ** (np.asarray(alpha) + 1) \
            * np.exp(-x)


def double_power_law(M, log_phi_star, M_star, alpha, beta):
    """Double power law in absolute magnitude [Mpc^-3 mag^-1].

    phi(M) = phi* / (10^(0.4 (alpha + 1) (M - M*)) + 10^(0.4 (beta + 1) (M - M*))):
    slope alpha faint of M*, beta bright of it (for beta < alpha).

    Parameters
    ----------
    M : array_like
        M_UV [AB mag].
    log_phi_star : float or array_like
        log10 phi* [Mpc^-3 mag^-1].
    M_star : float or array_like
        Break magnitude [AB mag].
    alpha, beta : float or array_like
        Faint- and bright-end slopes.
    """
    d = np.asarray(M, float) - M_star
    with np.errstate(over="ignore", under="ignore"):
        return 10.0 ** np.asarray(log_phi_star, float) / (10.0 ** (0.4 * (np.asarray(alpha) + 1) * d)
                                                        + 10.0 ** (0.4 * (np.asarray(beta) + 1) * d))


def stepwise(M, log_phi, edges):
    """Binned luminosity function: 10^(log_phi[k]) in bin k of ``edges``, 0 outside.

    Parameters
    ----------
    M : array_like
        M_UV [AB mag].
    log_phi : array_like (..., n_bins)
        log10 phi per bin [Mpc^-3 mag^-1].
    edges : array_like (n_bins + 1,)
        Increasing bin edges [AB mag]; bins are [lo, hi).

    Returns
    -------
    ndarray
        ``log_phi.shape[:-1] + M.shape``.
    """
    M = np.asarray(M, float)
    e = np.asarray(edges, float)
    lp = np.asarray(log_phi, float)
    k = np.searchsorted(e, M, side="right") - 1
    inside = (k >= 0) & (k < len(e) - 1)
    vals = 10.0 ** np.take(lp, np.clip(k, 0, len(e) - 2), axis=-1)
    return np.where(inside, vals, 0.0)


@dataclass(frozen=True)
class LFModel:
    """A luminosity-function model: parameter names, prior ranges and phi on M_UV.

    Attributes
    ----------
    name : str
        "schechter", "double_power_law" or "stepwise".
    param_names : tuple of str
    bounds : ndarray (n_params, 2)
        Uniform prior ranges.
    edges : ndarray or None
        Bin edges [AB mag] of a stepwise model.
    """

    name: str
    param_names: tuple
    bounds: np.ndarray
    edges: np.ndarray | None = None

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def phi(self, M, theta) -> np.ndarray:
        """phi(M) [Mpc^-3 mag^-1] for parameter vector(s) ``theta`` ((n_params,) or (W, n_params)).

        Returns ``theta.shape[:-1] + M.shape``.
        """
        th = np.asarray(theta, float)
        M = np.asarray(M, float)
        if self.name == "stepwise":
            return stepwise(M, th, self.edges)
        cols = [th[..., i].reshape(th.shape[:-1] + (1,) * M.ndim) for i in range(self.n_params)]
        f = schechter if self.name == "schechter" else double_power_law
        return f(M, *cols)

    def log_prior(self, theta) -> np.ndarray:
        """0 inside the uniform prior's support, -inf outside (per row of ``theta``)."""
        th = np.asarray(theta, float)
        ok = np.all((th >= self.bounds[:, 0]) & (th <= self.bounds[:, 1]), axis=-1)
        if self.name == "double_power_law":
            ok &= th[..., 3] < th[..., 2]
        return np.where(ok, 0.0, -np.inf)

    def check_fix(self, fix) -> dict:
        """``fix`` as {name: float}, every name a parameter of this model.

        Raises
        ------
        ValueError
            An unknown name (the message lists the allowed ones), a value that is not a
            finite number, or every parameter fixed.
        """
        out = {}
        for k, v in dict(fix or {}).items():
            if k not in self.param_names:
                raise ValueError(f"--fix: unknown parameter {k!r} for model {self.name!r}; "
                                 f"allowed: {', '.join(self.param_names)}")
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"--fix {k}={v!r}: not a number") from None
            if not np.isfinite(v):
                raise ValueError(f"--fix {k}={v}: not a finite number")
            out[k] = v
        if len(out) == self.n_params:
            raise ValueError(f"--fix: every parameter of {self.name!r} is fixed; nothing to fit")
        return out


def get_model(name: str, *, edges=None) -> LFModel:
    """The :class:`LFModel` called ``name`` ("schechter", "double_power_law"/"dpl", "stepwise").

    Parameters
    ----------
    name : str
    edges : array_like, optional
        Bin edges of the stepwise model [AB mag] (required for it).

    Raises
    ------
    ValueError
        Unknown model, or a stepwise model without >= 2 increasing edges.
    """
    key = _ALIASES.get(str(name).lower(), str(name).lower())
    if key not in MODELS:
        raise ValueError(f"unknown luminosity-function model {name!r}; choose one of "
                         f"{', '.join(MODELS)} (or 'dpl')")
    if key == "stepwise":
        if edges is None:
            raise ValueError("the stepwise model needs its M_UV bin edges")
        e = np.asarray(edges, float)
        if e.ndim != 1 or len(e) < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
            raise ValueError("stepwise: bin edges must be >= 2 finite increasing values")
        n = len(e) - 1
        return LFModel("stepwise", tuple(f"log_phi_{k}" for k in range(n)),
                       np.tile(STEP_PRIOR, (n, 1)), e)
    pri = PRIORS[key]
    return LFModel(key, tuple(pri), np.array(list(pri.values()), float))


def parse_fix(items, model: str = "schechter", *, param_names=None) -> dict:
    """``["alpha=-2", "M_star=-21"]`` -> ``{"alpha": -2.0, "M_star": -21.0}``, checked against the model.

    Parameters
    ----------
    items : iterable of str, or None
        ``NAME=VALUE`` strings (the CLI's ``--fix``).
    model : str
        Model whose parameters the names must be.  For "stepwise" (whose names depend on
        its bins) any ``log_phi_<k>`` is accepted unless ``param_names`` is given.
    param_names : sequence of str, optional
        The allowed names (overrides ``model``'s).

    Returns
    -------
    dict of str -> float

    Raises
    ------
    ValueError
        Not ``NAME=VALUE``, a value that is not a finite number, a name given twice, or a
        name that is not a parameter (the message lists the allowed ones).
    """
    key = _ALIASES.get(str(model).lower(), str(model).lower())
    if key not in MODELS:
        get_model(key)                                  # raises the unknown-model error
    if param_names is not None:
        allowed = tuple(param_names)
    elif key == "stepwise":
        allowed = None
    else:
        allowed = tuple(PRIORS[key])
    out = {}
    for item in items or ():
        name, sep, value = str(item).partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name or not value:
            raise ValueError(f"--fix {item!r}: expected NAME=VALUE")
        ok = (name in allowed) if allowed is not None else (
            name.startswith("log_phi_") and name[len("log_phi_"):].isdigit())
        if not ok:
            names = ", ".join(allowed) if allowed is not None else "log_phi_0, log_phi_1, ..."
            raise ValueError(f"--fix: unknown parameter {name!r} for model {key!r}; "
                             f"allowed: {names}")
        if name in out:
            raise ValueError(f"--fix: {name} given twice")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"--fix {item!r}: {value!r} is not a number") from None
        if not np.isfinite(v):
            raise ValueError(f"--fix {item!r}: not a finite number")
        out[name] = v
    return out
