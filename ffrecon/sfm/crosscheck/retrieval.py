"""Loop candidates without a model or a downloaded vocabulary: frames that look alike, by VLAD over their SIFT.

Sequential matching pairs each video frame with the next few (and those 2^k ahead), so a path that comes
back to where it began is never matched across the revisit, and the drift along the loop stays. COLMAP's
answer, vocabulary-tree retrieval, needs a tree file downloaded; here each frame's SIFT descriptors (already
in the database after extraction) are aggregated into one VLAD vector (Jegou et al., CVPR 2010: residuals
to the nearest of ``words`` centres, summed per centre, power- and L2-normalised) over a codebook learnt by
k-means (OpenCV's) on this capture's own descriptors, as RootSIFT (Arandjelovic and Zisserman, 2012).
Each frame is then matched with its most similar frames at least ``min_gap`` apart in capture order; COLMAP
verifies every such pair as any other. Written here because no maintained library among the dependencies
aggregates local descriptors (faiss and pyDBoW3 would be new, heavy dependencies for twenty lines).
"""

from __future__ import annotations

import json
import logging
import os
import struct
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.checks import GB, check_number, check_option_file, read_option_bytes
from ffrecon.errors import InputError

logger = logging.getLogger("ffrecon.sfm")


@dataclass(frozen=True, kw_only=True)
class RetrievalOptions:
    enabled: bool = True  # sequential pairing without a vocabulary tree adds these loop candidates
    words: int = 64  # VLAD codebook size
    codebook_samples: int = 200  # descriptors per image sampled to learn the codebook
    max_descriptors: int = 2000  # per image aggregated (COLMAP stores the strongest first)
    pairs_per_image: int = 3  # most similar frames matched per frame ...
    min_gap: int = 30  # ... at least this many frames apart in capture order (nearer ones are sequential's)
    min_similarity: float = 0.2  # cosine similarity of VLAD vectors below which a pair is not a candidate
    kmeans_iterations: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("words", "codebook_samples", "max_descriptors", "min_gap", "kmeans_iterations"):
            check_number(f"RetrievalOptions.{name}", getattr(self, name), low=1, integer=True)
        check_number("RetrievalOptions.pairs_per_image", self.pairs_per_image, low=0, integer=True)
        check_number("RetrievalOptions.min_similarity", self.min_similarity, low=0, high=1)


