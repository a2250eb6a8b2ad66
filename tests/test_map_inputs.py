"""`kbs map DIR` takes only scans from DIR: a poses file (the poses.txt `kbs synth --frames`
writes beside scans/, or any KITTI-style poses file) was read as a 2-point text scan and mapped
(exit 0); and a pose with an absurd translation (1e300) ended in an internal error (exit 1), or
in a garbage map. Both are now input errors naming the file (and the line)."""
from __future__ import annotations

from pathlib import Path

import pytest

from kbs.cli.main import main
from kbs.io.readers import why_not_a_scan


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("drive") / "drv"
    assert main(["-q", "synth", "outdoor", "--frames", "2", "--out", str(out)]) == 0
    assert (out / "poses.txt").is_file() and (out / "scans").is_dir()
    return out


def test_a_drive_folder_is_not_mapped_from_its_poses_file(drive, tmp_path, capsys):
    capsys.readouterr()
    code = main(["map", "--rules", "outdoor", str(drive), "--out", str(tmp_path / "m"), "-j", "1"])
    err = capsys.readouterr().err
    assert code == 3 and not (tmp_path / "m").exists(), err
    assert f"{drive}: no point-cloud file in this directory" in err and "skipped poses.txt: a poses file" in err
    assert f"kbs map {drive / 'scans'} --poses {drive / 'poses.txt'}" in err


def test_a_poses_file_under_another_name_is_not_a_scan(drive, tmp_path):
    other = tmp_path / "trajectory.txt"
    other.write_text((drive / "poses.txt").read_text())
    assert why_not_a_scan(other).startswith("a poses file (12 numbers a line")
    xyz = tmp_path / "cloud.txt"  # a text cloud of 12 columns (not rotations) is still a scan
    xyz.write_text("\n".join(" ".join(str(i + j) for j in range(12)) for i in range(5)) + "\n")
    assert why_not_a_scan(xyz) is None
    assert why_not_a_scan(tmp_path / "calib.txt") == "a KITTI calibration file"


@pytest.mark.parametrize("value", ["1e300", "-2e50"])
def test_a_pose_translation_beyond_the_coordinate_bound_is_refused_at_its_line(drive, tmp_path, capsys, value):
    lines = (drive / "poses.txt").read_text().splitlines()
    row = lines[1].split()
    row[3] = value  # the x of the second pose's translation
    lines[1] = " ".join(row)
    poses = tmp_path / "poses.txt"
    poses.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    code = main(["map", "--rules", "outdoor", str(drive / "scans"), "--poses", str(poses), "--out",
                 str(tmp_path / "m"), "-j", "1"])
    err = capsys.readouterr().err
    assert code == 3 and "internal error" not in err and not (tmp_path / "m").exists(), err
    assert f"{poses}:2:1: not a rigid transform: a translation of {float(value):g}, beyond +-1e+50" in err
