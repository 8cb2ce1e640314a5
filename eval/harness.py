"""One evaluation harness for every dataset: sequences x mask variants -> trajectories, metrics
and tables. Dataset readers (:mod:`eval.datasets`) turn a dataset folder into
:class:`EvalSequence` objects; nothing here knows Sintel from TUM.

Variants (the paper's Table 1 and ablation): ``none`` (no masks), ``mona`` (the method: filtered
boxes), ``mona-points`` (dynamic points only as prompts), ``mona-raw-boxes`` (every detector box),
``gt`` (ground-truth moving-object masks, where the dataset has them).

Outputs in ``out_dir``: ``<variant>/<seq>/trajectory.txt`` (TUM, camera-to-world),
``<variant>/<seq>/result.json`` (one run: metrics, status, seconds, config hash), and, rebuilt
after every run, ``results.csv``, ``results.json`` and ``results.md`` (per-variant means in the
layout of the paper's Table 1). A run whose result.json holds the same config hash and status ok
is skipped when the command is repeated; failed runs are retried; one failing run never stops the
others. A sequence with poses for fewer than 80 % of its frames counts as failed (ParticleSfM's
rule) and is reported, not dropped.

Parts (``parts``, the commands' ``--parts NAME=A:B``): each run is also scored on rows A to B-1
of its trajectory, each part aligned alone (as ``mona-vo eval traj --frames A:B``), so a tuning
part and a validation part of one sequence are reported apart, in every table and over the
draws. Scoring reads the written trajectory, so parts can be added to finished runs.
"""
from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import time
import traceback
from pathlib import Path
from typing import Iterable

import numpy as np

from data_tools.atomic import write_text_atomic
from data_tools.run_outputs import sigint_deferred
from data_tools.tum import read_tum_trajectory, write_tum_trajectory
from eval.datasets import EvalSequence
from eval.metrics import RotationMetrics, Trajectory, score_trajectory
from eval.variants import VARIANTS, parse_variants, variant_config
from mona_vo.batch import clip_verdict
from mona_vo.config import apply_overrides, to_dict
from mona_vo.errors import ConfigError, EvalError, MonaVoError
from mona_vo.pipeline import PipelineConfig, estimate_trajectory
from mona_vo.run import clip_summary

MIN_POSED_FRACTION = 0.8
MIN_MATCHED_FRACTION = 0.9   # fewer posed frames matched to GT than this: a warning on the row
COLUMNS = ("sequence", "variant", "status", "ate", "rpe_trans", "rpe_rot_deg", "ate_percent_of_path",
           "rot_rmse_deg", "rot_max_deg", "est_translation_extent",
           "frames", "frames_with_pose", "low_confidence", "n_matched", "scale", "seconds",
           "frames_per_second", "camera", "focal_px", "rolling_shutter_readout", "global_shift_pct",
           "support_p10", "usable", "warning")


