"""``mona-vo batch``: many videos through :func:`mona_vo.run.run`, one Ray task per input.

The engine is Ray: without an address an embedded local Ray is started in this process on this
machine's cores (nothing to install or start by hand); with ``address`` ("auto" or HOST:PORT) the
batch joins an existing cluster. Every input is one task that calls ``run`` exactly as the
``run`` command does, so ``DIR/<input name>/`` holds what ``run`` writes, written the same atomic
way (a staging folder renamed into place, report.json last).

``DIR/batch.csv`` (one row per input, :data:`COLUMNS`) and ``DIR/index.html`` are rewritten
atomically each time a task finishes, so an interrupted batch keeps what it finished. A rerun
skips the inputs whose row says ok (or skipped) with the same config hash and whose report.json
is there, and runs the others again (failed ones included).

Faults: a task whose worker process dies is re-run by Ray (``BatchConfig.max_retries``); before a
task starts it removes the staging leftovers of a dead attempt in its output folder, so a retry
leaves neither a duplicate nor a half-written output. A broken input fails alone: its row says
failed with a one-line reason; the other inputs go on.

Security of the embedded local Ray (what :func:`start_local_ray` sets): no dashboard, every Ray
process bound to the loopback address (Ray binds its gRPC servers to the node IP; the node IP is
forced to 127.0.0.1 through ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, Ray's local-only mode), and
token authentication on (``RAY_AUTH_MODE=token``; the token lives in ``~/.ray/auth_token``).

The quality verdict (:func:`clip_verdict`) says whether a clip is usable for curation, from its
posed share, low-confidence share, reprojection error, map segments, how far the global
refinement moved the keyframes and how many points held the poses up, with thresholds in
:class:`VerdictConfig`.

Ray is imported inside the functions that need it, so importing this module stays cheap.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import io
import json
import logging
import math
import os
import re
import shutil
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

from data_tools.atomic import write_text_atomic
from mona_vo import __version__
from mona_vo.config import apply_overrides, check_fields, setting, to_dict
from mona_vo.errors import ConfigError, InputError, MonaVoError

log = logging.getLogger(__name__)

COLUMNS = ("input", "name", "status", "usable", "reason", "frames", "frames_with_pose",
           "low_confidence_share", "mask_coverage", "keyframes", "map_segments",
           "reprojection_rmse_px", "global_shift_pct", "support_p10", "seconds",
           "frames_per_second", "node", "config_hash")
STATUSES = ("ok", "failed", "skipped")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm")
LOOPBACK = "127.0.0.1"


# ----------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class VerdictConfig:
    """When a clip is ``usable`` for curation. A clip failing any test is not usable."""

    min_frames: int = setting(10, ge=1)                      # frames; shorter clips are too short to judge
    min_posed_share: float = setting(0.8, ge=0.0, le=1.0)    # fraction of frames with a pose
    max_low_confidence_share: float = setting(0.3, ge=0.0, le=1.0)  # fraction of frames flagged low-confidence
    max_reprojection_rmse_px: float = setting(2.0, gt=0.0)   # final bundle-adjustment reprojection RMSE, px
    max_map_segments: int = setting(1, ge=1)  # maps the trajectory is made of: after a loss of
                                              # tracking (a cut between shots) the scale and the
                                              # pose across the join are not measured
    max_global_shift_pct: float = setting(0.5, gt=0.0)  # the global refinement moved the
                                              # keyframes by more than this % of their path
                                              # (after a similarity): the window's map was not
                                              # consistent (scale slid, wrong start)
    min_support_p10: float = setting(40.0, ge=0.0)  # a tenth of the posed frames rested on
                                              # fewer PnP inliers than this

    def validate(self) -> None:
        check_fields(self, "verdict.")


@dataclass(frozen=True)
class BatchConfig:
    """How a batch is spread over Ray. ``--set batch.<key>=...`` (``--set verdict.<key>=...``)."""

    cpus_per_video: float = setting(1.0, gt=0.0)   # Ray CPUs reserved by each video's task
    max_retries: int = setting(3, ge=0)             # re-runs of a task whose worker process died
    local_cpus: int | None = setting(None, ge=1)    # CPUs of the embedded local Ray; none: this machine's cores
    object_store_mb: int = setting(256, ge=80)      # embedded local Ray's shared-memory object store, MB
    verdict: VerdictConfig = field(default_factory=VerdictConfig)

    def validate(self) -> None:
        check_fields(self, "batch.")


def batch_config_from_sets(overrides: dict[str, str], base: BatchConfig | None = None) -> BatchConfig:
    """``{"batch.max_retries": "2", "verdict.min_posed_share": "0.9"}`` -> BatchConfig (checked)."""
    cfg = base or BatchConfig()
    mapped = {}
    for key, value in overrides.items():
        if key.startswith("batch."):
            mapped[key[len("batch."):]] = value
        elif key.startswith("verdict."):
            mapped[key] = value
        else:
            raise ConfigError(f"config key '{key}' is not a batch key (batch.* or verdict.*)")
    if not mapped:
        return cfg
    cfg = apply_overrides(cfg, mapped, prefix="batch.")
    cfg.validate()
    return cfg


def split_batch_sets(items: Sequence[str]) -> tuple[list[str], dict[str, str]]:
    """Split ``--set`` items into pipeline ones and batch ones (``batch.*``, ``verdict.*``)."""
    from mona_vo.config import parse_set_options

    pipeline, batch = [], {}
    for item in items or []:
        key = item.partition("=")[0].strip()
        if key.startswith(("batch.", "verdict.")):
            batch.update(parse_set_options([item]))
        else:
            pipeline.append(item)
    return pipeline, batch


@dataclass(frozen=True)
class RunOptions:
    """The options of ``run`` that a batch applies to every input."""

    config: Any = None                # mona_vo.pipeline.PipelineConfig; None: the defaults
    calib: str | None = None          # fx,fy,cx,cy or a file, for every input; None: the guess
    masks: str = "mona"               # mona | none | DIR (masks of input NAME in DIR/NAME/)
    stride: int = 1                   # every N-th frame
    max_frames: int | None = None     # at most this many frames per input
    overlay: bool = False             # also write overlay.mp4

    def pipeline_config(self):
        if self.config is not None:
            return self.config
        from mona_vo.pipeline import PipelineConfig

        return PipelineConfig()


def config_hash(options: RunOptions) -> str:
    """Hash of everything that changes a run's outputs (not the verdict thresholds)."""
    payload = {"config": to_dict(options.pipeline_config()), "calib": options.calib,
               "masks": options.masks, "stride": options.stride, "max_frames": options.max_frames,
               "overlay": options.overlay, "mona_vo_version": __version__}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------------------------
