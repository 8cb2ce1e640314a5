"""Shared fixtures: the real test data in ``../shared/data`` (never copied into the repository)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

# Under pytest-xdist (the README runs two workers on two cores) each worker already has a core:
# OpenCV's and OpenBLAS's own thread pools would only contend with the other worker. One thread
# each, set before either library is imported and inherited by the commands the tests start:
# a VO test run twice at once took 43.4 s instead of 47.5 s.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _name in ("OPENCV_FOR_THREADS_NUM", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Root of the shared real data (may be absent on a user's machine)."""
    return SHARED_DATA


@pytest.fixture(scope="session")
def shared_subdir(shared_data):
    """``shared_subdir('davis2016')`` -> that folder, or skip the test saying which is missing."""

    def get(name: str) -> Path:
        folder = shared_data / name
        if not folder.is_dir():
            pytest.skip(f"real test data {folder} is absent")
        return folder

    return get


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """A small generated dynamic sequence written as a frame folder (images, masks/,
    groundtruth.txt, calib.txt), shared by the command tests. Returns (folder, scene)."""
    from data_tools.synthetic import SceneConfig, SyntheticScene, write_frames_folder

    scene = SyntheticScene(SceneConfig(width=384, height=164, n_frames=24, preset="one-large", seed=0))
    folder = write_frames_folder(scene, tmp_path_factory.mktemp("small_scene") / "frames")
    return folder, scene


@pytest.fixture(scope="session")
def render(tmp_path_factory):
    """``render(SceneConfig(...))`` -> (scene, frames): the scene and its list of
    RenderedFrame, each sequence rendered once per test run and shared by the pytest-xdist
    workers through a file (the generator is deterministic from its config; a 640 x 272 'mixed'
    or 'creep' sequence of 40 frames takes 7-10 s to render, more than the VO runs on it, and
    several tests read the same ones)."""
    import copy
    import fcntl
    import hashlib
    import pickle

    from data_tools.synthetic import SyntheticScene

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent                  # the run's folder, above each worker's own
    folder = base / "rendered"
    folder.mkdir(exist_ok=True)
    memo: dict[str, list] = {}

    def get(config):
        key = hashlib.sha1(repr(config).encode()).hexdigest()[:20]
        scene = SyntheticScene(config)
        if key not in memo:
            path = folder / f"{key}.pkl"
            with open(folder / f"{key}.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)        # one worker renders, the other waits
                if path.exists():
                    frames = pickle.loads(path.read_bytes())
                else:
                    frames = list(scene)
                    tmp = path.with_suffix(".tmp")
                    tmp.write_bytes(pickle.dumps(frames, protocol=pickle.HIGHEST_PROTOCOL))
                    tmp.replace(path)
            if len(memo) >= 4:                          # a few sequences per worker in memory
                memo.pop(next(iter(memo)))
            memo[key] = frames
        return scene, copy.deepcopy(memo[key])   # a test that paints on its frames paints alone

    return get


@pytest.fixture(scope="session")
def sequence(render):
    """``sequence(preset, seed, n_frames, width, height)`` -> what eval.vo_bench.render_sequence
    gives (scene, frames, true masks), through :func:`render`."""
    from data_tools.synthetic import SceneConfig
    from eval.vo_bench import frames_of

    def get(preset: str, seed: int, n_frames: int, width: int, height: int):
        scene, frames = render(SceneConfig(width=width, height=height, n_frames=n_frames,
                                             preset=preset, seed=seed))
        return (scene, *frames_of(frames))

    return get


@pytest.fixture(scope="session")
def mona_vo_exe():
    """The installed console script, so that tests drive the real entry point."""
    import sys

    exe = Path(sys.executable).parent / "mona-vo"
    if not exe.exists():
        pytest.skip("the mona-vo console script is not installed in this environment")
    return str(exe)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """Keep `--dist loadgroup` grouping on pytest 9.2. pytest-xdist 3.8 groups a test by
    appending "@group" to its node id through a field pytest 9.2 no longer reads (pytest-xdist
    issue 1386, open): nothing fails, the groups are simply spread over the workers. Measured
    here (stop 52): the Ray tests ran on both workers, each starting its own local cluster and
    its own 18-21 s batch. This sets the node id the way pytest 9.2 keeps it; when xdist's own
    suffix took effect it does nothing."""
    if not getattr(config.option, "loadgroup", False):
        return
    try:
        from _pytest.nodeid import NodeId
    except ImportError:          # a pytest that still reads the field xdist writes
        return
    for item in items:
        names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                        for m in item.iter_markers("xdist_group")})
        suffix = "@" + "_".join(names)
        if names and not item.nodeid.endswith(suffix) and hasattr(item, "_id"):
            item._id = NodeId.parse(item.nodeid + suffix)