def config_hash(config: PipelineConfig, seq: EvalSequence, variant: str, extra: dict) -> str:
    payload = json.dumps({"config": to_dict(config), "variant": variant, "sequence": seq.name,
                          "frames": seq.n_frames, **extra}, sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def run_one(seq: EvalSequence, variant: str, config: PipelineConfig, run_dir: Path,
            chash: str) -> dict:
    """Run one (sequence, variant), write its trajectory and result.json, return the row."""
    row = {"sequence": seq.name, "variant": variant, "frames": seq.n_frames, "config_hash": chash}
    # An older result.json must never sit beside a newer trajectory: drop it before running.
    (run_dir / "result.json").unlink(missing_ok=True)
    t0 = time.perf_counter()
    try:
        if seq.error:
            raise MonaVoError(seq.error)
        masks_kind = VARIANTS[variant][0]
        if masks_kind == "gt":
            if seq.gt_masks is None:
                raise MonaVoError(f"sequence {seq.name} has no ground-truth masks for variant 'gt'")
            masks = seq.gt_masks()
        else:
            masks = masks_kind
        run_config = variant_config(config, variant)
        result = estimate_trajectory(seq.frames(), intrinsics=seq.intrinsics, masks=masks,
                                     config=run_config)
        vo = result.vo
        posed = np.isfinite(vo.poses).all(axis=(1, 2))
        with sigint_deferred():
            write_tum_trajectory(run_dir / "trajectory.txt", vo.timestamps[posed], vo.poses[posed])
        row.update(frames=len(vo.timestamps), frames_with_pose=int(posed.sum()),
                   low_confidence=int(vo.low_confidence.sum()), focal_px=float(vo.focal),
                   camera="given" if seq.intrinsics is not None else "estimated",
                   rolling_shutter_readout=(vo.refine.get("rolling_shutter") or {}).get("readout"))
        # The verdict batch would give the run, from the report run would write: beside the
        # metrics, every evaluated sequence is a check of the verdict against ground truth.
        summary = clip_summary(result, name=seq.name, masks=masks_kind or "none", config=run_config,
                               calib_given=seq.intrinsics is not None)
        row.update(global_shift_pct=summary["global_shift_pct"], support_p10=summary["support_p10"],
                   usable=clip_verdict(summary).usable)
        est = Trajectory(vo.timestamps[posed], vo.poses[posed])
        m = score_trajectory(seq.gt, est, max_diff=seq.max_diff)
        if isinstance(m, RotationMetrics):
            row.update(m.to_dict())
        else:
            row.update({k: v for k, v in m.to_dict().items()
                        if k in ("ate", "rpe_trans", "rpe_rot_deg", "ate_percent_of_path", "n_matched", "scale")})
            if m.n_matched < MIN_MATCHED_FRACTION * posed.sum():
                # evo's RPE pairs consecutive *matched* poses: across unmatched runs a "1-frame"
                # pair spans many frames and can dominate the RPE.
                row["warning"] = (f"only {m.n_matched} of {int(posed.sum())} poses matched a GT "
                                  f"timestamp within {seq.max_diff:g} s; RPE pairs span the gaps")
        ok = posed.sum() >= MIN_POSED_FRACTION * seq.n_frames
        row["status"] = "ok" if ok else f"failed: poses for {posed.sum()} of {seq.n_frames} frames"
    except MonaVoError as exc:
        row["status"] = f"failed: {exc}"
    except Exception as exc:  # one broken run must not stop the others; keep the cause
        row["status"] = f"error: {type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc(limit=8)
    row["seconds"] = round(time.perf_counter() - t0, 3)
    row["frames_per_second"] = round(seq.n_frames / row["seconds"], 2) if row["seconds"] > 0 else None
    write_text_atomic(run_dir / "result.json", json.dumps(row, indent=2) + "\n")
    return row


def load_done(run_dir: Path, chash: str) -> dict | None:
    path = run_dir / "result.json"
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if row.get("config_hash") == chash and row.get("status") == "ok" and (run_dir / "trajectory.txt").exists():
        return row
    return None


def _job(args):
    seq, variant, config, run_dir, chash = args
    return run_one(seq, variant, config, run_dir, chash)


def parse_parts(items: Iterable[str]) -> dict[str, tuple[int, int]]:
    """``--parts`` values ``NAME=A:B`` (repeatable, or comma-separated) -> {name: (A, B)}; a
    malformed one is a ConfigError naming the option."""
    parts: dict[str, tuple[int, int]] = {}
    for item in (x.strip() for text in items for x in text.split(",") if x.strip()):
        name, eq, rng = item.partition("=")
        a, colon, b = rng.partition(":")
        try:
            lo, hi = int(a), int(b)
        except ValueError:
            lo = hi = -1
        if not eq or not name.strip() or not colon or lo < 0 or hi - lo < 3:
            raise ConfigError(f"--parts expects NAME=A:B with 0 <= A and at least 3 rows, e.g. "
                              f"--parts tune=0:225, got '{item}'")
        if name.strip() in parts:
            raise ConfigError(f"--parts: part '{name.strip()}' is given twice")
        parts[name.strip()] = (lo, hi)
    return parts


def score_parts(seq: EvalSequence, trajectory: str | Path,
                parts: dict[str, tuple[int, int]]) -> dict[str, float | None]:
    """ATE (m) of each part (rows A to B-1 of the written trajectory, aligned alone, as
    ``mona-vo eval traj --frames A:B`` scores them); None where the run has fewer rows, or the
    part cannot be scored (a rotation-only part, too few matched poses)."""
    t, T = read_tum_trajectory(trajectory)
    out: dict[str, float | None] = {}
    for name, (lo, hi) in parts.items():
        out[name] = None
        if hi <= len(t):
            try:
                m = score_trajectory(seq.gt, Trajectory(t[lo:hi], T[lo:hi]), max_diff=seq.max_diff)
            except EvalError:
                continue
            if not isinstance(m, RotationMetrics):
                out[name] = float(m.ate)
    return out


def evaluate(sequences: list[EvalSequence], variants: list[str], out_dir: str | Path, *,
             config: PipelineConfig | None = None, workers: int = 1, extra_hash: dict | None = None,
             progress: bool = True, method_names: dict[str, str] | None = None,
             address: str | None = None, parts: dict[str, tuple[int, int]] | None = None
             ) -> list[dict]:
    """Run every (sequence, variant) not already done, then write the tables. Returns all rows.
    ``address``: run them on Ray, one task per run ("local": an embedded local Ray; "auto" or
    HOST:PORT: a cluster), as ``mona-vo batch`` does; None: here, ``workers`` processes.
    ``parts``: {name: (A, B)}, each run's ATE on those rows too (module docstring), in the
    rows' ``parts``."""
    config = config or PipelineConfig()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: dict[tuple[str, str], dict] = {}
    by_name = {seq.name: seq for seq in sequences}

    def scored(row):
        if parts and row.get("status") == "ok":
            path = out_dir / row["variant"] / row["sequence"] / "trajectory.txt"
            row = {**row, "parts": score_parts(by_name[row["sequence"]], path, parts)}
        return row

    todo = []
    for seq in sequences:
        for variant in variants:
            run_dir = out_dir / variant / seq.name
            chash = config_hash(variant_config(config, variant), seq, variant, extra_hash or {})
            done = load_done(run_dir, chash)
            if done is not None:
                rows[(seq.name, variant)] = scored({**done, "skipped": True})
            else:
                run_dir.mkdir(parents=True, exist_ok=True)
                todo.append((seq, variant, config, run_dir, chash))
    bar = None
    if progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc="runs", unit="run", leave=False)

    def finished(row):
        row = scored(row)
        rows[(row["sequence"], row["variant"])] = row
        write_tables(out_dir, _ordered(rows, sequences, variants), method_names)
        if bar is not None:
            bar.update(1)

    try:
        if address is not None and todo:
            # The batch engine: one Ray task per run, on the embedded local Ray ("local") or a
            # cluster ("auto", HOST:PORT); a run whose worker died past Ray's retries is failed.
            from mona_vo.batch import BatchConfig, ray_map, ray_session

            with ray_session(address, BatchConfig()):
                for k, row, reason in ray_map(_job, todo):
                    if row is None:
                        seq, variant, _, _, chash = todo[k]
                        row = {"sequence": seq.name, "variant": variant, "frames": seq.n_frames,
                               "config_hash": chash, "status": f"failed: {reason}"}
                    finished(row)
        elif workers > 1 and len(todo) > 1:
            from concurrent.futures import ProcessPoolExecutor, as_completed

            pool = ProcessPoolExecutor(max_workers=workers)
            try:
                futures = [pool.submit(_job, job) for job in todo]
                for fut in as_completed(futures):
                    finished(fut.result())
            except BaseException:
                # Ctrl-C: do not wait for every queued run; finished ones are already on disk.
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
        else:
            for job in todo:
                finished(_job(job))
    finally:
        if bar is not None:
            bar.close()
    ordered = _ordered(rows, sequences, variants)
    write_tables(out_dir, ordered, method_names)
    return ordered


