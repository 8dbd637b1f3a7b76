"""Proximity candidates: near in space and looking the same way, nearest first."""
import numpy as np

from mnemoslam.client.kernel.geometry import look_at, nearby


def _pose(position, target):
    return look_at(np.asarray(position, float), np.asarray(target, float))


def test_nearby_keeps_close_keyframes_that_look_the_same_way_nearest_first():
    current = _pose([0, 0, 0], [0, 0, 5])
    poses = np.stack([
        _pose([0.5, 0, 0], [0.5, 0, 5]),   # 0.5 m, same direction
        _pose([0.2, 0, 0], [0.2, 0, 5]),   # 0.2 m, same direction
        _pose([0.1, 0, 0], [0.1, 0, -5]),  # close but looking back
        _pose([3.0, 0, 0], [3.0, 0, 5]),   # too far
        _pose([0, 0.3, 0], [4, 0.3, 4]),   # 45° off: on the bound
    ])
    ids = np.array([10, 11, 12, 13, 14])
    assert nearby(poses, ids, current, 1.0, 50.0, 5).tolist() == [11, 14, 10]
    assert nearby(poses, ids, current, 1.0, 30.0, 5).tolist() == [11, 10]
    assert nearby(poses, ids, current, 1.0, 30.0, 1).tolist() == [11]
    assert nearby(poses[:0], ids[:0], current, 1.0, 30.0, 3).tolist() == []
