"""Study files: arrays packed into a checksummed ``.npz`` written atomically, and digests of pytrees."""

from __future__ import annotations

import contextlib
import hashlib
import os
import zipfile
import zlib
from typing import Any, Sequence

import jax
import numpy as np

from gmjax.montecarlo.accumulate import BlockSums, StudyMoments
from gmjax.montecarlo.runs import RunScores

# ----------------------------------------------------------------------------- files


def _pack(moments: StudyMoments, sums: BlockSums | None, scores: RunScores | None) -> dict[str, np.ndarray]:
    """The arrays of a result or checkpoint file (``moments.*``, ``sums.*`` stacked by node, ``scores.*``)."""
    arrays = {f"moments.{k}": np.asarray(v) for k, v in moments._asdict().items()}
    if sums is not None:
        arrays["sums.block_size"] = np.asarray(sums.block_size, np.int64)
        arrays["sums.n_blocks"] = np.asarray(sums.n_blocks, np.int64)
        arrays["sums.level"] = np.asarray([lv for lv, _, _ in sums.nodes], np.int64)
        arrays["sums.index"] = np.asarray([ix for _, ix, _ in sums.nodes], np.int64)
        for k in StudyMoments._fields:
            arrays[f"sums.{k}"] = np.stack([np.asarray(getattr(m, k)) for _, _, m in sums.nodes])
    if scores is not None:
        arrays.update({f"scores.{k}": np.asarray(v) for k, v in scores._asdict().items() if v is not None})
    return arrays


def _unpack(f: dict[str, np.ndarray]) -> tuple[StudyMoments, BlockSums | None, RunScores | None]:
    moments = StudyMoments(**{k: f[f"moments.{k}"] for k in StudyMoments._fields})
    sums = None
    if "sums.level" in f:
        nodes = tuple(
            (int(lv), int(ix), StudyMoments(**{k: f[f"sums.{k}"][j] for k in StudyMoments._fields}))
            for j, (lv, ix) in enumerate(zip(f["sums.level"], f["sums.index"]))
        )
        sums = BlockSums(int(f["sums.block_size"]), int(f["sums.n_blocks"]), nodes)
    kept: dict[str, Any] = {k[len("scores.") :]: f[k] for k in f if k.startswith("scores.")}
    return moments, sums, (RunScores(**kept) if kept else None)


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 of every array's name, dtype, shape and bytes (in name order; ``checksum`` itself excluded)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == "checksum":
            continue
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _tmp_path(path: str) -> str:
    return f"{path}.tmp-{os.getpid()}.npz"


def _remove_stale_tmp(path: str | os.PathLike) -> None:
    """Remove the temporary files that writes to ``path`` left behind (a write killed half-way)."""
    import glob

    for tmp in glob.glob(glob.escape(os.fspath(path)) + ".tmp-*.npz"):
        with contextlib.suppress(OSError):
            os.remove(tmp)


def _write_npz(path: str | os.PathLike, arrays: dict) -> None:
    """Write ``arrays`` and their checksum atomically: a temporary file, fsync, :func:`os.replace`."""
    path = os.fspath(path)
    arrays = dict(arrays, checksum=np.asarray(_checksum(arrays)))
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            os.remove(tmp)


def _read_npz(path: str | os.PathLike, what: str, required: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Every array of a file written by :func:`_write_npz`, its checksum verified (files written
    before gmjax kept checksums have none: the caller decides whether to accept them).

    Raises:
        ValueError: naming the file and the cause (missing, not an ``.npz``, truncated, checksum
            mismatch, ``required`` arrays missing).
    """
    name = os.fspath(path)
    try:
        with np.load(name, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except FileNotFoundError:
        raise ValueError(f"{what}: {name!r} does not exist") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        cause = "empty" if os.path.exists(name) and os.path.getsize(name) == 0 else "truncated or corrupt"
        raise ValueError(
            f"{what}: {name!r} is {cause} and cannot be read ({type(e).__name__}: {e})"
        ) from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ValueError(f"{what}: {name!r} is not a gmjax Monte Carlo {what} file (no {', '.join(missing)})")
    if "checksum" in arrays and str(arrays["checksum"]) != _checksum(arrays):
        raise ValueError(
            f"{what}: {name!r} is corrupt: its contents do not match the checksum it was written with"
        )
    return arrays


# ----------------------------------------------------------------------------- configuration & checkpoints


def _digest(tree: Any) -> str:
    """sha256 of a pytree's structure and leaf values (shape, dtype, bytes)."""
    h = hashlib.sha256()
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    h.update(str(treedef).encode())
    for leaf in leaves:
        a = np.asarray(leaf)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()