def _ordered(rows, sequences, variants):
    return [rows[(s.name, v)] for v in variants for s in sequences if (s.name, v) in rows]


def summarize(rows: list[dict]) -> list[dict]:
    """Per-variant means over sequences whose run succeeded, and counts of the others."""
    out = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        sel = [r for r in rows if r["variant"] == variant]
        ok = [r for r in sel if r.get("status") == "ok"]

        def mean(key):
            vals = [r[key] for r in ok if r.get(key) is not None]
            return float(np.mean(vals)) if vals else None
        part_means = {}
        for name in _part_names(ok):
            vals = [r["parts"][name] for r in ok if (r.get("parts") or {}).get(name) is not None]
            part_means[name] = float(np.mean(vals)) if vals else None
        out.append({"variant": variant, "sequences": len(sel), "ok": len(ok),
                    "failed": len(sel) - len(ok), "ate": mean("ate"), "rpe_trans": mean("rpe_trans"),
                    "rpe_rot_deg": mean("rpe_rot_deg"), "ate_percent_of_path": mean("ate_percent_of_path"),
                    **({"parts": part_means} if part_means else {})})
    return out


def _part_names(rows: list[dict]) -> list[str]:
    return list(dict.fromkeys(k for r in rows for k in (r.get("parts") or {})))


