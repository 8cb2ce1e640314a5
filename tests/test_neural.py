"""Neural back ends (mona_vo.neural): plumbing checked with RANDOM weights, nothing downloaded.

Each network is built from a checkpoint file that the test writes (a random state dict or model),
so the real loading path runs; outputs are checked for shape, dtype and coordinate conventions,
not for quality. Tests that need a network package skip, saying which, when it is absent (the main
venv has none of them; ``.ci/neural`` runs them all in ``.venv-neural``). The missing-checkpoint
tests need no torch and run everywhere.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mona_vo.detection import DETECTORS, Boxes
from mona_vo.errors import BackendError
from mona_vo.flow import FLOWS
from mona_vo.neural.cotracker import CoTrackerTracker
from mona_vo.neural.raft import RaftFlow
from mona_vo.neural.sam import SamSegmenter
from mona_vo.neural.weights import WEIGHT_FILES, WEIGHTS_ENV, resolve_checkpoint
from mona_vo.neural.yolo import COCO_GROUPS, YoloDetector
from mona_vo.segmentation import SEGMENTERS

REPO = Path(__file__).resolve().parents[1]
H, W = 60, 90        # small test frames; neither side a multiple of 8, both under RAFT's 128


def textured(seed: int, h: int = H, w: int = W) -> np.ndarray:
    """(h, w, 3) uint8 RGB: smooth random blobs (seeded), so networks see structure."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 6 + 2, w // 6 + 2, 3)).astype(np.float32)
    import cv2

    return np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------- checkpoints (no torch needed)

BACKENDS = [
    pytest.param(RaftFlow, {}, "raft_large_C_T_SKHT_V2-ff5fadd5.pth", id="raft"),
    pytest.param(RaftFlow, {"model": "small"}, "raft_small_C_T_V2-01064c6d.pth", id="raft-small"),
    pytest.param(YoloDetector, {}, "yolo11n.pt", id="yolo"),
    pytest.param(SamSegmenter, {}, "sam_vit_b_01ec64.pth", id="sam"),
    pytest.param(SamSegmenter, {"model_type": "vit_h"}, "sam_vit_h_4b8939.pth", id="sam-vit-h"),
    pytest.param(CoTrackerTracker, {}, "scaled_offline.pth", id="cotracker"),
]


def _one_line_naming(exc: BackendError, filename: str) -> str:
    msg = str(exc)
    assert "\n" not in msg
    assert filename in msg
    assert "https://" in msg
    assert WEIGHTS_ENV in msg
    return msg


@pytest.mark.parametrize("cls, kwargs, filename", BACKENDS)
def test_missing_checkpoint_without_weights_folder_says_what_to_download(monkeypatch, cls, kwargs,
                                                                         filename):
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    with pytest.raises(BackendError) as info:
        cls(**kwargs)
    url = next(w.url for w in WEIGHT_FILES.values() if w.name == filename)
    assert url in _one_line_naming(info.value, filename)


@pytest.mark.parametrize("cls, kwargs, filename", BACKENDS)
def test_missing_checkpoint_in_weights_folder_names_the_expected_path(monkeypatch, tmp_path, cls,
                                                                      kwargs, filename):
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path))
    with pytest.raises(BackendError) as info:
        cls(**kwargs)
    assert str(tmp_path / filename) in _one_line_naming(info.value, filename)


@pytest.mark.parametrize("cls, kwargs, filename", BACKENDS)
def test_missing_explicit_checkpoint_names_the_given_path(monkeypatch, tmp_path, cls, kwargs,
                                                          filename):
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path))
    given = tmp_path / "elsewhere" / "my-weights.pth"
    with pytest.raises(BackendError) as info:
        cls(checkpoint=given, **kwargs)
    assert str(given) in _one_line_naming(info.value, filename)


def test_checkpoint_found_as_file_as_folder_and_through_the_weights_folder(monkeypatch, tmp_path):
    name = WEIGHT_FILES["yolo"].name
    (tmp_path / name).write_bytes(b"x")
    other = tmp_path / "custom.pt"
    other.write_bytes(b"x")
    assert resolve_checkpoint("yolo", other) == other
    assert resolve_checkpoint("yolo", tmp_path) == tmp_path / name
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path))
    assert resolve_checkpoint("yolo") == tmp_path / name
    assert resolve_checkpoint("yolo", str(other)) == other    # an explicit path wins


def test_documented_file_names_are_the_download_file_names():
    for weight in WEIGHT_FILES.values():
        assert weight.url.startswith("https://")
        assert weight.url.rsplit("/", 1)[-1] == weight.name


