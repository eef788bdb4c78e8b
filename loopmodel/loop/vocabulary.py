"""Visual vocabulary.

A tree of descriptor clusters (hierarchical k-means; k-majority for binary descriptors such as ORB)
and TF-IDF bag-of-words vectors.

The tree has branching factor ``k`` and at most ``levels`` levels; its leaves are the
words. A descriptor is quantised by descending from the root to the nearest child at each
level (Hamming distance for binary descriptors, Euclidean for float ones). A bag of words
is the L1-normalised vector of term frequency times inverse document frequency; two bags
are compared with the L1 score ``1 - |v1 - v2|_1 / 2`` (the sum of element-wise minima).
A vocabulary is a value: :mod:`loopmodel.io.vocabulary_file` reads and writes its ``.npz`` (a
pre-trained one per descriptor kind ships as package data, ``loopmodel/data/vocabulary_<kind>.npz``,
written by ``loopmodel loop vocabulary``, :func:`train_from_images`); training on the fly from the
descriptors at hand is an option.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def hamming_to(desc: NDArray[np.uint8], centers: NDArray[np.uint8]) -> NDArray[np.int64]:
    """Hamming distances (N, K) between binary descriptors (N, B) and centres (K, B)."""
    a = np.ascontiguousarray(desc)
    b = np.ascontiguousarray(centers)
    nbytes = a.shape[1]
    if nbytes % 8 == 0:
        a = a.view(np.uint64)
        b = b.view(np.uint64)
    x = a[:, None, :] ^ b[None, :, :]
    return np.asarray(np.bitwise_count(x).sum(axis=2, dtype=np.int64))


def _sqdist(desc: NDArray[np.float32], centers: NDArray[np.float32]) -> NDArray[np.float32]:
    d2 = (desc * desc).sum(1)[:, None] + (centers * centers).sum(1)[None, :] - 2.0 * desc @ centers.T
    return np.maximum(d2, 0.0)


def _distances(desc: NDArray[Any], centers: NDArray[Any], binary: bool) -> NDArray[Any]:
    return hamming_to(desc, centers) if binary else _sqdist(desc, centers)


def _majority(desc: NDArray[np.uint8]) -> NDArray[np.uint8]:
    bits = np.unpackbits(desc, axis=1)
    return np.packbits(bits.mean(axis=0) >= 0.5)


def _cluster(
    desc: NDArray[Any], k: int, binary: bool, rng: np.random.Generator, iterations: int
) -> tuple[NDArray[Any], I64]:
    """k-means (k-majority for binary) with k-means++ seeding -> centres, labels."""
    n = desc.shape[0]
    first = int(rng.integers(n))
    centers = [desc[first]]
    d = _distances(desc, desc[first : first + 1], binary)[:, 0].astype(float)
    for _ in range(1, k):
        w = d**2 if binary else d
        tot = w.sum()
        idx = int(rng.integers(n)) if tot <= 0 else int(rng.choice(n, p=w / tot))
        centers.append(desc[idx])
        d = np.minimum(d, _distances(desc, desc[idx : idx + 1], binary)[:, 0].astype(float))
    C = np.stack(centers)
    labels = np.zeros(n, np.int64)
    for it in range(iterations):
        new = np.argmin(_distances(desc, C, binary), axis=1)
        if it > 0 and np.array_equal(new, labels):
            break
        labels = new
        for c in range(k):
            members = desc[labels == c]
            if members.shape[0] == 0:
                continue
            C[c] = _majority(members) if binary else members.mean(axis=0)
    return C, labels


@dataclass
class Vocabulary:
    """A trained vocabulary tree.

    ``centers`` (n_nodes, D) node centres (node 0 is the root, its centre unused),
    ``children`` (n_nodes, k) child node ids (-1: none), ``word`` (n_nodes,) word id of
    leaves (-1 for inner nodes), ``idf`` (n_words,) inverse document frequencies.
    """

    centers: NDArray[Any]
    children: NDArray[np.int32]
    word: NDArray[np.int32]
    idf: F64
    binary: bool
    #: Provenance (descriptor kind, training images, parameters) as plain strings.
    info: dict[str, str] = field(default_factory=dict)

    @property
    def n_words(self) -> int:
        """Number of words (leaves)."""
        return int(self.idf.shape[0])

    @classmethod
    def train(
        cls,
        descriptors: NDArray[Any],
        branching: int = 10,
        levels: int = 4,
        rng: np.random.Generator | None = None,
        iterations: int = 8,
        documents: list[NDArray[Any]] | None = None,
    ) -> Vocabulary:
        """Train a tree on descriptors (N, D) (uint8: binary, else float).

        ``documents`` (one descriptor array per image) set the IDF weights; without them
        every word gets the same weight."""
        desc = np.asarray(descriptors)
        if desc.ndim != 2 or desc.shape[0] < branching:
            raise InputError("vocabulary", f"need at least {branching} descriptors, got {desc.shape[0]}")
        if branching < 2 or levels < 1:
            raise InputError("vocabulary", "branching must be >= 2 and levels >= 1")
        binary = desc.dtype == np.uint8
        if not binary:
            desc = desc.astype(np.float32)
        rng = rng if rng is not None else np.random.default_rng(0)
        centers: list[NDArray[Any]] = [np.zeros(desc.shape[1], desc.dtype)]
        children: list[list[int]] = [[-1] * branching]
        words: list[int] = [-1]
        n_words = 0
        # (node id, indices of its descriptors, depth)
        stack: list[tuple[int, I64, int]] = [(0, np.arange(desc.shape[0]), 0)]
        while stack:
            node, idx, depth = stack.pop()
            if depth >= levels or idx.size <= branching:
                words[node] = n_words
                n_words += 1
                continue
            C, labels = _cluster(desc[idx], branching, binary, rng, iterations)
            for c in range(branching):
                member = idx[labels == c]
                if member.size == 0:
                    continue
                child = len(centers)
                centers.append(C[c])
                children.append([-1] * branching)
                words.append(-1)
                children[node][c] = child
                stack.append((child, member, depth + 1))
        voc = cls(
            np.stack(centers),
            np.array(children, np.int32),
            np.array(words, np.int32),
            np.ones(n_words),
            binary,
        )
        if documents is not None:
            voc.set_idf(documents)
        return voc

    def transform(self, descriptors: NDArray[Any]) -> NDArray[np.int64]:
        """Word id of each descriptor (N,)."""
        desc = np.asarray(descriptors)
        if desc.shape[0] == 0:
            return np.zeros(0, np.int64)
        if desc.shape[1] != self.centers.shape[1]:
            raise InputError(
                "vocabulary",
                f"descriptor length {desc.shape[1]} != vocabulary's {self.centers.shape[1]}",
            )
        if self.binary and desc.shape[1] % 8 == 0:  # compiled, the same words (issue 33)
            from loopmodel.loop._vocabulary_kernels import descend

            words = descend(np.ascontiguousarray(desc, dtype=np.uint8).view(np.uint64),
                            np.ascontiguousarray(self.centers, dtype=np.uint8).view(np.uint64),
                            np.ascontiguousarray(self.children), np.ascontiguousarray(self.word))
            return np.asarray(words, dtype=np.int64)
        if not self.binary:
            desc = desc.astype(np.float32)
        if desc.shape[0] > 4096:
            return np.concatenate([self.transform(desc[i : i + 4096]) for i in range(0, desc.shape[0], 4096)])
        node = np.zeros(desc.shape[0], np.int64)
        while True:
            ch = self.children[node]  # (N, k)
            inner = np.any(ch >= 0, axis=1)
            if not inner.any():
                break
            rows = np.flatnonzero(inner)
            chs = ch[rows]
            C = self.centers[np.maximum(chs, 0)]  # (n, k, D)
            if self.binary:
                a = np.ascontiguousarray(desc[rows])
                if a.shape[1] % 8 == 0:
                    d = (
                        np.bitwise_count(a.view(np.uint64)[:, None, :] ^ np.ascontiguousarray(C).view(np.uint64))
                        .sum(axis=2, dtype=np.int64)
                        .astype(float)
                    )
                else:
                    d = np.bitwise_count(a[:, None, :] ^ C).sum(axis=2, dtype=np.int64).astype(float)
            else:
                diff = desc[rows][:, None, :] - C
                d = np.einsum("nkd,nkd->nk", diff, diff)
            d[chs < 0] = np.inf
            node[rows] = chs[np.arange(rows.size), np.argmin(d, axis=1)]
        return self.word[node].astype(np.int64)

    def set_idf(self, documents: list[NDArray[Any]]) -> None:
        """IDF weights ``log(N / n_w)`` from N documents (descriptor arrays per image).

        Words no document contains get ``log(N)``.
        """
        counts = np.zeros(self.n_words)
        for d in documents:
            counts[np.unique(self.transform(d))] += 1
        n = max(len(documents), 1)
        self.idf = np.log(n / np.maximum(counts, 1.0))

    def bow(self, descriptors: NDArray[Any] | None = None, words: I64 | None = None) -> tuple[I64, F64]:
        """TF-IDF bag of words: sorted word ids and their L1-normalised weights."""
        if words is None:
            if descriptors is None:
                raise InputError("vocabulary", "bow() needs descriptors or words")
            w = self.transform(descriptors)
        else:
            w = np.asarray(words, np.int64)
        if w.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        ids, counts = np.unique(w, return_counts=True)
        val = counts / w.size * self.idf[ids]
        s = val.sum()
        if s <= 0:
            return ids, np.full(ids.size, 1.0 / ids.size)
        return ids, val / s

    def arrays(self) -> dict[str, NDArray[Any]]:
        """The arrays of a vocabulary file (:func:`loopmodel.io.vocabulary_file.save_vocabulary` writes them)."""
        return {
            "centers": self.centers,
            "children": self.children,
            "word": self.word,
            "idf": self.idf,
            "binary": np.array(self.binary),
            "info_keys": np.array(list(self.info), dtype=str),
            "info_values": np.array(list(self.info.values()), dtype=str),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, NDArray[Any]]) -> Vocabulary:
        """The vocabulary of :meth:`arrays`' output (read by :func:`loopmodel.io.vocabulary_file.read_vocabulary`).

        Raises ``KeyError`` / ``ValueError`` when an array is missing or malformed.
        """
        info = (
            dict(zip(arrays["info_keys"].tolist(), arrays["info_values"].tolist(), strict=True))
            if "info_keys" in arrays
            else {}
        )
        return cls(arrays["centers"], arrays["children"], arrays["word"], arrays["idf"], bool(arrays["binary"]), info)


def bow_score(a: tuple[I64, F64], b: tuple[I64, F64]) -> float:
    """L1 similarity in [0, 1] of two L1-normalised bags of words."""
    common, ia, ib = np.intersect1d(a[0], b[0], assume_unique=True, return_indices=True)
    if common.size == 0:
        return 0.0
    return float(np.minimum(a[1][ia], b[1][ib]).sum())


def train_from_images(
    images: Iterable[NDArray[np.uint8]],
    kind: str = "orb",
    n_features: int = 1500,
    branching: int = 8,
    levels: int = 4,
    seed: int = 0,
    max_descriptors: int = 200000,
    source: str = "",
) -> Vocabulary:
    """Train a vocabulary for descriptor ``kind`` on grey images.

    ``n_features`` detected per image (:func:`loopmodel.loop.features.detect_and_describe`), at most
    ``max_descriptors`` of them (seeded random subset) clustered into a ``branching``^``levels``
    tree, IDF weights from the images as documents. ``source`` describes the images (kept in
    :attr:`Vocabulary.info`). Deterministic for a seed.
    """
    from loopmodel.loop.features import detect_and_describe, make_extractor

    ex = make_extractor(kind, n_features)
    docs = [fs.descriptors for fs in (detect_and_describe(im, kind, n_features, ex) for im in images) if len(fs)]
    if not docs:
        raise InputError("vocabulary", "no features found in the training images")
    rng = np.random.default_rng(seed)
    allx = np.concatenate(docs)
    if allx.shape[0] > max_descriptors:
        allx = allx[np.sort(rng.choice(allx.shape[0], max_descriptors, replace=False))]
    voc = Vocabulary.train(allx, branching, levels, rng=rng, documents=docs)
    voc.info = {
        "kind": kind.lower(),
        "images": str(len(docs)),
        "descriptors": str(allx.shape[0]),
        "n_features": str(n_features),
        "branching": str(branching),
        "levels": str(levels),
        "seed": str(seed),
        "source": source,
    }
    return voc
