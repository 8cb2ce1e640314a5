"""mona_vo.tracking: the LK tracker's exposure compensation (auto exposure must not read as
motion, and a pan onto brighter scenery must not read as an exposure change)."""
import cv2
import numpy as np

from mona_vo.tracking import LKTracker, brightness_map, exposure_gain


def _texture(h=240, w=320, seed=0):
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.uniform(0, 1, (h, w)).astype(np.float32), (0, 0), 2.0)
    return (noise - noise.min()) / (noise.max() - noise.min())


def _grid(w, h, step=20, margin=30):
    xs, ys = np.meshgrid(np.arange(margin, w - margin, step), np.arange(margin, h - margin, step))
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)


def test_exposure_gain_measures_a_brightness_step_on_the_same_surfaces():
    tex = _texture()
    prev = np.clip(60 + 120 * tex, 0, 255).astype(np.uint8)
    now = np.clip(1.25 * (60 + 120 * np.roll(tex, 3, axis=1)), 0, 255).astype(np.uint8)
    pts = _grid(320, 240)
    assert abs(exposure_gain(brightness_map(prev), brightness_map(now), pts, pts + [3, 0]) - 1.25) < 0.02


def test_a_pan_onto_brighter_scenery_is_not_an_exposure_change():
    # Dark scenery left of column 200, bright right of it; the camera pans 80 px to the right:
    # the image mean rises by a fifth, but the surfaces seen in both frames keep their brightness.
    tex = _texture(240, 480)
    scene = (40 + 60 * tex) * np.where(np.arange(480) < 200, 1.0, 2.2)[None, :]
    prev = np.clip(scene[:, :320], 0, 255).astype(np.uint8)
    now = np.clip(scene[:, 80:400], 0, 255).astype(np.uint8)
    assert now.mean() / prev.mean() > 1.15
    pts = _grid(320, 240)
    pts = pts[pts[:, 0] >= 110]                    # points still in view after the pan
    assert abs(exposure_gain(brightness_map(prev), brightness_map(now), pts, pts - [80, 0]) - 1.0) < 0.01


def test_lk_tracks_through_an_exposure_step_only_with_gain_compensation():
    tex = _texture(seed=3)
    frames = [np.clip(50 + 140 * np.roll(tex, 2 * i, axis=1) * (1.3 if i == 2 else 1.0), 0, 255)
              .astype(np.uint8) for i in range(3)]
    results = {}
    for gain in (True, False):
        trk = LKTracker(gain=gain)
        trk.step(frames[0])
        pts = _grid(320, 240)
        ids = trk.add_points(pts)
        trk.step(frames[1])
        up = trk.step(frames[2])
        ok = up.visible & np.isin(up.ids, ids)
        err = np.linalg.norm(up.points[ok] - (pts[np.searchsorted(ids, up.ids[ok])] + [4, 0]), axis=1)
        results[gain] = (ok.mean(), float(np.median(err)) if ok.any() else np.inf)
    kept, err = results[True]
    assert kept > 0.95 and err < 0.1, results
    assert results[False][0] < kept - 0.2 or results[False][1] > 3 * err, results


def test_a_revived_track_goes_on_under_its_old_id_and_a_live_id_cannot_be_revived():
    import pytest

    img = (_texture() * 255).astype(np.uint8)
    tr = LKTracker()
    tr.step(img)
    ids = tr.add_points(_grid(320, 240))
    moved = np.roll(img, 2, axis=1)
    tr.step(moved)
    tr.remove(ids[:5])
    assert not np.isin(ids[:5], tr.live().ids).any()
    pts = _grid(320, 240)[:5] + (2.0, 0.0)
    assert tr.revive(ids[:5], pts)
    upd = tr.step(np.roll(img, 4, axis=1))
    back = np.isin(upd.ids, ids[:5]) & upd.visible
    assert back.sum() == 5
    got = upd.points[np.isin(upd.ids, ids[:5])]
    assert np.abs(got - (pts + (2.0, 0.0))).max() < 0.2
    with pytest.raises(ValueError):
        tr.revive(ids[5:6], pts[:1])
