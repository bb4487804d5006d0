"""``glaciar catalog``: the survey's own candidates, measured with the run's settings.

The edge around :func:`glaciar.engine.catalog.measure_catalog`: read a configuration or a
run directory, measure each field once (or map the run's field cache: one measurement
serves the catalogue and the selection function), add sky coordinates, write Parquet /
ECSV / FITS with the identity of the settings and inputs in the file's metadata, and
optionally a DS9 region file of the candidates.

Identity: a catalogue describes the same selection as a run's selection function when
both come from the same measurement settings (the run's ``store_hash``: everything that
fixes a row) and the same input files (their BLAKE2b fingerprints).  Both are written
into the catalogue (:func:`catalog_identity`) and checked by :func:`check_identity`
(``glaciar lf`` refuses a catalogue of another configuration).
"""
from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np
import pandas as pd

from ..version import __version__
from .. import constants as C

__all__ = ["run_catalog", "write_catalog", "read_catalog", "catalog_identity", "check_identity",
           "CATALOG_NAME", "CATALOG_FORMATS", "META_PREFIX"]

#: Default file name of a run's catalogue (``RUN_DIR/catalog.parquet``).
CATALOG_NAME = "catalog.parquet"
#: File formats by extension.
CATALOG_FORMATS = {".parquet": "parquet", ".ecsv": "ascii.ecsv", ".fits": "fits"}
#: Prefix of glaciar's keys in the Parquet schema metadata (ECSV/FITS: plain keys in ``meta``).
META_PREFIX = "glaciar."
#: Metadata keys that make up the identity (:func:`check_identity`).
IDENTITY_KEYS = ("store_hash", "inputs_digest", "fields", "detection_band")


def _inputs_digest(inputs: dict) -> str:
    """SHA-256 of the fingerprints (BLAKE2b) of every input file the measurement read (images,
    noise maps, PSFs, filter curves, detection files; :func:`glaciar.inputs.input_files`)."""
    items = {k: v.get("blake2b") for k, v in sorted(inputs.items())}
    return hashlib.sha256(json.dumps(items, sort_keys=True).encode("utf-8")).hexdigest()


def catalog_identity(store_hash: str, inputs: dict, fields, detection_band: str) -> dict:
    """The identity keys a catalogue carries (and a run must match)."""
    return {"store_hash": str(store_hash), "inputs_digest": _inputs_digest(inputs),
            "fields": [str(f) for f in fields], "detection_band": str(detection_band)}


def check_identity(meta: dict, manifest: dict, catalog_path, run_dir) -> None:
    """Raise ValueError (one line) unless the catalogue was measured as the run was.

    Parameters
    ----------
    meta : dict
        The catalogue's metadata (:func:`read_catalog`).
    manifest : dict
        The run's ``manifest.json``.
    """
    if "store_hash" not in meta:
        raise ValueError(f"{catalog_path}: no glaciar identity in its metadata (not written by "
                         "`glaciar catalog`?); catalogue the run with `glaciar catalog RUN`")
    want = catalog_identity(manifest.get("store_hash", ""), manifest.get("inputs") or {},
                            manifest.get("fields") or [], manifest.get("detection_band", ""))
    for key in IDENTITY_KEYS:
        got = meta.get(key)
        if got != want[key]:
            what = {"store_hash": "measurement settings", "inputs_digest": "input files",
                    "fields": "fields", "detection_band": "detection band"}[key]
            raise ValueError(f"{catalog_path}: made with other {what} than the run {run_dir} "
                             f"({key} {_short(got)} vs {_short(want[key])}); catalogue the run's "
                             f"own configuration: glaciar catalog {run_dir}")


def _short(v) -> str:
    if isinstance(v, str) and len(v) > 16:
        return v[:12] + "…"
    return json.dumps(v) if not isinstance(v, str) else v


def _sky_coordinates(survey, field: str, band: str, x, y):
    """RA, Dec [deg] of 0-based pixel positions from the band's WCS; NaN without a celestial one."""
    import warnings

    from astropy.wcs import WCS, FITSFixedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            w = WCS(survey.header(field, band), naxis=2)
        except Exception:          # noqa: BLE001  (a header astropy cannot read has no WCS for us)
            w = None
    if w is None or not w.has_celestial or not len(x):
        return np.full(len(x), np.nan), np.full(len(x), np.nan)
    ra, dec = w.all_pix2world(np.asarray(x, float), np.asarray(y, float), 0)
    return np.asarray(ra, float), np.asarray(dec, float)


