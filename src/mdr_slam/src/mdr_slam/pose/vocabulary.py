"""ORB bag-of-words vocabulary (DBoW2-style) and the KeyFrameDatabase (inverted file).

The vocabulary is a k-ary tree built by hierarchical k-majority clustering of ORB descriptors
(binary k-means: a centroid bit is the majority of its members' bits, as DBoW2 does for ORB);
leaves are words with idf weights. It is trained by the project itself (``mdr vocab``) from
images that exist locally: ray-cast textured rooms (mdr_slam.pose.synthetic), images shipped in
installed packages (matplotlib's sample data) and any user folders; nothing is downloaded. The
default file is src/mdr_slam/data/orb_vocab.npz (k=10, L=4 by default, about 0.4 MB); when it is
missing it is built at first use from the built-in sources and cached there (or under
~/.cache/mdr_slam when the package directory is read-only).

Images are scored with DBoW2's L1 score on tf-idf vectors:
s(v1, v2) = 1 - 0.5 * |v1/|v1| - v2/|v2||_1.
"""
from __future__ import annotations

import os
from typing import Dict, Iterable, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import StereoCamera
from ..io.atomic import atomic_path
from .orb import _POPCOUNT, ORBextractor, hamming
from .synthetic import BoxRoom, orbit_trajectory

__all__ = ["ORBVocabulary", "KeyFrameDatabase", "default_vocabulary_path", "load_vocabulary",
           "builtin_training_images", "bow_score"]


def _k_majority(desc: np.ndarray, k: int, rng: np.random.RandomState, iters: int = 8):
    """k centroids (k, 32) and labels of one node's descriptors (binary k-means, k-majority)."""
    n = len(desc)
    if n <= k:
        cents = np.concatenate([desc, np.repeat(desc[-1:], k - n, axis=0)]) if n else \
            np.zeros((k, 32), np.uint8)
        return cents, np.arange(n)
    bits = np.unpackbits(desc, axis=1).astype(np.float32)
    # k-means++ seeding on Hamming distance
    cents_idx = [rng.randint(n)]
    dmin = _POPCOUNT[np.bitwise_xor(desc, desc[cents_idx[0]])].sum(1).astype(float)
    for _ in range(1, k):
        p = dmin ** 2
        s = p.sum()
        j = rng.randint(n) if s <= 0 else rng.choice(n, p=p / s)
        cents_idx.append(j)
        dmin = np.minimum(dmin, _POPCOUNT[np.bitwise_xor(desc, desc[j])].sum(1))
    cents = desc[cents_idx].copy()
    labels = None
    for _ in range(iters):
        cb = np.unpackbits(cents, axis=1).astype(np.float32)
        D = bits.sum(1)[:, None] + cb.sum(1)[None, :] - 2.0 * bits @ cb.T
        new = np.argmin(D, axis=1)
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        counts = np.bincount(labels, minlength=k).astype(np.float32)
        sums = np.zeros((k, 256), np.float32)
        np.add.at(sums, labels, bits)
        maj = sums > (counts[:, None] / 2.0)
        empty = counts == 0
        cb_new = np.where(empty[:, None], cb > 0.5, maj)
        cents = np.packbits(cb_new.astype(np.uint8), axis=1)
    return cents, labels