def test_registry_names_load_the_neural_classes():
    assert FLOWS.get("raft") is RaftFlow
    assert DETECTORS.get("yolo") is YoloDetector
    assert SEGMENTERS.get("sam") is SamSegmenter


def test_importing_the_neural_modules_imports_no_network_package():
    code = ("import sys, mona_vo.neural.raft, mona_vo.neural.yolo, mona_vo.neural.sam, "
            "mona_vo.neural.cotracker, mona_vo.neural.weights\n"
            "heavy = [m for m in ('torch', 'torchvision', 'ultralytics', 'segment_anything', "
            "'cotracker') if m in sys.modules]\n"
            "assert not heavy, heavy")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


# ---------------------------------------------------------------- devices (torch only)

def test_device_names_are_checked():
    torch = pytest.importorskip("torch", reason="torch is not installed")
    from mona_vo.neural import torch_device

    assert torch_device("cpu", "test") == torch.device("cpu")
    with pytest.raises(BackendError, match="unknown device 'mps'"):
        torch_device("mps", "test")
    if not torch.cuda.is_available():
        with pytest.raises(BackendError, match="no CUDA GPU"):
            torch_device("cuda", "test")


# ---------------------------------------------------------------- CoTracker window (torch only)

class FakeCoTracker:
    """CoTrackerPredictor's contract with exact answers: every point moves by ``velocity``
    pixels per frame; points right of ``hide_x`` are not visible. Records its queries."""

    def __init__(self, velocity=(1.5, -0.5), hide_x=1e9):
        self.velocity = np.asarray(velocity, np.float32)
        self.hide_x = hide_x
        self.calls = []

    def __call__(self, video, queries):
        import torch

        assert video.dtype == torch.float32 and video.ndim == 5 and video.shape[2] == 3
        assert float(video.max()) <= 255.0
        q = queries[0].cpu().numpy()
        T = video.shape[1]
        self.calls.append((T, q.copy()))
        t = np.arange(T, dtype=np.float32)[:, None, None]                 # (T, 1, 1)
        tracks = q[None, :, 1:] + (t - q[None, :, :1]) * self.velocity    # (T, N, 2)
        vis = tracks[..., 0] <= self.hide_x
        return torch.from_numpy(tracks[None].astype(np.float32)), torch.from_numpy(vis[None])


def test_cotracker_window_follows_points_and_requeries_old_tracks_at_window_start():
    pytest.importorskip("torch", reason="torch is not installed")
    fake = FakeCoTracker()
    tracker = CoTrackerTracker(predictor=fake, window=4)
    first = tracker.step(textured(0))
    assert len(first.ids) == 0
    p0 = np.array([[20.0, 30.0], [40.5, 25.25]], np.float32)
    ids = tracker.add_points(p0)
    assert ids.dtype == np.int64 and len(set(ids.tolist())) == 2
    for t in range(1, 10):
        upd = tracker.step(textured(t))
        assert upd.ids.tolist() == ids.tolist()
        assert upd.points.shape == (2, 2) and upd.points.dtype == np.float32
        assert upd.visible.dtype == bool and upd.visible.all()
        assert upd.error.shape == (2,) and upd.error.dtype == np.float32
        np.testing.assert_allclose(upd.points, p0 + t * fake.velocity, atol=1e-4)
        np.testing.assert_allclose(upd.error, 0.0, atol=1e-4)
    # Frame 9 with a window of 4: the clip is frames 6..9 and the tracks (added at frame 0) are
    # queried at the clip's first frame, where they were last estimated.
    T, q = fake.calls[-1]
    assert T == 4
    np.testing.assert_allclose(q[:, 0], 0)
    np.testing.assert_allclose(q[:, 1:], p0 + 6 * fake.velocity, atol=1e-4)
    np.testing.assert_allclose(tracker.live().points, p0 + 9 * fake.velocity, atol=1e-4)


def test_cotracker_queries_new_tracks_at_the_frame_they_were_added():
    pytest.importorskip("torch", reason="torch is not installed")
    fake = FakeCoTracker(velocity=(0.0, 1.0))
    tracker = CoTrackerTracker(predictor=fake, window=8)
    tracker.step(textured(0))
    old = tracker.add_points(np.array([[10.0, 10.0]], np.float32))
    tracker.step(textured(1))
    tracker.step(textured(2))
    new = tracker.add_points(np.array([[50.0, 20.0]], np.float32))
    upd = tracker.step(textured(3))
    T, q = fake.calls[-1]
    assert T == 4
    np.testing.assert_allclose(q, [[0, 10, 10], [2, 50, 20]])
    assert upd.ids.tolist() == [old[0], new[0]]
    np.testing.assert_allclose(upd.points, [[10, 13], [50, 21]], atol=1e-4)