def _root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT: L1-normalise, square root (so that Euclidean distance compares as the Hellinger kernel)."""
    d = descriptors.astype(np.float32)
    return np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))


def _descriptors(db: pycolmap.Database, image_id: int, limit: int) -> np.ndarray:
    return _root_sift(np.asarray(db.read_descriptors(image_id).data)[:limit])


def _codebook(per_image: list[np.ndarray], options: RetrievalOptions) -> np.ndarray:
    """``[K, 128]`` k-means centres of a sample of the capture's descriptors (bounded iterations)."""
    rng = np.random.default_rng(options.seed)
    sample = [d[rng.choice(len(d), min(len(d), options.codebook_samples), replace=False)] for d in per_image if len(d)]
    data = np.concatenate(sample).astype(np.float32)
    k = min(options.words, len(data))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, options.kmeans_iterations, 1e-4)
    cv2.setRNGSeed(options.seed)
    _, _, centres = cv2.kmeans(data, k, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    return centres


def vlad(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """``[K * 128]`` VLAD vector of one image's descriptors (zeros for an image without any).

    >>> v = vlad(np.eye(2, 128, dtype=np.float32), np.zeros((3, 128), np.float32))
    >>> v.shape, round(float(np.linalg.norm(v)), 6)
    ((384,), 1.0)
    """
    out = np.zeros_like(centres)
    if len(descriptors):
        d2 = (descriptors**2).sum(1)[:, None] - 2 * descriptors @ centres.T + (centres**2).sum(1)[None]
        nearest = np.argmin(d2, axis=1)
        np.add.at(out, nearest, descriptors - centres[nearest])
    out = np.sign(out) * np.sqrt(np.abs(out))  # power normalisation (bursty features)
    norm = np.linalg.norm(out)
    return (out / norm if norm > 0 else out).ravel()


def global_descriptors(db_path: Path, names: Sequence[str], options: RetrievalOptions) -> np.ndarray:
    """``[N, K * 128]`` L2-normalised VLAD vectors of ``names`` from the database's SIFT descriptors."""
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        per_image = [
            _descriptors(db, ids[n], options.max_descriptors) if n in ids else np.zeros((0, 128), np.float32)
            for n in names
        ]
    finally:
        db.close()
    if sum(len(d) for d in per_image) < options.words:
        return np.zeros((len(names), options.words * 128), np.float32)
    centres = _codebook(per_image, options)
    return np.stack([vlad(d, centres) for d in per_image])


def loop_candidates(vectors: np.ndarray, options: RetrievalOptions) -> np.ndarray:
    """``[P, 2]`` pairs i < j: each frame's ``pairs_per_image`` most similar frames at least ``min_gap`` apart.

    >>> v = np.eye(4)[[0, 1, 2, 0, 3]]  # frame 3 looks like frame 0
    >>> loop_candidates(v, RetrievalOptions(min_gap=2, pairs_per_image=1)).tolist()
    [[0, 3]]
    """
    n = len(vectors)
    similarity = vectors @ vectors.T
    index = np.arange(n)
    similarity[np.abs(index[:, None] - index[None, :]) < options.min_gap] = -np.inf
    chosen = set()
    for i in range(n):
        for j in np.argsort(-similarity[i], kind="stable")[: options.pairs_per_image]:
            if similarity[i, j] >= options.min_similarity:
                chosen.add((min(i, int(j)), max(i, int(j))))
    return np.array(sorted(chosen), dtype=int).reshape(-1, 2)


def retrieval_pairs(db_path: Path, names: Sequence[str], options: RetrievalOptions) -> list[tuple[str, str]]:
    """Loop candidates by name (empty when ``options.enabled`` is off or the capture is shorter than the gap)."""
    if not options.enabled or options.pairs_per_image == 0 or len(names) <= options.min_gap:
        return []
    pairs = loop_candidates(global_descriptors(db_path, names, options), options)
    logger.info("retrieval (VLAD over SIFT): %d loop candidate pairs among %d frames", len(pairs), len(names))
    return [(names[i], names[j]) for i, j in pairs]


# --- COLMAP's vocabulary tree file (--vocab-tree) ----------------------------------------------------------------
# COLMAP reads it in its matching threads, where a failed check aborts the process (SIGABRT, a C++ stack dump),
# so a tree is checked first: its header here, then a full read by pycolmap in a child process, once per file.

VOCAB_TREE_LIMIT_BYTES = 8 * GB  # COLMAP's largest published tree (1M words) is a few hundred MB
VOCAB_TREE_PROBE_SECONDS = 120.0  # reading the 1M-word tree takes seconds
VOCAB_TREE_FIX = (
    "pass a faiss-format COLMAP vocabulary tree (COLMAP's releases publish vocab_tree_faiss_flickr100K_words32K.bin; "
    "trees made before May 2025 are FLANN-format and no longer read), build one with `colmap vocab_tree_builder`, "
    "or drop --vocab-tree"
)
_HEADER = struct.Struct("<iii")  # file version (1 or 2), descriptor dimension, embedding dimension (then faiss)
_PROBE = "import sys, pycolmap; pycolmap.VisualIndex.read(sys.argv[1])"


def check_vocab_tree(path: Path, *, cache_dir: Path | None = None) -> Path:
    """``path`` when COLMAP can read it as a vocabulary tree; else an :class:`InputError` (exit 2) saying why.

    The header (version 1 or 2, then SIFT's 128-dimensional descriptors with 64-bit embeddings, or 32/16) is read
    here; a FLANN-format tree (before May 2025) begins with its word count instead. Then pycolmap reads the
    whole tree in a child process (bounded by :data:`VOCAB_TREE_PROBE_SECONDS`), so a corrupt tree ends the
    child, not the run. A tree that passed is remembered in ``cache_dir`` (default ``$FFRECON_CACHE``, else
    ``~/.cache/ffrecon``) by path, inode, size, modification and change time, so it is read once per file.
    """
    path = check_option_file("--vocab-tree", Path(path), limit_bytes=VOCAB_TREE_LIMIT_BYTES, fix=VOCAB_TREE_FIX)
    with open(path, "rb") as file:  # a regular file (checked above): the header only
        head = file.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise InputError(f"--vocab-tree {path} is {len(head)} bytes, too short for a vocabulary tree", VOCAB_TREE_FIX)
    version, desc_dim, embedding_dim = _HEADER.unpack(head)
    if version not in (1, 2):
        # a FLANN tree begins with its word count as a 64-bit integer: e.g. 32768, then 0
        legacy = version > 2 and desc_dim == 0
        what = (
            "a FLANN-format tree (made before COLMAP switched to faiss in May 2025)"
            if legacy
            else "not a vocabulary tree"
        )
        raise InputError(f"--vocab-tree {path} is {what}: it begins {head[:8].hex(' ')}", VOCAB_TREE_FIX)
    if (desc_dim, embedding_dim) not in ((128, 64), (32, 16)):
        raise InputError(
            f"--vocab-tree {path}: descriptors of {desc_dim} and embeddings of {embedding_dim} dimensions; COLMAP "
            "reads 128/64 (SIFT) and 32/16",
            VOCAB_TREE_FIX,
        )
    _probe_once(path, cache_dir)
    return path


def _probe_once(path: Path, cache_dir: Path | None) -> None:
    cache_dir = cache_dir or Path(os.environ.get("FFRECON_CACHE", Path.home() / ".cache" / "ffrecon"))
    info = os.stat(path)
    stamp = json.dumps(
        [os.path.abspath(path), info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns, info.st_ctime_ns]
    )
    memo = Path(cache_dir) / "vocab_trees_read.json"
    try:
        known = json.loads(read_option_bytes("cache", memo, limit_bytes=GB, fix="")) if memo.is_file() else []
    except (InputError, ValueError):
        known = []
    known = known if isinstance(known, list) else []
    if stamp in known:
        return
    _probe(path)
    try:
        memo.parent.mkdir(parents=True, exist_ok=True)
        memo.write_text(json.dumps([*known[-99:], stamp]))
    except OSError as err:  # costs a second read next time, nothing else
        logger.info("cannot remember that %s was read (%s)", path, err)


def _probe(path: Path) -> None:
    """pycolmap reads the tree in a child process: an :class:`InputError` with its last words if it fails."""
    command = [sys.executable, "-c", _PROBE, str(path)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=VOCAB_TREE_PROBE_SECONDS, check=False)
    except subprocess.TimeoutExpired:
        raise InputError(
            f"--vocab-tree {path}: pycolmap did not finish reading it in {VOCAB_TREE_PROBE_SECONDS:g} s", VOCAB_TREE_FIX
        ) from None
    if done.returncode != 0:
        said = [line.strip() for line in done.stderr.splitlines() if "Check failed" in line or "Error" in line]
        why = said[-1][:300] if said else f"exit code {done.returncode}"
        raise InputError(f"--vocab-tree {path} is not a vocabulary tree COLMAP can read ({why})", VOCAB_TREE_FIX)
