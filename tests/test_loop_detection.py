"""Bayes-filter loop detection on synthetic places (random ORB-like descriptors) and, when
time allows, on the synthetic figure-eight scene."""
import numpy as np
import pytest

from mnemoslam.service.mapping.loop_detection import LoopDetector, LoopHypothesis
from mnemoslam.service.memory.vocabulary import Vocabulary

N_DESC = 400


class World:
    """Places are descriptor sets: 70% unique to the place, 30% from a pool shared by all
    places (repeated textures), each with a little noise. A revisit flips 20% of the bits
    of half of a place's descriptors... and replaces 30% by new ones."""

    def __init__(self, seed=0, stm_size=10):
        self.rng = np.random.default_rng(seed)
        self.pool = self.rng.integers(0, 256, (300, 32), dtype=np.uint8)
        self.voc = Vocabulary()
        self.det = LoopDetector(self.voc, stm_size=stm_size)
        self.places: list[np.ndarray] = []
        self.neighbours: dict[int, list[int]] = {}
        self.next_id = 0
        self.history: list[tuple[int, LoopHypothesis]] = []

    def _flip(self, d, p):
        bits = np.unpackbits(d, axis=1)
        bits ^= (self.rng.random(bits.shape) < p).astype(np.uint8)
        return np.packbits(bits, axis=1)

    def new_place(self):
        n_common = int(0.3 * N_DESC)
        d = self.rng.integers(0, 256, (N_DESC, 32), dtype=np.uint8)
        d[:n_common] = self._flip(self.pool[self.rng.integers(0, len(self.pool), n_common)], 0.02)
        self.places.append(d)
        return d

    def revisit(self, i):
        d = self.places[i].copy()
        half = self.rng.choice(N_DESC, N_DESC // 2, replace=False)
        d[half] = self._flip(d[half], 0.2 / 8)  # noise: flip bits on half of the descriptors
        new = self.rng.choice(N_DESC, int(0.3 * N_DESC), replace=False)
        d[new] = self.rng.integers(0, 256, (len(new), 32), dtype=np.uint8)
        return d

    def step(self, desc) -> LoopHypothesis:
        nid = self.next_id
        self.next_id += 1
        w = self.voc.add(nid, desc)
        self.neighbours[nid] = []
        if nid > 0:
            self.neighbours[nid].append(nid - 1)
            self.neighbours[nid - 1].append(nid)
        stm = set(range(max(0, nid - self.det.stm_size), nid + 1))
        cands = {n for n in self.neighbours if n not in stm}
        h = self.det.process(nid, w, self.neighbours, cands)
        self.history.append((nid, h))
        return h


def test_revisit_accepted_and_no_false_accepts():
    wd = World(seed=1)
    for _ in range(60):  # nodes 0..59: new places
        h = wd.step(wd.new_place())
        assert not h.accepted, h
    accepted = []
    for i in range(30, 40):  # nodes 60..69 revisit places 30..39 (30 nodes earlier)
        h = wd.step(wd.revisit(i))
        if h.accepted:
            accepted.append((i, h.best_id))
        assert h.likelihood and h.likelihood[0][0] == i  # the likelihood already peaks right
    assert len(accepted) >= 8, accepted
    assert all(abs(best - true) <= 1 for true, best in accepted), accepted
    for k in range(200):  # 200 more new places: nothing may be accepted
        h = wd.step(wd.new_place())
        assert not h.accepted, h
        if k >= 10:  # the belief left by the revisit has faded by then
            assert h.score < wd.det.loop_threshold, (k, h)


def test_never_proposes_stm_nodes():
    wd = World(seed=2)
    for _ in range(30):
        wd.step(wd.new_place())
    # Revisit the place just seen (in STM): it may not be proposed even with no exclusion
    # by the caller (candidates=None lets the detector pick every indexed node).
    for back in range(1, 6):
        nid = wd.next_id
        w = wd.voc.add(nid, wd.revisit(nid - back))
        h = wd.det.process(nid, w, wd.neighbours, None)
        wd.next_id += 1
        assert h.best_id not in wd.det.stm
        assert h.best_id is None or h.best_id < nid - wd.det.stm_size or not h.accepted
        assert all(n not in wd.det.stm for n in wd.det.posterior if n >= 0)


def test_prediction_moves_mass_to_neighbours():
    wd = World(seed=3)
    for _ in range(60):
        wd.step(wd.new_place())
    h1 = wd.step(wd.revisit(24))
    h = wd.step(wd.revisit(25))
    assert h1.best_id == 24 and h.best_id == 25
    # Before the next node: the prior from the prediction puts the mass around 25 (its
    # neighbours 24 and 26 well above any far node).
    det = wd.det
    post = det.posterior
    prior, prior_v = det._predict(det._post_ids, wd.neighbours)
    idx = {int(n): i for i, n in enumerate(det._post_ids)}
    far = max(prior[idx[n]] for n in idx if abs(n - 25) > 8)
    assert prior[idx[26]] > 3 * far and prior[idx[24]] > 3 * far
    assert prior[idx[26]] > post[26]  # the neighbour gained belief
    assert abs(prior.sum() + prior_v - 1) < 1e-6
    h2 = wd.step(wd.revisit(26))  # the next revisit: more confident than the first
    assert h2.best_id == 26 and h2.score > h.score > h1.score and h2.accepted
    assert max(p for n, p in det.posterior.items() if n >= 0 and abs(n - 26) > 8) < det.posterior[26] / 10


def test_posterior_bounded_to_candidates_and_forget():
    wd = World(seed=4)
    for _ in range(40):
        wd.step(wd.new_place())
    nid = wd.next_id
    w = wd.voc.add(nid, wd.new_place())
    h = wd.det.process(nid, w, wd.neighbours, {1, 2, 3, 5})
    assert set(wd.det.posterior) == {-1, 1, 2, 3, 5}
    assert abs(sum(wd.det.posterior.values()) - 1) < 1e-9
    wd.det.forget([2])
    assert 2 not in wd.det.posterior
    assert h.to_dict()["n_hypotheses"] == 4


def test_no_candidates():
    det = LoopDetector()
    h = det.process(0, np.arange(10), {}, set())
    assert h.best_id is None and not h.accepted and h.reason == "no candidates"


def _run_synthetic(trajectory, rate=1.0):
    from mnemoslam.client.synthetic import SyntheticDataset
    from mnemoslam.service.config import load_config
    from mnemoslam.service.tracking.features import FeatureExtractor

    ds = SyntheticDataset(trajectory, rate=rate, noise=True, width=320, height=240, fx=262.5)
    cfg = load_config()
    fe = FeatureExtractor(ds.calibration, cfg.features, cfg.stereo)
    voc = Vocabulary()
    det = LoopDetector(voc)
    neighbours: dict[int, list[int]] = {}
    out = []
    for i in range(len(ds)):
        w = voc.add(i, fe.extract(ds.frame(i)).descriptors)
        neighbours[i] = [i - 1] if i else []
        if i:
            neighbours[i - 1].append(i)
        out.append(det.process(i, w, neighbours, None))
    return ds, out


def _close(poses, i, j, dist, angle):
    d = np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3])
    c = np.clip(poses[i, :3, 2] @ poses[j, :3, 2], -1, 1)
    return d < dist and np.degrees(np.arccos(c)) < angle