def _resolve(source):
    """(Config, run directory or None, manifest or None) of a config path, Config or run directory."""
    from ..config import load_config
    from ..config.models import Config
    from ..rundir import read_manifest

    if isinstance(source, Config):
        return source, None, None
    path = Path(source)
    if path.is_dir():
        manifest = read_manifest(path)
        cfg_path = path / C.RUN_CONFIG_NAME
        if manifest is None or not cfg_path.is_file():
            raise FileNotFoundError(f"{path}: not a run directory (no {C.MANIFEST_NAME} and "
                                    f"{C.RUN_CONFIG_NAME}); give a configuration file or a run")
        return load_config(cfg_path), path, manifest
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such configuration file or run directory")
    return load_config(path), None, None


def run_catalog(source, out=None, *, regions: bool = False, progress: bool = False) -> pd.DataFrame:
    """Catalogue the survey's images with exactly the settings its injections get.

    Parameters
    ----------
    source : str, path-like or Config
        A configuration (file or object), or a run directory: then the run's stored
        configuration, and its field caches where they are still on disk (an
        unfinished run's); its input files must be those the run recorded.
    out : str or path-like, optional
        Where to write it: ``.parquet`` (default format), ``.ecsv`` or ``.fits``.
        Default for a run: ``RUN_DIR/catalog.parquet``; for a configuration, nothing
        is written unless given.
    regions : bool
        Also write a DS9 region file of the selected candidates beside ``out``
        (``<out stem>.reg``; image coordinates, one ``# tile`` per field).
    progress : bool
        Print one line per field.

    Returns
    -------
    pandas.DataFrame
        :func:`glaciar.engine.catalog.measure_catalog`'s rows of every field, with
        ``ra`` and ``dec`` [deg] (NaN without a celestial WCS); ``attrs["glaciar"]``
        holds the metadata written to the file.

    Raises
    ------
    FileNotFoundError, ValueError
        A missing or unusable input, a run whose inputs changed, a bad ``out``.
    """
    from ..config.io import config_hash
    from ..config.user_selection import selection_description
    from ..engine import fieldcache
    from ..engine.catalog import measure_catalog
    from ..contexts import context_dir, open_field_context
    from ..fieldprep import build_field_context
    from ..inputs import check_inputs
    from ..manifest import store_hash, store_settings
    from ..survey import Survey

    cfg, run_dir, manifest = _resolve(source)
    if out is None and run_dir is not None:
        out = run_dir / CATALOG_NAME
    if out is not None:
        _check_out(Path(out))
    survey = Survey.from_config(cfg)
    inputs = check_inputs(cfg, survey)
    if manifest is not None:
        recorded = manifest.get("inputs") or {}
        changed = sorted(k for k in recorded if k in inputs
                         and inputs[k].get("blake2b") != recorded[k].get("blake2b"))
        if changed:
            raise ValueError(f"{run_dir}: input file(s) changed since the run: {', '.join(changed)} "
                             f"({inputs[changed[0]]['path']}); its selection function describes "
                             "the old files")
    settings_hash = store_hash(store_settings(cfg))
    if manifest is not None:
        if manifest.get("store_hash") != settings_hash:
            raise ValueError(f"{run_dir}: its stored configuration's settings differ from the "
                             f"manifest's store_hash (edited {C.RUN_CONFIG_NAME}?)")
    chash = config_hash(cfg)
    # The run's seed (a config's own without a run): a probabilistic selection function's
    # draw for the catalogue is derived from it and the field (glaciar.engine.catalog).
    seed = int(manifest["seed"]) if manifest is not None and "seed" in manifest \
        else int(cfg.simulation.seed)
    frames = []
    det = cfg.survey.detection_band
    for field in cfg.survey.fields:
        cached = None if run_dir is None else context_dir(run_dir, chash, field,
                                                           manifest.get("inputs") or {})
        if cached is not None and fieldcache.exists(cached):
            ctx = open_field_context(cfg, survey, field, cached)
            how = "run's field cache"
        else:
            ctx = build_field_context(cfg, survey, field)
            how = "measured"
        frame = measure_catalog(ctx, seed=seed)
        ra, dec = _sky_coordinates(survey, field, det, frame[C.COL_X], frame[C.COL_Y])
        frame.insert(4, "ra", ra)
        frame.insert(5, "dec", dec)
        frames.append(frame)
        if progress:
            print(f"catalog {field}: {len(frame)} detections, {int(frame[C.COL_SELECTED].sum())} "
                  f"selected ({how})")
        del ctx
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    meta = {"glaciar_version": __version__, "config_hash": chash,
            **catalog_identity(settings_hash, manifest.get("inputs") if manifest else inputs,
                               cfg.survey.fields, det),
            "obs_mag_column": C.band_column(C.OBS_MAG_QUANTITY, det),
            "selection": selection_description(cfg.selection),
            **({"selection_seed": seed} if C.COL_P_SELECTED in table.columns else {}),
            "bands": [b.name for b in cfg.survey.bands],
            "zeropoints": {b.name: float(b.zeropoint) for b in cfg.survey.bands},
            "min_sn": float(cfg.classification.min_sn),
            "run_dir": None if run_dir is None else str(Path(run_dir).resolve())}
    table.attrs["glaciar"] = meta
    if out is not None:
        write_catalog(table, out, meta)
        if regions:
            _write_regions(table, Path(out).with_suffix(".reg"))
    return table


