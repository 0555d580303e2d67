"""The dotted job paths RQ stores in queued jobs are a wire format: jobs queued by an earlier
release name these functions, so each path stays the same and resolves to a job function."""

from __future__ import annotations

import importlib

import pytest

from producer import names

PATHS = {
    "RENDER_JOB": "workers.jobs.render.render_job",
    "SCENE_BAKE_PLAN_JOB": "workers.jobs.bake.bake_plan_job",
    "SCENE_BAKE_LDC_JOB": "workers.jobs.bake.bake_ldc_axis_job",
    "SCENE_BAKE_INDIRECT_JOB": "workers.jobs.bake.bake_ldc_indirect_job",
    "SCENE_BAKE_LLF_JOB": "workers.jobs.bake.bake_llf_views_job",
    "SCENE_BAKE_MERGE_JOB": "workers.jobs.bake.bake_merge_job",
    "DATASET_BAKE_JOB": "workers.jobs.datasets.bake_job",
    "RELIGHT_JOB": "workers.jobs.datasets.relight_job",
    "GENERATE_JOB": "workers.jobs.datasets.generate_job",
    "COMPOSITE_JOB": "workers.jobs.datasets.composite_job",
    "WALKTHROUGH_BAKE_JOB": "workers.jobs.walkthrough.walkthrough_bake_job",
    "WALKTHROUGH_CHUNK_JOB": "workers.jobs.walkthrough.walkthrough_chunk_job",
    "WALKTHROUGH_VIDEO_JOB": "workers.jobs.walkthrough.walkthrough_video_job",
    "CALIBRATE_JOB": "workers.jobs.calibrate.calibrate_job",
    "CALIBRATE_WALKTHROUGH_JOB": "workers.jobs.calibrate_walkthrough.calibrate_walkthrough_job",
    "VERIFY_JOB": "workers.jobs.verify.verify_job",
}


@pytest.mark.parametrize(("name", "path"), sorted(PATHS.items()))
def test_job_path_is_unchanged_and_resolves(name: str, path: str) -> None:
    assert getattr(names, name) == path
    module, _, func = path.rpartition(".")
    assert callable(getattr(importlib.import_module(module), func))


def test_every_job_path_is_pinned() -> None:
    declared = {n for n in names.__all__ if n.endswith("_JOB")}
    assert declared == set(PATHS)


def test_job_ids_are_unchanged() -> None:
    k = "0" * 64
    assert [names.render_job_id(k), names.scene_bake_job_id(k), names.scene_bake_plan_job_id(k),
            names.scene_bake_part_job_id(k), names.walkthrough_bake_job_id(k), names.walkthrough_chunk_job_id(k),
            names.walkthrough_video_job_id(k), names.dataset_job_id(names.DATASET_BAKE_KIND, k),
            names.calibrate_job_id(k), names.calibrate_walkthrough_job_id(k)] == [
        f"render-{k}", f"bake-{k}", f"bake-plan-{k}", f"bake-part-{k}", f"wtbake-{k}", f"wtchunk-{k}",
        f"walkthrough-{k}", f"relight-bake-{k}", f"calibrate-{k}",
        f"wtcalibrate-{k}"]