@pytest.mark.slow
def test_synthetic_figure8_recall_and_precision():
    """Keyframes at 1 Hz over two laps of the figure eight: every accepted hypothesis shows
    the same part of the scene (< 2.5 m, < 45°: the views overlap) and ≥ 80% of the keyframes
    that revisit a place seen ≥ 10 s earlier (< 0.5 m, < 30°) are accepted with a right node."""
    ds, hyps = _run_synthetic("figure8")
    poses, stamps = ds.ground_truth.poses, ds.ground_truth.stamps
    revisits = [i for i in range(len(ds))
                if any(stamps[i] - stamps[j] >= 10 and _close(poses, i, j, 0.5, 30) for j in range(i))]
    assert len(revisits) > 30
    wrong = [(i, h.best_id) for i, h in enumerate(hyps) if h.accepted and not _close(poses, i, h.best_id, 2.5, 45)]
    assert not wrong
    hit = [i for i in revisits if hyps[i].accepted and _close(poses, i, hyps[i].best_id, 2.5, 45)]
    assert len(hit) >= 0.8 * len(revisits), (len(hit), len(revisits))


@pytest.mark.slow
def test_synthetic_straight_walk_past_repeated_posters_no_loop():
    """No revisit: nothing accepted at 1 Hz. (At 2 Hz two keyframes facing the same poster
    3.1 m apart are accepted: identical appearance with one earlier look-alike, which only the
    geometric / graph-consistency checks downstream can reject.)"""
    ds, hyps = _run_synthetic("straight", rate=1.0)
    assert not [i for i, h in enumerate(hyps) if h.accepted]