# The verdict


@dataclass(frozen=True)
class Verdict:
    usable: bool
    reasons: tuple[str, ...]   # why not usable (empty when usable)

    def text(self) -> str:
        return "usable" if self.usable else "not usable: " + "; ".join(self.reasons)


def clip_verdict(summary: dict, config: VerdictConfig | None = None) -> Verdict:
    """Verdict of one clip from its summary numbers (``frames``, ``frames_with_pose``,
    ``low_confidence_share``, ``reprojection_rmse_px``; a missing or NaN RMSE is not judged)."""
    config = config or VerdictConfig()
    reasons = []
    n = int(summary.get("frames") or 0)
    if n < config.min_frames:
        reasons.append(f"{n} frames (< {config.min_frames})")
    posed = (summary.get("frames_with_pose") or 0) / n if n else 0.0
    if posed < config.min_posed_share:
        reasons.append(f"poses for {100 * posed:.0f} % of frames (< {100 * config.min_posed_share:.0f} %)")
    low = summary.get("low_confidence_share")
    if low is not None and low > config.max_low_confidence_share:
        reasons.append(f"{100 * low:.0f} % of frames low-confidence (> {100 * config.max_low_confidence_share:.0f} %)")
    segments = summary.get("map_segments")
    if segments is not None and segments > config.max_map_segments:
        reasons.append(f"{segments} map segments (> {config.max_map_segments}: tracking was lost, "
                       f"e.g. at a cut; no pose is measured across it)")
    # A number that was not measured (no bundle adjustment ran, an older report) is not held
    # against the clip.
    rmse = _finite(summary.get("reprojection_rmse_px"))
    if rmse is not None and rmse > config.max_reprojection_rmse_px:
        reasons.append(f"reprojection RMSE {rmse:.2f} px (> {config.max_reprojection_rmse_px:g} px)")
    shift = _finite(summary.get("global_shift_pct"))
    if shift is not None and shift > config.max_global_shift_pct:
        reasons.append(f"the global refinement moved the keyframes by {shift:.2f} % of their path "
                       f"(> {config.max_global_shift_pct:g} %: the streaming map was not consistent)")
    support = _finite(summary.get("support_p10"))
    if support is not None and support < config.min_support_p10:
        reasons.append(f"a tenth of the poses rest on fewer than {support:.0f} points "
                       f"(< {config.min_support_p10:g})")
    return Verdict(not reasons, tuple(reasons))


