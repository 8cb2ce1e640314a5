"""Throughput of ``mona-vo batch`` on this machine, against plain ``run``.

``python -m eval.batch_bench INPUT... --out DIR [--concurrency 1,2] [--max-frames N] [--preset P]``

1. plain: ``mona_vo.run.run`` on every input, one after the other, in this process (what a
   shell loop over ``mona-vo run`` does, without the per-process start);
2. for each concurrency c: ``run_batch`` on a fresh embedded local Ray with c CPUs (c videos at
   a time), its own output folder.

Printed and written to ``DIR/batch_bench.json``: videos/hour and frames/s of each (with and
without Ray's start-up), Ray's start-up, Ray's overhead per video (the batch at concurrency 1,
start-up left out, against plain run), the in-task overhead (task seconds minus run's own
total), the machine's load average before and after, and the projection to N machines.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

from data_tools.atomic import write_text_atomic


def bench_batch(inputs: list[str], out_dir: str | Path, *, concurrency=(1, 2), options=None,
                machines=(1, 10, 100)) -> dict:
    from mona_vo.batch import BatchConfig, RunOptions, expand_inputs, input_names, run_batch
    from mona_vo.run import run

    options = options or RunOptions()
    out_dir = Path(out_dir)
    paths = expand_inputs(inputs)
    names = input_names(paths)
    load_before = os.getloadavg()
    result = {"inputs": len(paths), "cpu_count": len(os.sched_getaffinity(0)), "load_before": load_before}

    plain_dir = out_dir / "plain"
    shutil.rmtree(plain_dir, ignore_errors=True)
    plain, frames = [], 0
    t_all = time.perf_counter()
    for path, name in zip(paths, names):
        t0 = time.perf_counter()
        report = run(path, plain_dir / name, calib=options.calib, masks=options.masks,
                     config=options.pipeline_config(), stride=options.stride,
                     max_frames=options.max_frames, progress=False)
        plain.append({"name": name, "seconds": time.perf_counter() - t0, "frames": report["frames"],
                      "run_total_s": report["seconds"]["total"]})
        frames += report["frames"]
    wall = time.perf_counter() - t_all
    result["frames"] = frames
    result["plain"] = {"wall_s": wall, "videos_per_hour": 3600 * len(paths) / wall,
                       "frames_per_second": frames / wall, "per_video_s": wall / len(paths),
                       "runs": plain}

    for c in concurrency:
        bdir = out_dir / f"batch_c{c}"
        shutil.rmtree(bdir, ignore_errors=True)
        res = run_batch(paths, bdir, options=options, config=BatchConfig(local_cpus=c), progress=False)
        work = res.seconds - res.ray_start_seconds
        in_task = []
        for row in res.rows:
            try:
                report = json.loads((bdir / row["name"] / "report.json").read_text())
                in_task.append(row["seconds"] - report["seconds"]["total"])
            except (OSError, ValueError, KeyError, TypeError):
                pass
        result[f"batch_c{c}"] = {
            "wall_s": res.seconds, "ray_start_s": res.ray_start_seconds, "work_s": work,
            "failed": len(res.failed),
            "videos_per_hour": 3600 * len(paths) / res.seconds,
            "videos_per_hour_without_start": 3600 * len(paths) / work,
            "frames_per_second": frames / res.seconds,
            "frames_per_second_without_start": frames / work,
            "in_task_overhead_s": sum(in_task) / len(in_task) if in_task else None,
            "task_seconds": [row.get("seconds") for row in res.rows]}
    if "batch_c1" in result:
        b1 = result["batch_c1"]
        result["ray_overhead_per_video_s"] = (b1["work_s"] - wall) / len(paths)
    best = max((result[f"batch_c{c}"] for c in concurrency), key=lambda b: b["videos_per_hour_without_start"])
    rate = best["videos_per_hour_without_start"]
    result["projection"] = {str(n): {"videos_per_hour": n * rate, "frames_per_second": n * best["frames_per_second_without_start"]}
                            for n in machines}
    result["load_after"] = os.getloadavg()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "batch_bench.json", json.dumps(result, indent=2) + "\n")
    return result


def format_result(r: dict) -> str:
    lines = [f"{r['inputs']} inputs, {r['frames']} frames; {r['cpu_count']} cores; load average before "
             f"{r['load_before'][0]:.1f} / after {r['load_after'][0]:.1f}",
             f"plain run, one after the other: {r['plain']['videos_per_hour']:.0f} videos/h, "
             f"{r['plain']['frames_per_second']:.2f} frames/s ({r['plain']['per_video_s']:.1f} s per video)"]
    for key in sorted(k for k in r if k.startswith("batch_c")):
        b = r[key]
        lines.append(f"batch, {key[7:]} at a time: {b['videos_per_hour']:.0f} videos/h, "
                     f"{b['frames_per_second']:.2f} frames/s; without the Ray start-up "
                     f"({b['ray_start_s']:.1f} s): {b['videos_per_hour_without_start']:.0f} videos/h, "
                     f"{b['frames_per_second_without_start']:.2f} frames/s; in-task overhead "
                     f"{b['in_task_overhead_s']:.2f} s per video; failed {b['failed']}")
    if "ray_overhead_per_video_s" in r:
        lines.append(f"Ray overhead per video (1 at a time, start-up left out, vs plain run): "
                     f"{r['ray_overhead_per_video_s']:+.2f} s")
    for n, p in r["projection"].items():
        lines.append(f"projection, {n} such machines: {p['videos_per_hour']:.0f} videos/h, "
                     f"{p['frames_per_second']:.1f} frames/s")
    return "\n".join(lines)


def main(argv=None) -> int:
    from mona_vo.batch import RunOptions
    from mona_vo.presets import PRESETS, preset_config

    p = argparse.ArgumentParser(prog="python -m eval.batch_bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", metavar="INPUT")
    p.add_argument("--out", required=True)
    p.add_argument("--concurrency", default="1,2", help="videos at a time, comma-separated (default 1,2)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--preset", default="default", choices=sorted(PRESETS))
    args = p.parse_args(argv)
    options = RunOptions(config=preset_config(args.preset),
                         max_frames=args.max_frames)
    r = bench_batch(args.inputs, args.out, options=options,
                    concurrency=tuple(int(c) for c in args.concurrency.split(",")))
    print(format_result(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
