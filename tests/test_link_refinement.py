"""Two-view reprojection refinement of loop / proximity links (service/mapping/link_refinement.py):
the estimate, its covariance and the accuracy check, on exact synthetic geometry."""
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose, rodrigues, rotation_angle
from mnemoslam.service.mapping.link_refinement import refine_link
from mnemoslam.service.mapping.verification import dense_information, loop_information
from mnemoslam.service.tracking.features import FrameFeatures

CAM = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


def _view(points_w, T_wc, descriptors, rng, pixel_noise, depth_noise):
    """Features of a camera at T_wc seeing world points (those in front and in the image)."""
    p = (points_w - T_wc[:3, 3]) @ T_wc[:3, :3]  # camera frame
    uv = p @ CAM.K.T
    uv = uv[:, :2] / uv[:, 2:3]
    ok = (p[:, 2] > 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    kp = uv[ok] + rng.normal(scale=pixel_noise, size=(ok.sum(), 2))
    z = p[ok, 2] * (1 + rng.normal(scale=depth_noise, size=ok.sum()))
    pts = np.column_stack([(kp[:, 0] - CAM.cx) / CAM.fx * z, (kp[:, 1] - CAM.cy) / CAM.fy * z, z])
    n = ok.sum()
    return FrameFeatures(kp.astype(np.float32), descriptors[ok], pts.astype(np.float32), np.zeros(n, np.int8))


def _scene(n, rng, spread=1.5):
    pts = np.column_stack([rng.uniform(-spread, spread, n), rng.uniform(-spread * 0.75, spread * 0.75, n),
                           rng.uniform(2.0, 4.0, n)])
    desc = rng.integers(0, 256, size=(n, 32), dtype=np.uint8)
    return pts, desc


def _error(T, T_true):
    e = invert(T_true) @ T
    return np.linalg.norm(e[:3, 3]), np.degrees(rotation_angle(e[:3, :3]))


def test_refined_link_recovers_the_true_pose_with_a_small_sigma():
    rng = np.random.default_rng(0)
    pts, desc = _scene(400, rng)
    T_w_cand = np.eye(4)
    T_w_new = make_pose(rodrigues([0.02, 0.25, -0.01]), [0.4, 0.05, 0.1])  # 0.4 m and ~14 deg apart
    cand = _view(pts, T_w_cand, desc, rng, 0.5, 0.01)
    new = _view(pts, T_w_new, desc, rng, 0.5, 0.01)
    T_true = invert(T_w_cand) @ T_w_new
    start = T_true @ make_pose(rodrigues([0.0, 0.005, 0.0]), [0.01, -0.01, 0.005])  # a PnP 1.5 cm / 0.3 deg off
    e = refine_link(CAM, new, cand, start)
    assert e.ok and e.reason == "ok" and e.inliers > 300
    dt, dr = _error(e.transform, T_true)
    assert dt < 0.005 and dr < 0.1, (dt, dr)
    assert 0 < e.sigma_translation < 0.005 and 0 < e.sigma_rotation < 0.1
    # the σ it claims is of the order of its real error (not a constant)
    assert dt < 5 * e.sigma_translation and dr < 5 * e.sigma_rotation
    # the link's information is the verification's (here 1 cm / 0.6 deg), never more confident
    # in any direction: the refinement's σ is far below the real errors of real links (issue 29)
    verified = loop_information(100)
    info = e.information(verified)
    assert np.allclose(info, info.T) and np.all(np.linalg.eigvalsh(info) > 0)
    assert np.allclose(info, verified)  # the refinement is more confident everywhere: the floor
    assert np.all(np.linalg.eigvalsh(verified - info) >= -1e-6 * np.abs(verified).max())


def test_a_refinement_less_confident_than_the_verification_loosens_the_information():
    rng = np.random.default_rng(1)
    pts, desc = _scene(25, rng, spread=0.05)  # 25 points in a 10 cm patch 2-4 m away: a large σ
    T_w_new = make_pose(rodrigues([0.0, 0.05, 0.0]), [0.2, 0.0, 0.0])
    cand = _view(pts, np.eye(4), desc, rng, 1.0, 0.02)
    new = _view(pts, T_w_new, desc, rng, 1.0, 0.02)
    e = refine_link(CAM, new, cand, T_w_new, min_inliers=20, max_sigma=(10.0, 90.0))
    verified = dense_information(0.005, 0.25)  # a dense registration's 5 mm / 0.25 deg
    info = e.information(verified)
    # never above the verification's information; below it along the directions the few
    # clustered points cannot see: there the refinement's σ (2.4 cm) is the link's
    assert np.all(np.linalg.eigvalsh(verified - info) >= -1e-6 * np.abs(verified).max())
    C = np.linalg.inv(info)
    assert e.sigma_translation > 0.01
    assert np.sqrt(np.linalg.eigvalsh(C[3:, 3:])[-1]) >= 0.99 * e.sigma_translation


def test_few_clustered_points_give_a_large_sigma_and_no_link():
    rng = np.random.default_rng(1)
    pts, desc = _scene(25, rng, spread=0.05)  # 25 points in a 10 cm patch 2-4 m away
    T_w_new = make_pose(rodrigues([0.0, 0.05, 0.0]), [0.2, 0.0, 0.0])
    cand = _view(pts, np.eye(4), desc, rng, 1.0, 0.02)
    new = _view(pts, T_w_new, desc, rng, 1.0, 0.02)
    e = refine_link(CAM, new, cand, T_w_new, min_inliers=20, max_sigma=(0.01, 0.5))
    assert not e.ok and e.reason == "inaccurate"
    assert e.sigma_translation > 0.01 or e.sigma_rotation > 0.5
    # the same geometry with bounds it does meet is accepted: the bound decides, not the count
    assert refine_link(CAM, new, cand, T_w_new, min_inliers=20, max_sigma=(10.0, 90.0)).ok


def test_too_few_matches_is_no_link():
    rng = np.random.default_rng(2)
    pts, desc = _scene(10, rng)
    cand = _view(pts, np.eye(4), desc, rng, 0.5, 0.01)
    e = refine_link(CAM, cand, cand, np.eye(4), min_inliers=20)
    assert not e.ok and e.reason == "few_matches" and e.transform is None


def test_a_link_whose_refinement_moves_it_far_is_dropped():
    """The map update's check (`Mapper._accurate`): a verified link the refinement moves by
    more than loop.link_max_disagreement (4 cm) was grossly off and is not trusted either way
    (TUM fr1/desk: a PnP link 10.3 cm off the motion capture, refined 4.6 cm to 5.9 cm off);
    one it moves by a centimetre takes the refined transform."""
    from mnemoslam.service.config import LoopConfig
    from mnemoslam.service.mapping.mapper import KeyframeUpdate, Mapper
    from mnemoslam.service.mapping.verification import Verification

    rng = np.random.default_rng(3)
    pts, desc = _scene(400, rng)
    T_w_new = make_pose(rodrigues([0.02, 0.25, -0.01]), [0.4, 0.05, 0.1])
    cand = _view(pts, np.eye(4), desc, rng, 0.5, 0.01)
    new = _view(pts, T_w_new, desc, rng, 0.5, 0.01)
    u = KeyframeUpdate(2, 1.0, T_w_new, new, None, None, None)
    mapper = Mapper(CAM, LoopConfig())
    decisions = {}
    for off in (0.01, 0.06):
        start = T_w_new @ make_pose(np.eye(3), [0.0, 0.0, off])
        v = Verification(True, "ok", 300, 300, start, loop_information(300))
        decision, out = mapper._accurate(u, 1, v, features=cand)
        decisions[off] = decision
        if decision == "ok":
            assert _error(out.transform, T_w_new)[0] < 0.005  # the refined transform
    assert decisions[0.01] == "ok", decisions
    assert decisions[0.06].startswith("rejected: inaccurate (refinement moved it"), decisions
    assert mapper.links_dropped == 1
    # without the check (0), the same link is kept at the refined transform
    mapper = Mapper(CAM, LoopConfig(link_max_disagreement=0.0))
    v = Verification(True, "ok", 300, 300, T_w_new @ make_pose(np.eye(3), [0.0, 0.0, 0.06]), loop_information(300))
    assert mapper._accurate(u, 1, v, features=cand)[0] == "ok"
    # (here it would have converged; started 5 cm off sideways it stops half-way, 2.1 cm off the
    # truth, as on fr1/desk: which of the two a far-off start gives cannot be told from the link)
