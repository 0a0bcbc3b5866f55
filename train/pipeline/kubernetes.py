"""The Kubernetes manifests (``--cluster k8s``): a render Indexed Job and a training Job for a plan, written to
``OUT/cluster``, never applied here (no Kubernetes cluster runs them in this project's tests: they are checked
against the Kubernetes API's schema, tests/train/test_kubernetes.py)."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

from deepcharuco.core.files import write_atomic
from train.pipeline.plan import ROOT, PipelineError
from train.pipeline.stages import Pipeline


def write_manifests(pipeline: Pipeline, num_shards: int) -> list[Path]:
    """A render Indexed Job over ``--shard-index/--num-shards`` and a training Job that runs this pipeline (its
    trainers under torchrun when --nproc-per-node > 1); written to ``OUT/cluster``, not applied."""
    if num_shards < 1:
        raise PipelineError(f"--num-shards {num_shards}: give 1 or more render jobs")
    stages = pipeline.stages()
    render = next(s for s in stages if s.name == "render")
    render_command = [a for a in render.command if a not in ("--resume", "--quiet")]
    render_command[0] = "python"
    folder = pipeline.run / "cluster"
    folder.mkdir(parents=True, exist_ok=True)
    pipeline_command = pipeline.reproduce_command()
    gpus = max(1, pipeline.args.nproc_per_node)
    ddp_note = ("# Training: train/loop.py supports torchrun (DDP): each rank takes every world-size-th sample of a\n"
                "# batch, rank 0 writes checkpoints and logs; one node, one process per GPU (--device auto gives rank r\n"
                "# the GPU LOCAL_RANK). Run with 2 CPU processes (gloo) only, never on several GPUs yet. Stop the job as\n"
                "# a whole (a rank stopped alone leaves the others waiting), then resume it.\n"
                f"# Paths are those of the checkout that wrote this ({ROOT}): edit them for the cluster's mounts.\n")
    render_path, train_path = folder / "render-job.yaml", folder / "train-job.yaml"
    image = "deepcharuco:latest  # an image with this repository at /work and its .venv"
    write_atomic(render_path,
        f"# Render stage of {pipeline.run} as a Kubernetes Indexed Job: pod i renders the shards i, i+{num_shards}, ...\n"
        f"# The run folder must be on a volume every pod mounts (here the PVC deepcharuco-runs at /work/{pipeline.run}).\n"
        f"# Apply: kubectl apply -f {render_path}; when it completes: kubectl apply -f {train_path}\n"
        "apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: deepcharuco-render\nspec:\n"
        f"  completions: {num_shards}\n  parallelism: {num_shards}\n  completionMode: Indexed\n  backoffLimitPerIndex: 3\n"
        "  template:\n    spec:\n      restartPolicy: Never\n      containers:\n      - name: render\n"
        f"        image: {image}\n        workingDir: /work\n"
        "        command: [\"/bin/bash\", \"-c\"]\n"
        f"        args: [{json.dumps(shlex.join(render_command) + ' --shard-index $JOB_COMPLETION_INDEX --num-shards ' + str(num_shards) + ' --resume --quiet')}]\n"
        "        resources: {requests: {cpu: \"8\", memory: 8Gi}}\n"
        f"        volumeMounts: [{{name: runs, mountPath: /work/{pipeline.run}}}]\n"
        "      volumes: [{name: runs, persistentVolumeClaim: {claimName: deepcharuco-runs}}]\n")
    write_atomic(train_path,
        ddp_note +
        "apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: deepcharuco-train\nspec:\n  backoffLimit: 3\n"
        "  template:\n    spec:\n      restartPolicy: OnFailure  # a rerun resumes where the pod stopped\n"
        "      containers:\n      - name: train\n"
        f"        image: {image}\n        workingDir: /work\n        command: [\"/bin/bash\", \"-c\"]\n"
        f"        args: [{json.dumps(pipeline_command + f' --device cuda --nproc-per-node {gpus} --quiet')}]\n"
        f"        resources: {{limits: {{nvidia.com/gpu: {gpus}}}, requests: {{cpu: \"16\", memory: 32Gi}}}}\n"
        f"        volumeMounts: [{{name: runs, mountPath: /work/{pipeline.run}}}]\n"
        "      volumes: [{name: runs, persistentVolumeClaim: {claimName: deepcharuco-runs}}]\n")
    return [render_path, train_path]