def test_cotracker_reports_an_invisible_or_outside_track_once_then_forgets_it():
    pytest.importorskip("torch", reason="torch is not installed")
    tracker = CoTrackerTracker(predictor=FakeCoTracker(velocity=(4.0, 0.0), hide_x=40.0), window=3)
    tracker.step(textured(0))
    ids = tracker.add_points(np.array([[10.0, 10.0], [33.0, 20.0], [80.0, 30.0]], np.float32))
    upd = tracker.step(textured(1))       # x: 14 visible; 37 visible; 84 hidden (> 40)
    assert upd.visible.tolist() == [True, True, False]
    assert tracker.live().ids.tolist() == ids[:2].tolist()
    upd = tracker.step(textured(2))       # x: 18 visible; 41 hidden
    assert upd.ids.tolist() == ids[:2].tolist() and upd.visible.tolist() == [True, False]
    tracker.remove(ids[:1])
    assert len(tracker.live().ids) == 0
    assert len(tracker.step(textured(3)).ids) == 0


def test_cotracker_accepts_grey_frames_and_leaves_the_image_with_visible_false():
    pytest.importorskip("torch", reason="torch is not installed")
    tracker = CoTrackerTracker(predictor=FakeCoTracker(velocity=(30.0, 0.0)), window=2)
    grey = textured(0)[..., 0]
    tracker.step(grey)
    tracker.add_points(np.array([[50.0, 30.0]], np.float32))
    assert tracker.step(grey).visible.tolist() == [True]     # x = 80 < W - 0.5
    assert tracker.step(grey).visible.tolist() == [False]    # x = 110: outside


# ---------------------------------------------------------------- RAFT (torchvision)

@pytest.fixture(scope="module")
def raft_checkpoint(tmp_path_factory):
    """A random torchvision raft_large state dict saved under its documented file name."""
    pytest.importorskip("torchvision", reason="torchvision is not installed (neural extra)")
    import torch
    from torchvision.models.optical_flow import raft_large

    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("raft")
    path = folder / WEIGHT_FILES["raft_large"].name
    torch.save(raft_large(weights=None, progress=False).state_dict(), path)
    return path


@pytest.fixture(scope="module")
def raft(raft_checkpoint):
    return RaftFlow(checkpoint=raft_checkpoint, device="cpu", iterations=2)


def test_raft_flow_is_hw2_float32_finite_on_small_odd_sized_frames(raft):
    flow = raft.compute(textured(1), textured(2))
    assert flow.shape == (H, W, 2) and flow.dtype == np.float32
    assert np.isfinite(flow).all()


def test_raft_is_built_by_registry_name_from_the_weights_folder(monkeypatch, raft_checkpoint):
    monkeypatch.setenv(WEIGHTS_ENV, str(raft_checkpoint.parent))
    flow = FLOWS.create("raft", device="cpu")        # how mona_vo.masks builds a neural back end
    assert isinstance(flow, RaftFlow) and flow.checkpoint == raft_checkpoint


def test_raft_passes_image0_first_and_returns_u_as_x_v_as_y_cropped(raft):
    """The plumbing around the network, with a stand-in whose answer is known: it returns
    u = column and v = 10 * row of the padded input, and records what it was given."""
    import torch

    seen = {}

    def stand_in(img1, img2, num_flow_updates):
        seen["img1"], seen["img2"], seen["iters"] = img1, img2, num_flow_updates
        n, _, h, w = img1.shape
        assert h % 8 == 0 and w % 8 == 0 and h >= 128 and w >= 128
        ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        return [torch.stack([xs, 10 * ys]).float()[None].repeat(n, 1, 1, 1)]

    real, raft._model = raft._model, stand_in
    try:
        a, b = textured(3), textured(4)
        flow = raft.compute(a, b)
    finally:
        raft._model = real
    left, _, top, _ = RaftFlow.padding(H, W)
    rows, cols = np.mgrid[0:H, 0:W]
    np.testing.assert_array_equal(flow[..., 0], cols + left)
    np.testing.assert_array_equal(flow[..., 1], 10 * (rows + top))
    crop = (0, slice(None), slice(top, top + H), slice(left, left + W))
    np.testing.assert_allclose(seen["img1"][crop].permute(1, 2, 0).numpy(), a / 127.5 - 1, atol=1e-6)
    np.testing.assert_allclose(seen["img2"][crop].permute(1, 2, 0).numpy(), b / 127.5 - 1, atol=1e-6)
    assert seen["iters"] == 2


