"""Sintel files (.cam/.dpt/.flo) and sequences: real flow, round trips, layout errors."""
from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data_tools.sintel import SintelSequence, list_sequences, write_sintel_frame
from data_tools.sintel_formats import read_cam, read_dpt, read_flo, write_cam, write_dpt, write_flo
from mona_vo.conventions import Intrinsics, invert_pose, make_pose
from mona_vo.errors import InputError

INTR = Intrinsics(40.0, 41.0, 15.5, 11.5)
W, H = 32, 24


def pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_pose(Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3))


def write_sequence(root, seq="alley_9", n=3, passes=("clean",), masks=True):
    rng = np.random.default_rng(7)
    written = []
    for k in range(1, n + 1):
        image = rng.integers(0, 256, (H, W, 3), np.uint8)
        depth = rng.uniform(1, 10, (H, W)).astype(np.float32)
        mask = np.zeros((H, W), bool)
        mask[k:k + 5, 3:9] = True
        write_sintel_frame(root, seq, k, image, INTR, pose(k), passes=passes, depth=depth,
                           mask=mask if masks else None)
        written.append((image, depth, mask))
    return written


# --- files --------------------------------------------------------------------------------------

def test_real_sintel_flow(shared_subdir):
    flow = read_flo(shared_subdir("sintel_clip_alley") / "training/flow/alley_1/frame_0002.flo")
    assert flow.shape == (436, 1024, 2) and flow.dtype == np.float32
    assert np.linalg.norm(flow, axis=2).mean() == pytest.approx(2.98, abs=0.01)


def test_cam_round_trip_stores_world_to_camera(tmp_path):
    T_world_cam = pose(1)
    path = tmp_path / "frame_0001.cam"
    write_cam(path, INTR, T_world_cam)
    intr, T = read_cam(path)
    assert intr == INTR
    np.testing.assert_allclose(T, T_world_cam, atol=1e-12)
    # On disk: tag, K (9 float64), then the world-to-camera 3x4 (12 float64).
    stored = np.frombuffer(path.read_bytes(), "<f8", 12, offset=4 + 72).reshape(3, 4)
    np.testing.assert_allclose(stored, invert_pose(T_world_cam)[:3], atol=1e-12)


def test_dpt_and_flo_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 80, (5, 7)).astype(np.float32)
    flow = rng.normal(size=(5, 7, 2)).astype(np.float32)
    write_dpt(tmp_path / "d.dpt", depth)
    write_flo(tmp_path / "f.flo", flow)
    assert np.array_equal(read_dpt(tmp_path / "d.dpt"), depth)
    assert np.array_equal(read_flo(tmp_path / "f.flo"), flow)


@pytest.mark.parametrize("reader, name", [(read_cam, "x.cam"), (read_dpt, "x.dpt"), (read_flo, "x.flo")])
def test_wrong_tag_and_short_files_name_the_file(tmp_path, reader, name):
    path = tmp_path / name
    path.write_bytes(np.array([1.0] * 50, "<f4").tobytes())
    with pytest.raises(InputError, match=re.escape(f"{path}: wrong tag")):
        reader(path)
    path.write_bytes(np.array([202021.25], "<f4").tobytes() + b"\x01\x00")
    with pytest.raises(InputError, match=re.escape(f"{path}: truncated")):
        reader(path)
    path.write_bytes(b"\x00")
    with pytest.raises(InputError, match=re.escape(f"{path}: too short")):
        reader(path)


# --- sequences ----------------------------------------------------------------------------------

def test_written_sequence_reads_back_with_the_written_poses(tmp_path):
    written = write_sequence(tmp_path, passes=("clean", "final"))
    seq = SintelSequence(tmp_path, "alley_9")  # pass 'final' by default
    assert seq.names == ["frame_0001", "frame_0002", "frame_0003"] and len(seq) == 3
    stamps, poses = seq.groundtruth()
    assert list(stamps) == [1.0, 2.0, 3.0]
    np.testing.assert_allclose(poses, np.stack([pose(k) for k in (1, 2, 3)]), atol=1e-12)
    assert seq.intrinsics() == [INTR] * 3
    assert np.array_equal(seq.depth(1), written[1][1])
    frames = list(seq.frames())
    assert [f.timestamp for f in frames] == [1.0, 2.0, 3.0]
    assert all(np.array_equal(f.image, w[0]) for f, w in zip(frames, written))
    assert seq.has_masks
    masks = seq.masks(size=(W, H))
    assert len(masks) == 3 and all(np.array_equal(m, w[2]) for m, w in zip(masks, written))
    clean = next(iter(SintelSequence(tmp_path, "alley_9", "clean").frames()))
    assert np.array_equal(clean.image, written[0][0])
    assert list_sequences(tmp_path) == ["alley_9"]


def test_real_clip_without_camera_data_is_refused(shared_subdir):
    root = shared_subdir("sintel_clip_alley")
    assert list_sequences(root, "clean") == ["alley_1"]
    with pytest.raises(InputError, match="camdata_left/alley_1: camera data missing"):
        SintelSequence(root, "alley_1", "clean")


def test_layout_errors_name_the_path(tmp_path):
    with pytest.raises(InputError, match=re.escape(f"{tmp_path}: no training/final folder")):
        SintelSequence(tmp_path, "alley_9")
    write_sequence(tmp_path, passes=("final",), masks=False)
    with pytest.raises(InputError, match=r"final/cave_2: no such sequence \(training/final has alley_9\)"):
        SintelSequence(tmp_path, "cave_2")
    missing = tmp_path / "training/camdata_left/alley_9/frame_0002.cam"
    missing.unlink()
    with pytest.raises(InputError, match=re.escape(f"{missing}: no camera file for frame frame_0002")):
        SintelSequence(tmp_path, "alley_9")


def test_missing_depth_and_masks_are_input_errors(tmp_path):
    write_sequence(tmp_path, passes=("final",), masks=False)
    seq = SintelSequence(tmp_path, "alley_9")
    assert not seq.has_masks
    with pytest.raises(InputError, match="mask folder not found"):
        seq.masks()
    (tmp_path / "training/depth/alley_9/frame_0001.dpt").unlink()
    with pytest.raises(InputError, match="frame_0001.dpt: file not found"):
        seq.depth(0)
