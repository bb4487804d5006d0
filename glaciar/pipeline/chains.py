"""Saved emcee chains under ``RUN_DIR/fit/``, so that a re-run of ``glaciar fit`` resumes them.

Per fit (``tag``, e.g. ``all_logistic``) and block (``c``, ``s``):
``chain_<tag>_<block>.npy`` and ``log_prob_<tag>_<block>.npy`` (no pickle), and
one ``state_<tag>.json`` with the MAP, the proposal, the accepted counts, the
random state and the key of the data, model, seed and walkers they belong to.
"""
from __future__ import annotations

import hashlib
import io
import json
import warnings
from pathlib import Path

import numpy as np

from ..inference.models import Cells, SurfaceModel
from ..inference.sampling import BlockChain, FitResult

__all__ = ["chains_key", "save_chains", "load_chains", "file_tag"]


def file_tag(name: str) -> str:
    """The file-name part of a fit's name (:func:`glaciar.paths.file_stem`: ordinary names as
    they are, others escaped with a hash, so two fields never share a fit's files)."""
    from ..paths import file_stem

    return file_stem(name)


def chains_key(cells: Cells, model: SurfaceModel, seed, n_walkers) -> str:
    """What saved chains must match to be resumed: the counts, the model, the seed and walkers."""
    h = hashlib.sha256()
    for a in (cells.z, cells.mag, cells.n, cells.k_rec, cells.k_sel):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps([model.to_header_dict(), repr(seed), n_walkers], default=str).encode())
    return h.hexdigest()[:16]


def save_chains(fit_dir, tag: str, res: FitResult, key: str) -> None:
    """Chains as .npy (no pickle) + a JSON with what is needed to resume, each atomically."""
    from ..rundir import atomic_write_bytes, atomic_write_text

    fit_dir = Path(fit_dir)
    state = {"key": key, "theta_map": res.theta_map.tolist(), "blocks": []}
    for b in res.blocks:
        for name, arr in (("chain", b.chain), ("log_prob", b.log_prob)):
            buf = io.BytesIO()
            np.save(buf, arr, allow_pickle=False)
            atomic_write_bytes(fit_dir / f"{name}_{tag}_{b.part}.npy", buf.getvalue())
        rs = b.random_state
        state["blocks"].append({
            "part": b.part, "n_accepted": b.n_accepted.tolist(),
            "laplace_cov": np.asarray(b.laplace_cov).tolist(),
            "proposal_mean": np.asarray(b.proposal_mean).tolist(),
            "random_state": [rs[0], np.asarray(rs[1]).tolist(), int(rs[2]), int(rs[3]), float(rs[4])]})
    atomic_write_text(fit_dir / f"state_{tag}.json", json.dumps(state))


def load_chains(fit_dir, tag: str, model: SurfaceModel, key: str) -> FitResult | None:
    """The saved chains of ``tag`` as a :class:`FitResult` to resume, or None.

    None when nothing is saved or the saved chains belong to other data, model,
    seed or walkers (``key``); a warning and None when the files are unreadable.
    """
    p = Path(fit_dir) / f"state_{tag}.json"
    if not p.exists():
        return None
    try:
        state = json.loads(p.read_text())
        if state.get("key") != key:
            return None
        blocks = []
        for b in state["blocks"]:
            chain = np.load(p.parent / f"chain_{tag}_{b['part']}.npy", allow_pickle=False)
            lp = np.load(p.parent / f"log_prob_{tag}_{b['part']}.npy", allow_pickle=False)
            rs = b["random_state"]
            blocks.append(BlockChain(
                part=b["part"], index=model.block_indices(b["part"]), chain=chain, log_prob=lp,
                n_accepted=np.asarray(b["n_accepted"]), tau=None, burn=0, thin=1, converged=False,
                random_state=(rs[0], np.asarray(rs[1], dtype=np.uint32), rs[2], rs[3], rs[4]),
                laplace_cov=np.asarray(b["laplace_cov"]), proposal_mean=np.asarray(b["proposal_mean"])))
        return FitResult(model=model, theta_map=np.asarray(state["theta_map"]), blocks=blocks)
    except (OSError, ValueError, KeyError) as exc:
        warnings.warn(f"{p}: cannot resume from the saved chains ({exc}); starting afresh")
        return None