def test_raft_rejects_a_checkpoint_of_the_other_model_size(tmp_path, raft_checkpoint):
    with pytest.raises(BackendError, match="does not fit"):
        RaftFlow(checkpoint=raft_checkpoint, model="small")


# ---------------------------------------------------------------- YOLO (ultralytics)

@pytest.fixture(scope="module")
def yolo_checkpoint(tmp_path_factory):
    """A random YOLO11n detection model with COCO class names, its class biases raised so that
    it proposes boxes, saved as an Ultralytics checkpoint under its documented file name."""
    folder = tmp_path_factory.mktemp("yolo")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("YOLO_OFFLINE", "1")
        if "YOLO_CONFIG_DIR" not in os.environ:        # Ultralytics writes settings on import
            mp.setenv("YOLO_CONFIG_DIR", str(folder))
        pytest.importorskip("ultralytics", reason="ultralytics is not installed (neural extra)")
        import torch
        from ultralytics.nn.tasks import DetectionModel
        from ultralytics.utils import ROOT, YAML

        torch.manual_seed(0)
        model = DetectionModel("yolo11n.yaml", nc=80, verbose=False)
        model.names = YAML.load(ROOT / "cfg/datasets/coco.yaml")["names"]
        for branch in model.model[-1].cv3:             # class logits: sigmoid(3) = 0.95
            branch[-1].bias.data.fill_(3.0)
        path = folder / WEIGHT_FILES["yolo"].name
        torch.save({"model": model, "train_args": {}}, path)
        yield path


def _check_boxes(boxes: Boxes, h: int, w: int) -> None:
    assert isinstance(boxes, Boxes)
    assert boxes.xyxy.dtype == np.float32 and boxes.xyxy.shape == (len(boxes), 4)
    assert boxes.score.dtype == np.float32 and boxes.score.shape == (len(boxes),)
    assert len(boxes.label) == len(boxes) and all(isinstance(s, str) for s in boxes.label.tolist())
    x0, y0, x1, y1 = boxes.xyxy.T
    assert (x0 <= x1).all() and (y0 <= y1).all()
    assert (x0 >= -0.5).all() and (x1 <= w - 0.5).all()
    assert (y0 >= -0.5).all() and (y1 <= h - 0.5).all()
    assert ((boxes.score >= 0) & (boxes.score <= 1)).all()


def test_yolo_boxes_are_ordered_inside_the_image_with_scores_and_names(yolo_checkpoint):
    det = YoloDetector(checkpoint=yolo_checkpoint, device="cpu", classes=None)
    boxes = det.detect(textured(5))
    assert len(boxes) > 0
    _check_boxes(boxes, H, W)
    assert set(boxes.label.tolist()) <= set(det.names.values())


def test_yolo_boxes_are_the_networks_shifted_to_pixel_centre_coordinates(yolo_checkpoint):
    det = YoloDetector(checkpoint=yolo_checkpoint, classes=None, max_det=20)
    image = textured(6)
    boxes = det.detect(image)
    raw = det._model.predict(np.ascontiguousarray(image[..., ::-1]), conf=det.conf, iou=det.iou,
                             imgsz=det.imgsz, max_det=20, device="cpu", verbose=False)[0]
    expect = raw.boxes.xyxy.cpu().numpy() - 0.5
    expect[:, [0, 2]] = np.clip(expect[:, [0, 2]], -0.5, W - 0.5)
    expect[:, [1, 3]] = np.clip(expect[:, [1, 3]], -0.5, H - 0.5)
    np.testing.assert_allclose(boxes.xyxy, expect, atol=1e-4)


def test_yolo_class_filter_keeps_only_the_chosen_groups(monkeypatch, yolo_checkpoint):
    monkeypatch.setenv(WEIGHTS_ENV, str(yolo_checkpoint.parent))
    people = DETECTORS.create("yolo", device="cpu")    # as mona_vo.masks builds it
    assert people.class_ids == sorted(sum(COCO_GROUPS.values(), ()))
    only = YoloDetector(classes=["people", "dog"])
    assert only.class_ids == [0, 16]
    boxes = YoloDetector(classes=["vehicles"]).detect(textured(7))
    _check_boxes(boxes, H, W)
    allowed = {only.names[i] for i in COCO_GROUPS["vehicles"]}
    assert set(boxes.label.tolist()) <= allowed
    with pytest.raises(BackendError, match="neither a group"):
        YoloDetector(classes=["unicorn"])