def write_tables(out_dir: Path, rows: list[dict], method_names: dict[str, str] | None = None) -> None:
    names = _part_names(rows)
    columns = COLUMNS + tuple(f"ate_{n}" for n in names)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        flat = {**r, **{f"ate_{n}": v for n, v in (r.get("parts") or {}).items()}}
        writer.writerow({k: ("" if flat.get(k) is None else flat.get(k)) for k in columns})
    write_text_atomic(out_dir / "results.csv", buf.getvalue())
    clean = [{k: v for k, v in r.items() if k not in ("traceback", "skipped")} for r in rows]
    summary = summarize(rows)
    write_text_atomic(out_dir / "results.json",
                      json.dumps({"runs": clean, "summary": summary}, indent=2) + "\n")
    write_text_atomic(out_dir / "results.md", markdown_table(summary, rows, method_names))


def _fmt(v, digits=3):
    return "-" if v is None else f"{v:.{digits}f}"


def markdown_table(summary: list[dict], rows: list[dict], method_names: dict[str, str] | None) -> str:
    names = {"none": "VO, no masks", "mona": "MONA + VO (filtered boxes)",
             "mona-points": "MONA + VO, points-only prompts", "mona-raw-boxes": "MONA + VO, raw boxes",
             "gt": "VO + ground-truth masks", **(method_names or {})}
    parts = _part_names(rows)
    head = "".join(f" ATE {p} (m) |" for p in parts)
    rule = "---|" * len(parts)
    lines = ["| Method | ATE (m) | RPE trans. (m) | RPE rot. (deg) | sequences ok / failed |" + head,
             "|---|---|---|---|---|" + rule]
    for s in summary:
        cells = "".join(f" {_fmt((s.get('parts') or {}).get(p))} |" for p in parts)
        lines.append(f"| {names.get(s['variant'], s['variant'])} | {_fmt(s['ate'])} | "
                     f"{_fmt(s['rpe_trans'])} | {_fmt(s['rpe_rot_deg'])} | {s['ok']} / {s['failed']} |"
                     + cells)
    lines += ["", "Mean over the sequences whose run succeeded (poses for >= 80 % of frames). "
              "ATE: translation RMSE after Sim(3) alignment; RPE: delta 1 frame, after the same "
              "alignment (evo's numbers)."
              + (" A part's ATE: its rows of the trajectory, aligned alone." if parts else ""),
              "", "| sequence | variant | status | ATE | RPE trans | RPE rot |" + head,
              "|---|---|---|---|---|---|" + rule]
    for r in rows:
        cells = "".join(f" {_fmt((r.get('parts') or {}).get(p), 4)} |" for p in parts)
        lines.append(f"| {r['sequence']} | {r['variant']} | {r.get('status')} | {_fmt(r.get('ate'), 4)} | "
                     f"{_fmt(r.get('rpe_trans'), 4)} | {_fmt(r.get('rpe_rot_deg'))} |" + cells)
    warned = [r for r in rows if r.get("warning")]
    if warned:
        lines += [""] + [f"Warning, {r['sequence']} [{r['variant']}]: {r['warning']}." for r in warned]
    return "\n".join(lines) + "\n"


