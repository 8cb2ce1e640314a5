"""mona_vo.vo_map: the VO's state as arrays (landmarks by id with flags, keyframes with all their
observations, frames whose status is written once)."""
import numpy as np
import pytest

from mona_vo.conventions import Intrinsics, make_pose
from mona_vo.vo_map import FrameStatus, LandmarkFlag, LandmarkTable, VOMap

INTR = Intrinsics(500.0, 500.0, 320.0, 240.0)


def test_landmarks_are_usable_only_when_triangulated_and_never_flagged():
    lm = LandmarkTable()
    lm.set_positions(np.array([3, 7]), np.array([[0, 0, 5.0], [1, 0, 6.0]]))
    ids = np.array([1, 3, 7, 900])
    assert lm.has_position(ids).tolist() == [False, True, True, False]
    assert lm.flag(np.array([7, 7, 1]), LandmarkFlag.MASKED) == 2   # 7 and 1 newly flagged
    assert lm.flag(np.array([7]), LandmarkFlag.DYNAMIC) == 0
    assert lm.usable(ids).tolist() == [False, True, False, False]
    assert lm.flagged(ids).tolist() == [True, False, True, False]
    assert lm.flags[7] == LandmarkFlag.MASKED | LandmarkFlag.DYNAMIC
    np.testing.assert_array_equal(lm.positions(np.array([7])), [[1, 0, 6.0]])  # kept for the record
    assert lm.n_usable == 1


def test_keyframe_table_keeps_every_keyframes_observations_in_order():
    m = VOMap()
    for k in range(70):   # past the first capacity, so the arrays grow
        n = 3 + k % 4
        m.keyframes.add(10 * k, make_pose(np.eye(3), [k, 0, 0]), INTR, 0, np.arange(n) + k,
                        np.full((n, 2), float(k)), np.arange(n) == 0)
    kf = m.keyframes
    assert kf.n == 70 and kf.frame[:kf.n].tolist() == [10 * k for k in range(70)]
    ids, uv, masked = kf.observations(65)
    assert ids.tolist() == list(range(65, 65 + 3 + 65 % 4)) and np.all(uv == 65.0)
    assert masked.tolist() == [True] + [False] * (len(ids) - 1)
    rows = kf.observation_rows([2, 65])
    assert rows.tolist() == [2] * (3 + 2) + [65] * (3 + 65 % 4)
    assert kf.intrinsics(5) == INTR
    m.window = [68, 69]
    r, lm_ids, _, _ = m.window_observations()
    assert set(r.tolist()) == {68, 69} and len(lm_ids) == len(r) == (3 + 0) + (3 + 1)


def test_frame_status_is_written_once_and_relative_poses_follow_their_keyframe():
    m = VOMap()
    for t in range(3):
        m.frames.append(float(t))
    row = m.keyframes.add(0, make_pose(np.eye(3), [1, 0, 0]), INTR, 0, np.zeros(0, np.int64),
                          np.zeros((0, 2)), np.zeros(0, bool))
    m.frames.write(0, FrameStatus.KEYFRAME, 50, ref_kf=row, T=np.eye(4))
    m.frames.write(1, FrameStatus.TRACKED, 40, ref_kf=row, T=make_pose(np.eye(3), [0, 0, 1]))
    m.frames.write(2, FrameStatus.ROTATION_ONLY, 0, T=make_pose(np.eye(3), [0, 0, 0]))
    with pytest.raises(RuntimeError, match="already written"):
        m.frames.write(1, FrameStatus.BOOTSTRAP, 40, ref_kf=row, T=np.eye(4))
    m.keyframes.T_world_cam[row] = make_pose(np.eye(3), [5, 0, 0])   # a BA moved the keyframe
    P = m.all_poses()
    np.testing.assert_allclose(P[1][:3, 3], [5, 0, 1])
    np.testing.assert_allclose(P[2], np.eye(4))       # absolute poses stay put
    assert m.frames.status_of(1) is FrameStatus.TRACKED


def test_an_attached_frame_keeps_its_pose_and_status_then_follows_its_keyframe():
    # A frame written with an absolute pose (extrapolated where tracking was lost) that becomes
    # a new map's first keyframe must move with it when a refinement moves the keyframes.
    m = VOMap()
    m.frames.append(0.0)
    T_frame = make_pose(np.eye(3), [0.5, 0.2, 0.1])
    m.frames.write(0, FrameStatus.EXTRAPOLATED, 0, T=T_frame)
    T_kf = make_pose(np.eye(3), [0.5, 0.0, 0.0])
    row = m.keyframes.add(0, T_kf, INTR, 1, np.zeros(0, np.int64), np.zeros((0, 2)),
                          np.zeros(0, bool))
    m.frames.attach(0, row, T_kf)
    np.testing.assert_allclose(m.all_poses()[0], T_frame, atol=1e-12)
    assert m.frames.status_of(0) is FrameStatus.EXTRAPOLATED
    m.keyframes.T_world_cam[row] = make_pose(np.eye(3), [2.5, 0.0, 0.0])
    np.testing.assert_allclose(m.pose_of(0)[:3, 3], [2.5, 0.2, 0.1])
    with pytest.raises(RuntimeError, match="absolute pose"):
        m.frames.attach(0, row, T_kf)      # already relative


def test_frame_observations_come_back_grouped_by_frame_and_a_reposed_frame_keeps_its_status():
    m = VOMap()
    k = m.keyframes.add(0, np.eye(4), Intrinsics(500, 500, 320, 240), 0, np.arange(3),
                        np.zeros((3, 2)), np.zeros(3, bool))
    for t in range(3):
        m.frames.append(float(t))
    m.frames.write(2, FrameStatus.TRACKED, 30, ref_kf=k, T=np.eye(4))
    m.frames.add_observations(2, np.array([5, 6]), np.array([[1.0, 2.0], [3.0, 4.0]]))
    m.frames.add_observations(1, np.array([7]), np.array([[5.0, 6.0]]))
    groups = list(m.frames.observation_groups())
    assert [g[0] for g in groups] == [1, 2]
    assert groups[1][1].tolist() == [5, 6] and groups[1][2].tolist() == [[1, 2], [3, 4]]
    moved = make_pose(np.eye(3), [0.1, 0, 0])
    m.frames.repose(2, moved)
    np.testing.assert_allclose(m.pose_of(2), moved)
    assert m.frames.status_of(2) is FrameStatus.TRACKED
    m.frames.write(1, FrameStatus.ROTATION_ONLY, 0, T=np.eye(4))
    with pytest.raises(RuntimeError):
        m.frames.repose(1, moved)        # absolute poses are not re-posed


def test_only_a_rotation_only_frame_can_be_backfilled_and_it_becomes_extrapolated():
    m = VOMap()
    for t in range(2):
        m.frames.append(float(t))
    m.frames.write(0, FrameStatus.ROTATION_ONLY, 0, T=np.eye(4))
    m.frames.write(1, FrameStatus.TRACKED, 30, T=np.eye(4))
    T = make_pose(np.eye(3), [0.0, 0.0, -0.3])
    m.frames.backfill(0, T)
    assert m.frames.status_of(0) is FrameStatus.EXTRAPOLATED
    np.testing.assert_allclose(m.pose_of(0), T)
    with pytest.raises(RuntimeError, match="rotation-only"):
        m.frames.backfill(1, T)
    with pytest.raises(RuntimeError, match="rotation-only"):
        m.frames.backfill(0, T)       # once only