def summary_from_report(report: dict) -> dict:
    """The key numbers of one run's report.json, as batch.csv holds them."""
    n = int(report.get("frames") or 0)
    refine, support = report.get("global_refinement") or {}, report.get("pose_support") or {}
    return {
        "frames": n,
        "frames_with_pose": int(report.get("frames_with_pose") or 0),
        "low_confidence_share": round(len(report.get("low_confidence_frames") or ()) / n, 4) if n else None,
        "mask_coverage": round(float(report.get("mean_mask_coverage") or 0.0), 4),
        "keyframes": int(report.get("keyframes") or 0),
        "map_segments": len(report["map_segments"]) if "map_segments" in report else None,
        "reprojection_rmse_px": _finite_or_none(report.get("reprojection_rmse_px")),
        "global_shift_pct": _finite_or_none(refine.get("keyframe_shift_pct")),
        "support_p10": _finite_or_none(support.get("inliers_p10")),
    }


def _finite(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _finite_or_none(value) -> float | None:
    """``value`` rounded to 4 decimals, as batch.csv holds it; None when it is not a finite number."""
    v = _finite(value)
    return None if v is None else round(v, 4)


def judged(row: dict, config: VerdictConfig | None = None) -> dict:
    """``row`` with ``usable`` and, for an unusable clip, the verdict's reasons in ``reason``."""
    row = dict(row)
    if row.get("status") in ("ok", "skipped"):
        v = clip_verdict(row, config)
        row["usable"] = v.usable
        row["reason"] = "" if v.usable else "not usable: " + "; ".join(v.reasons)
    else:
        row["usable"] = False
    return row


def run_page_files(staging: Path, report: dict, strip, *, name: str,
                   verdict: VerdictConfig | None = None) -> dict[str, Path]:
    """What ``run`` adds to its outputs for the page: the thumbnail strip and index.html (one row),
    written into ``staging``; returns {file name: path} for RunOutputs.commit's extra files."""
    from mona_vo.report_html import STRIP_NAME, write_index_html

    files = {}
    if strip is not None and strip.write(staging / STRIP_NAME):
        files[STRIP_NAME] = staging / STRIP_NAME
    seconds = (report.get("seconds") or {}).get("total")
    n = report.get("frames") or 0
    row = {"input": report.get("input", ""), "name": name, "status": "ok", **summary_from_report(report),
           "seconds": None if seconds is None else round(seconds, 2),
           "frames_per_second": round(n / seconds, 2) if seconds else None,
           "node": socket.gethostname(), "config_hash": ""}
    row = judged(row, verdict)
    write_index_html(staging / "index.html", [row], title=f"mona-vo run: {name}", here=True)
    files["index.html"] = staging / "index.html"
    return files


# ----------------------------------------------------------------------------------------------
# Inputs and names


def expand_inputs(items: Iterable[str]) -> list[str]:
    """Video files, frame folders, or ``@LIST`` (one path per line; blank lines and ``#``
    comments skipped; relative paths are relative to the list's folder). Absolute paths, in
    order, duplicates dropped. Missing inputs are kept: they fail alone when their task runs."""
    out = []
    for item in items:
        if item.startswith("@"):
            path = Path(item[1:])
            try:
                lines = path.read_text().splitlines()
            except (OSError, UnicodeDecodeError) as exc:
                raise InputError(f"{path}: cannot read the input list "
                                 f"({getattr(exc, 'strerror', None) or exc})") from None
            for line in lines:
                line = line.strip()
                if line and not line.startswith("#"):
                    p = Path(line).expanduser()
                    out.append(str(p if p.is_absolute() else (path.parent / p).absolute()))
        else:
            out.append(os.path.abspath(os.path.expanduser(item)))
    if not out:
        raise InputError("no inputs given (video files, frame folders or @LIST)")
    return list(dict.fromkeys(os.path.normpath(p) for p in out))


def _base_name(path: str) -> str:
    p = Path(path)
    base = p.stem if p.suffix.lower() in VIDEO_SUFFIXES else p.name
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", base).strip("._") or "input"
    return base


def input_names(inputs: Sequence[str]) -> list[str]:
    """One output folder name per input: its file stem (video) or folder name; names that two
    inputs share get a short hash of the path, so that the mapping does not depend on order."""
    bases = [_base_name(p) for p in inputs]
    counts: dict[str, int] = {}
    for b in bases:
        counts[b] = counts.get(b, 0) + 1
    return [b if counts[b] == 1 else f"{b}-{hashlib.sha1(p.encode()).hexdigest()[:6]}"
            for b, p in zip(bases, inputs)]


# ----------------------------------------------------------------------------------------------
# The Ray engine


class _EnvPatch:
    """Set environment variables for the life of the embedded Ray, then put them back."""

    def __init__(self, values: dict[str, str]):
        self.values = values
        self.saved: dict[str, str | None] = {}

    def apply(self) -> None:
        for k, v in self.values.items():
            self.saved[k] = os.environ.get(k)
            os.environ[k] = v

    def restore(self) -> None:
        for k, v in self.saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        self.saved = {}


# Local-only mode (node IP 127.0.0.1, so every Ray gRPC server binds to loopback) and token auth.
LOCAL_RAY_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_AUTH_MODE": "token",
                 "RAY_USAGE_STATS_ENABLED": "0"}


