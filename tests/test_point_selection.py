"""New-point selection: the score a new point needs adapts to weakly textured frames."""
import cv2
import numpy as np

from mona_vo.point_selection import TRACKABLE_SCORE, adaptive_min_score, grid_points, texture_score


def _texture(contrast=120.0, blur=0.0, shape=(272, 640), seed=0):
    """Smooth random texture (8-px blobs) of the given grey-level contrast, optionally blurred."""
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.uniform(0, 1, (shape[0] // 8, shape[1] // 8)).astype(np.float32),
                     shape[::-1], interpolation=cv2.INTER_CUBIC) * contrast + 128 - contrast / 2
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_a_textured_frame_keeps_the_trackable_score():
    s = texture_score(_texture())
    assert adaptive_min_score(s, 3e-5, 0.1) == TRACKABLE_SCORE


def test_a_blurred_frame_gets_its_best_corners_instead_of_almost_none():
    s = texture_score(_texture(contrast=40.0, blur=4.0))
    need = adaptive_min_score(s, 3e-5, 0.1)
    assert 3e-5 <= need < TRACKABLE_SCORE
    fixed = len(grid_points(s, 16, 16))
    adaptive = len(grid_points(s, 16, 16, min_score=need))
    assert fixed < 0.1 * 256 and adaptive > fixed + 64


def test_noise_alone_never_passes_the_floor():
    flat = np.clip(128 + np.random.default_rng(1).normal(0, 1.0, (272, 640)), 0, 255).astype(np.uint8)
    s = texture_score(flat)
    need = adaptive_min_score(s, 3e-5, 0.1)
    assert need == 3e-5
    assert len(grid_points(s, 16, 16, min_score=need)) < 0.1 * 256


def test_the_two_view_eval_seeds_the_pair_as_the_vo_seeds_its_start():
    # eval.two_view_eval measures the start pair; on a weakly textured frame its points must be
    # the ones the VO would seed there (the adaptive floor), not the fixed floor's few.
    from eval.two_view_eval import track_grid
    from mona_vo.point_selection import seed_points
    from mona_vo.vo import VOConfig

    img0 = _texture(contrast=40.0, blur=4.0)
    img1 = np.roll(img0, 2, axis=1)
    cfg = VOConfig()
    vo_points = seed_points(img0, cfg.start_grid, cfg.point_score, cfg.point_min_score,
                            cfg.point_quality)
    _, _, started = track_grid(img0, img1)
    fixed = len(grid_points(texture_score(img0, cfg.point_score), cfg.start_grid, cfg.start_grid))
    assert started == len(vo_points) > fixed + 0.25 * cfg.start_grid ** 2


def _grid_points_by_cell(score, cols, rows, border, exclude, occupied, min_score):
    """grid_points by its definition, one cell at a time (argmax's first pixel on ties)."""
    h, w = score.shape
    s = score.copy()
    if exclude is not None:
        s[exclude] = -1.0
    s[:border], s[h - border:], s[:, :border], s[:, w - border:] = -1.0, -1.0, -1.0, -1.0
    xs = np.linspace(0, w, cols + 1).astype(int)
    ys = np.linspace(0, h, rows + 1).astype(int)
    taken = np.zeros((rows, cols), bool)
    if occupied is not None and len(occupied):
        ci = np.clip(np.searchsorted(xs, occupied[:, 0], side="right") - 1, 0, cols - 1)
        ri = np.clip(np.searchsorted(ys, occupied[:, 1], side="right") - 1, 0, rows - 1)
        taken[ri, ci] = True
    out = []
    for r in range(rows):
        for c in range(cols):
            cell = s[ys[r]:ys[r + 1], xs[c]:xs[c + 1]]
            if taken[r, c] or cell.size == 0:
                continue
            cy, cx = divmod(int(np.argmax(cell)), cell.shape[1])
            if cell[cy, cx] >= min_score:
                out.append((xs[c] + cx, ys[r] + cy))
    return np.asarray(out, np.float32).reshape(-1, 2)


def test_grid_points_is_the_best_pixel_of_each_cell_ties_to_the_first():
    """The vectorised grid_points against its cell-by-cell definition: ties (quantised scores,
    flat zeros), excluded pixels, occupied cells, NaN rows, more cells than pixels."""
    rng = np.random.default_rng(0)
    for t in range(150):
        h, w = int(rng.integers(3, 200)), int(rng.integers(3, 300))
        cols, rows = int(rng.integers(1, 50)), int(rng.integers(1, 30))
        s = rng.random((h, w)).astype(np.float32) * 1e-3
        if t % 3 == 0:
            s = (np.round(s * 1e4) / 1e4).astype(np.float32)
        if t % 5 == 0:
            s[rng.random((h, w)) < 0.3] = 0.0
        if t % 7 == 0:
            s[1:3] = np.nan
        exclude = rng.random((h, w)) < 0.2 if t % 2 else None
        occupied = rng.random((int(rng.integers(0, 20)), 2)) * [w, h] if t % 4 else None
        border, min_score = int(rng.integers(0, 8)), float(rng.choice([0.0, 1e-4, 5e-4]))
        got = grid_points(s, cols, rows, border=border, exclude=exclude, occupied=occupied,
                          min_score=min_score)
        want = _grid_points_by_cell(s, cols, rows, border, exclude, occupied, min_score)
        np.testing.assert_array_equal(got, want)
