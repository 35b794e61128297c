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

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.checks import check_number

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
