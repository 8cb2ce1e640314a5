"""mona_vo.patch_align: tracks fitted to their first look (an affine patch warp), the start
deformation from a camera's turn, the anchor table, and the tracker taking the corrections."""
import cv2
import numpy as np

from mona_vo.geometry import homography_jacobians
from mona_vo.patch_align import Anchors, align_patches, patch_templates, sample_exact
from mona_vo.tracking import LKTracker, Tracker


def _texture(h=240, w=320, seed=0):
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.uniform(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5)
    return (40 + 180 * (noise - noise.min()) / (noise.max() - noise.min())).astype(np.float32)


def _grid(w, h, step=24, margin=40):
    xs, ys = np.meshgrid(np.arange(margin, w - margin, step), np.arange(margin, h - margin, step))
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)


def _affine(deg, scale, shear, shift):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return scale * np.array([[c, -s], [s, c]]) @ np.array([[1.0, shear], [0.0, 1.0]]), np.asarray(shift)


def test_a_rotated_scaled_sheared_patch_is_found_to_a_fiftieth_of_a_pixel():
    ref = _texture()
    M, b = _affine(8.0, 1.08, 0.05, [3.3, -2.7])
    image = cv2.warpAffine(ref, np.c_[M, b], (320, 240), flags=cv2.INTER_CUBIC)
    # Brighter and lower-contrast, as after an exposure change.
    image = 0.8 * image + 30.0
    ref_uv = _grid(320, 240)
    truth = ref_uv @ M.T + b
    start = truth + np.random.default_rng(1).uniform(-0.8, 0.8, truth.shape)
    deform = np.tile(M, (len(ref_uv), 1, 1)) + np.random.default_rng(2).normal(0, 0.02, (len(ref_uv), 2, 2))
    templates = patch_templates(ref, ref_uv)
    p, ncc, ok = align_patches(templates, image, start, deform)
    err = np.linalg.norm(p - truth, axis=1)
    assert ok.mean() > 0.95 and np.median(ncc) > 0.99
    assert np.median(err) < 0.02 and np.percentile(err, 90) < 0.05
    # A start without the deformation finds it too at this turn (the fit has 6 degrees of
    # freedom); the VO's start from the camera's turn matters for larger ones.
    p_id, _, ok_id = align_patches(templates, image, start)
    assert ok_id.mean() > 0.95 and np.median(np.linalg.norm(p_id - truth, axis=1)) < 0.02


def test_an_unrelated_patch_correlates_poorly():
    ref, other = _texture(seed=0), _texture(seed=5)
    uv = _grid(320, 240)
    _, ncc, _ = align_patches(patch_templates(ref, uv), other, uv)
    assert np.median(ncc) < 0.8


def test_homography_jacobians_are_the_homographys_derivative():
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    R = cv2.Rodrigues(np.array([0.03, -0.05, 0.2]))[0]
    H = K @ R @ np.linalg.inv(K)
    uv = _grid(320, 240, step=60)
    J = homography_jacobians(H, uv)

    def apply(x):
        q = np.c_[x, np.ones(len(x))] @ H.T
        return q[:, :2] / q[:, 2:]

    eps = 1e-4
    for k, d in enumerate(np.eye(2)):
        num = (apply(uv + eps * d) - apply(uv - eps * d)) / (2 * eps)
        np.testing.assert_allclose(J[:, :, k], num, atol=1e-6)


def test_anchors_keep_the_first_look_and_forget_lost_tracks():
    a = Anchors(half=2)
    img0, img1 = _texture(seed=0), _texture(seed=1)
    a.add(np.array([1, 2, 3]), np.array([[10.0, 10], [20, 20], [30, 30]]), 0, img0)
    a.add(np.array([2, 3, 4]), np.array([[90.0, 90], [90, 90], [40, 40]]), 5, img1)
    assert a.ids.tolist() == [1, 2, 3, 4] and a.rows.tolist() == [0, 0, 0, 5]
    assert a.uv[1].tolist() == [20.0, 20.0]             # the first look, not the second
    np.testing.assert_allclose(a.templates[1], patch_templates(img0, [[20.0, 20.0]], 2)[0])
    a.keep(np.array([4, 7]))
    assert a.ids.tolist() == [4] and a.templates.shape == (1, 3, 25)
    np.testing.assert_allclose(a.templates[0], patch_templates(img1, [[40.0, 40.0]], 2)[0])


def test_the_lk_tracker_takes_corrections_and_tracks_on_from_them():
    tex = _texture().astype(np.uint8)
    tr = LKTracker()
    tr.step(tex)
    ids = tr.add_points(_grid(320, 240)[:5])
    assert tr.move(ids[[1, 3]], np.array([[50.5, 60.25], [70.0, 80.0]]))
    live = tr.live()
    assert live.points[1].tolist() == [50.5, 60.25] and live.points[3].tolist() == [70.0, 80.0]
    upd = tr.step(tex)                                  # a still frame: the tracks stay
    assert np.allclose(upd.points[upd.visible][1], [50.5, 60.25], atol=0.05)

    class Fixed(Tracker):                               # a back end that takes no corrections
        def step(self, image): ...
        def add_points(self, points): ...
        def remove(self, ids): ...
        def live(self): ...

    assert Fixed().move(np.zeros(0, np.int64), np.zeros((0, 2))) is False
    assert not Fixed.takes_corrections and LKTracker.takes_corrections


def test_exact_sampling_is_opencvs_sub_pixel_rectangle_and_replicates_the_border():
    """sample_exact (patch_similarity's sampler) gives what cv2.getRectSubPix gives, to float32
    rounding, also for patches that reach past the border, where cv2.remap's 1/32-pixel table
    would be off by up to a sixty-fourth of a pixel's gradient."""
    rng = np.random.default_rng(4)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (60, 80)).astype(np.float32), (0, 0), 1.0)
    half = 3
    o = np.arange(-half, half + 1, dtype=np.float64)
    dv, du = (g.ravel() for g in np.meshgrid(o, o, indexing="ij"))
    centres = np.vstack([rng.uniform(0, [79, 59], (40, 2)), [[0.3, 0.7], [78.9, 58.2], [-1.4, 30.5]]])
    got = sample_exact(image, centres[:, :1] + du, centres[:, 1:] + dv)
    want = np.stack([cv2.getRectSubPix(image, (7, 7), (float(x), float(y))).ravel()
                     for x, y in centres])
    assert np.abs(got - want).max() < 1e-3
    table = cv2.remap(image, (centres[:, :1] + du).astype(np.float32),
                      (centres[:, 1:] + dv).astype(np.float32), cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
    assert np.abs(table - want).max() > 10 * np.abs(got - want).max()
