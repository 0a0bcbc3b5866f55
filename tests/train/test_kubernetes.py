"""--cluster k8s: the Job manifests read back against the Kubernetes API's JSON schema (kubernetes-validate ships
the schemas of each release: checked offline, strictly, so that a misspelt field is an error). They are not run
under a Kubernetes cluster anywhere in these tests."""

import json

import pytest

from deepcharuco import BoardSpec
from train.pipeline import command

kubernetes_validate = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate (the dev extra) is needed")
yaml = pytest.importorskip("yaml", reason="PyYAML (kubernetes-validate's dependency) is needed")

BOARD = BoardSpec(squares_x=4, squares_y=4, square_length=0.04, marker_length=0.03, dictionary="DICT_4X4_50")
RATES = {"render_s_per_frame": 1.0, "charuconet_s_per_step": 0.5, "refinenet_s_per_step": 0.2,
         "patch_s_per_patch": 0.002}


def test_manifests_follow_the_kubernetes_schema(tmp_path, capsys):
    board = BOARD.save(tmp_path / "board.yaml")
    run = tmp_path / "run"
    run.mkdir()
    (run / "rates.json").write_text(json.dumps({k: {"value": v, "source": "test"} for k, v in RATES.items()}))
    code = command.main(["--board", str(board), "--out", str(run), "--frames", "4", "--cluster", "k8s",
                         "--num-shards", "3", "--nproc-per-node", "2"])
    assert code == 0, capsys.readouterr().err
    version = kubernetes_validate.latest_version()
    manifests = [yaml.safe_load((run / "cluster" / name).read_text()) for name in ("render-job.yaml", "train-job.yaml")]
    for manifest in manifests:
        assert manifest["apiVersion"] == "batch/v1" and manifest["kind"] == "Job"
        kubernetes_validate.validate(manifest, version, strict=True)
    assert manifests[0]["spec"]["completionMode"] == "Indexed" and manifests[0]["spec"]["completions"] == 3
    # The check catches a typo: a misspelt field, a string where the schema wants a number.
    container = manifests[0]["spec"]["template"]["spec"]["containers"][0]
    container["comand"] = container.pop("command")
    with pytest.raises(kubernetes_validate.ValidationError, match="comand"):
        kubernetes_validate.validate(manifests[0], version, strict=True)
    manifests[1]["spec"]["backoffLimit"] = "three"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(manifests[1], version, strict=True)
