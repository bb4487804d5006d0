"""glaciar: injection-recovery completeness and selection functions for galaxy surveys.

The public API, the functions the ``glaciar`` command calls (imported lazily, so that
``import glaciar`` stays cheap):

- :func:`glaciar.load_config` -- read and check a configuration file;
- :func:`glaciar.simulate` -- run (or resume) the injection-recovery simulation;
- :func:`glaciar.catalog` -- the survey's own candidates, measured with the run's settings;
- :func:`glaciar.fit` -- fit C and S; returns the :class:`SelectionFunction`;
- :mod:`glaciar.report` -- ``write_summary_files`` and ``write_html_report`` of a run;
- :func:`glaciar.lf` -- the UV luminosity function of a catalogue through a run's selection
  function (``glaciar.lf`` is also the package of LF models and likelihoods);
- :class:`glaciar.SelectionFunction` -- read an exported selection-function file;
- :func:`glaciar.sersic_stamp` -- render a pixel-integrated Sersic stamp;
- :func:`glaciar.demo.build_demo_survey` -- write the built-in demo survey.
"""
from __future__ import annotations

from .version import __version__

__all__ = ["load_config", "simulate", "catalog", "fit", "lf", "sersic_stamp", "SelectionFunction",
           "__version__"]


def load_config(path, *, check_inputs: bool = True):
    """Read a configuration file (YAML, or GLACiAR's ``parameters.yaml``).

    Parameters
    ----------
    path : str or path-like
    check_inputs : bool
        Also check that every input file exists (all missing ones are listed).

    Returns
    -------
    glaciar.config.Config
        Typed, validated settings; ``.warnings`` lists what was mapped or adjusted
        (a GLACiAR file's keys), also issued as Python warnings.

    Raises
    ------
    glaciar.config.ConfigError
        A bad key or value: the message names the file and key path.
    FileNotFoundError
        Missing input files.
    """
    import warnings

    from .config import check_files
    from .config import load_config as _load

    cfg = _load(path)
    if check_inputs:
        check_files(cfg)
    for w in getattr(cfg, "warnings", ()) or ():
        warnings.warn(str(w), stacklevel=2)
    return cfg


def _config(config):
    from pathlib import Path

    from .config.models import Config

    if isinstance(config, Config):
        return config
    if isinstance(config, (str, Path)):
        return load_config(config)
    raise TypeError(f"expected a Config or a configuration path, got {type(config).__name__}")


def simulate(config, out, *, workers: int = 1, seed: int | None = None, progress: bool = False,
             executor=None, mode: str = "windowed", shard: tuple[int, int] | None = None) -> dict:
    """Run (or resume) the injection-recovery simulation into the run directory ``out``.

    Parameters
    ----------
    config : Config or str or path-like
    out : str or path-like
        Run directory (created; an existing one of the same settings is resumed or grown).
    workers : int
        Worker processes.
    seed : int, optional
        Overrides ``simulation.seed``.
    progress : bool
        Progress bar.
    executor : concurrent.futures.Executor, optional
        E.g. a Dask client's executor, instead of a process pool.
    mode : {"windowed", "full"}
    shard : (int, int), optional
        ``(k, n)``: run shard k of n of the tasks, beside the other shards' processes
        into the same ``out`` (docs/scale-out.md).

    Returns
    -------
    dict
        Run statistics (tasks run, sources, wall and CPU seconds).
    """
    from .execute import simulate as _simulate

    return _simulate(_config(config), out, workers=workers, seed=seed, executor=executor,
                     progress=progress, mode=mode, shard=shard)


def catalog(source, out=None, *, regions: bool = False, progress: bool = False):
    """The survey's own detections, measured and selected as the injections are.

    ``source`` is a configuration (path or Config) or a run directory (then the run's
    settings and, where still on disk, its field caches; written to
    ``RUN/catalog.parquet`` unless ``out`` says otherwise).  See
    :func:`glaciar.pipeline.catalog.run_catalog`.

    Returns
    -------
    pandas.DataFrame
        One row per detection: ``field``, ``id``, ``x``, ``y``, ``ra``, ``dec``, every
        band's fluxes, errors, magnitudes (``mag_auto_<band>`` is the total magnitude),
        S/N and ``maglim``, ``source_flags``, ``recovered`` and ``selected``.
    """
    from .pipeline.catalog import run_catalog

    return run_catalog(source, out, regions=regions, progress=progress)


def fit(run_dir, *, seed=0, n_walkers=None, max_steps=None, progress=False, **kwargs):
    """Fit C(m, z) and S(z, m) of a run; write ``RUN/selection_function.fits`` and return it.

    ``seed``, ``n_walkers``, ``max_steps`` and ``progress`` are the sampler's settings
    (:class:`glaciar.inference.sampling.SamplerSettings`); the other keyword arguments
    are those of :func:`glaciar.pipeline.run_fit` (``model``, ``per_field``,
    ``cosmology``, ``area_arcmin2``, ``max_draws``, ``plots``, ``depth``).

    Returns
    -------
    SelectionFunction
        The survey's (pooled) fit as written to the file.
    """
    from .inference.sampling import SamplerSettings
    from .inference.selection_function import SelectionFunction
    from .pipeline import run_fit

    sampler = SamplerSettings(n_walkers=n_walkers, max_steps=max_steps, seed=seed,
                              progress=progress)
    path = run_fit(run_dir, sampler=sampler, **kwargs)
    return SelectionFunction.read(path) if not kwargs.get("per_field") else \
        SelectionFunction.read_all(path)


def __getattr__(name):
    if name == "sersic_stamp":
        from .galaxy.sersic import sersic_stamp
        return sersic_stamp
    if name == "SelectionFunction":
        from .inference.selection_function import SelectionFunction
        return SelectionFunction
    if name in ("lf", "demo", "report"):
        import importlib
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'glaciar' has no attribute {name!r}")
