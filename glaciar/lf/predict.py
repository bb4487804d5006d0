"""What a luminosity function predicts besides its fit: expected counts, and the interlopers'.

:func:`expected_counts` (moved here from :mod:`glaciar.lf.fit`, which re-exports it) and
:func:`interloper_background`, the phi-independent counts :func:`glaciar.lf.fit_lf` adds
to every bin when the selection function holds a contamination (docs/contamination.md).
"""
from __future__ import annotations

import numpy as np

from .models import get_model

__all__ = ["expected_counts", "interloper_background"]


def interloper_background(sfs, m_obs_edges, n_d: int, area=None, interlopers=None):
    """Expected interlopers per m_obs bin for each of ``n_d`` selection draws, (n_d, n_k), or None.

    Summed over the fits (each with its own area, or ``area``), contamination draw
    ``d mod D_c`` paired with selection draw d
    (:meth:`glaciar.SelectionFunction.expected_interlopers`).  None when ``interlopers``
    is False, or None and no fit holds a contamination.

    Raises
    ------
    ValueError
        ``interlopers=True`` and no fit holds a contamination.
    """
    have = [s for s in sfs if getattr(s, "interlopers", None) is not None]
    if interlopers is False or (interlopers is None and not have):
        return None
    if not have:
        raise ValueError("fit_lf: interlopers=True but the selection function holds no "
                         "contamination (the run had no interlopers: section)")
    per = sum(s.expected_interlopers(m_obs_edges, area=area, draws=True) for s in have)
    return per[np.arange(int(n_d)) % len(per)]


def expected_counts(sf, phi, m_obs_edges, *, params=None, **kw):
    """Expected counts per measured-magnitude bin for a luminosity function.

    Parameters
    ----------
    sf : SelectionFunction
    phi : callable or str
        ``phi(M, z)`` [Mpc^-3 mag^-1], or a model name ("schechter", "double_power_law")
        evaluated at ``params``.
    m_obs_edges : array_like
        Measured-magnitude bins [AB mag].
    params : dict, optional
        The model's parameters, by name (with a model name).
    **kw
        :meth:`glaciar.inference.SelectionFunction.expected_counts`'s keywords.

    Returns
    -------
    glaciar.inference.counts.ExpectedCounts
    """
    if isinstance(phi, str):
        mdl = get_model(phi)
        missing = [n for n in mdl.param_names if n not in (params or {})]
        if missing:
            raise ValueError(f"expected_counts: model {mdl.name!r} needs {', '.join(missing)}")
        th = np.array([float(params[n]) for n in mdl.param_names])

        def phi(M, z, th=th, mdl=mdl):
            return mdl.phi(np.asarray(M, float) + 0 * np.asarray(z, float), th)
    return sf.expected_counts(phi, m_obs_edges, **kw)