def parse_draws(items: Iterable[str], config: PipelineConfig) -> list[dict[str, str]]:
    """``["vo.grid_size=14,15", "masks.dynamic_points.seed=1"]`` -> one override per draw, in
    order (``[{"vo.grid_size": "14"}, {"vo.grid_size": "15"}, {"masks.dynamic_points.seed":
    "1"}]``), each checked against ``config``: a malformed item, an unknown key or a bad value
    raises ConfigError naming it."""
    from mona_vo.config import check_config

    draws = []
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        vals = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key or not vals:
            raise ConfigError(f"--draws expects key=v1,v2,..., e.g. --draws vo.grid_size=14,15,16, "
                              f"got '{item}'")
        for v in vals:
            check_config(apply_overrides(config, {key: v}))
            draws.append({key: v})
    return draws


def draw_name(draw: dict[str, str]) -> str:
    return ",".join(f"{k}={v}" for k, v in draw.items())


def evaluate_draws(sequences: list[EvalSequence], variants: list[str], out_dir: str | Path,
                   draws: list[dict[str, str]], *, config: PipelineConfig | None = None,
                   **kwargs) -> dict[str, list[dict]]:
    """:func:`evaluate` once per draw (``config`` with that draw's override), into
    ``out_dir/draws/<key=value>/``; then ``draws.json`` and ``draws.md`` in ``out_dir``: per
    sequence and variant the ATE of every draw and their mean, median and range
    (:func:`summarize_draws`). On a chaotic clip one run does not measure a change: a one-cell
    change of the point grid moved Bonn crowd's ATE between 3.6 and 11.8 cm (README). A draw of
    a ``masks.*`` key runs only the MONA variants."""
    config = config or PipelineConfig()
    out_dir = Path(out_dir)
    by_draw = {}
    for draw in draws:
        # A masks key does not touch a run without MONA masks: that run would only repeat
        # the default's and weigh it twice in the means.
        used = [v for v in variants
                if VARIANTS[v][0] == "mona" or not any(k.startswith("masks.") for k in draw)]
        by_draw[draw_name(draw)] = evaluate(sequences, used, out_dir / "draws" / draw_name(draw),
                                            config=apply_overrides(config, draw), **kwargs)
        write_draws(out_dir, by_draw)
    return by_draw


def summarize_draws(by_draw: dict[str, list[dict]]) -> list[dict]:
    """Per (sequence, variant), over the draws: the ATE of each (None when its run failed), and
    the mean, median, min and max of those that succeeded, with the mean RPE rotation."""
    out: dict[tuple[str, str], dict] = {}
    for name, rows in by_draw.items():
        for r in rows:
            s = out.setdefault((r["sequence"], r["variant"]),
                               {"sequence": r["sequence"], "variant": r["variant"], "ate": {},
                                "rpe_rot_deg": {}})
            ok = r.get("status") == "ok"
            s["ate"][name] = r.get("ate") if ok else None
            s["rpe_rot_deg"][name] = r.get("rpe_rot_deg") if ok else None
            for part, v in (r.get("parts") or {}).items():
                s.setdefault("parts", {}).setdefault(part, {"ate": {}})["ate"][name] = \
                    v if ok else None
    for s in out.values():
        for p in (s.get("parts") or {}).values():
            vals = [v for v in p["ate"].values() if v is not None]
            p.update(ok=len(vals), ate_mean=float(np.mean(vals)) if vals else None,
                     ate_median=float(np.median(vals)) if vals else None)
        ate = [v for v in s["ate"].values() if v is not None]
        rot = [v for v in s["rpe_rot_deg"].values() if v is not None]
        s.update(draws=len(s["ate"]), ok=len(ate),
                 ate_mean=float(np.mean(ate)) if ate else None,
                 ate_median=float(np.median(ate)) if ate else None,
                 ate_min=float(np.min(ate)) if ate else None,
                 ate_max=float(np.max(ate)) if ate else None,
                 rpe_rot_mean=float(np.mean(rot)) if rot else None)
    return list(out.values())


