"""The package as a user installs it: the wheel alone into a fresh virtual environment (its dependencies from the
package index), with no PyTorch, running `deepcharuco detect` with both detectors, `deepcharuco board` and a rig's
`deepcharuco calibrate`."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "deepcharuco" / "examples"


def run(*command, **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True, **kwargs)
    assert done.returncode == 0, f"{command}:\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    return done


def test_the_wheel_installs_alone_without_torch_and_detects(tmp_path):
    run(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--quiet", "-w", tmp_path / "dist",
        ROOT)
    (wheel,) = (tmp_path / "dist").glob("deepcharuco-*.whl")
    assert wheel.stat().st_size < 30e6
    venv = tmp_path / "venv"
    run(sys.executable, "-m", "venv", venv)
    python, command = venv / "bin" / "python", venv / "bin" / "deepcharuco"
    run(python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", wheel)
    assert subprocess.run([python, "-c", "import torch"], capture_output=True).returncode != 0  # not pulled in
    work = tmp_path / "work"  # outside the checkout: the installed package, not this one, is imported
    work.mkdir()
    for detector in ("opencv", "deep"):
        run(command, "detect", EXAMPLES / "board_320x240.png", "--camera", EXAMPLES / "webcam_320x240.yaml",
            "--detector", detector, "--out", detector, cwd=work)
        frame = json.loads((work / detector / "board_320x240.json").read_text())["frames"][0]
        assert frame["num_corners"] >= 15 and frame["pose"]["reprojection_error"] < 0.3
    run(command, "board", "--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm",
        "--out", "my_board", cwd=work)
    assert (work / "my_board.pdf").read_bytes().startswith(b"%PDF-") and (work / "my_board.yaml").is_file()
    # A rig (scipy's least_squares under the index's numpy and OpenCV): three cameras' drawn frames.
    from evaluate.calibration.rig_views import RIG_BOARD, drawn_rig

    folders = drawn_rig(RIG_BOARD, seed=11, instants=14).save_frames(work)
    RIG_BOARD.save(work / "rig_board.yaml")
    run(command, "calibrate", *folders, "--board", work / "rig_board.yaml", "--detector", "opencv", "--out", "rig",
        "--no-report", "--quiet", cwd=work)
    assert "[cam_2]" in (work / "rig" / "rig.toml").read_text() and (work / "rig" / "cam1.yaml").is_file()
    missing = subprocess.run([command, "train", "--help"], capture_output=True, text=True, cwd=work)
    assert missing.returncode == 2 and "pip install 'deepcharuco[train]'" in missing.stderr
    size = sum(p.stat().st_size for p in venv.rglob("*") if p.is_file())
    assert size < 1.5e9, f"the runtime's environment is {size / 1e6:.0f} MB"
    print(f"wheel {wheel.stat().st_size / 1e6:.1f} MB, environment {size / 1e6:.0f} MB")
