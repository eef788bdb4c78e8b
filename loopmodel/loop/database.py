"""Keyframe database and place recognition.

Each keyframe is stored with its features and its TF-IDF bag of words. A query scores
every stored keyframe older than ``min_gap`` through an inverted file (sparse matrix of
word weights), keeps candidates near the best score, groups them into *islands* of
neighbouring keyframes (neighbours in time see the same scene, so they stand in for
covisibility), and accepts an island only when the islands of ``consistency`` consecutive
queries agree (temporal consistency, as in DBoW2). Accepted candidates still need the
geometric verification of :mod:`loopmodel.loop.closure`.

Without a given vocabulary the database trains one on the fly from its own keyframes once
it holds ``train_after`` of them, and retrains when their number has grown by
``retrain_growth`` (up to ``max_train_keyframes``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.errors import EstimationError
from loopmodel.loop.features import FeatureSet
from loopmodel.loop.vocabulary import Vocabulary

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
_LOOP = LoopConfig.model_fields


@dataclass
class PlaceParams:
    """Place-recognition parameters.

    Ids are keyframe or frame indices; defaults: those of :class:`loopmodel.config.LoopConfig`.
    """

    min_gap: int = _LOOP["min_gap_keyframes"].default
    min_score: float = _LOOP["min_score"].default
    relative_score: float = _LOOP["relative_score"].default
    island_gap: int = _LOOP["island_gap"].default
    consistency: int = _LOOP["consistency"].default
    consistency_tol: int = _LOOP["consistency_tol"].default
    max_islands: int = _LOOP["max_islands"].default
    branching: int = _LOOP["vocabulary_branching"].default
    levels: int = _LOOP["vocabulary_levels"].default
    train_after: int = _LOOP["vocabulary_train_after"].default
    retrain_growth: float = _LOOP["retrain_growth"].default
    max_train_keyframes: int = _LOOP["max_train_keyframes"].default
    max_train_descriptors: int = _LOOP["max_train_descriptors"].default
    seed: int = 0

    @classmethod
    def from_config(cls, cfg: LoopConfig) -> PlaceParams:
        """The place-recognition knobs of the ``loop`` configuration section."""
        return cls(
            min_gap=cfg.min_gap_keyframes,
            min_score=cfg.min_score,
            relative_score=cfg.relative_score,
            island_gap=cfg.island_gap,
            consistency=cfg.consistency,
            consistency_tol=cfg.consistency_tol,
            max_islands=cfg.max_islands,
            branching=cfg.vocabulary_branching,
            levels=cfg.vocabulary_levels,
            train_after=cfg.vocabulary_train_after,
            retrain_growth=cfg.retrain_growth,
            max_train_keyframes=cfg.max_train_keyframes,
            max_train_descriptors=cfg.max_train_descriptors,
        )


@dataclass
class PlaceCandidate:
    """An island of stored keyframes matching a query.

    ``best_id`` is the island's best-scoring keyframe, ``members`` its keyframe ids,
    ``score`` the island's summed score, ``consistent`` how many consecutive queries
    (this one included) produced an agreeing island, ``accepted`` whether that reaches
    the required consistency."""

    best_id: int
    members: list[int]
    score: float
    best_score: float
    consistent: int = 1
    accepted: bool = False


@dataclass
class _Entry:
    kf_id: int
    features: FeatureSet
    words: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    bow_ids: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    bow_w: F64 = field(default_factory=lambda: np.zeros(0))


class KeyframeDatabase:
    """Bag-of-words database of keyframes with temporal-consistency checks."""

    def __init__(self, vocabulary: Vocabulary | None = None, params: PlaceParams | None = None) -> None:
        self.params = params if params is not None else PlaceParams()
        self.vocabulary = vocabulary
        self._trained_on_the_fly = vocabulary is None
        self._trained_at = 0
        self._entries: list[_Entry] = []
        self._index: dict[int, int] = {}
        self._matrix: Any = None
        self._history: list[tuple[int, int, int, int]] = []  # (query id, lo, hi, count)
        self._last_query: int | None = None
        #: the last scored feature set, the vocabulary it was described with and its words (kf15)
        self._scored: tuple[FeatureSet, Vocabulary, I64] | None = None

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._index

    def features(self, kf_id: int) -> FeatureSet:
        """The features stored with a keyframe."""
        return self._entries[self._index[kf_id]].features

    def ids(self) -> list[int]:
        """Stored keyframe ids in insertion order."""
        return [e.kf_id for e in self._entries]

    # -- vocabulary ---------------------------------------------------------------------
    def _maybe_train(self) -> None:
        if not self._trained_on_the_fly:
            return
        n = len(self._entries)
        p = self.params
        if n < p.train_after or n > p.max_train_keyframes:
            return
        if self.vocabulary is not None and n < p.retrain_growth * self._trained_at:
            return
        rng = np.random.default_rng(p.seed)
        docs = [e.features.descriptors for e in self._entries if len(e.features)]
        allx = np.concatenate(docs)
        if allx.shape[0] > p.max_train_descriptors:
            allx = allx[rng.choice(allx.shape[0], p.max_train_descriptors, replace=False)]
        if allx.shape[0] < p.branching:
            return
        self.vocabulary = Vocabulary.train(allx, p.branching, p.levels, rng=rng, documents=docs)
        self._trained_at = n
        for e in self._entries:
            self._set_bow(e)
        self._matrix = None
        logger.info("vocabulary trained on %d keyframes: %d words", n, self.vocabulary.n_words)

    def _words(self, features: FeatureSet) -> I64:
        """The vocabulary's word of each feature; a keyframe scored just before it is stored is described once."""
        assert self.vocabulary is not None
        last = self._scored
        if last is not None and last[0] is features and last[1] is self.vocabulary:
            return last[2]
        words = self.vocabulary.transform(features.descriptors)
        self._scored = (features, self.vocabulary, words)
        return words

    def _set_bow(self, e: _Entry) -> None:
        assert self.vocabulary is not None
        e.words = self._words(e.features)
        e.bow_ids, e.bow_w = self.vocabulary.bow(words=e.words)

    # -- storage and scoring ------------------------------------------------------------
    def add(self, kf_id: int, features: FeatureSet) -> None:
        """Store a keyframe (ids must increase)."""
        if self._entries and kf_id <= self._entries[-1].kf_id:
            raise EstimationError(f"keyframe ids must increase: {kf_id} after {self._entries[-1].kf_id}")
        e = _Entry(kf_id, features)
        self._index[kf_id] = len(self._entries)
        self._entries.append(e)
        if self.vocabulary is not None:
            self._set_bow(e)
            self._matrix = None
        self._maybe_train()

    def add_precomputed(self, kf_id: int, features: FeatureSet, words: I64, bow_ids: I64, bow_w: F64) -> None:
        """Store a keyframe with its words and bag of words already computed (a saved map's).

        Needs the vocabulary they were computed with; ids must increase; never retrains.
        """
        if self.vocabulary is None:
            raise EstimationError("a keyframe with precomputed words needs the database's vocabulary")
        if self._entries and kf_id <= self._entries[-1].kf_id:
            raise EstimationError(f"keyframe ids must increase: {kf_id} after {self._entries[-1].kf_id}")
        self._trained_on_the_fly = False
        self._index[kf_id] = len(self._entries)
        self._entries.append(_Entry(kf_id, features, np.asarray(words, np.int64), bow_ids, bow_w))
        self._matrix = None

    def _csr(self) -> Any:
        if self._matrix is None:
            import scipy.sparse as sp  # about 0.3 s to import: not with the pipeline

            assert self.vocabulary is not None
            rows = np.concatenate([np.full(e.bow_ids.size, i) for i, e in enumerate(self._entries)])
            cols = np.concatenate([e.bow_ids for e in self._entries])
            vals = np.concatenate([e.bow_w for e in self._entries])
            self._matrix = sp.csr_matrix((vals, (rows, cols)), shape=(len(self._entries), self.vocabulary.n_words))
        return self._matrix

    def words_of(self, kf_id: int) -> I64:
        """Word id of every feature of a stored keyframe (empty before training)."""
        return self._entries[self._index[kf_id]].words

    def score_all(self, features: FeatureSet, max_id: int | None = None) -> tuple[I64, F64]:
        """L1 bag-of-words scores of ``features`` against every stored keyframe with id ``<= max_id``.

        (ids, scores).
        """
        if self.vocabulary is None or not self._entries:
            return np.zeros(0, np.int64), np.zeros(0)
        q_ids, q_w = self.vocabulary.bow(words=self._words(features))
        ids = np.array([e.kf_id for e in self._entries], np.int64)
        if q_ids.size == 0:
            return ids, np.zeros(ids.size)
        M = self._csr()[:, q_ids].tocsr()
        qfull = q_w
        M.data = np.minimum(M.data, qfull[M.indices])
        scores = np.asarray(M.sum(axis=1)).ravel()
        if max_id is not None:
            keep = ids <= max_id
            return ids[keep], scores[keep]
        return ids, scores

    # -- place recognition --------------------------------------------------------------
    def query(self, query_id: int, features: FeatureSet) -> list[PlaceCandidate]:
        """Candidate revisits of the place seen by ``features`` (keyframe ``query_id``), best island first.

        ``accepted`` marks the temporally consistent ones. Call once per keyframe in increasing id
        order (before or after :meth:`add`).
        """
        p = self.params
        ids, scores = self.score_all(features, max_id=query_id - p.min_gap)
        islands: list[PlaceCandidate] = []
        if ids.size and scores.max() >= p.min_score:
            best = float(scores.max())
            keep = scores >= max(p.min_score, p.relative_score * best)
            cid, csc = ids[keep], scores[keep]
            order = np.argsort(cid)
            cid, csc = cid[order], csc[order]
            start = 0
            for k in range(1, cid.size + 1):
                if k == cid.size or cid[k] - cid[k - 1] > p.island_gap:
                    mem, sc = cid[start:k], csc[start:k]
                    j = int(np.argmax(sc))
                    islands.append(PlaceCandidate(int(mem[j]), mem.tolist(), float(sc.sum()), float(sc[j])))
                    start = k
            islands.sort(key=lambda c: -c.score)
            islands = islands[: p.max_islands]
        # Temporal consistency with the previous query's islands.
        prev = self._history if self._last_query is not None else []
        new_hist: list[tuple[int, int, int, int]] = []
        for c in islands:
            lo, hi = min(c.members), max(c.members)
            count = 1
            for _, plo, phi, pc in prev:
                if lo <= phi + p.consistency_tol and hi >= plo - p.consistency_tol:
                    count = max(count, pc + 1)
            c.consistent = count
            c.accepted = count >= p.consistency
            new_hist.append((query_id, lo, hi, count))
        self._history = new_hist
        self._last_query = query_id
        return islands

    def reset_consistency(self) -> None:
        """Forget the temporal-consistency history (e.g. after tracking was lost)."""
        self._history = []
        self._last_query = None