def start_local_ray(num_cpus: int | None = None, object_store_mb: int = 256) -> Callable[[], None]:
    """Start the embedded local Ray in this process (no dashboard, loopback only, token auth on).
    Returns the function that shuts it down and restores the environment."""
    env = _EnvPatch(LOCAL_RAY_ENV)
    env.apply()
    try:
        import ray
        from ray._private import ray_constants
        from ray._raylet import Config

        # Both are read when ray is imported; an earlier import has read the old values. Ray's
        # own token set-up refreshes its config the same way.
        cluster_mode = ray_constants.ENABLE_RAY_CLUSTER
        ray_constants.ENABLE_RAY_CLUSTER = False
        Config.initialize("")
        # address="local": always a new Ray of our own, never one `ray start` left running.
        ray.init(address="local", num_cpus=num_cpus or _cpu_count(), include_dashboard=False,
                 _node_ip_address=LOOPBACK, object_store_memory=object_store_mb * 1024 * 1024,
                 log_to_driver=False, logging_level=logging.WARNING, configure_logging=False)
    except BaseException:
        env.restore()
        raise

    return _stopper(env, cluster_mode)


def _stopper(env: "_EnvPatch", cluster_mode: bool) -> Callable[[], None]:
    """The shutdown of a Ray this process started or joined: Ray stops, then Ray's cluster-mode
    constant, the environment and Ray's config are put back as they were before."""
    def stop() -> None:
        import ray
        from ray._private import ray_constants
        from ray._raylet import Config

        try:
            ray.shutdown()
        finally:
            ray_constants.ENABLE_RAY_CLUSTER = cluster_mode
            env.restore()
            Config.initialize("")
    return stop


