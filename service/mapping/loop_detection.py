"""Appearance-based loop-closure detection: RTAB-Map's discrete Bayes filter over the nodes
of working memory (BayesFilter.cpp, Rtabmap::adjustLikelihood, Memory::computeLikelihood).

Per new node:
  * likelihood — tf-idf over the vocabulary's inverted index: for every (distinct) word of
    the new node shared with place i, add (n_wi / n_i) · log10(N / n_w) (n_wi: occurrences
    of the word in i, n_i: words of i, N: indexed nodes, n_w: nodes holding the word);
    then RTAB-Map's adjustment: a score s > mean + σ becomes (s − σ)/mean, every other
    score 1, and the virtual "no loop" place gets mean/σ + 1;
  * prior — prediction matrix × last posterior, as BayesFilter builds it: the virtual
    place keeps virtual_prior (Bayes/VirtualPlacePriorThr 0.9) of its own mass and spreads
    the rest uniformly over the candidates (so new nodes start with a small prior); each
    hypothesis gives prediction[0] (0.1) to the virtual place and spreads the rest over
    itself (0.36) and its graph neighbours (level 1 0.30, level 2 0.16, …);
  * posterior = prior × likelihood, normalised;
  * acceptance — the hypothesis score is 1 − p(virtual place), the best hypothesis is the
    node of highest posterior; accepted when score ≥ loop_threshold (Rtabmap/LoopThr 0.11),
    there is more than one hypothesis, the node is not in short-term memory, and (our
    addition, `require_evidence`) its own adjusted likelihood in this node is above the
    virtual place's.

The posterior only holds current candidates (bounded by WM). Work per node: one pass
over the postings of the node's words (vectorized), and a bounded graph walk from the
`max_predicted` strongest hypotheses (the others keep their mass in place).
"""
from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..memory.vocabulary import Vocabulary
from ..memory.working_memory import graph_levels

PREDICTION_LC = (0.1, 0.36, 0.30, 0.16, 0.062, 0.0151, 0.00255, 0.000324, 2.5e-05)


@dataclass
class LoopHypothesis:
    best_id: int | None  # node of highest posterior (None when there was no candidate)
    posterior: float  # posterior of best_id
    accepted: bool
    likelihood: list[tuple[int, float]] = field(default_factory=list)  # raw tf-idf top-k
    reason: str = ""
    score: float = 0.0  # 1 - p(virtual place), compared with loop_threshold
    virtual_posterior: float = 1.0
    n_hypotheses: int = 0
    shared: float = 0.0  # fraction of the node's distinct words also seen in best_id
    distinct: float = 0.0  # raw likelihood of best_id / best raw likelihood away from it

    def to_dict(self) -> dict:
        return {
            "best_id": self.best_id, "posterior": self.posterior, "accepted": self.accepted,
            "likelihood": [[int(i), float(s)] for i, s in self.likelihood], "reason": self.reason,
            "score": self.score, "virtual_posterior": self.virtual_posterior,
            "n_hypotheses": self.n_hypotheses, "shared": self.shared,
            "distinct": self.distinct,
        }


