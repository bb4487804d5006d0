"""``glaciar export``: the selection function in other codes' layouts.

``--format jollof``: the two completeness files of ``jollof`` (the JADES UV
luminosity-function code), which reads each with ``astropy.io.fits.getdata(path,
EXTNAME)`` and interpolates bilinearly (``scipy.interpolate.RegularGridInterpolator``
on the axis vectors, 0 outside them):

``detection_completeness.fits``
    ``MAB`` (binary table, one float64 column ``MAB``: apparent AB magnitude in the
    detection band), ``LOGRHALF`` (column ``LOGRHALF``: log10 of the half-light radius
    [arcsec]) and the image ``DET_COMP``, numpy shape (n_MAB, n_LOGRHALF):
    ``DET_COMP[i, j] = C(MAB_i | r_half = 10**LOGRHALF_j)``, the posterior median of the
    survey-averaged completeness averaged uniformly over the simulated redshift nodes
    ``ZNODES`` (jollof's detection completeness has no z axis; header ``DCZSPRD`` is the
    largest spread of C over those z at any node, what the average hides).  Needs a fit
    with the size covariate (``glaciar fit --covariates r_eff``).
``selection_completeness.fits``
    ``MUV`` (column ``MUV``: absolute UV magnitude at 1600 A), ``Z`` (column ``z``) and
    ``SEL_COMP``, numpy shape (n_z, n_MUV): the posterior median of
    S = P(selected | recovered, z, m) at m = M_UV + K(z, beta), averaged over the
    injected beta ~ N(BETAMEAN, BETASD) (Gauss-Hermite nodes, as ``VEFF_MUV``), 0 where
    the detection band receives no flux.  jollof multiplies it by DET_COMP.  Beyond the
    simulated magnitude range S is the fitted form's extrapolation (there C is ~0 for
    a grid that reaches the detection limit; jollof clips MAB to the DET_COMP axis).

Both grids are the file's simulated box (magnitude step 0.1, 25 radii over the
injected size range, z step 0.05, the M_UV grid of ``VEFF_MUV``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..inference.products import beta_nodes, kcorrection
from ..inference.selection_function import SelectionFunction
from ..rundir import atomic_write_bytes

__all__ = ["EXPORT_FORMATS", "export", "export_jollof", "jollof_grids", "JOLLOF_FILES"]

EXPORT_FORMATS = ("jollof",)
#: File names jollof's example driver (jof.py) is pointed at.
JOLLOF_FILES = ("detection_completeness.fits", "selection_completeness.fits")
#: Radii on the LOGRHALF axis.
N_RHALF = 25
#: Gauss-Hermite nodes of the beta average of SEL_COMP.
N_BETA = 5


def _selection_file(source) -> Path:
    p = Path(source)
    if p.is_dir():
        p = p / "selection_function.fits"
    if not p.exists():
        raise FileNotFoundError(f"{source}: no selection-function file (run `glaciar fit` first)")
    return p


def jollof_grids(sf: SelectionFunction) -> dict:
    """The export's axes: ``mab``, ``logrhalf``, ``z_det`` (DET_COMP's z average), ``z``, ``muv``."""
    lo, hi = sf.domain["mag"]
    n_m = int(np.floor((hi - lo) / 0.1 + 1e-9)) + 1
    mab = np.linspace(lo, lo + 0.1 * (n_m - 1), n_m) if n_m > 1 else np.array([lo])
    zlo, zhi = sf.domain["z"]
    n_z = max(2, int(round((zhi - zlo) / 0.05)) + 1) if zhi > zlo else 1
    z = np.linspace(zlo, zhi, n_z)
    z_det = np.asarray(sf.z_grid, float) if sf.z_grid is not None else z
    out = {"mab": mab, "z_det": z_det, "z": z, "muv": sf.muv_grid(0.1)}
    if "r_eff" in sf.covariates:
        clo, chi = sf.covariates["r_eff"].covered
        out["logrhalf"] = np.linspace(clo, chi, N_RHALF)
    return out


def _axis_hdu(name, column, values):
    from astropy.io import fits
    from astropy.table import Table

    h = fits.table_to_hdu(Table({column: np.asarray(values, float)}))
    h.name = name
    return h


def det_comp(sf: SelectionFunction, mab, logrhalf, z_det):
    """DET_COMP (n_m, n_r) and the largest spread of C over ``z_det`` at any node."""
    M, Z = np.meshgrid(mab, z_det, indexing="ij")
    img = np.empty((len(mab), len(logrhalf)))
    spread = 0.0
    for j, x in enumerate(logrhalf):
        c = sf.completeness(M, Z, r_eff_arcsec=10.0 ** x, draws=True)       # (D, n_m, n_z)
        img[:, j] = np.median(np.mean(c, axis=2), axis=0)
        med = np.median(c, axis=0)
        spread = max(spread, float(np.max(np.ptp(med, axis=1))))
    return img, spread


def sel_comp(sf: SelectionFunction, z, muv):
    """SEL_COMP (n_z, n_M): S at m = M_UV + K(z, beta), averaged over the injected beta."""
    sed = sf.sed
    if sed is None:
        raise ValueError("export --format jollof: the file records no injection spectra (DETFILT); "
                         "refit the run with this glaciar")
    bn, bw = beta_nodes(sed.beta_mean, sed.beta_sd, N_BETA)
    k = kcorrection(z, bn, sed.detection_filter, igm=sed.igm, cosmology=sed.cosmology)  # (n_z, n_b)
    acc = 0.0
    for b, wb in enumerate(bw):
        kb = k[:, b]
        flux = np.isfinite(kb)
        m = np.asarray(muv, float)[None, :] + np.where(flux, kb, 0.0)[:, None]
        s = sf.selection_given_recovered(np.broadcast_to(z[:, None], m.shape), m, draws=True,
                                         outside="extrapolate")
        s = np.where(flux[None, :, None], np.nan_to_num(s, nan=0.0), 0.0)
        acc = acc + wb * s
    return np.median(acc, axis=0)


def export_jollof(source, out_dir, *, field: str | None = None) -> list[Path]:
    """Write jollof's ``detection_completeness.fits`` and ``selection_completeness.fits``.

    Parameters
    ----------
    source : path-like
        A run directory (its ``selection_function.fits``) or a selection-function file.
    out_dir : path-like
        Directory to write into (created).
    field : str, optional
        Which fit of a per-field file.

    Returns
    -------
    list of pathlib.Path
        The two files written.

    Raises
    ------
    ValueError
        A fit in absolute magnitudes, or without the size covariate.
    """
    from astropy.io import fits

    path = _selection_file(source)
    sf = SelectionFunction.read(path, field)
    if sf.magnitude_type != "apparent":
        raise ValueError(f"{path}: export --format jollof needs a fit in apparent magnitudes "
                         "(DET_COMP is a function of the detection band's AB magnitude)")
    if "r_eff" not in sf.covariates:
        raise ValueError(f"{path}: DET_COMP(m, log r_half) needs a fit with the size covariate; "
                         f"run `glaciar fit RUN_DIR --covariates r_eff`")
    g = jollof_grids(sf)
    img, spread = det_comp(sf, g["mab"], g["logrhalf"], g["z_det"])
    d = fits.ImageHDU(img, name="DET_COMP")
    d.header["QUANTITY"] = "detection completeness C(MAB, LOGRHALF), posterior median"
    d.header["ZNODES"] = (len(g["z_det"]), "C averaged uniformly over these simulated z")
    d.header["ZMIN"], d.header["ZMAX"] = float(g["z_det"][0]), float(g["z_det"][-1])
    d.header["DCZSPRD"] = (spread, "largest spread of C over those z at a node")
    det = fits.HDUList([_primary(path, sf), _axis_hdu("MAB", "MAB", g["mab"]),
                        _axis_hdu("LOGRHALF", "LOGRHALF", g["logrhalf"]), d])
    s = fits.ImageHDU(sel_comp(sf, g["z"], g["muv"]), name="SEL_COMP")
    s.header["QUANTITY"] = "selection given detection S(z, M_UV), posterior median, beta-averaged"
    s.header["BETAMEAN"], s.header["BETASD"] = float(sf.sed.beta_mean), float(sf.sed.beta_sd)
    sel = fits.HDUList([_primary(path, sf), _axis_hdu("MUV", "MUV", g["muv"]),
                        _axis_hdu("Z", "z", g["z"]), s])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, hdul in zip(JOLLOF_FILES, (det, sel)):
        import io

        buf = io.BytesIO()
        hdul.writeto(buf)
        atomic_write_bytes(out / name, buf.getvalue())
        written.append(out / name)
    return written


def _primary(path, sf):
    from astropy.io import fits

    from ..version import __version__

    p = fits.PrimaryHDU()
    p.header["ORIGIN"] = "glaciar export --format jollof"
    p.header["GLACVER"] = __version__
    p.header["SFFILE"] = str(Path(path).name)
    p.header["FIELD"] = sf.field
    return p


def export(source, out_dir, *, fmt: str = "jollof", field: str | None = None) -> list[Path]:
    """``glaciar export``: dispatch on ``fmt`` (:data:`EXPORT_FORMATS`)."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"--format {fmt!r}: expected one of {EXPORT_FORMATS}")
    return export_jollof(source, out_dir, field=field)