@contextlib.contextmanager
def ray_session(address: str | None = None, config: BatchConfig | None = None):
    """Ray for the duration of the block: an already connected Ray as it is, the cluster at
    ``address`` ("auto" or HOST:PORT), or (None, "local") the embedded local Ray."""
    config = config or BatchConfig()
    import ray

    if ray.is_initialized():
        yield
        return
    if address in (None, "", "local"):
        stop = start_local_ray(config.local_cpus, config.object_store_mb)
    else:
        # Token authentication stays on unless the user switched it off (RAY_AUTH_MODE=disabled):
        # Ray itself turns it on for an explicit address only when told to.
        env = _EnvPatch({} if os.environ.get("RAY_AUTH_MODE") else {"RAY_AUTH_MODE": "token"})
        env.apply()
        from ray._private import ray_constants
        from ray._raylet import Config

        Config.initialize("")
        cluster_mode = ray_constants.ENABLE_RAY_CLUSTER
        if _is_loopback_cluster(address):
            # A cluster bound to loopback (`ray start --head --node-ip-address=127.0.0.1`): Ray
            # would otherwise swap 127.0.0.1 for this machine's network address and never connect.
            ray_constants.ENABLE_RAY_CLUSTER = False
        try:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING,
                     configure_logging=False)
        except (ConnectionError, ValueError, RuntimeError, ray.exceptions.RayError) as exc:
            env.restore()
            ray_constants.ENABLE_RAY_CLUSTER = cluster_mode
            Config.initialize("")
            text = " ".join(str(exc).split())[:300] or type(exc).__name__
            raise ConfigError(f"--address {address}: cannot join the Ray cluster ({text}); with token "
                              f"authentication every node and this machine need the cluster's "
                              f"~/.ray/auth_token (or RAY_AUTH_TOKEN)") from None

        stop = _stopper(env, cluster_mode)
    try:
        yield
    finally:
        stop()


def _is_loopback_cluster(address: str) -> bool:
    """Whether ``address`` ("auto": the cluster `ray start` made on this machine) is on loopback."""
    import ipaddress

    if address == "auto":
        try:
            from ray._private import services

            address = services.get_ray_address_from_environment("auto", None) or ""
        except Exception:
            return False
    host = str(address).rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    first = next((t.strip() for t in text if t.strip()), "")
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def ray_map(fn: Callable, jobs: Sequence, *, num_cpus: float = 1.0, max_retries: int = 3,
            cancel_grace_s: float = 10.0) -> Iterator[tuple[int, Any, str | None]]:
    """Run ``fn(job)`` as one Ray task per job on the connected Ray; yield ``(i, result, None)``
    as tasks finish, or ``(i, None, reason)`` for a task Ray could not complete (its worker died
    more than ``max_retries`` times, say). On KeyboardInterrupt the unfinished tasks are
    cancelled (a KeyboardInterrupt inside each, so their outputs clean up; forced after
    ``cancel_grace_s``) before it propagates."""
    import ray

    remote = ray.remote(fn).options(num_cpus=num_cpus, max_retries=max_retries, retry_exceptions=False)
    refs = {remote.remote(job): i for i, job in enumerate(jobs)}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=1.0)
            for ref in done:
                try:
                    yield refs[ref], ray.get(ref), None
                except ray.exceptions.RayError as exc:
                    yield refs[ref], None, _one_line(exc)
    except BaseException:
        _cancel(pending, cancel_grace_s)
        raise


