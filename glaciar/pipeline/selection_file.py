"""What ``glaciar fit`` adds to the selection-function file for luminosity-function codes.

The injections' spectra (:func:`injection_sed`, from the run's manifest), V_eff(M_UV)
and the photometric transfer matrices (:func:`add_lf_products`, from the run's store):
the run-directory side of the file.  The file's layout itself is encoded and decoded by
:mod:`glaciar.inference.selection_format` (``SelectionFunction.to_bytes``,
``from_bytes``, ``read``, ``write``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import constants as C
from ..galaxy.filters import get_filter
from ..galaxy.population import get_cosmology
from ..inference.lensed import LensNodes
from ..inference.products import InjectionSED, VeffTable
from ..inference.selection_function import SelectionFunction
from ..counting import COUNT_K_REC, COUNT_K_SEL, COUNT_N, HIST_MIN_KEY, HIST_MOBS_BIN
from ..store import read_current_histograms
from ..tables import transfer_from_histograms, transfer_matrix
from .inputs import read_columns

__all__ = ["add_lf_products", "injection_sed", "lens_nodes_from_manifest"]

#: V_eff(M_UV) in the file: M_UV step [mag], posterior draws, Simpson nodes in z and
#: Gauss-Hermite nodes in beta (within 6.5e-4 of 401 z and 9 beta nodes, every draw and M_UV
#: above 1e-3 of the peak, on a depth-aware demo fit).
VEFF_MUV_STEP = 0.1
VEFF_MUV_DRAWS = 200
VEFF_MUV_NZ = 101
VEFF_MUV_NBETA = 5
VEFF_MUV_INTERVAL = 0.68
def injection_sed(run_dir, manifest: dict) -> InjectionSED | None:
    """The injections' spectra of a run: detection filter, beta distribution, IGM, cosmology.

    From the manifest's ``store_settings`` (the resolved configuration); a detection
    filter given as a file is read from the run's ``config.yaml``.  None when the
    manifest does not record them (a run made before they were stored).
    """
    st = manifest.get("store_settings") or {}
    src = st.get("source") or {}
    det = manifest.get("detection_band")
    band = ((st.get("survey") or {}).get("bands") or {}).get(det) or {}
    spec = band.get("filter")
    if not (src and det and spec) or any(k not in src for k in ("beta_mean", "beta_sd", "igm")):
        return None
    if spec == "<file>":
        import yaml

        cfg_path = Path(run_dir) / C.RUN_CONFIG_NAME
        try:
            spec = yaml.safe_load(cfg_path.read_text())["survey"]["bands"][det]["filter"]
        except (OSError, KeyError, TypeError) as exc:
            raise ValueError(f"{cfg_path}: cannot read the detection band's filter file "
                             f"({exc})") from exc
        p = Path(spec)
        spec = p if p.is_absolute() else Path(run_dir) / p
    return InjectionSED(get_filter(spec), float(src["beta_mean"]), float(src["beta_sd"]),
                        str(src["igm"]), str(src.get("cosmology", "Planck18")))


def lens_nodes_from_manifest(manifest: dict) -> dict:
    """``{field: {model: LensNodes}}`` of a run's lensed fields (manifest ``lens`` and
    ``lens_nodes``, written at set-up); empty for an unlensed run."""
    lens = manifest.get("lens") or {}
    out = {}
    for field, per in sorted((manifest.get("lens_nodes") or {}).items()):
        out[field] = {name: LensNodes.from_dict(field, name, lens["z_lens"], nodes)
                      for name, nodes in per.items()}
    return out


def add_lf_products(run_dir, manifest: dict, fits_list: list[SelectionFunction], *,
                    cosmology=None, seed=0) -> None:
    """Attach the injections' SED, V_eff(M_UV) and the transfer matrices to each fit.

    The transfer matrices come from the per-task histograms of the measured
    magnitude stored in the footers (:func:`glaciar.store.read_current_histograms`,
    no row read) when every task has them, else from the per-source rows
    (:func:`glaciar.pipeline.inputs.read_columns`: input and measured
    detection-band magnitudes and the flags); fits named by a field use that
    field's sources, the pooled fit ("all") every listed field's.  V_eff(M_UV)
    is left out (with the reason in ``fit_info["veffmuv"]``) when the fit has
    no area or no redshift range; the transfer matrices when the store has no
    measured magnitude.

    Parameters
    ----------
    run_dir : path-like
    manifest : dict
    fits_list : list of SelectionFunction
        Modified in place (``sed``, ``veff_muv``, ``transfer_matrix``).
    cosmology : astropy Cosmology, optional
        Default: the injections'.
    seed : int
        Seed of the transfer matrices' draws (fit i uses ``[seed, i]``).
    """
    import warnings

    sed = injection_sed(run_dir, manifest)
    det = manifest.get("detection_band")
    obs_col = C.band_column(C.OBS_MAG_QUANTITY, det) if det else None
    transfer = _transfer_source(run_dir, obs_col)
    listed = [str(f) for f in (manifest.get("fields") or [])]
    lens = lens_nodes_from_manifest(manifest)
    for i, sf in enumerate(fits_list):
        sf.sed = sed
        sf.lens_nodes = {f: per for f, per in lens.items() if sf.field in ("all", f)} or None
        cosmo = get_cosmology(cosmology if cosmology is not None else
                              (sed.cosmology if sed is not None else None))
        if sed is not None or sf.magnitude_type == "absolute":
            try:
                grid = sf.muv_grid(VEFF_MUV_STEP, cosmology=cosmo)
                if not grid.size:
                    raise ValueError("no M_UV maps inside the simulated magnitude range at every z")
                few = SelectionFunction(sf.model, sf.draws[:VEFF_MUV_DRAWS], meta=sf.meta,
                                        field=sf.field, depth_area=sf.depth_area,
                                        domain=sf.domain, sed=sed)
                few.lens_nodes = sf.lens_nodes
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")     # the fit already warns about z edges
                    vol = few.effective_volume_muv(grid, cosmology=cosmo,
                                                   n_z=VEFF_MUV_NZ, n_beta=VEFF_MUV_NBETA,
                                                   interval=VEFF_MUV_INTERVAL)
                sf.veff_muv = VeffTable(M_uv=grid, volume=vol, interval=VEFF_MUV_INTERVAL,
                                        area_arcmin2=float(few.area_arcmin2() or np.nan),
                                        cosmology=str(getattr(cosmo, "name", cosmo)))
            except ValueError as exc:
                sf.fit_info["veffmuv"] = f"none: {exc}"[:60]
        if transfer is not None:
            keep = ([sf.field] if sf.field != "all" else listed) or None
            tm = transfer(keep, [int(seed), i])
            if tm is not None:
                sf.transfer_matrix = tm


def _transfer_source(run_dir, obs_col):
    """``f(fields or None, seed) -> TransferMatrix or None`` over the store, or None.

    From the stored histograms when every current task has them for
    ``obs_col``; else from the rows (None when they lack the columns).
    """
    if obs_col is None:
        return None
    got = read_current_histograms(run_dir)
    if got is not None and got[1] == obs_col:
        hist = got[0]

        def from_hist(keep, seed):
            h = hist
            if keep and C.COL_FIELD in h.columns:
                h = h[h[C.COL_FIELD].astype(str).isin(keep)]
            if not int(h[COUNT_N].sum()):
                return None
            return transfer_from_histograms(
                h[C.COL_Z].to_numpy(float), h[HIST_MIN_KEY].to_numpy(float),
                h[HIST_MOBS_BIN].to_numpy(), h[COUNT_N].to_numpy(), h[COUNT_K_REC].to_numpy(),
                h[COUNT_K_SEL].to_numpy(), seed=seed)
        return from_hist

    want = [C.COL_FIELD, C.COL_Z, C.COL_MAG_INPUT, C.COL_RECOVERED, C.COL_SELECTED, obs_col]
    df = read_columns(run_dir, want)
    if obs_col not in df.columns or C.COL_MAG_INPUT not in df.columns:
        return None

    def from_rows(keep, seed):
        rows = df
        if keep and C.COL_FIELD in df.columns:
            rows = df[df[C.COL_FIELD].astype(str).isin(keep)]
        if not len(rows):
            return None
        return transfer_matrix(
            rows[C.COL_Z].to_numpy(float), rows[C.COL_MAG_INPUT].to_numpy(float),
            rows[obs_col].to_numpy(float), rows[C.COL_RECOVERED].to_numpy(bool),
            rows[C.COL_SELECTED].to_numpy(bool), seed=seed)
    return from_rows