class ORBVocabulary:
    """Complete k-ary tree: ``levels[l]`` holds the (k^(l+1), 32) centroids of depth l+1."""

    def __init__(self, k: int, L: int, levels: List[np.ndarray], idf: np.ndarray):
        self.k, self.L = int(k), int(L)
        self.levels = levels
        self.idf = np.asarray(idf, dtype=np.float32)

    @property
    def n_words(self) -> int:
        return self.k ** self.L

    # ------------------------------------------------------------------ training
    @classmethod
    def train(cls, descriptor_sets: List[np.ndarray], k: int = 10, L: int = 4, seed: int = 0,
              max_descriptors: int = 200000) -> "ORBVocabulary":
        """Hierarchical k-majority over all descriptors; each set is one 'document' for idf."""
        rng = np.random.RandomState(seed)
        allds = np.concatenate(descriptor_sets) if descriptor_sets else np.zeros((0, 32), np.uint8)
        if len(allds) < k:
            raise ValueError("need at least %d descriptors to train a vocabulary" % k)
        if len(allds) > max_descriptors:
            allds = allds[rng.choice(len(allds), max_descriptors, replace=False)]
        levels = []
        node = np.zeros(len(allds), dtype=np.int64)      # node index at the current depth
        for lvl in range(L):
            cents = np.zeros((k ** (lvl + 1), 32), np.uint8)
            new_node = np.zeros(len(allds), dtype=np.int64)
            order = np.argsort(node, kind="stable")
            bounds = np.searchsorted(node[order], np.arange(k ** lvl + 1))
            for parent in range(k ** lvl):   # loop over tree nodes (not descriptors)
                members = order[bounds[parent]:bounds[parent + 1]]
                c, lab = _k_majority(allds[members], k, rng)
                cents[parent * k:(parent + 1) * k] = c
                if len(members):
                    new_node[members] = parent * k + lab
            levels.append(cents)
            node = new_node
        voc = cls(k, L, levels, np.ones(k ** L, np.float32))
        # idf over documents: log(N / n_w)
        n_docs = len(descriptor_sets)
        df = np.zeros(voc.n_words, np.float64)
        for d in descriptor_sets:
            if len(d):
                df[np.unique(voc.transform_words(d))] += 1
        voc.idf = np.log(n_docs / np.maximum(df, 1.0)).astype(np.float32)
        voc.idf[df == 0] = np.log(max(n_docs, 1))
        return voc

    # ------------------------------------------------------------------ use
    def transform_words(self, desc: np.ndarray, depth: Optional[int] = None) -> np.ndarray:
        """Word id of each descriptor (descend the tree, vectorized over descriptors); with
        ``depth`` (1 = the root's children) the node at that depth instead (DBoW2's direct index).
        Distances by orb.hamming's word-wise popcount (about 2x a byte lookup table)."""
        n = len(desc)
        node = np.zeros(n, dtype=np.int64)
        if n == 0:
            return node
        depth = self.L if depth is None else max(1, min(int(depth), self.L))
        ar = np.arange(self.k)
        rep = np.repeat(np.ascontiguousarray(desc, dtype=np.uint8), self.k, axis=0)
        rows = np.arange(n)
        for lvl in range(depth):
            cand = node[:, None] * self.k + ar[None, :]
            d = hamming(rep, self.levels[lvl][cand.ravel()]).reshape(n, self.k)
            node = cand[rows, np.argmin(d, axis=1)]
        return node

    def transform(self, desc: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Sparse L1-normalised tf-idf vector: (sorted word ids, weights)."""
        return self.bow_vector(self.transform_words(desc))

    def bow_vector(self, w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """:meth:`transform`'s vector from the descriptors' word ids (``transform_words``)."""
        if len(w) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        words, counts = np.unique(w, return_counts=True)
        val = counts.astype(np.float32) / len(w) * self.idf[words]
        s = val.sum()
        return words, (val / s if s > 0 else val)

    def node_of_words(self, words: np.ndarray, depth: int) -> np.ndarray:
        """The node at ``depth`` (1 = the root's children) above each word: DBoW2's direct index
        (FeatureVector) from the words, as ``transform_words(desc, depth)`` would give it (the tree
        is complete, so a node's children are numbered node * k + 0..k-1)."""
        up = self.L - max(1, min(int(depth), self.L))
        return np.asarray(words) // (self.k ** up)

    def save(self, path: str) -> None:
        with atomic_path(path, ".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, k=self.k, L=self.L, idf=self.idf,
                                    **{"level%d" % i: c for i, c in enumerate(self.levels)})
        try:
            os.chmod(path, 0o644)   # a shared data file, not a private temp file
        except OSError:
            pass

    @classmethod
    def load(cls, path: str) -> "ORBVocabulary":
        z = np.load(path)
        k, L = int(z["k"]), int(z["L"])
        return cls(k, L, [z["level%d" % i] for i in range(L)], z["idf"])


def bow_score(a: Tuple[np.ndarray, np.ndarray], b: Tuple[np.ndarray, np.ndarray]) -> float:
    """DBoW2 L1 score in [0, 1]."""
    _, ia, ib = np.intersect1d(a[0], b[0], assume_unique=True, return_indices=True)
    if len(ia) == 0:
        return 0.0
    va, vb = a[1][ia], b[1][ib]
    return float(0.5 * np.sum(np.abs(va) + np.abs(vb) - np.abs(va - vb)))


# ---------------------------------------------------------------------- training sources
def builtin_training_images(n_synthetic: int = 24, seed: int = 7) -> Iterable[np.ndarray]:
    """Grey images available offline: ray-cast rooms with several textures and poses, and the
    sample images shipped inside matplotlib (if installed)."""
    cam = StereoCamera.from_rectified(640, 480, 420.0, 420.0, 320.0, 240.0, 0.1)
    per_room = 6
    for r in range(max(1, n_synthetic // per_room)):
        room = BoxRoom((3.0 + r, 1.5 + 0.3 * r, 3.0 + 0.5 * r), tex_size=768, seed=seed + r)
        for T in orbit_trajectory(per_room, radius=0.8, arc=2 * np.pi, yaw_offset=0.3 * r):
            yield room.render(T, cam.fx, cam.fy, cam.cx, cam.cy, 640, 480)
    try:
        import matplotlib
        sample = os.path.join(os.path.dirname(matplotlib.__file__), "mpl-data", "sample_data")
        for root, _, files in os.walk(sample):
            for fn in sorted(files):
                if fn.lower().endswith((".png", ".jpg", ".jpeg")):
                    img = cv2.imread(os.path.join(root, fn), cv2.IMREAD_GRAYSCALE)
                    if img is not None and min(img.shape) >= 100:
                        yield img
    except ImportError:
        pass


def image_descriptor_sets(images: Iterable[np.ndarray], n_features: int = 1000) -> List[np.ndarray]:
    ex = ORBextractor(n_features)
    out = []
    for img in images:
        d = ex(img)[3]
        if len(d):
            out.append(d)
    return out


def default_vocabulary_path() -> str:
    """data/orb_vocab.npz of the catkin package: src/mdr_slam/data in the source and devel
    layouts (the package four levels above src/mdr_slam/src/mdr_slam/pose/vocabulary.py), else
    share/mdr_slam/data found through the ROS package path (an install space, where this module
    sits in lib/python3/dist-packages). Without either, the user cache ~/.cache/mdr_slam."""
    here = os.path.dirname(os.path.abspath(__file__))
    pkg = os.path.dirname(os.path.dirname(os.path.dirname(here)))
    if os.path.isfile(os.path.join(pkg, "package.xml")):
        return os.path.join(pkg, "data", "orb_vocab.npz")
    try:
        import rospkg
        return os.path.join(rospkg.RosPack().get_path("mdr_slam"), "data", "orb_vocab.npz")
    except ImportError:
        pass
    except rospkg.ResourceNotFound:  # mdr_slam not on ROS_PACKAGE_PATH (library used without ROS)
        pass
    return os.path.join(os.path.expanduser("~"), ".cache", "mdr_slam", "orb_vocab.npz")


def load_vocabulary(path: Optional[str] = None) -> ORBVocabulary:
    """The given vocabulary, or the packaged one (built from builtin sources and cached when
    missing: takes tens of seconds once)."""
    if path:
        return ORBVocabulary.load(path)
    p = default_vocabulary_path()
    if os.path.exists(p):
        return ORBVocabulary.load(p)
    cache = os.path.join(os.path.expanduser("~"), ".cache", "mdr_slam", "orb_vocab.npz")
    if os.path.exists(cache):
        return ORBVocabulary.load(cache)
    voc = ORBVocabulary.train(image_descriptor_sets(builtin_training_images()))
    for target in (p, cache):
        try:
            os.makedirs(os.path.dirname(target), exist_ok=True)
            voc.save(target)
            break
        except OSError:
            continue
    return voc


class KeyFrameDatabase:
    """Inverted file word -> keyframe ids (ORB-SLAM2 KeyFrameDatabase), held as flat arrays of
    every keyframe's (word, weight) entries, so a query is a few vectorized passes over them
    instead of a Python loop over its words' lists."""

    def __init__(self, voc: ORBVocabulary):
        self.voc = voc
        self.bows: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}
        self._flat = None   # (keyframe ids, entry -> keyframe index, words, weights); None: stale

    def add(self, kf_id: int, bow) -> None:
        self.bows[kf_id] = bow
        self._flat = None

    def erase(self, kf_id: int) -> None:
        if self.bows.pop(kf_id, None) is not None:
            self._flat = None

    def _entries(self):
        if self._flat is None:
            ids = np.fromiter(self.bows, dtype=np.int64, count=len(self.bows))
            bows = list(self.bows.values())
            n = np.array([len(b[0]) for b in bows], dtype=np.int64)
            self._flat = (ids, np.repeat(np.arange(len(ids)), n),
                          np.concatenate([b[0] for b in bows]).astype(np.int64),
                          np.concatenate([b[1] for b in bows]).astype(np.float64))
        return self._flat

    def query(self, bow, exclude=(), min_score: float = 0.0, top: int = 10) -> List[Tuple[int, float]]:
        """Keyframes sharing words with ``bow``: those with >= 80 % of the best common-word count,
        scored with the L1 score, best first (ORB-SLAM2 DetectLoopCandidates, without the
        covisibility-group accumulation)."""
        if not self.bows or len(bow[0]) == 0:
            return []
        ids, row, words, weights = self._entries()
        slot = np.zeros(max(int(self.voc.n_words), int(words.max()) + 1,
                            int(np.max(bow[0])) + 1), dtype=np.int64)
        slot[bow[0]] = np.arange(1, len(bow[0]) + 1)   # query words are unique (transform)
        s = slot[words]
        common = s > 0
        r = row[common]
        counts = np.bincount(r, minlength=len(ids))
        if exclude:
            counts[np.isin(ids, np.fromiter(exclude, dtype=np.int64))] = 0
        mx = int(counts.max())
        if mx == 0:
            return []
        va = np.asarray(bow[1], np.float64)[s[common] - 1]
        vb = weights[common]
        score = 0.5 * np.bincount(r, weights=np.abs(va) + np.abs(vb) - np.abs(va - vb),
                                  minlength=len(ids))   # bow_score for every keyframe at once
        cand = np.nonzero((counts >= 0.8 * mx) & (score >= min_score))[0]
        cand = cand[np.lexsort((ids[cand], -score[cand]))][:top]
        return [(int(ids[i]), float(score[i])) for i in cand]