def _cancel(pending: list, grace_s: float) -> None:
    import ray

    for ref in pending:
        with contextlib.suppress(Exception):
            ray.cancel(ref, force=False)
    deadline = time.monotonic() + grace_s
    left = list(pending)
    while left and time.monotonic() < deadline:
        _, left = ray.wait(left, num_returns=len(left), timeout=0.5)
    for ref in left:
        with contextlib.suppress(Exception):
            ray.cancel(ref, force=True)


# ----------------------------------------------------------------------------------------------
# One input (runs in a Ray worker)


def _is_staging_leftover(name: str) -> bool:
    """Temporaries of RunOutputs and data_tools.atomic: .partial-*, .<stem>.*.tmp*, .<name>.old-*."""
    return name.startswith(".") and (name.startswith(".partial-") or ".tmp" in name or ".old-" in name)


def remove_staging_leftovers(out_dir: Path) -> int:
    """Remove what a run killed half-way (no Python clean-up ran) left in ``out_dir``."""
    n = 0
    try:
        entries = list(out_dir.iterdir())
    except OSError:
        return 0
    for p in entries:
        if _is_staging_leftover(p.name):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()
            n += 1
    return n


def batch_video_task(job: dict) -> dict:
    """One input: ``run`` into ``job["out"]``, return its batch.csv row. Never raises for a bad
    input: the row says failed with a one-line reason."""
    from mona_vo.run import run

    out = Path(job["out"])
    options: RunOptions = job["options"]
    row = {"input": job["input"], "name": job["name"], "config_hash": job["config_hash"],
           "node": _node_name()}
    t0 = time.perf_counter()
    try:
        row["_stale_removed"] = remove_staging_leftovers(out)
        masks = options.masks
        if masks not in ("mona", "none", None):
            masks = str(Path(masks) / job["name"])
        report = run(job["input"], out, calib=options.calib, masks=masks,
                     config=options.pipeline_config(), overlay=options.overlay, stride=options.stride,
                     max_frames=options.max_frames, progress=False, verdict=job.get("verdict"),
                     page_name=job["name"])
        row.update(status="ok", reason="", **summary_from_report(report))
    except MonaVoError as exc:
        row.update(status="failed", reason=_one_line_text(str(exc)))
    except Exception as exc:  # one broken input must not stop the others; keep the cause
        log.exception("input %s", job["input"])
        row.update(status="failed", reason=_one_line(exc))
    seconds = time.perf_counter() - t0
    row["seconds"] = round(seconds, 3)
    if row.get("frames"):
        row["frames_per_second"] = round(row["frames"] / seconds, 2) if seconds > 0 else None
    row["_pid"] = os.getpid()
    return row


def _one_line_text(text: str) -> str:
    return " ".join(text.split())


def _node_name() -> str:
    try:
        import ray

        ip = ray.util.get_node_ip_address()
    except Exception:
        ip = ""
    host = socket.gethostname()
    return f"{host} ({ip})" if ip else host


def _cpu_count() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


# ----------------------------------------------------------------------------------------------
# The batch (the driver)


@dataclass
class BatchResult:
    rows: list[dict]          # one per input, in input order (finished ones; all, unless interrupted)
    out_dir: Path
    seconds: float            # wall time of the batch, Ray start-up included
    ray_start_seconds: float  # of which connecting to / starting Ray

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r.get("status") == "failed"]


def read_batch_csv(path: Path) -> dict[str, dict]:
    """Rows of an earlier batch.csv by input path ({} when there is none or it is unreadable)."""
    try:
        text = path.read_text()
    except OSError:
        return {}
    try:
        return {r["input"]: r for r in csv.DictReader(io.StringIO(text)) if r.get("input")}
    except (csv.Error, KeyError):
        return {}


def write_batch_csv(path: Path, rows: Sequence[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _csv_value(r.get(k)) for k in COLUMNS})
    write_text_atomic(path, buf.getvalue())


def _csv_value(v):
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    return v


