"""`rig_eval.rig_agreement`: how far one solved rig's cameras sit from another's, each seen from its camera 0."""

import cv2
import numpy as np
import pytest

from evaluate.calibration.rig_eval import rig_agreement


class Rig:
    """The attributes `rig_agreement` reads of a `RigResult`: x_cam = R X + t."""

    def __init__(self, rotations, centres):
        self.rotations = np.asarray(rotations, float)
        self.translations = np.array([-r @ c for r, c in zip(self.rotations, np.asarray(centres, float))])
        self.cameras = list(range(len(self.rotations)))

    def centre(self, camera):
        return -self.rotations[camera].T @ self.translations[camera]

    def moved(self, rotation, translation):
        """The same rig in another world frame (X' = rotation X + translation)."""
        return Rig([r @ rotation.T for r in self.rotations], [rotation @ c + translation for c in
                                                              [self.centre(i) for i in self.cameras]])


def turn(axis, degrees):
    return cv2.Rodrigues(np.asarray(axis, float) * np.radians(degrees))[0]


def test_the_same_rig_in_another_frame_agrees_and_a_moved_camera_is_measured():
    reference = Rig([np.eye(3), turn([0, 1, 0], -20), turn([1, 0, 0], 15)], [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    same = reference.moved(turn([0.3, 1, 0.2], 40), np.array([2.0, -1.0, 0.5]))
    agreement = rig_agreement(same, reference)
    assert agreement["worst_rotation_deg"] < 1e-6 and agreement["worst_centre_mm_per_m"] < 1e-6
    # camera 2 turned by 1 degree and moved 10 mm: 10 mm over the longest baseline (sqrt 2 m)
    rotations, centres = list(reference.rotations), [reference.centre(i) for i in range(3)]
    rotations[2] = turn([0, 0, 1], 1.0) @ rotations[2]
    centres[2] = centres[2] + [0.0, 0.0, 0.010]
    agreement = rig_agreement(Rig(rotations, centres), reference)
    assert agreement["cameras"][2]["rotation_deg"] == pytest.approx(1.0, abs=1e-6)
    assert agreement["cameras"][2]["centre_mm_per_m"] == pytest.approx(10 / np.sqrt(2), rel=1e-6)
    assert agreement["cameras"][1]["rotation_deg"] < 1e-6 and agreement["cameras"][1]["centre_mm_per_m"] < 1e-6


def test_rig_eval_refuses_a_folder_as_out_before_it_works(tmp_path, capsys):
    """``--out`` names the JSON file written at the end: a folder is refused (exit 2, one line) before any rig is
    solved, not after the work."""
    from evaluate.calibration.rig_eval import main

    with pytest.raises(SystemExit) as stop:
        main(["--seeds", "1", "--out", str(tmp_path)])
    assert stop.value.code == 2
    assert f"--out {tmp_path} is a folder" in capsys.readouterr().err