class LoopDetector:
    def __init__(self, vocabulary: Vocabulary | None = None, loop_threshold: float = 0.11,
                 virtual_prior: float = 0.9, prediction=PREDICTION_LC, stm_size: int = 10,
                 tfidf: bool = True, top_k: int = 5, max_predicted: int = 64,
                 require_evidence: bool = True, min_shared: float = 0.05, min_distinct: float = 2.0,
                 distinct_depth: int = 4, **_unused):
        self.vocabulary = vocabulary if vocabulary is not None else Vocabulary()
        self.loop_threshold = float(loop_threshold)
        self.virtual_prior = float(virtual_prior)
        self.prediction = tuple(float(x) for x in prediction)
        self.stm_size = int(stm_size)
        self.tfidf = bool(tfidf)
        self.top_k = int(top_k)
        self.max_predicted = int(max_predicted)
        # Accept only a hypothesis whose own (adjusted) likelihood in this node beats the
        # virtual place's (mean/σ + 1), i.e. this observation favours it over "new place":
        # after the robot leaves a revisited path the posterior lingers a few nodes on the
        # prediction alone; RTAB-Map leaves those to geometric verification, we reject them.
        self.require_evidence = bool(require_evidence)
        # Absolute floor: the fraction of the node's distinct words the hypothesis shares
        # (the mean/σ adjustment also magnifies a handful of shared words when all scores are
        # tiny, e.g. early on with few nodes).
        self.min_shared = float(min_shared)
        self.min_distinct = float(min_distinct)
        self.distinct_depth = int(distinct_depth)
        self._post_ids = np.zeros(0, np.int64)  # hypotheses (sorted ids)
        self._post = np.zeros(0, np.float64)
        self._post_virtual = 1.0
        self._stm: deque[int] = deque(maxlen=max(self.stm_size, 0) or None)

    # -- state --------------------------------------------------------------------------
    @property
    def posterior(self) -> dict[int, float]:
        """Current posterior of the hypotheses (the virtual place under key -1)."""
        d = dict(zip(self._post_ids.tolist(), self._post.tolist()))
        d[-1] = self._post_virtual
        return d

    @property
    def stm(self) -> list[int]:
        return list(self._stm)

    def forget(self, node_ids) -> None:
        """Drop nodes from the posterior (e.g. transferred to long-term memory)."""
        keep = ~np.isin(self._post_ids, np.asarray(list(node_ids), np.int64))
        self._post_ids, self._post = self._post_ids[keep], self._post[keep]

    # -- likelihood ---------------------------------------------------------------------
    def raw_likelihood(self, word_ids: np.ndarray, cand: np.ndarray, node_id: int | None = None) -> np.ndarray:
        """Score of each candidate (sorted ids `cand`) against the node's words."""
        s = np.zeros(len(cand), np.float64)
        self._last_shared = (np.zeros(len(cand), np.int64), 1)
        if not len(cand):
            return s
        voc = self.vocabulary
        uw, df, idx, nodes, counts = voc.postings(word_ids)
        if not len(nodes):
            return s
        pos = np.minimum(np.searchsorted(cand, nodes), len(cand) - 1)
        ok = cand[pos] == nodes
        if node_id is not None:
            ok &= nodes != node_id
        pos, idx, counts, nodes = pos[ok], idx[ok], counts[ok], nodes[ok]
        self._last_shared = (np.bincount(pos, minlength=len(cand)), max(len(uw), 1))
        n_i = np.array([max(voc.node_size(n), 1) for n in cand.tolist()], np.float64)
        if self.tfidf:
            N = max(voc.n_nodes, 1)
            idf = np.log10(N / np.maximum(df[idx], 1))
            np.add.at(s, pos, counts / n_i[pos] * idf)
        else:  # shared words / max(#words) (Signature::compareTo)
            w = np.asarray(word_ids)
            n_new = max(int((w >= 0).sum()), 1)
            np.add.at(s, pos, np.ones(len(pos)))
            s /= np.maximum(n_i, n_new)
        return s

    @staticmethod
    def adjust_likelihood(s: np.ndarray) -> tuple[np.ndarray, float]:
        """RTAB-Map's adjustLikelihood: (adjusted scores, virtual place likelihood)."""
        if not len(s):
            return s.copy(), 1.0
        mean = float(s.mean())
        std = float(s.std())
        if mean <= 1e-12 or std <= 1e-12:
            return np.ones_like(s), 1.0
        adj = np.where(s > mean + std, (s - std) / mean, 1.0)
        return adj, mean / std + 1.0

    # -- prediction ---------------------------------------------------------------------
    def _predict(self, cand: np.ndarray, neighbours: Mapping[int, list[int]]) -> tuple[np.ndarray, float]:
        """prior = prediction matrix × last posterior (BayesFilter::generatePrediction /
        updatePrediction / normalize): (prior of each candidate, prior of the virtual place).

        Virtual place column: keeps virtual_prior, spreads 1 − virtual_prior uniformly over
        the candidates (new nodes start there). Column of hypothesis j: the virtual place
        gets prediction[0]; j itself prediction[1], its graph neighbours at depth k
        prediction[k+1] (only candidates receive belief; the values of levels with no
        candidate go back to j), the rest of the model's mass spread over all places; the
        column is normalised to 1 − prediction[0]."""
        M = len(cand)
        prior = np.zeros(M, np.float64)
        pv_old = self._post_virtual
        if not M:
            return prior, 1.0
        pred = self.prediction
        lc_total = float(sum(pred))
        hyp_col = 1.0 - pred[0]  # node mass of a hypothesis column
        prior += pv_old * (1.0 - self.virtual_prior) / M
        prior_v = self.virtual_prior * pv_old
        if not len(self._post_ids):
            return prior, prior_v
        pos = np.minimum(np.searchsorted(cand, self._post_ids), M - 1)
        present = cand[pos] == self._post_ids
        ids, post, pos = self._post_ids[present], self._post[present], pos[present]
        prior_v += pred[0] * float(post.sum())
        other = max(1.0 - lc_total, 0.0) / M  # "all other places" value of every column
        order = np.argsort(-post, kind="stable")
        strong = order[: self.max_predicted]
        weak = order[self.max_predicted:]
        # Weak hypotheses: their whole column mass stays on themselves (bounded work).
        prior[pos[weak]] += post[weak] * hyp_col
        levels = pred[1:]
        stm = set(self._stm)
        dst, val = [], []
        for j in strong.tolist():  # bounded: max_predicted graph walks of depth len(levels)-1
            start = int(ids[j])
            col_ids, col_vals = [start], [levels[0]]
            for lvl, nxt in enumerate(graph_levels(neighbours, start, len(levels) - 1), 1):
                keep = [b for b in nxt if b not in stm]
                col_ids.extend(keep)
                col_vals.extend([levels[lvl]] * len(keep))
            ci = np.asarray(col_ids, np.int64)
            cv = np.asarray(col_vals, np.float64)
            p = np.minimum(np.searchsorted(cand, ci), M - 1)
            keep = cand[p] == ci
            p, cv = p[keep], cv[keep]
            cv[0] += max(lc_total - pred[0] - cv.sum(), 0.0)  # missing neighbours -> self
            tot = cv.sum() + other * (M - len(cv))
            scale = hyp_col / tot
            dst.append(p)
            val.append(cv * scale * post[j])
            prior += other * scale * post[j]  # (also adds to p: negligible, < 1e-6)
        if dst:
            np.add.at(prior, np.concatenate(dst), np.concatenate(val))
        return prior, prior_v

    def _distinctiveness(self, raw, cand, best, neighbours) -> float:
        """raw[best] / max raw over candidates farther than `distinct_depth` graph hops from
        best (a place that looks like several unrelated places — repeated textures — is
        not distinctive)."""
        near = {best}
        for level in graph_levels(neighbours, best, self.distinct_depth):
            near.update(level)
        far = ~np.isin(cand, np.fromiter(near, np.int64, len(near)))
        i = int(np.searchsorted(cand, best))
        other = float(raw[far].max()) if far.any() else 0.0
        return float(raw[i]) / other if other > 0 else float("inf")

    # -- update -------------------------------------------------------------------------
    def process(self, node_id: int, word_ids, neighbours: Mapping[int, list[int]] | None = None,
                candidates=None) -> LoopHypothesis:
        node_id = int(node_id)
        word_ids = np.asarray(word_ids, np.int64)
        voc = self.vocabulary
        if node_id not in voc:
            voc.index_node(node_id, word_ids)
        neighbours = neighbours or {}
        stm = set(self._stm) | {node_id}
        if candidates is None:
            candidates = [n for n in voc.node_ids() if n not in stm]
        cand = np.unique(np.asarray([c for c in candidates if c not in stm], np.int64))
        self._stm.append(node_id)

        if not len(cand):
            self._post_ids, self._post, self._post_virtual = cand, np.zeros(0), 1.0
            return LoopHypothesis(None, 0.0, False, [], "no candidates", 0.0, 1.0, 0)
        raw = self.raw_likelihood(word_ids, cand, node_id)
        adj, lik_virtual = self.adjust_likelihood(raw)
        prior, prior_v = self._predict(cand, neighbours)
        post = prior * adj
        post_v = prior_v * lik_virtual
        z = post.sum() + post_v
        post /= z
        post_v /= z
        self._post_ids, self._post, self._post_virtual = cand, post, post_v

        b = int(np.argmax(post))
        best, p_best = int(cand[b]), float(post[b])
        score = 1.0 - post_v
        k = min(self.top_k, len(raw))
        top = np.argsort(-raw, kind="stable")[:k]
        lik = [(int(cand[i]), float(raw[i])) for i in top if raw[i] > 0]
        shared_counts, n_words = self._last_shared
        shared = float(shared_counts[b]) / n_words
        distinct = self._distinctiveness(raw, cand, best, neighbours)
        if len(cand) < 2:
            accepted, reason = False, "single hypothesis"
        elif best in stm:
            accepted, reason = False, "best hypothesis in STM"
        elif self.require_evidence and adj[b] <= lik_virtual:
            accepted, reason = False, (f"no appearance evidence for {best} in this node "
                                       f"(score {score:.3f}, belief carried by the prediction)")
        elif shared < self.min_shared:
            accepted, reason = False, (f"too few shared words with {best}: {shared:.3f} < {self.min_shared} "
                                       f"(score {score:.3f})")
        elif distinct < self.min_distinct:
            accepted, reason = False, (f"not distinctive: {best} scores {distinct:.2f}x the best place "
                                       f"outside its neighbourhood < {self.min_distinct} (score {score:.3f})")
        elif score >= self.loop_threshold:
            accepted, reason = True, f"accepted (score {score:.3f} >= {self.loop_threshold})"
        else:
            accepted, reason = False, f"below threshold (score {score:.3f} < {self.loop_threshold})"
        return LoopHypothesis(best, p_best, accepted, lik, reason, float(score), float(post_v), len(cand), shared,
                              distinct)