# ---------------------------------------------------------------- SAM (segment-anything)

@pytest.fixture(scope="module")
def sam(tmp_path_factory):
    """A SamSegmenter built from a random ViT-B state dict (the file, 375 MB, is deleted once
    loaded)."""
    pytest.importorskip("segment_anything", reason="segment-anything is not installed (neural extra)")
    import torch
    from segment_anything import sam_model_registry

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("sam") / WEIGHT_FILES["sam_vit_b"].name
    torch.save(sam_model_registry["vit_b"]().state_dict(), path)
    try:
        seg = SamSegmenter(checkpoint=path, device="cpu", dilate_px=0)
    finally:
        path.unlink()
    calls = {"set_image": 0, "boxes": []}
    predictor = seg._predictor
    set_image, predict_torch = predictor.set_image, predictor.predict_torch

    def counting_set_image(*args, **kwargs):
        calls["set_image"] += 1
        return set_image(*args, **kwargs)

    def recording_predict(*args, **kwargs):
        if kwargs.get("boxes") is not None:
            calls["boxes"].append(kwargs["boxes"].cpu().numpy())
        return predict_torch(*args, **kwargs)

    predictor.set_image, predictor.predict_torch = counting_set_image, recording_predict
    seg.test_calls = calls
    return seg


def test_sam_box_prompt_gives_an_image_sized_bool_mask_with_sam_box_convention(sam):
    image = textured(8)
    boxes = Boxes.from_arrays([[9.5, 14.5, 40.5, 50.5], [-0.5, -0.5, 20.5, 10.5]], [0.9, 0.8])
    mask = sam.segment(image, boxes)
    assert mask.shape == (H, W) and mask.dtype == bool
    # SAM gets the first/last pixel indices, scaled to its 1024-pixel input.
    scale = 1024 / max(H, W)
    sent = sam.test_calls["boxes"][-1] / scale
    np.testing.assert_allclose(sent, [[10, 15, 40, 50], [0, 0, 20, 10]], atol=0.1)


def test_sam_point_prompts_give_a_mask_and_reuse_the_frames_embedding(sam):
    image = textured(8)              # the frame of the box test: its embedding may be cached
    sam.segment(image, Boxes.from_arrays([[10, 10, 30, 30]]))
    before = sam.test_calls["set_image"]
    mask = sam.segment(image, None, np.array([[20.0, 30.0], [60.0, 40.0]], np.float32))
    assert mask.shape == (H, W) and mask.dtype == bool
    assert sam.test_calls["set_image"] == before             # one embedding per frame
    sam.segment(image.copy(), Boxes.from_arrays([[0, 0, 5, 5]]))
    assert sam.test_calls["set_image"] == before             # the same pixels, another array


def test_sam_without_prompts_is_empty_and_costs_no_embedding(sam):
    before = sam.test_calls["set_image"]
    mask = sam.segment(textured(10), Boxes.empty(), None)
    assert mask.shape == (H, W) and mask.dtype == bool and not mask.any()
    assert sam.test_calls["set_image"] == before


# ---------------------------------------------------------------- CoTracker (cotracker package)

def test_cotracker_network_tracks_have_the_interface_shapes(tmp_path):
    pytest.importorskip("cotracker", reason="cotracker is not installed (not on PyPI: "
                                            "facebookresearch/co-tracker)")
    import torch
    from cotracker.models.build_cotracker import build_cotracker

    torch.manual_seed(0)
    path = tmp_path / WEIGHT_FILES["cotracker"].name
    torch.save(build_cotracker(checkpoint=None, offline=True, window_len=60).state_dict(), path)
    tracker = CoTrackerTracker(checkpoint=path, device="cpu", window=3)
    tracker.step(textured(11))
    ids = tracker.add_points(np.array([[20.0, 20.0], [60.0, 40.0]], np.float32))
    for t in range(12, 15):
        upd = tracker.step(textured(t))
        assert upd.points.dtype == np.float32 and upd.points.shape == (len(upd.ids), 2)
        assert upd.visible.dtype == bool and upd.error.dtype == np.float32
        assert set(upd.ids.tolist()) <= set(ids.tolist())
