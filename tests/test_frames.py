"""data_tools.frames: opening, ordering, timestamps, streaming and the one-line input errors."""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from data_tools.frames import Frame, open_frames, timestamps_from_names
from mona_vo.errors import InputError


def write_png(path: Path, width: int = 32, height: int = 24, value: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((height, width, 3), value, np.uint8))
    return path


def make_folder(folder: Path, names, **kw) -> Path:
    for i, name in enumerate(names):
        write_png(folder / name, value=i * 10 % 256, **kw)
    return folder


def write_video(path: Path, n: int, size=(80, 64), fps: float = 10.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    assert writer.isOpened()
    for i in range(n):
        frame = np.zeros((size[1], size[0], 3), np.uint8)
        frame[:, :, 2] = 200  # red in BGR
        frame[: 8 * (i + 1), :8] = 255  # a bar whose length says which frame this is
        writer.write(frame)
    writer.release()
    return path


def test_folder_plays_in_natural_order_with_frame_numbers(tmp_path):
    src = open_frames(make_folder(tmp_path, ["frame_10.png", "frame_2.png", "frame_1.png"]))
    assert src.kind == "folder" and src.fps is None and len(src) == 3
    assert src.names == ["frame_1", "frame_2", "frame_10"]
    assert src.timestamp_kind == "frame_number" and src.timestamps == [1.0, 2.0, 10.0]
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == [1.0, 2.0, 10.0]
    assert (src.width, src.height) == (32, 24)


def test_decimal_stems_are_seconds_in_time_order(tmp_path):
    # Natural name order would put .6179 (6179) before .58438 (58438); time order must win.
    src = open_frames(make_folder(tmp_path, ["1548339827.6179.png", "1548339827.58438.png",
                                             "1548339827.65141.png"]))
    assert src.timestamp_kind == "seconds"
    assert src.names == ["1548339827.58438", "1548339827.6179", "1548339827.65141"]
    assert src.timestamps == [1548339827.58438, 1548339827.6179, 1548339827.65141]


def test_names_without_numbers_get_index_timestamps(tmp_path):
    src = open_frames(make_folder(tmp_path, ["b.jpg", "a.png", "c.bmp"]))
    assert src.timestamp_kind == "index" and src.timestamps == [0.0, 1.0, 2.0]
    assert src.names == ["a", "b", "c"]


def test_repeated_trailing_numbers_fall_back_to_index():
    values, kind = timestamps_from_names(["left_1", "right_1"])
    assert kind == "index" and values == [0.0, 1.0]


def test_stride_and_max_frames_keep_input_indices(tmp_path):
    folder = make_folder(tmp_path, [f"{i:05d}.png" for i in range(10)])
    src = open_frames(folder, stride=3)
    assert len(src) == 4 and [f.index for f in src] == [0, 3, 6, 9]
    src = open_frames(folder, stride=3, max_frames=2)
    assert len(src) == 2 and src.names == ["00000", "00003"] and src.timestamps == [0.0, 3.0]


def test_images_come_out_rgb(tmp_path):
    red_bgr = np.zeros((10, 12, 3), np.uint8)
    red_bgr[:, :, 2] = 255
    for name in ("0.png", "1.png"):
        cv2.imwrite(str(tmp_path / name), red_bgr)
    frame = next(iter(open_frames(tmp_path)))
    assert isinstance(frame, Frame)
    assert frame.image.shape == (10, 12, 3) and frame.image.dtype == np.uint8
    assert tuple(frame.image[0, 0]) == (255, 0, 0)


def test_frames_are_decoded_lazily(tmp_path):
    folder = make_folder(tmp_path, ["0.png", "1.png", "2.png"])
    src = open_frames(folder)
    it = iter(src)
    next(it)
    (folder / "2.png").write_bytes(b"")  # damaged after opening: found only when reached
    next(it)
    with pytest.raises(InputError, match=re.escape(str(folder / "2.png"))):
        next(it)


@pytest.mark.parametrize("make, fragment", [
    (lambda d: d / "nope", "no such file or folder"),
    (lambda d: (d / "a.txt").write_text("x") and d / "a.txt", "neither a folder of images nor a video"),
    (lambda d: write_png(d / "one.png"), "a single image"),
    (lambda d: d, "no images"),
    (lambda d: make_folder(d, ["0.png"]), "needs at least 2 frames"),
])
def test_bad_inputs_fail_at_open_naming_the_path(tmp_path, make, fragment):
    path = make(tmp_path)
    with pytest.raises(InputError) as err:
        open_frames(path)
    message = str(err.value)
    assert fragment in message and str(path) in message and "\n" not in message


def test_max_frames_of_one_cannot_give_a_trajectory(tmp_path):
    with pytest.raises(InputError, match="1 after stride/max_frames; a camera trajectory needs"):
        open_frames(make_folder(tmp_path, ["0.png", "1.png"]), max_frames=1)


def test_mixed_image_sizes_name_the_odd_file_and_both_sizes(tmp_path):
    make_folder(tmp_path, ["0.png", "1.png"])
    write_png(tmp_path / "2.png", width=40)
    with pytest.raises(InputError, match=r"2\.png is 40x24 but 0\.png is 32x24"):
        open_frames(tmp_path)


def test_truncated_png_fails_when_decoded_naming_the_file(tmp_path):
    make_folder(tmp_path, ["0.png"])
    data = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8))[1]
    bad = tmp_path / "1.png"
    bad.write_bytes(data.tobytes()[: data.size // 2])  # header intact, pixels cut off
    src = open_frames(tmp_path)  # the header still gives the size
    with pytest.raises(InputError, match=re.escape(f"{bad}: cannot decode image")):
        list(src)


def test_garbage_image_fails_at_open(tmp_path):
    make_folder(tmp_path, ["0.png"])
    (tmp_path / "1.png").write_bytes(b"not a png at all")
    with pytest.raises(InputError, match=r"1\.png: not a readable image"):
        open_frames(tmp_path)


def test_corrupt_video_fails_at_open(tmp_path):
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(InputError, match=re.escape(f"{bad}: cannot open video")):
        open_frames(bad)


def test_single_frame_video_cannot_give_a_trajectory(tmp_path):
    with pytest.raises(InputError, match="only 1 frame; a camera trajectory needs at least 2"):
        open_frames(write_video(tmp_path / "one.mp4", 1))


def test_mp4_video_streams_rgb_frames_with_index_timestamps(tmp_path):
    src = open_frames(write_video(tmp_path / "clip.mp4", 6))
    assert (src.kind, len(src), src.width, src.height, src.fps) == ("video", 6, 80, 64, 10.0)
    assert src.timestamp_kind == "index" and src.names[:2] == ["000000", "000001"]
    frames = list(src)
    assert [f.timestamp for f in frames] == [0.0, 1, 2, 3, 4, 5]
    assert frames[3].name == "000003"
    r, g, b = frames[0].image[40, 40].astype(int)  # away from the bar; mp4v is lossy
    assert r > 150 and g < 60 and b < 60


def test_video_stride_skips_frames(tmp_path):
    src = open_frames(write_video(tmp_path / "clip.mp4", 7), stride=3)
    frames = list(src)
    assert len(src) == 3 and [f.index for f in frames] == [0, 3, 6]
    # The bar is 8 * (index + 1) rows long: check the right frames were decoded.
    bar_rows = [int((f.image[:, 2, 0] > 230).sum()) for f in frames]
    assert bar_rows == pytest.approx([8, 32, 56], abs=3)


def test_real_tum_folder_is_in_seconds(shared_subdir):
    src = open_frames(shared_subdir("bonn_crowd") / "rgb")
    assert len(src) == 53 and (src.width, src.height) == (640, 480)
    assert src.timestamp_kind == "seconds"
    assert src.timestamps[0] == 1548339827.58438 and src.timestamps[-1] == 1548339829.32688
    assert all(a < b for a, b in zip(src.timestamps, src.timestamps[1:]))


def test_real_grey_kitti_frames_become_three_channels(shared_subdir):
    src = open_frames(shared_subdir("kitti06") / "image_0")
    frame = next(iter(src))
    assert frame.name == "000012" and frame.timestamp == 12.0
    assert frame.image.shape == (370, 1226, 3)
    assert np.array_equal(frame.image[..., 0], frame.image[..., 2])