def _check_out(out: Path) -> None:
    if out.suffix.lower() not in CATALOG_FORMATS:
        raise ValueError(f"--out {out}: unknown extension {out.suffix!r}; expected one of "
                         f"{', '.join(CATALOG_FORMATS)}")
    if out.is_dir():
        raise FileExistsError(f"--out {out}: is a directory")
    if not out.resolve().parent.is_dir():
        raise FileNotFoundError(f"--out {out}: directory {out.parent} does not exist")


def write_catalog(table: pd.DataFrame, path, meta: dict) -> Path:
    """Write a catalogue atomically; format by extension (:data:`CATALOG_FORMATS`)."""
    from ..rundir import atomic_write_bytes

    path = Path(path)
    _check_out(path)
    fmt = CATALOG_FORMATS[path.suffix.lower()]
    if fmt == "parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        t = pa.Table.from_pandas(table, preserve_index=False)
        md = dict(t.schema.metadata or {})
        md.update({(META_PREFIX + k).encode(): json.dumps(v).encode() for k, v in meta.items()})
        t = t.replace_schema_metadata(md)
        buf = io.BytesIO()
        pq.write_table(t, buf)
        atomic_write_bytes(path, buf.getvalue())
        return path
    from astropy.table import Table

    t = Table.from_pandas(table)
    t[C.COL_FIELD] = np.asarray(table[C.COL_FIELD], dtype=str)
    if fmt == "fits":
        # FITS header cards hold short scalars: the metadata goes in as JSON strings.
        t.meta.update({k.upper()[:8]: json.dumps(v) for k, v in meta.items()
                       if len(json.dumps(v)) <= 68})
        t.meta["GLACIAR"] = "metadata in extension GLACMETA (JSON)"
        from astropy.io import fits

        hdus = fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(t),
                             fits.ImageHDU(np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
                                           name="GLACMETA")])
        buf = io.BytesIO()
        hdus.writeto(buf)
    else:
        t.meta.update(meta)
        buf = io.StringIO()
        t.write(buf, format="ascii.ecsv")
        buf = io.BytesIO(buf.getvalue().encode("utf-8"))
    atomic_write_bytes(path, buf.getvalue())
    return path


def read_catalog(path) -> tuple[pd.DataFrame, dict]:
    """A catalogue and its glaciar metadata (empty dict when it has none).

    Raises
    ------
    FileNotFoundError, ValueError
        Missing file, unknown extension, unreadable file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: catalogue not found")
    fmt = CATALOG_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: unknown catalogue extension {path.suffix!r}; expected one of "
                         f"{', '.join(CATALOG_FORMATS)}")
    try:
        if fmt == "parquet":
            import pyarrow.parquet as pq

            t = pq.read_table(path)
            md = t.schema.metadata or {}
            meta = {k.decode()[len(META_PREFIX):]: json.loads(v) for k, v in md.items()
                    if k.decode().startswith(META_PREFIX)}
            return t.to_pandas(), meta
        from astropy.table import Table

        if fmt == "fits":
            from astropy.io import fits

            with fits.open(path) as hdul:
                meta = json.loads(bytes(hdul["GLACMETA"].data).decode()) if "GLACMETA" in hdul else {}
                t = Table(hdul[1].data)
        else:
            t = Table.read(path, format=fmt)
            meta = {k: v for k, v in t.meta.items()}
        return t.to_pandas(), meta
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{path}: cannot read the catalogue: {exc}") from None


def _write_regions(table: pd.DataFrame, path: Path) -> Path:
    """DS9 regions of the selected candidates (image coordinates, 1-based), one tile per field."""
    from ..rundir import atomic_write_text

    lines = ["# Region file format: DS9 version 4.1", "# glaciar catalog: selected candidates",
             'global color=green width=1 font="helvetica 9 normal"']
    sel = table[table[C.COL_SELECTED].astype(bool)] if len(table) else table
    for field, sub in sel.groupby(C.COL_FIELD, sort=True):
        lines.append(f"# tile {field}")
        lines.append("image")
        for r in sub.itertuples(index=False):
            x, y = getattr(r, C.COL_X) + 1.0, getattr(r, C.COL_Y) + 1.0
            lines.append(f"circle({x:.3f},{y:.3f},6) # text={{{field}:{int(getattr(r, 'id'))}}}")
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def default_out(source) -> Path | None:
    """Where ``glaciar catalog SOURCE`` writes without ``--out``: a run's ``catalog.parquet``,
    or ``<config stem>_catalog.parquet`` beside a configuration file."""
    p = Path(source)
    if p.is_dir():
        return p / CATALOG_NAME
    return p.with_name(p.stem + "_catalog.parquet")


