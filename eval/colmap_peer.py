"""The peers to beat, run side by side on the same frames through pycolmap: COLMAP's incremental
structure from motion and its global SfM (GLOMAP, ``pycolmap.global_mapping``), after one SIFT
extraction and sequential matching shared by both, given the true pinhole intrinsics (held
fixed in their bundle adjustments, as ours are).

Poses are ``cam_from_world`` per registered image; T_world_cam is their inverse. Unregistered
frames get no pose. When a mapper splits the sequence into several models, the largest is scored
(as a user would take it). ATE is computed on the registered frames with the same Sim(3) protocol
as ours; the share of frames registered is reported beside it. Each mapper's time is the shared
feature extraction and matching plus its own mapping.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from mona_vo.conventions import Intrinsics, invert_pose

MAPPERS = ("incremental", "global")


def _poses(models) -> dict:
    poses = {}
    if models:
        best = max(models.values(), key=lambda r: r.num_reg_images())
        for image in best.images.values():
            if not image.has_pose:
                continue
            T_cam_world = np.eye(4)
            T_cam_world[:3] = image.cam_from_world().matrix()
            poses[image.name] = invert_pose(T_cam_world)
    return poses


def run_colmap(image_dir: str | Path, intrinsics: Intrinsics, *, overlap: int = 10,
               num_threads: int = 2, work_dir: str | Path | None = None,
               mask_dir: str | Path | None = None,
               mappers: tuple[str, ...] = ("incremental",)) -> dict:
    """Run COLMAP on a folder of images. Returns, for one mapper, {names, poses (dict name ->
    T_world_cam), seconds, registered, models}; with several ``mappers`` (``incremental``,
    ``global``), {mapper: that dict}."""
    import pycolmap

    for m in mappers:
        if m not in MAPPERS:
            raise ValueError(f"unknown COLMAP mapper {m!r}; valid: {', '.join(MAPPERS)}")
    pycolmap.logging.minloglevel = 2   # COLMAP logs every image at INFO; keep warnings quiet too
    pycolmap.logging.stderrthreshold = 2
    image_dir = Path(image_dir)
    own = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="colmap-peer-")) if own else Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    names = sorted(p.name for p in image_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    t0 = time.perf_counter()
    try:
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        # COLMAP puts pixel centres at +0.5; mona-vo at integers.
        reader.camera_params = f"{intrinsics.fx},{intrinsics.fy},{intrinsics.cx + 0.5},{intrinsics.cy + 0.5}"
        if mask_dir is not None:
            reader.mask_path = str(mask_dir)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.use_gpu = False
        pycolmap.extract_features(db, image_dir, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        pairing.num_threads = num_threads
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = num_threads
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
        shared = time.perf_counter() - t0
        out = {}
        for mapper in mappers:
            t1 = time.perf_counter()
            if mapper == "incremental":
                opts = pycolmap.IncrementalPipelineOptions()
                opts.num_threads = num_threads
                opts.ba_refine_focal_length = False
                opts.ba_refine_principal_point = False
                opts.ba_refine_extra_params = False
                opts.random_seed = 0
                models = pycolmap.incremental_mapping(db, image_dir, work / "sparse", options=opts)
            else:
                opts = pycolmap.GlobalPipelineOptions()
                opts.num_threads = num_threads
                opts.random_seed = 0
                ba = opts.mapper.bundle_adjustment
                ba.refine_focal_length = False
                ba.refine_principal_point = False
                ba.refine_extra_params = False
                ba.ceres.use_gpu = False
                models = pycolmap.global_mapping(db, image_dir, work / "sparse_global", options=opts)
            poses = _poses(models)
            out[mapper] = {"names": names, "poses": poses,
                           "seconds": shared + time.perf_counter() - t1,
                           "registered": len(poses), "models": len(models)}
        return out[mappers[0]] if len(mappers) == 1 else out
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)