def compare_draws(base: list[dict], new: list[dict]) -> list[dict]:
    """Paired comparison of two draws summaries (``draws.json``'s ``summary``: the same command
    before and after a change): per sequence, variant and part ('all' for the whole run) the
    draws both ran, their means, the mean paired difference (new - base, m) with its standard
    error, and in how many draws the new run is lower. On a chaotic sequence the draws move
    both ways, so a difference within about two standard errors is no difference."""
    def series(s):
        out = {"all": s["ate"]}
        out.update({p: v["ate"] for p, v in (s.get("parts") or {}).items()})
        return out

    old = {(s["sequence"], s["variant"]): series(s) for s in base}
    rows = []
    for s in new:
        key = (s["sequence"], s["variant"])
        if key not in old:
            continue
        for part, ate in series(s).items():
            prev = old[key].get(part, {})
            both = [d for d in ate if ate[d] is not None and prev.get(d) is not None]
            if not both:
                continue
            a = np.array([prev[d] for d in both])
            b = np.array([ate[d] for d in both])
            diff = b - a
            se = float(np.std(diff, ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else None
            rows.append({"sequence": key[0], "variant": key[1], "part": part, "draws": len(both),
                         "base_mean": float(a.mean()), "new_mean": float(b.mean()),
                         "base_median": float(np.median(a)), "new_median": float(np.median(b)),
                         "diff_mean": float(diff.mean()), "diff_se": se,
                         "lower": int(np.sum(diff < 0))})
    return rows


def write_draws(out_dir: Path, by_draw: dict[str, list[dict]]) -> None:
    summary = summarize_draws(by_draw)
    write_text_atomic(Path(out_dir) / "draws.json", json.dumps({"summary": summary}, indent=2) + "\n")
    lines = ["| sequence | variant | draws ok | ATE mean | median | min | max | RPE rot mean (deg) |",
             "|---|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['sequence']} | {s['variant']} | {s['ok']} / {s['draws']} | "
                     f"{_fmt(s['ate_mean'], 4)} | {_fmt(s['ate_median'], 4)} | "
                     f"{_fmt(s['ate_min'], 4)} | {_fmt(s['ate_max'], 4)} | {_fmt(s['rpe_rot_mean'])} |")
    lines += ["", "ATE in metres, one run per draw (`draws/<key=value>/`): "
              + ", ".join(f"`{n}`" for n in by_draw) + "."]
    # A part the sequence is too short for (or that never scored) is no row of the table.
    parted = [s for s in summary if any(p["ok"] for p in (s.get("parts") or {}).values())]
    if parted:
        lines += ["", "Per part (rows of each trajectory, aligned alone), ATE in metres, each draw:", "",
                  "| sequence | variant | part | draws ok | mean | median | " +
                  " | ".join(f"`{n}`" for n in by_draw) + " |",
                  "|---|---|---|---|---|---|" + "---|" * len(by_draw)]
        for s in parted:
            for part, p in ((k, v) for k, v in s["parts"].items() if v["ok"]):
                lines.append(f"| {s['sequence']} | {s['variant']} | {part} | {p['ok']} / {len(p['ate'])} | "
                             f"{_fmt(p['ate_mean'], 4)} | {_fmt(p['ate_median'], 4)} | " +
                             " | ".join(_fmt(p["ate"].get(n), 4) for n in by_draw) + " |")
    write_text_atomic(Path(out_dir) / "draws.md", "\n".join(lines) + "\n")