def _skipped_row(prev: dict, out: Path, chash: str) -> dict | None:
    """The row of an input done earlier with the same config, from its report.json, or None."""
    if prev.get("status") not in ("ok", "skipped") or prev.get("config_hash") != chash:
        return None
    try:
        report = json.loads((out / "report.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(report, dict) or os.path.normpath(str(report.get("input", ""))) != prev["input"]:
        return None
    row = {"input": prev["input"], "name": prev["name"], "status": "skipped", "reason": "",
           **summary_from_report(report), "node": prev.get("node", ""), "config_hash": chash}
    for key in ("seconds", "frames_per_second"):
        try:
            row[key] = float(prev.get(key))
        except (TypeError, ValueError):
            row[key] = None
    return row


def run_batch(inputs: Sequence[str], out_dir: str | Path, *, options: RunOptions | None = None,
              config: BatchConfig | None = None, address: str | None = None, progress: bool = True,
              on_row: Callable[[dict], None] | None = None) -> BatchResult:
    """Run every input not already done (same config hash) as one Ray task; write
    ``out_dir/<name>/`` (``run``'s outputs), ``out_dir/batch.csv`` and ``out_dir/index.html``.

    ``address``: None or "local" (embedded local Ray), "auto" or HOST:PORT (join a cluster).
    Paths must be visible at the same place on every node of a cluster (a shared file system).
    ``on_row`` is called in the driver with each finished row.
    """
    from mona_vo.report_html import write_index_html

    options = options or RunOptions()
    config = config or BatchConfig()
    config.validate()
    t_start = time.perf_counter()
    paths = expand_inputs(inputs)
    names = input_names(paths)
    out_dir = Path(out_dir).absolute()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MonaVoError(f"{out_dir}: cannot make the output folder ({exc.strerror or exc})") from None
    chash = config_hash(options)
    earlier = read_batch_csv(out_dir / "batch.csv")
    rows: dict[int, dict] = {}
    jobs, job_index = [], []
    for i, (path, name) in enumerate(zip(paths, names)):
        prev = earlier.get(path)
        skipped = _skipped_row(prev, out_dir / name, chash) if prev else None
        if skipped is not None:
            rows[i] = judged(skipped, config.verdict)
        else:
            jobs.append({"input": path, "name": name, "out": str(out_dir / name), "options": options,
                         "config_hash": chash, "verdict": config.verdict})
            job_index.append(i)

    def write_tables() -> None:
        ordered = [rows[i] for i in sorted(rows)]
        write_batch_csv(out_dir / "batch.csv", ordered)
        write_index_html(out_dir / "index.html", ordered, title=f"mona-vo batch: {out_dir.name}",
                         pending=len(paths) - len(ordered))

    write_tables()
    ray_seconds = 0.0
    bar = None
    if jobs:
        t_ray = time.perf_counter()
        with ray_session(address, config):
            ray_seconds = time.perf_counter() - t_ray
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=len(jobs), desc="mona-vo batch", unit="video", leave=False)
            frames_done, failures = 0, 0
            try:
                for k, row, reason in ray_map(batch_video_task, jobs, num_cpus=config.cpus_per_video,
                                              max_retries=config.max_retries):
                    job = jobs[k]
                    if row is None:
                        row = {"input": job["input"], "name": job["name"], "status": "failed",
                               "reason": f"the task could not complete ({reason})",
                               "config_hash": chash}
                    row = judged(row, config.verdict)
                    rows[job_index[k]] = row
                    write_tables()
                    frames_done += int(row.get("frames") or 0)
                    failures += row["status"] == "failed"
                    if on_row is not None:
                        on_row(row)
                    if bar is not None:
                        bar.set_postfix_str(f"{frames_done} frames, {failures} failed", refresh=False)
                        bar.update(1)
            finally:
                if bar is not None:
                    bar.close()
    ordered = [rows[i] for i in sorted(rows)]
    write_tables()
    return BatchResult(rows=ordered, out_dir=out_dir, seconds=time.perf_counter() - t_start,
                       ray_start_seconds=ray_seconds)
